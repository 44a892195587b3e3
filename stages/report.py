"""``make reproduce``'s report: the paper's experiments (§6, Table 2) and the quantities its §7 leaves
as future work (computation cost per stage, stability margins along the plan, numbers of gaits,
tumbles and regrasps), read from the artifacts under ``build/`` and written as Markdown with figures.

Only reads artifacts; a missing one (a variant with no plan, hence no execution) shows as "–".
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from stages import artifacts

VARIANTS = ("full", "no-regrasp", "no-tumble", "no-usp")
STAGE_TIMINGS = (("analysis", "analysis/analysis.json.timings.json", "total"),
                 ("sample", "sample/sample.json.timings.json", "total"),
                 ("graph", "graph/graph.json.timings.json", "total"))
PAPER = {
    "exp1_reach": "Exp. 1 (§6.3, Fig. 16, Table 2): regrasping extends the reach; the graph MPC gait [3] "
                  "ends 12.5 cm short",
    "exp2_rotate": "Exp. 2 (§6.4, Fig. 17): a -90° turn about z with regrasps onto other faces",
    "exp3_obstacle": "Exp. 3 (§6.5, Fig. 18): an obstacle in front and a narrow table: a tumble over the table's "
                     "edge into USP onto the catcher's ball, a regrasp in USP one ball at a time (each move while "
                     "the other ball alone holds the piano) and a pivot back into SP",
    "default": "Simulation (§6.2, Fig. 15): move the piano forward",
}
#: What was calibrated to reach a paper figure: scene -> (the scene before, what changed).
CALIBRATED = {
    "exp1_reach": ("exp1_reach_first", "the robot's base moved 4 cm back (x -0.70 -> -0.74 m) and the goal's CoM "
                   "from (0.38, 0.00) to (0.27, -0.025) m until the one-grasp gait stopped short along x as in "
                   "Table 2; at the first geometry (`exp1_reach_first`) the first grasp reached far enough that "
                   "no goal on the table needed a regrasp by reach"),
}


def _read(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _fmt(v, spec=".3f", none="–") -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return none
    return format(v, spec) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def _plan_margins(build: Path, plan: dict) -> list[float]:
    """Stability margins (N) of the grasps the plan holds the object with, in order."""
    try:
        gr = artifacts.read_table(build / "sample" / "grasps.parquet", "grasps")
    except artifacts.ArtifactError:
        return []
    out = []
    for s in plan.get("steps", []):
        g = s.get("grasp", s.get("grasp_to"))
        if g is not None and 0 <= g < len(gr):
            out.append(float(gr["margin"][g]))
    return out


def _robustness(d: Path, ex: dict | None) -> dict | None:
    """``robustness.json`` of the variant folder ``d`` (``pivot execute --seeds K``) when made from the same
    trajectories as its current execution ``ex``."""
    rb = _read(d / "robustness.json")
    if rb is None or ex is None:
        return None
    same = rb.get("meta", {}).get("inputs", {}).get("trajectories") == ex.get("meta", {}).get("inputs", {}).get(
        "trajectories")
    return rb if same else None


def _seeds_cell(rb: dict | None) -> str:
    if rb is None:
        return "–"
    fails = ", ".join(f"{k} {n}" for k, n in sorted(rb.get("failures", {}).items()))
    return f"{rb['succeeded']} of {rb['seeds']}" + (f" ({fails})" if fails else "")


def _current(d: Path, full: Path) -> tuple[dict | None, dict | None]:
    """``trajectories.json`` and ``execution.json`` of the variant folder ``d``, each only when made
    from the artifact before it there (by the sha256 its metadata records): a stage that failed
    leaves the older ones of an earlier plan behind. ``make reproduce`` copies the full planner's
    into a variant with the same steps, so its plan may also be ``full``'s."""
    mpc, ex = _read(d / "trajectories.json"), _read(d / "execution.json")
    traj = d / "trajectories.parquet"
    plans = {artifacts.sha256_file(p) for p in (d / "plan.json", full / "plan.json") if p.exists()}
    if mpc is None or mpc.get("meta", {}).get("inputs", {}).get("plan") not in plans:
        return None, None
    if not traj.exists() or artifacts.read_table(traj, "trajectories").meta["inputs"].get("plan") not in plans:
        return mpc, None
    if ex is not None and ex.get("meta", {}).get("inputs", {}).get("trajectories") != artifacts.sha256_file(traj):
        ex = None
    return mpc, ex


def collect(build_root: str | Path, scenes: list[str]) -> list[dict]:
    """One row per scene and variant with the plan, execution and timing figures."""
    rows = []
    root = Path(build_root)
    for scene in scenes:
        b = root / scene
        timings = {name: (_read(b / f) or {}).get(key) for name, f, key in STAGE_TIMINGS}
        for v in VARIANTS:
            plan = _read(b / v / "plan.json")
            if plan is None:
                continue
            mpc, ex = _current(b / v, b / "full")
            rows.append({
                "scene": scene, "variant": v, "build": b, "dir": b / v, "plan": plan, "execution": ex, "mpc": mpc,
                "timings": {**timings, "plan": (_read(b / v / "plan.json.timings.json") or {}).get("plan"),
                            "mpc": (_read(b / v / "trajectories.json.timings.json") or {}).get("mpc"),
                            "execute": (_read(b / v / "execution.json.timings.json") or {}).get("wall")},
                "margins": _plan_margins(b, plan), "robustness": _robustness(b / v, ex),
            })
    return rows


def _physics_lines(e: dict, rb: dict | None) -> list[str]:
    """The scene section's physics lines: the nominal run's criteria, force, slip, and the seeds."""
    err = 100 * e.get("final_position_error", 0)
    out = [f"- physics (nominal): success {e.get('success')}"
           f"{' (failed: ' + ', '.join(e.get('failures', [])) + ')' if e.get('failures') else ''}, final error "
           f"{err:.2f} cm / {e.get('final_yaw_error_deg', 0):.2f}° / tilt "
           f"{_fmt(e.get('final_tilt_error_deg'), '.2f')}°, {_fmt(e.get('rest_duration'), '.1f')} s after the "
           f"release (released {_fmt(e.get('released'))}, "
           f"retreated {_fmt(e.get('retreated'))}, at rest {_fmt(e.get('at_rest'))}), max deviation from the "
           f"planned path {100 * e.get('max_com_deviation', 0):.2f} cm, fell {e.get('fell')}",
           f"- ball force: peak {_fmt(e.get('max_ball_force'), '.1f')} N (20 ms average; one solver step "
           f"{_fmt(e.get('max_ball_force_step'), '.1f')} N) against the scene's bound "
           f"{_fmt(e.get('force_bound'), '.0f')} N, above it {_fmt(e.get('time_over_force_bound'), '.2f')} s, "
           f"commanded at its limit {_fmt(e.get('time_at_force_bound'), '.1f')} s; planned peak "
           f"{_fmt(e.get('max_planned_ball_force'), '.1f')} N",
           f"- support slip, worst: {_fmt(e.get('max_support_slip', None) and 1000 * e['max_support_slip'], '.1f')}"
           f" mm (primitive {_fmt(e.get('worst_slip_primitive'), 'd')}), "
           f"{_fmt(e.get('max_support_rotation_slip_deg'), '.2f')}° of rotation (primitive "
           f"{_fmt(e.get('worst_rotation_slip_primitive'), 'd')}); per primitive: " + ", ".join(
               f"{s['primitive']} {s['kind']} {1000 * s['translation']:.1f} mm / {s['rotation_deg']:.2f}°"
               for s in e.get("slip", []))]
    if rb is not None:
        q = {k: rb.get("meta", {}).get("params", {}).get(k, float("nan"))
             for k in ("friction_jitter", "mass_jitter", "com_jitter", "pose_jitter")}
        out.append(f"- robustness: {_seeds_cell(rb)} perturbed seeds succeed (friction ±"
                   f"{100 * q['friction_jitter']:.0f} %, mass ±{100 * q['mass_jitter']:.0f} %, CoM "
                   f"±{100 * q['com_jitter']:.1f} cm per axis, initial position ±{1000 * q['pose_jitter']:.0f} mm; "
                   f"{rb['required']} needed)")
    return out


def _calibration_lines(root: Path, scene: str) -> list[str]:
    """What was calibrated to reach the scene's paper figure (:data:`CALIBRATED`), with the one-grasp
    gait's planned stop at the geometry before (``pivot plan --no-regrasp`` of that scene, when built)."""
    if scene not in CALIBRATED:
        return []
    before, what = CALIBRATED[scene]
    plan = _read(root / before / "no-regrasp" / "plan.json")
    if plan is None:
        figure = f"not built here (`make SCENE={before} VARIANT=no-regrasp plan`)"
    elif plan.get("status") == "infeasible":
        figure = f"no plan ({plan.get('reason', '')})"
    else:
        e = plan.get("remaining_error", {"x": 0.0, "y": 0.0, "distance": 0.0})
        figure = (f"{100 * e['x']:+.1f} cm along x, {100 * e['y']:+.1f} cm along y ({100 * e['distance']:.1f} cm "
                  f"from its goal; plan {plan.get('status')})")
    return [f"Calibrated: {what}. The one-grasp gait's stop at the first geometry: {figure}."]


def _runs_table(rows: list[dict]) -> list[str]:
    """The report's "All runs" table: one row per scene and variant (plan, counts, physics criteria,
    final errors, peak force, slip, collision, perturbed seeds)."""
    lines = ["## All runs", "",
             "| scene | variant | plan | pivots | tumbles | regrasps | USP steps | removed edges | physics "
             "success | failed criteria | final error (cm / deg / tilt deg) | peak ball force (N, bound) | "
             "worst support slip (mm / deg) | collision | perturbed seeds that succeed |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p, e = r["plan"], r["execution"] or {}
        c = p.get("counts", {})
        usp = sum(1 for s in p.get("steps", []) if s.get("support") == "USP")
        err = (f"{_fmt(e.get('final_position_error', None) and 100 * e['final_position_error'], '.2f')} / "
               f"{_fmt(e.get('final_yaw_error_deg'), '.2f')} / {_fmt(e.get('final_tilt_error_deg'), '.2f')}") \
            if e else "–"
        force = f"{_fmt(e.get('max_ball_force'), '.1f')} ({_fmt(e.get('force_bound'), '.0f')})" if e else "–"
        slip = (f"{_fmt(e.get('max_support_slip', None) and 1000 * e['max_support_slip'], '.1f')} / "
                f"{_fmt(e.get('max_support_rotation_slip_deg'), '.2f')}") if e else "–"
        failed = ", ".join(e.get("failures", [])) or "none" if e else "–"
        lines.append(f"| {r['scene']} | {r['variant']} | {p['status']} | {c.get('pivot', '–')} | "
                     f"{c.get('tumble', '–')} | {c.get('regrasp', '–')} | {usp} | {len(p.get('log', []))} | "
                     f"{_fmt(e.get('success'))} | {failed} | {err} | {force} | {slip} | "
                     f"{_fmt(e.get('collision'))} | {_seeds_cell(r['robustness'])} |")
    lines.append("")
    return lines


def _scene_section(scene: str, r: dict, rel) -> list[str]:
    """The report's section of one scene's full planner: the paper's setting, the plan, the
    computation times, the grasps' stability margins, the physics and the figures (``rel`` makes
    their paths relative to the report)."""
    lines = [f"## {scene}", "", PAPER.get(scene, ""), ""]
    p, e = r["plan"], r["execution"] or {}
    c = p.get("counts", {})
    lines.append(f"- plan: {p['status']}, cost {_fmt(p.get('cost'), '.2f')}, {c.get('pivot', 0)} pivots, "
                 f"{c.get('tumble', 0)} tumbles, {c.get('regrasp', 0)} regrasps; "
                 f"{len(p.get('log', []))} edges removed by backtracking")
    if scene == "exp2_rotate" and e:
        lines.append(f"- achieved rotation about z in physics: {_fmt(e.get('achieved_yaw_deg'), '.1f')}° "
                     f"(goal error {_fmt(e.get('final_yaw_error_deg'), '.2f')}°)")
    if scene == "exp3_obstacle":
        usp = [i for i, s in enumerate(p.get("steps", [])) if s.get("support") == "USP"]
        usp_regrasp = c.get("usp_regrasp", 0)
        lines.append(f"- USP steps: {len(usp)}, regrasps in USP: {usp_regrasp}; object–obstacle contact in "
                     f"physics: {_fmt(e.get('object_obstacle_contacts'))}")
    t = r["timings"]
    lines.append("- computation (s): " + ", ".join(f"{k} {_fmt(v, '.2f')}" for k, v in t.items()))
    if r["margins"]:
        m = np.array(r["margins"])
        lines.append(f"- stability margins of the grasps along the plan (N, L1 wrench margin): min {m.min():.2f}, "
                     f"median {np.median(m):.2f}, max {m.max():.2f}")
    if e:
        lines += _physics_lines(e, r["robustness"])
    figs = [("plan", r["dir"] / "plan.png"), ("trajectories", r["dir"] / "trajectories.png"),
            ("execution", r["dir"] / "execution.png"), ("animation", r["dir"] / "execution.gif")]
    lines.append("")
    lines += [f"![{name}]({rel(path)})" for name, path in figs if path.exists()]
    lines.append("")
    return lines


def write_report(build_root: str | Path, out: str | Path, scenes: list[str]) -> str:
    """Write the Markdown report to ``out`` (atomically) and return its text."""
    rows = collect(build_root, scenes)
    out = Path(out)
    rel = lambda p: os.path.relpath(p, out.parent)  # noqa: E731
    lines = ["# pivot: the paper's experiments, reproduced", "",
             "Generated by `make reproduce` from the artifacts under `build/`. Plans come from `pivot plan` "
             "(with the ablation flags of each variant), trajectories from `pivot mpc`, and the physics "
             "columns from `pivot execute` (PyBullet; the object moves only through its contacts).", ""]
    lines += _runs_table(rows)

    by = {(r["scene"], r["variant"]): r for r in rows}
    full, base = by.get(("exp1_reach", "full")), by.get(("exp1_reach", "no-regrasp"))
    lines += ["## Table 2: reach with and without regrasping (Exp. 1)", "",
              "| method | ability to regrasp | error along x, planned | error along x, in physics | paper |",
              "|---|---|---|---|---|"]
    for label, r, regrasp, paper in (("graph MPC gait [3] (`--no-regrasp`)", base, "no", "−12.5 cm"),
                                     ("this planner", full, "yes", "0")):
        if r is None:
            lines.append(f"| {label} | {regrasp} | – | – | {paper} |")
            continue
        planned = r["plan"].get("remaining_error", {}).get("x", 0.0) if r["plan"]["status"] != "infeasible" else None
        e = r["execution"] or {}
        phys = e.get("final_com_error_x")
        lines.append(f"| {label} | {regrasp} | {_fmt(planned and 100 * planned, '+.1f')} cm | "
                     f"{_fmt(phys and 100 * phys, '+.1f')} cm | {paper} |")
    lines += ["", *_calibration_lines(Path(build_root), "exp1_reach"), ""]
    for scene in scenes:
        if (r := by.get((scene, "full"))) is not None:
            lines += _scene_section(scene, r, rel)
    text = "\n".join(lines) + "\n"
    with artifacts.atomic_path(out) as tmp:
        tmp.write_text(text)
    return text
