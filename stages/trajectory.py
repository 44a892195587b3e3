"""Stage ``mpc``: a plan's primitives as dense force and joint trajectories (§5.2, eq. 5–11, Fig. 12, 14).

Reads ``plan.json`` and writes ``trajectories.parquet``: one row per time step (``Params.mpc.dt``),
in plan order, with the object's planned pose, both ball centres, both ball forces on the object,
the table reaction, all joint angles and the contact flags. Per primitive:

- **transit** (the arms of a regrasp, the pusher before a tumble): the plan's joint waypoints,
  time-parameterized under the joint velocity limits (``stages.transit.time_parameterize``); the
  moving ball is off the object, the other keeps its contact when it had one;
- **pivot**: the tilt → rotate → lower reference about the support vertex, tracked by the MPC
  (``stages.mpc.run_pivot_mpc``); the object pose is the MPC's simulated pose, the ball centres
  follow it (``p_i(t) = X_WO(t) p_Oi`` moved out by the ball radius) and the joints are those of the
  planner's own IK check of the pivot (:func:`pivot_joints`), so that they end where the plan's next
  transit starts. The MPC minimises the ball forces and so leans on the table's friction up to its
  bound; it first runs with a smaller table friction (``Params.table_friction_tries``), each ball
  pressing at least ``Params.pivot_squeeze``, then with the plan's least force, and keeps the first
  feasible run whose ball forces stay within the plan's ``mpc_max_force`` share of the bound (the
  plan checked no more; the controller commands no more), which leaves physics with 20 % less
  friction than the scene a margin;
- **tumble** (:func:`plan_tumble`): a front/back squeeze about the support edge, as measured in
  PyBullet (notes/pybullet-pivoting.md, "Tumbling"); see below;
- **squeeze tumble** (a tumble step of ``mode`` ``squeeze``, :func:`plan_squeeze`): both balls stay
  on the grasp's contacts and roll the object over the edge onto its next face
  (``stages.squeeze.squeeze_motion``), the forces from the tumbling MPC with both balls on
  throughout (``stages.squeeze.mpc_params``, as ``pivot plan`` checked it), the joints as for a
  pivot (:func:`pivot_joints`, the plan's own check);
- **hold**: a short pause before and after each contact change.

Around every contact of a pivot or a regrasp the balls are then turned about their centres where
their tools (stick, flange) come closer to the object than ``Params.stick_clearance``
(:func:`refine_stick_clearance`): the plan places the ball centres only, and a tool at 0.1 mm from
the object touches it in physics.

Tumble
------
The plan names the pusher, its contact and the hull edge. The object *rolls* over that edge onto the
next stable face (:func:`roll_segments`): a legged body turns about its foot line until its body edge
touches the table, then about that edge, so the reference (``stages.mpc.roll_poses``) is piecewise,
with the motion at rest at every switch. The other arm is the **catcher**: its ball sits on the face
that lands (the "back" the object falls onto), high up, and both balls follow the rotation:

1. the pusher takes its contact (the plan's transit), the catcher its own (a transit planned here,
   ``stages.transit.plan_transit``; into SP from its rest posture when the plan first moves it there,
   ``{catcher}_before``, out of the object's way); both contacts switch on together (a squeeze from
   both sides);
2. *push*: both rotate the object to the release angle (``stages.graph.release_angle``: its
   ``push_angle``, at least ``release_past_tip`` past the angle where the CoM crosses the axis, where
   the graph's pusher check ends);
3. *release*: the object pauses while the pusher's force ramps out and the catcher takes the load;
4. *catch*: the catcher alone lowers the object;
5. the catcher lets go, in one of three ways:

   - *place*: its ball ends beyond the table's edge, so it lowers the object all the way onto the
     new face, lets go and backs off along the contact normal;
   - *slide*: its ball would end under the object, so it lowers it to ``slide_short`` before the
     landing and slides out past the far edge of the face in ``slide_time`` (notes: 84° of 90°,
     0.1–0.2 s; a slow slide drags the object); the object then drops the rest of the way, planned
     as a free fall about the current axis (``stages.mpc.integrate_rotation`` with no force);
   - *hold* (into USP, Fig. 14): the catcher's contact is the plan's catch node's (its
     ``{catcher}_before`` transit ends there); it lowers the object into the USP pose and keeps
     holding it alone; the plan's next step (a regrasp) hands the object over to a grasp.

Into SP, when no catcher works (none within reach, as where the object tips away from the robot, or
none whose joints or MPC pass), the tumble is a **drop** (:func:`_plan_drop`; §5.2.2: "one EEF rotates
the object around one edge ... until it moves to SP"): the other arm backs off its contact, the pusher
alone turns the object to its tip (``stages.graph.tip_angle``) and reaches it at a known rate with no
acceleration (:func:`drop_profile`; the tumbling MPC with the pusher only and no least force, which
fades to nothing there), and the object falls on from that rate as gravity alone turns it
(:func:`_free_fall`), a fall physics follows to a few degrees, where one from rest past the tip runs
ahead of any plan. A drop is planned only where that fall is the whole story: about one edge onto
its face (a fall that lands on a facet and rolls on over its edge rocks on the crease, which no row
models), with its edge held by the table's friction, slipping at most ``drop_slip`` before it lands
and never lifting off (:func:`fall_slip`, a planar rigid body under Coulomb friction).

The catching contact in SP is chosen here, deterministically: contacts on the landing face (outward
normal within ``catch_cone`` of the landing direction) whose ball the catcher reaches at the start and
at the release, largest lever arm about the axis first (less the offset from the CoM along the axis),
the first whose joint path (IK along the whole motion, seeded step to step), rolling and collisions
(the batched checker of ``stages.robot``, at every other row) pass and with which the tumbling MPC is
feasible. Rolling: a ball whose orientation is that of position-only IK rolls on the turning
object (``stages.execute`` shifts its target by :func:`rolling_shift`), 2-4 cm over a 90° tumble; its
contact must stay ``roll_margin`` inside its face, else the joints are solved by :func:`ik_follow`,
which turns the ball with the object about the turning axis (the pusher's always are). Into USP the
catcher's joints are solved backwards from the plan's final configuration, so the following USP
regrasp starts exactly where the plan expects; its contact must be able to hold the object through
the fall, which a contact on a face other than the landing one is not (the MPC is then infeasible
after the release): ``stages.graph`` offers catch nodes on the landing face only, with the ball
under the overhang beyond the table's edge, and ``pivot plan`` runs the same MPC
(:func:`tumble_mpc`) on every tumble into USP and refuses a catch it fails, so a plan it accepts
does not fail here for it. The forces come from the tumbling MPC
(``stages.mpc.run_tumble_mpc``), one run per segment of the roll, with the pusher switched off at
its release. After the tumble each arm goes (a planned transit) to the configuration the plan
assumes at the end of the step: the pusher to the end of its push, the catcher back where it was
(SP) or on its grasp contact (USP).

An MPC failure on an existing plan is reported (status ``mpc_infeasible`` with the primitive) and
the stage exits 1: ``pivot plan`` runs the same MPC while it searches, so a plan it accepted passes
unless the MPC parameters were changed here. A tumble that finds no catcher, no IK or no transit is
reported the same way with its reason code (``no_catcher``, ``ik_unreachable``, ``no_transit_path``,
...); into SP that code is the catch's, after the drop failed too (both reasons in the message).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from stages import artifacts, mpc, poses, provenance, se3, squeeze, stability, stagelog, transit
from stages.artifacts import Field
from stages.errors import InputError, about
from stages.graph import Params as GraphParams
from stages.graph import push_limits, pusher_motion, recorded_params, release_angle, spread, tip_angle
from stages.objectmodel import load_object_model
from stages.poses import Roll, roll_segments
from stages.robot import follow_ik, ik_pose, load_robot
from stages.rolling import rolling_shift
from stages.sample import clearance_of, make_scene_collision_fn
from stages.scene import load_scene

ARMS = ("left", "right")


@dataclass(frozen=True)
class TumbleParams:
    """How a tumble is carried out (s, rad, m); see the module docstring and the notes' "Tumbling"."""

    #: Both contacts ramp in at the start pose for this long before the push.
    grip_time: float = 0.6
    #: From the start to the release angle, both balls on the object.
    push_time: float = 3.5
    #: Pause at the release angle; the pusher's contact ends halfway (its force ramps out before).
    release_dwell: float = 1.2
    #: From the release angle to the end of the catch, the catcher alone.
    catch_time: float = 4.0
    #: A catcher that would end under the object stops this far short of the landing, then slides out.
    slide_short: float = np.radians(6.0)
    slide_time: float = 0.15
    #: Ball clearance beyond the face's far edge after sliding out, and above the table while catching (m).
    slide_clearance: float = 0.01
    table_clearance: float = 0.003
    #: A catcher placing the object must end at least this far beyond the table's edge (m).
    edge_clearance: float = 0.005
    #: Catching contacts: outward normal within this angle of the landing direction; candidates tried:
    #: the best ``catch_candidates``, then as many more spread over the rest of the ranking.
    catch_cone: float = np.radians(30.0)
    catch_candidates: int = 8
    #: Where the catcher's ball has rolled to at the end of the catch must lie this far inside its face (m).
    roll_margin: float = 0.005
    #: A drop whose edge would slide further than this as the object falls from the tip is refused (m).
    drop_slip: float = 0.005
    #: The object rests this long after landing before the arms leave (s).
    settle: float = 1.0
    #: A placing catcher backs off this far along its contact normal (m), in ``retreat_time`` s.
    retreat: float = 0.03
    retreat_time: float = 0.6
    #: Collisions are checked on every this many rows of the tumble.
    check_every: int = 2


@dataclass(frozen=True)
class Params:
    """Trajectory generation: MPC settings and primitive timing (s)."""

    #: MPC settings; dt = 1/24 s puts every row on the physics clock (10 steps of 1/240 s, stages.execute).
    mpc: mpc.Params = field(default_factory=lambda: mpc.Params(dt=1.0 / 24.0))
    #: The MPC plans with this fraction of the scene's friction coefficients, so that the forces it
    #: plans leave room for what the compliant arms add in execution (the squeeze).
    friction_safety: float = 0.8
    #: A pivot's MPC first tries these smaller fractions of the table's friction (in order; the
    #: balls' stays ``friction_safety``) and keeps the first feasible one: the MPC minimises the
    #: ball forces, so it leans on the table's friction up to its bound, and physics whose friction
    #: is 20 % lower than the scene's (``pivot execute --randomize``) then has no margin left.
    table_friction_tries: tuple[float, ...] = (0.6, 0.7)
    #: ... each first with both balls pressing at least this hard (N, normal): the MPC minimises the
    #: ball forces, and where a pivot needs little (the duck's, 11-14 N at the peak) a ball pressing
    #: 2 N slips on the object and the object slides on its vertex (12-52 mm, 3-13 deg in physics).
    pivot_squeeze: float = 10.0
    pivot_durations: tuple[float, float, float] = (2.5, 3.0, 2.5)
    tumble: TumbleParams = field(default_factory=TumbleParams)
    hold: float = 0.5
    #: A ball holding the object alone in USP (:func:`hold_force`) pushes with this multiple of the
    #: least force that holds it with the SP margin, found first with ``hold_eef_friction`` of the
    #: ball's friction (as ``stages.sample`` checks ``hold_*``): with the least force the piano tipped
    #: in physics whenever its CoM lay a few mm further out than planned (``--randomize``: up to 1 cm).
    hold_force_factor: float = 3.0
    hold_eef_friction: float = 0.3
    #: IK on every this many rows of a pivot, a push or a catch (joints interpolated in between).
    ik_every: int = 4
    #: Fraction of the joint velocity limits used by transits.
    vel_scale: float = 0.5
    acc: float = 2.0
    #: Transits planned here (a tumble's catcher, and the arms' way back to the plan's configurations).
    transit: transit.Params = field(default_factory=transit.Params)
    #: The tool (stick and flange) keeps this clearance (m) from the object around each contact of a
    #: pivot or regrasp (:func:`refine_stick_clearance`; 0: the plan's postures as they are).
    stick_clearance: float = 0.006
    #: ... by turning the ball about its centre by at most this much (rad), ramped in and out over
    #: ``stick_ramp`` s around the rows that need it.
    stick_max_turn: float = np.radians(20.0)
    stick_ramp: float = 0.6


COLUMNS = ("t", "primitive", "kind", "phase", "X", "X_ref", "X_start", "p_l", "p_r", "f_l", "f_r", "f_table",
           "q_l", "q_r", "c_l", "c_r")


class TumbleError(Exception):
    """A tumble that cannot be carried out: ``code`` is a reason code (DESIGN.md), ``args[0]`` says why."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def _ik_path(robot, arm: str, targets: np.ndarray, q0: np.ndarray, every: int, check: bool = False):
    """Joint path ``(T, n)`` through ball targets ``(T, 3)``: IK (seeded step to step, one branch) on
    every ``every``-th target and the last, joints interpolated linearly in between (the motions are
    slow: the ball then strays well under a millimetre from its target between IK samples).

    With ``check`` also returns the first IK failure's reason ("ok" when none)."""
    T = len(targets)
    keys = np.unique(np.r_[np.arange(0, T, max(every, 1)), T - 1])
    res = robot.ik_trajectory(arm, targets[keys], q0)
    t = np.arange(T)
    q = np.stack([np.interp(t, keys, res.q[:, j]) for j in range(res.q.shape[1])], axis=1)
    if not check:
        return q
    return q, ("ok" if res.ok.all() else str(res.reason[np.argmin(res.ok)]))


def pivot_joints(robot, X_ref: np.ndarray, p_O: np.ndarray, n_O: np.ndarray, q0: np.ndarray, r: float,
                 dt: float, gp: GraphParams, sample_time: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Joint paths ``(T, n)`` of the left and right arm along a pivot's reference poses ``X_ref (T, 4, 4)``.

    The same IK as ``pivot plan``'s check of the pivot (``stages.plan``: ``stages.graph.check_arm_motion``
    on every ``sample_time`` s of the reference and the last row, ``Robot.ik_trajectory(batch=True)``
    from ``q0 (2, n)``), joints interpolated linearly in between. The plan's next transit of an arm
    starts from the configuration that check ended in; any other IK (step-by-step seeding, other
    samples) ends elsewhere on the arm's self-motion and the transit would begin with a jump of the
    planned joints (0.7 rad of the SDA5F's joint 5 on Exp. 1, which the arm cannot follow). The ball
    centres of the dense rows (the MPC's poses, within a millimetre of the reference) are the
    impedance's targets in execution; these joints are its posture. ``p_O, n_O (2, 3)``: contacts and
    outward normals (O) of the left and right ball; ``r`` the ball radius (m); ``gp`` the graph's
    parameters (its IK tolerance and largest joint step).
    """
    T = len(X_ref)
    every = max(1, int(round(sample_time / dt)))
    sub = np.unique(np.r_[np.arange(0, T, every), T - 1])
    X = X_ref[sub][None]  # (1, K, 4, 4), laid out as the planner's batch of one motion
    out = []
    for k, arm in enumerate(ARMS):
        ball_O = (p_O[k] + r * n_O[k])[None]
        targets = np.einsum("etij,ej->tei", X[..., :3, :3], ball_O) + np.swapaxes(X[..., :3, 3], 0, 1)
        res = robot.ik_trajectory(arm, targets, np.asarray(q0[k], dtype=float)[None], tol=gp.ik_tol,
                                  max_joint_step=gp.max_joint_step, batch=True)
        q = res.q[:, 0]
        out.append(np.stack([np.interp(np.arange(T), sub, q[:, j]) for j in range(q.shape[1])], axis=1))
    return out[0], out[1]


def ik_follow(robot, arm: str, targets: np.ndarray, X_WO: np.ndarray, n_O: np.ndarray, q0: np.ndarray,
              every: int, iters: int = 12, tol: float = 1e-3, both: bool = False) -> tuple[np.ndarray, str]:
    """Joint path ``(T, n)`` that puts the ball on ``targets (T, 3)`` (W) *and turns it with the object*
    at poses ``X_WO (T, 4, 4)`` (:func:`stages.robot.follow_ik`, ``n_O`` the contact's outward normal in
    O), solved on every ``every``-th row and the last from ``q0``, joints interpolated between (the
    motions are slow). Returns the path and "ok", or the first failure (``ik_unreachable``,
    ``joint_jump``)."""
    T = len(targets)
    keys = np.unique(np.r_[np.arange(0, T, max(every, 1)), T - 1])
    res = follow_ik(robot, arm, targets[keys][:, None], X_WO[None], keys, np.asarray(n_O, dtype=float)[None],
                    np.asarray(q0, dtype=float)[None], iters=iters, tol=tol, both=both)
    q = res.q[:, 0]
    why = "ok" if res.ok.all() else str(res.reason[np.argmin(res.ok[:, 0]), 0])
    t = np.arange(T)
    return np.stack([np.interp(t, keys, q[:, j]) for j in range(q.shape[1])], axis=1), why

def tool_capsules(robot, arm: str) -> np.ndarray:
    """Indices of ``arm``'s collision capsules rigid with its ball, the ball excepted (the stick and the
    flange): they turn about the ball's centre when the ball does."""
    a = robot.arm(arm)
    group = np.cumsum(a.joint >= 0) - 1  # rigid group of each frame
    link = np.asarray(a.cap_link)
    return np.flatnonzero((group[link] == group[a.eef_index]) & (link != a.eef_index))


def tool_clearance(robot, arm: str, q: np.ndarray, X_WO: np.ndarray, mesh, samples: int = 11,
                   exact_within: float = np.inf):
    """Clearance of the tool capsules (:func:`tool_capsules`) from the object, per row.

    ``q (T, n)``, ``X_WO (T, 4, 4)``; ``mesh`` the object (O). Points every ``1 / (samples - 1)`` of
    each capsule's segment against the mesh (``trimesh.proximity.closest_point``) less its radius;
    a point farther than ``exact_within`` (m) from the mesh's convex hull gets its distance to the
    hull (a lower bound, so a row's clearance is exact whenever it is below ``exact_within``).
    Returns ``clearance (T,)`` (m), ``p (T, 3)`` the nearest tool point and ``g (T, 3)`` the unit
    direction from the object to it (W).
    """
    a = robot.arm(arm)
    caps = tool_capsules(robot, arm)
    F = robot.fk(arm, q)  # (T, L, 4, 4)
    s = np.linspace(0.0, 1.0, samples)
    P, rad = [], []
    for c in caps:
        seg = a.cap_a[c][None] + s[:, None] * (a.cap_b[c] - a.cap_a[c])[None]  # (S, 3) link frame
        P.append(se3.transform_points(F[:, a.cap_link[c], None], seg[None]))  # (T, S, 3)
        rad.append(np.full(samples, a.cap_r[c]))
    P, rad = np.concatenate(P, axis=1), np.concatenate(rad)  # (T, K, 3), (K,)
    T, K = P.shape[:2]
    P_O = se3.transform_points(se3.invert(X_WO)[:, None], P).reshape(-1, 3)
    # The distance to the convex hull's farthest face plane is a lower bound of the distance to the
    # mesh; the exact closest point (slow) is only needed where that bound is within ``exact_within``.
    hull = mesh.convex_hull
    bound = np.max(P_O @ hull.face_normals.T - np.einsum("ij,ij->i", hull.face_normals,
                                                          hull.vertices[hull.faces[:, 0]]), axis=1)
    dist, c_O = np.maximum(bound, 0.0), np.zeros_like(P_O)
    near = np.flatnonzero(bound - np.tile(rad, T) < exact_within)
    if len(near):
        c_O[near], dist[near], _ = trimesh.proximity.closest_point(mesh, P_O[near])
    P_O = P_O.reshape(T, K, 3)
    d = dist.reshape(T, K) - rad
    k = np.argmin(d, axis=1)
    rows = np.arange(T)
    g_O = P_O[rows, k] - c_O.reshape(T, K, 3)[rows, k]
    g = se3.rotate_vectors(X_WO, g_O / np.maximum(np.linalg.norm(g_O, axis=1, keepdims=True), 1e-12))
    return d[rows, k], P[rows, k], g


def refine_stick_clearance(env, rows: dict, params: Params) -> list[dict]:
    """Turn each ball about its centre, around its contacts, until its tool clears the object by
    ``params.stick_clearance``; modifies ``rows["q_l"]``, ``rows["q_r"]`` in place.

    The plan's IK places the ball centre only; the stick's direction is whatever the arm's posture
    gives, and on Exp. 1 a grasp leaned the right stick 33 deg into its contact face: 0.1-2.6 mm from
    the piano, which it touched in physics as soon as the object stood a millimetre off its planned
    pose. A ball is a sphere, so its orientation is free: for each stretch of rows an arm is in
    contact (with ``stick_ramp`` s of its approach and retreat; stretches that include a tumble are
    left to :func:`plan_tumble`), the rows whose tool clearance (:func:`tool_clearance`) is below the
    target get a turn about the ball centre, about the axis that moves the tool's nearest point away
    from the object, by the deficit over that point's lever (at most ``stick_max_turn``), spread over
    the neighbouring rows with a minimum-jerk ramp so that it is zero where the stretch begins and
    ends; the joints are solved again (:func:`stages.robot.ik_pose`, the ball centre exactly where planned). The
    new joints are kept only when the ball stays within 1 mm of its planned centre, the joints stay
    below their speed limits and the scene's collision checker passes every row; the refinement is
    reported per stretch (arm, rows, clearance before and after, kept or why not).
    """
    robot, dt = env.robot, env.mp.dt
    X, kind = rows["X"], rows["kind"]
    T = len(X)
    ramp = max(int(round(params.stick_ramp / dt)), 1)
    exact = params.stick_clearance + 0.004  # which rows turn, and by how much, only needs this much exact
    out = []
    for arm, qk, ck in (("left", "q_l", "c_l"), ("right", "q_r", "c_r")):
        contact = np.asarray(rows[ck], dtype=bool)
        d = np.diff(np.r_[0, contact.astype(int), 0])
        for s0, e0 in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
            s, e = max(s0 - ramp, 0), min(e0 + ramp, T)
            if np.any(kind[s:e] == "tumble"):
                continue
            q = rows[qk][s:e]
            clear, p_tool, g = tool_clearance(robot, arm, q, X[s:e], env.mesh, exact_within=exact)
            need = clear < params.stick_clearance
            rec = {"arm": arm, "rows": [int(s), int(e)], "clearance": float(clear.min())}
            if not need.any():
                continue
            q_new, err = _turned_joints(robot, arm, q, p_tool, g, clear, need, ramp, params)
            clear_new = tool_clearance(robot, arm, q_new, X[s:e], env.mesh, exact_within=exact)[0]
            rec["clearance_after"] = float(clear_new.min())
            rec["kept"] = why = _stretch_verdict(env, rows, arm, (s, e), q, q_new, err, clear, clear_new)
            if why == "ok":
                rows[qk][s:e] = q_new
            out.append(rec)
    return out


def _turned_joints(robot, arm: str, q: np.ndarray, p_tool: np.ndarray, g: np.ndarray, clear: np.ndarray,
                   need: np.ndarray, ramp: int, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """:func:`refine_stick_clearance`'s turn of one contact stretch: each row of ``need`` turns its
    ball about the centre, about the axis that moves the tool's nearest point ``p_tool`` away along
    the clearance gradient ``g`` (W), by the deficit over that point's lever (at most
    ``stick_max_turn``), spread over ``ramp`` rows each side with a minimum-jerk kernel and faded to
    zero at the stretch's ends; the joints solved again (:func:`stages.robot.ik_pose`, the centre kept).
    Returns ``(q_new (T, n), IK error (T,) m)``; rows that do not turn keep ``q``."""
    F = robot.fk(arm, q)
    i_eef = robot.arm(arm).eef_index
    c_ball, R_ball = F[:, i_eef, :3, 3], F[:, i_eef, :3, :3]
    lever = p_tool - c_ball
    axis = np.cross(lever, g)
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    turn = np.where(need, (params.stick_clearance - clear) / np.maximum(np.linalg.norm(lever, axis=1), 0.01),
                    0.0)
    turn = np.minimum(turn, params.stick_max_turn)
    # Spread each row's turn over its neighbours (minimum-jerk kernel), zero at the stretch's ends.
    k = np.arange(-ramp, ramp + 1)
    kernel = 1.0 - _min_jerk_kernel(np.abs(k) / ramp)
    spread = np.zeros(len(q))
    rv = np.zeros((len(q), 3))
    for i in np.flatnonzero(need):
        lo, hi = max(i - ramp, 0), min(i + ramp + 1, len(q))
        w = turn[i] * kernel[lo - i + ramp: hi - i + ramp]
        better = w > spread[lo:hi]
        spread[lo:hi] = np.where(better, w, spread[lo:hi])
        rv[lo:hi][better] = axis[i]
    edge = np.minimum(np.arange(len(q)), np.arange(len(q))[::-1]) / ramp
    spread *= _min_jerk_kernel(np.minimum(edge, 1.0))
    R_t = Rotation.from_rotvec(rv * spread[:, None]).as_matrix() @ R_ball
    q_new, err = ik_pose(robot, arm, c_ball, R_t, q)
    q_new[spread == 0.0] = q[spread == 0.0]
    return q_new, err


def _stretch_verdict(env, rows: dict, arm: str, span: tuple[int, int], q: np.ndarray, q_new: np.ndarray,
                     err: np.ndarray, clear: np.ndarray, clear_new: np.ndarray) -> str:
    """Whether :func:`refine_stick_clearance` keeps the turned joints ``q_new`` of rows ``span`` of
    ``arm``: ``"ok"``, or ``ik_unreachable`` (the ball more than 1 mm off its centre), ``joint_jump``
    (the stretch's ends moved, or a joint over its speed limit), ``no_better`` (no clearance gained)
    or the scene checker's collision (the ball's own contact exempt)."""
    s, e = span
    a, dt = env.robot.arm(arm), env.mp.dt
    qk = "q_l" if arm == "left" else "q_r"
    why = "ok"
    ends = np.abs(np.concatenate([q_new[:1] - q[:1], q_new[-1:] - q[-1:]])).max()
    speed = np.abs(np.diff(np.concatenate([rows[qk][s - 1:s], q_new, rows[qk][e:e + 1]]), axis=0)) / dt
    if err.max() > 1e-3:
        why = "ik_unreachable"
    elif ends > 1e-9 or (speed / a.velocity).max() > 1.0:
        why = "joint_jump"
    elif clear_new.min() <= clear.min():
        why = "no_better"
    else:
        other = rows["q_r" if arm == "left" else "q_l"][s:e]
        ql, qr = (q_new, other) if arm == "left" else (other, q_new)
        # The ball's centre is the plan's (approach and retreat included): only the rest is checked.
        touching = np.stack([rows["c_l"][s:e], rows["c_r"][s:e]], axis=1).astype(bool)
        touching[:, ARMS.index(arm)] = True
        ok, reason = env.collide(ql, qr, rows["X"][s:e], touching)
        if not ok.all():
            why = str(reason[np.argmin(ok)])
    return why


def _min_jerk_kernel(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _ball_centres(X, p_O, n_O, r):
    """Ball centres ``(T, 3)`` (W) touching at ``p_O`` with outward normal ``n_O`` (O)."""
    return se3.transform_points(X, p_O + r * n_O)


def _other(arm: str) -> str:
    return "right" if arm == "left" else "left"


#: Time (s) over which a holding ball's force is eased in and out around the other ball's transit.
HOLD_RAMP = 0.3


def hold_force(env: _Env, X: np.ndarray, contact: int) -> np.ndarray | None:
    """The force ``(3,)`` (N, W) with which one ball on ``contact`` holds the object at ``X`` still on
    its table contact: ``Params.hold_force_factor`` times the least one (``poses.table_support``;
    ``stability.least_eef_forces`` with ``hold_eef_friction`` of the ball's friction and the MPC's
    of the table's, else the MPC's reduced friction, else the scene's), at most the force bound; None
    when it cannot.

    It holds the object with the SP margin (``poses.held_com``): a USP pose may have its CoM just
    inside the table contact, where the least force would be nil and physics tips it.
    """
    model, scene = env.model, env.scene
    g = int(np.argmax(model.normals @ (X[:3, :3].T @ np.array([0.0, 0.0, -1.0]))))  # the face it stands on
    poly = poses.table_support(model, X, g, np.asarray(scene.table.size) / 2)
    com = poses.held_com(poly, se3.transform_points(X, model.com), env.sp_margin)
    pts = np.c_[poly, np.zeros(len(poly))]
    p = se3.transform_points(X, env.p_O[contact])[None]
    n = -se3.rotate_vectors(X, env.n_O[contact])[None]
    prm = env.params
    for mu_e, mu_t in ((prm.hold_eef_friction * scene.object.friction, env.mp.mu_table),
                       (env.mp.mu_eef, env.mp.mu_table), (scene.object.friction, scene.table.friction)):
        out = stability.least_eef_forces(scene.object.mass, com, pts, p, n,
                                         stability.Params(mu_eef=mu_e, mu_table=mu_t, f_max=env.mp.f_max))
        if out is not None:
            f = out[0][0] * prm.hold_force_factor
            return f * min(1.0, env.mp.f_max / max(float(np.linalg.norm(f)), 1e-12))
    return None


# ----------------------------------------------------------------------------------------------------
# Rows


class _Timeline:
    """Trajectory rows, primitive by primitive, and where each arm is (joints, contact id or -1)."""

    def __init__(self, robot, r: float, p_O: np.ndarray, n_O: np.ndarray, dt: float, weight: float,
                 v_max: dict, acc: float):
        self.robot, self.r, self.p_O, self.n_O, self.dt = robot, r, p_O, n_O, dt
        self.weight, self.v_max, self.acc = weight, v_max, acc
        self.n = robot.arm("left").dof
        self.cols: dict = {k: [] for k in COLUMNS}
        self.t = 0.0
        self.q = {a: np.zeros(self.n) for a in ARMS}
        self.contact = {a: -1 for a in ARMS}

    def ball(self, arm: str, X: np.ndarray) -> np.ndarray:
        """Ball centre ``(3,)`` (W): on its contact of the object at ``X``, else where its joints put it."""
        c = self.contact[arm]
        if c < 0:
            return self.robot.eef_position(arm, self.q[arm][None])[0]
        return _ball_centres(X[None], self.p_O[c], self.n_O[c], self.r)[0]

    def add(self, k: int, kind: str, phase, X, X_ref=None, p=None, f=None, q=None, c=None, f_table=None,
            X_start=None) -> None:
        """Rows ``dt`` apart from the current time: object poses ``X (T, 4, 4)``; per arm (dicts keyed by
        arm) ball centres ``p (T, 3)``, forces ``f (T, 3)``, joints ``q (T, n)`` and contact flags
        ``c (T,)``; an arm left out stays still on its contact (or where it is), with no force."""
        T = len(X)
        p, f, q, c = p or {}, f or {}, q or {}, c or {}
        X_start = X[0] if X_start is None else X_start
        out = {"t": self.t + self.dt * np.arange(T), "primitive": np.full(T, k), "kind": np.full(T, kind),
               "phase": np.broadcast_to(np.asarray(phase), (T,)), "X": X, "X_ref": X if X_ref is None else X_ref,
               "X_start": np.broadcast_to(X_start, (T, 4, 4)),
               "f_table": (np.broadcast_to([0.0, 0.0, self.weight], (T, 3)) if f_table is None else f_table)}
        for a, s in (("left", "l"), ("right", "r")):
            out[f"p_{s}"] = p[a] if a in p else np.broadcast_to(self.ball(a, X[0]), (T, 3))
            out[f"f_{s}"] = f[a] if a in f else np.zeros((T, 3))
            out[f"q_{s}"] = q[a] if a in q else np.broadcast_to(self.q[a], (T, self.n))
            out[f"c_{s}"] = c[a] if a in c else np.full(T, self.contact[a] >= 0)
        for key in COLUMNS:
            v = np.asarray(out[key])
            assert len(v) == T, key
            self.cols[key].append(v)
        self.t += self.dt * T

    def hold(self, X, k: int, duration: float, kind: str = "hold", phase: str = "hold", X_start=None) -> None:
        T = max(1, int(round(duration / self.dt)))
        self.add(k, kind, phase, np.broadcast_to(X, (T, 4, 4)), X_start=X_start)

    def move_arm(self, arm: str, path, X, k: int, new_contact: int, phase: str | None = None,
                 f_hold: np.ndarray | None = None) -> None:
        """A transit of ``arm`` along joint waypoints ``path (K, n)``; it then rests on ``new_contact``.

        ``f_hold (3,)`` (N, W): the force the other ball, alone on the object, holds it with meanwhile
        (in USP). It is eased in over ``HOLD_RAMP`` s while this ball still touches its contact, held in
        full along the whole transit, and eased out over ``HOLD_RAMP`` s once this ball touches the new
        one (the two then squeeze it): the object is never left with neither ball loaded, as it was when
        the ramps ran during the transit itself (the leaving ball is off at once, the arriving one only
        touches at the end)."""
        leaves = self.contact[arm] >= 0
        holder = _other(arm)
        fh = None if f_hold is None else np.asarray(f_hold, dtype=float)
        n_r = max(1, int(round(HOLD_RAMP / self.dt)))
        ramp = _min_jerk_kernel(np.arange(1, n_r + 1) / n_r)[:, None]
        if fh is not None and leaves:  # load the holder; this ball stays on its contact meanwhile
            self.add(k, "transit", phase or arm, np.broadcast_to(X, (n_r, 4, 4)), f={holder: ramp * fh})
        self.contact[arm] = -1
        _, qs = transit.time_parameterize(np.asarray(path, dtype=float), self.v_max[arm], self.acc, dt=self.dt)
        T = len(qs)
        f = {} if fh is None else {holder: np.broadcast_to(fh, (T, 3))}
        self.add(k, "transit", phase or arm, np.broadcast_to(X, (T, 4, 4)),
                 p={arm: self.robot.eef_position(arm, qs)}, q={arm: qs}, f=f)
        self.q[arm] = qs[-1]
        self.contact[arm] = new_contact
        if fh is not None and new_contact >= 0:  # unload the holder, this ball on its new contact
            self.add(k, "transit", phase or arm, np.broadcast_to(X, (n_r, 4, 4)), f={holder: ramp[::-1] * fh})

    def arrays(self) -> dict:
        """The rows so far as arrays (:data:`COLUMNS`), or {} when there are none."""
        if not self.cols["t"]:
            return {}
        return {k: np.concatenate(v) for k, v in self.cols.items()}

    def columns(self) -> dict:
        rows = self.arrays()
        return _columns(rows) if rows else {}


# ----------------------------------------------------------------------------------------------------
# Tumble


@dataclass
class _Env:
    """What a tumble needs, loaded once."""

    scene: object
    robot: object
    model: object
    mesh: object
    p_O: np.ndarray
    n_O: np.ndarray
    r: float
    inertia: np.ndarray
    mp: mpc.Params
    params: Params
    sp_margin: float = 0.005  # the analysis' (placements.parquet parameters)
    clearance: tuple = (0.0, 0.0)  # m, arm and stick, the sampler's (plan.json parameters)
    graph: GraphParams = field(default_factory=GraphParams)  # the graph's (plan.json parameters)
    _collide: object = None

    @property
    def collide(self):
        if self._collide is None:  # built on the first tumble: pivots and transits of the plan need none here
            self._collide = make_scene_collision_fn(self.scene, self.robot, self.mesh,
                                                    clearance=self.clearance)
        return self._collide


def _face_margin(model, p_O: np.ndarray, n_O: np.ndarray, x_O: np.ndarray) -> float:
    """How far (m) the point ``x_O`` lies inside the flat face through contact ``p_O`` with outward
    normal ``n_O``, measured in the rectangle its mesh vertices span in the face's plane along the
    face's principal directions (exact for a rectangular face, an over-estimate for others)."""
    V = model.mesh_vertices[np.abs((model.mesh_vertices - p_O) @ n_O) < 1e-4]
    if len(V) < 3:
        return -np.inf
    Q = V - V.mean(axis=0)
    Q -= np.outer(Q @ n_O, n_O)
    _, _, Wt = np.linalg.svd(Q, full_matrices=False)
    e = Wt[:2]  # in-plane axes
    lo, hi = (V @ e.T).min(axis=0), (V @ e.T).max(axis=0)
    x = x_O @ e.T
    return float(np.min(np.r_[x - lo, hi - x]))


def _contact_at(env: _Env, arm: str, q: np.ndarray, X: np.ndarray, where: str) -> int:
    """The contact whose ball centre the joints ``q`` put the ball on, with the object at ``X``."""
    b_O = se3.transform_points(se3.invert(X), env.robot.eef_position(arm, q[None])[0])
    d = np.linalg.norm(env.p_O + env.r * env.n_O - b_O, axis=1)
    c = int(np.argmin(d))
    if d[c] > 2e-3:
        raise InputError(f"{where}: the {arm} ball ends {1000 * d[c]:.1f} mm from the nearest contact")
    return c


def _catch_candidates(env: _Env, roll: Roll, catcher: str, th_r: float, params: TumbleParams) -> np.ndarray:
    """Contact ids on the landing face, best catcher first (module docstring), of those whose ball the
    ``catcher`` arm reaches (IK of the ball centre) both at the start and at the release angle ``th_r``:
    it holds the object all the way between, whatever its mode. The best ``catch_candidates``, then as
    many spread evenly over the rest of the ranking (``stages.graph.spread``): neighbouring contacts
    rank alike and fail alike (one link across the object, one IK limit), so when the best all fail
    the next ones are tried far apart on the face."""
    d_O = roll.X_end[2, :3] * -1.0  # the landing direction (W -z) in O: R^T (0, 0, -1)
    cand = np.flatnonzero(env.n_O @ d_O >= np.cos(params.catch_cone))
    X0 = roll.X_seg[0]
    a_O = X0[:3, :3].T @ roll.a_axis[0]
    p_O = se3.transform_points(se3.invert(X0), roll.p_axis[0])
    rel = env.p_O[cand] - p_O
    along = rel @ a_O
    lever = np.linalg.norm(rel - along[:, None] * a_O, axis=1)
    off = np.abs((env.p_O[cand] - env.model.com) @ a_O)
    cand = cand[np.lexsort((cand, -(lever - 0.5 * off)))]
    ball_O = env.p_O[cand] + env.r * env.n_O[cand]
    X = roll.poses([0.0, th_r])
    balls = np.concatenate([se3.transform_points(X[0], ball_O), se3.transform_points(X[1], ball_O)])
    res = env.robot.ik(catcher, balls, rng=np.random.default_rng(0))
    ranked, n = cand[res.ok.reshape(2, -1).all(axis=0)], params.catch_candidates
    return np.concatenate([ranked[:n], spread(ranked[n:], n)])


def _collision_free(env: _Env, q_l, q_r, X, touching, every: int) -> tuple[bool, str]:
    """Batched collision check of rows (every ``every``-th and the last)."""
    T = len(X)
    rows = np.unique(np.r_[np.arange(0, T, max(every, 1)), T - 1])
    ok, why = env.collide(q_l[rows], q_r[rows], X[rows], touching[rows])
    if ok.all():
        return True, "ok"
    return False, str(why[np.argmin(ok)])


def _catcher_motion(env: _Env, roll: Roll, catcher: str, c: int, mode: str, th_c: float, X_ref, X_to, q_p, q_end,
                    follow: bool, P: TumbleParams):
    """The catcher's joints on contact ``c`` along ``X_ref`` and on its way out (slide or back off),
    checked for IK, rolling and collisions (module docstring); ``(q_c, X_out, tgt_out, q_out)`` or the
    reason it fails."""
    robot, model, r = env.robot, env.model, env.r
    T = len(X_ref)
    tgt_c = _ball_centres(X_ref, env.p_O[c], env.n_O[c], r)
    if mode == "hold":  # backwards from the plan's final configuration; it must end on its contact
        q_c, why = ik_follow(robot, catcher, tgt_c[::-1], X_ref[::-1], env.n_O[c], q_end, env.params.ik_every,
                             both=not follow)
        q_c = q_c[::-1]
        # Its first solve, seeded with q_end, moves the posture by ~1e-4 rad; end exactly on q_end, so that
        # no transit (backing off the contact the ball holds the object by) is needed to get there.
        q_c[-1] = q_end
    else:
        first = robot.ik(catcher, tgt_c[:1], rng=np.random.default_rng(0))
        if not first.ok[0]:
            return f"{first.reason[0]} at the start"
        if follow:
            q_c, why = ik_follow(robot, catcher, tgt_c, X_ref, env.n_O[c], first.q[0], env.params.ik_every)
        else:
            q_c, why = _ik_path(robot, catcher, tgt_c, first.q[0], env.params.ik_every, check=True)
    if why != "ok":
        return why
    # Where the ball touches at the end of the catch, having rolled, must still be on the face.
    shift = rolling_shift(robot, catcher, q_c, X_ref, env.n_O[c], r)[-1]
    inside = _face_margin(model, env.p_O[c], env.n_O[c], env.p_O[c] + shift)
    if inside < P.roll_margin:
        return f"the ball rolls to {1000 * inside:.0f} mm from the face's edge"
    # The way out: slide past the far edge of the face (from where the ball has rolled to), or back off
    # along the contact normal.
    s = np.zeros(0)
    X_out, tgt_out, q_out = np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros((0, q_c.shape[1]))
    dt = env.params.mpc.dt
    if mode == "slide":
        X_c = X_ref[-1]
        seg = roll.segment_of(th_c)
        p_ax = se3.transform_points(se3.invert(X_c), roll.p_axis[seg])
        a_ax = X_c[:3, :3].T @ roll.a_axis[seg]
        u = env.p_O[c] - p_ax
        u -= (u @ a_ax) * a_ax + (u @ env.n_O[c]) * env.n_O[c]
        u /= np.linalg.norm(u)
        reach = float(np.max((model.vertices - env.p_O[c]) @ u)) + r + P.slide_clearance + max(0.0, -shift @ u)
        n_s = max(2, int(np.ceil(P.slide_time / dt)))
        s = reach * mpc.min_jerk(np.arange(1, n_s + 1) / n_s)
        X_out = np.broadcast_to(X_c, (n_s, 4, 4))
        tgt_out = se3.transform_points(X_c, env.p_O[c] + r * env.n_O[c] + s[:, None] * u)
    elif mode == "place":
        n_s = max(2, int(np.ceil(P.retreat_time / dt)))
        s = P.retreat * mpc.min_jerk(np.arange(1, n_s + 1) / n_s)
        X_out = np.broadcast_to(X_to, (n_s, 4, 4))
        tgt_out = se3.transform_points(X_to, env.p_O[c] + (r + s[:, None]) * env.n_O[c])
    if len(tgt_out):
        res = robot.ik_trajectory(catcher, tgt_out, q_c[-1])
        if not res.ok.all():
            return f"{res.reason[np.argmin(res.ok)]} on the way out"
        q_out = res.q
    # Collisions along the whole motion. The pusher's ball is exempt from the object throughout (the
    # object turns away from it); the catcher's while it touches: until it has slid out (the last slide
    # row is clear) or backed off half way, and for good when it holds.
    X_all = np.concatenate([X_ref, X_out, X_to[None]])
    qc_all = np.concatenate([q_c, q_out, (q_out if len(q_out) else q_c)[-1:]])
    qp_all = np.concatenate([q_p, np.broadcast_to(q_p[-1], (len(X_out) + 1, q_p.shape[1]))])
    out = s < (s[-1] if mode == "slide" else 0.5 * s[-1]) if len(s) else np.zeros(0, bool)
    touch_c = np.r_[np.ones(T, bool), out, mode == "hold"]
    touching = np.stack([np.ones(len(X_all), bool), touch_c], axis=1)
    if catcher == "left":
        touching = touching[:, ::-1]
    q_l, q_r = (qc_all, qp_all) if catcher == "left" else (qp_all, qc_all)
    ok, why = _collision_free(env, q_l, q_r, X_all, touching, P.check_every)
    if not ok:
        return why
    return q_c, X_out, tgt_out, q_out


class _Catch(NamedTuple):
    """A catch that works (:func:`_find_catch`): the catcher's contact, its mode (module docstring, 5.)
    and the angle its catch ends at, the tumble's profile ``t_prof, theta, on_p`` and reference
    ``X_ref``, the pusher's joints ``q_p`` (its first ``n_rel`` rows pushing), the catcher's IK kind,
    joints ``q_c`` and way out ``X_out, tgt_out, q_out``, and the MPC's ``(X, f_eef, f_table, errors)``."""

    c: int
    mode: str
    th_c: float
    t_prof: np.ndarray
    theta: np.ndarray
    on_p: np.ndarray
    n_rel: int
    X_ref: np.ndarray
    q_p: np.ndarray
    ik: str
    q_c: np.ndarray
    X_out: np.ndarray
    tgt_out: np.ndarray
    q_out: np.ndarray
    mpc: tuple


def _catch_mode(env: _Env, roll: Roll, c: int, usp: bool, X_to: np.ndarray, P: TumbleParams) -> tuple[str, float]:
    """How a catcher on contact ``c`` lets go (``hold``, ``place`` or ``slide``) and the roll angle at
    which its catch ends (module docstring, 5.)."""
    r, half = env.r, np.asarray(env.scene.table.size) / 2
    b_end = _ball_centres(X_to[None], env.p_O[c], env.n_O[c], r)[0]
    if usp:
        return "hold", roll.total
    if np.any(np.abs(b_end[:2]) > half + r + P.edge_clearance):
        return "place", roll.total
    grid = np.linspace(0.0, roll.total, 721)  # slide out short of the landing, the ball above the table
    z = _ball_centres(roll.poses(grid), env.p_O[c], env.n_O[c], r)[:, 2]
    high = grid[(z >= r + P.table_clearance) & (grid <= roll.total - P.slide_short)]
    return "slide", float(high.max()) if len(high) else 0.0


def _find_catch(env: _Env, roll: Roll, k: int, pusher: str, c_p: int, q_p0: np.ndarray, candidates, usp: bool,
                X_to: np.ndarray, q_end: np.ndarray, th_r: float) -> _Catch:
    """The first of ``candidates`` (best first) whose catch works: its mode leaves a catch past the
    release, its joints pass (:func:`_catcher_motion`, plain IK first, then turning with the object)
    and the tumbling MPC with the pusher's contact ``c_p`` is feasible (:func:`tumble_mpc`; a catcher
    the MPC refuses, e.g. one so high on the landing face that its squeeze keeps the push from
    starting, gives way to the next instead of failing the tumble). The pusher follows its contact
    from ``q_p0`` by :func:`ik_follow`. Raises :class:`TumbleError`: the pusher's IK code when it
    fails, ``mpc_infeasible`` when the catchers whose joints pass all fail the MPC, else
    ``no_catcher``; both name each candidate's failure."""
    P, dt, robot = env.params.tumble, env.params.mpc.dt, env.robot
    catcher, fails, mpc_why, pusher_paths = _other(pusher), [], None, {}
    for c in candidates:  # a handful, best first
        mode, th_c = _catch_mode(env, roll, c, usp, X_to, P)
        if th_c < th_r + np.radians(5.0):
            fails.append(f"contact {c}: the catch would end at {np.degrees(th_c):.0f} deg, before the release")
            continue
        t_prof, theta, on_p = tumble_profile(roll, th_r, th_c, P, dt)
        X_ref = roll.poses(theta)
        n_rel = int(np.count_nonzero(on_p))
        if n_rel not in pusher_paths:  # the same for every catcher
            tgt_p = _ball_centres(X_ref[:n_rel], env.p_O[c_p], env.n_O[c_p], env.r)
            pusher_paths[n_rel] = ik_follow(robot, pusher, tgt_p, X_ref[:n_rel], env.n_O[c_p], q_p0,
                                            env.params.ik_every)
        q_p, why_p = pusher_paths[n_rel]
        if why_p != "ok":
            raise TumbleError(why_p, f"step {k}: the pusher's IK fails on the way to the release angle")
        q_p = np.concatenate([q_p, np.broadcast_to(q_p[-1], (len(theta) - n_rel, q_p.shape[1]))])
        # Plain IK first (the ball then rolls on its face, stages.execute's "Ball rotation"), the ball
        # turning with the object (no rolling) when that rolls it off its face or fails. Into USP the
        # catcher must end on its contact: solved backwards from the plan's final configuration, turning
        # with the object (no rolling at all), else about the turning axis only (rolling along it).
        for follow in (False, True):
            got = _catcher_motion(env, roll, catcher, c, mode, th_c, X_ref, X_to, q_p, q_end, follow, P)
            if not isinstance(got, str):
                break
        if isinstance(got, str):
            fails.append(f"contact {c}: {got}")
            continue
        out = tumble_mpc(env.scene.object.mass, env.inertia, env.model, roll, theta, t_prof, X_ref, on_p,
                         env.p_O[[c_p, c]], env.n_O[[c_p, c]], env.mp)
        if isinstance(out, str):
            mpc_why = mpc_why or _mpc_failure(env, roll, k, c, mode, out)
            fails.append(f"contact {c}: the tumbling MPC fails")
            continue
        ik = ("both" if mode == "hold" else "plain") if not follow else "turn"
        return _Catch(c, mode, th_c, t_prof, theta, on_p, n_rel, X_ref, q_p, ik, *got, out)
    tried = "; ".join(fails) or "no candidate"
    if mpc_why is not None:  # a catcher's joints pass: the forces are what fail
        raise TumbleError("mpc_infeasible", f"{mpc_why} (catchers tried: {tried})")
    raise TumbleError("no_catcher", f"step {k}: no catcher works ({tried})")


def _mpc_failure(env: _Env, roll: Roll, k: int, c: int, mode: str, out: str) -> str:
    """Why the tumbling MPC refuses catcher ``c`` (into USP, that its contact cannot hold the fall)."""
    why = f"step {k}: {out}"
    if mode == "hold" and "after the release" in out:
        off = np.degrees(np.arccos(np.clip(env.n_O[c] @ -roll.X_end[2, :3], -1.0, 1.0)))
        why += (f": the destination grasp's catching contact {c} (its normal {off:.0f} deg from the "
                f"landing face's) cannot hold the object alone")
    return why


def plan_tumble(env: _Env, tl: _Timeline, k: int, step: dict, X_from: np.ndarray, X_to: np.ndarray) -> dict:
    """Rows of one tumble step (module docstring, "Tumble"), appended to ``tl``; returns a summary
    (catcher, contact, mode, angles, MPC figures). Raises :class:`TumbleError` when it cannot be done."""
    P, r = env.params.tumble, env.r
    robot, model, gp = env.robot, env.model, env.graph
    pusher = str(step["pusher"])
    catcher = _other(pusher)
    c_p = int(step["pusher_contact"])
    e0, e1 = (int(v) for v in step["edge"])
    roll = roll_segments(model, X_from, e0, e1)
    if np.abs(roll.X_end - X_to).max() > 1e-5:
        raise InputError(f"plan step {k}: rolling over edge ({e0}, {e1}) does not land on X_WO_to")
    found, c_found, q_push = pusher_motion(robot, env.collide, model, X_from, X_to, e0, e1, env.p_O, env.n_O, r,
                                           gp, push_limits(env.scene, gp), arms=(pusher,))
    if found is None or c_found != c_p:
        raise InputError(f"plan step {k}: the tumble's pusher no longer works; replan")
    usp = "catcher" in step  # into USP: the plan's catcher holds the object at the end
    before = step.get("transit", {}).get(f"{catcher}_before")
    if not usp and before is not None:  # the plan moves the other arm out of the object's way first
        tl.move_arm(catcher, before, X_from, k, -1)
    q_after = {pusher: q_push[-1], catcher: tl.q[catcher]}
    if usp:  # the plan moves the catcher to its catching configuration before the push
        q_after[catcher] = np.asarray(step["transit"][f"{catcher}_before"][-1], dtype=float)
        candidates = np.array([_contact_at(env, catcher, q_after[catcher], X_to, f"plan step {k}")])
    else:
        candidates = _catch_candidates(env, roll, catcher, release_angle(model, roll, gp), P)
    th_r = release_angle(model, roll, gp)
    try:
        if not len(candidates):
            raise TumbleError("no_catcher",
                              f"step {k}: no contact on the landing face within the {catcher} arm's reach")
        got = _find_catch(env, roll, k, pusher, c_p, q_push[0], candidates, usp, X_to, q_after[catcher], th_r)
    except TumbleError as err:  # into SP the pusher alone may tip the object over and let it fall
        if usp or err.code not in ("no_catcher", "mpc_infeasible"):
            raise
        return _plan_drop(env, tl, _Drop(k, step, roll, X_from, X_to, pusher, c_p, q_push[0], q_after), err)
    c, mode, th_c, t_prof, theta, on_p, n_rel, X_ref, q_p, ik, q_c = got[:11]
    X_mpc, f_mpc, f_tab, errs = got.mpc
    T = len(theta)
    tgt_p = _ball_centres(X_ref, env.p_O[c_p], env.n_O[c_p], r)

    ip, ic = (0, 1)
    tl.move_arm(pusher, step["transit"][pusher], X_from, k, -1)
    n_start = se3.rotate_vectors(X_from, env.n_O[tl.contact[catcher]]) if tl.contact[catcher] >= 0 else None
    res = transit.plan_transit(robot, env.collide, catcher, tl.q[catcher], q_c[0], tl.q[pusher], X_from,
                               env.params.transit, n_start=n_start, n_goal=se3.rotate_vectors(X_from, env.n_O[c]))
    if res.status != "ok":
        raise TumbleError(res.status, f"step {k}: the catcher's transit: {res.reason}")
    tl.move_arm(catcher, res.path, X_from, k, -1)
    phase = np.where(t_prof < P.grip_time, "grip", np.where(on_p, "push", np.where(
        theta < th_r + 1e-9, "release", "catch")))
    tl.add(k, "tumble", phase, X_mpc, X_ref=X_ref, X_start=X_from,
           p={pusher: np.concatenate([_ball_centres(X_mpc[:n_rel], env.p_O[c_p], env.n_O[c_p], r),
                                      np.broadcast_to(tgt_p[n_rel - 1], (T - n_rel, 3))]),
              catcher: _ball_centres(X_mpc, env.p_O[c], env.n_O[c], r)},
           f={pusher: f_mpc[:, ip], catcher: f_mpc[:, ic]}, q={pusher: q_p, catcher: q_c},
           c={pusher: on_p, catcher: np.ones(T, bool)}, f_table=f_tab)
    tl.q[pusher], tl.q[catcher] = q_p[-1], q_c[-1]
    tl.contact[pusher], tl.contact[catcher] = -1, c
    f_h = _let_go(env, tl, k, got, roll, catcher, X_from, X_to)
    _arms_back(env, tl, k, (pusher, catcher), q_after, X_to, f_h if usp else None)
    return {"catcher": catcher, "catch_contact": int(c), "mode": mode, "catcher_ik": ik,
            "release_deg": float(np.degrees(th_r)),
            "catch_end_deg": float(np.degrees(th_c)), "total_deg": float(np.degrees(roll.total)),
            "segments": len(roll.angle), "mpc_max_error": max(errs) if errs else 0.0}


def _let_go(env: _Env, tl: _Timeline, k: int, got: _Catch, roll: Roll, catcher: str, X_from: np.ndarray,
            X_to: np.ndarray):
    """Rows of the catcher letting go after its catch ``got`` (module docstring, "Tumble", 5.): it
    slides out and the object drops the rest of the way, or it places the object and backs off, or
    (into USP) it holds the object alone, its force going from the MPC's last to the least that holds
    (:func:`hold_force`), which it returns (N, W; None in SP). Raises :class:`TumbleError`
    (``unstable``) when no force of the catcher alone holds the object there."""
    P, dt = env.params.tumble, env.params.mpc.dt
    f_last = got.mpc[1][-1, 1]  # the catcher's last MPC force (W)
    n_out = len(got.X_out)
    if got.mode == "slide":
        tl.contact[catcher] = -1
        tl.add(k, "tumble", "slide", got.X_out, X_start=X_from, p={catcher: got.tgt_out},
               f={catcher: np.broadcast_to(f_last, (n_out, 3))}, q={catcher: got.q_out},
               c={catcher: np.ones(n_out, bool)})
        tl.q[catcher] = got.q_out[-1]
        X_drop = roll.poses(_free_fall(env, roll, got.th_c, dt))
        tl.add(k, "tumble", "drop", X_drop, X_start=X_from)
        tl.hold(X_to, k, P.settle, kind="tumble", phase="settle", X_start=X_from)
        return None
    if got.mode == "place":
        tl.hold(X_to, k, P.settle / 2, kind="tumble", phase="place", X_start=X_from)
        tl.contact[catcher] = -1
        tl.add(k, "tumble", "retreat", got.X_out, X_start=X_from, p={catcher: got.tgt_out}, q={catcher: got.q_out},
               c={catcher: np.zeros(n_out, bool)})
        tl.q[catcher] = got.q_out[-1]
        tl.hold(X_to, k, P.settle / 2, kind="tumble", phase="settle", X_start=X_from)
        return None
    f_h = hold_force(env, X_to, got.c)  # held alone in USP from now on
    if f_h is None:
        raise TumbleError("unstable", f"step {k}: the catcher on contact {got.c} cannot hold the object alone")
    T_s = max(1, int(round(P.settle / dt)))
    s_ = _min_jerk_kernel(np.arange(T_s) / max(T_s - 1, 1))[:, None]
    tl.add(k, "tumble", "settle", np.broadcast_to(X_to, (T_s, 4, 4)), X_start=X_from,
           f={catcher: (1.0 - s_) * f_last + s_ * f_h})
    return f_h


def _arms_back(env: _Env, tl: _Timeline, k: int, arms: tuple, q_after: dict, X_to: np.ndarray, f_h) -> None:
    """Each of ``arms`` (pusher first), by a planned transit, to where the plan has it at the end of the
    step, ``q_after``; ``f_h`` (N, W): the catcher's holding force in USP meanwhile, None in SP."""
    for arm in arms:
        if np.abs(tl.q[arm] - q_after[arm]).max() < 1e-9:
            continue
        touching = tl.contact[arm] >= 0
        n_c = se3.rotate_vectors(X_to, env.n_O[tl.contact[arm]]) if touching else None
        res = transit.plan_transit(env.robot, env.collide, arm, tl.q[arm], q_after[arm], tl.q[_other(arm)], X_to,
                                   env.params.transit, n_start=n_c, n_goal=n_c)
        if res.status != "ok":
            raise TumbleError(res.status, f"step {k}: the {arm} arm's way back: {res.reason}")
        tl.move_arm(arm, res.path, X_to, k, tl.contact[arm], f_hold=f_h if arm == arms[0] else None)


class _Drop(NamedTuple):
    """A tumble into SP to be done by a drop (:func:`_plan_drop`): plan step ``k`` and its ``step``, the
    ``roll`` from ``X_from`` to ``X_to``, the ``pusher`` on contact ``c_p`` from joints ``q_p0``, and
    where the plan has each arm at the end, ``q_after``."""

    k: int
    step: dict
    roll: Roll
    X_from: np.ndarray
    X_to: np.ndarray
    pusher: str
    c_p: int
    q_p0: np.ndarray
    q_after: dict


def drop_profile(roll: Roll, th_tip: float, P: TumbleParams, dt: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``(t, theta, rate)`` of a drop: grip, then the pusher alone turns the object to the tip ``th_tip``
    (rad), at rest at each axis switch before it; the last piece is the first half of a minimum-jerk
    move to twice its angle, so that the object reaches the tip at its top speed ``rate`` (rad/s),
    with no acceleration, and falls on from there as gravity alone turns it (:func:`_free_fall`): a
    fall from a known rate, not from rest at an unstable balance whose timing physics cannot match."""
    sw = [float(a) for a in roll.switches if 1e-9 < a < th_tip - 1e-9]
    ks = [0.0, 0.0, *sw]
    ds = [P.grip_time, *[max(P.push_time * (b - a) / th_tip, 0.25) for a, b in zip(ks[1:-1], ks[2:], strict=True)]]
    t1, th1 = mpc.knot_profile(ks, ds, dt)
    n = max(2, int(round(max(P.push_time * (th_tip - ks[-1]) / th_tip, 0.5) / dt)))
    s_ = np.arange(1, n + 1) / n
    th2 = ks[-1] + 2.0 * (th_tip - ks[-1]) * mpc.min_jerk(0.5 * s_)
    return np.r_[t1, t1[-1] + n * dt * s_], np.r_[th1, th2], 1.875 * (th_tip - ks[-1]) / (n * dt)


def _back_off(env: _Env, tl: _Timeline, arm: str, X: np.ndarray, k: int) -> str:
    """``arm``'s ball, if on the object at ``X``, backs off ``TumbleParams.retreat`` along its contact's
    normal (a transit by IK along the line); ``"ok"`` or why it cannot."""
    c = tl.contact[arm]
    if c < 0:
        return "ok"
    P = env.params.tumble
    s_ = P.retreat * mpc.min_jerk(np.linspace(0.0, 1.0, 8))
    tgt = se3.transform_points(X, env.p_O[c] + (env.r + s_[:, None]) * env.n_O[c])
    res = env.robot.ik_trajectory(arm, tgt, tl.q[arm])
    if not res.ok.all():
        return f"the {arm} ball cannot back off its contact ({res.reason[np.argmin(res.ok)]})"
    tl.move_arm(arm, res.q, X, k, -1)
    return "ok"


def _drop_clear(env: _Env, q_other: np.ndarray, pusher: str, q_p: np.ndarray, X: np.ndarray) -> str:
    """The collision check of a drop (``"ok"`` or the first collision): the pusher along ``q_p`` (then
    still) with its ball exempt from the object (it pushes, then the object falls away from it), the
    other arm still at ``q_other``, the object along ``X (T, 4, 4)``."""
    qp = np.concatenate([q_p, np.broadcast_to(q_p[-1], (len(X) - len(q_p), q_p.shape[1]))])
    qo = np.broadcast_to(q_other, qp.shape)
    touching = np.zeros((len(X), 2), bool)
    touching[:, ARMS.index(pusher)] = True
    ok, why = _collision_free(env, *((qp, qo) if pusher == "left" else (qo, qp)), X, touching,
                              env.params.tumble.check_every)
    return "ok" if ok else why


def _plan_drop(env: _Env, tl: _Timeline, d: _Drop, no_catch: TumbleError) -> dict:
    """Rows of a tumble into SP that no catcher can do (``no_catch`` says why): the other arm lets go of
    the object, the pusher alone turns it over its edge to the tip (:func:`drop_profile`, the tumbling
    MPC with the pusher only) and leaves it there; it falls onto its new face (module docstring,
    "Tumble", 5.; §5.2.2: "one EEF rotates the object around one edge ... until it moves to SP").
    Checked as a catch is (IK, collisions, MPC; the other arm goes to its rest posture first when it
    is in the object's way); raises :class:`TumbleError` with the catch's code and both reasons when
    it fails too."""
    P, dt, r, robot = env.params.tumble, env.params.mpc.dt, env.r, env.robot
    k, pusher, c_p = d.k, d.pusher, d.c_p
    catcher = _other(pusher)

    def fail(why: str):
        return TumbleError(no_catch.code, f"{no_catch}; no drop either: {why}")

    th_tip = tip_angle(env.model, d.roll)
    t_prof, theta, rate = drop_profile(d.roll, th_tip, P, dt)
    s_id = d.roll.segment_of(th_tip)
    if s_id + 1 < len(d.roll.angle):
        more = np.degrees(d.roll.angle[s_id + 1:].sum())
        raise fail(f"it would land on a facet and roll on over its edge ({more:.1f} deg more), a fall about a "
                   "second edge the plan does not model")
    fall = fall_slip(env.scene.object.mass, env.inertia, env.model.com, d.roll, th_tip, rate, env.mp.g,
                     env.mp.mu_table)
    if fall.lifted or fall.slip > P.drop_slip:
        raise fail(f"its edge would {'lift off' if fall.lifted else f'slide {fall.slip * 1e3:.1f} mm'} as it "
                   f"falls from the tip (friction {env.mp.mu_table:.2f})")
    X_ref = d.roll.poses(theta)
    T = len(theta)
    tgt_p = _ball_centres(X_ref, env.p_O[c_p], env.n_O[c_p], r)
    q_p, why = ik_follow(robot, pusher, tgt_p, X_ref, env.n_O[c_p], d.q_p0, env.params.ik_every)
    if why != "ok":
        raise fail(f"the pusher's IK to the tip: {why}")
    X_fall = d.roll.poses(_free_fall(env, d.roll, th_tip, dt, rate))
    tl.move_arm(pusher, d.step["transit"][pusher], d.X_from, k, -1)
    why = _back_off(env, tl, catcher, d.X_from, k)
    if why != "ok":
        raise fail(why)
    X_all = np.concatenate([X_ref, X_fall, d.X_to[None]])
    why = _drop_clear(env, tl.q[catcher], pusher, q_p, X_all)
    rest = robot.arm(catcher).q_rest
    if why != "ok" and np.abs(tl.q[catcher] - rest).max() > 1e-9:  # the other arm out of the way, at rest
        res = transit.plan_transit(robot, env.collide, catcher, tl.q[catcher], rest, tl.q[pusher], d.X_from,
                                   env.params.transit)
        if res.status == "ok" and _drop_clear(env, rest, pusher, q_p, X_all) == "ok":
            tl.move_arm(catcher, res.path, d.X_from, k, -1)
            why = "ok"
    if why != "ok":
        raise fail(why)
    # The pusher's force fades to nothing at the tip, where the object leaves it: no least force.
    out = tumble_mpc(env.scene.object.mass, env.inertia, env.model, d.roll, theta, t_prof, X_ref, np.ones(T, bool),
                     env.p_O[[c_p, c_p]], env.n_O[[c_p, c_p]], replace(env.mp, f_min=0.0), on_c=np.zeros(T, bool))
    if isinstance(out, str):
        raise fail(out)
    X_mpc, f_mpc, f_tab, errs = out
    tl.add(k, "tumble", np.where(t_prof < P.grip_time, "grip", "push"), X_mpc, X_ref=X_ref, X_start=d.X_from,
           p={pusher: _ball_centres(X_mpc, env.p_O[c_p], env.n_O[c_p], r)}, f={pusher: f_mpc[:, 0]},
           q={pusher: q_p}, c={pusher: np.ones(T, bool)}, f_table=f_tab)
    tl.q[pusher] = q_p[-1]  # where the object leaves it: it stays there until the object has landed
    tl.add(k, "tumble", "drop", X_fall, X_start=d.X_from)
    tl.hold(d.X_to, k, P.settle, kind="tumble", phase="settle", X_start=d.X_from)
    _arms_back(env, tl, k, (pusher, catcher), d.q_after, d.X_to, None)
    return {"catcher": catcher, "catch_contact": -1, "mode": "drop", "catcher_ik": "",
            "release_deg": float(np.degrees(th_tip)), "catch_end_deg": float(np.degrees(th_tip)),
            "total_deg": float(np.degrees(d.roll.total)), "segments": len(d.roll.angle),
            "mpc_max_error": max(errs) if errs else 0.0, "drop_rate_deg_s": float(np.degrees(rate))}


def tumble_profile(roll: Roll, th_r: float, th_c: float, P: TumbleParams, dt: float):
    """``(t, theta, pusher_on)``: grip, push to ``th_r``, release dwell, catch to ``th_c``; knots at every
    axis switch, durations by angle (module docstring, "Tumble")."""
    knots_hi = np.r_[roll.switches, roll.total]

    def pieces(a, b, duration):
        ks = np.r_[a, knots_hi[(knots_hi > a + 1e-9) & (knots_hi < b - 1e-9)], b]
        d = np.diff(ks) / max(b - a, 1e-12) * duration
        return list(ks[1:]), list(np.maximum(d, 0.25))

    k1, d1 = pieces(0.0, th_r, P.push_time)
    k2, d2 = pieces(th_r, th_c, P.catch_time)
    t_prof, theta = mpc.knot_profile([0.0, 0.0, *k1, th_r, *k2], [P.grip_time, *d1, P.release_dwell, *d2], dt)
    on_p = t_prof < P.grip_time + sum(d1) + P.release_dwell / 2 - 1e-9
    return t_prof, theta, on_p


def tumble_mpc(mass, inertia, model, roll: Roll, theta, t_prof, X_ref, on_p, p_O, n_O, mp: mpc.Params,
               on_c=None):
    """The tumbling MPC along a roll, one run per segment (at rest at every switch): pusher and catcher
    contacts ``p_O, n_O (2, 3)`` (outward normals), the pusher on while ``on_p``, the catcher while
    ``on_c`` (None: throughout). Returns ``(X, f_eef (T, 2, 3), f_table, max errors)`` or the reason
    it fails."""
    T = len(theta)
    on_c = np.ones(T, bool) if on_c is None else np.asarray(on_c, bool)
    seg = np.array([roll.segment_of(th) for th in theta])
    X_mpc, f_mpc, f_tab = X_ref.copy(), np.zeros((T, 2, 3)), np.zeros((T, 3))
    errs = []
    for s_id in np.unique(seg):  # one to three segments
        rows = np.flatnonzero(seg == s_id)
        if len(rows) < 2:
            f_mpc[rows] = f_mpc[max(rows[0] - 1, 0)]
            continue
        p_edge = se3.transform_points(roll.X_seg[s_id], model.vertices[roll.edge[s_id]])
        res = mpc.run_tumble_mpc(mass, inertia, model.com, p_O, -n_O, p_edge, t_prof[rows] - t_prof[rows[0]],
                                 X_ref[rows], mp, contact_mask=np.stack([on_p[rows], on_c[rows]], 1))
        if res.status != "ok":
            when = "before" if on_p[rows[min(res.fail_step, len(rows) - 1)]] else "after"
            return (f"the tumbling MPC fails at row {res.fail_step} of segment {s_id} ({res.fail_reason}, "
                    f"{when} the release)")
        X_mpc[rows], f_mpc[rows], f_tab[rows] = res.X_WO, res.f_eef_W, res.f_table_W
        errs.append(float(np.max(res.tracking_error)))
    return X_mpc, f_mpc, f_tab, errs


class FallSlip(NamedTuple):
    """How a fall from the tip goes on a table of friction ``mu`` (:func:`fall_slip`)."""

    slip: float    # how far the edge has slid on the table when the object lands (m)
    lifted: bool   # the edge left the table (its normal force vanished) before the landing


def fall_slip(mass: float, I_com_O: np.ndarray, com_O: np.ndarray, roll: Roll, th_c: float, rate: float,
              g: float, mu: float, dt: float = 2e-4) -> FallSlip:
    """The fall about the roll's edge from ``th_c`` (rad), turning at ``rate`` (rad/s), onto the face it
    reaches, with the edge on the table under Coulomb friction ``mu``: sticking (the rotation about a
    fixed edge) while the reaction lies in the friction cone, sliding (friction ``mu N`` against the
    slip) when not; a planar rigid body (the plane normal to the edge, CoM lever and inertia about
    the edge's direction), integrated by semi-implicit Euler every ``dt`` s; stops at a lift-off.

    Why: :func:`_free_fall` plans the fall with the edge fixed; an edge that slides (a falling ladder's
    foot) or lifts off lands the object off its plan (§5.2.2)."""
    s_id = roll.segment_of(th_c)
    fall = float(np.cumsum(roll.angle)[s_id]) - th_c
    X = roll.poses([th_c])[0]
    a, z = roll.a_axis[s_id], np.array([0.0, 0.0, 1.0])
    u = np.cross(a, z) / np.linalg.norm(np.cross(a, z))               # horizontal, normal to the edge
    rho = X[:3, :3] @ com_O + X[:3, 3] - roll.p_axis[s_id]
    rho0 = np.array([rho @ u, rho @ z])                                # edge to CoM in the (u, z) plane
    i_c = float(a @ X[:3, :3] @ I_com_O @ X[:3, :3].T @ a)            # about the CoM, along the edge
    sgn = float(np.cross(a, u) @ z)                                    # a x u = sgn z, u x z = sgn a
    phi, w, v, x = 0.0, rate, 0.0, 0.0
    for _ in range(int(10.0 / dt)):  # ten seconds of fall: from rest at the very tip it never starts
        if phi >= fall:
            break
        c, s = np.cos(sgn * phi), np.sin(sgn * phi)
        r = np.array([c * rho0[0] - s * rho0[1], s * rho0[0] + c * rho0[1]])
        ar = sgn * np.array([-r[1], r[0]])                             # a x r in (u, z)
        # Unknowns (phi'', N, F): m (phi'' ar - w^2 r) = (F, N - m g); i_c phi'' = torque of (F, N) at -r.
        A = np.array([[mass * ar[0], 0.0, -1.0], [mass * ar[1], -1.0, 0.0],
                      [i_c, sgn * r[0], -sgn * r[1]]])
        b = np.array([mass * w * w * r[0], mass * w * w * r[1] - mass * g, 0.0])
        sliding = abs(v) > 1e-9
        if not sliding:
            acc, n_f, f_t = np.linalg.solve(A, b)
            sliding = abs(f_t) > mu * n_f
            sigma = np.sign(f_t)
        if sliding:
            sigma = -np.sign(v) if abs(v) > 1e-9 else sigma
            # Unknowns (phi'', N, x''): the edge slides along u, friction sigma mu N.
            A2 = np.array([[mass * ar[0], -sigma * mu, mass], [mass * ar[1], -1.0, 0.0],
                           [i_c, sgn * (r[0] - sigma * mu * r[1]), 0.0]])
            acc, n_f, x_acc = np.linalg.solve(A2, b)
            v_new = v + x_acc * dt
            v = 0.0 if v != 0.0 and np.sign(v_new) != np.sign(v) else v_new
        if n_f <= 0.0:
            return FallSlip(abs(x), True)
        w += acc * dt
        phi += w * dt
        x += v * dt
    return FallSlip(abs(x), False)


def _free_fall(env: _Env, roll: Roll, th_c: float, dt: float, rate: float = 0.0) -> np.ndarray:
    """Planned roll angles ``(T,)`` (rad), a row ``dt`` apart, of the object falling from ``th_c``,
    turning at ``rate`` (rad/s, along the roll), onto its face: the rotation about the current axis
    with gravity alone (``mpc.integrate_rotation``), then any narrow faces left, a row each."""
    s_id = roll.segment_of(th_c)
    end = float(np.cumsum(roll.angle)[s_id])
    X_c = roll.poses([th_c])[0]
    sup_O = env.model.vertices[roll.edge[s_id]]
    zeros = np.zeros((2, 3))
    rot = mpc.make_rotation_model(env.scene.object.mass, env.inertia, env.model.com, zeros,
                                  np.array([[0.0, 0.0, 1.0]] * 2), sup_O, env.mp.g)
    # The model's rate is about its edge's direction (first to second vertex), the roll's about a_axis.
    e_W = X_c[:3, :3] @ (sup_O[1] - sup_O[0])
    R, nu, th, out = X_c[:3, :3], np.array([rate * np.sign(e_W @ roll.a_axis[s_id] or 1.0)]), th_c, []
    while th < end - 1e-9 and len(out) < 200:  # a fraction of a second
        R, nu = mpc.integrate_rotation(rot, R, nu, zeros, dt, substeps=4)
        th = th_c + float(Rotation.from_matrix(R @ X_c[:3, :3].T).as_rotvec() @ roll.a_axis[s_id])
        out.append(min(th, end))
    later = np.cumsum(roll.angle)[s_id + 1:]
    return np.r_[out, later]


# ----------------------------------------------------------------------------------------------------
# The stage


def make_env(scene, model, tables: dict, robot, params: Params, collide=None,
             clearance: tuple[float, float] = (0.0, 0.0), graph: GraphParams | None = None) -> _Env:
    """What the tumbles of a plan need (``collide``: the scene's checker, built on first use if None,
    its links kept ``clearance = (arm, stick)`` (m, ``stages.sample.Params``) from the object; ``graph``
    the graph's parameters the plan was checked with, ``stages.graph.recorded_params``)."""
    con = tables["contacts"]
    mp = replace(params.mpc, mu_eef=params.friction_safety * scene.object.friction,
                 mu_table=params.friction_safety * scene.table.friction, f_max=scene.robot.max_eef_force)
    return _Env(scene=scene, robot=robot, model=model, mesh=tables["mesh"],
                p_O=np.stack([con["px"], con["py"], con["pz"]], axis=1),
                n_O=np.stack([con["nx"], con["ny"], con["nz"]], axis=1), r=scene.robot.ball_radius,
                inertia=np.asarray(tables["summary"]["inertia"]), mp=mp, params=params,
                sp_margin=float(tables["placements"].meta["params"]["sp_margin"]), clearance=clearance,
                graph=GraphParams() if graph is None else graph, _collide=collide)


def make_timeline(env: _Env) -> _Timeline:
    """An empty timeline: both arms at zero joints, off the object."""
    P = env.params
    return _Timeline(env.robot, env.r, env.p_O, env.n_O, env.mp.dt, env.scene.object.mass * env.mp.g,
                     {a: env.robot.arm(a).velocity * P.vel_scale for a in ARMS}, P.acc)


def check_tumble(env: _Env, q: dict, step: dict, X_from: np.ndarray, X_to: np.ndarray) -> tuple[str, str]:
    """Whether :func:`plan_tumble` can do the plan's tumble ``step`` with the arms at joints ``q`` (arm ->
    (n,)), off the object: ``("ok", "")``, or ``(reason code, why)``. ``pivot plan`` asks this of every
    tumble it walks (§5.3's motion-level check, lazily), so that this stage does not fail on one."""
    tl = make_timeline(env)
    tl.q = {a: np.asarray(q[a], dtype=float).copy() for a in ARMS}
    for a in ARMS:  # a ball the plan left on the object leaves it as in this stage's timeline
        try:
            tl.contact[a] = _contact_at(env, a, tl.q[a], X_from, "check_tumble")
        except InputError:
            tl.contact[a] = -1
    try:
        plan_tumble(env, tl, 0, step, X_from, X_to)
    except TumbleError as err:
        return err.code, str(err)
    except InputError as err:  # the pusher's check disagrees with the graph's: no pusher here
        return "no_pusher_contact", str(err)
    return "ok", ""


def plan_squeeze(env: _Env, tl: _Timeline, k: int, step: dict, X_from: np.ndarray, X_to: np.ndarray) -> dict:
    """Rows of one squeeze tumble (``stages.squeeze``; the module docstring's list), appended
    to ``tl``; returns a summary. Raises :class:`TumbleError` (``mpc_infeasible``) when the tumbling
    MPC finds no forces, ``InputError`` when the step's roll does not land on ``X_to``."""
    P = squeeze.recorded(step["squeeze"])  # what the plan checked
    e0, e1 = (int(v) for v in step["edge"])
    cl, cr = int(step["contacts"]["left"]), int(step["contacts"]["right"])
    m = squeeze.squeeze_motion(env.model, X_from, (e0, e1), P, env.mp.dt)
    if np.abs(m.roll.X_end - X_to).max() > 1e-5:
        raise InputError(f"plan step {k}: rolling over edge ({e0}, {e1}) does not land on X_WO_to")
    p_c, n_c = env.p_O[[cl, cr]], env.n_O[[cl, cr]]
    scene = env.scene
    out = tumble_mpc(scene.object.mass, env.inertia, env.model, m.roll, m.theta, m.t, m.X_ref, np.ones(len(m.t), bool),
                     p_c, n_c, squeeze.mpc_params(env.mp, P, scene.object.friction, scene.table.friction,
                                                  scene.robot.max_eef_force))
    if isinstance(out, str):
        raise TumbleError("mpc_infeasible", f"step {k}: {out}")
    X, f, f_tab, errs = out
    ql, qr = pivot_joints(env.robot, m.X_ref, p_c, n_c, np.stack([tl.q["left"], tl.q["right"]]), env.r, env.mp.dt,
                          env.graph)
    T = len(m.t)
    tl.add(k, "tumble", np.where(m.t < P.grip_time, "grip", "squeeze"), X, X_ref=m.X_ref, X_start=X_from,
           p={"left": _ball_centres(X, p_c[0], n_c[0], env.r), "right": _ball_centres(X, p_c[1], n_c[1], env.r)},
           f={"left": f[:, 0], "right": f[:, 1]}, q={"left": ql, "right": qr},
           c={"left": np.ones(T, bool), "right": np.ones(T, bool)}, f_table=f_tab)
    tl.q["left"], tl.q["right"] = ql[-1], qr[-1]
    tl.contact["left"], tl.contact["right"] = cl, cr
    return {"mode": "squeeze", "contacts": [cl, cr],
            "total_deg": float(np.degrees(m.roll.total)), "segments": len(m.roll.angle),
            "mpc_max_error": max(errs) if errs else 0.0}


def _pivot_forces(env, f_cap: float, p_c: np.ndarray, n_in: np.ndarray, p0: np.ndarray, t: np.ndarray,
                  Xr: np.ndarray):
    """The pivot's MPC (``stages.mpc.run_pivot_mpc``: contacts ``p_c (2, 3)`` and inward normals ``n_in``
    (O), table vertex ``p0`` (W), reference times ``t`` and poses ``Xr``) with the first of
    ``table_friction_tries`` (each ball's normal force at least ``pivot_squeeze``, then at least the
    MPC's ``f_min``) whose solution is feasible and keeps every ball force within ``f_cap`` (N, the
    plan's ``mpc_max_force`` share of the bound: what the plan checked and the controller commands),
    else with ``friction_safety`` and ``f_min``, the plan's own check. Returns ``(result, table
    friction share, least normal force (N))``."""
    scene, params = env.scene, env.params
    tries = [(f, fs) for f in (min(params.pivot_squeeze, env.mp.f_max), env.mp.f_min)
             for fs in (*params.table_friction_tries, params.friction_safety)]
    for f_min, fs in tries:
        res = mpc.run_pivot_mpc(scene.object.mass, env.inertia, env.model.com, p_c, n_in, p0, t, Xr,
                                replace(env.mp, mu_table=fs * scene.table.friction, f_min=f_min))
        if res.status == "ok" and ((f_min, fs) == tries[-1]
                                   or float(np.max(np.linalg.norm(res.f_eef_W, axis=2))) <= f_cap):
            break
    return res, fs, f_min


def compute(scene, analysis_dir, plan: dict, params: Params) -> tuple[dict, dict]:
    """Dense trajectories of ``plan`` (module docstring); returns ``(columns, summary)``."""
    model, tables = load_object_model(analysis_dir)
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    recorded = plan.get("meta", {}).get("params", {})
    env = make_env(scene, model, tables, robot, params, clearance=clearance_of(recorded),
                   graph=recorded_params(recorded.get("graph", {})))
    f_cap = float(recorded.get("mpc_max_force", 1.0)) * scene.robot.max_eef_force
    tl = make_timeline(env)
    stats = {"primitives": 0, "mpc_max_error": 0.0, "mpc_iters": [], "status": "ok", "failed_primitive": -1,
             "tumbles": [], "pivot_table_friction": [], "pivot_squeeze": []}

    def pose_of(step, key):
        return se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in step[key].items()})[0]

    for k, step in enumerate(plan["steps"]):  # a few dozen primitives
        prim = step["primitive"]
        X_from, X_to = pose_of(step, "X_WO_from"), pose_of(step, "X_WO_to")
        if prim == "regrasp" and not _regrasp_rows(env, tl, k, step, X_from, stats):
            break
        if prim == "pivot" and not _pivot_rows(env, tl, k, step, X_from, X_to, f_cap, stats):
            break
        if prim == "tumble":
            try:
                if step.get("mode") == "squeeze":
                    info = plan_squeeze(env, tl, k, step, X_from, X_to)
                else:
                    info = plan_tumble(env, tl, k, step, X_from, X_to)
            except TumbleError as err:
                stats.update(status=err.code, failed_primitive=k, reason=str(err))
                break
            stats["mpc_max_error"] = max(stats["mpc_max_error"], info["mpc_max_error"])
            stats["tumbles"].append({"step": k, **info})
            tl.hold(X_to, k, params.hold)
        stats["primitives"] += 1
    rows = tl.arrays()
    if rows and stats["status"] == "ok" and params.stick_clearance > 0:
        stats["stick_clearance"] = refine_stick_clearance(env, rows, params)
    cols = _columns(rows) if rows else {}
    stats["mpc_iters"] = float(np.median(stats["mpc_iters"])) if stats["mpc_iters"] else 0.0
    stats["steps"] = int(len(cols.get("step", [])))
    # The planned joints must be a path the arms can follow: the largest row-to-row joint speed as a
    # fraction of the joint's velocity limit (transits run at vel_scale; a value above 1 is a jump).
    ratio = 0.0
    for a in ARMS if cols else ():
        speed = np.abs(np.diff(np.stack(cols[f"q_{a}"]), axis=0)) / env.mp.dt
        ratio = max(ratio, float(np.max(speed / robot.arm(a).velocity, initial=0.0)))
    stats["max_joint_speed_ratio"] = ratio
    stats["duration"] = float(cols["t"][-1]) if cols else 0.0
    return cols, stats


def _regrasp_rows(env: _Env, tl: _Timeline, k: int, step: dict, X_from: np.ndarray, stats: dict) -> bool:
    """Rows of regrasp step ``k``, appended to ``tl``: the moving arms' transits (in USP one at a time,
    the other ball holding the object alone with :func:`hold_force`), then a hold. False (and
    ``stats`` says why) when a ball cannot hold the object alone."""
    for arm in step.get("arms", []):
        f_hold = None
        if step["support"] == "USP" and tl.contact[_other(arm)] >= 0:
            f_hold = hold_force(env, X_from, tl.contact[_other(arm)])
            if f_hold is None:
                stats.update(status="unstable", failed_primitive=k,
                             reason=f"step {k}: the {_other(arm)} ball cannot hold the object alone")
                return False
        tl.move_arm(arm, step["transit"][arm], X_from, k, int(step["contacts"][arm]), f_hold=f_hold)
    if step.get("arms"):
        tl.hold(X_from, k, env.params.hold)
    return True


def _pivot_rows(env: _Env, tl: _Timeline, k: int, step: dict, X_from: np.ndarray, X_to: np.ndarray, f_cap: float,
                stats: dict) -> bool:
    """Rows of pivot step ``k``, appended to ``tl`` (§5.2.1): the tilt -> rotate -> lower reference
    (``mpc.pivot_reference``), its forces by the pivoting MPC within ``f_cap`` N (:func:`_pivot_forces`),
    the joints as ``pivot plan`` checked them (:func:`pivot_joints`), then a hold. False (and ``stats``
    says why) when the MPC finds no forces."""
    model, scene, p_O, n_O, r, dt = env.model, env.scene, env.p_O, env.n_O, env.r, env.mp.dt
    vtx = int(step["vertex"])
    p0 = se3.transform_points(X_from, model.vertices[vtx])
    d = poses.tilt_direction(model, X_from, vtx, scene.planner.tilt)
    t, Xr, phase = mpc.pivot_reference(X_from, X_to, p0, scene.planner.tilt, dt, env.params.pivot_durations,
                                       p_com_O=model.com, tilt_dir=d)
    cl, cr = int(step["contacts"]["left"]), int(step["contacts"]["right"])
    res, fs, f_min = _pivot_forces(env, f_cap, p_O[[cl, cr]], -n_O[[cl, cr]], p0, t, Xr)
    stats["pivot_table_friction"].append(fs)
    stats["pivot_squeeze"].append(f_min)
    if res.status != "ok":
        stats.update(status="mpc_infeasible", failed_primitive=k)
        return False
    X = res.X_WO
    targets = np.stack([_ball_centres(X, p_O[c], n_O[c], r) for c in (cl, cr)], axis=1)
    ql, qr = pivot_joints(env.robot, Xr, p_O[[cl, cr]], n_O[[cl, cr]], np.stack([tl.q["left"], tl.q["right"]]),
                          r, dt, env.graph)
    T = len(t)
    tl.add(k, "pivot", phase, X, X_ref=Xr, X_start=X_from, p={"left": targets[:, 0], "right": targets[:, 1]},
           f={"left": res.f_eef_W[:, 0], "right": res.f_eef_W[:, 1]}, q={"left": ql, "right": qr},
           c={"left": np.ones(T, bool), "right": np.ones(T, bool)}, f_table=res.f_table_W)
    tl.q["left"], tl.q["right"] = ql[-1], qr[-1]
    tl.contact["left"], tl.contact["right"] = cl, cr
    stats["mpc_max_error"] = max(stats["mpc_max_error"], float(np.max(res.tracking_error)))
    stats["mpc_iters"].append(float(np.median(res.n_iter[res.n_iter >= 0])))
    tl.hold(X_to, k, env.params.hold)
    return True


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
    provenance.check_made_from(plan_path, plan["meta"], scene, analysis_dir)
    if plan["status"] == "infeasible":
        raise InputError(f"{plan_path}: the plan is infeasible ({plan.get('reason')}); nothing to execute")
    if not plan["steps"]:
        raise InputError(f"{plan_path}: the plan has no steps (the start is already the goal); nothing to move")
    hull = artifacts.read_table(Path(analysis_dir) / "hull.parquet", "hull")
    provenance.check_plan_steps(plan_path, plan, int((hull["kind"] == "vertex").sum()),
                                len(artifacts.read_table(Path(analysis_dir) / "contacts.parquet", "contacts")))
    with about(plan_path):
        cols, stats = compute(scene, analysis_dir, plan, params)
    meta_params = {**asdict(params), "N_p": params.mpc.horizon, "dt": params.mpc.dt, "alpha": params.mpc.alpha,
                   "beta": params.mpc.beta}
    inputs = {"scene": scene_path, "plan": plan_path, **provenance.analysis_inputs(analysis_dir)}
    out = Path(out_path)
    # The target (trajectories.parquet, what Make tracks) goes last, after the summary it vouches for.
    if stats["status"] != "ok":  # no trajectories for this plan: an older file would pass for them
        out.unlink(missing_ok=True)
    artifacts.write_json(out.with_suffix(".json"), stats, artifacts.make_meta("mpc", meta_params, inputs, producer))
    if stats["status"] == "ok":
        artifacts.write_table(out, cols, FIELDS, artifacts.make_meta("trajectories", meta_params, inputs, producer))
    artifacts.write_timings(out.with_suffix(".json"), {"mpc": time.perf_counter() - t0})
    stagelog.log_trajectories(stats, cols.get("primitive") if stats["status"] == "ok" else None)
    return stats
