"""``pivot graph SCENE`` and ``pivot plan SCENE``: the grasp-augmented graph and its search (§5)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info, step
from pivotcli.layout import VARIANTS, Layout, variant_of
from stages.artifacts import output_lock

VARIANT_HELP = f"Planner variant whose plan to use: {', '.join(VARIANTS)} (its folder under the build)."


def graph(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
) -> None:
    """Build the grasp-augmented graph: pivot, regrasp and tumble edges with their motion checks."""
    from stages import graph as graph_stage

    lay = Layout.of(scene, build)
    with cli_errors(), output_lock(lay.graph), step("building the graph"):
        g = graph_stage.run(scene, lay.analysis, lay.sample, lay.graph, graph_stage.Params(),
                            producer=f"graph {scene}")
    e = g.summary["edges"]
    info(f"{scene.stem}: {sum(g.summary['nodes'].values())} nodes; edges ok/rejected: pivot "
         f"{e['pivot']['ok']}/{e['pivot']['rejected']}, regrasp {e['regrasp']['ok']}/{e['regrasp']['rejected']}, "
         f"tumble {e['tumble']['ok']}/{e['tumble']['rejected']} in {g.timings['total']:.2f} s -> {lay.graph}/")


def plan(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Plan file (default <build>/<variant>/plan.json, "
                                                                  "the variant full or the ablation).")] = None,
    no_regrasp: Annotated[bool, typer.Option("--no-regrasp", help="Ablation: pivoting gait only [3].")] = False,
    no_tumble: Annotated[bool, typer.Option("--no-tumble", help="Ablation: no tumbling.")] = False,
    no_usp: Annotated[bool, typer.Option("--no-usp", help="Ablation: no unstable placements.")] = False,
    no_mpc: Annotated[bool, typer.Option("--no-mpc", help="Skip the MPC check of each pivot.")] = False,
) -> None:
    """Search the graph, check each primitive at the motion level and backtrack (§5.3) -> plan.json."""
    from stages import plan as plan_stage
    from stages import stagelog

    lay = Layout.of(scene, build, variant_of(no_regrasp, no_tumble, no_usp))
    out = out or lay.plan
    params = plan_stage.Params(no_regrasp=no_regrasp, no_tumble=no_tumble, no_usp=no_usp, check_mpc=not no_mpc)
    with cli_errors(), output_lock(out), step("planning"):
        p = plan_stage.run(scene, lay.analysis, lay.sample, lay.graph, out, params, producer=f"plan {scene}")
    removed = len(p["log"])
    if p["status"] == "infeasible":
        why = f"{p['reason']}; {p['diagnosis']['detail']}" if "diagnosis" in p else p["reason"]
        typer.echo(f"pivot: no plan for {scene.stem}: {why} ({removed} edges removed) -> {out}", err=True)
        raise typer.Exit(code=1)
    c = p["counts"]
    msg = (f"{scene.stem}: {p['status']} plan, cost {p['cost']:.2f}: {c['pivot']} pivots, {c['tumble']} tumbles, "
           f"{c['regrasp']} regrasps ({c.get('usp_regrasp', 0)} in USP), {c.get('retake', 0)} retakes; "
           f"{stagelog.backtracks(p)} edges removed by backtracking; {p['time']:.2f} s -> {out}")
    if p["status"] == "partial":
        err = p["remaining_error"]
        msg += f"\n  goal out of reach: ended {err['distance'] * 100:.1f} cm short (x {err['x'] * 100:+.1f} cm)"
    info(msg)


def mpc(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    variant: Annotated[str, typer.Option(help=VARIANT_HELP)] = "full",
    plan_file: Annotated[Path | None, typer.Option("--plan", help="Default <build>/<variant>/plan.json.")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Default: beside the plan.")] = None,
    horizon: Annotated[int, typer.Option(help="MPC prediction horizon N_p (steps).")] = 20,
    alpha: Annotated[float, typer.Option(help="MPC state-error weight (eq. 11).")] = 1e7,
    beta: Annotated[float, typer.Option(help="MPC force weight (eq. 11).")] = 1.0,
) -> None:
    """Recompute the force and joint trajectories of an existing plan with the MPC (§5.2), no replanning."""
    from dataclasses import replace

    from stages import trajectory

    lay = Layout.of(scene, build, variant)
    plan_file = plan_file or lay.plan
    out = out or plan_file.parent / "trajectories.parquet"
    params = trajectory.Params()
    params = replace(params, mpc=replace(params.mpc, horizon=horizon, alpha=alpha, beta=beta))
    with cli_errors(), output_lock(out), step("computing trajectories"):
        stats = trajectory.run(scene, lay.analysis, plan_file, out, params,
                               producer=f"mpc {scene}")
    if stats["status"] != "ok":
        why = f": {stats['reason']}" if stats.get("reason") else ""
        typer.echo(f"pivot: {stats['status']} on primitive {stats['failed_primitive']} of {scene.stem}{why}", err=True)
        raise typer.Exit(code=1)
    info(f"{scene.stem}: {stats['primitives']} primitives, {stats['steps']} steps, {stats['duration']:.1f} s of "
         f"motion, MPC tracking error <= {stats['mpc_max_error']:.2e} rad -> {out}")
