"""``pivot diff A B``: compare two artifacts (or folders of artifacts) with numeric tolerances."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors
from stages.artifacts import diff_artifacts
from stages.errors import ArtifactError


def diff(
    a: Annotated[Path, typer.Argument(help="First artifact file or folder.")],
    b: Annotated[Path, typer.Argument(help="Second artifact file or folder.")],
    rtol: Annotated[float, typer.Option(help="Relative tolerance for floats.")] = 1e-9,
    atol: Annotated[float, typer.Option(help="Absolute tolerance for floats.")] = 1e-9,
    only: Annotated[str | None, typer.Option(help="Compare only this top-level key of two JSON artifacts.")] = None,
) -> None:
    """Compare two artifacts of the same kind, ignoring timings; exit 1 when they differ."""
    with cli_errors():
        for p in (a, b):
            if not p.exists():
                raise ArtifactError(f"{p}: no such artifact")
        lines = diff_artifacts(a, b, rtol=rtol, atol=atol, only=only)
    if lines:
        shown = lines[:20]
        typer.echo("\n".join(shown + ([f"... and {len(lines) - 20} more"] if len(lines) > 20 else [])))
        raise typer.Exit(code=1)
    typer.echo("equal")
