"""``pivot show <artifact>``: draw the figure a person wants to see (PNG)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info

app = typer.Typer(help="Draw figures of artifacts (PNG).", no_args_is_help=True)


@app.command("analysis")
def analysis(
    analysis_dir: Annotated[Path, typer.Argument(help="Folder written by pivot analyze.")],
    png: Annotated[Path, typer.Option(help="Output PNG.")] = Path("analysis.png"),
) -> None:
    """Fig. 4: pivot vertices and tumble edges; facets, contact points and some contact pairs."""
    from stages import plots

    with cli_errors():
        plots.show_analysis(analysis_dir, png)
    info(f"wrote {png}")
