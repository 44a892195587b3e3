"""``pivot view``: a plan and its physics execution in 3D, as one self-contained HTML page."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info
from stages.errors import InputError

REPO = Path(__file__).resolve().parents[1]


def default_scene(build_dir: Path) -> Path:
    """``data/scenes/<build folder name>.json`` (the Makefile's layout), here or in the source tree."""
    name = f"{build_dir.resolve().name}.json"
    for root in (Path("data/scenes"), REPO / "data" / "scenes"):
        if (root / name).is_file():
            return root / name
    raise InputError(f"{build_dir}: no scene data/scenes/{name} for this build folder; pass --scene")


def view(
    build_dir: Annotated[Path, typer.Argument(help="Build folder of a scene (build/<scene>).")],
    variant: Annotated[str, typer.Option(help="full, no-regrasp, no-tumble or no-usp.")] = "full",
    scene: Annotated[Path | None, typer.Option(help="Scene file (default data/scenes/<build name>.json).")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="HTML file (default <build>/<variant>/view.html).")]
    = None,
    execution: Annotated[Path | None, typer.Option(help="Folder of the execution to show (default: the plan's).")]
    = None,
) -> None:
    """Write a self-contained HTML page (MeshCat) that animates the plan beside its physics execution:
    turn, zoom and scrub through time in a browser, offline."""
    from stages import view as stage

    with cli_errors():
        if not build_dir.is_dir():
            raise InputError(f"{build_dir}: no such build folder")
        res = stage.run(build_dir, scene or default_scene(build_dir), out or build_dir / variant / "view.html",
                        variant=variant, execution_dir=execution)
    info(f"wrote {res.path} ({res.size / 1e6:.1f} MB, {res.keyframes} keyframes)"
         + (f"; no motion to show: {res.reason}" if res.status != "ok" else ""))
    if res.status != "ok":
        raise typer.Exit(code=1)
