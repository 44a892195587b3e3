"""Throughput of the robot model: batched IK (targets/s, success) and collision checks (checks/s).

Run from the repository root: ``python bench/bench_robot.py [--n 10000] [--seed 0] [--no-retain]``.
The grasp sampler calls IK on 30,000-60,000 targets per scene and must finish its whole refinement
(IK, collisions, stability) in about a second on two cores, so IK needs roughly 100,000 targets/s.
Rates are given against wall-clock time and against this process's CPU time (the latter is steadier
when other work shares the machine).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from stages import se3  # noqa: E402
from stages.robot import load_robot, make_collision_fn, retain_freed_memory  # noqa: E402

URDF = ROOT / "data" / "robots" / "sda5f.urdf"
#: Robot base on the floor 0.75 m behind the centre of a 0.9 x 0.6 m table whose top (the world
#: origin) is 0.6 m above the floor: the shoulders are 0.3 m above the table.
X_WB = se3.make_transform(np.eye(3), [-0.75, 0.0, -0.6])
TABLE = ((0.9, 0.6), 0.0)
#: The toy piano's bounding box (0.425 x 0.45 x 0.205 m) standing on the table.
OBJECT_SIZE = np.array([0.425, 0.45, 0.205])


def _timed(fn, repeats: int):
    """Median wall and CPU seconds of ``repeats`` calls, and the last result."""
    wall, cpu, out = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu), out


def bench_ik(n: int = 10000, seed: int = 0, repeats: int = 3, retain: bool = True) -> dict:
    """Time IK and collision checks; returns rates (per second), success and outcome counts.

    IK: ``n`` random reachable targets (ball centres of uniformly random in-limit postures of the left
    arm), with one and with two worker threads, after the seed libraries are built (timed apart).
    Collisions: ``n`` grasp-like pairs, each ball on one side face of a piano-sized box on the table
    (random x and z on the face), both arms solved by IK, then checked against the table and the box
    with both balls touching it. ``retain`` calls ``retain_freed_memory`` first (process-wide).
    """
    out = {"n": n, "retain": retain and retain_freed_memory()}
    robot = load_robot(URDF, X_WB=X_WB)
    rng = np.random.default_rng(seed)
    left = robot.arms["left"]
    p = robot.eef_position("left", rng.uniform(left.lower, left.upper, (n, left.dof)))

    t0 = time.perf_counter()
    robot._library("left")
    robot._library("right")
    out["library_s"] = time.perf_counter() - t0
    for threads in (1, 2):
        r = replace(robot, ik_params=replace(robot.ik_params, threads=threads), _cache=robot._cache)
        wall, cpu, res = _timed(lambda r=r: r.ik("left", p, rng=np.random.default_rng(seed)), repeats)
        out[f"ik_per_s_{threads}t"] = n / wall
        out[f"ik_per_cpu_s_{threads}t"] = n / cpu
    out["ik_success"] = float(np.mean(res.err <= 1e-3))
    out["ik_reasons"] = {k: int(v) for k, v in zip(*np.unique(res.reason, return_counts=True), strict=True)}

    # Grasp-like pairs: contacts on the box's +y / -y faces, ball centres 2 cm outside.
    half = OBJECT_SIZE / 2
    X_WO = se3.make_transform(np.eye(3), [0.0, 0.0, half[2]])
    u = rng.uniform(-0.8, 0.8, (n, 2))
    p_O = np.column_stack([u[:, 0] * half[0], np.full(n, half[1] + 0.02), half[2] * u[:, 1]])
    res_l = robot.ik("left", se3.transform_points(X_WO, p_O), rng=np.random.default_rng(seed))
    res_r = robot.ik("right", se3.transform_points(X_WO, p_O * [1.0, -1.0, 1.0]), rng=np.random.default_rng(seed))
    check = make_collision_fn(robot, table=TABLE, object_mesh=trimesh.creation.box(OBJECT_SIZE))
    args = (res_l.q, res_r.q, np.broadcast_to(X_WO, (n, 4, 4)), np.ones((n, 2), bool))
    wall, cpu, (ok, reason) = _timed(lambda: check(*args), repeats)
    out["collision_per_s"] = n / wall
    out["collision_per_cpu_s"] = n / cpu
    out["grasp_ik_success"] = float(np.mean(res_l.ok & res_r.ok))
    out["collision_free"] = float(np.mean(ok))
    kinds, counts = np.unique([r.split(":")[0] for r in reason], return_counts=True)
    out["collision_kinds"] = dict(zip(kinds.tolist(), counts.tolist(), strict=True))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-retain", action="store_true", help="leave glibc's memory trimming as it is")
    args = ap.parse_args(argv)
    r = bench_ik(args.n, args.seed, args.repeats, retain=not args.no_retain)
    rows = [
        ("targets", f"{r['n']:d}  (retain_freed_memory: {'on' if r['retain'] else 'off'})"),
        ("seed libraries, both arms", f"{r['library_s'] * 1e3:.0f} ms"),
        ("IK, 1 thread", f"{r['ik_per_s_1t']:>9,.0f} targets/s  ({r['ik_per_cpu_s_1t']:,.0f} per CPU s)"),
        ("IK, 2 threads", f"{r['ik_per_s_2t']:>9,.0f} targets/s  ({r['ik_per_cpu_s_2t']:,.0f} per CPU s)"),
        ("IK success (err <= 1 mm)", f"{100 * r['ik_success']:.2f} %  "
         + ", ".join(f"{k} {v}" for k, v in r["ik_reasons"].items())),
        ("collision checks", f"{r['collision_per_s']:>9,.0f} checks/s   ({r['collision_per_cpu_s']:,.0f} per CPU s)"),
        ("grasp-like pairs: IK ok, free", f"{100 * r['grasp_ik_success']:.1f} %, {100 * r['collision_free']:.1f} %  "
         + ", ".join(f"{k} {v}" for k, v in r["collision_kinds"].items())),
    ]
    width = max(len(k) for k, _ in rows)
    print(f"robot bench: {os.cpu_count()} cores, median of {args.repeats}")
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")


if __name__ == "__main__":
    main()


def rows(result: dict | None = None) -> list[tuple[str, str, str, str]]:
    """``(what, measured, target, paper)`` rows for ``make bench``."""
    r = result or bench_ik()
    best = max(r["ik_per_s_1t"], r["ik_per_s_2t"])
    ok = "ok" if best >= 100_000 else "MISSED"
    return [
        ("IK throughput (position, batched)", f"{best:,.0f} targets/s, {100 * r['ik_success']:.2f} % within 1 mm",
         f">= 100,000/s {ok}", "–"),
        ("collision checks (both arms)", f"{r['collision_per_s']:,.0f} configurations/s", "", "–"),
    ]
