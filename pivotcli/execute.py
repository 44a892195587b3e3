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
    seed: Annotated[int, typer.Option(min=0, help="0: the nominal physics; N > 0: friction, mass, CoM, inertia "
                                      "and the initial position perturbed, drawn from seed N.")] = 0,
    seeds: Annotated[int, typer.Option(min=0, help="Also run seeds 1..K (perturbed) into <out>/seeds/ and "
                                       "write <out>/robustness.json.")] = 0,
    gui: Annotated[bool, typer.Option(help="Open PyBullet's window (results are the same).")] = False,
    frames: Annotated[int | None, typer.Option(help="Frames to render for pivot show execution "
                                                    "(default: one per second of motion).")] = None,
) -> None:
    """Run the trajectories in PyBullet: the object moves only through its contacts (§6)."""
    from dataclasses import replace

    from pivotcli.common import quiet_import
    from stages.artifacts import output_lock

    stage = quiet_import("stages.execute")
    lay = Layout.of(scene, build, variant)
    trajectories = trajectories or lay.trajectories
    out = out or trajectories.parent
    params = replace(stage.Params(), seed=seed)
    with cli_errors(), output_lock(out):
        res = stage.run(scene, lay.analysis, trajectories, out, params, frames=frames, gui=gui,
                        producer=f"execute {scene}")
        m = res.metrics
        failed = f" (failed: {', '.join(m['failures'])})" if m["failures"] else ""
        info(f"{scene.stem}: success {m['success']}{failed}: final error {100 * m['final_position_error']:.2f} cm"
             f" / {m['final_yaw_error_deg']:.2f}° / tilt {m['final_tilt_error_deg']:.2f}°, peak ball force "
             f"{m['max_ball_force']:.1f} N of {m['force_bound']:.0f}, worst support slip "
             f"{1000 * m['max_support_slip']:.1f} mm / {m['max_support_rotation_slip_deg']:.2f}°; "
             f"{res.timings.get('sim_speed', 0):.0f}x real time -> {out}/execution.json")
        robust_ok = True
        if seeds:
            summary = stage.run_seeds(scene, lay.analysis, trajectories, out, params, seeds,
                                      producer=f"execute {scene} --seeds {seeds}")
            robust_ok = summary["succeeded"] >= summary["required"]
            info(f"{scene.stem}: {summary['succeeded']} of {seeds} perturbed seeds succeed (need "
                 f"{summary['required']}) -> {out}/robustness.json")
    if not m["success"] or not robust_ok:
        raise typer.Exit(code=1)
