"""Regrasp transits (§5.2.2, §5.3) on the default scene: planning time and success rate.

The toy piano stands at the default scene's start placement. Grasps are the analysis's antipodal
contact pairs (the left ball on the contact with the larger world y) whose IK succeeds for both arms and
whose configuration is collision-free. A regrasp query moves one arm from its contact in one grasp to
its contact in another while the other arm holds its contact; both end configurations are
collision-free, so a failure is the transit's. Queries are drawn with a seeded generator.

Run ``python bench/bench_transit.py [n_queries]``.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stages import analyze, se3, transit  # noqa: E402
from stages.robot import load_robot  # noqa: E402
from stages.sample import make_scene_collision_fn  # noqa: E402
from stages.scene import load_scene  # noqa: E402

#: Target for one regrasp transit on a 2-core machine (DESIGN.md leaves it to the bench).
TARGET_S = 0.2


#: Object poses: the scene's start and goal placements and the goal turned about z by these angles (rad).
EXTRA_YAWS = (-np.pi / 6, np.pi / 6)
#: IK attempts per contact (the IK returns one solution; other seeds find other branches).
IK_SEEDS = 6


def make_setup():
    """``(robot, collide, cases)`` on the default scene. Each case is a dict with ``X_WO (4, 4)`` and
    ``q_left, q_right (G, n)``, ``n_left, n_right (G, 3)`` (outward contact normals, W) of its
    collision-free grasps."""
    scene = load_scene(REPO / "data" / "scenes" / "default.json")
    mesh = analyze.load_mesh(scene.object.mesh_path, scene.object.scale)
    an = analyze.compute(mesh, scene.object.mass, analyze.Params())
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    collide = make_scene_collision_fn(scene, robot, mesh)
    normals = np.stack([an.placements["nx"], an.placements["ny"], an.placements["nz"]], axis=1)
    X_TO = se3.matrix_from_columns(an.placements)
    poses = []
    for spec, yaws in ((scene.start, (0.0,)), (scene.goal, (0.0, *EXTRA_YAWS))):
        g = int(np.argmax(normals @ np.asarray(spec.down_unit)))
        for dy in yaws:
            poses.append(se3.make_transform(se3.rot_z(spec.yaw + dy), np.array([*spec.xy, 0.0])) @ X_TO[g])
    c = an.contacts
    p_O = np.stack([c["px"], c["py"], c["pz"]], axis=1)
    n_O = np.stack([c["nx"], c["ny"], c["nz"]], axis=1)
    rng = np.random.default_rng(0)
    cases = []
    for X_WO in poses:
        p, nrm = se3.transform_points(X_WO, p_O), se3.rotate_vectors(X_WO, n_O)
        ball = p + scene.robot.ball_radius * nrm
        C = len(p)
        # Per arm and contact: the first IK solution (over several seeds) that is collision-free with the
        # other arm out of the way (q = 0: upper arm sideways, forearm up).
        q_arm = {}
        for arm in ("left", "right"):
            a = robot.arm(arm)
            best = np.full((C, a.dof), np.nan)
            for k in range(IK_SEEDS):
                seed = None if k == 0 else np.clip(a.q_rest + rng.normal(0.0, 0.6, (C, a.dof)), a.lower, a.upper)
                ik = robot.ik(arm, ball, q_seed=seed, rng=rng)
                away = np.zeros_like(ik.q)
                args = (ik.q, away) if arm == "left" else (away, ik.q)
                free, _ = collide(*args, np.broadcast_to(X_WO, (C, 4, 4)), np.ones((C, 2), bool))
                take = ik.ok & free & np.isnan(best[:, 0])
                best[take] = ik.q[take]
            q_arm[arm] = best
        pa, pb = an.pairs["contact_a"], an.pairs["contact_b"]
        left = np.where(p[pa, 1] >= p[pb, 1], pa, pb)
        right = np.where(p[pa, 1] >= p[pb, 1], pb, pa)
        has = ~np.isnan(q_arm["left"][left, 0]) & ~np.isnan(q_arm["right"][right, 0])
        left, right = left[has], right[has]
        ql, qr = q_arm["left"][left], q_arm["right"][right]
        free, _ = collide(ql, qr, np.broadcast_to(X_WO, (len(ql), 4, 4)), np.ones((len(ql), 2), bool))
        cases.append({"X_WO": X_WO, "q_left": ql[free], "q_right": qr[free], "n_left": nrm[left[free]],
                      "n_right": nrm[right[free]]})
    return robot, collide, cases


def make_queries(robot, collide, cases, n: int, seed: int = 0) -> list[dict]:
    """``n`` regrasp queries (keyword arguments of ``plan_transit`` without robot, collide, params)."""
    rng = np.random.default_rng(seed)
    cases = [c for c in cases if len(c["q_left"]) >= 2]
    out = []
    while len(out) < n:
        case = cases[int(rng.integers(0, len(cases)))]
        X_WO = case["X_WO"]
        i, j = rng.integers(0, len(case["q_left"]), 2)
        arm = ("left", "right")[int(rng.integers(0, 2))]
        other = "right" if arm == "left" else "left"
        qs, qg, qo = case[f"q_{arm}"][i], case[f"q_{arm}"][j], case[f"q_{other}"][i]
        if np.linalg.norm(robot.eef_position(arm, qs[None]) - robot.eef_position(arm, qg[None])) < 0.05:
            continue  # not a regrasp
        q_l, q_r = (qg, qo) if arm == "left" else (qo, qg)
        if not collide(q_l[None], q_r[None], X_WO[None], np.ones((1, 2), bool))[0][0]:
            continue  # the goal collides with the holding arm: not a transit problem
        out.append(dict(arm=arm, q_start=qs, q_goal=qg, q_other=qo, X_WO=X_WO, n_start=case[f"n_{arm}"][i],
                        n_goal=case[f"n_{arm}"][j]))
    return out


def bench_transit(n: int = 20, params: transit.Params | None = None) -> dict:
    """Plan ``n`` random regrasp queries; times, statuses and planner use."""
    params = params or transit.Params()
    robot, collide, cases = make_setup()
    queries = make_queries(robot, collide, cases, n)
    transit.plan_transit(robot, collide, **queries[0], params=params)  # warm-up (IK library, imports)
    times, results = [], []
    for q in queries:
        t0 = time.perf_counter()
        res = transit.plan_transit(robot, collide, **q, params=params)
        times.append(time.perf_counter() - t0)
        results.append(res)
    return {"n": n, "grasps": [len(c["q_left"]) for c in cases], "times": times, "results": results}


def rows(b: dict | None = None) -> list[tuple[str, str, str, str]]:
    """(what, measured, target, paper) rows of ``bench_transit(20)`` (or of ``b``)."""
    b = b or bench_transit(20)
    times, res = b["times"], b["results"]
    ok = sum(r.status == "ok" for r in res)
    rrt = [t for t, r in zip(times, res, strict=True) if r.stats.get("planner") == "rrt_connect"]
    med = statistics.median(times)
    status = "ok" if med <= TARGET_S else "MISSED"
    out = [("transit: regrasp, median planning time", f"{med:.3f} s (max {max(times):.3f} s; "
            f"{b['n'] - len(rrt)}/{b['n']} straight)", f"<= {TARGET_S} s {status}", "RRT, no time given")]
    if rrt:
        out.append(("transit: regrasp needing RRT-Connect, median", f"{statistics.median(rrt):.3f} s "
                    f"({len(rrt)} queries)", "", ""))
    out.append((f"transit: regrasp success, {b['n']} random queries", f"{ok}/{b['n']} (grasps per pose "
                f"{b['grasps']})", "", ""))
    return out


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 20
    b = bench_transit(n)
    for r, t in zip(b["results"], b["times"], strict=True):
        print(f"{t:.3f} s  {r.status:18s} {r.stats.get('planner', ''):12s} checks {r.stats.get('checks')} "
              f"states {r.stats.get('states')} K {len(r.path)}  {r.reason if r.status != 'ok' else ''}")
    for row in rows(b):
        print(row)
