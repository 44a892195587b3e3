"""Throughput of ``stages.stability.evaluate`` on grasp candidates like the sampler's (§4.3, §5.1).

The object is the paper's toy piano as a box (0.425 x 0.45 x 0.205 m, 3.1 kg). Three support cases,
a third of the candidates each: SP (resting on its base, four table corners, two EEFs on opposite side
faces), pivot (tilted 5-12 degrees onto one base corner, two EEFs on opposite side faces) and USP hold
(tilted 10-70 degrees onto one base edge, one EEF on the top face or the raised end face). Contacts
are drawn uniformly on the faces, so some candidates are stable and some are not.

Run ``python bench/bench_stability.py [n]``; ``bench/run.py`` calls :func:`rows`. Times are the best of
three runs, single-threaded.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages import se3  # noqa: E402
from stages.stability import Params, evaluate  # noqa: E402

SIZE = np.array([0.425, 0.45, 0.205])
MASS = 3.1


def _box_pose(rng, n, tilt_max):
    """Poses ``X_WO (n, 4, 4)`` of the box resting on (or tilted about) its base corner 0."""
    yaw = rng.uniform(-np.pi, np.pi, n)
    tilt = np.deg2rad(rng.uniform(5.0, tilt_max, n)) if tilt_max > 0 else np.zeros(n)
    # Tilt about the horizontal axis through corner 0 perpendicular to the corner-to-CoM direction.
    half = SIZE / 2
    corner_O = -half * np.array([1, 1, 1])
    r = -corner_O[:2] / np.linalg.norm(corner_O[:2])
    axis = np.array([-r[1], r[0], 0.0])
    X_tilt = se3.transform_about_line(corner_O, axis, tilt)
    X_lift = se3.make_transform(np.eye(3), np.array([0, 0, half[2]]))
    X_yaw = se3.make_transform(se3.rot_z(yaw), rng.uniform(-0.2, 0.2, (n, 3)) * [1, 1, 0])
    return X_yaw @ X_lift @ X_tilt


def _side_contacts(rng, n, e):
    """``e`` EEF contacts on the box's side faces ``(n, e, 3)`` in O, with inward normals."""
    half = SIZE / 2
    axis = rng.integers(0, 2, n)                       # opposite x faces or opposite y faces
    p = rng.uniform(-1, 1, (n, e, 3)) * half * 0.9
    sign = np.array([1.0, -1.0])[:e]
    rows = np.arange(n)
    p[rows, :, axis] = sign * half[axis][:, None]
    nrm = np.zeros((n, e, 3))
    nrm[rows, :, axis] = -sign
    return p, nrm


def make_candidates(n, seed=0):
    """Candidate sets per case: dict name -> keyword arguments of ``evaluate`` (W frame)."""
    rng = np.random.default_rng(seed)
    half = SIZE / 2
    corners_O = np.array([[sx, sy, -1] for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]) * half
    counts = [n // 3, n // 3, n - 2 * (n // 3)]
    out = {}
    # SP: flat on the base, four corners.
    X = _box_pose(rng, counts[0], 0.0)
    p, nrm = _side_contacts(rng, counts[0], 2)
    out["sp"] = dict(X=X, table=corners_O, eef=p, nrm=nrm)
    # Pivot: one corner, two EEFs.
    X = _box_pose(rng, counts[1], 12.0)
    p, nrm = _side_contacts(rng, counts[1], 2)
    out["pivot"] = dict(X=X, table=corners_O[:1], eef=p, nrm=nrm)
    # USP: tilted 10-70 degrees about its base edge x = -half (corners 0 and 3), one EEF on the top
    # face or on the raised end face x = +half.
    nu = counts[2]
    tilt = np.deg2rad(rng.uniform(10.0, 70.0, nu))
    X_tilt = se3.transform_about_line(np.array([-half[0], 0.0, -half[2]]), np.array([0.0, -1.0, 0.0]), tilt)
    X_lift = se3.make_transform(np.eye(3), np.array([0, 0, half[2]]))
    X = se3.make_transform(se3.rot_z(rng.uniform(-np.pi, np.pi, nu)), np.zeros(3)) @ X_lift @ X_tilt
    p = rng.uniform(-1, 1, (nu, 1, 3)) * half * 0.9
    top = rng.random(nu) < 0.5
    p[top, 0, 2] = half[2]
    p[~top, 0, 0] = half[0]
    nrm = np.where(top[:, None, None], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0])
    out["usp"] = dict(X=X, table=corners_O[[0, 3]], eef=p, nrm=nrm)
    cases = {}
    for name, c in out.items():
        X = c["X"]
        N = len(X)
        table = se3.transform_points(X[:, None], np.broadcast_to(c["table"], (N,) + c["table"].shape))
        cases[name] = dict(
            mass=MASS, com_W=X[:, :3, 3], table_pts_W=table, table_mask=np.ones(table.shape[:2], bool),
            eef_pts_W=se3.transform_points(X[:, None], c["eef"]),
            eef_normals_W=se3.rotate_vectors(X[:, None], c["nrm"]),
            eef_mask=np.ones(c["eef"].shape[:2], bool), L=float(np.linalg.norm(half)),
            R_WD=X[:, :3, :3])
    return cases


def bench_stability(n=30000, seed=0, params=None, repeats=3):
    """Candidates per second of ``evaluate``, feasibility only and with margins; best of ``repeats``.

    Returns a dict: totals (``feasibility_s``, ``feasibility_per_s``, ``with_margin_s``,
    ``with_margin_per_s``, ``margin_per_stable_s``: stable candidates whose 12 margin LPs are solved
    per second) and, per case, its counts (``stats`` of the result) and times.
    """
    params = Params() if params is None else params
    cases = make_candidates(n, seed)
    result = {"n": n}
    per_case = {k: {} for k in cases}
    for label, margin in (("feasibility", False), ("with_margin", True)):
        total = 0.0
        for name, c in cases.items():
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                res = evaluate(**c, params=params, compute_margin=margin)
                best = min(best, time.perf_counter() - t0)
            total += best
            per_case[name][f"{label}_s"] = round(best, 4)
            per_case[name].update(stable=int(res.stable.sum()), **res.stats)
        result[f"{label}_s"] = total
        result[f"{label}_per_s"] = n / total
    n_stable = sum(v["stable"] for v in per_case.values())
    result["margin_per_stable_s"] = n_stable / max(result["with_margin_s"] - result["feasibility_s"], 1e-9)
    result.update(per_case)
    return result


def rows(n=30000):
    """Table rows ``(what, measured, target, paper)`` for ``bench/run.py``."""
    r = bench_stability(n)
    lp = sum(r[k]["feasibility_lps"] for k in ("sp", "pivot", "usp"))
    return [
        (f"stability: feasibility, {n} candidates ({lp} LPs)",
         f"{r['feasibility_s']:.3f} s ({r['feasibility_per_s']:.0f}/s)", "<= 1 s (whole refinement)",
         "9.362 s refinement, 33,170 checks"),
        ("stability: + L1 margins of the stable ones (12 LPs each)",
         f"{r['with_margin_s']:.3f} s ({r['margin_per_stable_s']:.0f} stable/s)", "", ""),
    ]


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 30000
    for key, value in bench_stability(n).items():
        print(f"{key}: {value}")
