"""``pivot execute``: the trajectories in PyBullet physics (§6)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info
from pivotcli.layout import Layout


def execute(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    variant: Annotated[str, typer.Option(help="Planner variant: its folder under the build.")] = "full",
    trajectories: Annotated[Path | None, typer.Option(help="Default <build>/<variant>/trajectories.parquet.")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default: beside it).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the physics perturbations (with --randomize).")] = 0,
    randomize: Annotated[bool, typer.Option(help="Perturb friction, CoM, inertia and mass (robustness runs).")] = False,
    gui: Annotated[bool, typer.Option(help="Open PyBullet's window (results are the same).")] = False,
    frames: Annotated[int | None, typer.Option(help="Frames to render for pivot show execution "
                                                    "(default: one per second of motion).")] = None,
) -> None:
    """Run the trajectories in PyBullet: the object moves only through its contacts (§6)."""
    from dataclasses import replace

    from stages import execute as stage

    lay = Layout.of(scene, build, variant)
    trajectories = trajectories or lay.trajectories
    out = out or trajectories.parent
    params = replace(stage.Params(), seed=seed, randomize=randomize)
    with cli_errors():
        if frames is None:
            from stages import artifacts

            duration = artifacts.read_json(trajectories.with_suffix(".json"), "mpc").get("duration", 0.0)
            frames = max(2, round(duration))
        res = stage.run(scene, lay.analysis, trajectories, out, params, frames=frames, gui=gui,
                        producer=f"execute {scene}")
    m = res.metrics
    info(f"{scene.stem}: success {m['success']}: final error {100 * m['final_position_error']:.2f} cm / "
         f"{m['final_yaw_error_deg']:.2f}°, max pivot slip {1000 * m['max_pivot_slip']:.1f} mm, edge slip "
         f"{1000 * m['max_edge_slip']:.1f} mm, fell {m['fell']}, "
         f"collision {m['collision']}; {res.timings.get('sim_speed', 0):.0f}x real time -> {out}/execution.json")
    if not m["success"]:
        raise typer.Exit(code=1)
