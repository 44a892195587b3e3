"""``pivot execute``, ``pivot run`` and ``pivot report``: physics, the whole chain, the paper's report."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, console, info, state
from stages.errors import InputError

REPO = Path(__file__).resolve().parents[1]


def execute(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    trajectories: Annotated[Path | None, typer.Option(help="Default <build>/full/trajectories.parquet.")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default: beside it).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the physics perturbations (with --randomize).")] = 0,
    randomize: Annotated[bool, typer.Option(help="Perturb friction, CoM, inertia and mass (robustness runs).")] = False,
    gui: Annotated[bool, typer.Option(help="Open PyBullet's window (results are the same).")] = False,
    frames: Annotated[int, typer.Option(help="Frames to render for pivot show execution.")] = 24,
) -> None:
    """Run the trajectories in PyBullet: the object moves only through its contacts (§6)."""
    from dataclasses import replace

    from pivotcli.common import quiet_import
    from stages.artifacts import output_lock

    stage = quiet_import("stages.execute")
    b = build or Path("build") / scene.stem
    trajectories = trajectories or b / "full" / "trajectories.parquet"
    out = out or trajectories.parent
    params = replace(stage.Params(), seed=seed, randomize=randomize)
    with cli_errors(), output_lock(out):
        res = stage.run(scene, b / "analysis", trajectories, out, params, frames=frames, gui=gui,
                        producer=f"execute {scene}")
    m = res.metrics
    info(f"{scene.stem}: success {m['success']}: final error {100 * m['final_position_error']:.2f} cm / "
         f"{m['final_yaw_error_deg']:.2f}°, max pivot slip {1000 * m['max_pivot_slip']:.1f} mm, edge slip "
         f"{1000 * m['max_edge_slip']:.1f} mm, fell {m['fell']}, "
         f"collision {m['collision']}; {res.timings.get('sim_speed', 0):.0f}x real time -> {out}/execution.json")
    if not m["success"]:
        raise typer.Exit(code=1)


STAGES = (("analyze", "analysis/analysis.json"), ("sample", "sample/sample.json"), ("graph", "graph/graph.json"),
          ("plan", "{v}/plan.json"), ("mpc", "{v}/trajectories.parquet"), ("execute", "{v}/execution.json"))


def run(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    variant: Annotated[str, typer.Option(help="full, no-regrasp, no-tumble or no-usp.")] = "full",
    seed: Annotated[int, typer.Option(help="Seed of the execution.")] = 0,
    figures: Annotated[bool, typer.Option(help="Also draw every stage's figure.")] = True,
) -> None:
    """The whole chain analyze -> sample -> graph -> plan -> mpc -> execute through Make (only what changed
    reruns), with progress and a one-screen summary."""
    from stages import artifacts

    if variant not in ("full", "no-regrasp", "no-tumble", "no-usp"):
        typer.echo(f"pivot: error: --variant {variant}: not one of full, no-regrasp, no-tumble, no-usp", err=True)
        raise typer.Exit(code=2)
    with cli_errors():
        if not scene.is_file():
            raise InputError(f"{scene}: no such scene file")
    b = build or Path("build") / scene.stem
    make = ["make", "-C", str(REPO), "--no-print-directory", f"SCENE={scene.stem}",
            f"SCENE_FILE={scene.resolve()}", f"B={b.resolve()}", f"SEED={seed}",
            f"VARIANT={'' if variant == 'full' else variant}", f"PIVOT={Path(sys.executable).parent / 'pivot'}",
            "INSTALLED="]
    v = variant
    times = {}
    for name, target in STAGES:  # six stages, each a Make target
        path = b.resolve() / target.format(v=v)
        t0 = time.perf_counter()
        with console.status(f"[bold]{name}[/bold] ({path.relative_to(b.resolve())})", spinner="dots") \
                if not state["quiet"] else contextlib.nullcontext():
            proc = subprocess.run([*make, str(path)], capture_output=True, text=True)
        times[name] = time.perf_counter() - t0
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout).strip().splitlines()
            typer.echo(f"pivot: {name} failed for {scene.stem}: {tail[-1] if tail else 'make failed'}", err=True)
            _summary(b, v, times, scene.stem)
            raise typer.Exit(code=1 if name in ("plan", "execute") else 2)
        if not state["quiet"]:
            console.print(f"  {name:<8} {times[name]:6.1f} s  {path.relative_to(b.resolve())}")
        if name == "plan" and artifacts.read_json(path, "plan")["status"] == "infeasible":
            _summary(b, v, times, scene.stem)
            raise typer.Exit(code=1)
    if figures:
        with console.status("drawing the figures", spinner="dots") if not state["quiet"] else contextlib.nullcontext():
            pngs = [b.resolve() / f for f in ("analysis.png", "poses.png", f"{v}/plan.png", f"{v}/trajectories.png",
                                              f"{v}/execution.png")]
            subprocess.run([*make, *map(str, pngs)], capture_output=True, text=True)
        if not state["quiet"]:
            console.print("  figures: " + ", ".join(str(p.relative_to(b.resolve())) for p in pngs if p.exists())
                          + (", execution.gif" if (b.resolve() / v / "execution.gif").exists() else ""))
    ok = _summary(b, v, times, scene.stem)
    if not ok:
        raise typer.Exit(code=1)


def _summary(b: Path, v: str, times: dict, name: str) -> bool:
    """Print the one-screen summary; returns whether the run succeeded in physics."""
    import json

    from rich.table import Table

    def read(p):
        try:
            return json.loads((b / p).read_text())
        except (OSError, json.JSONDecodeError):
            return {}

    plan, ex = read(f"{v}/plan.json"), read(f"{v}/execution.json")
    t = Table(title=f"pivot run {name} ({v})", show_header=False)
    c = plan.get("counts", {})
    t.add_row("plan", f"{plan.get('status', '–')}: {c.get('pivot', 0)} pivots, {c.get('tumble', 0)} tumbles, "
              f"{c.get('regrasp', 0)} regrasps ({c.get('usp_regrasp', 0)} in USP), "
              f"{len(plan.get('log', []))} edges removed by backtracking")
    if "remaining_error" in plan:
        t.add_row("goal out of reach", f"{100 * plan['remaining_error']['distance']:.1f} cm short")
    if ex:
        err, yaw = 100 * ex.get("final_position_error", 0), ex.get("final_yaw_error_deg", 0)
        slip = 1000 * ex.get("max_pivot_slip", 0)
        t.add_row("physics", f"success {ex.get('success')}, final error {err:.2f} cm / {yaw:.2f}°, pivot slip "
                  f"{slip:.1f} mm, fell {ex.get('fell')}, collision {ex.get('collision')}")
    t.add_row("time per stage", ", ".join(f"{k} {s:.1f} s" for k, s in times.items()))
    t.add_row("outputs", str(b / v))
    console.print(t)
    return bool(ex.get("success"))


def report(
    build_root: Annotated[Path, typer.Argument(help="The build folder holding one folder per scene.")] = Path("build"),
    out: Annotated[Path, typer.Option("--out", "-o", help="Report file.")] = Path("build/report/README.md"),
    scenes: Annotated[str, typer.Option(help="Comma-separated scene names.")] =
        "default,exp1_reach,exp2_rotate,exp3_obstacle",
) -> None:
    """Write the reproduction report (Table 2, Exp. 1-3, costs, margins, counts) from the artifacts."""
    from stages import report as stage

    with cli_errors():
        stage.write_report(build_root, out, [s for s in scenes.split(",") if s])
    info(f"wrote {out}")
