"""Connect two poses of an object on the same placement by a short sequence of pivots (§5.3).

A pivot turns the object by an angle ``alpha`` about the vertical line through one of its support
corners; the corner stays where it is on the table (§5.1, Fig. 7). §5.3 links a start or goal pose
that is not in the graph to the graph with the controllability result of pivoting [18]: three pivots
reach any pose of the same base face in a neighbourhood. This module finds such a sequence.

Planar form: on a fixed base face the object has a planar pose ``(x, y, yaw)`` (m, m, rad) and its
support corners are points ``(k, 2)`` of its planar frame, so that corner ``c`` is at
``p_W = (x, y) + R(yaw) @ corners[c]`` on the table. A pivot about ``c`` by ``alpha`` keeps ``p_W`` and
adds ``alpha`` to the yaw.

Every corner sequence has a closed-form answer (no search over angles, no Newton step):

- **1 pivot** about ``c``: exists iff ``c`` is at the same place in both poses; ``alpha = dyaw``.
- **2 pivots** ``c1, c2``: ``c1`` stays at ``w1`` (its start position) and ``c2`` must already be at its
  goal position ``g2`` after the first pivot (the second pivot does not move it), so ``c2`` has to lie on
  the circle of radius ``|c2 - c1|`` about ``w1``: exists iff ``| |g2 - w1| - |c2 - c1| | <= tol_xy``,
  then ``alpha1`` is the unique angle turning ``c1 -> c2`` towards ``g2 - w1`` and ``alpha2 = dyaw - alpha1``.
  Two pivots therefore reach only a surface of the 3-D pose space.
- **3 pivots** ``c1, c2, c3``: ``c2`` pivots about ``w1`` (first pivot) and ``c3`` must be at its goal
  ``g3`` after the second, so ``c2``'s position ``w2`` between pivots 1 and 2 lies on the circle of
  radius ``|c2 - c1|`` about ``w1`` and on the circle of radius ``|c3 - c2|`` about ``g3``: at most two
  solutions (circle intersection), each giving ``alpha1``, then ``alpha2`` (turning ``c2 -> c3`` towards
  ``g3 - w2``), then ``alpha3 = dyaw - alpha1 - alpha2``. Circles that miss by at most ``tol_xy`` are
  taken as tangent.

Every candidate is checked by replaying its pivots (:func:`apply_pivots`): it is kept when
``|alpha_i| <= max_angle`` and the replay ends within ``tol_xy`` / ``tol_yaw`` of the goal. Sequences are
enumerated in a fixed order (fewer pivots first, then corner ids lexicographically, then the two circle
intersections); the answer has the fewest pivots, then the smallest ``sum |alpha|``. That cost ties
exactly (``|dyaw|``) for every sequence whose angles share one sign, so ties (within 1e-9) go to the
smallest ``sum alpha^2`` (the most even split), then to the first enumerated. With ``alternate=False``
a pivot may repeat the previous corner: a run of ``r`` pivots about one corner is solved as one pivot
bounded by ``r * max_angle`` and split into ``r`` equal angles.

Angles are wrapped to ``(-pi, pi]`` (the smallest turn reaching a heading); yaws along a connection are
continuous from the start yaw, so the last pose equals the goal up to the tolerances and a multiple of
``2 pi`` in yaw. A pose equal to the goal connects with zero pivots.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

from stages import se3
from stages.errors import InputError

NO_SEQUENCE = "no_pivot_sequence"
DIFFERENT_PLACEMENT = "different_placement"

# Slack (rad) on the angle bound so that an exact 30 deg pivot solved back is not rejected for round-off;
# accepted angles are clipped to the bound, which moves the end pose by far less than tol_xy / tol_yaw.
_ANGLE_SLACK = 1e-12
# Two costs (rad, rad^2) closer than this are a tie: far above round-off, far below a meaningful difference.
_TIE = 1e-9
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Params:
    """Pivot connection parameters (rad, m).

    ``max_angle`` bounds each pivot's |angle|; ``max_pivots`` (1 to 3) the sequence length; ``tol_xy``
    (m) and ``tol_yaw`` (rad) how close the replayed end must be to the goal (and, in
    :func:`connect_poses`, how planar the relative motion must be); ``alternate`` forbids two consecutive
    pivots about the same corner. ``face_tilt`` (rad): in :func:`connect_poses` the support corners may
    lie off the table by ``tol_xy + tan(face_tilt) * spread`` (m, ``spread`` the largest distance between
    two corners), since a placement face merges hull triangles whose normals differ by up to the
    analysis' ``hull_coplanar_deg`` and its corners are coplanar only to about that slope (the duck's
    16-corner base: 0.2 mm over 0.25 m); the pivots are about verticals, so they stay exact.
    """

    max_angle: float = np.radians(30.0)
    max_pivots: int = 3
    tol_xy: float = 1e-6
    tol_yaw: float = 1e-8
    alternate: bool = True
    face_tilt: float = np.radians(0.5)


@dataclass(frozen=True)
class Connection:
    """A pivot sequence from pose a to pose b (planar or 3-D form).

    ``corners (m,)`` int corner ids, ``angles (m,)`` rad (about +z, counter-clockwise positive),
    ``poses`` the ``m + 1`` poses from a to b: ``(m + 1, 3)`` planar ``(x, y, yaw)`` from
    :func:`connect_planar`, ``(m + 1, 4, 4)`` ``X_WO`` from :func:`connect_poses`. ``cost`` is
    ``sum |angles|`` (rad); sequences rank by ``(m, cost, sum angles^2)``. When ``ok`` is False the arrays
    are empty (``poses`` holds pose a only), ``cost`` is inf and ``reason`` says why; otherwise ``reason``
    is "".
    """

    ok: bool
    corners: np.ndarray
    angles: np.ndarray
    poses: np.ndarray
    cost: float
    reason: str

    @property
    def n_pivots(self) -> int:
        return len(self.corners)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles ``(...)`` rad wrapped to ``(-pi, pi]``."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def _rot2(yaw: np.ndarray) -> np.ndarray:
    """Planar rotations ``(..., 2, 2)`` by ``yaw (...)`` rad."""
    yaw = np.asarray(yaw, dtype=float)
    R = np.empty(yaw.shape + (2, 2))
    R[..., 0, 0] = R[..., 1, 1] = np.cos(yaw)
    R[..., 1, 0] = np.sin(yaw)
    R[..., 0, 1] = -R[..., 1, 0]
    return R


def _apply(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", R, v)


def _angle_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Signed angle (rad) turning 2-D vectors ``u (..., 2)`` onto the direction of ``v (..., 2)``."""
    return np.arctan2(u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0], np.sum(u * v, axis=-1))


def corner_positions(pose: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """World positions ``(..., k, 2)`` (m) of ``corners (k, 2)`` for planar poses ``pose (..., 3)``."""
    pose = np.asarray(pose, dtype=float)
    return pose[..., None, :2] + np.einsum("...ij,kj->...ki", _rot2(pose[..., 2]), corners)


def apply_pivots(pose: np.ndarray, corners: np.ndarray, ids: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Replay pivot sequences: planar poses ``(..., m + 1, 3)`` after each pivot.

    Parameters
    ----------
    pose : (..., 3) float
        Start poses ``(x, y, yaw)`` (m, m, rad).
    corners : (k, 2) float
        Support corners in the object's planar frame (m).
    ids : (..., m) int
        Corner pivoted about at each step.
    angles : (..., m) float
        Pivot angles (rad, counter-clockwise about +z). The yaw accumulates without wrapping.
    """
    pose = np.asarray(pose, dtype=float)
    ids = np.asarray(ids, dtype=int)
    angles = np.asarray(angles, dtype=float)
    shape = np.broadcast_shapes(pose.shape[:-1], ids.shape[:-1], angles.shape[:-1])
    out = np.empty(shape + (ids.shape[-1] + 1, 3))
    out[..., 0, :] = pose
    for i in range(ids.shape[-1]):
        cur = out[..., i, :]
        p_c = corners[ids[..., i]]
        # The corner's world position is the fixed point of the rotation.
        w = cur[..., :2] + _apply(_rot2(cur[..., 2]), p_c)
        yaw = cur[..., 2] + angles[..., i]
        out[..., i + 1, :2] = w - _apply(_rot2(yaw), p_c)
        out[..., i + 1, 2] = yaw
    return out


@functools.lru_cache(maxsize=64)
def corner_sequences(k: int, n: int) -> np.ndarray:
    """All corner sequences ``(N, n)`` of length ``n`` over ``k`` corners without a repeat in a row.

    Lexicographic order: ``(0, 1, 0), (0, 1, 2), ...``. Made once per ``(k, n)`` and read-only.
    """
    seqs = np.array(list(itertools.product(range(k), repeat=n)), dtype=int).reshape(-1, n)
    seqs = seqs[np.all(seqs[:, 1:] != seqs[:, :-1], axis=1)]
    seqs.flags.writeable = False
    return seqs


def solve_pivot_angles(pose_a: np.ndarray, pose_b: np.ndarray, corners: np.ndarray,
                       seqs: np.ndarray) -> np.ndarray:
    """Closed-form pivot angles taking ``pose_a`` to ``pose_b`` for each corner sequence.

    Parameters
    ----------
    pose_a, pose_b : (3,) float
        Planar poses ``(x, y, yaw)`` (m, m, rad).
    corners : (k, 2) float
        Support corners in the object's planar frame (m).
    seqs : (N, n) int
        Corner sequences, ``n`` in 1..3, no corner twice in a row.

    Returns
    -------
    angles : (N, B, n) float
        Angles (rad, wrapped to ``(-pi, pi]``) of the ``B`` candidate solutions per sequence (``B = 2``
        circle intersections for ``n = 3``, else 1). Only the yaw is exact by construction: the caller
        replays them (:func:`apply_pivots`) to see whether the position is reached. NaN where the
        geometry is degenerate (coincident circle centres).
    """
    seqs = np.asarray(seqs, dtype=int)
    N, n = seqs.shape
    dyaw = wrap_angle(pose_b[2] - pose_a[2])
    w_a = corner_positions(pose_a, corners)  # (k, 2) corners at the start
    g_b = corner_positions(pose_b, corners)  # (k, 2) corners at the goal
    R_a = _rot2(pose_a[2])
    if n == 1:
        return np.full((N, 1, 1), dyaw)
    c1, c2 = seqs[:, 0], seqs[:, 1]
    w1 = w_a[c1]  # (N, 2) the first pivot's fixed point
    v12 = _apply(R_a, corners[c2] - corners[c1])  # c1 -> c2 at the start, world frame
    if n == 2:
        # c2 must reach its goal with the first pivot alone.
        a1 = _angle_between(v12, g_b[c2] - w1)
        return np.stack([a1, wrap_angle(dyaw - a1)], -1)[:, None, :]
    if n != 3:
        raise InputError(f"solve_pivot_angles: sequences of 1 to 3 pivots, got {n}")
    c3 = seqs[:, 2]
    g3 = g_b[c3]  # (N, 2) the last pivot's fixed point
    r1 = np.linalg.norm(corners[c2] - corners[c1], axis=-1)
    r2 = np.linalg.norm(corners[c3] - corners[c2], axis=-1)
    d_vec = g3 - w1
    D = np.linalg.norm(d_vec, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = d_vec / D[:, None]
        # Foot of the chord along w1 -> g3; clipping keeps w2 on the first circle when they miss
        # (the replay then measures by how much).
        a = np.clip((D**2 + r1**2 - r2**2) / (2.0 * D), -r1, r1)
    h = np.sqrt(np.maximum(r1**2 - a**2, 0.0))
    u_perp = np.stack([-u[:, 1], u[:, 0]], -1)
    out = np.empty((N, 2, 3))
    for b, sign in enumerate((1.0, -1.0)):
        w2 = w1 + a[:, None] * u + sign * h[:, None] * u_perp
        a1 = _angle_between(v12, w2 - w1)
        v23 = _apply(_rot2(pose_a[2] + a1), corners[c3] - corners[c2])
        a2 = _angle_between(v23, g3 - w2)
        out[:, b] = np.stack([a1, a2, wrap_angle(dyaw - a1 - a2)], -1)
    return out


def _compositions(m: int, alternate: bool) -> list[tuple[int, ...]]:
    """Run lengths of ``m`` pivots: ``(1,) * m`` only when consecutive corners must differ."""
    if alternate:
        return [(1,) * m]
    runs = [c for n in range(1, m + 1) for c in itertools.product(range(1, m + 1), repeat=n) if sum(c) == m]
    return sorted(runs, key=lambda c: (len(c), c))


def _check(params: Params, corners: np.ndarray, poses: tuple[np.ndarray, ...]) -> None:
    p = params
    if not (0.0 < p.max_angle <= np.pi):
        raise InputError(f"connect: max_angle must be in (0, pi] rad, got {p.max_angle}")
    if p.max_pivots not in (1, 2, 3):
        raise InputError(f"connect: max_pivots must be 1, 2 or 3, got {p.max_pivots}")
    if not (p.tol_xy > 0.0 and p.tol_yaw > 0.0):
        raise InputError(f"connect: tolerances must be positive, got tol_xy={p.tol_xy}, tol_yaw={p.tol_yaw}")
    if not (0.0 <= p.face_tilt < np.pi / 2):
        raise InputError(f"connect: face_tilt must be in [0, pi/2) rad, got {p.face_tilt}")
    for name, x, shape in poses:
        if x.shape != shape or not np.all(np.isfinite(x)):
            raise InputError(f"connect: {name} must be a finite {shape} array, got shape {x.shape}")
    if corners.ndim != 2 or len(corners) == 0 or not np.all(np.isfinite(corners)):
        raise InputError(f"connect: corners must be a finite (k, 2) array with k >= 1, got shape {corners.shape}")
    d = np.linalg.norm(corners[:, None] - corners[None], axis=-1)
    d[np.diag_indices(len(corners))] = np.inf
    if np.any(d <= p.tol_xy):
        i, j = np.unravel_index(np.argmin(d), d.shape)
        raise InputError(f"connect: corners {i} and {j} coincide (a pivot about either is the same)")


def _pick(cost: np.ndarray, square: np.ndarray) -> int:
    """Index of the best candidate: least ``sum |alpha|``, then least ``sum alpha^2``, then the first.

    Costs within ``_TIE`` are equal: every sequence whose angles share one sign costs exactly
    ``|dyaw|``, so without the second key round-off would pick among them (and the choice would change
    under a rigid motion of both poses). ``sum alpha^2`` prefers the most even split of the turn.
    """
    near = np.flatnonzero(cost <= cost.min() + _TIE)
    near = near[square[near] <= square[near].min() + _TIE]
    return int(near[0])


def _failure(pose: np.ndarray, reason: str) -> Connection:
    return Connection(False, np.zeros(0, dtype=int), np.zeros(0), pose[None].copy(), np.inf, reason)


def connect_planar(pose_a: np.ndarray, pose_b: np.ndarray, corners: np.ndarray,
                   params: Params = Params()) -> Connection:
    """Shortest pivot sequence (fewest pivots, then least ``sum |alpha|``) from ``pose_a`` to ``pose_b``.

    Parameters
    ----------
    pose_a, pose_b : (3,) float
        Planar poses ``(x, y, yaw)`` (m, m, rad) of the object on one base face.
    corners : (k, 2) float
        Support corners (pivot vertices) in the object's planar frame (m).
    params : Params

    Returns
    -------
    Connection
        ``poses (m + 1, 3)`` replayed from ``pose_a``; ``reason`` ``"no_pivot_sequence"`` when no sequence
        of at most ``max_pivots`` pivots within ``max_angle`` reaches ``pose_b``.
    """
    pose_a = np.asarray(pose_a, dtype=float)
    pose_b = np.asarray(pose_b, dtype=float)
    corners = np.asarray(corners, dtype=float)
    _check(params, corners, (("pose_a", pose_a, (3,)), ("pose_b", pose_b, (3,))))
    if corners.shape[1] != 2:
        raise InputError(f"connect_planar: corners must be (k, 2), got shape {corners.shape}")

    def reaches(end: np.ndarray) -> np.ndarray:
        return ((np.linalg.norm(end[..., :2] - pose_b[:2], axis=-1) <= params.tol_xy)
                & (np.abs(wrap_angle(end[..., 2] - pose_b[2])) <= params.tol_yaw))

    if reaches(pose_a):
        return Connection(True, np.zeros(0, dtype=int), np.zeros(0), pose_a[None].copy(), 0.0, "")
    k = len(corners)
    for m in range(1, params.max_pivots + 1):
        cost, ids, ang = [], [], []  # of every sequence that reaches pose_b, in enumeration order
        for runs in _compositions(m, params.alternate):
            seqs = corner_sequences(k, len(runs))
            if len(seqs) == 0:
                continue
            limit = params.max_angle * np.array(runs, dtype=float)
            a = solve_pivot_angles(pose_a, pose_b, corners, seqs)  # (N, B, n)
            ok = np.all(np.abs(a) <= limit + _ANGLE_SLACK, axis=-1)  # NaN compares False
            a = np.clip(a, -limit, limit)
            end = apply_pivots(pose_a, corners, np.broadcast_to(seqs[:, None, :], a.shape), a)[..., -1, :]
            i, b = np.nonzero(ok & reaches(end))
            cost.append(np.sum(np.abs(a[i, b]), axis=1))
            # A run of r pivots about one corner: r equal turns.
            ids.append(np.repeat(seqs[i], runs, axis=1))
            ang.append(np.repeat(a[i, b] / np.array(runs), runs, axis=1))
        if sum(len(c) for c in cost):
            cost, ids, ang = np.concatenate(cost), np.concatenate(ids), np.concatenate(ang)
            j = _pick(cost, np.sum(ang**2, axis=1))
            return Connection(True, ids[j], ang[j], apply_pivots(pose_a, corners, ids[j], ang[j]), float(cost[j]), "")
    return _failure(pose_a, NO_SEQUENCE)


def walk_planar(pose_a: np.ndarray, pose_b: np.ndarray, corners: np.ndarray, params: Params = Params(),
                strides: int = 12, grid: int = 7, stride_angle: float | None = None) -> Connection:
    """A pivot walk from ``pose_a`` to ``pose_b`` (planar, m, m, rad) beyond the closed form's reach.

    The quasi-static pivot gait of §5.1 (Fig. 7) steered greedily: each stride is two pivots about two
    different ``corners (k, 2)`` (m, planar frame), the pair and angles (``grid`` values in
    ``[-stride_angle, stride_angle]``, default ``max_angle``) that bring the pose nearest ``pose_b``
    (the corners' centroid in plan view plus half the corners' spread in m per rad of heading), until
    :func:`connect_planar` finishes from the pose reached; at most ``strides`` strides, and a stride
    that brings it no nearer ends the walk. §5.3 joins poses within three pivots ([18]'s
    neighbourhood); the walk joins lattices whose nearest poses lie several pivots apart (a small
    base moves a few cm per pivot). Greedy: it may miss a sequence that exists. Two pivots in a row
    may share a corner where a stride meets the next or the closed form (two bounded pivots, each
    exact).
    """
    pose_a, pose_b = np.asarray(pose_a, dtype=float), np.asarray(pose_b, dtype=float)
    corners = np.asarray(corners, dtype=float)
    _check(params, corners, (("pose_a", pose_a, (3,)), ("pose_b", pose_b, (3,))))
    k = len(corners)
    ref = corners.mean(axis=0)
    spread = float(np.max(np.linalg.norm(corners[:, None] - corners[None], axis=-1)))
    goal_ref = pose_b[:2] + _apply(_rot2(pose_b[2]), ref)

    def distance(p: np.ndarray) -> np.ndarray:  # (..., 3) -> (...)
        return (np.linalg.norm(p[..., :2] + _apply(_rot2(p[..., 2]), ref) - goal_ref, axis=-1)
                + 0.5 * spread * np.abs(wrap_angle(p[..., 2] - pose_b[2])))

    pairs = corner_sequences(k, 2)
    if not len(pairs):  # one corner: no stride
        return connect_planar(pose_a, pose_b, corners, params)
    bound = params.max_angle if stride_angle is None else min(stride_angle, params.max_angle)
    a = np.linspace(-bound, bound, grid)
    ids = np.repeat(pairs, grid * grid, axis=0)                                    # (P * g^2, 2)
    ang = np.tile(np.stack(np.meshgrid(a, a, indexing="ij"), -1).reshape(-1, 2), (len(pairs), 1))
    seq_ids, seq_ang, cur = [], [], pose_a
    for n in range(strides + 1):
        end = connect_planar(cur, pose_b, corners, params)
        if end.ok:
            ids_all = np.concatenate([*seq_ids, end.corners]).astype(int)
            ang_all = np.concatenate([*seq_ang, end.angles])
            return Connection(True, ids_all, ang_all, apply_pivots(pose_a, corners, ids_all, ang_all),
                              float(np.sum(np.abs(ang_all))), "")
        if n == strides:
            break
        step = apply_pivots(cur, corners, ids, ang)[:, -1]
        d = distance(step)
        best = int(np.argmin(d))
        if d[best] >= distance(cur) - params.tol_xy:
            break
        seq_ids.append(ids[best])
        seq_ang.append(ang[best])
        cur = step[best]
    return _failure(pose_a, NO_SEQUENCE)


def planar_motion(X_a: np.ndarray, X_b: np.ndarray, params: Params = Params()) -> np.ndarray | None:
    """The planar pose ``(x, y, yaw)`` of ``X_WT = X_b @ inv(X_a)``, or None when it is not planar.

    Planar: a rotation about +z (tilt of its z axis <= ``tol_yaw``) and no vertical shift (<= ``tol_xy``),
    i.e. both poses rest on the same base face of the table.
    """
    X_T = X_b @ se3.invert(X_a)
    R = X_T[:3, :3]
    # sin(tilt) from the z column's horizontal part: accurate near zero, unlike arccos(R[2, 2]).
    tilt = np.arctan2(np.hypot(R[0, 2], R[1, 2]), R[2, 2])
    if tilt > params.tol_yaw or abs(X_T[2, 3]) > params.tol_xy:
        return None
    return np.array([X_T[0, 3], X_T[1, 3], se3.yaw_of(R)])


def on_table_tolerance(corners_O: np.ndarray, params: Params = Params()) -> float:
    """How far (m) support corners ``corners_O (k, 3)`` (m, O) may lie off the table and still rest on it:
    ``tol_xy + tan(face_tilt) * spread``, ``spread`` the largest distance between two corners. It scales
    with the face, so that a mesh's own unevenness (hull triangles merged within ``face_tilt``) is
    not taken for a pose off the table."""
    c = np.asarray(corners_O, dtype=float)
    spread = float(np.max(np.linalg.norm(c[:, None] - c[None], axis=-1))) if len(c) else 0.0
    return params.tol_xy + np.tan(params.face_tilt) * spread


def connect_poses(X_a: np.ndarray, X_b: np.ndarray, corners_O: np.ndarray,
                  params: Params = Params(), face_O: np.ndarray | None = None, strides: int = 0,
                  stride_angle: float | None = None) -> Connection:
    """Shortest pivot sequence between two world poses of the object on the same placement.

    Parameters
    ----------
    X_a, X_b : (4, 4) float
        Object poses ``X_WO`` (m); ``X_b = X_WT @ X_a`` with ``X_WT`` a planar rigid motion, else the
        answer is ``ok=False, reason="different_placement"``.
    corners_O : (k, 3) float
        Support corners ``p_OC`` in the object frame (m); at ``X_a`` they must lie on the table (z = 0)
        within ``tol_xy + tan(face_tilt) * spread`` (:class:`Params`): a hull face's own flatness.
    params : Params
    face_O : (m, 3) float, optional
        The support face's vertices (m, O), whose spread sets that tolerance when ``corners_O`` are
        some of its corners only (default ``corners_O``).
    strides : int
        0: the closed form (:func:`connect_planar`, at most ``max_pivots`` pivots); else the pivot walk
        of at most that many strides before it (:func:`walk_planar`), its pivots within ``stride_angle``.

    Returns
    -------
    Connection
        ``poses`` are ``X_WO (m + 1, 4, 4)``: each pivot is the rotation about the vertical through the
        corner's current world position (:func:`stages.se3.transform_about_line`), starting at ``X_a``.
    """
    X_a = np.asarray(X_a, dtype=float)
    X_b = np.asarray(X_b, dtype=float)
    corners_O = np.asarray(corners_O, dtype=float)
    _check(params, corners_O, (("X_a", X_a, (4, 4)), ("X_b", X_b, (4, 4))))
    if corners_O.shape[1] != 3:
        raise InputError(f"connect_poses: corners_O must be (k, 3), got shape {corners_O.shape}")
    p_WC = se3.transform_points(X_a, corners_O)  # (k, 3)
    off = np.abs(p_WC[:, 2])
    allowed = on_table_tolerance(corners_O if face_O is None else np.asarray(face_O, dtype=float), params)
    if np.any(off > allowed):
        raise InputError(f"connect_poses: corner {int(np.argmax(off))} is {off.max():.3g} m off the table "
                         f"(z = 0) at X_a, more than the face's flatness {allowed:.3g} m; pivot corners must rest "
                         "on the table")
    pose_b = planar_motion(X_a, X_b, params)
    if pose_b is None:
        return Connection(False, np.zeros(0, dtype=int), np.zeros(0), X_a[None].copy(), np.inf, DIFFERENT_PLACEMENT)
    # Planar frame = world at X_a: the start is the origin and the corners are their world positions.
    if strides:
        c = walk_planar(np.zeros(3), pose_b, p_WC[:, :2], params, strides, stride_angle=stride_angle)
    else:
        c = connect_planar(np.zeros(3), pose_b, p_WC[:, :2], params)
    X = np.empty((c.n_pivots + 1, 4, 4))
    X[0] = X_a
    for i, (ci, a) in enumerate(zip(c.corners, c.angles, strict=True)):
        p_pivot = se3.transform_points(X[i], corners_O[ci])
        X[i + 1] = se3.transform_about_line(p_pivot, _Z, a) @ X[i]
    return Connection(c.ok, c.corners, c.angles, X, c.cost, c.reason)
