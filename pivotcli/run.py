"""``pivot run``, ``pivot deps`` and ``pivot report``: the whole chain, its Make prerequisites, the report.

``pivot run SCENE`` runs the six stages in this process, each only when it is stale by the rules of
``pivotcli.layout`` (a missing output, or a prerequisite newer than an output: the same rules the
Makefile follows, from the same declarations through ``pivot deps``), so it works in any folder from
a plain ``pip install``. The end-of-run summary goes to stdout (``--json``: machine-readable).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info, state, step
from pivotcli.layout import FIGURES, STAGES, VARIANTS, Layout, code_files
from stages.errors import InputError

log = logging.getLogger("pivot.run")


@dataclass
class RunRecord:
    """What ``pivot run`` did: per stage whether it ran and why, its time (s) and exit code."""

    ran: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    exit: dict[str, int] = field(default_factory=dict)
    figures: list[str] = field(default_factory=list)


def _call_stage(name: str, lay: Layout, seed: int) -> int:
    """Run one stage's command on the layout's defaults; its exit code (0 ok, 1 infeasible, 2 bad input)."""
    from pivotcli import analyze, execute, plan, sample

    ablation = {f"no_{v[3:].replace('-', '_')}": True for v in lay.variant.split("+") if v != "full"}
    calls = {
        "analyze": lambda: analyze.analyze(scene=lay.scene, build=lay.build),
        "sample": lambda: sample.sample(lay.scene, build=lay.build),
        "graph": lambda: plan.graph(lay.scene, build=lay.build),
        "plan": lambda: plan.plan(lay.scene, build=lay.build, **ablation),
        "mpc": lambda: plan.mpc(lay.scene, build=lay.build, variant=lay.variant),
        "execute": lambda: execute.execute(lay.scene, build=lay.build, variant=lay.variant, seed=seed),
    }
    try:
        calls[name]()
    except typer.Exit as e:
        return e.exit_code
    return 0


def _seed_changed(lay: Layout, seed: int) -> bool:
    """Whether the execution on disk ran with another seed (a parameter Make's mtimes cannot see)."""
    try:
        return json.loads(lay.execution.read_text())["meta"]["params"].get("seed") != seed
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False


def run_chain(lay: Layout, seed: int) -> RunRecord:
    """Run each stale stage in order; stop after a stage that fails (plan infeasible, MPC, bad input)."""
    rec = RunRecord()
    for s in STAGES:
        why = lay.stale(s.name)
        if s.name == "execute" and not why and _seed_changed(lay, seed):
            why = [f"seed {seed} differs from the execution's"]
        if not why:
            log.info("%s: up to date (%s)", s.name, lay.folder(s.name))
            continue
        log.info("%s: runs: %s", s.name, why[0] + (f" (and {len(why) - 1} more)" if len(why) > 1 else ""))
        for reason in why[1:]:
            log.debug("%s: also %s", s.name, reason)
        t0 = time.perf_counter()
        code = _call_stage(s.name, lay, seed)
        rec.ran[s.name] = why[0]
        rec.seconds[s.name] = time.perf_counter() - t0
        rec.exit[s.name] = code
        if code != 0 and s.name != "execute":
            break
        if s.name == "plan" and json.loads(lay.plan.read_text()).get("status") == "infeasible":
            break
    return rec


def draw_figures(lay: Layout, rec: RunRecord) -> None:
    """Draw each figure whose artifact exists and which is missing or older than it or its code."""
    from pivotcli import show, view

    draw = {
        "analysis": lambda png: show.analysis(lay.analysis, png=png),
        "poses": lambda png: show.poses(lay.sample, scene=lay.scene, analysis=lay.analysis, png=png),
        "plan": lambda png: show.plan(lay.build, scene=lay.scene, plan_file=lay.plan, png=png),
        "trajectories": lambda png: show.trajectories(lay.trajectories, scene=lay.scene, png=png),
        "execution": lambda png: show.execution(lay.run_dir, png=png),
        "view": lambda html: view.view(lay.build, variant=lay.variant, scene=lay.scene, out=html),
    }
    for f in FIGURES:
        outs = lay.outputs(f.stage, required_only=True)
        if not all(p.is_file() for p in outs):
            continue
        png = lay.figure(f.name)
        if png.is_file():
            newest = max(p.stat().st_mtime_ns for p in [*outs, *code_files(f.command)])
            if png.stat().st_mtime_ns >= newest:
                continue
        log.info("figure %s: draws %s", f.name, png)
        try:
            draw[f.name](png)
        except typer.Exit:
            continue
        rec.figures.append(str(png))


def summarize(lay: Layout, rec: RunRecord) -> dict:
    """The run's summary: plan status and counts, physics metrics, what ran and its times, the outputs."""

    def read(p: Path) -> dict:
        try:
            data = json.loads(p.read_text())
        except (OSError, ValueError):
            return {}
        data.pop("meta", None)
        return data

    plan, ex = read(lay.plan), read(lay.execution)
    physics = {k: ex[k] for k in ("success", "final_position_error", "final_yaw_error_deg", "max_pivot_slip",
                                  "max_edge_slip", "fell", "collision") if k in ex}
    return {"scene": lay.scene.stem, "variant": lay.variant, "build": str(lay.build),
            "plan": {"status": plan.get("status"), "counts": plan.get("counts", {}), "cost": plan.get("cost"),
                     "reason": plan.get("reason"), "edges_removed": len(plan.get("log", [])),
                     **({"remaining_error": plan["remaining_error"]} if "remaining_error" in plan else {})},
            "physics": physics, "ran": rec.ran, "seconds": {k: round(v, 3) for k, v in rec.seconds.items()},
            "exit": rec.exit, "figures": rec.figures}


def print_summary(s: dict) -> None:
    """The summary as plain lines on stdout (one fact a line, never wrapped)."""
    p, c = s["plan"], s["plan"]["counts"]
    lines = [f"pivot run {s['scene']} ({s['variant']}): {s['build']}/{s['variant']}"]
    if p["status"] == "infeasible":
        lines.append(f"plan: infeasible: {p['reason']}")
    elif p["status"]:
        lines.append(f"plan: {p['status']}, cost {p['cost']:.2f}: {c.get('pivot', 0)} pivots, {c.get('tumble', 0)} "
                     f"tumbles, {c.get('regrasp', 0)} regrasps ({c.get('usp_regrasp', 0)} in USP), "
                     f"{c.get('retake', 0)} retakes, {p['edges_removed']} edges removed by backtracking")
    if "remaining_error" in p:
        lines.append(f"goal out of reach: {100 * p['remaining_error']['distance']:.1f} cm short")
    ph = s["physics"]
    if ph:
        lines.append(f"physics: success {ph.get('success')}, final error {100 * ph.get('final_position_error', 0):.2f} "
                     f"cm / {ph.get('final_yaw_error_deg', 0):.2f} deg, pivot slip "
                     f"{1000 * ph.get('max_pivot_slip', 0):.1f} mm, fell {ph.get('fell')}, "
                     f"collision {ph.get('collision')}")
    ran = ", ".join(f"{k} {v:.1f} s" for k, v in s["seconds"].items())
    lines.append(f"ran: {ran}" if ran else "ran: nothing (every stage up to date)")
    typer.echo("\n".join(lines))


def run(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    variant: Annotated[str, typer.Option(help=f"Planner variant: {', '.join(VARIANTS)}.")] = "full",
    seed: Annotated[int, typer.Option(help="Seed of the execution.")] = 0,
    figures: Annotated[bool, typer.Option(help="Also draw every stage's figure.")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as JSON on stdout.")] = False,
) -> None:
    """The whole chain analyze -> sample -> graph -> plan -> mpc -> execute (only what is stale reruns)."""
    with cli_errors():
        if variant not in VARIANTS:
            raise InputError(f"--variant {variant}: not one of {', '.join(VARIANTS)}")
        if not scene.is_file():
            raise InputError(f"{scene}: no such scene file")
    lay = Layout.of(scene, build, variant)
    rec = run_chain(lay, seed)
    if figures and not any(code == 2 for code in rec.exit.values()):
        with step("drawing the figures"):
            quiet, state["quiet"] = state["quiet"], True
            try:
                draw_figures(lay, rec)
            finally:
                state["quiet"] = quiet
    s = summarize(lay, rec)
    typer.echo(json.dumps(s, indent=1, sort_keys=True)) if as_json else print_summary(s)
    codes = [c for c in rec.exit.values() if c]
    if codes:
        raise typer.Exit(code=max(codes))
    if s["plan"]["status"] == "infeasible" or s["physics"].get("success") is False:
        raise typer.Exit(code=1)


def deps(
    scene: Annotated[Path, typer.Argument(help="Scene file (JSON).")],
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene>).")] = None,
    variant: Annotated[str, typer.Option(help=f"Planner variant: {', '.join(VARIANTS)}.")] = "full",
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Write here instead of stdout.")] = None,
) -> None:
    """Print the Make variables of each stage's outputs and prerequisites (the import graph, like gcc -M)."""
    from stages.artifacts import atomic_path

    lay = Layout.of(scene, build, variant)
    text = make_deps(lay, Path.cwd())
    if out is None:
        typer.echo(text, nl=False)
        return
    with atomic_path(out) as tmp:
        tmp.write_text(text)


def make_deps(lay: Layout, root: Path) -> str:
    """``<STAGE>_OUT`` and ``<STAGE>_DEPS`` per stage, ``<FIGURE>_FIG_DEPS`` per figure, paths relative to
    ``root`` where they lie under it."""

    def rel(paths) -> str:
        out = []
        for p in paths:
            try:
                out.append(str(Path(p).resolve().relative_to(root.resolve())))
            except ValueError:
                out.append(str(p))
        return " ".join(out)

    lines = [f"# generated by pivot deps {lay.scene} --build {lay.build} --variant {lay.variant}; do not edit"]
    for s in STAGES:
        key = s.name.upper()
        lines.append(f"{key}_OUT := {rel(lay.outputs(s.name))}")
        lines.append(f"{key}_DEPS := {rel(lay.prerequisites(s.name))}")
    for f in FIGURES:
        lines.append(f"{f.name.upper()}_FIG_DEPS := {rel(code_files(f.command))}")
    return "\n".join(lines) + "\n"


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
