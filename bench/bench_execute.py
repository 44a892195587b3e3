"""Speed of ``stages.execute`` (§6): the PyBullet runs of the pivot and tumble trajectories of the tests.

The trajectory is ``tests.test_execute.make_pivot_case``: the toy piano on the default scene, an
approach, a grip, one pivot about its front-right foot (tilt 8 deg, yaw -15 deg, 3 x 2.5 s), a settle
and a release, 10.7 s at 1/240 s physics steps (rows every 5 steps). Target: at least 10 simulated
seconds per wall second for the stepping loop (the notes measured 7-10x for two free balls with
per-step contact queries; here the whole robot is simulated and controlled). The CPU-time figure is
beside it because a loaded 2-core machine halves the wall-clock one.

The tumble is ``tests.test_execute._tumble_plan`` on a 1 m deep table: the upright piano tumbled onto
its back, the catcher sliding out (``stages.trajectory.plan_tumble``); the time to compute its
trajectory (the MPC stage: catcher search, IK, transits, MPC) is measured too.

Run ``python bench/bench_execute.py``; ``bench/run.py`` calls :func:`rows`.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stages import analyze, artifacts, execute, trajectory  # noqa: E402
from tests.conftest import PIANO  # noqa: E402
from tests.test_execute import SCENE_PATH, _tumble_plan, make_pivot_case  # noqa: E402

RUNS = 3
SPEED_TARGET = 20.0  # issue 20


def bench_execute() -> dict:
    """Medians over ``RUNS`` runs (after one warm-up that also fills the decomposition cache).

    Returns ``sim_speed`` (simulated s per wall s of the stepping loop), ``sim_speed_cpu`` (per CPU s),
    ``sim_speed_total`` (including world set-up), ``steps``, ``duration`` (s) and the outcome of the
    first run (``final_position_error`` m, ``final_yaw_error_deg``, ``max_pivot_slip`` m, ``success``).
    """
    case = make_pivot_case()
    with tempfile.TemporaryDirectory() as cache:
        params = execute.Params(cache_dir=cache)

        def run():
            return execute.simulate(case["scene"], PIANO, case["mass"], case["com_O"], case["inertia_O"],
                                    case["traj"], case["X1"], params)

        run()
        results = [run() for _ in range(RUNS)]
    m = results[0].metrics
    out = {k: statistics.median(r.timings[k] for r in results)
           for k in ("sim_speed", "sim_speed_cpu", "sim_speed_total")}
    out.update({k: m[k] for k in ("steps", "duration", "final_position_error", "final_yaw_error_deg",
                                  "max_pivot_slip", "success")})
    return out


def bench_tumble() -> dict:
    """One run of the tumble: ``mpc_s`` (wall s to compute its trajectory), ``sim_speed``, ``steps``,
    ``duration`` (s), the catcher's ``mode`` and the outcome (``final_position_error`` m,
    ``final_yaw_error_deg``, ``max_edge_slip`` m, ``success``)."""
    import time

    from stages.scene import load_scene

    with tempfile.TemporaryDirectory() as tmp:
        an = Path(tmp) / "analysis"
        analyze.run(PIANO, an, load_scene(SCENE_PATH).object.mass, analyze.Params())
        scene, plan, X_to = _tumble_plan(an, (0.9, 1.0))
        t0 = time.perf_counter()
        cols, stats = trajectory.compute(scene, an, plan, trajectory.Params())
        mpc_s = time.perf_counter() - t0
        summ = artifacts.read_json(an / "analysis.json", "analysis")
        ex = execute.simulate(scene, an / "object.ply", float(summ["mass"]), summ["com"], summ["inertia"], cols, X_to,
                              execute.Params(cache_dir=tmp))
    m = ex.metrics
    return {"mpc_s": mpc_s, "sim_speed": ex.timings["sim_speed"], "mode": stats["tumbles"][0]["mode"],
            **{k: m[k] for k in ("steps", "duration", "final_position_error", "final_yaw_error_deg", "max_edge_slip",
                                 "success")}}


def rows(result: dict | None = None, tumble: dict | None = None) -> list[tuple[str, str, str, str]]:
    """Table rows ``(what, measured, target, paper)`` for ``bench/run.py``."""
    r = bench_execute() if result is None else result
    u = bench_tumble() if tumble is None else tumble
    ok = "ok" if r["sim_speed"] >= SPEED_TARGET else "MISSED"
    ok_u = "ok" if u["sim_speed"] >= SPEED_TARGET else "MISSED"
    return [
        (f"execute: pivot in PyBullet ({r['steps']} steps, {r['duration']:.1f} s simulated)",
         f"{r['sim_speed']:.1f}x real time wall ({r['sim_speed_cpu']:.1f}x per CPU s, "
         f"{r['sim_speed_total']:.1f}x with set-up)",
         f">= {SPEED_TARGET:.0f}x {ok}", ""),
        ("execute: pivot outcome (final error, slip)",
         f"{1e3 * r['final_position_error']:.2f} mm, {r['final_yaw_error_deg']:.2f} deg, slip "
         f"{1e3 * r['max_pivot_slip']:.2f} mm, success {r['success']}",
         "<= 10 mm, <= 2 deg, slip < 5 mm", "Fig. 15-16 (qualitative)"),
        (f"mpc: tumble trajectory (catcher, IK, transits, MPC; {u['duration']:.1f} s of motion)",
         f"{u['mpc_s']:.1f} s", "", ""),
        (f"execute: tumble onto the back in PyBullet ({u['steps']} steps, catcher {u['mode']})",
         f"{u['sim_speed']:.1f}x real time wall", f">= {SPEED_TARGET:.0f}x {ok_u}", ""),
        ("execute: tumble outcome (final error, edge slip)",
         f"{1e3 * u['final_position_error']:.2f} mm, {u['final_yaw_error_deg']:.2f} deg, edge slip "
         f"{1e3 * u['max_edge_slip']:.2f} mm, success {u['success']}",
         "<= 10 mm, <= 2 deg (notes: 0.4-5.3 mm, slip 3-8 mm)", "Fig. 18 (qualitative)"),
    ]


if __name__ == "__main__":
    table = rows()
    widths = [max(len(row[i]) for row in table) for i in range(4)]
    for row in table:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)))
