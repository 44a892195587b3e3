"""``pivot``: plan how a dual-arm robot moves a large object by pivoting, tumbling and regrasping.

Each pipeline stage is a subcommand that reads and writes artifacts (DESIGN.md, Pipeline). A command's
module is imported only when that command runs (``pivot --help`` reads the commands' docstrings from
their sources), so that the CLI starts in a fraction of a second.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path
from typing import Annotated

import click
import typer
from typer import rich_utils
from typer.core import TyperGroup

from pivotcli import started
from pivotcli.common import configure
from stages import __version__

# name -> "module:attribute": a command function, or a Typer sub-application (``app``).
COMMANDS = {
    "analyze": "pivotcli.analyze:analyze", "sample": "pivotcli.sample:sample", "graph": "pivotcli.plan:graph",
    "plan": "pivotcli.plan:plan", "mpc": "pivotcli.plan:mpc", "execute": "pivotcli.execute:execute",
    "run": "pivotcli.run:run", "deps": "pivotcli.run:deps", "report": "pivotcli.run:report",
    "diff": "pivotcli.diff:diff", "view": "pivotcli.view:view", "show": "pivotcli.show:app",
    "benchmark": "pivotcli.benchmark:app",
}


def load_command(name: str) -> click.Command:
    """Import the command's module and build its click command (Typer's conversion)."""
    module, _, attr = COMMANDS[name].partition(":")
    obj = getattr(importlib.import_module(module), attr)
    if isinstance(obj, typer.Typer):
        return typer.main.get_command(obj)
    sub = typer.Typer(add_completion=False, pretty_exceptions_show_locals=False)
    sub.command(name)(obj)
    return typer.main.get_command(sub)


def _summary_line(name: str) -> str:
    """The first line of a command's docstring (or its Typer app's ``help=``), read from its source."""
    module, _, attr = COMMANDS[name].partition(":")
    path = Path(__file__).resolve().parents[1].joinpath(*module.split(".")).with_suffix(".py")
    tree = ast.parse(path.read_text())
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == attr:
            return (ast.get_docstring(node) or "").split("\n")[0]
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == attr for t in node.targets):
            kw = {k.arg: k.value for k in getattr(node.value, "keywords", [])}
            return ast.literal_eval(kw["help"]) if "help" in kw else ""
    return ""


class _LazyCommand(click.Command):
    """Stands in for a command in the help listing; builds the real command when it is invoked."""

    def __init__(self, name: str):
        super().__init__(name, help=_summary_line(name))

    def make_context(self, info_name, args, parent=None, **extra):
        return load_command(self.name).make_context(info_name, args, parent=parent, **extra)


class LazyGroup(TyperGroup):
    """The root group: the commands of ``COMMANDS``, each imported on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        return _LazyCommand(cmd_name) if cmd_name in COMMANDS else None


app = typer.Typer(
    name="pivot",
    cls=LazyGroup,
    help=__doc__.splitlines()[0].split(": ", 1)[1],
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


_format_error = rich_utils.rich_format_error


def _format_error_unwrapped(e) -> None:
    """typer's usage-error box, as wide as its message, so that its last line names the option or
    argument (at 80 columns "Invalid value for '--mass': ..." wrapped onto "string as a number")."""
    width = max((len(line) for line in e.format_message().splitlines()), default=0) + 4
    saved = rich_utils.MAX_WIDTH
    rich_utils.MAX_WIDTH = max(width, saved or 80)
    try:
        _format_error(e)
    finally:
        rich_utils.MAX_WIDTH = saved


rich_utils.rich_format_error = _format_error_unwrapped


def _version(value: bool) -> None:
    if value:
        typer.echo(f"pivot {__version__}")
        raise typer.Exit()


@app.callback()
def main_options(
    verbose: Annotated[int, typer.Option("-v", "--verbose", count=True,
                                         help="Log each stage's counts and decisions (-vv: every edge and step).")] = 0,
    quiet: Annotated[bool, typer.Option("-q", "--quiet", help="Only errors.")] = False,
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
) -> None:
    """Plan how a dual-arm robot moves a large object by pivoting, tumbling and regrasping."""
    started()
    configure(verbose, quiet)


def main() -> None:
    app()
