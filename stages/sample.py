"""Stage ``sample``: object poses on the table and the feasible grasps of each (§4.2, §4.3, §5.1).

Reads the scene and the analysis; writes

- ``poses.parquet``: the pose lattice of ``stages.poses`` (pivoting by θ_t about support corners,
  tumbling over support edges; SP and USP; rejected poses kept with their status; the scene's
  obstacles and the robot's base and torso are the obstacles),
- ``pose_links.parquet``: the pivot and tumble links between kept poses,
- ``grasps.parquet``: per kept pose, every contact pair (left ball on the pair's contact with the
  larger world y, right ball on the other) that passes the grasp refinement of §4.2–4.3, with both
  arms' joint vectors and the stability margins,
- ``grasp_rejects.parquet``: every refused (pose, pair) candidate with its reason code,
- ``sample.json``: counts per status and reason, and ``face_route``: the placements of the fewest
  tumbles from the start's face to the goal's (``poses.face_route``; ``[]`` when no sequence of tumbles
  leads there, which the plan's diagnosis reports as such) and ``walk_joins``, the joins the lattice
  made by a pivot walk (``poses.Params.walk_strides``).

A start or goal that cannot be a pose (``poses.describe_pose``: off the table's edge, unstable, or
in an obstacle or the robot's trunk) is bad input: an ``InputError`` that names what it hits.

Grasp refinement, cheapest test first, all batched over the (pose, pair) candidates:

1. ``eef_under_object``: a contact whose outward normal points down (the ball would be under the
   object, Fig. 5 r1/r2), or ``env_collision:ball/table``: a ball centre too close to the table;
2. ``normal_away``: a contact normal facing away from its arm's shoulder (Fig. 5 r3/r4);
3. ``env_collision:<first link>/object``: the object, in that pose, overlaps a part of an arm that
   no posture moves (``CollisionFn.object_blocks_arm``: link 1 only turns about its own axis), so
   every candidate of the pose collides whatever its IK (one test per pose);
4. ``ik_unreachable`` / ``joint_limit``: batched position IK of each ball centre (``stages.robot``);
5. ``env_collision:*`` / ``self_collision:*`` / ``object_clearance:*``: the arms against the table,
   obstacles, object (their links kept ``arm_clearance``, the sticks ``stick_clearance``, from it) and
   each other; a colliding candidate gets new IK solutions (from other library postures near its
   target), for the arms the colliding pair involves, up to ``collision_retries`` times;
6. ``unstable``: the stability LP (``stages.stability``, eq. 1–4): in SP the object must stay in
   equilibrium on at least one support corner alone with both balls (a pivot can start); in USP
   the on-table support vertices and both balls must hold it, with its CoM the SP margin further out
   (``poses.held_com``: a USP pose just inside that margin is not held by a ball that does not
   push). The margin recorded is, in SP, the pivot margin on the first support corner (in hull
   vertex order) that holds, in USP the margin of holding with both balls; ``hold_left`` /
   ``hold_right`` say whether that ball alone holds the USP with ``Params.hold_friction_safety`` of
   the table's friction and ``Params.hold_eef_friction`` of the ball's (which a regrasp in USP
   needs, §5.2.2; a verdict only, its margin is never used).
   ``pivot_vertices`` are the support corners on the table on which the object stays in equilibrium
   with both balls, with ``pivot_friction_safety`` and ``pivot_force_safety``, both at the start of
   the tilt (the other corners just lifted, the CoM at its full offset from the corner: the hardest
   instant, which the plan's pivot MPC meets with the same friction and force) and at the pivot's full
   tilt (``mpc.pivot_reference``): the graph stage's test of a pivot edge, so that a pivot no shared
   grasp lists is refused before its arm motion is checked, not after its MPC.
   Every pose of a placement is its resting pose turned about the vertical and shifted, and the
   stability LP is invariant under that motion, so the pivot tests are solved once per (placement,
   pair, corner) and shared by all poses of the placement.

Grasp-aware reach (``Params.reach_rounds``, our addition): the lattice is laid out before any grasp
is known. When the start does not reach the goal along links whose grasps pass the graph stage's
checks (LazySP over the lattice, :func:`lazy_reach`), it grows on from the poses the start does reach,
pivoting them only about the corners their grasps hold, and the new poses' grasps are refined; the
artifacts hold every round's poses and grasps, and ``sample.json`` the rounds grown. When the rounds
leave the goal unreached, pivot walks join the two sides as a last resort (``poses.walk_lattice``,
``sample.json``'s ``walk_joins``): only then, since a walk's long pivot chains replace routes that
plan without them.
"""

from __future__ import annotations

import functools
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import networkx as nx
import numpy as np

from stages import artifacts, poses, provenance, se3, stability, stagelog
from stages.artifacts import Field
from stages.errors import InputError
from stages.objectmodel import load_object_model
from stages.robot import IKParams, load_robot, make_collision_fn
from stages.scene import ObstacleGeometry, PlacementSpec, Scene, load_scene


@dataclass(frozen=True)
class Params:
    """Sampling and grasp-refinement parameters not in the scene (m, rad)."""

    #: Ball centres closer than this to the table top are refused (m).
    table_clearance: float = 0.01
    #: A contact normal whose z component is below this points under the object.
    under_nz: float = -0.5
    #: A contact normal is "away" when its horizontal part turns more than this from the shoulder (rad):
    #: Fig. 5's r3/r4, "too far to be reached". Only a prefilter: the IK and the arms' collision checks
    #: (with ``arm_clearance``) decide reach; at 120 deg it refused every grasp of a box turned 45 deg in place.
    away_angle: float = np.radians(150.0)
    #: The arms' links keep this far from the object (m), the sticks that carry the balls
    #: ``stick_clearance``, in every check of the planner (the grasps here; pivots, tumbles, holds and
    #: transits read them from ``grasps.parquet``), or fail as ``object_clearance``; and as far from the
    #: table and the obstacles, or fail as ``env_collision``. Physics counts a
    #: robot-object contact from where Bullet reports contact points: 3.6 mm apart for the arm's
    #: 45-101 mm capsules, 1.0 mm for the 8 mm stick (against the object's hulls, measured); its
    #: compliant arms came up to 3.0 mm (links) and 2.7 mm (sticks) closer to the object than planned
    #: while the object kept to its plan.
    arm_clearance: float = 0.007
    stick_clearance: float = 0.004
    #: IK tolerance (m) and restarts.
    ik_tol: float = 1e-3
    ik_restarts: int = 2
    #: New IK solutions tried for a candidate whose first solution collides, each from the next
    #: seed-library posture near its target (after those of the IK restarts) jittered by
    #: ``retry_jitter`` (rad, std). One round recovers about as many candidates on the default scene
    #: as three rounds from random postures around the rest posture did (7138 vs 7239 grasps).
    collision_retries: int = 1
    retry_jitter: float = 0.3
    #: A ball alone holds a USP pose (``hold_*``) with this fraction of the table's friction, the
    #: one the MPC plans with (``stages.plan.Params.friction_safety``): a hold at the friction limit
    #: tips in physics at the least disturbance (Exp. 3's hand-over, seed 1).
    hold_friction_safety: float = 0.8
    #: ... and its ball with only this fraction of the object's friction: a hold that needs the
    #: ball's friction (a ball on an inboard side face dragging it down, 0.4 of the force tangential)
    #: tipped the piano in physics once the other ball let go, although the ball pressed with the
    #: planned force (likely it rolls on the face, its wrist holding its orientation only
    #: compliantly; not measured); holds by the normal force (a ball under the overhang, on the
    #: outboard face, pressing on the top inboard) stood.
    hold_eef_friction: float = 0.3
    #: Corner clustering and tumble edge length of the pose sampler (m).
    corner_cluster: float = 0.03
    min_tumble_edge: float = 0.05
    #: A grasp's ``pivot_vertices`` hold at the pivot's full tilt with this fraction of the friction and
    #: of the ball force bound: ``graph.Params.friction_safety`` and ``force_safety``, the graph's test.
    pivot_friction_safety: float = 0.8
    pivot_force_safety: float = 0.9
    #: Grasp-aware reach (our addition to §5.1): while the goal is not reached from the start by links
    #: whose grasps pass the graph stage's checks (:func:`lazy_reach`), the lattice grows on from the
    #: poses the start reaches toward those the goal reaches (``poses.extend_lattice``) by
    #: ``reach_share`` of ``max_poses`` kept poses, and the new poses get their grasps, up to
    #: ``reach_rounds`` times. The lattice is laid out before any grasp is known, so it may reach the
    #: goal only through corners no reachable grasp holds (a short T-shaped block: 46 % of its pivot
    #: links); a lattice that reaches it with grasps is left as it is.
    reach_rounds: int = 3
    reach_share: float = 0.25
    #: LazySP walks per round before the goal counts as not reached (each checks the pivots of one
    #: shortest lattice path as the graph stage will).
    reach_walks: int = 30
    #: Worker threads for IK, collision checks and stability LPs (numpy releases the GIL in its
    #: kernels); every candidate's result is the same for any number. On the project's 2-core VM two
    #: threads made the collision checks ~8 % faster but IK and the stability LPs 15-20 % slower
    #: (their arrays are small, so the threads mostly wait for the GIL), hence 1.
    threads: int = 1


@dataclass(frozen=True)
class Result:
    poses: poses.PoseSet
    grasps: dict
    rejects: dict
    summary: dict
    timings: dict


def placement_pose(spec: PlacementSpec, model: poses.ObjectModel, where: str) -> tuple[np.ndarray, int]:
    """``(X_WO (4, 4), placement id)`` of a scene's start or goal placement."""
    if spec.placement is not None:
        g = int(spec.placement)
        if g >= len(model.X_TO):
            raise InputError(f"{where}.placement: {g} is not a placement id (the analysis has {len(model.X_TO)})")
    else:
        g = int(np.argmax(model.normals @ spec.down_unit))
    X = se3.make_transform(se3.rot_z(spec.yaw), np.array([spec.xy[0], spec.xy[1], 0.0])) @ model.X_TO[g]
    return X, g


def trunk_obstacles(robot) -> list[ObstacleGeometry]:
    """The robot's base and torso boxes as obstacles for the object: a pose must not reach into the
    robot (the arms' own checks leave the object out of the trunk's)."""
    st = robot.static
    return [ObstacleGeometry(name=f"robot:{n}", kind="box", X_WOb=np.asarray(X, float), size=tuple(2.0 * h))
            for n, X, h in zip(st.box_names, st.box_X_W, st.box_half, strict=True)]


def make_scene_collision_fn(scene: Scene, robot, object_mesh, threads: int = 1,
                            clearance: tuple[float, float] = (0.0, 0.0)):
    """The robot's batched collision checker against the scene's table, obstacles and the object, its
    links kept ``clearance = (arm, stick)`` (m, ``Params.arm_clearance``, ``stick_clearance``) from it."""
    obstacles = []
    for ob in scene.obstacle_geometries():
        dims = {"box": ob.size, "cylinder": (ob.radius, ob.height), "mesh": (ob.vertices, ob.faces)}[ob.kind]
        obstacles.append((ob.kind, dims, ob.X_WOb, ob.name))
    return make_collision_fn(robot, (tuple(scene.table.size), 0.0), obstacles, object_mesh,
                             table_depth=scene.table.height, threads=threads, link_clearance=clearance[0],
                             tool_clearance=clearance[1])


def clearance_of(params: dict) -> tuple[float, float]:
    """``(arm_clearance, stick_clearance)`` (m) from an artifact's parameters (``grasps.parquet``'s, which
    the grasps were checked with, or ``plan.json``'s), for the later stages' checks; 0 when absent."""
    return float(params.get("arm_clearance", 0.0)), float(params.get("stick_clearance", 0.0))


def _prefilter(scene, robot, collide, params: Params, X_kept: np.ndarray, points: tuple, normals: tuple,
               balls: tuple) -> np.ndarray:
    """The cheap refusals of grasp candidates before any IK (module docstring, steps 1-3), one reason
    code per candidate ("" where none): a ball under the object but over the table, a ball in the
    table, a contact normal facing away from its arm, and the poses ``X_kept`` where the object
    overlaps a part of an arm no posture moves. Candidates are pose-major (every pair of each pose of
    ``X_kept``); ``points``, ``normals``, ``balls`` are the (left, right) contact points, outward
    normals and ball centres (W, m)."""
    (p_l, p_r), (n_l, n_r), (ball_l, ball_r) = points, normals, balls
    r = scene.robot.ball_radius
    reason = np.full(len(p_l), "", dtype=object)

    def refuse(mask, why):
        new = mask & (reason == "")
        reason[new] = why

    # A ball beyond the table's edge (in plan view) is under nothing but the object: in USP it may
    # hold the overhang from below (Fig. 14's catcher on its grasp contact).
    half = np.asarray(scene.table.size) / 2
    clear_l, clear_r = (np.max(np.abs(b[:, :2]) - half, axis=1) >= r + params.table_clearance
                        for b in (ball_l, ball_r))
    refuse(((n_l[:, 2] < params.under_nz) & ~clear_l) | ((n_r[:, 2] < params.under_nz) & ~clear_r),
           "eef_under_object")
    refuse(((ball_l[:, 2] < r + params.table_clearance) & ~clear_l) |
           ((ball_r[:, 2] < r + params.table_clearance) & ~clear_r), "env_collision:ball/table")
    for arm, p, n in (("left", p_l, n_l), ("right", p_r, n_r)):
        s = robot.arm(arm).reach_centre
        to_s = s[:2] - p[:, :2]
        cos = np.einsum("ij,ij->i", n[:, :2], to_s) / np.maximum(
            np.linalg.norm(n[:, :2], axis=1) * np.linalg.norm(to_s, axis=1), 1e-12)
        flat = np.linalg.norm(n[:, :2], axis=1) < 0.3  # a top face is reached from above
        refuse(~flat & (cos < np.cos(params.away_angle)), "normal_away")
    # Poses where the object overlaps a part of an arm that no posture moves out of it: every
    # candidate of the pose collides, whatever its IK (one check per pose).
    blocked, why = collide.object_blocks_arm(X_kept)
    K = len(p_l) // max(len(X_kept), 1)
    hit = np.repeat(blocked.any(axis=1), K) & (reason == "")
    reason[hit] = np.repeat(why, K)[hit]
    return reason


#: Rows of the table of IK jitters a collision retry draws per call (:func:`_collide_with_retries`).
RETRY_ROWS = 4096


def _target_rows(p_W: np.ndarray, rows: int) -> np.ndarray:
    """``(N,)`` a row in ``[0, rows)`` for each target ``p_W (N, 3)`` (m), from its coordinates to 0.01 mm
    (a multiplicative hash: the same target, the same row, on any machine)."""
    k = np.round(np.asarray(p_W) * 1e5).astype(np.int64).astype(np.uint64)
    h = (k[:, 0] * np.uint64(0x9E3779B97F4A7C15)) ^ (k[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)) \
        ^ (k[:, 2] * np.uint64(0x165667B19E3779F9))
    return ((h >> np.uint64(33)) % np.uint64(rows)).astype(np.int64)


def _collide_with_retries(robot, collide, params: Params, rng, X: np.ndarray, balls: tuple, qs: tuple,
                          cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Collisions of the arms with the table, obstacles, the object and each other for candidates
    ``cand`` (poses ``X``, ball centres ``balls`` = (left, right) (n, 3) W, joints ``qs`` = (left,
    right), updated in place); returns the rows that still collide and their reasons. The IK knows
    nothing of obstacles, so a colliding candidate gets more IK solutions, from other comfortable
    library postures near its target (collision-aware IK by retry, ``collision_retries`` times), before
    it is refused. Only the arms that the colliding pair involves are solved again (the other keeps its
    solution), and only the rows that got a new solution are checked again: the check of a row depends
    on its joints."""
    q_l, q_r = qs
    # Each target's jitter is a row of one table drawn per call, picked by the target itself: a
    # candidate's grasp does not depend on which others share its batch.
    jitter = rng.normal(0.0, params.retry_jitter, (params.collision_retries, RETRY_ROWS, q_l.shape[1]))
    touching = np.ones((len(cand), 2), bool)
    ok, why, blame = collide(q_l[cand], q_r[cand], X[cand], touching, blame=True)
    failed, why, blame = cand[~ok], why[~ok].astype(object), blame[~ok]
    for attempt in range(params.collision_retries):
        if len(failed) == 0:
            break
        moved = np.zeros(len(failed), bool)
        for s, (arm, ball, q) in enumerate(zip(("left", "right"), balls, qs, strict=True)):
            a = robot.arm(arm)
            redo = np.flatnonzero(blame[:, s])
            seed = robot.library_seeds(arm, ball[failed[redo]], 1 + params.ik_restarts + attempt)
            seed = np.clip(seed + jitter[attempt, _target_rows(ball[failed[redo]], len(jitter[attempt]))],
                           a.lower, a.upper)
            res = robot.ik(arm, ball[failed[redo]], q_seed=seed, rng=rng, restarts=0, tol=params.ik_tol)
            q[failed[redo[res.ok]]] = res.q[res.ok]
            moved[redo[res.ok]] = True
        m = np.flatnonzero(moved)
        ok, why[m], blame[m] = collide(q_l[failed[m]], q_r[failed[m]], X[failed[m]], touching[:len(m)], blame=True)
        keep = np.ones(len(failed), bool)
        keep[m[ok]] = False
        failed, why, blame = failed[keep], why[keep], blame[keep]
    return failed, why


def refine_grasps(scene: Scene, model: poses.ObjectModel, tables: dict, ps: poses.PoseSet, robot, collide,
                  params: Params, rng: np.random.Generator,
                  pose_ids: np.ndarray | None = None) -> tuple[dict, dict, dict]:
    """Grasp refinement (see the module docstring) over every kept pose (of ``pose_ids`` when given) ×
    contact pair.

    Returns ``(grasps, rejects, timings)`` column dicts.
    """
    timings = {}
    t0 = time.perf_counter()
    con, pairs = tables["contacts"], tables["pairs"]
    p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    r = scene.robot.ball_radius
    kept = np.flatnonzero(ps.status == "ok")
    if pose_ids is not None:
        kept = np.intersect1d(kept, pose_ids)
    P, K = len(kept), len(pairs)
    pose_idx = np.repeat(kept, K)
    pair_idx = np.tile(np.arange(K), P)
    X = ps.X_WO[pose_idx]
    ca, cb = pairs["contact_a"][pair_idx], pairs["contact_b"][pair_idx]
    pa, pb = se3.transform_points(X, p_O[ca]), se3.transform_points(X, p_O[cb])
    # The left ball takes the contact with the larger world y (arms do not cross).
    swap = pa[:, 1] < pb[:, 1]
    c_left, c_right = np.where(swap, cb, ca), np.where(swap, ca, cb)
    p_l, p_r = se3.transform_points(X, p_O[c_left]), se3.transform_points(X, p_O[c_right])
    n_l, n_r = se3.rotate_vectors(X, n_O[c_left]), se3.rotate_vectors(X, n_O[c_right])
    ball_l, ball_r = p_l + r * n_l, p_r + r * n_r
    reason = _prefilter(scene, robot, collide, params, ps.X_WO[kept], (p_l, p_r), (n_l, n_r), (ball_l, ball_r))
    t1 = time.perf_counter()

    # IK for both arms on the candidates still alive.
    q_l = np.zeros((len(X), robot.arm("left").dof))
    q_r = np.zeros((len(X), robot.arm("right").dof))
    live = np.flatnonzero(reason == "")
    for arm, ball, q in (("left", ball_l, q_l), ("right", ball_r, q_r)):
        res = robot.ik(arm, ball[live], rng=rng, restarts=params.ik_restarts, tol=params.ik_tol)
        q[live] = res.q
        bad = ~res.ok
        reason[live[bad & (reason[live] == "")]] = res.reason[bad & (reason[live] == "")]
        live = np.flatnonzero(reason == "")
    t2 = time.perf_counter()

    failed, why = _collide_with_retries(robot, collide, params, rng, X, (ball_l, ball_r), (q_l, q_r),
                                        np.flatnonzero(reason == ""))
    reason[failed] = why
    t3 = time.perf_counter()

    # Stability.
    live = np.flatnonzero(reason == "")
    margins = _stability(scene, model, tables, ps, pose_idx[live], pair_idx[live], X[live], p_l[live], p_r[live],
                         n_l[live], n_r[live], params)
    refuse_live = ~margins["stable"]
    reason[live[refuse_live]] = "unstable"
    t4 = time.perf_counter()
    timings.update(prefilter=t1 - t0, ik=t2 - t1, collision=t3 - t2, stability=t4 - t3, refine=t4 - t0)

    good, g_sel, bad = live[~refuse_live], ~refuse_live, np.flatnonzero(reason != "")
    ids = {"pose_id": pose_idx, "pair_id": pair_idx, "contact_left": c_left, "contact_right": c_right}
    grasps = {"grasp_id": np.arange(len(good)), **{k: v[good].astype(np.int64) for k, v in ids.items()},
              **{k: margins[k][g_sel] for k in ("margin", "hold_left", "hold_right")},
              "pivot_vertices": [v for v, s in zip(margins["pivot_vertices"], g_sel, strict=True) if s],
              "q_left": list(q_l[good]), "q_right": list(q_r[good])}
    rejects = {"pose_id": pose_idx[bad].astype(np.int64), "pair_id": pair_idx[bad].astype(np.int64),
               "reason": np.array([str(x) for x in reason[bad]], dtype=str)}
    return grasps, rejects, timings


def link_candidates(ps: poses.PoseSet, grasps: dict, tumbles: bool) -> dict[int, list[tuple[int, int]]]:
    """Per link a grasp could make, its candidates as the graph stage forms them: for a pivot link the
    grasp pairs ``(grasp at a, grasp at b)`` with one contact on each ball at both poses and the link's
    vertex among both grasps' ``pivot_vertices`` (its first test, §5.2.1); with ``tumbles``, a tumble
    link out of an SP pose that has grasps, ``[(-1, -1)]`` (its pusher is found by the graph stage; a
    goal on the start's placement is reached by pivots alone). Links without any are left out."""
    key = {}
    for gi, (p, cl, cr) in enumerate(zip(grasps["pose_id"].tolist(), grasps["contact_left"].tolist(),
                                         grasps["contact_right"].tolist(), strict=True)):
        key.setdefault(p, {})[(cl, cr)] = gi
    piv = [set(np.asarray(v).tolist()) for v in grasps["pivot_vertices"]]
    out = {}
    for li, ((a, b), prim, v) in enumerate(zip(ps.links.tolist(), ps.link_primitive.tolist(),
                                                ps.link_vertex.tolist(), strict=True)):
        if prim == "tumble":
            if tumbles and a in key and ps.support[a] == "SP":
                out[li] = [(-1, -1)]
            continue
        ga, gb = key.get(a, {}), key.get(b, {})
        found = [(i, gb[k]) for k, i in ga.items() if k in gb and v in piv[i] and v in piv[gb[k]]]
        if found:
            out[li] = found
    return out


def held_corners(grasps: dict) -> dict[int, np.ndarray]:
    """Per pose with grasps, the hull vertex ids some grasp there can pivot about (``pivot_vertices``)."""
    by_pose: dict[int, list] = {}
    for p, vs in zip(grasps["pose_id"].tolist(), grasps["pivot_vertices"], strict=True):
        by_pose.setdefault(p, []).extend(np.asarray(vs).tolist())
    return {p: np.unique(np.array(v, dtype=np.int64)) for p, v in by_pose.items()}


def reach_graph(ps: poses.PoseSet, cands: dict) -> nx.DiGraph:
    """The kept poses (nodes) and the links of ``cands`` (:func:`link_candidates`) between them (arcs,
    their link ids in ``links``): a pivot both ways (it turns back about the same corner), a tumble
    only from its pose ``a`` to its landing ``b``, the way its pusher was found (rolling back over the
    edge is another link, with its own pusher)."""
    G = nx.DiGraph()
    G.add_nodes_from(np.flatnonzero(ps.status == "ok").tolist())
    for li in sorted(cands):
        a, b = ps.links[li].tolist()
        for u, v in ((a, b), (b, a)) if ps.link_primitive[li] == "pivot" else ((a, b),):
            if G.has_edge(u, v):
                G.edges[u, v]["links"].append(li)
            else:
                G.add_edge(u, v, links=[li])
    return G


def lazy_reach(G: nx.DiGraph, goal: int, cands: dict, check, verified: dict, walks: int) -> bool:
    """LazySP (Dellin & Srinivasa) on the lattice: whether the goal is reached from pose 0 along links
    one of whose candidates passes ``check`` (candidates ``(n, 3)`` (grasp a, grasp b, link) -> status
    ``(n,)``, the graph stage's checks), checking only the shortest path's untested candidates each walk, up to
    ``walks`` walks (then False: undecided). ``verified`` caches (grasp a, grasp b, link) -> ok across
    calls; links all of whose candidates failed are removed from ``G``."""
    for _ in range(walks):
        try:
            path = nx.shortest_path(G, 0, goal)
        except nx.NetworkXNoPath:
            return False
        on_path = [li for a, b in zip(path, path[1:], strict=False) for li in G.edges[a, b]["links"]]
        todo = [(ga, gb, li) for li in on_path for ga, gb in cands[li] if (ga, gb, li) not in verified]
        if todo:
            for key, st in zip(todo, check(np.array(todo, dtype=np.int64)), strict=True):
                verified[key] = st == "ok"
        cut = False
        for a, b in zip(path, path[1:], strict=False):
            for u, v in ((a, b), (b, a)):  # a failed pivot is cut both ways
                if not G.has_edge(u, v):
                    continue
                links = G.edges[u, v]["links"]
                links[:] = [li for li in links if any(verified.get((ga, gb, li), True) for ga, gb in cands[li])]
                if not links:
                    G.remove_edge(u, v)
                    cut |= (u, v) == (a, b)
        if not cut:
            return True
    return False


def _concat(a: dict, b: dict) -> dict:
    """Two column tables one after the other; ``grasp_id`` renumbered."""
    out = {k: (a[k] + b[k]) if isinstance(a[k], list) else np.concatenate([a[k], b[k]]) for k in a}
    if "grasp_id" in out:
        out["grasp_id"] = np.arange(len(out["grasp_id"]))
    return out


def _stability(scene, model, tables, ps, pose_id, pair_id, X, p_l, p_r, n_l, n_r, params: Params) -> dict:
    """Stability verdicts and margins of grasp candidates (see the module docstring, step 6).

    The pivot tests (one support corner and both balls) are shared: every pose of a placement is that
    placement's resting pose ``X_TO`` turned about the vertical and shifted (checked here to 1e-9), and
    the stability LP is invariant under such motions (friction pyramids, wrench axes and the margin's
    frame D all turn with the object), so each (placement, pair, corner) is solved once, in the resting
    pose, and its verdict and margin hold for every pose of that placement. Only which corners lie on
    the table depends on the pose.
    """
    N = len(X)
    mass = scene.object.mass
    L = float(np.linalg.norm(tables["summary"]["extents"]) / 2)

    def evaluate(*args, **kwargs):  # the candidates in slices, one per thread
        return stability.evaluate_threaded(*args, **kwargs, threads=params.threads, min_rows=256)

    prm, prm_hold, prm_pivot = _lp_params(scene, params)
    corners = poses.pivot_corners(model, params.corner_cluster, scene.planner.tilt)
    half = np.asarray(scene.table.size) / 2
    out = {"hold_left": np.zeros(N, bool), "hold_right": np.zeros(N, bool), "pivot_vertices": [None] * N,
           "margin": np.zeros(N)}
    usp = ps.support[pose_id] == "USP"
    g = ps.placement[pose_id]
    cid = corners.table(g)  # padded corner ids per placement, sorted (those of these poses only)
    kmax = cid.shape[1]
    ids = cid[g]                                                                   # (N, kmax)
    V = se3.transform_points(X[:, None], model.vertices[np.maximum(ids, 0)])
    on = (ids >= 0) & np.all(np.abs(V[..., :2]) <= half, axis=2)                 # corner on the table

    # One class per (placement, pair); a pose that is not an upright turn of X_TO is its own class.
    Y = X @ se3.invert(model.X_TO[g])
    upright = np.all(np.abs(Y[:, 2, :] - [0.0, 0.0, 1.0, 0.0]) <= 1e-9, axis=1)
    key = np.stack([g, pair_id, np.where(upright, -1, np.arange(N))], axis=1)
    ukey, rep, cls = np.unique(key, axis=0, return_index=True, return_inverse=True) if N else (
        np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    cls = cls.reshape(-1)
    C = len(ukey)
    X_c = np.where(upright[rep][:, None, None], model.X_TO[ukey[:, 0]], X[rep])  # (C, 4, 4)
    con, pairs = tables["contacts"], tables["pairs"]
    p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    ab = np.stack([pairs["contact_a"][ukey[:, 1]], pairs["contact_b"][ukey[:, 1]]], axis=1)     # (C, 2)
    eef_p = se3.transform_points(X_c[:, None], p_O[ab])
    eef_n = -se3.rotate_vectors(X_c[:, None], n_O[ab])                              # inward normals
    com_c = se3.transform_points(X_c, model.com)
    V_c = se3.transform_points(X_c[:, None], model.vertices[np.maximum(cid[ukey[:, 0]], 0)])  # (C, kmax, 3)
    need = np.zeros((C, kmax), bool)
    np.logical_or.at(need, cls, on)
    rows, cols = np.nonzero(need)
    res = evaluate(mass, com_c[rows], V_c[rows, cols][:, None], None, eef_p[rows], eef_n[rows], None, L, prm,
                   compute_margin=False)
    holds_c = np.zeros((C, kmax), bool)
    holds_c[rows, cols] = res.stable
    alpha_c = np.zeros((C, kmax))
    alpha_c[rows, cols] = res.alpha
    holds = on & holds_c[cls]                                                      # (N, kmax)
    has = holds.any(axis=1)
    first = np.argmax(holds, axis=1)
    piv_c = np.zeros((C, kmax), bool)
    r2, c2 = rows[res.stable], cols[res.stable]
    classes = _Classes(X_c, com_c, V_c, cid[ukey[:, 0]], eef_p, eef_n)
    piv_c[r2, c2] = _pivot_holds(classes, r2, c2, mass, L, scene.planner.tilt, model, prm_pivot, evaluate)
    pivots = on & piv_c[cls]
    out["pivot_vertices"] = [ids[i][pivots[i]] for i in range(N)]
    # Margins cost twelve LPs each: measure them on one pivot corner per SP grasp, the first that holds
    # (a USP grasp records its margin of holding, below).
    sp = has & ~usp
    mk, minv = np.unique(np.stack([cls[sp], first[sp]], axis=1), axis=0, return_inverse=True)
    m = evaluate(mass, com_c[mk[:, 0]], V_c[mk[:, 0], mk[:, 1]][:, None], None, eef_p[mk[:, 0]], eef_n[mk[:, 0]],
                 None, L, prm, R_WD=X_c[mk[:, 0], :3, :3], alpha=alpha_c[mk[:, 0], mk[:, 1]])
    out["margin"][sp] = m.margin[minv.reshape(-1)]
    out["stable"] = sp
    us = np.flatnonzero(usp)
    if len(us):
        _usp_stability(out, us, model, tables, pose_id, g, X, np.stack([p_l, p_r], axis=1),
                       -np.stack([n_l, n_r], axis=1), half, (mass, L, prm, prm_hold), evaluate)
    return out


def _usp_stability(out, us, model, tables, pose_id, g, X, eef_p, eef_n, half, lp: tuple, evaluate) -> None:
    """The USP candidates ``us`` of :func:`_stability`: the object on its table contact
    (``poses.table_support``, cut by the table's edge) with both balls, then with each ball alone
    (``eef_p``, inward ``eef_n (N, 2, 3)``, W), its CoM the SP margin further out (``poses.held_com``).
    ``lp`` is (mass kg, LP length scale m, both-ball and one-ball ``stability.Params``); fills ``out``."""
    mass, L, prm, prm_hold = lp
    com = se3.transform_points(X, model.com)
    uniq, first = np.unique(pose_id[us], return_index=True)
    polys = {int(p): poses.table_support(model, X[us[f]], g[us[f]], half) for p, f in zip(uniq, first, strict=True)}
    # Held with the SP margin: the CoM that far further out (poses.held_com), one shift per pose.
    sp_margin = float(tables["placements"].meta["params"]["sp_margin"])
    shift = {p: poses.held_com(polys[p], com[us[f]], sp_margin) - com[us[f]] for p, f in zip(polys, first, strict=True)}
    com[us] += np.stack([shift[int(p)] for p in pose_id[us]])
    size = np.array([len(polys[int(p)]) for p in pose_id[us]])
    for kmax in np.unique(size):  # one batch per polygon size: no LP carries another's padding
        _usp_holds(out, us[size == kmax], kmax, polys, pose_id, mass, com, eef_p, eef_n, X, L, prm, prm_hold,
                   evaluate)


def _lp_params(scene, params: Params) -> tuple[stability.Params, stability.Params, stability.Params]:
    """The stability LPs' friction and force bounds (module docstring, step 6): holding with both balls
    (the scene's own), a one-ball USP hold (``hold_eef_friction``, ``hold_friction_safety``) and a pivot
    (``pivot_friction_safety``, ``pivot_force_safety`` as a bound on the whole ball force)."""
    mu, f_max = scene.object.friction, scene.robot.max_eef_force
    mu_pivot = params.pivot_friction_safety * mu
    return (stability.Params(mu_eef=mu, mu_table=scene.table.friction, f_max=f_max),
            stability.Params(mu_eef=params.hold_eef_friction * mu,
                             mu_table=params.hold_friction_safety * scene.table.friction, f_max=f_max),
            stability.Params(mu_eef=mu_pivot, mu_table=params.pivot_friction_safety * scene.table.friction,
                             f_max=stability.normal_bound(params.pivot_force_safety * f_max, mu_pivot)))


class _Classes(NamedTuple):
    """The (placement, pair) classes of :func:`_stability`, each in its placement's resting pose (W, m):
    ``X (C, 4, 4)``, ``com (C, 3)``, support corners ``V (C, kmax, 3)`` and their hull vertex ids
    ``vid (C, kmax)`` (-1: padding), the balls' contact points ``eef_p`` and inward normals
    ``eef_n (C, 2, 3)``."""

    X: np.ndarray
    com: np.ndarray
    V: np.ndarray
    vid: np.ndarray
    eef_p: np.ndarray
    eef_n: np.ndarray


def _pivot_holds(cl: _Classes, r: np.ndarray, c: np.ndarray, mass: float, L: float, tilt: float, model,
                 prm: stability.Params, evaluate) -> np.ndarray:
    """``(n,)`` whether the balls of class ``r`` hold the object on its corner ``c`` (column of
    ``cl.V``) through a pivot (eq. 1-4, §5.2.1): at the start of the tilt first, the object already on
    that corner alone with its CoM at its full offset (the hardest instant: the tilt then brings the
    CoM towards the corner), then at the full ``tilt`` (rad) along ``mpc.pivot_reference``'s tilt
    direction (``poses.tilt_direction``)."""
    ok = _tilted_holds(mass, cl.com[r], cl.V[r, c], cl.eef_p[r], cl.eef_n[r], L, 0.0, prm, evaluate)
    i = np.flatnonzero(ok)
    dirs = np.zeros((len(i), 3))  # the tilt direction where it is not the CoM's
    for k, (ri, vi) in enumerate(zip(r[i].tolist(), cl.vid[r[i], c[i]].tolist(), strict=True)):
        d = poses.tilt_direction(model, cl.X[ri], vi, tilt)
        dirs[k] = 0.0 if d is None else d
    ri, ci = r[i], c[i]
    ok[i] = _tilted_holds(mass, cl.com[ri], cl.V[ri, ci], cl.eef_p[ri], cl.eef_n[ri], L, tilt, prm, evaluate, dirs)
    return ok


def _tilted_holds(mass, com, p0, eef_p, eef_n, L: float, tilt: float, prm: stability.Params, evaluate,
                  tilt_dir: np.ndarray | None = None) -> np.ndarray:
    """Whether each object stays in equilibrium tilted by ``tilt`` (rad) onto its corner ``p0 (n, 3)``
    with both balls (``eef_p``, inward ``eef_n (n, 2, 3)``; CoM ``com (n, 3)``; W, m), ``(n,)`` bool:
    the graph stage's test of a pivot edge at its full tilt and, with ``tilt = 0``, at the start of its
    tilt (``graph.build_graph``), about the axis of
    ``mpc.pivot_reference`` (horizontal through the corner, across the corner's direction to the CoM,
    raising the CoM side, or along ``tilt_dir (n, 3)``'s non-zero rows, ``poses.tilt_direction``;
    §5.2.1, Fig. 12). Yaw and the shift do not change the verdict, so one test per (placement, pair,
    corner) is every pose's."""
    if not len(p0):
        return np.zeros(0, bool)
    d = com - p0
    if tilt_dir is not None:
        own = np.any(tilt_dir != 0.0, axis=1)
        d[own] = tilt_dir[own]
    d[:, 2] = 0.0
    defined = np.linalg.norm(d, axis=1) > 1e-9  # a CoM above its corner has no tilt direction: no pivot
    d[~defined] = [1.0, 0.0, 0.0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    T = se3.transform_about_line(p0, np.cross(d, [0.0, 0.0, 1.0]), np.full(len(p0), tilt))
    res = evaluate(mass, se3.transform_points(T, com), p0[:, None], None, se3.transform_points(T[:, None], eef_p),
                   se3.rotate_vectors(T[:, None], eef_n), None, L, prm, compute_margin=False)
    return res.stable & defined


def _usp_holds(out, us, kmax, polys, pose_id, mass, com, eef_p, eef_n, X, L, prm, prm_hold, evaluate) -> None:
    """USP candidates ``us`` whose table contact has ``kmax`` corners: hold with both balls (``prm``),
    with the left alone and with the right alone (``prm_hold``), and the both-ball margin."""
    upose, inv = np.unique(pose_id[us], return_inverse=True)
    V = np.zeros((len(us), kmax, 3))
    V[:, :, :2] = np.stack([polys[int(p)] for p in upose])[inv.reshape(-1)]  # one polygon per pose
    n = len(us)
    em = np.ones((3, n, 2), bool)
    em[1, :, 1] = em[2, :, 0] = False

    def two(a):
        return np.concatenate([a, a])

    res = evaluate(mass, com[us], V, None, eef_p[us], eef_n[us], None, L, prm, R_WD=X[us, :3, :3],
                   compute_margin=False)
    alone = evaluate(mass, two(com[us]), two(V), None, two(eef_p[us]), two(eef_n[us]), em[1:].reshape(2 * n, 2), L,
                     prm_hold, R_WD=two(X[us, :3, :3]), compute_margin=False)
    stable = np.concatenate([res.stable, alone.stable]).reshape(3, n)
    out["stable"][us] = stable[0]
    out["hold_left"][us], out["hold_right"][us] = stable[1], stable[2]
    # The margin of holding with both (not pivoting: holding is what a USP grasp must do first); a
    # ball alone is only ever asked whether it holds, so its twelve margin LPs are not solved.
    s0 = us[stable[0]]
    m = evaluate(mass, com[s0], V[stable[0]], None, eef_p[s0], eef_n[s0], None, L, prm,
                 R_WD=X[s0, :3, :3], alpha=res.alpha[stable[0]])
    out["margin"][s0] = m.margin


POSE_FIELDS = [
    Field("pose_id", "id"), *[Field(c, "m", "W") for c in ("x", "y", "z")],
    *[Field(c, "1", "W") for c in ("qx", "qy", "qz", "qw")], Field("placement_id", "id"), Field("support"),
    Field("status"), Field("parent", "id"), Field("primitive"), Field("vertex", "id"), Field("edge_v0", "id"),
    Field("edge_v1", "id"), Field("angle", "rad"), Field("margin", "m"),
]
LINK_FIELDS = [
    Field("link_id", "id"), Field("pose_a", "id"), Field("pose_b", "id"), Field("primitive"), Field("vertex", "id"),
    Field("edge_v0", "id"), Field("edge_v1", "id"), Field("angle", "rad"),
]
GRASP_FIELDS = [
    Field("grasp_id", "id"), Field("pose_id", "id"), Field("pair_id", "id"), Field("contact_left", "id"),
    Field("contact_right", "id"), Field("margin", "N"), Field("hold_left"),
    Field("hold_right"), Field("pivot_vertices", "id"), Field("q_left", "rad"), Field("q_right", "rad"),
]
REJECT_FIELDS = [Field("pose_id", "id"), Field("pair_id", "id"), Field("reason")]


def _check_links(graph, gp, checks, tables, cand: np.ndarray) -> np.ndarray:
    """The graph stage's checks of link candidates ``cand (n, 3)`` (:func:`lazy_reach`): a pivot's
    (``graph.check_pivot_edges`` with ``checks``, a ``graph.PivotChecks``), a tumble's pusher
    (``graph.pusher_motions``; rows ``(-1, -1, link)``). ``graph`` is the module, ``gp`` its parameters."""
    out = np.empty(len(cand), dtype=object)
    tum = cand[:, 0] < 0
    if np.any(~tum):
        out[~tum] = graph.check_pivot_edges(checks, cand[~tum], gp)
    if np.any(tum):
        li, X = cand[tum, 2], checks.X_WO
        con = tables["contacts"]
        pc = np.stack([con["px"], con["py"], con["pz"]], axis=1)
        nc = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
        found = graph.pusher_motions(checks.robot, checks.collide, checks.model, X[checks.link_poses[li, 0]],
                                     X[checks.link_poses[li, 1]], checks.link_edge[li], pc, nc,
                                     checks.scene.robot.ball_radius, gp, graph.push_limits(checks.scene, gp))
        out[tum] = ["ok" if arm is not None else str(what) for arm, what, _ in found]
    return out


class _Reached(NamedTuple):
    """What the grasp-aware reach leaves: the pose set, grasps and rejects of every round, rounds grown."""

    pose_set: poses.PoseSet
    grasps: dict
    rejects: dict
    rounds: int


def _sides(G: nx.DiGraph, goal: int) -> tuple[list[int], list[int]]:
    """The poses the start reaches in the reach graph ``G`` and those that reach the goal (the goal first)."""
    return sorted(nx.descendants(G, 0) | {0}), [goal, *sorted(nx.ancestors(G, goal) - {goal})]


def _goal_reached(scene, model, tables, arms: tuple, ps, grasps, reach: tuple, gp, verified: dict,
                  params: Params) -> bool:
    """Whether the start reaches the goal along links whose pivots pass the graph's checks
    (:func:`lazy_reach` over ``reach`` = (reach graph, link candidates); ``arms`` = (robot, collision
    function); ``verified`` carried between rounds)."""
    from stages import graph  # it imports this module's helpers, not this module

    G, cands = reach
    p_g, n_g = graph.grasp_geometry(tables, grasps, scene.robot.ball_radius)
    q_g = np.stack([np.stack(grasps["q_left"]), np.stack(grasps["q_right"])], axis=1)
    checks = graph.PivotChecks(scene, model, tables, *arms, ps.X_WO, ps.links, ps.link_vertex,
                               ps.link_edge, [set(np.asarray(v).tolist()) for v in grasps["pivot_vertices"]],
                               p_g, n_g, q_g)
    check = functools.partial(_check_links, graph, gp, checks, tables)
    return lazy_reach(G, ps.goal_id, cands, check, verified, params.reach_walks)


def _refine_more(scene, model, tables, ps, robot, collide, params: Params, rng, n0: int, grasps: dict,
                 rejects: dict, timings: dict) -> tuple[dict, dict]:
    """The grasps and rejects with those of the poses from row ``n0`` on refined and added (timings summed)."""
    more = refine_grasps(scene, model, tables, ps, robot, collide, params, rng, np.arange(n0, len(ps.status)))
    for k, v in more[2].items():
        timings[k] = timings.get(k, 0.0) + v
    return _concat(grasps, more[0]), _concat(rejects, more[1])


def _reach(scene, model, tables, lattice, placements: tuple[int, int], robot, collide, params: Params, rng,
           found: tuple[dict, dict, dict]) -> _Reached:
    """Grasp-aware reach (``Params.reach_rounds``): while the goal is not reached by links whose pivots
    pass the graph stage's checks (:func:`lazy_reach`), grow the lattice on from the poses the start
    reaches toward those the goal reaches (``poses.extend_lattice``) and refine the new poses' grasps.
    When the rounds do not reach it, pivot walks join the two sides as a last resort
    (``poses.walk_lattice``). ``found`` is ``(grasps, rejects, timings)`` so far (timings updated in
    place)."""
    from stages import graph  # it imports this module's helpers, not this module

    grasps, rejects, timings = found
    gp = graph.Params(pivot_arms=True)
    verified: dict = {}
    ps, reached = lattice.pose_set(), False
    for rounds in range(params.reach_rounds + 1):
        cands = link_candidates(ps, grasps, tumbles=placements[0] != placements[1])
        G = reach_graph(ps, cands)
        if ps.goal_id < 0:
            break
        if reached := _goal_reached(scene, model, tables, (robot, collide), ps, grasps, (G, cands), gp, verified,
                                    params):
            break
        if rounds == params.reach_rounds:
            break
        n0 = len(ps.status)
        poses.extend_lattice(lattice, *_sides(G, ps.goal_id), held_corners(grasps),
                             int(np.ceil(params.reach_share * scene.planner.max_poses)))
        ps = lattice.pose_set()
        if not np.any(ps.status[n0:] == "ok"):
            rounds += 1
            break
        grasps, rejects = _refine_more(scene, model, tables, ps, robot, collide, params, rng, n0, grasps, rejects,
                                       timings)
    if ps.goal_id >= 0 and not reached:  # the last resort: pivot walks between the two sides
        n0 = len(ps.status)
        if poses.walk_lattice(lattice, *_sides(G, ps.goal_id)):
            ps = lattice.pose_set()
            grasps, rejects = _refine_more(scene, model, tables, ps, robot, collide, params, rng, n0, grasps,
                                           rejects, timings)
    return _Reached(ps, grasps, rejects, rounds)


def compute(scene: Scene, analysis_dir: str | Path, params: Params) -> Result:
    """Sample poses and refine grasps for ``scene`` with the analysis in ``analysis_dir``."""
    t0 = time.perf_counter()
    model, tables = load_object_model(analysis_dir)
    X0, g0 = placement_pose(scene.start, model, f"{scene.path}: start")
    pl = scene.planner
    upstream = tables["placements"].meta["params"]
    pp = poses.Params(theta_t=pl.theta_t, max_poses=pl.max_poses, goal_reach_share=pl.goal_reach,
                      usp=pl.usp, sp_margin=float(upstream["sp_margin"]),
                      corner_cluster=params.corner_cluster, tilt=pl.tilt, min_tumble_edge=params.min_tumble_edge,
                      face_tilt=np.radians(float(upstream["hull_coplanar_deg"])))
    Xg, gg = placement_pose(scene.goal, model, f"{scene.path}: goal")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links),
                       ik_params=IKParams(threads=params.threads, min_chunk=1024))
    obstacles = list(scene.obstacle_geometries()) + trunk_obstacles(robot)
    for where, X, g in (("start", X0, g0), ("goal", Xg, gg)):  # bad input, with what it hits
        status, why = poses.describe_pose(model, X, g, scene.table.size, obstacles, pp)
        if status != "ok":
            raise InputError(f"{scene.path}: {where}: the {where} pose (placement {g}) is {status}: {why}")
    lattice = poses.build_lattice(model, X0, g0, scene.table.size, obstacles, pp, goal=(Xg, gg))
    ps = lattice.pose_set()
    t1 = time.perf_counter()
    # Robot set-up, before the refinement: self-collision pairs and IK seed libraries.
    collide = make_scene_collision_fn(scene, robot, tables["mesh"], params.threads,
                                      (params.arm_clearance, params.stick_clearance))
    robot.prepare_ik()
    t2 = time.perf_counter()
    rng = np.random.default_rng(pl.seed)
    grasps, rejects, timings = refine_grasps(scene, model, tables, ps, robot, collide, params, rng)
    ps, grasps, rejects, rounds = _reach(scene, model, tables, lattice, (g0, gg), robot, collide, params, rng,
                                         (grasps, rejects, timings))
    timings.update(poses=t1 - t0, robot_setup=t2 - t1, total=time.perf_counter() - t0)
    reasons, counts = np.unique(rejects["reason"], return_counts=True)
    summary = {
        "poses": {s: int((ps.status == s).sum()) for s in ("ok", "off_table", "unstable", "obstacle")},
        "poses_sp": int(((ps.status == "ok") & (ps.support == "SP")).sum()),
        "poses_usp": int(((ps.status == "ok") & (ps.support == "USP")).sum()),
        "links": {p: int((ps.link_primitive == p).sum()) for p in ("pivot", "tumble")},
        "candidates": int(len(grasps["grasp_id"]) + len(rejects["reason"])),
        "grasps": int(len(grasps["grasp_id"])),
        "reach_rounds": rounds,
        "rejected": {str(r): int(c) for r, c in zip(reasons, counts, strict=True)},
        "start": {"pose_id": 0, "placement_id": g0},
        "goal": {"pose_id": ps.goal_id, "placement_id": gg,
                 "status": "ok" if ps.goal_id >= 0 else "not_reached"},
        "face_route": poses.face_route(model, g0, gg, params.min_tumble_edge),
        "walk_joins": lattice.walks,
    }
    return Result(ps, grasps, rejects, summary, timings)


def run(scene_path: str | Path, analysis_dir: str | Path, out_dir: str | Path, params: Params,
        producer: str = "sample") -> Result:
    """Read the scene and analysis, sample, write the artifacts (module docstring) into ``out_dir``."""
    scene = load_scene(scene_path)
    provenance.check_analysis(analysis_dir, scene)
    result = compute(scene, analysis_dir, params)
    out = Path(out_dir)
    # Threads change how fast, not what: left out so that the artifacts do not depend on them.
    meta_params = {**{k: v for k, v in asdict(params).items() if k != "threads"}, "scene": scene.to_dict()}
    inputs = {"scene": scene_path, **{n: Path(analysis_dir) / f"{n}.parquet" for n in ("hull", "placements",
                                                                                       "contacts", "pairs")}}
    ps = result.poses
    cols = se3.columns_from_matrix(ps.X_WO)
    pose_cols = {"pose_id": np.arange(len(ps.status)), **cols, "placement_id": ps.placement, "support": ps.support,
                 "status": ps.status, "parent": ps.parent, "primitive": ps.primitive, "vertex": ps.vertex,
                 "edge_v0": ps.edge[:, 0], "edge_v1": ps.edge[:, 1], "angle": ps.angle, "margin": ps.margin}
    link_cols = {"link_id": np.arange(len(ps.links)), "pose_a": ps.links[:, 0], "pose_b": ps.links[:, 1],
                 "primitive": ps.link_primitive, "vertex": ps.link_vertex, "edge_v0": ps.link_edge[:, 0],
                 "edge_v1": ps.link_edge[:, 1], "angle": ps.link_angle}
    for name, columns, fields in (("poses", pose_cols, POSE_FIELDS), ("pose_links", link_cols, LINK_FIELDS),
                                  ("grasps", result.grasps, GRASP_FIELDS),
                                  ("grasp_rejects", result.rejects, REJECT_FIELDS)):
        artifacts.write_table(out / f"{name}.parquet", columns, fields,
                              artifacts.make_meta(name, meta_params, inputs, producer))
    artifacts.write_json(out / "sample.json", result.summary, artifacts.make_meta("sample", meta_params, inputs,
                                                                                   producer))
    artifacts.write_timings(out / "sample.json", result.timings)
    stagelog.log_sample(result.summary, result.rejects)
    return result
