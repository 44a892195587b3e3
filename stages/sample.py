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
- ``sample.json``: counts per status and reason.

Grasp refinement, cheapest test first, all batched over the (pose, pair) candidates:

1. ``eef_under_object``: a contact whose outward normal points down (the ball would be under the
   object, Fig. 5 r1/r2), or ``env_collision:ball/table``: a ball centre too close to the table;
2. ``normal_away``: a contact normal facing away from its arm's shoulder (Fig. 5 r3/r4);
3. ``ik_unreachable`` / ``joint_limit``: batched position IK of each ball centre (``stages.robot``);
4. ``env_collision:*`` / ``self_collision:*``: the arms against the table, obstacles, object and
   each other;
5. ``unstable``: the stability LP (``stages.stability``, eq. 1–4): in SP the object must stay in
   equilibrium tilted on at least one support corner with both balls (a pivot can start); in USP
   the on-table support vertices and both balls must hold it. The margins recorded are the best
   pivot margin (SP) and, in USP, the margins of holding with the left or the right ball alone
   (which a regrasp in USP needs, §5.2.2).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from stages import artifacts, poses, se3, stability
from stages.artifacts import Field
from stages.errors import InputError
from stages.objectmodel import load_object_model
from stages.robot import load_robot, make_collision_fn
from stages.scene import ObstacleGeometry, PlacementSpec, Scene, load_scene


@dataclass(frozen=True)
class Params:
    """Sampling and grasp-refinement parameters not in the scene (m, rad)."""

    #: Ball centres closer than this to the table top are refused (m).
    table_clearance: float = 0.01
    #: A contact normal whose z component is below this points under the object.
    under_nz: float = -0.5
    #: A contact normal is "away" when its horizontal part turns more than this from the shoulder (rad).
    away_angle: float = np.radians(120.0)
    #: IK tolerance (m) and restarts.
    ik_tol: float = 1e-3
    ik_restarts: int = 2
    #: New IK solutions tried for a candidate whose first solution collides.
    collision_retries: int = 3
    #: Corner clustering and tumble edge length of the pose sampler (m).
    corner_cluster: float = 0.03
    min_tumble_edge: float = 0.05


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


def make_scene_collision_fn(scene: Scene, robot, object_mesh):
    """The robot's batched collision checker against the scene's table, obstacles and the object."""
    obstacles = []
    for ob in scene.obstacle_geometries():
        dims = {"box": ob.size, "cylinder": (ob.radius, ob.height), "mesh": (ob.vertices, ob.faces)}[ob.kind]
        obstacles.append((ob.kind, dims, ob.X_WOb, ob.name))
    return make_collision_fn(robot, (tuple(scene.table.size), 0.0), obstacles, object_mesh,
                             table_depth=scene.table.height)


def refine_grasps(scene: Scene, model: poses.ObjectModel, tables: dict, ps: poses.PoseSet, robot, collide,
                  params: Params, rng: np.random.Generator) -> tuple[dict, dict, dict]:
    """Grasp refinement (see the module docstring) over every kept pose × contact pair.

    Returns ``(grasps, rejects, timings)`` column dicts.
    """
    timings = {}
    t0 = time.perf_counter()
    con, pairs = tables["contacts"], tables["pairs"]
    p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    r = scene.robot.ball_radius
    kept = np.flatnonzero(ps.status == "ok")
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
    reason = np.full(len(X), "", dtype=object)

    def refuse(mask, why):
        new = mask & (reason == "")
        reason[new] = why

    refuse((n_l[:, 2] < params.under_nz) | (n_r[:, 2] < params.under_nz), "eef_under_object")
    refuse((ball_l[:, 2] < r + params.table_clearance) | (ball_r[:, 2] < r + params.table_clearance),
           "env_collision:ball/table")
    for arm, p, n in (("left", p_l, n_l), ("right", p_r, n_r)):
        s = robot.arm(arm).reach_centre
        to_s = s[:2] - p[:, :2]
        cos = np.einsum("ij,ij->i", n[:, :2], to_s) / np.maximum(
            np.linalg.norm(n[:, :2], axis=1) * np.linalg.norm(to_s, axis=1), 1e-12)
        flat = np.linalg.norm(n[:, :2], axis=1) < 0.3  # a top face is reached from above
        refuse(~flat & (cos < np.cos(params.away_angle)), "normal_away")
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

    # Collisions of the arms with the table, obstacles, the object and each other. The IK knows
    # nothing of obstacles, so a colliding candidate gets a few more IK solutions from random seeds
    # around the rest posture (collision-aware IK by retry) before it is refused.
    cand = np.flatnonzero(reason == "")
    for attempt in range(params.collision_retries + 1):
        ok, why = collide(q_l[cand], q_r[cand], X[cand], np.ones((len(cand), 2), bool))
        failed = cand[~ok]
        if attempt == params.collision_retries or len(failed) == 0:
            reason[failed] = why[~ok]
            break
        for arm, ball, q in (("left", ball_l, q_l), ("right", ball_r, q_r)):
            a = robot.arm(arm)
            seed = np.clip(a.q_rest + rng.normal(0.0, 0.35, (len(failed), a.dof)) * (a.upper - a.lower),
                           a.lower, a.upper)
            res = robot.ik(arm, ball[failed], q_seed=seed, rng=rng, restarts=0, tol=params.ik_tol)
            q[failed[res.ok]] = res.q[res.ok]
        cand = failed
    t3 = time.perf_counter()

    # Stability.
    live = np.flatnonzero(reason == "")
    margins = _stability(scene, model, tables, ps, pose_idx[live], X[live], p_l[live], p_r[live], n_l[live],
                         n_r[live], params.corner_cluster)
    refuse_live = ~margins["stable"]
    reason[live[refuse_live]] = "unstable"
    t4 = time.perf_counter()
    timings.update(prefilter=t1 - t0, ik=t2 - t1, collision=t3 - t2, stability=t4 - t3, refine=t4 - t0)

    good = live[~refuse_live]
    g_sel = ~refuse_live
    grasps = {
        "grasp_id": np.arange(len(good)),
        "pose_id": pose_idx[good].astype(np.int64),
        "pair_id": pair_idx[good].astype(np.int64),
        "contact_left": c_left[good].astype(np.int64),
        "contact_right": c_right[good].astype(np.int64),
        "margin": margins["margin"][g_sel],
        "margin_hold_left": margins["hold_left"][g_sel],
        "margin_hold_right": margins["hold_right"][g_sel],
        "pivot_vertices": [v for v, s in zip(margins["pivot_vertices"], g_sel, strict=True) if s],
        "q_left": list(q_l[good]),
        "q_right": list(q_r[good]),
    }
    bad = np.flatnonzero(reason != "")
    rejects = {
        "pose_id": pose_idx[bad].astype(np.int64),
        "pair_id": pair_idx[bad].astype(np.int64),
        "reason": np.array([str(x) for x in reason[bad]], dtype=str),
    }
    return grasps, rejects, timings


def _stability(scene, model, tables, ps, pose_id, X, p_l, p_r, n_l, n_r, corner_cluster: float) -> dict:
    """Stability verdicts and margins of grasp candidates (see the module docstring, step 5)."""
    N = len(X)
    mass = scene.object.mass
    com = se3.transform_points(X, model.com)
    L = float(np.linalg.norm(tables["summary"]["extents"]) / 2)
    prm = stability.Params(mu_eef=scene.object.friction, mu_table=scene.table.friction,
                           f_max=scene.robot.max_eef_force)
    eef_p = np.stack([p_l, p_r], axis=1)
    eef_n = -np.stack([n_l, n_r], axis=1)  # inward normals
    corners = poses.pivot_corners(model, corner_cluster)
    half = np.asarray(scene.table.size) / 2
    out = {"hold_left": np.full(N, np.nan), "hold_right": np.full(N, np.nan), "pivot_vertices": [None] * N}
    usp = ps.support[pose_id] == "USP"
    g = ps.placement[pose_id]
    # Pivot on each support corner that lies on the table, with both balls (QS gait in SP, DS in USP).
    kmax = max(len(c) for c in corners)
    V = np.zeros((N, kmax, 3))
    mask = np.zeros((N, kmax), bool)
    ids = -np.ones((N, kmax), np.int64)
    for i in range(N):  # fill a padded corner table (four or so corners a pose); the LPs are batched
        c = corners[g[i]]
        V[i, :len(c)] = se3.transform_points(X[i], model.vertices[c])
        mask[i, :len(c)] = np.all(np.abs(V[i, :len(c), :2]) <= half, axis=1)
        ids[i, :len(c)] = c
    rows, cols = np.nonzero(mask)
    res = stability.evaluate_threaded(mass, com[rows], V[rows, cols][:, None], None, eef_p[rows], eef_n[rows],
                                      None, L, prm, compute_margin=False)
    # Margins cost twelve LPs each: measure them on one pivot corner per grasp, the first that holds.
    first = np.full(N, -1)
    hit = np.flatnonzero(res.stable)
    first[rows[hit][::-1]] = hit[::-1]
    has = np.flatnonzero(first >= 0)
    k = first[has]
    m = stability.evaluate_threaded(mass, com[rows[k]], V[rows[k], cols[k]][:, None], None, eef_p[rows[k]],
                                    eef_n[rows[k]], None, L, prm, R_WD=X[rows[k], :3, :3])
    out["stable"] = (first >= 0) & ~usp
    out["margin"] = np.zeros(N)
    out["margin"][has] = m.margin
    stable_ids = np.where(res.stable, ids[rows, cols], -1)
    per_row = np.split(stable_ids, np.cumsum(np.bincount(rows, minlength=N))[:-1]) if N else []
    out["pivot_vertices"] = [np.sort(v[v >= 0]) for v in per_row]
    # USP: the object on the table's edge (its support face clipped to the table top) with both balls,
    # then with each ball alone.
    us = np.flatnonzero(usp)
    if len(us):
        uniq, first = np.unique(pose_id[us], return_index=True)
        polys = {int(p): poses.table_support(model, X[us[f]], g[us[f]], half)
                 for p, f in zip(uniq, first, strict=True)}
        kmax = max(len(v) for v in polys.values())
        V = np.zeros((len(us), kmax, 3))
        mask = np.zeros((len(us), kmax), bool)
        for k, i in enumerate(us):  # padded table-contact polygons, one per pose
            poly = polys[int(pose_id[i])]
            V[k, :len(poly), :2] = poly
            mask[k, :len(poly)] = True
        R = X[us, :3, :3]
        both = stability.evaluate_threaded(mass, com[us], V, mask, eef_p[us], eef_n[us], None, L, prm, R_WD=R)
        out["stable"][us] = both.stable
        out["margin"][us] = both.margin  # holding, not pivoting, is what a USP grasp must do first
        for j, key in ((0, "hold_left"), (1, "hold_right")):
            em = np.zeros((len(us), 2), bool)
            em[:, j] = True
            one = stability.evaluate_threaded(mass, com[us], V, mask, eef_p[us], eef_n[us], em, L, prm, R_WD=R)
            out[key][us] = np.where(one.stable, one.margin, -1.0)
    return out


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
    Field("contact_right", "id"), Field("margin", "N"), Field("margin_hold_left", "N"),
    Field("margin_hold_right", "N"), Field("pivot_vertices", "id"), Field("q_left", "rad"), Field("q_right", "rad"),
]
REJECT_FIELDS = [Field("pose_id", "id"), Field("pair_id", "id"), Field("reason")]


def compute(scene: Scene, analysis_dir: str | Path, params: Params) -> Result:
    """Sample poses and refine grasps for ``scene`` with the analysis in ``analysis_dir``."""
    t0 = time.perf_counter()
    model, tables = load_object_model(analysis_dir)
    X0, g0 = placement_pose(scene.start, model, f"{scene.path}: start")
    pl = scene.planner
    pp = poses.Params(theta_t=pl.theta_t, max_poses=pl.max_poses, usp=pl.usp,
                      sp_margin=float(tables["placements"].meta["params"]["sp_margin"]),
                      corner_cluster=params.corner_cluster, min_tumble_edge=params.min_tumble_edge)
    Xg, gg = placement_pose(scene.goal, model, f"{scene.path}: goal")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    obstacles = list(scene.obstacle_geometries()) + trunk_obstacles(robot)
    ps = poses.sample_poses(model, X0, g0, scene.table.size, obstacles, pp, goal=(Xg, gg))
    if ps.status[0] != "ok":
        raise InputError(f"{scene.path}: start: the start pose is {ps.status[0]} (placement {g0})")
    t1 = time.perf_counter()
    collide = make_scene_collision_fn(scene, robot, tables["mesh"])
    rng = np.random.default_rng(pl.seed)
    grasps, rejects, timings = refine_grasps(scene, model, tables, ps, robot, collide, params, rng)
    timings.update(poses=t1 - t0, total=time.perf_counter() - t0)
    reasons, counts = np.unique(rejects["reason"], return_counts=True)
    summary = {
        "poses": {s: int((ps.status == s).sum()) for s in ("ok", "off_table", "unstable", "obstacle")},
        "poses_sp": int(((ps.status == "ok") & (ps.support == "SP")).sum()),
        "poses_usp": int(((ps.status == "ok") & (ps.support == "USP")).sum()),
        "links": {p: int((ps.link_primitive == p).sum()) for p in ("pivot", "tumble")},
        "candidates": int(len(grasps["grasp_id"]) + len(rejects["reason"])),
        "grasps": int(len(grasps["grasp_id"])),
        "rejected": {str(r): int(c) for r, c in zip(reasons, counts, strict=True)},
        "start": {"pose_id": 0, "placement_id": g0},
        "goal": {"pose_id": ps.goal_id, "placement_id": gg,
                 "status": "ok" if ps.goal_id >= 0 else "not_reached"},
    }
    return Result(ps, grasps, rejects, summary, timings)


def run(scene_path: str | Path, analysis_dir: str | Path, out_dir: str | Path, params: Params,
        producer: str = "sample") -> Result:
    """Read the scene and analysis, sample, write the artifacts (module docstring) into ``out_dir``."""
    scene = load_scene(scene_path)
    result = compute(scene, analysis_dir, params)
    out = Path(out_dir)
    meta_params = {**asdict(params), "scene": scene.to_dict()}
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
    return result
