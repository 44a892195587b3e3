"""``pivot sample SCENE``: object poses by pivoting and tumbling, and their feasible grasps (§4.2–§5.1)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info, step
from pivotcli.layout import Layout
from stages.artifacts import output_lock


def sample(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    analysis: Annotated[Path | None, typer.Option(help="Analysis folder (default <build>/analysis).")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default <build>/sample).")] = None,
) -> None:
    """Sample object poses on the table and refine the grasps of each (IK, collisions, stability)."""
    from stages import sample as stage

    layout = Layout.of(scene, build)
    name = scene.stem
    analysis, out = analysis or layout.analysis, out or layout.sample
    with cli_errors():
        with output_lock(out), step("sampling poses and grasps"):
            result = stage.run(scene, analysis, out, stage.Params(), producer=f"sample {scene}")
    s = result.summary
    info(f"{name}: {s['poses']['ok']} poses ({s['poses_sp']} SP, {s['poses_usp']} USP), "
         f"{s['links']['pivot']} pivot and {s['links']['tumble']} tumble links, {s['grasps']} grasps of "
         f"{s['candidates']} candidates in {result.timings['total']:.2f} s -> {out}/")
