"""Speed of ``stages.mpc`` (§5.2): single QPs, piqp iterations, whole pivot and tumble primitives.

Objects: the paper's toy piano as a box (0.425 x 0.45 x 0.205 m, 3.1 kg, as ``bench_stability``)
and the 0.2 m, 2 kg cube of the tests. A pivot is one tilt-rotate-lower step about a base corner
(tilt 8 deg, yaw 20 deg, 0.8 + 1.2 + 0.8 s: the notes' slow-enough step) with two EEFs on opposite
side faces, high and past the CoM; a tumble turns the cube 90 deg about a base edge in 3 s with a
pusher and a catcher. Targets (2-core machine): a single QP <= 2 ms; a whole plan of ~10 primitives
<= 2 s, so one primitive <= 0.2 s.

Run ``python bench/bench_mpc.py``; ``bench/run.py`` calls :func:`rows`.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stages import mpc, se3  # noqa: E402

RUNS = 5
PIANO = np.array([0.425, 0.45, 0.205])
PIANO_MASS = 3.1
QP_TARGET_S = 2e-3
PRIMITIVE_TARGET_S = 0.2


def _box_inertia(size, mass):
    return mass / 12.0 * np.diag([size[1] ** 2 + size[2] ** 2, size[0] ** 2 + size[2] ** 2,
                                  size[0] ** 2 + size[1] ** 2])


def pivot_case(size, mass, yaw_deg=20.0, tilt_deg=8.0, durations=(0.8, 1.2, 0.8)):
    """Keyword arguments of :func:`stages.mpc.run_pivot_mpc` for one pivot of a box about corner 0."""
    half = np.asarray(size, dtype=float) / 2
    X0 = se3.make_transform(np.eye(3), [0.0, 0.0, half[2]])
    p0_O = -half
    p0_W = se3.transform_points(X0, p0_O)
    goal = se3.transform_about_line(p0_W, [0.0, 0.0, 1.0], np.deg2rad(yaw_deg)) @ X0
    t, X_ref, _ = mpc.pivot_reference(X0, goal, p0_W, np.deg2rad(tilt_deg), 0.02, durations)
    # Opposite y faces, at 0.9 of the height and 4 cm past the CoM away from the corner (notes).
    z = 0.8 * half[2]
    p_c = np.array([[0.04, -half[1], z], [0.04, half[1], z]])
    n_c = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    return dict(mass=mass, I_com_O=_box_inertia(size, mass), p_com_O=np.zeros(3), p_contacts_O=p_c,
                n_contacts_O=n_c, p0_W=p0_W, t=t, X_WO_ref=X_ref)


def tumble_case(a=0.2, mass=2.0):
    """Keyword arguments of :func:`stages.mpc.run_tumble_mpc`: a cube tipped 90 deg onto its front."""
    X0 = se3.make_transform(np.eye(3), [0.0, 0.0, a / 2])
    edge_W = np.array([[a / 2, -a / 2, 0.0], [a / 2, a / 2, 0.0]])
    t, X_ref, _ = mpc.tumble_reference(X0, edge_W[0], [0.0, 1.0, 0.0], np.pi / 2, 0.02, 3.0)
    p_c = np.array([[-a / 2, 0.0, 0.4 * a], [a / 2, 0.0, 0.4 * a]])
    n_c = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    return dict(mass=mass, I_com_O=_box_inertia([a, a, a], mass), p_com_O=np.zeros(3), p_contacts_O=p_c,
                n_contacts_O=n_c, p_edge_W=edge_W, t=t, X_WO_ref=X_ref, catch_time=1.0)


def _time_runs(fn, kwargs):
    wall, cpu, results = [], [], []
    for _ in range(RUNS):
        w0, c0 = time.perf_counter(), time.process_time()
        results.append(fn(**kwargs))
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return results, statistics.median(wall), statistics.median(cpu)


def bench_mpc() -> dict:
    """Figures of the MPC: per-QP solve time and iterations, whole-primitive times.

    Returns a dict with, per case (``piano_pivot``, ``cube_pivot``, ``cube_tumble``): ``steps``,
    ``status``, ``max_tracking_error_rad``, ``primitive_wall_s`` and ``primitive_cpu_s`` (medians
    of ``RUNS`` runs), ``per_step_ms``; and over every QP of the piano pivot runs:
    ``qp_median_s``, ``qp_p95_s``, ``iter_median``, ``iter_max``; and the targets.
    """
    out: dict = {"qp_target_s": QP_TARGET_S, "primitive_target_s": PRIMITIVE_TARGET_S, "runs": RUNS}
    cases = (("piano_pivot", mpc.run_pivot_mpc, pivot_case(PIANO, PIANO_MASS)),
             ("cube_pivot", mpc.run_pivot_mpc, pivot_case([0.2, 0.2, 0.2], 2.0, yaw_deg=15.0)),
             ("cube_tumble", mpc.run_tumble_mpc, tumble_case()))
    for name, fn, kwargs in cases:
        fn(**kwargs)  # warm-up (imports, caches)
        results, wall, cpu = _time_runs(fn, kwargs)
        res = results[0]
        out[name] = {
            "steps": len(res.t),
            "status": res.status,
            "max_tracking_error_rad": float(np.nanmax(res.tracking_error)),
            "primitive_wall_s": wall,
            "primitive_cpu_s": cpu,
            "per_step_ms": 1e3 * wall / len(res.t),
        }
        if name == "piano_pivot":
            solve = np.concatenate([r.timings.solve_time_s for r in results])
            iters = np.concatenate([r.n_iter for r in results])
            out["qp_median_s"] = float(np.nanmedian(solve))
            out["qp_p95_s"] = float(np.nanpercentile(solve, 95))
            out["iter_median"] = float(np.median(iters[iters >= 0]))
            out["iter_max"] = int(iters.max())
    return out


def rows(result: dict | None = None) -> list[tuple[str, str, str, str]]:
    """Table rows ``(what, measured, target, paper)`` for ``bench/run.py``."""
    r = bench_mpc() if result is None else result

    def ok(value, target):
        return "ok" if value <= target else "MISSED"

    out = [("mpc: single QP (piano pivot), median / p95",
            f"{1e3 * r['qp_median_s']:.3f} / {1e3 * r['qp_p95_s']:.3f} ms",
            f"<= {1e3 * r['qp_target_s']:.0f} ms {ok(r['qp_median_s'], r['qp_target_s'])}", ""),
           ("mpc: piqp iterations per QP, median / max", f"{r['iter_median']:.0f} / {r['iter_max']}", "", "")]
    for name in ("piano_pivot", "cube_pivot", "cube_tumble"):
        c = r[name]
        out.append((f"mpc: whole {name.replace('_', ' ')} ({c['steps']} steps, {c['status']})",
                    f"{c['primitive_wall_s']:.3f} s wall, {c['primitive_cpu_s']:.3f} s cpu "
                    f"({c['per_step_ms']:.2f} ms/step, max err {c['max_tracking_error_rad']:.1e} rad)",
                    f"<= {r['primitive_target_s']} s {ok(c['primitive_wall_s'], r['primitive_target_s'])}", ""))
    return out


if __name__ == "__main__":
    table = rows()
    widths = [max(len(row[i]) for row in table) for i in range(3)]
    for row in table:
        print("  ".join(c.ljust(w) for c, w in zip(row[:3], widths, strict=True)))
