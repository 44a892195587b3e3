"""``pivot``: plan how a dual-arm robot moves a large object by pivoting, tumbling and regrasping.

Each pipeline stage is a subcommand that reads and writes artifacts (DESIGN.md, Pipeline).
"""

from __future__ import annotations

from typing import Annotated

import typer

from pivotcli import analyze, benchmark, diff, execute, plan, sample, show, view
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
app.command(name="view")(view.view)
app.add_typer(show.app, name="show")
app.add_typer(benchmark.app, name="benchmark")


def main() -> None:
    app()
