"""Stage ``graph``: the grasp-augmented graph of §5.1 (Fig. 10b, 11).

Nodes (``nodes.parquet``):

- a **grasp node** per feasible grasp of a sampled pose (node id = grasp id): the object at that pose,
  both balls on the grasp's contacts;
- a **free node** per SP pose: the object standing alone, both arms away. It makes regrasping in SP
  linear in the number of grasps: grasp → free → grasp costs the regrasp weight, split in two;
- a **catch node** per catching candidate of a tumble into USP (``catches.parquet``, kind ``catch``:
  pose, arm, contact, joints, status): the object just tumbled, one ball holding it alone (Fig. 14);
- a **hold node** per place where the pusher's ball alone holds a caught object, pressing it onto
  the table from above (``catches.parquet``, kind ``hold``; :func:`hold_candidates`).

Edges (``edges.parquet``; every candidate is kept, with ``status`` ``ok`` or its reason code):

- **pivot** (weight ``w_pivot``): two grasp nodes with the same contacts on two poses linked by a
  pivot about vertex v (§5.2.1), with the object in equilibrium on v with the two balls at the start
  of the tilt and at the largest tilt of the tilt → rotate → lower motion (``stages.mpc.
  pivot_reference``): v among both grasps' ``pivot_vertices`` (``stages.sample``: the stability LP,
  with the friction and ball force the plan's MPC may use). The arms along that motion (IK,
  collisions, each ball's tool axis turning against its contact normal by at most
  ``max_eef_normal_change``, §5.1's ``eef_normal_angle``: batched IK seeded from the first node's
  grasp, collisions at every sample) are checked lazily by ``pivot plan`` on the paths it finds
  (LazySP, §5.3's re-search), or here with ``pivot_arms``. Undirected.
- **regrasp** (weight ``w_regrasp``): in SP grasp node ↔ free node (half the weight each way); in USP
  between any two grasps of the pose whose balls can change their contacts one at a time, each
  move made while the other ball alone holds the object on its table edge (``hold_*``, §5.2.2;
  :func:`usp_regrasp_edges`). Undirected. The transit motions themselves are planned lazily by
  ``pivot plan``.
- **tumble** (weight ``w_tumble``, directed): over a support edge onto the next stable face
  (§5.2.2). One ball pushes: a contact whose push, within the ball's friction cone and force bound,
  turns the object against its weight (:func:`push_levers`), with IK and no collision along the roll
  up to the release angle of ``stages.trajectory`` (:func:`release_angle`, past the tip-over); the
  other arm stays away. This is a necessary condition only: ``pivot plan`` runs the tumbling MPC with
  the catch on every tumble it walks. Into SP: free node → free node. Into USP (Fig. 14): free node →
  a **catch node** of the new pose (its catching ball, the other arm's, waits on the landing face
  under the overhang beyond the table's edge and then holds the object alone,
  :func:`catch_candidates`; the candidates and their checks are in ``catches.parquet``, rejected ones
  with their reason, which the tumble edges into them carry).
- **squeeze tumble** (a tumble, weight ``w_tumble``, directed, arm ``both``; ``stages.squeeze``):
  grasp node → grasp node with the same contacts over a tumble link out of SP, into SP or USP: the
  grasp itself rolls the object over the edge onto the landing face, both balls on it throughout
  (where no pusher or catcher works, as when the object tips away from the robot). Checked by
  :func:`check_squeeze_edges`: the roll lands on the link's pose, the two balls hold the object on
  its edge at sampled angles (the stability LP), IK, collisions and ``eef_normal_angle`` along it.
- **hand-over** (a regrasp, weight ``w_regrasp``, directed; :func:`handover_edges`): catch node →
  each grasp of its pose: the pusher takes its contact of the grasp while the catcher holds, then
  the catcher moves to its own while the pusher's ball holds alone (Fig. 18 e–f); or through a hold
  (:func:`hold_edges`, half the weight each): catch node → hold node (the pusher onto the hold) →
  grasp (the catcher onto its grasp contact, then the pusher onto its own while the catcher's ball
  holds alone). Every one-ball hold is checked with ``hold_eef_friction`` of the ball's friction, so
  it holds by its normal force (a hold by the ball's friction tipped the piano in physics).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from stages import artifacts, mpc, poses, provenance, se3, squeeze, stability, stagelog
from stages.artifacts import Field
from stages.errors import InputError
from stages.objectmodel import load_object_model
from stages.robot import follow_ik, load_robot
from stages.sample import clearance_of, make_scene_collision_fn
from stages.scene import Scene, load_scene


@dataclass(frozen=True)
class Params:
    """Motion checks of the graph edges (s, rad)."""

    #: Tilt, rotate and lower durations of the sampled pivot path; with ``check_dt`` they set how
    #: many intermediate configurations are checked.
    check_durations: tuple[float, float, float] = (1.0, 1.5, 1.0)
    check_dt: float = 0.4
    #: Pivot edges checked per batch of IK and collision checks (their results do not depend on it;
    #: peak memory grows with it: the duck's 8,300 in one batch took 4.8 GB, in batches of 512 0.7 GB).
    pivot_chunk: int = 512
    #: A pusher follows the tumble for at least this angle (notes: 35–45°) and ``release_past_tip``
    #: past the angle where the CoM crosses over the axis (:func:`release_angle`), then lets go; its IK
    #: and collisions are checked at most ``push_step`` apart up to there, as ``stages.trajectory`` pushes.
    push_angle: float = np.radians(40.0)
    release_past_tip: float = np.radians(10.0)
    push_step: float = np.radians(8.0)
    #: Pusher candidates tried per tumble and arm, best first (:func:`_push_candidates`).
    push_candidates: int = 8
    #: A catcher of a tumble into USP (:func:`catch_candidates`): on the landing face (its outward normal
    #: within ``catch_cone`` of straight down after the landing), its ball at least ``catch_clearance``
    #: beyond the table's edge; ``catch_candidates`` per tumble and arm, largest lever first.
    catch_cone: float = np.radians(30.0)
    catch_clearance: float = 0.01
    catch_candidates: int = 8
    #: ... and it holds the landed object alone with these fractions of the table's and the ball's
    #: friction, as the sampler's ``hold_*`` (``stages.sample.Params``).
    hold_friction_safety: float = 0.8
    hold_eef_friction: float = 0.3
    #: A hand-over's hold (:func:`hold_candidates`): the pusher's ball on a face within ``catch_cone`` of
    #: straight up, over the table; this many per USP pose, farthest from the CoM first.
    hold_candidates: int = 8
    #: Squeeze tumbles (``stages.squeeze``): timing and the angles of their statics check.
    squeeze: squeeze.SqueezeParams = field(default_factory=squeeze.SqueezeParams)
    ik_tol: float = 1e-3
    max_joint_step: float = 0.5
    #: §5.1: "we also evaluate the change in the angle between the EEF and the contact surface normal
    #: during pivoting motion". A pivot edge along which either ball's tool axis turns against the
    #: contact normal by more than this (from its angle at the start) is ``eef_normal_angle``
    #: (:func:`eef_normal_angle_change`). The ball then rolls on the object by ``r`` times that change
    #: (the execution's rolling correction shifts its target by as much) and its stick sweeps towards
    #: the surface. The paper gives no figure; the bound is the envelope validated in physics: the
    #: reproduced runs' pivots turn it by 7-72 deg (Exp. 1's widest, 2.5 cm of rolling) and succeed,
    #: nominal and perturbed. On Exp. 1's graph the change's median is 35 deg, its 99th percentile 65.
    max_eef_normal_change: float = np.radians(75.0)
    #: LazySP (§5.3: the motion is checked on the path the search takes, a failure re-searches): a
    #: pivot edge's arm motion (IK, collisions, ``eef_normal_angle``) is checked here only with
    #: ``pivot_arms``; otherwise ``pivot plan`` runs these same checks on the pivot edges of each path
    #: it finds, before walking it (``stages.plan._graph_arm_checks``). They took nine tenths of the
    #: stage (the duck: 22 of 25 s) and refuse one edge in fourteen. The sampler's reach
    #: (``stages.sample.lazy_reach``) checks them here, once per walk.
    pivot_arms: bool = False
    #: The friction and ball force the planner's MPC may use (``stages.plan.Params``: 0.8 of the
    #: friction, each ball's whole force within 0.9 of the force bound, ``stability.normal_bound``), so
    #: that the search does not find motions its MPC check then refuses: a pusher's (:func:`push_limits`)
    #: and a squeeze's force. A pivot's equilibrium is the sampler's ``pivot_vertices`` test, with the
    #: same fractions (``stages.sample.Params.pivot_*_safety``).
    friction_safety: float = 0.8
    force_safety: float = 0.9
    #: Worker threads of the collision checks, each taking a slice of the configurations (numpy
    #: releases the GIL in its kernels; every configuration's answer is its own, so the graph is the
    #: same for any number). The pivot checks test ~60,000 configurations at once, where two threads
    #: took 0.65 s instead of 0.89 s on the 2-core VM with the other core busy. Not in the artifacts'
    #: parameters.
    threads: int = 2


@dataclass(frozen=True)
class Graph:
    nodes: dict
    edges: dict
    catches: dict
    summary: dict
    timings: dict


def grasp_geometry(tables, grasps, r):
    """Ball contact points and centres in O for each grasp: ``(G, 2, 3)`` points, normals (outward)."""
    con = tables["contacts"]
    p = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    c = np.stack([grasps["contact_left"], grasps["contact_right"]], axis=1)
    return p[c], n[c]


#: Samples of a motion checked for collisions at once (:func:`check_arm_motion`).
COLLISION_BLOCK = 8


def recorded_params(params: dict) -> Params:
    """The graph's parameters as its artifacts record them (``edges.parquet``'s ``params``; ``plan.json``
    carries them on as ``graph``), so that ``pivot plan`` and ``pivot mpc`` check and move as the graph
    did rather than by this module's defaults. Fields not recorded (``threads``, ``pivot_chunk``: how
    fast, not what) keep their defaults."""
    names = {f.name for f in fields(Params)}
    kw = {k: v for k, v in params.items() if k in names}
    if "squeeze" in kw:
        kw["squeeze"] = squeeze.recorded(kw["squeeze"])
    if "check_durations" in kw:
        kw["check_durations"] = tuple(kw["check_durations"])
    return replace(Params(), **kw)


def check_arm_motion(robot, collide, X_traj, p_O, n_O, q0, ball_radius, params: Params, active=(True, True),
                     touching=None, batch: bool = False, follow: bool = False):
    """IK and collisions along object trajectories with both balls on their contacts.

    Parameters
    ----------
    X_traj : (E, T, 4, 4) object poses over time for E motions.
    p_O, n_O : (E, 2, 3) contact points and outward normals (O) of the left and right ball.
    q0 : (E, 2, n) joint seeds at the first sample.
    active : which balls follow the object; an inactive arm stays at its seed.
    touching : which balls may touch the object (default: the active ones).
    batch : solve the IK of all samples at once first (``Robot.ik_trajectory``; for few long motions).
    follow : the balls turn with the object (``stages.robot.follow_ik``, as ``stages.trajectory`` moves
        a tumble's pusher) instead of position-only IK.

    Returns ``ok (E,)``, ``reason (E,)`` (first failure), ``q (T, E, 2, n)``.
    """
    E, T = X_traj.shape[:2]
    q = np.repeat(q0[None], T, axis=0).copy()
    touching = active if touching is None else touching
    reason = np.full(E, "ok", dtype=object)
    if E == 0:
        return np.zeros(0, bool), reason.astype(str), q
    for k, arm in enumerate(("left", "right")):
        if not active[k]:
            continue
        ball_O = p_O[:, k] + ball_radius * n_O[:, k]
        targets = np.einsum("etij,ej->tei", X_traj[..., :3, :3], ball_O) + np.swapaxes(X_traj[..., :3, 3], 0, 1)
        if follow:
            res = follow_ik(robot, arm, targets, X_traj, np.arange(T), n_O[:, k], q0[:, k], tol=params.ik_tol,
                            max_jump=params.max_joint_step)
        else:
            res = robot.ik_trajectory(arm, targets, q0[:, k], tol=params.ik_tol,
                                      max_joint_step=params.max_joint_step, batch=batch)
        q[:, :, k] = res.q
        bad = ~res.ok
        first = np.argmax(bad, axis=0)
        failed = bad.any(axis=0) & (reason == "ok")
        reason[failed] = res.reason[first[failed], np.flatnonzero(failed)]
    live = np.flatnonzero(reason == "ok")
    # Collisions in blocks of samples, in time order: a motion stops at its first block with a hit,
    # which holds its first hit (each sample is checked on its own, so the reason is the same).
    for t0 in range(0, T, COLLISION_BLOCK):
        if not len(live):
            break
        t1 = min(t0 + COLLISION_BLOCK, T)
        ql = q[t0:t1, live, 0].reshape(-1, q.shape[-1])
        qr = q[t0:t1, live, 1].reshape(-1, q.shape[-1])
        X = np.swapaxes(X_traj[live, t0:t1], 0, 1).reshape(-1, 4, 4)
        ok, why = collide(ql, qr, X, np.broadcast_to(np.asarray(touching, bool), (len(ql), 2)))
        ok = ok.reshape(t1 - t0, len(live))
        why = why.reshape(t1 - t0, len(live))
        first = np.argmax(~ok, axis=0)
        failed = ~ok.all(axis=0)
        reason[live[failed]] = why[first[failed], np.flatnonzero(failed)]
        live = live[~failed]
    return reason == "ok", reason.astype(str), q


def eef_normal_angle_change(robot, q: np.ndarray, X_traj: np.ndarray, n_O: np.ndarray) -> np.ndarray:
    """How far each ball's tool axis turns against its contact's surface normal along a motion (§5.1).

    ``q (T, E, 2, n)`` joints (rad) of both arms at T samples of E motions, ``X_traj (E, T, 4, 4)`` the
    object's poses, ``n_O (E, 2, 3)`` the contacts' outward normals (O). The tool axis is the ball
    frame's z (the stick's direction, flange to ball; Fig. 5's EEF rotational vector e); its angle to
    the inward normal ``-R_WO n_O`` is taken at every sample. Returns ``(E,)`` rad: the largest change
    of that angle from the first sample, over both balls."""
    T, E = q.shape[:2]
    out = np.zeros(E)
    if E == 0:
        return out
    for k, arm in enumerate(("left", "right")):
        e = robot.eef_rotation(arm, q[:, :, k].reshape(T * E, -1))[:, :, 2].reshape(T, E, 3)
        n_W = -np.einsum("etij,ej->tei", X_traj[..., :3, :3], n_O[:, k])
        ang = np.arccos(np.clip(np.einsum("tei,tei->te", e, n_W), -1.0, 1.0))
        out = np.maximum(out, np.abs(ang - ang[:1]).max(axis=0))
    return out


class PivotChecks(NamedTuple):
    """What :func:`check_pivot_edges` checks pivot edges with: the scene, object model and analysis
    tables, robot and collision function, poses ``X_WO (N, 4, 4)`` (W, m), the pivot links' poses
    ``link_poses (L, 2)``, vertices ``link_vertex (L,)`` and tumble edges ``link_edge (L, 2)``, and per
    grasp its ``pivot_vertices`` as sets, contact points and outward normals ``p_g, n_g (G, 2, 3)`` (O)
    and joints ``q_g (G, 2, n)``."""

    scene: Scene
    model: poses.ObjectModel
    tables: dict
    robot: object
    collide: object
    X_WO: np.ndarray
    link_poses: np.ndarray
    link_vertex: np.ndarray
    link_edge: np.ndarray
    pivot_sets: list
    p_g: np.ndarray
    n_g: np.ndarray
    q_g: np.ndarray


def check_pivot_edges(pc: PivotChecks, cand: np.ndarray, params: Params) -> np.ndarray:
    """Status of pivot edge candidates ``cand (n, 3)`` (grasp at a, grasp at b, link), ``(n,)``:
    ``unstable`` when either grasp does not list the link's vertex among its ``pivot_vertices``,
    ``not_a_pivot``, then with ``params.pivot_arms`` the arms along the tilt -> rotate -> lower
    reference (:func:`_pivot_arms`). The equilibrium on the vertex at the start of the tilt and at
    its largest is the sampler's ``pivot_vertices`` test (the stability LP, eq. 1-4, with the plan
    MPC's friction and force, ``stages.sample.Params.pivot_friction_safety`` and ``_force_safety``)."""
    status = np.full(len(cand), "ok", dtype=object)
    v = pc.link_vertex[cand[:, 2]] if len(cand) else np.zeros(0, np.int64)
    piv_a = pc.pivot_sets
    for i, (ga, gb, _), vi in zip(range(len(cand)), cand.tolist(), v.tolist(), strict=True):  # set lookups
        if vi not in piv_a[ga] or vi not in piv_a[gb]:
            status[i] = "unstable"
    live = np.flatnonzero(status == "ok")
    by_link = _pivot_references(pc, np.unique(cand[live, 2]), params) if len(live) else {}
    status[[i for i in live if cand[i, 2] not in by_link]] = "not_a_pivot"
    live = np.array([i for i in live if cand[i, 2] in by_link], dtype=np.int64)
    if len(live) and params.pivot_arms:
        trajs = [by_link[cand[i, 2]] for i in live]
        T = min(len(x) for x in trajs)
        status[live] = _pivot_arms(pc, cand[live, 0], np.stack([x[:T] for x in trajs]), params)
    return status


def _pivot_references(pc: PivotChecks, links: np.ndarray, params: Params) -> dict:
    """Per pivot link of ``links`` (one per link, shared by its grasps) its tilt -> rotate -> lower
    reference poses ``(T, 4, 4)`` (``mpc.pivot_reference``) with ``params.pivot_arms``, else its yaw and
    tilt axis (``mpc.pivot_axes``: whether it is a pivot is all that is asked of it then); a link that
    is no exact rotation about its vertex, or has no tilt onto it (``InputError``), is left out."""
    scene, model, X_WO = pc.scene, pc.model, pc.X_WO
    out = {}
    for li in links.tolist():
        Xa, Xb, vtx = X_WO[pc.link_poses[li, 0]], X_WO[pc.link_poses[li, 1]], int(pc.link_vertex[li])
        p0 = se3.transform_points(Xa, model.vertices[vtx])
        try:
            d = poses.tilt_direction(model, Xa, vtx, scene.planner.tilt)
            out[li] = mpc.pivot_reference(Xa, Xb, p0, scene.planner.tilt, params.check_dt, params.check_durations,
                                          p_com_O=model.com, tilt_dir=d)[1] if params.pivot_arms else \
                mpc.pivot_axes(Xa, Xb, p0, model.com, d)
        except InputError:
            pass
    return out


def _pivot_arms(pc: PivotChecks, g: np.ndarray, X_traj: np.ndarray, params: Params) -> np.ndarray:
    """The arms along pivot references ``X_traj (E, T, 4, 4)`` with grasps ``g (E,)`` from their own
    joints: :func:`check_arm_motion` and §5.1's ``eef_normal_angle``; status ``(E,)`` (``ok`` or why)."""
    why = np.empty(len(g), dtype=object)
    r = pc.scene.robot.ball_radius
    for s in range(0, len(g), params.pivot_chunk):  # fixed-size chunks bound the checker's memory
        c, gc = slice(s, s + params.pivot_chunk), g[s:s + params.pivot_chunk]
        ok, why[c], q_c = check_arm_motion(pc.robot, pc.collide, X_traj[c], pc.p_g[gc], pc.n_g[gc], pc.q_g[gc],
                                           r, params)
        turned = ok & (eef_normal_angle_change(pc.robot, q_c, X_traj[c], pc.n_g[gc]) > params.max_eef_normal_change)
        why[c][turned] = "eef_normal_angle"
    return why


def squeeze_candidates(links, support: np.ndarray, by_pose: dict) -> np.ndarray:
    """Squeeze-tumble edge candidates ``(n, 3)`` (grasp at a, grasp at b, link): every tumble link out
    of an SP pose (``support`` per pose) and every grasp of its pose ``a`` whose contact pair is also a
    grasp of the landing pose ``b`` (``by_pose``: pose -> {(left contact, right contact): grasp})."""
    cand = []
    for li in np.flatnonzero(links["primitive"] == "tumble").tolist():
        a, b = int(links["pose_a"][li]), int(links["pose_b"][li])
        if support[a] != "SP":
            continue
        gb = by_pose.get(b, {})
        cand += [(gi, gb[key], li) for key, gi in by_pose.get(a, {}).items() if key in gb]
    return np.array(cand, dtype=np.int64).reshape(-1, 3)


def _squeeze_rolls(pc: PivotChecks, links: np.ndarray) -> dict:
    """Link -> its roll (``stages.poses.roll_segments``) where rolling over the link's edge from its
    pose a lands on its pose b."""
    out = {}
    for li in links.tolist():
        Xa, Xb = pc.X_WO[pc.link_poses[li, 0]], pc.X_WO[pc.link_poses[li, 1]]
        try:
            roll = poses.roll_segments(pc.model, Xa, *(int(v) for v in pc.link_edge[li]))
        except InputError:
            continue
        if np.abs(roll.X_end - Xb).max() <= 1e-5:
            out[li] = roll
    return out


def check_squeeze_edges(pc: PivotChecks, cand: np.ndarray, params: Params) -> np.ndarray:
    """Status of squeeze-tumble candidates ``cand (n, 3)`` (grasp at a, grasp at b, link), ``(n,)``
    (``stages.squeeze``): ``not_a_tumble`` when the roll does not land on pose b; ``unstable`` when
    the two balls cannot hold the object on its edge at one of the sampled angles (the stability LP
    with ``SqueezeParams.friction`` of the frictions and ``force_safety``, all candidates in one
    batch); then the arms along the roll sampled every ``push_step``, in chunks of ``pivot_chunk``
    (:func:`check_arm_motion`, §5.1's ``eef_normal_angle``)."""
    status = np.full(len(cand), "ok", dtype=object)
    if not len(cand):
        return status.astype(str)
    scene, model, P = pc.scene, pc.model, params.squeeze
    rolls = _squeeze_rolls(pc, np.unique(cand[:, 2]))
    status[[li not in rolls for li in cand[:, 2].tolist()]] = "not_a_tumble"
    live = np.flatnonzero(status == "ok")
    mu = P.friction * scene.object.friction
    sp = stability.Params(mu_eef=mu, mu_table=P.friction * scene.table.friction,
                          f_max=stability.normal_bound(params.force_safety * scene.robot.max_eef_force, mu))
    L = float(np.linalg.norm(pc.tables["summary"]["extents"]) / 2)
    # Statics: every candidate at its link's angles, in one batch of LPs.
    angles = {li: squeeze.sample_angles(rolls[li], P.samples) for li in np.unique(cand[live, 2]).tolist()}
    X = {li: rolls[li].poses(th) for li, th in angles.items()}
    edge = {li: squeeze.edge_points(model, rolls[li], th) for li, th in angles.items()}
    links = cand[live, 2].tolist()
    reps = np.array([len(angles[li]) for li in links], dtype=np.int64)
    g = np.repeat(cand[live, 0], reps)
    ok = squeeze.squeeze_holds(scene.object.mass, model.com, np.concatenate([X[li] for li in links]),
                               np.concatenate([edge[li] for li in links]), pc.p_g[g], pc.n_g[g], L, sp,
                               params.threads)
    held = np.logical_and.reduceat(ok, np.r_[0, np.cumsum(reps)[:-1]]) if len(ok) else np.zeros(0, bool)
    status[live[~held]] = "unstable"
    live = np.flatnonzero(status == "ok")
    if len(live):
        K = int(np.ceil(max(rolls[li].total for li in cand[live, 2].tolist()) / params.push_step)) + 1
        X_traj = np.stack([rolls[li].poses(np.linspace(0.0, rolls[li].total, K)) for li in cand[live, 2].tolist()])
        for s in range(0, len(live), params.pivot_chunk):  # fixed-size chunks bound the checker's memory
            c, g = slice(s, s + params.pivot_chunk), cand[live[s:s + params.pivot_chunk], 0]
            ok, why, q = check_arm_motion(pc.robot, pc.collide, X_traj[c], pc.p_g[g], pc.n_g[g], pc.q_g[g],
                                          scene.robot.ball_radius, params)
            turned = ok & (eef_normal_angle_change(pc.robot, q, X_traj[c], pc.n_g[g]) > params.max_eef_normal_change)
            why[turned] = "eef_normal_angle"
            status[live[c]] = why
    return status.astype(str)


def build_graph(scene: Scene, analysis_dir, sample_dir, params: Params) -> Graph:
    """Nodes and edges with their checks (module docstring)."""
    t0 = time.perf_counter()
    model, tables = load_object_model(analysis_dir)
    sd = Path(sample_dir)
    ps = artifacts.read_table(sd / "poses.parquet", "poses")
    links = artifacts.read_table(sd / "pose_links.parquet", "pose_links")
    grasps = artifacts.read_table(sd / "grasps.parquet", "grasps")
    X_WO = se3.matrix_from_columns(ps.columns)
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    collide = make_scene_collision_fn(scene, robot, tables["mesh"], params.threads,
                                      clearance_of(grasps.meta["params"]))
    r = scene.robot.ball_radius
    w = scene.planner.weights
    G = len(grasps)
    q_g = np.stack([np.stack(list(grasps["q_left"])), np.stack(list(grasps["q_right"]))], axis=1) if G else \
        np.zeros((0, 2, robot.arm("left").dof))
    p_g, n_g = grasp_geometry(tables, grasps, r)

    # Nodes: grasp nodes first (node id = grasp id), then one free node per kept SP pose.
    kept_sp = np.flatnonzero((ps["status"] == "ok") & (ps["support"] == "SP"))
    free_of_pose = -np.ones(len(ps), np.int64)
    free_of_pose[kept_sp] = G + np.arange(len(kept_sp))
    nodes = {
        "node_id": np.arange(G + len(kept_sp)),
        "kind": np.array(["grasp"] * G + ["free"] * len(kept_sp)),
        "pose_id": np.concatenate([grasps["pose_id"], kept_sp]).astype(np.int64),
        "grasp_id": np.concatenate([np.arange(G), -np.ones(len(kept_sp), np.int64)]),
        "support": np.concatenate([ps["support"][grasps["pose_id"]], ps["support"][kept_sp]]).astype(str),
    }
    edges: list[tuple] = []  # (a, b, primitive, weight, status, vertex, edge_v0, edge_v1, arm)

    # --- regrasp edges ------------------------------------------------------------------------
    sp_grasp = ps["support"][grasps["pose_id"]] == "SP"
    sp_ids = np.flatnonzero(sp_grasp)  # one free-node edge per SP grasp
    edges += [(gi, f, "regrasp", w.regrasp / 2, "ok", -1, -1, -1, "both")
              for gi, f in zip(sp_ids.tolist(), free_of_pose[grasps["pose_id"][sp_ids]].tolist(), strict=True)]
    edges += usp_regrasp_edges(grasps, np.flatnonzero(~sp_grasp), q_g, X_WO, collide, w.regrasp)
    t1 = time.perf_counter()

    # --- pivot edges --------------------------------------------------------------------------
    by_pose, cand = pivot_candidates(grasps, links)
    v = links["vertex"][cand[:, 2]] if len(cand) else np.zeros(0, np.int64)
    checks = PivotChecks(scene, model, tables, robot, collide, X_WO,
                         np.stack([links["pose_a"], links["pose_b"]], axis=1), links["vertex"],
                         np.stack([links["edge_v0"], links["edge_v1"]], axis=1),
                         [set(x.tolist()) for x in grasps["pivot_vertices"]], p_g, n_g, q_g)
    status = check_pivot_edges(checks, cand, params)
    edges += [(ga, gb, "pivot", w.pivot, str(st), vi, -1, -1, "both")
              for (ga, gb, _), st, vi in zip(cand.tolist(), status, v.tolist(), strict=True)]
    t2 = time.perf_counter()

    # --- tumble edges -------------------------------------------------------------------------
    push_edges, catches = pushed_tumble_edges(scene, model, tables, robot, collide, X_WO, ps, links, grasps,
                                              free_of_pose, G + len(kept_sp), params)
    edges += push_edges
    sq = squeeze_candidates(links, ps["support"], by_pose)
    edges += [(ga, gb, "tumble", w.tumble, str(st), -1, int(links["edge_v0"][li]), int(links["edge_v1"][li]), "both")
              for (ga, gb, li), st in zip(sq.tolist(), check_squeeze_edges(checks, sq, params), strict=True)]
    edges += handover_edges(catches, grasps, q_g, X_WO, collide, w.regrasp)
    holds = hold_candidates(scene, model, tables, robot, collide, X_WO, ps["placement_id"], catches, params)
    holds["node_id"] = G + len(kept_sp) + len(catches["node_id"]) + np.arange(len(holds["pose_id"]))
    edges += hold_edges(catches, holds, grasps, q_g, X_WO, collide, w.regrasp)
    t3 = time.perf_counter()

    nodes, one = with_one_ball_nodes(nodes, catches, holds)
    edge_cols = edge_table(edges, one["node_id"])
    summary = graph_summary(nodes, edge_cols, catches, holds)
    timings = {"regrasp": t1 - t0, "pivot": t2 - t1, "tumble": t3 - t2, "total": time.perf_counter() - t0}
    return Graph(nodes, edge_cols, one, summary, timings)


def pivot_candidates(grasps, links) -> tuple[dict, np.ndarray]:
    """Pivot edge candidates: per pivot link, every grasp of its pose ``a`` whose contact pair is also a
    grasp of its pose ``b`` (a pivot keeps its grasp, §5.1). Returns ``by_pose`` (pose -> (left, right
    contact) -> grasp id) and ``cand (n, 3)`` rows (grasp at a, grasp at b, link)."""
    by_pose: dict[int, dict[tuple, int]] = {}
    for gi, (pose, cl, cr) in enumerate(zip(grasps["pose_id"].tolist(), grasps["contact_left"].tolist(),
                                            grasps["contact_right"].tolist(), strict=True)):
        by_pose.setdefault(pose, {})[(cl, cr)] = gi
    cand = []  # (grasp_a, grasp_b, link)
    pivots = np.flatnonzero(links["primitive"] == "pivot")
    for li, a, b in zip(pivots.tolist(), links["pose_a"][pivots].tolist(), links["pose_b"][pivots].tolist(),
                        strict=True):
        ga, gb = by_pose.get(a, {}), by_pose.get(b, {})
        for key, gi in ga.items():
            if key in gb:
                cand.append((gi, gb[key], li))
    return by_pose, np.array(cand, dtype=np.int64).reshape(-1, 3)


def with_one_ball_nodes(nodes: dict, catches: dict, holds: dict) -> tuple[dict, dict]:
    """The node table with the catch and hold nodes (USP, one ball holding) appended, and those nodes'
    own table (``catches.parquet``: node, pose, arm, contact, status, joints ``q``, kind)."""
    one = {k: np.concatenate([catches[k], holds[k]]) for k in ("node_id", "pose_id", "arm", "contact", "status")}
    one["q"] = np.concatenate([catches["q"], holds["q"]])
    one["kind"] = np.r_[np.full(len(catches["node_id"]), "catch"), np.full(len(holds["pose_id"]), "hold")]
    n = len(one["node_id"])
    return {"node_id": np.r_[nodes["node_id"], one["node_id"]],
            "kind": np.r_[nodes["kind"], one["kind"]],
            "pose_id": np.r_[nodes["pose_id"], one["pose_id"]].astype(np.int64),
            "grasp_id": np.r_[nodes["grasp_id"], -np.ones(n, np.int64)],
            "support": np.r_[nodes["support"], np.full(n, "USP")].astype(str)}, one


def pushed_tumble_edges(scene: Scene, model, tables, robot, collide, X_WO: np.ndarray, ps, links, grasps,
                        free_of_pose: np.ndarray, first_catch: int, params: Params) -> tuple[list, dict]:
    """The tumble edges a pusher makes out of every SP pose's free node (§5.2.2, Fig. 14): into SP onto
    the landing's free node, into USP onto a catch node of the other arm (:func:`catch_candidates`,
    numbered from ``first_catch``); a tumble with no pusher (:func:`pusher_motions`) gets its reason on
    every edge. ``free_of_pose (N,)`` is each pose's free node (-1 for none). Returns the edge rows and
    the catch table (with its ``node_id``)."""
    w, r = scene.planner.weights, scene.robot.ball_radius
    con = tables["contacts"]
    pc = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    nc = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    tumbles = [li for li in np.flatnonzero(links["primitive"] == "tumble")
               if ps["support"][links["pose_a"][li]] == "SP"]  # out of USP its holding ball would have to push
    la, lb = links["pose_a"][tumbles], links["pose_b"][tumbles]
    tumble_edges = np.stack([links["edge_v0"][tumbles], links["edge_v1"][tumbles]], axis=1).astype(np.int64)
    found = pusher_motions(robot, collide, model, X_WO[la], X_WO[lb], tumble_edges, pc, nc, r, params,
                           push_limits(scene, params))
    into_usp = ps["support"][lb] == "USP"
    own: dict[tuple, set] = {}  # (landing pose, arm) -> that arm's contacts in the pose's grasps
    landing = np.isin(grasps["pose_id"], lb[into_usp])
    for pose, cl, cr in zip(grasps["pose_id"][landing].tolist(), grasps["contact_left"][landing].tolist(),
                            grasps["contact_right"][landing].tolist(), strict=True):
        own.setdefault((pose, "left"), set()).add(cl)
        own.setdefault((pose, "right"), set()).add(cr)
    catches = catch_candidates(scene, model, tables, robot, collide, X_WO, ps["placement_id"], lb[into_usp],
                               tumble_edges[into_usp], params, own)
    catch_ids = first_catch + np.arange(len(catches["pose_id"]))
    catches["node_id"] = catch_ids
    by_landing: dict[tuple, list] = {}  # (pose, catcher arm) -> catch nodes
    for n, pose, arm in zip(catch_ids.tolist(), catches["pose_id"].tolist(), catches["arm"].tolist(), strict=True):
        by_landing.setdefault((pose, arm), []).append(n)
    edges = []
    for a, b, (e0, e1), (arm, what, _) in zip(la, lb, tumble_edges, found, strict=True):
        pusher, why = (arm, "ok") if arm is not None else ("none", what)
        src = free_of_pose[a]
        if ps["support"][b] == "SP":
            edges.append((src, free_of_pose[b], "tumble", w.tumble, why, -1, e0, e1, pusher))
            continue
        # Into USP (Fig. 14): onto a catch node of the other arm; a failed pusher is the reason for all.
        arms = ("left", "right") if pusher == "none" else ("right" if pusher == "left" else "left",)
        for catcher in arms:
            for n in by_landing.get((int(b), catcher), []):
                st = why if why != "ok" else str(catches["status"][n - catch_ids[0]])
                edges.append((src, n, "tumble", w.tumble, st, -1, e0, e1, pusher))
    return edges, catches


def edge_table(edges: list[tuple], one_ball_nodes: np.ndarray) -> dict:
    """The ``edges.parquet`` columns of edge rows ``(a, b, primitive, weight, status, vertex, edge_v0,
    edge_v1, arm)``: tumbles and every edge out of a one-ball node (catch, hold) are directed."""
    E = len(edges)
    cols = list(zip(*edges, strict=True)) if E else [[]] * 9
    node_a = np.array(cols[0], dtype=np.int64)
    return {
        "edge_id": np.arange(E),
        "node_a": node_a,
        "node_b": np.array(cols[1], dtype=np.int64),
        "primitive": np.array(cols[2], dtype=str),
        "weight": np.array(cols[3], dtype=float),
        "status": np.array(cols[4], dtype=str),
        "directed": np.array([p == "tumble" for p in cols[2]], dtype=bool) | np.isin(node_a, one_ball_nodes),
        "vertex": np.array(cols[5], dtype=np.int64),
        "edge_v0": np.array(cols[6], dtype=np.int64),
        "edge_v1": np.array(cols[7], dtype=np.int64),
        "arm": np.array(cols[8], dtype=str),
    }


def graph_summary(nodes: dict, edge_cols: dict, catches: dict, holds: dict) -> dict:
    """``graph.json``'s counts: nodes by kind (catch and hold nodes kept and rejected), edges by
    primitive kept and rejected, and the rejected edges by reason."""
    st, ct = np.unique(edge_cols["status"], return_counts=True)
    prim, ok = edge_cols["primitive"], edge_cols["status"] == "ok"
    counts = {k: int(np.sum(nodes["kind"] == k)) for k in ("grasp", "free")}
    for k, rows in (("catch", catches), ("hold", holds)):
        counts[k], counts[f"{k}_rejected"] = int(np.sum(rows["status"] == "ok")), int(np.sum(rows["status"] != "ok"))
    return {
        "nodes": counts,
        "edges": {p: {"ok": int((ok & (prim == p)).sum()), "rejected": int((~ok & (prim == p)).sum())}
                  for p in ("pivot", "regrasp", "tumble")},
        "reasons": {str(s): int(c) for s, c in zip(st, ct, strict=True) if s != "ok"},
    }


def usp_regrasp_edges(grasps, usp_ids, q_g, X_WO, collide, weight: float) -> list[tuple]:
    """Regrasp edges between the grasps of each USP pose: the balls change their contacts in turn (§5.2.2).

    From grasp (a, b) to (c, d) of one pose (contacts of the left, right ball): when a = c only the
    right ball moves while the left one alone holds the object on its table edge (``hold_left``), and
    likewise when b = d. Otherwise both move, one after the other (§1: "the left EEF moves to the
    desired position while the right EEF maintains contact with the object and vice versa"): the right
    first (the left holds at a; then the right holds at d while the left moves), which needs
    ``hold_left`` of (a, b) and ``hold_right`` of (c, d) and the two arms at (a, d) free of collision,
    or else the left first, with the holds and the arms at (c, b). The edge's ``arm`` names the movers
    in order from ``node_a`` to ``node_b`` ("right,left"); the reverse edge moves them in the other
    order through the same intermediate configuration. Every pair of grasps of a USP pose is a
    candidate: ``unstable`` when no order has both holds, else the collision reason of its
    intermediate configuration.

    Parameters
    ----------
    grasps : the grasps table (``pose_id``, ``contact_left``, ``contact_right``, ``hold_left``, ``hold_right``).
    usp_ids : (U,) ids of the grasps of USP poses.
    q_g : (G, 2, n) joints of every grasp (left, right).
    X_WO : (P, 4, 4) poses.

    Returns a list of ``(a, b, "regrasp", weight, status, -1, -1, -1, movers)`` rows, a < b.
    """
    pose = grasps["pose_id"][usp_ids]
    order = np.lexsort((usp_ids, pose))
    ids, pose = usp_ids[order], pose[order]
    a_l, b_l = [], []  # every pair (i < j) of grasps of one pose, in id order
    for group in np.split(ids, np.flatnonzero(np.diff(pose)) + 1):  # one group per USP pose: a few hundred
        i, j = np.triu_indices(len(group), 1)
        a_l.append(group[i])
        b_l.append(group[j])
    a = np.concatenate(a_l) if a_l else np.zeros(0, np.int64)
    b = np.concatenate(b_l) if b_l else np.zeros(0, np.int64)
    cl, cr = grasps["contact_left"], grasps["contact_right"]
    hl, hr = np.asarray(grasps["hold_left"], bool), np.asarray(grasps["hold_right"], bool)
    same_l, same_r = cl[a] == cl[b], cr[a] == cr[b]
    both = ~same_l & ~same_r
    movers = np.where(same_l, "right", np.where(same_r, "left", "right,left")).astype(object)
    right_first = both & hl[a] & hr[b]  # the left holds at a, then the right at d
    left_first = both & hr[a] & hl[b]  # the right holds at b, then the left at c
    status = np.where(same_l, np.where(hl[a], "ok", "unstable"),
                      np.where(same_r, np.where(hr[a], "ok", "unstable"), "unstable")).astype(object)
    done = ~both
    for first, l_of, r_of, name in ((right_first, a, b, "right,left"), (left_first, b, a, "left,right")):
        rows = np.flatnonzero(first & ~done)  # the right first when it can, else the left first
        if len(rows) == 0:
            continue
        ok, why = collide(q_g[l_of[rows], 0], q_g[r_of[rows], 1], X_WO[grasps["pose_id"][a[rows]]],
                          np.ones((len(rows), 2), bool))
        status[rows] = why
        movers[rows[ok]] = name
        done[rows[ok]] = True
    return [(int(x), int(y), "regrasp", weight, str(st), -1, -1, -1, str(m))
            for x, y, st, m in zip(a.tolist(), b.tolist(), status, movers, strict=True)]


def catch_candidates(scene: Scene, model, tables, robot, collide, X_WO, placement, pose_b, edge_v,
                     params: Params, grasp_contacts: dict | None = None) -> dict:
    """Where a ball can wait for an object tumbled into USP, catch it and hold it alone (§5.2.2, Fig. 14).

    For each tumble over hull edge ``edge_v (K, 2)`` onto the USP pose ``pose_b (K,)`` (``X_WO (P, 4, 4)``
    and ``placement (P,)`` of every pose), the
    candidates of each arm are the contacts on the landing face (outward normal within ``catch_cone``
    of straight down at the landing) whose ball lies beyond the table's edge by ``catch_clearance``
    (the ball under the overhang: the notes' catcher on the face the object falls onto; a ball on
    another face cannot stop the fall, ``stages.plan`` checks the fall with the tumbling MPC), the
    ``catch_candidates`` with the largest lever about the tumble's axis (less half their offset from
    the CoM along it) first. A candidate (pose, arm, contact) is checked once: IK of the ball centre
    at the landing, no collision with the other arm at rest (only the catching ball touches the
    object) and the object held by that ball alone on its table contact (``poses.table_support``; the
    stability LP: :func:`check_holds`).

    Returns :func:`check_holds`' columns.
    """
    con = tables["contacts"]
    p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    r, half = scene.robot.ball_radius, np.asarray(scene.table.size) / 2
    rows: dict[tuple, None] = {}  # (pose, arm, contact), in the order first found
    for b, (e0, e1) in zip(np.asarray(pose_b).tolist(), np.asarray(edge_v).tolist(), strict=True):  # a few dozen
        X = X_WO[b]
        n_W = se3.rotate_vectors(X, n_O)
        ball = se3.transform_points(X, p_O) + r * n_W
        beyond = np.max(np.abs(ball[:, :2]) - half, axis=1) >= r + params.catch_clearance
        cand = np.flatnonzero((n_W[:, 2] <= -np.cos(params.catch_cone)) & beyond)
        axis = model.vertices[e1] - model.vertices[e0]
        axis /= np.linalg.norm(axis)
        rel = p_O[cand] - model.vertices[e0]
        lever = np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)
        off = np.abs((p_O[cand] - model.com) @ axis)
        best = spread(cand[np.lexsort((cand, -(lever - 0.5 * off)))], params.catch_candidates)
        for arm in ("left", "right"):
            rows.update(dict.fromkeys((b, arm, int(c)) for c in best))
            # ... and every such contact that is the arm's contact of a grasp of the landing pose: the
            # catcher then holds on its grasp contact and only the pusher moves (Fig. 14).
            own = (grasp_contacts or {}).get((b, arm), ())
            rows.update(dict.fromkeys((b, arm, int(c)) for c in cand if int(c) in own))
    return check_holds(scene, model, tables, robot, collide, X_WO, placement, list(rows), params)


def hold_candidates(scene: Scene, model, tables, robot, collide, X_WO, placement, catches: dict,
                    params: Params) -> dict:
    """Where the pusher's ball can hold the object alone after a catch, pressing it onto the table from
    above (the hand-over's intermediate state, :func:`hold_edges`).

    For each USP pose with an ok catch, the pusher's (the other arm's) candidates are the contacts
    whose outward normal is within ``catch_cone`` of straight up, their ball above the table top
    (inside its edges), the ``hold_candidates`` farthest from the CoM (horizontally) first: a ball
    pressing down there turns the object back onto the table with a long lever, by its normal force,
    where a ball on a side face holds it only by friction. No antipodal pair offers them (their
    partner lies under the object on the table). The checks are :func:`check_holds`'.
    """
    con = tables["contacts"]
    p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    r, half = scene.robot.ball_radius, np.asarray(scene.table.size) / 2
    ok = catches["status"] == "ok"
    keys = dict.fromkeys(zip(catches["pose_id"][ok].tolist(),
                             ["right" if a == "left" else "left" for a in catches["arm"][ok].tolist()], strict=True))
    rows = []
    for b, arm in keys:  # a few dozen (pose, pusher)
        X = X_WO[b]
        n_W = se3.rotate_vectors(X, n_O)
        p_W = se3.transform_points(X, p_O)
        ball = p_W + r * n_W
        over = np.all(np.abs(ball[:, :2]) <= half - params.catch_clearance, axis=1)
        cand = np.flatnonzero((n_W[:, 2] >= np.cos(params.catch_cone)) & over)
        com = se3.transform_points(X, model.com)
        lever = np.linalg.norm(p_W[cand, :2] - com[:2], axis=1)
        rows += [(b, arm, int(c)) for c in cand[np.lexsort((cand, -lever))][: params.hold_candidates]]
    return check_holds(scene, model, tables, robot, collide, X_WO, placement, rows, params)


def check_holds(scene: Scene, model, tables, robot, collide, X_WO, placement, rows: list, params: Params) -> dict:
    """Check one-ball hold candidates ``rows [(pose, arm, contact)]``: IK of the ball centre, no
    collision with the other arm at rest (only this ball touches the object) and the object held by
    this ball alone on its table contact (``poses.table_support``; the stability LP with
    ``hold_friction_safety`` of the table's friction and ``hold_eef_friction`` of the ball's, the
    scene's force bound and the CoM moved out by the SP margin, ``poses.held_com``, as
    ``stages.sample`` checks ``hold_*``).

    Returns columns ``pose_id, arm, contact, status`` (``ok`` or the first failure) and ``q (N, n)``.
    """
    con = tables["contacts"]
    p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    r, half = scene.robot.ball_radius, np.asarray(scene.table.size) / 2
    n = robot.arm("left").dof
    N = len(rows)
    pose = np.array([k[0] for k in rows], dtype=np.int64)
    arm = np.array([k[1] for k in rows], dtype=str)
    contact = np.array([k[2] for k in rows], dtype=np.int64)
    status = np.full(N, "ok", dtype=object)
    q = np.zeros((N, n))
    X = X_WO[pose] if N else np.zeros((0, 4, 4))
    ball = se3.transform_points(X, p_O[contact] + r * n_O[contact]) if N else np.zeros((0, 3))
    for k, name in enumerate(("left", "right")):
        sel = np.flatnonzero(arm == name)
        if len(sel) == 0:
            continue
        res = robot.ik(name, ball[sel], rng=np.random.default_rng(0), restarts=1, tol=params.ik_tol)
        q[sel] = res.q
        status[sel[~res.ok]] = res.reason[~res.ok]
        live = sel[res.ok]
        if len(live):
            rest = np.broadcast_to(robot.arm("right" if name == "left" else "left").q_rest, (len(live), n))
            ql, qr = (q[live], rest) if name == "left" else (rest, q[live])
            touching = np.zeros((len(live), 2), bool)
            touching[:, k] = True
            ok, why = collide(ql, qr, X[live], touching)
            status[live[~ok]] = why[~ok]
    live = np.flatnonzero(status == "ok")
    if len(live):
        polys = {b: poses.table_support(model, X_WO[b], int(placement[b]), half)
                 for b in np.unique(pose[live]).tolist()}
        kmax = max(len(v) for v in polys.values())
        V = np.zeros((len(live), kmax, 3))
        mask = np.zeros((len(live), kmax), bool)
        for i, b in enumerate(pose[live].tolist()):  # a few hundred candidates
            V[i, :len(polys[b]), :2] = polys[b]
            mask[i, :len(polys[b])] = True
        sp_margin = float(tables["placements"].meta["params"]["sp_margin"])
        com = np.stack([poses.held_com(polys[b], se3.transform_points(X_WO[b], model.com), sp_margin)
                        for b in pose[live].tolist()])
        res = stability.evaluate(scene.object.mass, com, V, mask,
                                 se3.transform_points(X[live], p_O[contact[live]])[:, None],
                                 -se3.rotate_vectors(X[live], n_O[contact[live]])[:, None], None,
                                 float(np.linalg.norm(tables["summary"]["extents"]) / 2),
                                 stability.Params(mu_eef=params.hold_eef_friction * scene.object.friction,
                                                  mu_table=params.hold_friction_safety * scene.table.friction,
                                                  f_max=scene.robot.max_eef_force), compute_margin=False)
        status[live[~res.stable]] = "unstable"
    return {"pose_id": pose, "arm": arm, "contact": contact, "status": status.astype(str), "q": q}


def handover_edges(catches: dict, grasps, q_g, X_WO, collide, weight: float) -> list[tuple]:
    """Directed regrasp edges from each ok catch node to the grasps of its pose (Fig. 14, 18 e-f).

    The catcher (arm k on contact e) holds the object alone; the other ball (the pusher) takes its
    contact of grasp (c, d); when the grasp's contact of arm k is not e, the catcher then moves to it
    while the pusher's ball alone holds the object (``hold_*`` of the grasp). The two arms at the
    pusher's grasp configuration and the catcher's must be free of collision (both balls on the
    object). ``arm`` names the movers in order ("left" or "left,right").
    """
    ok = np.flatnonzero(catches["status"] == "ok")
    by_pose: dict[int, np.ndarray] = {}
    rows = []  # (catch row, grasp)
    for i in ok.tolist():  # a few hundred catches, each with the grasps of its pose
        pose = int(catches["pose_id"][i])
        if pose not in by_pose:
            by_pose[pose] = np.flatnonzero(grasps["pose_id"] == pose)
        rows += [(i, g) for g in by_pose[pose].tolist()]
    if not rows:
        return []
    ci, g = np.array(rows, dtype=np.int64).T
    catcher = catches["arm"][ci]
    k = (catcher == "right").astype(int)  # the catcher's index, 1 - k the pusher's
    c_catch = catches["contact"][ci]
    c_grasp = np.where(k == 0, grasps["contact_left"][g], grasps["contact_right"][g])
    pusher_holds = np.where(k == 0, grasps["hold_right"][g], grasps["hold_left"][g]).astype(bool)
    same = c_grasp == c_catch
    q_c = catches["q"][ci]
    ql = np.where((k == 0)[:, None], q_c, q_g[g, 0])
    qr = np.where((k == 1)[:, None], q_c, q_g[g, 1])
    _, why = collide(ql, qr, X_WO[catches["pose_id"][ci]], np.ones((len(ci), 2), bool))
    status = np.where(~same & ~pusher_holds, "unstable", why)
    pusher = np.where(k == 0, "right", "left")
    movers = np.where(same, pusher, np.char.add(np.char.add(pusher, ","), catcher.astype(str)))
    return [(int(n), int(x), "regrasp", weight, str(st), -1, -1, -1, str(m))
            for n, x, st, m in zip(catches["node_id"][ci].tolist(), g.tolist(), status, movers, strict=True)]


def hold_edges(catches: dict, holds: dict, grasps, q_g, X_WO, collide, weight: float) -> list[tuple]:
    """The hand-over through a hold (Fig. 18 e-f, each ball moving while the other holds alone by its
    normal force): directed regrasp edges, half the regrasp weight each,

    - catch node (catcher k on e) -> hold node of its pose (the pusher p on H): p moves to H while k
      holds; the two arms there free of collision (``status`` else the hold's own reason);
    - hold node (p on H) -> each grasp (c, d) of its pose: k moves to its contact of the grasp while p
      holds alone at H, then p to its own while k's ball holds alone (``hold_*`` of the grasp, else
      ``unstable``); the arms at H and at k's grasp contact free of collision. ``arm`` is "k,p".

    Returns rows as :func:`usp_regrasp_edges`'.
    """
    rows = []
    ok_c = np.flatnonzero(catches["status"] == "ok")
    for i in ok_c.tolist():  # catch -> hold: a few hundred pairs
        sel = np.flatnonzero((holds["pose_id"] == catches["pose_id"][i]) & (holds["arm"] != catches["arm"][i]))
        rows += [(i, j) for j in sel.tolist()]
    out = []
    if rows:
        ci, hj = np.array(rows, dtype=np.int64).T
        left = catches["arm"][ci] == "left"
        ql = np.where(left[:, None], catches["q"][ci], holds["q"][hj])
        qr = np.where(left[:, None], holds["q"][hj], catches["q"][ci])
        _, why = collide(ql, qr, X_WO[catches["pose_id"][ci]], np.ones((len(ci), 2), bool))
        status = np.where(holds["status"][hj] == "ok", why, holds["status"][hj])
        out += [(int(a), int(b), "regrasp", weight / 2, str(st), -1, -1, -1, str(m)) for a, b, st, m in
                zip(catches["node_id"][ci].tolist(), holds["node_id"][hj].tolist(), status, holds["arm"][hj],
                    strict=True)]
    rows = []
    for j in np.flatnonzero(holds["status"] == "ok").tolist():  # hold -> grasp: the grasps of its pose
        rows += [(j, g) for g in np.flatnonzero(grasps["pose_id"] == holds["pose_id"][j]).tolist()]
    if rows:
        hj, g = np.array(rows, dtype=np.int64).T
        p_left = holds["arm"][hj] == "left"
        k_holds = np.where(p_left, grasps["hold_right"][g], grasps["hold_left"][g]).astype(bool)
        ql = np.where(p_left[:, None], holds["q"][hj], q_g[g, 0])
        qr = np.where(p_left[:, None], q_g[g, 1], holds["q"][hj])
        _, why = collide(ql, qr, X_WO[holds["pose_id"][hj]], np.ones((len(hj), 2), bool))
        status = np.where(k_holds, why, "unstable")
        movers = np.where(p_left, "right,left", "left,right")
        out += [(int(a), int(b), "regrasp", weight / 2, str(st), -1, -1, -1, str(m)) for a, b, st, m in
                zip(holds["node_id"][hj].tolist(), g.tolist(), status, movers, strict=True)]
    return out


class PushLimits(NamedTuple):
    """What a pushing ball can do, as the tumbling MPC bounds it (``stages.trajectory.make_env``): the
    ball's friction coefficient ``mu`` (the scene's times ``friction_safety``), the bound on its normal
    force ``f_max`` (N), the weight it lifts ``weight`` (N) and the friction coefficient ``mu_table`` of
    the edge it turns the object on (the table's times ``friction_safety``)."""

    mu: float
    f_max: float
    weight: float
    mu_table: float


def push_limits(scene: Scene, params: Params) -> PushLimits:
    """The :class:`PushLimits` of ``scene``'s ball and object."""
    return PushLimits(params.friction_safety * scene.object.friction, scene.robot.max_eef_force,
                      scene.object.mass * mpc.Params().g, params.friction_safety * scene.table.friction)


def tip_holds(com_W: np.ndarray, edge_W: np.ndarray, p_W: np.ndarray, n_W: np.ndarray,
              limits: PushLimits, threads: int = 1) -> np.ndarray:
    """Whether a ball alone on each contact can start a tumble, ``(n,)`` bool: the object stays in
    equilibrium on the edge it turns about alone (its other table contacts just lifting, the hardest
    instant: the turn then brings the CoM over the edge), the ball's force in its friction cone
    (``limits.mu``) with its normal part at most ``limits.f_max``, the edge's two ends in the table's
    (``limits.mu_table``): the stability LP (§4.3, eq. 1-4) with the edge as the support and the
    pusher as the only EEF, as the tumbling MPC's first row is when no catcher helps (a drop, §5.2.2,
    Fig. 14). A push whose horizontal part the edge's friction cannot hold slides the object instead of
    tipping it, unless another ball holds that part.
    ``com_W (n, 3)``, ``edge_W (n, 2, 3)``, contact points ``p_W`` and outward normals ``n_W (n, 3)``, W;
    ``threads`` share the LPs (the same answer for any number)."""
    if not len(p_W):
        return np.zeros(0, bool)
    prm = stability.Params(mu_eef=limits.mu, mu_table=limits.mu_table, f_max=limits.f_max)
    res = stability.evaluate_threaded(limits.weight / prm.g, com_W, edge_W, None, p_W[:, None], -n_W[:, None], None,
                                      1.0, prm, compute_margin=False, threads=threads)
    return res.stable


def push_levers(p_W: np.ndarray, n_W: np.ndarray, p_axis: np.ndarray, a_axis: np.ndarray, mu: float) -> np.ndarray:
    """The largest moment about a rotation axis per unit normal force of a ball pushing on each contact.

    A ball on contact ``p`` (inward normal ``n``) pushes with ``f = f_n (n + t)``, ``t`` tangent to the
    face with ``|t| <= mu`` (its friction cone); the moment ``((p - p_axis) x f) . a = f . m`` with
    ``m = a x (p - p_axis)`` (the contact's velocity per unit angular rate) is largest with ``t`` along
    ``m``'s tangential part: ``f_n (n . m + mu |m - (n . m) n|)``. A positive value is a push that
    opens the rotation; the force bound of the MPC is on ``f_n``, so this ranks pushers by what they can
    turn. (A ball on the side face opposite a box's tipping edge, at height z and the face's width w
    from the axis: ``z + mu w``; its normal alone is ``atan(w / z)`` off its motion.)

    Parameters
    ----------
    p_W, n_W : (C, 3) contact points and outward unit normals (W).
    p_axis, a_axis : (3,) a point of the axis and its unit direction, right-handed in the rotation's sense.

    Returns ``(C,)`` m.
    """
    m = np.cross(a_axis, p_W - p_axis)
    n_in = -n_W
    along = np.einsum("ij,ij->i", n_in, m)
    return along + mu * np.linalg.norm(m - along[:, None] * n_in, axis=1)


def tip_angle(model, roll: poses.Roll) -> float:
    """The roll angle (rad) at which the CoM crosses over the axis (its highest point along ``roll``)."""
    grid = np.linspace(0.0, roll.total, 721)
    return float(grid[np.argmax(se3.transform_points(roll.poses(grid), model.com)[:, 2])])


def release_angle(model, roll: poses.Roll, params: Params) -> float:
    """The pusher's release angle along ``roll`` (rad): ``push_angle``, and at least ``release_past_tip``
    past the tip (:func:`tip_angle`), at most the landing."""
    return min(max(params.push_angle, tip_angle(model, roll) + params.release_past_tip), roll.total)


def pusher_motion(robot, collide, model, Xa, Xb, e0, e1, pc, nc, r, params: Params, limits: PushLimits,
                  arms=("left", "right")):
    """A ball that can push the object over hull edge (e0, e1) from ``Xa`` toward ``Xb`` (§5.2.2).

    Returns ``(arm, contact, q (T, n))`` for the first that works, or ``(None, reason, None)``; see
    :func:`pusher_motions`, which does this for many tumbles at once.
    """
    return pusher_motions(robot, collide, model, Xa[None], Xb[None], np.array([[e0, e1]]), pc, nc, r, params,
                          limits, arms)[0]


class _PushRows(NamedTuple):
    """Pusher candidates of K tumbles: ``rows (R, 4)`` (tumble, arm index, contact, rank) and the push
    each would follow, ``X_push (K, S, 4, 4)`` (zeros where the tumble has no roll), and the reason
    ``why (K,)`` of a tumble that has no candidate."""

    rows: np.ndarray
    X_push: np.ndarray
    why: np.ndarray


def _push_candidates(model, Xa, Xb, edges, pc, nc, params: Params, limits: PushLimits, arms) -> _PushRows:
    """The candidates of :func:`pusher_motions`: per tumble, its roll (``poses.roll_segments``, which
    must land on ``Xb``) and the push along it to :func:`release_angle` at most ``push_step`` apart (the
    last pose repeated to the longest push's length); per arm, the contacts on its side of the object,
    not under it, whose best push (:func:`push_levers`, about the roll's first axis at the start)
    overcomes the weight's moment about that axis within the force bound (the catcher's ball, on the
    landing face, can only resist the turn). Those that start the tumble alone on the edge's friction
    (:func:`tip_holds`: a drop needs it; with a catcher, whose ball may take the push's horizontal part,
    the others may do) come first, then the others; each best first: largest moment less half the
    contact's offset from the CoM along the axis (as the catchers of ``stages.trajectory``): a push off
    the CoM's line twists the object on its edge (Exp. 3's piano pushed 9 cm off it slid 19 mm on its
    edge in PyBullet, 4.5 mm pushed in line)."""
    K = len(Xa)
    why, pushes = np.full(K, "no_pusher_contact", dtype=object), [None] * K
    found = []  # (tumble, its lever-passing contacts, their rank scores (C,), contacts (C, 3) W)
    tips = ([], [], [], [])  # CoM, edge, contact point and normal of every lever-passing contact (W)
    for k in range(K):  # a few hundred tumbles: geometry only, the IK and collisions are batched after
        try:
            roll = poses.roll_segments(model, Xa[k], int(edges[k, 0]), int(edges[k, 1]))
        except InputError:
            roll = None
        if roll is None or np.abs(roll.X_end - Xb[k]).max() > 1e-5:  # as stages.trajectory requires
            why[k] = "not_a_tumble"
            continue
        th_r = release_angle(model, roll, params)
        pushes[k] = roll.poses(np.linspace(0.0, th_r, int(np.ceil(th_r / params.push_step - 1e-9)) + 1))
        p_W = se3.transform_points(Xa[k], pc)
        n_W = se3.rotate_vectors(Xa[k], nc)
        a = roll.a_axis[0]
        lever = push_levers(p_W, n_W, roll.p_axis[0], a, limits.mu)
        com = se3.transform_points(Xa[k], model.com)
        weight_moment = limits.weight * np.cross(a, com - roll.p_axis[0])[2]  # what the push must overcome
        good = np.flatnonzero((lever * limits.f_max > weight_moment) & (lever > 0.0) & (n_W[:, 2] > -0.5))
        found.append((k, good, lever - 0.5 * np.abs((p_W - com) @ a), p_W))
        edge = se3.transform_points(roll.X_seg[0], model.vertices[roll.edge[0]])
        for acc, x in zip(tips, (np.broadcast_to(com, (len(good), 3)), np.broadcast_to(edge, (len(good), 2, 3)),
                                 p_W[good], n_W[good]), strict=True):
            acc.append(x)
    holds = tip_holds(*(np.concatenate(x) for x in tips), limits, params.threads) if found else np.zeros(0, bool)
    rows, i0, n = [], 0, params.push_candidates
    for k, good, score, p_W in found:
        ok, i0 = holds[i0:i0 + len(good)], i0 + len(good)
        order = np.lexsort((-score[good], ~ok))  # those that start the tip alone first, each best first
        ranked, tip = good[order], ok[order]
        for j, arm in enumerate(("left", "right")):
            if arm not in arms:
                continue
            side = p_W[ranked, 1] >= Xa[k][1, 3] if arm == "left" else p_W[ranked, 1] <= Xa[k][1, 3]
            r, t = ranked[side], tip[side]
            pick = np.concatenate([spread(r[t], n), spread(r[~t], max(n - int(t.sum()), 0))])
            rows += [(k, j, int(c), rank) for rank, c in enumerate(pick)]
    S = max([len(x) for x in pushes if x is not None], default=1)
    X_push = np.zeros((K, S, 4, 4))
    for k, x in enumerate(pushes):
        if x is not None:
            X_push[k] = np.concatenate([x, np.repeat(x[-1:], S - len(x), axis=0)])
    return _PushRows(np.array(rows, dtype=np.int64).reshape(-1, 4), X_push, why)


def spread(ranked: np.ndarray, n: int) -> np.ndarray:
    """``n`` of the ``ranked`` candidates, best first, evenly spaced in rank: neighbouring contacts
    of one face rank alike and fail alike (the same reach, the same collision), so the best ``n`` are
    one bet where the spread are ``n``."""
    if len(ranked) <= n:
        return ranked
    return ranked[np.unique(np.round(np.linspace(0, len(ranked) - 1, n)).astype(np.int64))]


def pusher_motions(robot, collide, model, Xa, Xb, edges, pc, nc, r, params: Params, limits: PushLimits,
                   arms=("left", "right")):
    """Pushers for K tumbles at once: ``Xa, Xb (K, 4, 4)``, ``edges (K, 2)`` hull vertex ids.

    A necessary condition, cheap, for the tumbling MPC that ``pivot plan`` then runs on the tumbles it
    walks (``stages.trajectory.check_tumble``): candidate contacts (``pc``, ``nc``: all contacts and
    outward normals, O) are those whose push within the ball's friction cone and force bound
    (``limits``) turns the object over the edge against its weight (:func:`push_levers`: no fixed cone
    about the contact's motion, which refused the push a person makes on a box's far side face), on
    the arm's side of the object, best first (``push_candidates`` per arm; :func:`_push_candidates`).
    A tumble's candidates are followed along the roll (``poses.roll_segments``) to
    :func:`release_angle`, where ``stages.trajectory`` lets go, with IK from a fresh solution, the ball
    turning with the object as ``stages.trajectory`` moves it (``stages.robot.follow_ik``), and
    checked for collisions, the other arm at its rest posture (its ball may meet the object: it is the
    one that catches), in order until one works: in waves over all tumbles (1, 2, 4, ... candidates
    of each), one batch per arm each (:func:`_check_pushers`).

    Returns a list of K ``(arm, contact, q (T, n))`` for the first candidate that works (left before
    right, then best first; the last rows of ``q`` may repeat the release pose's), or ``(None, reason,
    None)`` with the most common failure (``no_pusher_contact`` when no contact can push,
    ``not_a_tumble`` when the edge does not roll ``Xa`` onto ``Xb``).
    """
    K = len(Xa)
    cand = _push_candidates(model, Xa, Xb, edges, pc, nc, params, limits, arms)
    rows = cand.rows
    status = np.full(len(rows), "no_pusher_contact", dtype=object)
    q_path: list = [None] * len(rows)
    # Each tumble's candidates in order (left before right, then best first), checked in waves of 1,
    # 2, 4, ... a tumble's next ones while none before them worked. Each check depends on its row
    # alone, so the first that works is the one a check of all would pick, at a fraction of the checks.
    order = [mine[np.lexsort((rows[mine, 3], rows[mine, 1]))] for mine in
             np.split(np.argsort(rows[:, 0], kind="stable"), np.cumsum(np.bincount(rows[:, 0], minlength=K))[:-1])]
    pos, size = np.zeros(K, np.int64), 1
    while wave := [order[k][pos[k]:pos[k] + size] for k in range(K) if pos[k] < len(order[k])]:
        _check_pushers(robot, collide, cand, np.concatenate(wave), pc, nc, r, params, status, q_path)
        for w in wave:
            k = rows[w[0], 0]
            pos[k] = len(order[k]) if np.any(status[w] == "ok") else pos[k] + size
        size *= 2
    out = []
    for k in range(K):
        win = [i for i in order[k] if status[i] == "ok"]
        if win:
            i = win[0]
            out.append(("left" if rows[i, 1] == 0 else "right", int(rows[i, 2]), q_path[i]))
            continue
        if len(order[k]) == 0:
            out.append((None, str(cand.why[k]), None))
            continue
        vals, counts = np.unique(np.array([str(x) for x in status[order[k]]]), return_counts=True)
        out.append((None, str(vals[np.argmax(counts)]), None))
    return out


def _check_pushers(robot, collide, cand: _PushRows, sel: np.ndarray, pc, nc, r, params: Params, status: np.ndarray,
                   q_path: list) -> None:
    """Check the pusher candidate rows ``sel`` of ``cand`` (:func:`pusher_motions`), one batch per arm:
    IK of the ball at the push's first pose from a fresh solution, then the push with the ball turning
    with the object (``follow_ik``) and its collisions, the other arm at rest. Writes each row's
    ``status`` and, where ok, its joints ``q_path`` (T, n)."""
    rows = cand.rows
    for j, arm in enumerate(("left", "right")):
        s = sel[rows[sel, 1] == j]
        if len(s) == 0:
            continue
        k, c = rows[s, 0], rows[s, 2]
        X0 = cand.X_push[k, 0]
        seed = robot.ik(arm, se3.transform_points(X0, pc[c] + r * nc[c]), rng=np.random.default_rng(0), restarts=1,
                        tol=params.ik_tol)
        status[s[~seed.ok]] = seed.reason[~seed.ok]
        s, k, c, q0 = s[seed.ok], k[seed.ok], c[seed.ok], seed.q[seed.ok]
        other = robot.arm("right" if arm == "left" else "left")
        q0_both = np.repeat(other.q_rest[None, None], len(s), axis=0).repeat(2, axis=1)
        q0_both[:, j] = q0
        p_O = np.repeat(pc[c][:, None], 2, axis=1)
        n_O = np.repeat(nc[c][:, None], 2, axis=1)
        active = (True, False) if arm == "left" else (False, True)
        ok, why, q = check_arm_motion(robot, collide, cand.X_push[k], p_O, n_O, q0_both, r, params, active=active,
                                      touching=(True, True), follow=True)  # the idle ball may catch
        status[s] = why
        for i in np.flatnonzero(ok):
            q_path[s[i]] = q[:, i, j]


NODE_FIELDS = [Field("node_id", "id"), Field("kind"), Field("pose_id", "id"), Field("grasp_id", "id"),
               Field("support")]
CATCH_FIELDS = [Field("node_id", "id"), Field("kind"), Field("pose_id", "id"), Field("arm"), Field("contact", "id"),
                Field("status"), Field("q", "rad")]
EDGE_FIELDS = [Field("edge_id", "id"), Field("node_a", "id"), Field("node_b", "id"), Field("primitive"),
               Field("weight"), Field("status"), Field("directed"), Field("vertex", "id"), Field("edge_v0", "id"),
               Field("edge_v1", "id"), Field("arm")]


def run(scene_path, analysis_dir, sample_dir, out_dir, params: Params, producer: str = "graph") -> Graph:
    """Build the graph of ``scene_path`` from its analysis and samples; write it into ``out_dir``."""
    scene = load_scene(scene_path)
    provenance.check_sample(sample_dir, scene, analysis_dir)
    graph = build_graph(scene, analysis_dir, sample_dir, params)
    out = Path(out_dir)
    meta_params = {**{k: v for k, v in asdict(params).items() if k not in ("threads", "pivot_chunk")},
                   "weights": asdict(scene.planner.weights), "tilt": scene.planner.tilt}
    inputs = {"scene": scene_path, "poses": Path(sample_dir) / "poses.parquet",
              "grasps": Path(sample_dir) / "grasps.parquet", "pose_links": Path(sample_dir) / "pose_links.parquet"}
    artifacts.write_table(out / "nodes.parquet", graph.nodes, NODE_FIELDS,
                          artifacts.make_meta("nodes", meta_params, inputs, producer))
    artifacts.write_table(out / "edges.parquet", graph.edges, EDGE_FIELDS,
                          artifacts.make_meta("edges", meta_params, inputs, producer))
    artifacts.write_table(out / "catches.parquet", {**graph.catches, "q": list(graph.catches["q"])}, CATCH_FIELDS,
                          artifacts.make_meta("catches", meta_params, inputs, producer))
    artifacts.write_json(out / "graph.json", graph.summary, artifacts.make_meta("graph", meta_params, inputs, producer))
    artifacts.write_timings(out / "graph.json", graph.timings)
    stagelog.log_graph(graph.summary, graph.edges)
    return graph
