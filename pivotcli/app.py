"""``pivot``: plan how a dual-arm robot moves a large object by pivoting, tumbling and regrasping.

Each pipeline stage is a subcommand that reads and writes artifacts (DESIGN.md, Pipeline).
"""

from __future__ import annotations

from typing import Annotated

import typer
from typer import rich_utils

from pivotcli import analyze, benchmark, diff, execute, plan, sample, show, started
from pivotcli.common import configure
from stages import __version__

app = typer.Typer(
    name="pivot",
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
    verbose: Annotated[int, typer.Option("-v", "--verbose", count=True, help="More log output (-vv: debug).")] = 0,
    quiet: Annotated[bool, typer.Option("-q", "--quiet", help="Only errors.")] = False,
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
) -> None:
    """Plan how a dual-arm robot moves a large object by pivoting, tumbling and regrasping."""
    started()
    configure(verbose, quiet)


app.command(name="analyze")(analyze.analyze)
app.command(name="sample")(sample.sample)
app.command(name="graph")(plan.graph)
app.command(name="plan")(plan.plan)
app.command(name="mpc")(plan.mpc)
app.command(name="execute")(execute.execute)
app.command(name="run")(execute.run)
app.command(name="report")(execute.report)
app.command(name="diff")(diff.diff)
app.add_typer(show.app, name="show")
app.add_typer(benchmark.app, name="benchmark")


def main() -> None:
    app()
