"""Stage ``mpc``: a plan's primitives as dense force and joint trajectories (§5.2, eq. 5–11, Fig. 12).

Reads ``plan.json`` and writes ``trajectories.parquet``: one row per time step (``Params.mpc.dt``),
in plan order, with the object's planned pose, both ball centres, both ball forces on the object,
the table reaction, all joint angles and the contact flags. Per primitive:

- **transit** (the arms of a regrasp, the pusher before a tumble): the plan's joint waypoints,
  time-parameterized under the joint velocity limits (``stages.transit.time_parameterize``); the
  moving ball is off the object, the other keeps its contact when it had one;
- **pivot**: the tilt → rotate → lower reference about the support vertex, tracked by the MPC
  (``stages.mpc.run_pivot_mpc``); the object pose is the MPC's simulated pose, the ball centres
  follow it (``p_i(t) = X_WO(t) p_Oi`` moved out by the ball radius) and batched IK gives the joints
  along the way, seeded step by step (no branch flips);
- **tumble**: the rotation about the support edge, pushed by one ball for ``push_angle`` with the
  tumbling MPC (``run_tumble_mpc``, one ball), then the ball lets go and the object lands; the planned
  pose follows the reference to the new face;
- **hold**: a short pause before and after each contact change.

An MPC failure on an existing plan is reported (status ``mpc_infeasible`` with the primitive) and
the stage exits 1: ``pivot plan`` runs the same MPC while it searches, so a plan it accepted passes
unless the MPC parameters were changed here.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from stages import artifacts, mpc, se3, transit
from stages.artifacts import Field
from stages.errors import InputError
from stages.graph import Params as GraphParams
from stages.graph import pusher_motion
from stages.objectmodel import load_object_model
from stages.robot import load_robot
from stages.sample import make_scene_collision_fn
from stages.scene import load_scene


@dataclass(frozen=True)
class Params:
    """Trajectory generation: MPC settings and primitive timing (s)."""

    #: MPC settings; dt = 1/24 s puts every row on the physics clock (10 steps of 1/240 s, stages.execute).
    mpc: mpc.Params = field(default_factory=lambda: mpc.Params(dt=1.0 / 24.0))
    #: The MPC plans with this fraction of the scene's friction coefficients, so that the forces it
    #: plans leave room for what the compliant arms add in execution (the squeeze).
    friction_safety: float = 0.8
    pivot_durations: tuple[float, float, float] = (2.5, 3.0, 2.5)
    tumble_duration: float = 4.0
    hold: float = 0.5
    #: IK on every this many rows of a pivot or push (joints interpolated in between).
    ik_every: int = 4
    #: Fraction of the joint velocity limits used by transits.
    vel_scale: float = 0.5
    acc: float = 2.0


@dataclass
class _Rows:
    """Accumulates trajectory rows, primitive by primitive."""

    cols: dict = field(default_factory=lambda: {k: [] for k in COLUMNS})

    def add(self, **arrays):
        """One primitive's rows: every array has the same leading length T."""
        T = len(arrays["t"])
        for k in COLUMNS:
            v = np.asarray(arrays[k])
            assert len(v) == T, k
            self.cols[k].append(v)


COLUMNS = ("t", "primitive", "kind", "phase", "X", "X_ref", "X_start", "p_l", "p_r", "f_l", "f_r", "f_table",
           "q_l", "q_r", "c_l", "c_r")


def _ik_path(robot, arm: str, targets: np.ndarray, q0: np.ndarray, every: int) -> np.ndarray:
    """Joint path ``(T, n)`` through ball targets ``(T, 3)``: IK (seeded step to step, one branch) on
    every ``every``-th target and the last, joints interpolated linearly in between (the motions are
    slow: the ball then strays well under a millimetre from its target between IK samples)."""
    T = len(targets)
    keys = np.unique(np.r_[np.arange(0, T, max(every, 1)), T - 1])
    qk = robot.ik_trajectory(arm, targets[keys], q0).q
    t = np.arange(T)
    return np.stack([np.interp(t, keys, qk[:, j]) for j in range(qk.shape[1])], axis=1)


def _ball_centres(X, p_O, n_O, r):
    """Ball centres ``(T, 3)`` (W) touching at ``p_O`` with outward normal ``n_O`` (O)."""
    return se3.transform_points(X, p_O + r * n_O)


def compute(scene, analysis_dir, plan: dict, params: Params) -> tuple[dict, dict]:
    """Dense trajectories of ``plan`` (module docstring); returns ``(columns, summary)``."""
    model, tables = load_object_model(analysis_dir)
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    collide = None  # built on the first tumble only: pivots and transits need no collision checks here
    con = tables["contacts"]
    p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    r = scene.robot.ball_radius
    summ = tables["summary"]
    mp = replace(params.mpc, mu_eef=params.friction_safety * scene.object.friction,
                   mu_table=params.friction_safety * scene.table.friction,
                 f_max=scene.robot.max_eef_force)
    dt = mp.dt
    rows = _Rows()
    n = robot.arm("left").dof
    q = {"left": np.zeros(n), "right": np.zeros(n)}
    contact = {"left": -1, "right": -1}
    t_now = 0.0
    stats = {"primitives": 0, "mpc_max_error": 0.0, "mpc_iters": [], "status": "ok", "failed_primitive": -1}
    v_max = {a: robot.arm(a).velocity * params.vel_scale for a in ("left", "right")}

    def pose_of(step, key):
        return se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in step[key].items()})[0]

    def ball(arm, X):
        c = contact[arm]
        if c < 0:
            return robot.eef_position(arm, q[arm][None])[0]
        return _ball_centres(X[None], p_O[c], n_O[c], r)[0]

    def hold(X, k, kind="hold"):
        nonlocal t_now
        T = max(1, int(round(params.hold / dt)))
        t = t_now + dt * np.arange(T)
        rows.add(t=t, primitive=np.full(T, k), kind=np.full(T, kind), phase=np.full(T, "hold"),
                 X=np.broadcast_to(X, (T, 4, 4)), X_ref=np.broadcast_to(X, (T, 4, 4)),
                 X_start=np.broadcast_to(X, (T, 4, 4)), p_l=np.broadcast_to(ball("left", X), (T, 3)),
                 p_r=np.broadcast_to(ball("right", X), (T, 3)), f_l=np.zeros((T, 3)), f_r=np.zeros((T, 3)),
                 f_table=np.broadcast_to([0, 0, scene.object.mass * mp.g], (T, 3)),
                 q_l=np.broadcast_to(q["left"], (T, n)), q_r=np.broadcast_to(q["right"], (T, n)),
                 c_l=np.full(T, contact["left"] >= 0), c_r=np.full(T, contact["right"] >= 0))
        t_now = t[-1] + dt

    def move_arm(arm, path, X, k, new_contact):
        nonlocal t_now
        contact[arm] = -1
        t, qs = transit.time_parameterize(np.asarray(path), v_max[arm], params.acc, dt=dt)
        T = len(t)
        other = "right" if arm == "left" else "left"
        p_arm = robot.eef_position(arm, qs)
        p_other = np.broadcast_to(ball(other, X), (T, 3))
        q_other = np.broadcast_to(q[other], (T, n))
        rows.add(t=t_now + t, primitive=np.full(T, k), kind=np.full(T, "transit"), phase=np.full(T, arm),
                 X=np.broadcast_to(X, (T, 4, 4)), X_ref=np.broadcast_to(X, (T, 4, 4)),
                 X_start=np.broadcast_to(X, (T, 4, 4)), p_l=p_arm if arm == "left" else p_other,
                 p_r=p_arm if arm == "right" else p_other, f_l=np.zeros((T, 3)), f_r=np.zeros((T, 3)),
                 f_table=np.broadcast_to([0, 0, scene.object.mass * mp.g], (T, 3)),
                 q_l=qs if arm == "left" else q_other, q_r=qs if arm == "right" else q_other,
                 c_l=np.full(T, contact["left"] >= 0), c_r=np.full(T, contact["right"] >= 0))
        t_now += t[-1] + dt
        q[arm] = qs[-1]
        contact[arm] = new_contact

    for k, step in enumerate(plan["steps"]):  # a few dozen primitives
        prim = step["primitive"]
        X_from, X_to = pose_of(step, "X_WO_from"), pose_of(step, "X_WO_to")
        if prim == "regrasp":
            for arm in step.get("arms", []):
                move_arm(arm, step["transit"][arm], X_from, k, int(step["contacts"][arm]))
            if step.get("arms"):
                hold(X_from, k)
        elif prim == "pivot":
            vtx = int(step["vertex"])
            p0 = se3.transform_points(X_from, model.vertices[vtx])
            t, Xr, phase = mpc.pivot_reference(X_from, X_to, p0, scene.planner.tilt, dt, params.pivot_durations,
                                               p_com_O=model.com)
            cl, cr = int(step["contacts"]["left"]), int(step["contacts"]["right"])
            res = mpc.run_pivot_mpc(scene.object.mass, np.asarray(summ["inertia"]), model.com, p_O[[cl, cr]],
                                    -n_O[[cl, cr]], p0, t, Xr, mp)
            if res.status != "ok":
                stats.update(status="mpc_infeasible", failed_primitive=k)
                break
            X = res.X_WO
            targets = np.stack([_ball_centres(X, p_O[c], n_O[c], r) for c in (cl, cr)], axis=1)
            ql = _ik_path(robot, "left", targets[:, 0], q["left"], params.ik_every)
            qr = _ik_path(robot, "right", targets[:, 1], q["right"], params.ik_every)
            T = len(t)
            rows.add(t=t_now + t, primitive=np.full(T, k), kind=np.full(T, "pivot"), phase=phase, X=X, X_ref=Xr,
                     X_start=np.broadcast_to(X_from, (T, 4, 4)),
                     p_l=targets[:, 0], p_r=targets[:, 1], f_l=res.f_eef_W[:, 0], f_r=res.f_eef_W[:, 1],
                     f_table=res.f_table_W, q_l=ql, q_r=qr, c_l=np.ones(T, bool), c_r=np.ones(T, bool))
            t_now += t[-1] + dt
            q["left"], q["right"] = ql[-1], qr[-1]
            stats["mpc_max_error"] = max(stats["mpc_max_error"], float(np.max(res.tracking_error)))
            stats["mpc_iters"].append(float(np.median(res.n_iter[res.n_iter >= 0])))
            hold(X_to, k)
        elif prim == "tumble":
            pusher = step["pusher"]
            c = int(step["pusher_contact"])
            move_arm(pusher, step["transit"][pusher], X_from, k, c)
            e0, e1 = step["edge"]
            collide = collide or make_scene_collision_fn(scene, robot, tables["mesh"])
            found, _, q_push = pusher_motion(robot, collide, model, X_from, X_to, e0, e1, p_O, n_O, r,
                                             GraphParams(), arms=(pusher,))
            if found is None:
                raise InputError(f"plan step {k}: the tumble's pusher no longer works; replan")
            pe = se3.transform_points(X_from, model.vertices[[e0, e1]])
            axis = (pe[1] - pe[0]) / np.linalg.norm(pe[1] - pe[0])
            ang = float(np.arccos(np.clip((np.trace(X_to[:3, :3] @ X_from[:3, :3].T) - 1) / 2, -1, 1)))
            if np.dot(se3.quat_from_matrix(X_to[:3, :3] @ X_from[:3, :3].T)[:3], axis) < 0:
                axis = -axis
            t, Xr, phase = mpc.tumble_reference(X_from, pe[0], axis, ang, dt, params.tumble_duration)
            push_end = np.flatnonzero(np.array([se3.tilt_of(Xr[i][:3, :3] @ X_from[:3, :3].T)
                                                for i in range(len(Xr))]) <= GraphParams().push_angle)[-1]
            target = _ball_centres(Xr[: push_end + 1], p_O[c], n_O[c], r)
            qp = _ik_path(robot, pusher, target, q[pusher], params.ik_every)
            T = len(t)
            f = np.zeros((T, 3))
            res = mpc.run_tumble_mpc(scene.object.mass, np.asarray(summ["inertia"]), model.com,
                                     p_O[[c, c]], -n_O[[c, c]], pe, t[: push_end + 1], Xr[: push_end + 1], mp,
                                     contact_mask=(True, False))
            if res.status == "ok":
                f[: push_end + 1] = res.f_eef_W[:, 0]
            q_arm = np.concatenate([qp, np.broadcast_to(qp[-1], (T - len(qp), n))])
            p_arm = np.concatenate([target, np.broadcast_to(target[-1], (T - len(target), 3))])
            other = "right" if pusher == "left" else "left"
            in_contact = np.arange(T) <= push_end
            rows.add(t=t_now + t, primitive=np.full(T, k), kind=np.full(T, "tumble"), phase=phase, X=Xr, X_ref=Xr,
                     X_start=np.broadcast_to(X_from, (T, 4, 4)),
                     p_l=p_arm if pusher == "left" else np.broadcast_to(ball(other, X_from), (T, 3)),
                     p_r=p_arm if pusher == "right" else np.broadcast_to(ball(other, X_from), (T, 3)),
                     f_l=f if pusher == "left" else np.zeros((T, 3)), f_r=f if pusher == "right" else np.zeros((T, 3)),
                     f_table=np.broadcast_to([0, 0, scene.object.mass * mp.g], (T, 3)),
                     q_l=q_arm if pusher == "left" else np.broadcast_to(q[other], (T, n)),
                     q_r=q_arm if pusher == "right" else np.broadcast_to(q[other], (T, n)),
                     c_l=in_contact if pusher == "left" else np.zeros(T, bool),
                     c_r=in_contact if pusher == "right" else np.zeros(T, bool))
            t_now += t[-1] + dt
            q[pusher] = q_arm[-1]
            contact[pusher] = -1
            for arm in ("left", "right"):  # into USP: the catcher, then the pusher, take the new grasp
                key = f"{arm}_after"
                if key in step["transit"]:
                    move_arm(arm, step["transit"][key], X_to, k, int(step.get("contacts", {}).get(arm, -1)))
            hold(X_to, k)
        stats["primitives"] += 1
    cols = {}
    if rows.cols["t"]:
        cat = {k: np.concatenate(v) for k, v in rows.cols.items()}
        cols = _columns(cat)
    stats["mpc_iters"] = float(np.median(stats["mpc_iters"])) if stats["mpc_iters"] else 0.0
    stats["steps"] = int(len(cols.get("step", [])))
    stats["duration"] = float(cols["t"][-1]) if cols else 0.0
    return cols, stats


def _columns(c: dict) -> dict:
    X = c["X"]
    out = {"step": np.arange(len(c["t"])), "t": c["t"], "primitive": c["primitive"].astype(np.int64),
           "kind": c["kind"].astype(str), "phase": c["phase"].astype(str), **se3.columns_from_matrix(X)}
    for name, key in (("l", "p_l"), ("r", "p_r")):
        for i, ax in enumerate("xyz"):
            out[f"{name}{ax}"] = c[key][:, i]
    for name, key in (("fl", "f_l"), ("fr", "f_r"), ("f0", "f_table")):
        for i, ax in enumerate("xyz"):
            out[f"{name}{ax}"] = c[key][:, i]
    # Tilt and yaw of the object relative to the primitive's start pose, and of the reference (Fig. 12).
    for name, key in (("", "X"), ("_ref", "X_ref")):
        R_rel = np.einsum("tij,tkj->tik", c[key][:, :3, :3], c["X_start"][:, :3, :3])
        out[f"tilt{name}"] = se3.tilt_of(R_rel)
        out[f"yaw{name}"] = se3.yaw_of(R_rel)
    out["q_left"] = list(c["q_l"])
    out["q_right"] = list(c["q_r"])
    out["left_contact"] = c["c_l"].astype(bool)
    out["right_contact"] = c["c_r"].astype(bool)
    return out


FIELDS = [
    Field("step", "id"), Field("t", "s"), Field("primitive", "id"), Field("kind"), Field("phase"),
    *[Field(k, "m", "W") for k in ("x", "y", "z")], *[Field(k, "1", "W") for k in ("qx", "qy", "qz", "qw")],
    *[Field(f"{b}{ax}", "m", "W") for b in ("l", "r") for ax in "xyz"],
    *[Field(f"{b}{ax}", "N", "W") for b in ("fl", "fr", "f0") for ax in "xyz"],
    Field("tilt", "rad"), Field("yaw", "rad"), Field("tilt_ref", "rad"), Field("yaw_ref", "rad"),
    Field("q_left", "rad"), Field("q_right", "rad"), Field("left_contact"), Field("right_contact"),
]


def run(scene_path, analysis_dir, plan_path, out_path, params: Params, producer: str = "mpc") -> dict:
    """Read ``plan.json``, write ``trajectories.parquet`` (and ``trajectories.json`` with the summary)."""
    t0 = time.perf_counter()
    scene = load_scene(scene_path)
    plan = artifacts.read_json(plan_path, "plan")
    if plan["status"] == "infeasible":
        raise InputError(f"{plan_path}: the plan is infeasible ({plan.get('reason')}); nothing to execute")
    cols, stats = compute(scene, analysis_dir, plan, params)
    meta_params = {**asdict(params), "N_p": params.mpc.horizon, "dt": params.mpc.dt, "alpha": params.mpc.alpha,
                   "beta": params.mpc.beta}
    inputs = {"scene": scene_path, "plan": plan_path}
    out = Path(out_path)
    if stats["status"] == "ok":
        artifacts.write_table(out, cols, FIELDS, artifacts.make_meta("trajectories", meta_params, inputs, producer))
    artifacts.write_json(out.with_suffix(".json"), stats, artifacts.make_meta("mpc", meta_params, inputs, producer))
    artifacts.write_timings(out.with_suffix(".json"), {"mpc": time.perf_counter() - t0})
    return stats
