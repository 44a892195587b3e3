"""Object pose sampling on the table by pivoting and tumbling (§5.1, Fig. 7–9).

Poses are not sampled at random: pivoting keeps a table vertex fixed, so the reachable poses form a
lattice. From the start pose, best first (below), every pose is

- **pivoted** about each corner of its support polygon (the pivot vertex stays on the table) by
  ±θ_t about the vertical through that vertex (QS gait in SP; DS gait in USP, on the vertices that
  lie on the table), and
- **tumbled** about each support-polygon edge (a hull edge at least ``min_tumble_edge`` long with
  both ends on the table) onto the adjacent hull face.

Only placements that are SP on their own are sampled. The object touches the table where its mesh
lies in the support plane, clipped to the table top (:func:`table_support`: the soles of a piano's
feet, not the face between them; near the table's edge the edge cuts them). A new pose is SP when
the CoM's vertical projection lies inside that polygon by
``sp_margin``; with USP allowed it is USP when the CoM lies beyond it, by at least ``usp_margin`` and
at most ``max_usp_overhang``, over the table's edge: the object would tip off the table unless one
ball holds it (§5.1, Fig. 14, 18; the grasp stage decides with the stability test). Between the two
margins a pose is neither: whether it stands alone is a matter of millimetres the robot does not
know. It is rejected as ``off_table`` (not SP and less than ``min_usp_edge`` of contact with the table,
or too much overhang), ``unstable`` (USP not allowed, or the CoM between the margins) or ``obstacle``
(python-fcl: the object mesh at the pose overlaps an obstacle or the robot's trunk, or swept by the
pivot, flat and tilted onto its vertex, or the tumble that reaches it, comes within ``sweep_clearance``
of one). Poses closer than ``merge_xy`` and
``merge_yaw`` on the same placement are one pose; the defaults only merge what is the same pose up
to rounding (e.g. +θ then −θ about one vertex), so that every link is an exact pivot or tumble.
Every pivot or tumble between two kept poses is a link.

Expansion order (our addition to §5.1): the lattice is capped at ``max_poses``. Pivots seldom
return to a pose, so it grows like a tree, and breadth first over all poses a cap spends the poses
on the start's placement: the placements a tumble reaches are hardly expanded past their landing,
and a goal on another face is not reached. Each placement therefore keeps its own breadth-first
queue and the placements take turns: the start's and the goal's alike, any other ``other_share``
as often. With a goal and ``goal_reach_share`` > 0 (the scene's ``planner.goal_reach``, 0.5 by
default), once the goal is joined to that lattice (``_insert_goal``, ``_join_trees``), the lattice
grows on from its unexpanded poses on the start's and the goal's placements by
``goal_reach_share`` of ``max_poses`` more, by weighted A* (Pohl's static weighting): the path's
length from the start (CoM in plan view plus ``yaw_weight`` m per rad of heading, summed over its
steps) plus ``goal_bias`` times the pose's distance to the goal by the same measure (to the goal's
CoM alone on another placement), and is joined to the goal and its lattice again. It reaches out to a goal
that the breadth-first lattice never nears, and leaves that lattice and its joins (whose short
pivots make short plans) as they were. Once the grasps are known, :func:`extend_lattice` grows it on
from the poses the start reaches by pivots a grasp holds, about those corners only (``stages.sample``).

Pivot corners: the support polygon of a curved foot has many hull vertices on its rim; vertices of a
placement's support polygon closer than ``corner_cluster`` form one corner, represented by the vertex
farthest from the polygon's centre (§4.1's rotational vertices, one under each foot).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import NamedTuple

import fcl
import networkx as nx
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from stages import connect, fclmesh, mpc, se3
from stages.analyze import _polygon_margins
from stages.errors import InputError

PRIMITIVES = ("start", "goal", "pivot", "tumble")


@dataclass(frozen=True)
class Params:
    """Pose sampling parameters (m, rad)."""

    theta_t: float = np.radians(15.0)
    max_poses: int = 400
    usp: bool = True
    sp_margin: float = 0.005
    corner_cluster: float = 0.03
    #: The pivots' tilt (rad, the scene's ``planner.tilt_deg``): a corner the object cannot be tilted onto
    #: alone is no pivot corner (:func:`tilt_direction`).
    tilt: float = np.radians(8.0)
    min_tumble_edge: float = 0.05
    merge_xy: float = 1e-4
    merge_yaw: float = 1e-4
    #: Goal insertion: lattice poses tried (nearest first), connections kept, largest pivot angle.
    goal_candidates: int = 40
    goal_connections: int = 6
    goal_max_angle: float = np.radians(30.0)
    #: A lattice grown from the goal as well (``goal_tree_share`` of ``max_poses`` kept poses more),
    #: joined to the start's by up to ``tree_joins`` closed-form pivot sequences between the
    #: ``tree_candidates`` nearest pairs (a heading difference weighs ``yaw_weight`` m per rad); 0:
    #: the start's lattice alone.
    goal_tree_share: float = 0.25
    tree_joins: int = 12
    #: Each closed-form join is also made avoiding each corner it used, up to this many corners
    #: (:func:`_connect`): which corners a grasp holds is known only after the lattice.
    join_alternatives: int = 3
    tree_candidates: int = 80
    yaw_weight: float = 0.2
    #: The last resort of the grasp-aware reach (:func:`walk_lattice`): the ``walk_candidates`` nearest
    #: pairs joined by a pivot walk of at most ``walk_strides`` two-pivot strides, each pivot at most
    #: ``theta_t`` (the lattice's own step), before the closed form (``connect.walk_planar``); 0: none.
    walk_strides: int = 12
    walk_candidates: int = 20
    #: After its ``max_poses`` breadth first and the goal's joins, the start's lattice grows on from its
    #: unexpanded poses on the start's and the goal's placements by ``goal_reach_share`` of ``max_poses``
    #: kept poses more, by weighted A* toward the goal: path length from the start plus ``goal_bias``
    #: times the distance to the goal (CoM in plan view plus ``yaw_weight`` m per rad of heading on the
    #: goal's placement); 0: breadth first alone.
    goal_reach_share: float = 0.0
    goal_bias: float = 4.0
    #: USP: the object rests on at least this much table (m, along its contact with the table) and
    #: its CoM lies at most this far beyond that contact (m), where one ball holds it.
    min_usp_edge: float = 0.05
    max_usp_overhang: float = 0.15
    #: USP: the CoM lies at least this far (m) beyond the contact. What the plan knows of the CoM is
    #: off by up to ~1.5 cm in execution: the object's CoM up to 1 cm per axis (``pivot execute
    #: --seed``'s perturbation, a mass model's honest error), its position 2-3 mm from the plan after a
    #: tumble and a few mm more per hand-over (measured on Exp. 3); a pose nearer the edge than that
    #: may stand alone or tip either way, so the plan could rely on a hold the object does not need or
    #: leave it where it tips. 2 cm clears that error (about 5 % of the piano's 0.43 m).
    usp_margin: float = 0.02
    #: Expansions a placement other than the start's and the goal's gets per one of theirs.
    other_share: float = 0.1
    #: The object in motion (a pivot's tilt, turn and lowering; a tumble) keeps this far (m) from the
    #: obstacles and the robot's trunk: physics moves it a few mm off its plan (tilt, slip). A pose at
    #: rest only must not overlap them.
    sweep_clearance: float = 0.01
    #: How far from coplanar the hull triangles of one placement face may be (rad): the analysis'
    #: ``hull_coplanar_deg``. A face's corners lie off its plane by up to about its tangent times the
    #: face's size, which the goal's pivots (``connect.Params.face_tilt``) must not take for an error.
    face_tilt: float = np.radians(0.5)


@dataclass(frozen=True)
class ObjectModel:
    """What pose sampling needs of the analysis, frame O (arrays as read from the artifacts)."""

    vertices: np.ndarray  # (V, 3) hull corner vertices
    edges: np.ndarray  # (E, 2) hull vertex ids
    edge_faces: np.ndarray  # (E, 2) placement ids on both sides
    edge_angle: np.ndarray  # (E,) rad between the two faces' normals
    normals: np.ndarray  # (G, 3) outward placement normals
    X_TO: np.ndarray  # (G, 4, 4) resting transforms
    support: list  # G arrays of hull vertex ids
    stable: np.ndarray  # (G,) bool: SP when wholly on the table
    com: np.ndarray  # (3,)
    mesh_vertices: np.ndarray  # (n, 3) object mesh, for obstacle checks
    mesh_faces: np.ndarray  # (m, 3)
    #: per placement, its support triangles and hull rim (:func:`support_sets`), derived on construction
    supports: tuple = field(init=False, repr=False, compare=False)
    #: the mesh's fcl bounding-volume hierarchy, built on first use (:func:`_object_fcl`)
    bvh: list = field(default_factory=list, init=False, repr=False, compare=False)
    #: pivot tilt directions by (vertex, tilt, table normal in O), on first use (:func:`tilt_direction`)
    tilt_dirs: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "supports", support_sets(self.mesh_vertices, self.mesh_faces, self.X_TO))


class SupportSet(NamedTuple):
    """The mesh where it lies in one placement's support plane (frame O): what :func:`table_support` needs.

    vertices : (u, 3) float m, the vertices of the mesh triangles within ``tol`` of the plane.
    faces : (k, 3) int, those triangles, as indices into ``vertices``.
    rim : (r, 3) float m, the vertices within ``RIM_TOL`` of their convex hull's boundary in the plane
        (hull vertices and the points on its edges): wholly on the table, the contact polygon is the
        hull of these and the support corners, whatever the pose on the placement.
    """

    vertices: np.ndarray
    faces: np.ndarray
    rim: np.ndarray


#: Distance (m) within which a support vertex counts as on its hull's boundary (:class:`SupportSet`):
#: far above the 1e-9 m rounding and the 1e-12 m^2 collinearity test of :func:`_convex_hull_2d`, so the
#: rim keeps every point that hull can return.
RIM_TOL = 1e-7
#: Distance (m) from a placement's plane within which a mesh vertex lies in it (:func:`table_support`).
SUPPORT_TOL = 1e-4


def support_sets(vertices: np.ndarray, faces: np.ndarray, X_TO: np.ndarray, tol: float = SUPPORT_TOL) -> tuple:
    """One :class:`SupportSet` per placement (``X_TO (G, 4, 4)``) of the mesh ``vertices (n, 3)`` m,
    ``faces (m, 3)``: computed once, so that the per-pose :func:`table_support` does not rescan the mesh."""
    out = []
    for Xp in np.asarray(X_TO, dtype=float).reshape(-1, 4, 4):
        z = vertices @ Xp[2, :3] + Xp[2, 3]
        used, local = np.unique(faces[np.all(np.abs(z[faces]) < tol, axis=1)], return_inverse=True)
        xy = vertices[used] @ Xp[:2, :3].T
        rim = np.arange(len(used))
        if len(used) >= 3:
            try:
                eq = ConvexHull(xy).equations
                rim = rim[(xy @ eq[:, :2].T + eq[:, 2]).max(axis=1) >= -RIM_TOL]
            except QhullError:  # collinear or coincident: every point may be on the hull
                pass
        out.append(SupportSet(vertices[used], local.reshape(-1, 3), vertices[used[rim]]))
    return tuple(out)


@dataclass(frozen=True)
class PoseSet:
    """Sampled poses (struct of arrays) and the pivot/tumble links between them."""

    X_WO: np.ndarray  # (N, 4, 4)
    placement: np.ndarray  # (N,) int
    support: np.ndarray  # (N,) str: "SP", "USP"
    status: np.ndarray  # (N,) str: "ok", "off_table", "unstable", "obstacle"
    parent: np.ndarray  # (N,) int, -1 for the start
    primitive: np.ndarray  # (N,) str: start / pivot / tumble
    vertex: np.ndarray  # (N,) int pivot vertex (hull id), -1 otherwise
    edge: np.ndarray  # (N, 2) int tumble edge vertex ids, -1 otherwise
    angle: np.ndarray  # (N,) rad, signed rotation from the parent
    margin: np.ndarray  # (N,) m, CoM margin inside the on-table support polygon (< 0 outside)
    links: np.ndarray  # (L, 2) pose ids (a, b), both kept
    link_primitive: np.ndarray  # (L,) str pivot / tumble
    link_vertex: np.ndarray  # (L,) int
    link_edge: np.ndarray  # (L, 2) int
    link_angle: np.ndarray  # (L,) rad, rotation from a to b
    goal_id: int = -1  # the goal's pose id, -1 when not asked for or not reached


class PivotCorners:
    """Per placement ``g``, ``corners[g]``: the hull vertex ids of its support-polygon corners (one per
    ``cluster``); with ``tilt`` (rad), only those the object can be tilted onto alone
    (:func:`tilt_direction`). Each placement's are found on first use: a rounded mesh has hundreds of
    placements (the duck 893, at 10-40 ms of tilt search a corner) of which a lattice visits a few.
    :meth:`holding` fixes one placement's to a subset, sharing the rest."""

    def __init__(self, model: ObjectModel, cluster: float, tilt: float | None = None):
        self.model, self.cluster, self.tilt = model, cluster, tilt
        self._found: dict[int, np.ndarray] = {}
        self._fixed: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.model.support)

    def __getitem__(self, g: int) -> np.ndarray:
        g = int(g)
        if g in self._fixed:
            return self._fixed[g]
        if g not in self._found:
            self._found[g] = _placement_corners(self.model, g, self.cluster, self.tilt)
        return self._found[g]

    def table(self, placements) -> np.ndarray:
        """``(G, k)`` corner ids per placement, sorted and padded with -1, filled for ``placements``
        only (the others all -1); ``k`` their most corners, at least 1."""
        placed = np.unique(np.asarray(placements, dtype=np.int64)).tolist()
        out = -np.ones((len(self), max([1, *(len(self[g]) for g in placed)])), np.int64)
        for g in placed:
            out[g, :len(self[g])] = self[g]
        return out

    def holding(self, g: int, ids: np.ndarray) -> PivotCorners:
        """These corners with placement ``g``'s replaced by ``ids``."""
        out = PivotCorners(self.model, self.cluster, self.tilt)
        out._found, out._fixed = self._found, {**self._fixed, int(g): ids}
        return out


def pivot_corners(model: ObjectModel, cluster: float, tilt: float | None = None) -> PivotCorners:
    """Per placement, the hull vertex ids of its support-polygon corners (:class:`PivotCorners`)."""
    return PivotCorners(model, cluster, tilt)


def _placement_corners(model: ObjectModel, g: int, cluster: float, tilt: float | None) -> np.ndarray:
    """:class:`PivotCorners` of placement ``g``: its support vertices farthest from their centre first,
    each at least ``cluster`` (m) from those chosen, sorted; with ``tilt``, those it tilts onto."""
    sup = np.asarray(model.support[g], dtype=np.int64)
    p = se3.transform_points(model.X_TO[g], model.vertices[sup])[:, :2]
    centre = p.mean(axis=0)
    far = np.linalg.norm(p - centre, axis=1)
    order = np.argsort(-far, kind="stable")
    chosen: list[int] = []
    for i in order:  # a handful of vertices per face
        if all(np.linalg.norm(p[i] - p[j]) >= cluster for j in chosen):
            chosen.append(i)
    ids = np.sort(sup[chosen])
    if tilt is not None:
        ids = np.array([v for v in ids if _tilt_dir_O(model, v, model.X_TO[g], tilt) is not _NO_TILT],
                       dtype=np.int64)
    return ids


#: The most (m) a hull vertex may sink below the table's plane when the object tilts onto a pivot
#: corner: a flat-bottomed mesh's rim vertices lie within a fraction of a millimetre of its plane,
#: which the contact's compliance takes; a deeper one would carry the object instead of the corner.
TILT_TOLERANCE = 1e-3
#: The height (m) the tilt direction keeps the other hull vertices above the table where some
#: direction can: a vertex that touches (or nearly) drags on the table while the object turns about
#: the corner, a friction torque the pivot's model leaves out. Vertices closer than
#: ``TILT_CORNER_RADIUS`` (m, horizontally) to the corner are the corner itself (a rounded tip).
TILT_CLEARANCE = 1e-3
TILT_CORNER_RADIUS = 5e-3
_TILT_ANGLES = np.radians(np.arange(0.0, 360.0, 0.5))
_NO_TILT = np.zeros(0)  # sentinel: no direction stands the object on the corner


def tilt_direction(model: ObjectModel, X_WO: np.ndarray, v: int, tilt: float) -> np.ndarray | None:
    """The horizontal unit direction (W) whose side rises when the object at ``X_WO`` (resting on the
    table) tilts by ``tilt`` (rad) onto its hull vertex ``v``: ``mpc.pivot_reference``'s ``tilt_dir``
    (§5.2.1, Fig. 12; its tilt axis is ``d x z``). None when the default, the direction from the
    vertex to the CoM, works: at the full tilt no hull vertex sinks below the table by more than
    ``TILT_TOLERANCE`` and those apart from the corner (``TILT_CORNER_RADIUS``) stay
    ``TILT_CLEARANCE`` above it, or as high as the best direction keeps them, so the object stands on
    ``v`` alone and turns about it. Otherwise the direction nearest to the CoM's (less than 90 deg
    off, 0.5 deg steps) that does: next to a wide corner or a rounded rim the CoM's would roll the
    object onto a neighbour, or let it drag one, which physics then turns about instead. Raises
    ``InputError`` when no direction does (``pivot_corners`` with ``tilt`` leaves such corners out).
    Yaw and shift do not change it: solved once per (vertex, table normal in O)."""
    d_O = _tilt_dir_O(model, v, X_WO, tilt)
    if d_O is _NO_TILT:
        raise InputError(f"no tilt by {np.degrees(tilt):.1f} deg stands the object on its vertex {v}")
    if d_O is None:
        return None
    d = X_WO[:3, :3] @ d_O
    d[2] = 0.0
    return d / np.linalg.norm(d)


def _tilt_dir_O(model: ObjectModel, v: int, X_WO: np.ndarray, tilt: float):
    """:func:`tilt_direction` in frame O: None (the CoM's direction), ``_NO_TILT`` or a unit (3,)."""
    up = np.round(X_WO[2, :3], 9)
    key = (int(v), float(tilt), *up.tolist())
    if key in model.tilt_dirs:
        return model.tilt_dirs[key]
    up = up / np.linalg.norm(up)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    E = np.stack([e1, np.cross(up, e1)])                                  # (2, 3) the table's plane in O
    q = model.vertices - model.vertices[v]
    z, s = q @ up, q @ E.T                                                # height, horizontal offset
    dc = (model.com - model.vertices[v]) @ E.T
    dc = dc / np.linalg.norm(dc) if np.linalg.norm(dc) > 1e-9 else np.array([1.0, 0.0])

    far = np.linalg.norm(s, axis=1) >= TILT_CORNER_RADIUS

    def lowest(D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # (A, 2) -> every vertex's, the far ones'
        h = z[:, None] * np.cos(tilt) + np.sin(tilt) * (s @ D.T)
        return h.min(axis=0), np.where(far[:, None], h, np.inf).min(axis=0)

    low_c, low_far_c = lowest(dc[None])
    if low_c[0] >= -TILT_TOLERANCE and low_far_c[0] >= TILT_CLEARANCE - 1e-9:  # clears: no search
        model.tilt_dirs[key] = None
        return None
    D = np.stack([np.cos(_TILT_ANGLES), np.sin(_TILT_ANGLES)], axis=1)
    cosa = D @ dc
    low, low_far = lowest(D)
    ok = (low >= -TILT_TOLERANCE) & (cosa > 0.0)
    # The clearance to seek: TILT_CLEARANCE, or the best one an allowed direction gives when less.
    want = min(TILT_CLEARANCE, float(np.max(np.where(ok, low_far, -np.inf)))) if ok.any() else np.inf
    if low_c[0] >= -TILT_TOLERANCE and low_far_c[0] >= want - 1e-9:  # a nanometre: the grid's rounding
        out = None
    else:
        ok &= low_far >= want
        out = D[np.argmax(np.where(ok, cosa, -2.0))] @ E if ok.any() else _NO_TILT
    model.tilt_dirs[key] = out
    return out


def sample_poses(model: ObjectModel, X_WO_start: np.ndarray, start_placement: int, table_size, obstacles,
                 params: Params, goal: tuple[np.ndarray, int] | None = None) -> PoseSet:
    """Pose lattice from the start (see the module docstring): :func:`build_lattice`'s poses."""
    return build_lattice(model, X_WO_start, start_placement, table_size, obstacles, params, goal).pose_set()


def build_lattice(model: ObjectModel, X_WO_start: np.ndarray, start_placement: int, table_size, obstacles,
                  params: Params, goal: tuple[np.ndarray, int] | None = None) -> _Lattice:
    """The pose lattice from the start (see the module docstring), kept growable (:func:`extend_lattice`).

    ``obstacles`` is a sequence of ``stages.scene.ObstacleGeometry``; ``table_size`` (sx, sy) m;
    ``goal`` ``(X_WO (4, 4), placement)`` is joined to the lattice afterwards (``_insert_goal``).
    """
    lat = _Lattice(model, table_size, obstacles, params)
    rows, add = lat.rows, lat.add
    lat.share = {int(start_placement): 1.0} | ({int(goal[1]): 1.0} if goal is not None else {})
    first, _ = add(np.asarray(X_WO_start, dtype=float), int(start_placement), -1, "start", -1, (-1, -1), 0.0)
    popped = lat.grow([first], params.max_poses)  # breadth first, at most max_poses poses
    n_tree = len(rows)
    if goal is None:
        return lat
    goal_id = lat.goal_id = _insert_goal(lat, *goal, params)
    n_start = len(rows)

    def ok(lo: int, hi: int) -> list[int]:  # the kept poses of rows lo..hi - 1 but the goal
        return [i for i in range(lo, hi) if rows[i]["status"] == "ok" and i != goal_id]

    if goal_id >= 0 and params.goal_tree_share > 0:
        start_keys = np.array([r["key"] for r in rows[:n_tree] if r["status"] == "ok"], dtype=float)  # start first
        lat.grow([goal_id], int(np.ceil(params.goal_tree_share * params.max_poses)), toward=start_keys)
        _join_trees(lat, ok(0, n_start), [goal_id, *ok(n_start, len(rows))], params)
    if goal_id >= 0 and params.goal_reach_share > 0:  # on from the unexpanded poses, A* toward the goal
        n_reach = len(rows)
        leaves = [i for i in ok(0, n_tree) if i not in popped]
        lat.grow(leaves, int(np.ceil(params.goal_reach_share * params.max_poses)),
                 toward=np.array([rows[goal_id]["key"]], dtype=float), bias=params.goal_bias,
                 cost=_tree_costs(rows, params), only={int(start_placement), int(goal[1])})
        n_grown = len(rows)
        _join_goal(lat, goal_id, range(n_reach, n_grown), params)
        _join_trees(lat, ok(n_reach, n_grown), [goal_id, *ok(n_start, n_reach)], params)
    return lat


def walk_lattice(lat: _Lattice, start_side: list[int], goal_side: list[int]) -> int:
    """The grasp-aware reach's last resort (``stages.sample``): join the poses the start reaches
    (``start_side``, row ids) to those the goal reaches (``goal_side``, the goal first) by pivot walks
    (``Params.walk_strides``, ``connect.walk_planar``) where no closed-form join or grown lattice met
    them. A small base moves a few cm per pivot, so lattices a decimetre apart never meet by three
    pivots. A walk may pivot about any corner: the grasps of its poses, and so which corners they
    hold, are refined after it. Returns the joins made."""
    start_side = [i for i in start_side if lat.rows[i]["status"] == "ok"]
    if not start_side or not goal_side or lat.params.walk_strides <= 0:
        return 0
    return _join_trees(lat, start_side, list(goal_side), lat.params, None, lat.params.walk_strides)


def extend_lattice(lat: _Lattice, start_side: list[int], goal_side: list[int], usable: dict[int, np.ndarray],
                   budget: int) -> None:
    """Grasp-aware reach (our addition to §5.1, §5.3): grow the lattice from the poses the start reaches
    by pivots some grasp can make (``start_side``, row ids) toward those the goal reaches
    (``goal_side``, the goal first), pivoting each pose whose grasps are known only about the corners
    they hold (``usable``: row id -> hull vertex ids; a pose not in it may pivot about any corner).

    First closed-form joins (:func:`_join_trees`) between the two sides, about corners both ends hold;
    then weighted A* (``goal_bias``) from the start's side on the start's and the goal's placements by
    ``budget`` kept poses, whose new poses are joined to the goal's side in turn. Which grasps a pose
    has is known only after the grasp refinement, so the sample stage alternates the two
    (``stages.sample``). Adds rows and links to ``lat``."""
    rows, params = lat.rows, lat.params
    start_side, goal_side = [i for i in start_side if rows[i]["status"] == "ok"], list(goal_side)
    if not start_side or not goal_side:
        return
    _join_trees(lat, start_side, goal_side, params, usable)
    n_grown = len(rows)
    only = {rows[start_side[0]]["g"], rows[goal_side[0]]["g"]}
    lat.grow(start_side, budget, toward=np.array([rows[i]["key"] for i in goal_side], dtype=float),
             bias=params.goal_bias, cost=_tree_costs(rows, params), only=only, usable=usable)
    grown = [i for i in range(n_grown, len(rows)) if rows[i]["status"] == "ok"]
    _join_trees(lat, grown, goal_side, params, usable)


class _Lattice:
    """The pose lattice as it grows: its poses (``rows``, dicts with ``X``, ``g``, ``kind``, ``status``,
    ``parent``, ``primitive``, ``vertex``, ``edge``, ``angle``, ``margin``, ``key``), the links between
    kept poses, and a spatial hash of the keys that merges twins (module docstring)."""

    def __init__(self, model: ObjectModel, table_size, obstacles, params: Params):
        self.model, self.params, self.obstacles = model, params, obstacles
        self.corners = pivot_corners(model, params.corner_cluster, params.tilt)
        self.half = np.asarray(table_size, dtype=float) / 2
        self.collide = _make_object_collision_fn(model, obstacles)
        self.sweep_collide = _make_object_collision_fn(model, obstacles, params.sweep_clearance)
        self.rows: list[dict] = []
        self.links: list[tuple] = []
        self.index: dict[tuple, list[int]] = {}
        self.share: dict[int, float] = {}  # expansions per turn of the placements (module docstring)
        self.goal_id = -1
        self.walks = 0  # joins made by a pivot walk (:func:`_connect_via`)

    def pose_set(self) -> PoseSet:
        """The lattice's poses and links so far (row id = pose id)."""
        return _to_pose_set(self.rows, self.links, self.goal_id)

    def corners_at(self, i: int, usable: dict[int, np.ndarray] | None) -> PivotCorners:
        """The pivot corners per placement for row ``i``: those its grasps hold where ``usable`` knows them."""
        return _held(self.corners, self.rows[i]["g"], (i,), usable)

    def key_of(self, X: np.ndarray, g: int) -> tuple[int, float, float, float]:
        """(placement, CoM x, CoM y, yaw) of the object at ``X`` on placement ``g`` (m, rad, W)."""
        com = se3.transform_points(X, self.model.com)
        R = X[:3, :3] @ self.model.X_TO[g][:3, :3].T
        return g, com[0], com[1], float(se3.yaw_of(R))

    def find(self, k) -> int:
        """The row of the pose with key ``k`` up to ``merge_xy`` and ``merge_yaw``, or -1."""
        g, x, y, yaw = k
        m = self.params.merge_xy
        cx, cy = int(np.floor(x / m)), int(np.floor(y / m))
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for i in self.index.get((g, cx + dx, cy + dy), ()):
                    _, x2, y2, yaw2 = self.rows[i]["key"]
                    dyaw = abs((yaw - yaw2 + np.pi) % (2 * np.pi) - np.pi)
                    if np.hypot(x - x2, y - y2) < m and dyaw < self.params.merge_yaw:
                        return i
        return -1

    def add(self, X, g, parent, primitive, vertex, edge, angle) -> tuple[int, bool]:
        """Add a pose (or find its twin); returns its row and whether it is new."""
        rows, model = self.rows, self.model
        k = self.key_of(X, g)
        found = self.find(k)
        swept_hit = parent >= 0 and self.obstacles and _swept_hits(model, self.sweep_collide, rows[parent]["X"], X,
                                                                   primitive, vertex, edge, self.params.tilt)
        if found >= 0:
            if parent >= 0 and rows[found]["status"] == "ok" and found != parent and not swept_hit:
                self.links.append((parent, found, primitive, vertex, edge, angle))
            return found, False
        status, kind, margin = classify_pose(model, X, g, self.half, self.collide, self.params)[:3]
        if swept_hit and status == "ok":
            status = "obstacle"
        i = len(rows)
        rows.append(dict(X=X, g=g, kind=kind, status=status, parent=parent, primitive=primitive, vertex=vertex,
                         edge=edge, angle=angle, margin=margin, key=k))
        m = self.params.merge_xy
        self.index.setdefault((g, int(np.floor(k[1] / m)), int(np.floor(k[2] / m))), []).append(i)
        if status == "ok" and parent >= 0:
            self.links.append((parent, i, primitive, vertex, edge, angle))
        return i, True

    def _priority(self, j: int, toward, bias: float, cost: dict) -> float:
        if toward is None:
            return float(j)  # breadth first
        near = _nearness(self.rows[j]["key"], toward, self.params)
        return near if bias < 0 else cost[j] + bias * near

    def grow(self, roots: list[int], budget: int, toward: np.ndarray | None = None, bias: float = -1.0,
             cost: dict | None = None, only: set | None = None, usable: dict[int, np.ndarray] | None = None) -> set:
        """Expand from ``roots`` until ``budget`` new kept poses (module docstring: placements take
        turns): breadth first; nearest first to the lattice whose keys are ``toward`` (``_nearness``,
        greedy, ``bias`` < 0); or weighted A* toward it, ``bias`` >= 0: the path's length from the start
        (``cost`` of the roots, :func:`_step_cost` summed on) plus ``bias`` times the nearness. The
        roots count in the budget unless ``cost`` is given (they are already in the lattice); with
        ``only``, poses on other placements are kept but not expanded; with ``usable``, a pose it knows pivots
        only about its corners there (:meth:`corners_at`). Returns the rows expanded."""
        rows, params = self.rows, self.params
        queues: dict[int, list] = {}  # per placement, a heap of (priority, row)
        expanded: dict[int, int] = {}
        popped: set = set()
        fresh = cost is None
        cost = {r: 0.0 for r in roots} if fresh else cost  # path length from the start (m)

        def push(j: int) -> None:
            if only is None or rows[j]["g"] in only:
                heapq.heappush(queues.setdefault(rows[j]["g"], []), (self._priority(j, toward, bias, cost), j))
                expanded.setdefault(rows[j]["g"], 0)

        for r in roots:
            if rows[r]["status"] == "ok":
                push(r)
        n_ok = sum(len(q) for q in queues.values()) if fresh else 0
        while n_ok < budget:
            open_ = [g for g in queues if queues[g]]
            if not open_:
                break
            g = min(open_, key=lambda g: (expanded[g] / self.share.get(g, params.other_share), queues[g][0]))
            i = heapq.heappop(queues[g])[1]
            expanded[g] += 1
            popped.add(i)
            for child in _successors(self.model, self.corners_at(i, usable), rows[i]["X"], g, self.half, params):
                if n_ok >= budget:
                    break
                j, new = self.add(child[0], child[1], i, *child[2:])
                if new and rows[j]["status"] == "ok":
                    n_ok += 1
                    cost[j] = cost[i] + _step_cost(rows[i]["key"], rows[j]["key"], params)
                    push(j)
        return popped


def classify_pose(model: ObjectModel, X: np.ndarray, g: int, half: np.ndarray, collide,
                  params: Params) -> tuple[str, str, float, str]:
    """Whether the object at ``X_WO (4, 4)`` on placement ``g`` can be a pose (module docstring).

    ``half (2,)`` m is half the table's size, ``collide`` a :func:`_make_object_collision_fn`.
    Returns ``(status, support, margin, why)``: ``ok`` / ``off_table`` / ``unstable`` / ``obstacle``,
    ``SP`` / ``USP``, the CoM's margin (m) inside the table contact (``-inf`` without one), and why
    the pose is refused, in words for a user ("" when ok; an obstacle is named by
    :func:`describe_pose`).
    """
    contact = table_support(model, X, g, half)
    com = se3.transform_points(X, model.com)
    if len(contact) < 2:
        return "off_table", "USP", -np.inf, "its support face is not on the table"
    margin = _margin(contact, com[:2])
    extent = _extent(contact)
    if margin >= params.sp_margin:
        kind = "SP"  # it stands alone, however small its contact (the duck has stable faces 3 cm wide)
    elif extent < params.min_usp_edge:
        return "off_table", "USP", -np.inf, (f"it is over the table's edge with {extent:.3f} m of its support on "
                                            f"the table (a USP pose needs {params.min_usp_edge:g} m)")
    elif not params.usp:
        where = f"{-margin:.3f} m beyond" if margin < 0 else f"only {margin:.3f} m inside"
        return "unstable", "USP", margin, (f"its CoM is {where} its contact with the table (SP needs "
                                           f"{params.sp_margin:g} m inside) and the planner does not allow USP")
    elif -margin < params.usp_margin:
        return "unstable", "USP", margin, (f"its CoM is {-margin:.4f} m beyond its contact with the table, between "
                                           f"SP ({params.sp_margin:g} m inside) and USP ({params.usp_margin:g} m "
                                           f"beyond): it may stand or tip")
    elif -margin > params.max_usp_overhang:
        return "off_table", "USP", margin, (f"its CoM is {-margin:.3f} m beyond its contact with the table's edge "
                                            f"(a USP pose allows {params.max_usp_overhang:g} m)")
    else:
        kind = "USP"
    if collide(X):
        return "obstacle", kind, margin, "it hits an obstacle"
    return "ok", kind, margin, ""


def describe_pose(model: ObjectModel, X: np.ndarray, g: int, table_size, obstacles,
                  params: Params) -> tuple[str, str]:
    """``(status, why)`` of one pose as :func:`classify_pose` has them, an obstacle named: "it hits
    robot:torso_link" (``ObstacleGeometry.name``), so that a scene's start or goal that cannot be a
    pose is refused with what it hits. ``table_size`` (sx, sy) m; ``obstacles`` as in
    :func:`sample_poses`."""
    half = np.asarray(table_size, dtype=float) / 2
    status, _, _, why = classify_pose(model, X, g, half, _make_object_collision_fn(model, obstacles), params)
    if status == "obstacle":
        why = "it hits " + ", ".join(obstacles_hit(model, X, obstacles))
    return status, why


def _insert_goal(lat: _Lattice, X_goal, g_goal, params: Params) -> int:
    """Join the goal pose to the lattice (§5.3): by up to three pivots from the nearest kept poses on
    the goal's placement (``stages.connect``, the controllability of pivoting [18]), first from the
    nearest pose of each subtree (the poses pivoted from one tumble landing, or from the start), so
    that every way onto the goal's placement gets its chance. Returns the goal's pose id, or -1 when
    no sequence of kept poses reaches it."""
    rows, add = lat.rows, lat.add
    goal, new = add(np.asarray(X_goal, dtype=float), int(g_goal), -1, "goal", -1, (-1, -1), 0.0)
    if not new or rows[goal]["status"] != "ok":
        return goal if rows[goal]["status"] == "ok" else -1
    _join_goal(lat, goal, range(len(rows)), params)
    return goal


def _join_goal(lat: _Lattice, goal: int, among, params: Params) -> int:
    """Join pose ``goal`` by up to three pivots from the nearest kept poses ``among`` (row ids) on its
    placement, the nearest of each subtree first (:func:`_insert_goal`), until ``goal_connections``
    joins are made or ``goal_candidates`` poses were tried. Returns the joins made."""
    model, rows = lat.model, lat.rows
    X_goal, g_goal = rows[goal]["X"], rows[goal]["g"]
    c_goal = se3.transform_points(X_goal, model.com)[:2]
    cand = [i for i in among if rows[i]["status"] == "ok" and rows[i]["g"] == g_goal and i != goal]
    cand.sort(key=lambda i: float(np.linalg.norm(se3.transform_points(rows[i]["X"], model.com)[:2] - c_goal)))

    def root(i: int) -> int:  # the start or the tumble landing whose pivots reached pose i
        while rows[i]["primitive"] == "pivot":
            i = rows[i]["parent"]
        return i

    firsts, seen = [], set()  # the nearest pose of each subtree first, then the nearest others
    for i in cand:
        if root(i) not in seen:
            seen.add(root(i))
            firsts.append(i)
    cand = firsts[: params.goal_candidates] + [i for i in cand[: params.goal_candidates] if i not in firsts]
    joined = 0
    for i in cand:  # a few dozen closed-form solves
        joined += _connect(lat, lat.corners, i, X_goal, g_goal, params) == goal
        if joined >= params.goal_connections:
            break
    return joined


def _nearness(key: tuple, others: np.ndarray, params: Params) -> float:
    """How far a pose is from a lattice it grows toward (m): the least, over that lattice's poses on
    its placement, of the CoM distance in plan view plus ``yaw_weight`` m per rad of heading; with
    none there, the CoM distance to ``others``' first pose (the root). ``key`` is (placement, CoM x,
    CoM y, yaw); ``others (n, 4)`` the lattice's keys, its root first."""
    same = others[others[:, 0] == key[0]]
    if not len(same):
        return float(np.hypot(key[1] - others[0, 1], key[2] - others[0, 2]))
    dyaw = np.abs((key[3] - same[:, 3] + np.pi) % (2 * np.pi) - np.pi)
    return float(np.min(np.hypot(key[1] - same[:, 1], key[2] - same[:, 2]) + params.yaw_weight * dyaw))


def _tree_costs(rows: list[dict], params: Params) -> dict:
    """Each kept pose's path length from its tree's root (m) along its parents (:func:`_step_cost`)."""
    cost: dict = {}
    for i, r in enumerate(rows):  # a parent precedes its children
        p = r["parent"]
        cost[i] = 0.0 if p < 0 or p not in cost else cost[p] + _step_cost(rows[p]["key"], r["key"], params)
    return cost


def _step_cost(a: tuple, b: tuple, params: Params) -> float:
    """Length (m) of one lattice step between pose keys ``a`` and ``b`` (placement, CoM x, y, yaw): the
    CoM's distance in plan view plus ``yaw_weight`` m per rad of heading (on one placement)."""
    dyaw = abs((a[3] - b[3] + np.pi) % (2 * np.pi) - np.pi) if a[0] == b[0] else 0.0
    return float(np.hypot(a[1] - b[1], a[2] - b[2]) + params.yaw_weight * dyaw)


def _join_trees(lat: _Lattice, a: list[int], b: list[int], params: Params,
                usable: dict[int, np.ndarray] | None = None, strides: int = 0) -> int:
    """Join kept poses ``b`` (the goal and the lattice grown from it) to kept poses ``a`` (the start's
    lattice, or the part of it grown toward the goal) by up to three pivots (``stages.connect``)
    between the nearest pairs of poses on one placement, nearest first (CoM distance plus
    ``yaw_weight`` m per rad of heading), until ``tree_joins`` joins are made or ``tree_candidates``
    pairs were tried. Returns the joins made.

    The start's lattice reaches the goal only when its few closed-form joins find grasps at every pose
    they pass; a lattice grown from the goal as well gives the search many more places to meet (§5.3's
    graph search then picks among them, with the motion checks deciding). With ``usable`` (row id -> hull
    vertex ids its grasps hold), a join pivots only about the corners both its ends hold, where known.
    With ``strides``, the ``walk_candidates`` nearest pairs are joined by pivot walks instead.
    """
    rows = lat.rows
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    if not len(a) or not len(b):
        return 0
    key = np.array([r["key"][:4] for r in rows], dtype=float)  # placement, CoM x, y, yaw
    d = np.hypot(key[a, 1][:, None] - key[b, 1][None], key[a, 2][:, None] - key[b, 2][None])
    dyaw = np.abs((key[a, 3][:, None] - key[b, 3][None] + np.pi) % (2 * np.pi) - np.pi)
    cost = np.where(key[a, 0][:, None] == key[b, 0][None], d + params.yaw_weight * dyaw, np.inf)
    order = np.argsort(cost, axis=None, kind="stable")[: params.walk_candidates if strides else params.tree_candidates]
    joined = 0
    for flat in order:  # a few dozen closed-form solves, or a few walks
        i, j = a[flat // len(b)], b[flat % len(b)]
        if not np.isfinite(cost.flat[flat]) or joined >= params.tree_joins:
            break
        cs = _held(lat.corners, rows[j]["g"], (int(i), int(j)), usable)
        joined += _connect(lat, cs, int(i), rows[j]["X"], rows[j]["g"], params, strides) == j
    return joined


def _held(corners: PivotCorners, g: int, rows: tuple[int, ...], usable: dict[int, np.ndarray] | None):
    """``corners`` (hull vertex ids per placement) with placement ``g``'s cut to those the grasps of every
    row in ``rows`` hold, where ``usable`` (row id -> vertex ids) knows them (:func:`extend_lattice`)."""
    if usable is None:
        return corners
    ids = corners[g]
    for k in rows:
        if k in usable:
            ids = np.intersect1d(ids, usable[k])
    return corners.holding(g, ids)


def _connect(lat: _Lattice, corners, i: int, X_to: np.ndarray, g: int, params: Params, strides: int = 0) -> int:
    """Pivot from kept pose ``i`` to ``X_to`` on placement ``g`` by up to three closed-form pivots
    (``stages.connect``), adding the poses on the way; then by the best sequence that avoids each
    corner the first one used, in turn, up to ``join_alternatives`` more (which corners a grasp
    holds is known only later, so one corner no reachable grasp holds would sink every join through
    it). With ``strides``, by a pivot walk (``connect.walk_planar``) instead. Returns the last kept pose
    the first sequence reached (``i`` when none, or when a pivot is too small to be kept apart from
    its parent)."""
    ids = corners[g]
    first = _connect_via(lat, i, X_to, g, ids, params, strides)
    if first is None:
        return i
    used, end = first
    for c in used[: params.join_alternatives]:
        _connect_via(lat, i, X_to, g, ids[ids != c], params, strides)
    return end


def _connect_via(lat: _Lattice, i: int, X_to: np.ndarray, g: int, ids: np.ndarray, params: Params,
                 strides: int = 0):
    """:func:`_connect` over the corners ``ids`` only: ``(corners used, last kept pose)`` or None."""
    model, rows, add = lat.model, lat.rows, lat.add
    if len(ids) == 0:
        return None
    conn = connect.connect_poses(rows[i]["X"], X_to, model.vertices[ids], connect.Params(
        max_angle=params.goal_max_angle, face_tilt=params.face_tilt),
        face_O=model.vertices[np.asarray(model.support[g], dtype=np.int64)], strides=strides,
        stride_angle=params.theta_t)
    if not conn.ok or np.any(np.abs(conn.angles) < 10 * params.merge_yaw):
        return None
    lat.walks += bool(strides)
    prev = i
    for step in range(len(conn.angles)):  # three pivots, more on a walk
        X = np.asarray(X_to, dtype=float) if step == len(conn.angles) - 1 else conn.poses[step + 1]
        j, _ = add(X, g, prev, "pivot", int(ids[conn.corners[step]]), (-1, -1), float(conn.angles[step]))
        if rows[j]["status"] != "ok":
            break
        prev = j
    return list(dict.fromkeys(int(ids[c]) for c in conn.corners)), prev


def table_support(model: ObjectModel, X: np.ndarray, g: int, half: np.ndarray, tol: float = SUPPORT_TOL) -> np.ndarray:
    """Where the object at ``X`` on placement ``g`` touches the table, ``(k, 2)`` m, W: the convex
    hull of the mesh's triangles that lie in the support plane (within ``tol`` m), each clipped to the
    table top (the table's edge cuts them when the object overhangs), and of the support corners (the
    placement's hull face vertices) that are on the table. Not the support face's hull polygon
    clipped: a piano on two feet with one foot off the table stands on the other foot alone, not on
    the part of the polygon between them.

    The corners count whatever ``tol``: a hull face merges triangles within the analysis'
    ``hull_coplanar_deg``, so on an organic mesh its corners lie up to ~0.2 mm off its mean plane and
    the triangles between them miss ``tol`` (the bunny's base kept 70 % of its area without them).

    The object rests on that polygon; its CoM projection inside it is SP, outside it USP (the object
    tips over the polygon's edge unless a ball holds it, §5.1, Fig. 14).
    """
    if tol == SUPPORT_TOL:
        verts, tri, rim = model.supports[g]
    else:
        verts, tri, rim = support_sets(model.mesh_vertices, model.mesh_faces, model.X_TO[g : g + 1], tol)[0]
    corners = se3.transform_points(X, model.vertices[np.asarray(model.support[g], dtype=np.int64)])[:, :2]
    corners = corners[np.all(np.abs(corners) <= half, axis=1)]
    if len(tri) == 0:
        return _convex_hull_2d(corners).reshape(-1, 2)
    level = abs((X @ se3.invert(model.X_TO[g]))[2, 2] - 1.0) < 1e-12  # a turn about the vertical
    R = se3.transform_points(X, rim)[:, :2]
    if level and np.all(np.abs(R) <= half):  # wholly on the table: the placement's rim suffices
        return _convex_hull_2d(np.concatenate([corners, R])).reshape(-1, 2)
    U = se3.transform_points(X, verts)[:, :2]                                   # (u, 2)
    inside = np.all(np.abs(U) <= half, axis=1)[tri].all(axis=1)                 # (n,) wholly on the table
    beyond = np.any((U > half)[tri].all(axis=1) | (U < -half)[tri].all(axis=1), axis=1)  # all past one side
    kept = np.zeros(len(U), dtype=bool)
    kept[tri[inside].ravel()] = True
    P = U[tri[~beyond & ~inside]]  # (m, 3, 2) only those the table's edge may cut
    n = np.full(len(P), 3)
    for axis in (0, 1):  # Sutherland–Hodgman against the four table sides, all triangles at once
        for sign in (1.0, -1.0):
            P, n = _clip_all(P, n, axis, sign, half[axis])
    clipped = P[np.arange(P.shape[1]) < n[:, None]]
    pts = np.concatenate([corners, U[kept], clipped])
    return _convex_hull_2d(_near_hull(pts)).reshape(-1, 2) if len(pts) else pts


def _clip_all(P: np.ndarray, n: np.ndarray, axis: int, sign: float, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_clip` of many polygons at once: polygon ``i`` is ``P[i, :n[i]]`` (``P (k, w, 2)``);
    returns them clipped the same way (each vertex kept if inside, then the crossing of its edge to
    the next, with the same arithmetic) as ``(P', n')``, ``P' (k, w + 1, 2)``."""
    k, w = P.shape[:2]
    idx = np.arange(w)
    valid = idx < n[:, None]
    nxt = np.where(idx + 1 < n[:, None], idx + 1, 0)
    A, B = P, np.take_along_axis(P, nxt[..., None], axis=1)
    da, db = sign * A[..., axis] - limit, sign * B[..., axis] - limit
    keep = valid & (da <= 0)
    cross = valid & (((da < 0) & (0 < db)) | ((db < 0) & (0 < da)))
    with np.errstate(divide="ignore", invalid="ignore"):
        X = A + (B - A) * (da / (da - db))[..., None]
    cand = np.stack([A, X], axis=2).reshape(k, 2 * w, 2)  # each vertex, then its edge's crossing
    emit = np.stack([keep, cross], axis=2).reshape(k, 2 * w)
    order = np.argsort(~emit, axis=1, kind="stable")[:, : w + 1]
    out = np.take_along_axis(cand, order[..., None], axis=1)
    return out, emit.sum(axis=1)


def _near_hull(p: np.ndarray) -> np.ndarray:
    """The points of ``p (k, 2)`` within ``RIM_TOL`` of their convex hull's boundary (Qhull), all of
    them when Qhull cannot tell (collinear or too few): the only ones :func:`_convex_hull_2d` may keep."""
    if len(p) < 16:
        return p
    try:
        eq = ConvexHull(p).equations
    except QhullError:
        return p
    return p[(p @ eq[:, :2].T + eq[:, 2]).max(axis=1) >= -RIM_TOL]


def _extent(p: np.ndarray) -> float:
    """Largest distance between two of the points ``p (k, 2)``."""
    return float(np.max(np.linalg.norm(p[:, None] - p[None], axis=2))) if len(p) else 0.0


def _successors(model, corners, X, g, half, params):
    """Candidate (X, placement, primitive, vertex, edge, angle) children of one pose."""
    out = []
    for v in corners[g]:
        p = se3.transform_points(X, model.vertices[v])
        if np.any(np.abs(p[:2]) > half):
            continue  # a vertex off the table cannot be the pivot
        for sign in (1.0, -1.0):
            T = se3.transform_about_line(p, np.array([0.0, 0.0, 1.0]), sign * params.theta_t)
            out.append((T @ X, g, "pivot", int(v), (-1, -1), sign * params.theta_t))
    for e in _roll_edges(model, g, params.min_tumble_edge):
        a, b = model.edges[e]
        if np.any(np.abs(se3.transform_points(X, model.vertices[[a, b]])[:, :2]) > half):
            continue
        done = _tumble(model, X, g, e)
        if done is not None:
            out.append((done[0], done[1], "tumble", -1, (int(a), int(b)), done[2]))
    return out


def _roll_edges(model: ObjectModel, g: int, min_edge: float) -> np.ndarray:
    """Ids of the hull edges of face ``g`` at least ``min_edge`` long (m, ``Params.min_tumble_edge``):
    the support edges a tumble from ``g`` may roll over (§5.1, the module docstring)."""
    e = np.flatnonzero((model.edge_faces == g).any(axis=1))
    v = model.vertices[model.edges[e]]
    return e[np.linalg.norm(v[:, 1] - v[:, 0], axis=1) >= min_edge]


def face_route(model: ObjectModel, start: int, goal: int, min_edge: float) -> list[int]:
    """The fewest tumbles' sequence of placements from ``start`` to ``goal`` (ids, both included;
    ``[start]`` when they are one), ``[]`` when no sequence of tumbles leads there.

    A tumble's landing face depends on neither the heading nor the place (the roll is the same in the
    object's frame), so the placements and the tumbles between them form a small directed graph
    (§5.1, Fig. 8): an arc g -> h when the object resting on the stable placement g rolls over one of
    its support edges at least ``min_edge`` long (m) onto h (:func:`_tumble`, the lattice's tumbles).
    A roll is not reversible in general: the roll back over the same edge may fall back, or on."""
    G = nx.DiGraph()
    G.add_nodes_from([int(start), int(goal)])
    for g in np.flatnonzero(model.stable).tolist():
        for e in _roll_edges(model, g, min_edge).tolist():
            if (done := _tumble(model, model.X_TO[g], g, e)) is not None:
                G.add_edge(g, done[1])
    try:
        return [int(g) for g in nx.shortest_path(G, int(start), int(goal))]
    except nx.NetworkXNoPath:
        return []


def _swept_hits(model: ObjectModel, collide, X_from: np.ndarray, X_to: np.ndarray, primitive: str, vertex: int,
                edge, tilt: float, fractions=(0.25, 0.5, 0.75)) -> bool:
    """Does the object hit an obstacle on its way from ``X_from`` to ``X_to``, checked at a few fractions
    of the rotation: a tumble over ``edge``, or a pivot about the vertical through ``vertex``, both as
    turned flat and as tilted by ``tilt`` (rad) onto the vertex (``mpc.pivot_reference``'s tilt, turn
    and lowering: the tilt leans the object's top over, toward whatever stands beside it)?"""
    R_rel = X_to[:3, :3] @ X_from[:3, :3].T
    rotvec = se3.quat_from_matrix(R_rel)
    angle = 2.0 * np.arctan2(np.linalg.norm(rotvec[:3]), rotvec[3])
    if angle < 1e-9:
        return False
    axis = rotvec[:3] / np.linalg.norm(rotvec[:3])
    point = model.vertices[vertex] if primitive == "pivot" else model.vertices[edge[0]]
    point = se3.transform_points(X_from, point)
    if any(collide(X) for X in se3.transform_about_line(point, axis, np.asarray(fractions) * angle) @ X_from):
        return True
    if primitive != "pivot":
        return False
    try:
        d = tilt_direction(model, X_from, vertex, tilt)
    except InputError:  # no tilt stands it on this vertex: no pivot edge (graph), nothing to sweep
        return False
    d = se3.transform_points(X_from, model.com) - point if d is None else d
    lean = np.cross([d[0], d[1], 0.0], [0.0, 0.0, 1.0])
    X_tilt = se3.transform_about_line(point, lean / np.linalg.norm(lean), tilt) @ X_from
    turns = se3.transform_about_line(point, axis, np.array([0.0, *fractions, 1.0]) * angle) @ X_tilt
    return any(collide(X) for X in turns)


def _tumble(model: ObjectModel, X: np.ndarray, g: int, e: int, max_faces: int = 16):
    """Roll the object from face ``g`` (the face it rests on at ``X``, as :func:`roll_segments` finds
    it) over hull edge ``e`` until it rests on a stable face: the same roll the motion stage follows.
    Returns ``(X_WO, face, total angle)`` or None when no stable face comes within ``max_faces`` faces
    or half a turn, or the roll comes back onto face ``g`` (it rocks over one edge and falls back
    over another: no tumble, and a displacement no contact controls)."""
    try:
        roll = roll_segments(model, X, *(int(v) for v in model.edges[e]), max_faces=max_faces)
    except InputError:
        return None
    if roll.face == g:
        return None
    return roll.X_end, roll.face, float(roll.angle.sum())


@dataclass(frozen=True)
class Roll:
    """A roll over successive hull edges onto a stable face (:func:`roll_segments`), W frame.

    X_seg : (K, 4, 4) pose at the start of each segment; p_axis, a_axis : (K, 3) a point of its axis
    (the first edge vertex) and the unit axis, right-handed in the sense of the roll; angle : (K,) rad;
    edge : (K, 2) the hull vertex ids of each axis; face : the stable placement it lands on; X_end.
    """

    X_seg: np.ndarray
    p_axis: np.ndarray
    a_axis: np.ndarray
    angle: np.ndarray
    edge: np.ndarray
    face: int
    X_end: np.ndarray

    @property
    def total(self) -> float:
        return float(self.angle.sum())

    @property
    def switches(self) -> np.ndarray:
        """Cumulative angles where the axis changes, ``(K - 1,)``."""
        return np.cumsum(self.angle)[:-1]

    def poses(self, theta) -> np.ndarray:
        return mpc.roll_poses(self.X_seg, self.p_axis, self.a_axis, self.angle, theta)

    def segment_of(self, theta: float) -> int:
        return int(np.clip(np.searchsorted(np.cumsum(self.angle), theta - 1e-9), 0, len(self.angle) - 1))


def roll_segments(model, X_WO: np.ndarray, v0: int, v1: int, max_faces: int = 16) -> Roll:
    """Roll the object from its resting face over hull edge ``(v0, v1)`` until it rests on a stable face.

    The same roll as the pose sampler's (:func:`_tumble`): over the edge onto the adjacent hull face;
    while that face is not stable (a narrow face between a foot and the body, a facet of a rounded
    body), over the next edge of it (:func:`_next_edge`). Raises ``InputError`` when ``(v0, v1)`` is
    not an edge of the resting face or no stable face comes within ``max_faces`` faces or half a turn.
    """
    down = se3.rotate_vectors(X_WO, model.normals)[:, 2]
    g = int(np.argmin(down))  # the resting face: outward normal straight down
    match = np.flatnonzero(((model.edges[:, 0] == v0) & (model.edges[:, 1] == v1))
                           | ((model.edges[:, 0] == v1) & (model.edges[:, 1] == v0)))
    if len(match) == 0 or not np.any(model.edge_faces[match[0]] == g):
        raise InputError(f"tumble: ({v0}, {v1}) is not a hull edge of the resting face {g}")
    e, X, total = int(match[0]), X_WO.copy(), 0.0
    segs = []
    for _ in range(max_faces):  # a few faces at most
        a, b = model.edges[e]
        pa, pb = se3.transform_points(X, model.vertices[[a, b]])
        g2 = int(model.edge_faces[e, 1] if model.edge_faces[e, 0] == g else model.edge_faces[e, 0])
        angle = float(model.edge_angle[e])
        axis = (pb - pa) / np.linalg.norm(pb - pa)
        n2 = se3.rotate_vectors(X, model.normals[g2])
        for sign in (1.0, -1.0):  # the sense that turns face g2 onto the table
            T = se3.transform_about_line(pa, sign * axis, angle)
            if se3.rotate_vectors(T, n2)[2] < -np.cos(ROLL_ALIGN):
                break
        else:
            raise InputError(f"tumble over ({v0}, {v1}): face {g2} does not turn onto the table")
        segs.append((X, pa, sign * axis, angle, (int(a), int(b))))
        X, g, total = T @ X, g2, total + angle
        if total > np.pi + 1e-9:
            break
        if model.stable[g]:
            return Roll(X_seg=np.stack([s[0] for s in segs]), p_axis=np.stack([s[1] for s in segs]),
                        a_axis=np.stack([s[2] for s in segs]), angle=np.array([s[3] for s in segs]),
                        edge=np.array([s[4] for s in segs], dtype=np.int64), face=g, X_end=_settle(model, X, g))
        e = _next_edge(model, X, g, e)
        if e < 0:
            break
    raise InputError(f"tumble over ({v0}, {v1}): no stable face within {max_faces} faces or half a turn")


def _next_edge(model, X: np.ndarray, g: int, e: int) -> int:
    """The hull edge of face ``g`` (on the table at ``X``) a roll that came over edge ``e`` goes on
    over: the one the CoM lies beyond, farthest (it topples over it alone); with none, the one
    straight ahead, whose outward normal is nearest the roll's direction (away from ``e``): the CoM
    is still over the face or back over ``e``, so the pusher keeps turning the object, as it rolls a
    rounded body over the facets of its hull. -1 when no edge lies ahead. Plan view, W."""
    es = np.array([e2 for e2 in np.flatnonzero((model.edge_faces == g).any(axis=1)) if e2 != e], dtype=np.int64)
    if not len(es):
        return -1
    centre = se3.transform_points(X, model.vertices[np.asarray(model.support[g])]).mean(axis=0)[:2]

    def outward(ids):  # (k,) edges -> first vertex (k, 2), unit outward normal (k, 2)
        q = se3.transform_points(X, model.vertices[model.edges[ids]])[..., :2]
        d = q[:, 1] - q[:, 0]
        n = np.stack([d[:, 1], -d[:, 0]], axis=1) / np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
        return q[:, 0], np.where((np.einsum("ij,ij->i", centre - q[:, 0], n) > 0)[:, None], -n, n)

    q0, nrm = outward(es)
    beyond = np.einsum("ij,ij->i", se3.transform_points(X, model.com)[:2] - q0, nrm)
    if beyond.max() > 0.0:
        return int(es[np.argmax(beyond)])
    ahead = -outward(np.array([e]))[1][0] @ nrm.T
    return int(es[np.argmax(ahead)]) if ahead.max() > 0.0 else -1


#: How far (rad) a roll over a hull edge may leave the next face off the table's plane: the hull's
#: merged faces (``stages.analyze.Params.hull_coplanar_deg``, 0.5 deg) meet at edges that are not
#: exactly their planes' intersection. The roll's end settles onto the face (:func:`_settle`).
ROLL_ALIGN = np.radians(1.0)


def _settle(model: ObjectModel, X: np.ndarray, g: int) -> np.ndarray:
    """``X`` turned by the least rotation that lays face ``g`` on the table (its outward normal straight
    down, about its lowest support vertex): where gravity settles a roll that ends within
    ``ROLL_ALIGN`` of it; then put at the height the analysis rests that face at (``X_TO``, whose
    turns about the vertical and shifts are every other pose of the placement), the CoM's plan-view
    place kept. A face merged from hull triangles within ``hull_coplanar_deg`` is flat only to a
    fraction of a millimetre, and two conventions for its height would make poses of one placement
    differ by more than a planar motion (``connect.planar_motion``), so that no pivot could join them.
    Exact input comes back unchanged up to round-off."""
    n = se3.rotate_vectors(X, model.normals[g])
    axis = np.cross(n, [0.0, 0.0, -1.0])
    out = np.array(X, dtype=float)
    if np.linalg.norm(axis) >= 1e-12:
        sup = se3.transform_points(X, model.vertices[np.asarray(model.support[g])])
        p = sup[np.argmin(sup[:, 2])]
        angle = float(np.arctan2(np.linalg.norm(axis), -n[2]))
        out = se3.transform_about_line(p, axis / np.linalg.norm(axis), angle) @ X
    rest = model.X_TO[g]
    snapped = se3.make_transform(se3.rot_z(se3.yaw_of(out[:3, :3] @ rest[:3, :3].T)), np.zeros(3)) @ rest
    snapped[:2, 3] += se3.transform_points(out, model.com)[:2] - se3.transform_points(snapped, model.com)[:2]
    return snapped


def held_com(poly: np.ndarray, com_W: np.ndarray, margin: float) -> np.ndarray:
    """Where a USP hold check puts the CoM ``com_W (..., 3)`` of an object on the table contact ``poly
    (k, 2)`` (W): ``margin`` m further out, away from the polygon through its boundary point nearest the
    CoM (outward across that edge when the CoM is inside). A ball that holds the object in USP holds it
    with the margin SP asks of an object standing alone (``Params.sp_margin``): a USP pose whose CoM is
    just inside that margin would otherwise be "held" by any ball, with no force at all, and tip over in
    physics at the least push."""
    com_W = np.array(com_W, dtype=float)
    q = com_W[..., :2].reshape(-1, 2)
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    rel = q[:, None] - a[None]                                                      # (N, k, 2)
    t = np.clip(np.einsum("nij,ij->ni", rel, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    near = a[None] + t[..., None] * ab[None]
    d_all = q[:, None] - near
    i = np.argmin(np.linalg.norm(d_all, axis=2), axis=1)
    d = d_all[np.arange(len(q)), i]
    inside = np.array([_margin(poly, x) > 0 for x in q])  # a handful of points
    d = np.where(inside[:, None], -d, d)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    com_W[..., :2] += margin * d.reshape(com_W[..., :2].shape)
    return com_W


def _margin(p: np.ndarray, q: np.ndarray) -> float:
    """Signed distance of ``q (2,)`` inside the convex hull of ``p (k, 2)`` (< 0 outside)."""
    c = p.mean(axis=0)
    order = np.argsort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))
    hull = _convex_hull_2d(p[order])
    if len(hull) < 3:
        if len(hull) == 2:  # an edge: outside by the distance to the segment
            a, b = hull
            t = np.clip(np.dot(q - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0, 1)
            return -float(np.linalg.norm(a + t * (b - a) - q))
        return -float(np.linalg.norm(hull[0] - q)) if len(hull) else -np.inf
    a = hull - q
    return float(_polygon_margins(a, np.roll(a, -1, axis=0), np.zeros(len(a), dtype=np.int64), 1)[0])


def _convex_hull_2d(p: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of 2-D points (monotone chain; a few dozen points)."""
    p = np.unique(np.round(p, 9), axis=0)
    if len(p) < 3:
        return p

    def chain(points):
        out: list = []
        for q in points:
            while len(out) >= 2 and _cross2(out[-1] - out[-2], q - out[-2]) <= 1e-12:
                out.pop()
            out.append(q)
        return out

    lower, upper = chain(p), chain(p[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _cross2(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _object_fcl(model: ObjectModel) -> fcl.CollisionObject:
    """The object mesh as an fcl collision object (at the identity); its hierarchy is built once per
    model (seconds on a 200k-triangle mesh), each call gets its own object to move."""
    if not model.bvh:
        model.bvh.append(fclmesh.bvh(model.mesh_vertices, model.mesh_faces))
    return fcl.CollisionObject(model.bvh[0], fcl.Transform())


def obstacles_hit(model: ObjectModel, X: np.ndarray, obstacles) -> list[str]:
    """Names of the ``obstacles`` (``stages.scene.ObstacleGeometry``) that the object at ``X_WO (4, 4)``
    overlaps, in their order (fcl, as :func:`_make_object_collision_fn`)."""
    obj = _object_fcl(model)
    obj.setTransform(fcl.Transform(X[:3, :3], X[:3, 3]))
    req = fcl.CollisionRequest()
    return [ob.name for ob in obstacles if fcl.collide(obj, fcl_object(ob), req, fcl.CollisionResult())]


def _make_object_collision_fn(model: ObjectModel, obstacles, clearance: float = 0.0):
    """A callable ``collide(X_WO) -> bool``: does the object at ``X_WO`` come within ``clearance`` (m)
    of any obstacle (fcl; boxes and cylinders grown by it, a mesh by fcl's distance)."""
    if not obstacles:
        return lambda X: False
    obj = _object_fcl(model)
    bodies = [fcl_object(ob, clearance) for ob in obstacles]
    near = [clearance > 0 and ob.kind not in ("box", "cylinder") for ob in obstacles]
    req = fcl.CollisionRequest()

    def hits(b, by_distance: bool) -> bool:
        if by_distance:
            return fcl.distance(obj, b, fcl.DistanceRequest(), fcl.DistanceResult()) < clearance
        return fcl.collide(obj, b, req, fcl.CollisionResult()) > 0

    def collide(X: np.ndarray) -> bool:
        obj.setTransform(fcl.Transform(X[:3, :3], X[:3, 3]))
        return any(hits(b, n) for b, n in zip(bodies, near, strict=True))

    return collide


def fcl_object(ob, grow: float = 0.0) -> fcl.CollisionObject:
    """An fcl collision object for a ``stages.scene.ObstacleGeometry``, a box or cylinder grown by
    ``grow`` (m) on every side (a mesh is not grown)."""
    if ob.kind == "box":
        geom = fcl.Box(*(np.asarray(ob.size, dtype=float) + 2 * grow))
    elif ob.kind == "cylinder":
        geom = fcl.Cylinder(ob.radius + grow, ob.height + 2 * grow)
    else:
        geom = fclmesh.bvh(ob.vertices, ob.faces)
    X = np.asarray(ob.X_WOb, dtype=float)
    return fcl.CollisionObject(geom, fcl.Transform(X[:3, :3], X[:3, 3]))


def _to_pose_set(rows: list[dict], links: list[tuple], goal_id: int = -1) -> PoseSet:
    n = len(rows)
    L = len(links)
    return PoseSet(
        X_WO=np.array([r["X"] for r in rows]).reshape(n, 4, 4),
        placement=np.array([r["g"] for r in rows], dtype=np.int64),
        support=np.array([r["kind"] for r in rows], dtype=str),
        status=np.array([r["status"] for r in rows], dtype=str),
        parent=np.array([r["parent"] for r in rows], dtype=np.int64),
        primitive=np.array([r["primitive"] for r in rows], dtype=str),
        vertex=np.array([r["vertex"] for r in rows], dtype=np.int64),
        edge=np.array([r["edge"] for r in rows], dtype=np.int64).reshape(n, 2),
        angle=np.array([r["angle"] for r in rows], dtype=float),
        margin=np.array([r["margin"] for r in rows], dtype=float),
        links=np.array([(a, b) for a, b, *_ in links], dtype=np.int64).reshape(L, 2),
        link_primitive=np.array([lk[2] for lk in links], dtype=str),
        link_vertex=np.array([lk[3] for lk in links], dtype=np.int64),
        link_edge=np.array([lk[4] for lk in links], dtype=np.int64).reshape(L, 2),
        link_angle=np.array([lk[5] for lk in links], dtype=float),
        goal_id=int(goal_id),
    )
