"""Dual-arm robot model: URDF parsing, batched forward and position-only inverse kinematics, collisions.

Works on batches of joint vectors ``q (N, n)`` (rad) and world points ``p_W (N, 3)`` (m); every kernel
is vectorized over N. The robot is read from a URDF (``data/robots/sda5f.urdf`` by default) with
``xml.etree``: the tree is split into a static *trunk* (the base and everything reached from it through
fixed joints or the torso joint, which planning holds at a fixed angle) and two serial *arms*, each the
path from the trunk to one end-effector link. A ball end-effector makes a point contact, so IK solves for
the ball centre only (paper §4.2: "we check whether the inverse kinematics (IK) is solvable").

Collision geometry is a set of simple primitives: on moving links capsules (segment ``a -> b`` in the
link frame plus radius; a sphere is a zero-length capsule and a cylinder its enclosing capsule), on the
trunk boxes or capsules. ``make_collision_fn`` tests them in numpy against the table, obstacles, each
other and (with python-fcl, after numpy pre-filters) the object mesh.

Frames use Drake's monogram notation (see STYLE.md): ``X_WB`` is the robot base in the world,
``p_W`` a point in world coordinates.
"""

from __future__ import annotations

import hashlib
import math
import threading
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from stages import se3
from stages.errors import InputError

#: IK outcome names; ``IKResult.reason`` holds these strings.
IK_REASONS = ("ok", "ik_unreachable", "joint_limit", "joint_jump")

#: Default rest posture (rad) for both arms: the IK's secondary objective and the centre of its seed
#: library. Chosen once by optimisation on this model: the ball about 0.6 m in front of the shoulders at
#: shoulder height, the tool pointing inwards (towards the other arm), the elbow out to the side, every
#: joint at least 0.59 rad inside its limits and every tested capsule pair at least 1 cm apart. The
#: same vector gives the mirrored posture on the right arm.
SDA5F_REST = (1.64, -0.18, -0.22, 0.0, 0.0, -1.31, 0.0)

_ZERO = 1e-12  # rotation-matrix entries below this are structural zeros (cos(pi/2) = 6e-17)


def retain_freed_memory(trim_threshold: int = 1 << 30, mmap_threshold: int = 32 << 20) -> bool:
    """Ask glibc to keep freed heap memory for reuse instead of returning it to the OS (process-wide).

    The batched kernels allocate and free tens of MB of numpy temporaries per iteration. With glibc's
    defaults those pages go back to the OS and are faulted in again on the next iteration, which is
    slow on the project's 2-core VM (``bench/bench_robot.py``, shared machine: IK 111,000 -> 130,000
    targets/s on 10,000 targets and 156,000 -> 191,000 on 60,000; collision checks 84,000 -> 108,000
    checks/s on 10,000). Call once at program start (same effect as ``MALLOC_TRIM_THRESHOLD_`` and
    ``MALLOC_MMAP_THRESHOLD_`` in the environment). Returns False where glibc's ``mallopt`` is missing.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # from glibc's malloc.h
    return bool(mallopt(M_TRIM_THRESHOLD, int(trim_threshold))) and bool(
        mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)))


# ----------------------------------------------------------------------------------------------------
# URDF parsing


@dataclass(frozen=True)
class _Geom:
    kind: str  # "box" | "capsule"
    X_LG: np.ndarray  # (4, 4) pose of the geometry in its link frame
    dims: np.ndarray  # box: half extents (3,); capsule: (a (3,), b (3,), radius) packed as (7,)


@dataclass(frozen=True)
class _Joint:
    name: str
    kind: str
    parent: str
    child: str
    X_PC: np.ndarray  # (4, 4) origin: child joint frame in the parent link frame at q = 0
    axis: np.ndarray  # (3,) unit, in the joint frame
    lower: float
    upper: float
    velocity: float


def _floats(text: str | None, n: int, default: float, where: str) -> np.ndarray:
    if text is None:
        return np.full(n, default)
    try:
        v = np.array([float(x) for x in text.split()])
    except ValueError as exc:
        raise InputError(f"{where}: cannot read numbers from {text!r}") from exc
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise InputError(f"{where}: expected {n} finite numbers, got {text!r}")
    return v


def _matrix_from_rpy(rpy: np.ndarray) -> np.ndarray:
    """URDF rpy: fixed axes X, Y, Z, i.e. ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def _origin(el: ET.Element | None, where: str) -> np.ndarray:
    o = None if el is None else el.find("origin")
    xyz = _floats(None if o is None else o.get("xyz"), 3, 0.0, where)
    rpy = _floats(None if o is None else o.get("rpy"), 3, 0.0, where)
    return se3.make_transform(_matrix_from_rpy(rpy), xyz)


def _parse_geom(el: ET.Element, where: str) -> _Geom:
    X = _origin(el, where)
    g = el.find("geometry")
    shape = None if g is None else next(iter(g), None)
    if shape is None:
        raise InputError(f"{where}: <collision> without a geometry")

    def num(attr: str) -> float:
        value = _floats(shape.get(attr), 1, math.nan, f"{where} <{shape.tag} {attr}>")[0]
        if not value >= 0:
            raise InputError(f"{where}: <{shape.tag}> needs a non-negative {attr}")
        return value

    if shape.tag == "box":
        return _Geom("box", X, _floats(shape.get("size"), 3, math.nan, where) / 2)
    if shape.tag in ("capsule", "cylinder"):
        # A cylinder is replaced by its enclosing capsule (conservative by one radius at each end).
        r, h = num("radius"), num("length")
        a = se3.transform_points(X, np.array([0.0, 0.0, -h / 2]))
        b = se3.transform_points(X, np.array([0.0, 0.0, h / 2]))
        return _Geom("capsule", np.eye(4), np.concatenate([a, b, [r]]))
    if shape.tag == "sphere":
        c = X[:3, 3]
        return _Geom("capsule", np.eye(4), np.concatenate([c, c, [num("radius")]]))
    raise InputError(f"{where}: collision geometry <{shape.tag}> is not supported (use box, capsule, "
                     "cylinder or sphere)")


def _parse_urdf(path: Path) -> tuple[dict[str, list[_Geom]], dict[str, _Joint]]:
    """Links (name -> collision geometries) and joints (child link name -> joint) of a URDF file."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputError(f"{path}: cannot read URDF ({exc})") from exc
    if root.tag != "robot":
        raise InputError(f"{path}: the root element is <{root.tag}>, expected <robot>")
    links: dict[str, list[_Geom]] = {}
    for el in root.findall("link"):
        name = el.get("name")
        if not name or name in links:
            raise InputError(f"{path}: a <link> has no name or a duplicate name {name!r}")
        links[name] = [_parse_geom(c, f"{path}: link {name}") for c in el.findall("collision")]
    joints: dict[str, _Joint] = {}
    for el in root.findall("joint"):
        name, kind = el.get("name"), el.get("type")
        where = f"{path}: joint {name}"
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None:
            raise InputError(f"{where}: needs <parent> and <child>")
        p, c = parent.get("link"), child.get("link")
        if p not in links or c not in links:
            raise InputError(f"{where}: unknown link {p!r} or {c!r}")
        if c in joints:
            raise InputError(f"{where}: link {c!r} has two parent joints")
        if kind not in ("fixed", "revolute", "continuous"):
            raise InputError(f"{where}: joint type {kind!r} is not supported (fixed, revolute, continuous)")
        axis = _floats(None if el.find("axis") is None else el.find("axis").get("xyz"), 3, 0.0, where)
        if el.find("axis") is None:
            axis = np.array([1.0, 0.0, 0.0])  # the URDF default
        lo, hi, vel = -math.pi, math.pi, math.inf
        if kind != "fixed":
            if np.linalg.norm(axis) < 1e-9:
                raise InputError(f"{where}: zero axis")
            axis = axis / np.linalg.norm(axis)
            lim = el.find("limit")
            if lim is not None:
                vel = _floats(lim.get("velocity"), 1, math.inf, where)[0]
            if kind == "revolute":
                if lim is None or lim.get("lower") is None or lim.get("upper") is None:
                    raise InputError(f"{where}: a revolute joint needs <limit lower upper>")
                lo = _floats(lim.get("lower"), 1, 0.0, where)[0]
                hi = _floats(lim.get("upper"), 1, 0.0, where)[0]
                if not lo < hi:
                    raise InputError(f"{where}: lower limit {lo} is not below upper limit {hi}")
        joints[c] = _Joint(name, kind, p, c, _origin(el, where), axis, lo, hi, vel)
    return links, joints


# ----------------------------------------------------------------------------------------------------
# Model


@dataclass(frozen=True, eq=False)
class Arm:
    """One serial arm: the links from its first movable joint to the end-effector link.

    ``frames`` are the links in chain order (movable links, then fixed ones such as tool0, stick and
    ball); ``fk`` returns their world poses in that order. Frame ``k`` is ``origin_R/origin_t[k]`` after
    frame ``k - 1`` (frame -1 is ``X_WR``, the static link the arm hangs from, in the world), then a
    rotation by ``q[joint[k]]`` about ``axis[k]`` when ``joint[k] >= 0``.
    """

    name: str
    joint_names: tuple[str, ...]  # (n,) movable joints
    link_names: tuple[str, ...]  # (L,) frames returned by fk
    eef_index: int  # index of the end-effector (ball) link in link_names
    X_WR: np.ndarray  # (4, 4)
    origin_R: np.ndarray  # (L, 3, 3)
    origin_t: np.ndarray  # (L, 3) m
    joint: np.ndarray  # (L,) int, -1 for fixed
    axis: np.ndarray  # (L, 3) unit, in the frame after the origin
    lower: np.ndarray  # (n,) rad
    upper: np.ndarray  # (n,) rad
    velocity: np.ndarray  # (n,) rad/s
    q_rest: np.ndarray  # (n,) rad, clipped into the limits
    cap_link: np.ndarray  # (C,) int, frame of each collision capsule
    cap_a: np.ndarray  # (C, 3) m, segment start in its link frame
    cap_b: np.ndarray  # (C, 3) m, segment end
    cap_r: np.ndarray  # (C,) m radius
    cap_names: tuple[str, ...]  # (C,) link name of each capsule
    reach_centre: np.ndarray  # (3,) world point: every reachable ball centre lies ...
    reach_radius: float  # ... within this distance of reach_centre (m)

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    @cached_property
    def frame_origins(self) -> tuple[tuple[np.ndarray | None, np.ndarray | None], ...]:
        """Per frame, its origin's translation and rotation, each None when zero or the identity (the
        forward kinematics skips them)."""
        return tuple((t if np.any(t != 0.0) else None, None if np.array_equal(A, np.eye(3)) else A)
                     for t, A in zip(self.origin_t, self.origin_R, strict=True))


@dataclass(frozen=True, eq=False)
class Static:
    """Collision primitives of the trunk (base, torso at its planning angle), in the world frame."""

    box_names: tuple[str, ...]  # (K,)
    box_X_W: np.ndarray  # (K, 4, 4) box centre poses
    box_half: np.ndarray  # (K, 3) half extents (m)
    cap_names: tuple[str, ...]  # (M,)
    cap_a: np.ndarray  # (M, 3) world
    cap_b: np.ndarray  # (M, 3) world
    cap_r: np.ndarray  # (M,)


@dataclass(frozen=True)
class IKResult:
    """Batched IK outcome. ``q (..., n)`` rad, ``ok (...)``, ``reason (...)`` one of ``IK_REASONS``,
    ``err (...)`` m, the distance from the ball centre at ``q`` to its target."""

    q: np.ndarray
    ok: np.ndarray
    reason: np.ndarray
    err: np.ndarray


@dataclass(frozen=True)
class IKParams:
    """Settings of the damped-least-squares position IK (documented defaults)."""

    #: Iterations per attempt. Seeded from the library, most targets converge in 3-5.
    max_iter: int = 20
    #: Damping lambda (m) of ``J^T (J J^T + lambda^2 I)^-1``; small against the arm's 0.3-0.9 m lever
    #: arms, large enough to keep steps bounded near singular (stretched) postures.
    damping: float = 0.02
    #: Fraction of the way to the rest posture taken in the null space per iteration, while the
    #: error exceeds ``posture_fade`` (m); below it the pull fades quadratically.
    posture_gain: float = 0.1
    posture_fade: float = 0.02
    #: Largest joint change per iteration (rad); the step is scaled down to respect it.
    max_step: float = 0.5
    #: Largest Cartesian error fed to one step (m); far targets are approached in several steps.
    max_err_step: float = 0.15
    #: Iterate until the error is below ``stop_fraction * tol``.
    stop_fraction: float = 0.1
    #: Seed library: self-collision-free postures sampled around the rest posture (plus uniform ones)
    #: with their ball positions in a k-d tree. A target starts from the most comfortable (closest to
    #: the rest posture) of its ``neighbours`` nearest entries that lie within ``seed_slack`` (m) of
    #: the nearest; its restarts take the next ones. Seeding from comfortable, collision-free postures
    #: is what keeps the solutions clear of the arm's own links: on grasp-like targets beside a box,
    #: 100 % of solution pairs were collision-free this way against 47 % from the nearest entry of an
    #: unfiltered library.
    library_size: int = 10000
    library_uniform: float = 0.3  # fraction drawn uniformly within the limits
    library_sigma: float = 0.2  # std of the others, as a fraction of each joint's range
    library_seed: int = 0
    neighbours: int = 8
    seed_slack: float = 0.05
    restart_jitter: float = 0.3  # rad std of the jitter added to restart seeds
    #: Worker threads for batches of at least ``threads * min_chunk`` targets (numpy releases the GIL
    #: in its kernels). Two threads gained about a third on an idle 2-core machine with
    #: ``retain_freed_memory`` in effect, and nothing or less when the other core was busy.
    threads: int = 1
    min_chunk: int = 4096


@dataclass(frozen=True, eq=False)
class Robot:
    """A dual-arm robot with its trunk held still; build it with ``load_robot``.

    ``_cache`` holds what is derived from the robot alone (``_self_pairs``, ``Robot._library``); robots
    loaded with the same inputs share it."""

    urdf_path: Path
    X_WB: np.ndarray  # (4, 4) base link in the world
    torso_angle: float
    arms: dict[str, Arm]
    static: Static
    ik_params: IKParams = IKParams()
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def arm(self, arm: str) -> Arm:
        try:
            return self.arms[arm]
        except KeyError:
            raise ValueError(f"unknown arm {arm!r}; this robot has {sorted(self.arms)}") from None

    # -- forward kinematics ------------------------------------------------------------------------

    def fk(self, arm: str, q: np.ndarray) -> np.ndarray:
        """World poses ``(N, L, 4, 4)`` of the arm's links (``Arm.link_names``) at ``q (N, n)``."""
        a = self.arm(arm)
        q = _check_q(a, q)
        frames = _fk_frames(a, np.ascontiguousarray(q.T))
        N, L = len(q), len(a.link_names)
        X = np.zeros((N, L, 4, 4))
        for k, (cols, p, _) in enumerate(frames):
            for j in range(3):
                X[:, k, :3, j] = cols[j].T
            X[:, k, :3, 3] = p.T
        X[:, :, 3, 3] = 1.0
        return X

    def eef_rotation(self, arm: str, q: np.ndarray) -> np.ndarray:
        """Ball frames' rotations ``R_WE (N, 3, 3)`` at ``q (N, n)``: ``fk``'s, without the other links."""
        a = self.arm(arm)
        q = _check_q(a, q)
        cols = _fk_frames(a, np.ascontiguousarray(q.T), upto=a.eef_index + 1)[-1][0]
        return np.stack([c.T for c in cols], axis=-1)

    def eef_position(self, arm: str, q: np.ndarray) -> np.ndarray:
        """Ball centres ``p_W (N, 3)`` (m) at ``q (N, n)``."""
        a = self.arm(arm)
        q = _check_q(a, q)
        return np.array(_fk_frames(a, np.ascontiguousarray(q.T), upto=a.eef_index + 1)[-1][1].T, copy=True)

    # -- inverse kinematics ------------------------------------------------------------------------

    def ik(self, arm: str, p_W: np.ndarray, q_seed: np.ndarray | None = None,
           rng: np.random.Generator | None = None, restarts: int = 3, tol: float = 1e-3) -> IKResult:
        """Joint vectors that put the ball centre of ``arm`` on the targets ``p_W (N, 3)`` (m).

        Damped least squares on all targets at once, with the rest posture as a null-space objective
        and joint limits enforced by projection after every step. Targets farther than
        ``Arm.reach_radius`` from ``Arm.reach_centre`` are ``ik_unreachable`` at once. The first
        attempt starts from ``q_seed (N, n)`` when given, else from the most comfortable of the
        nearby seed-library postures (see ``IKParams``); targets still failing get up to ``restarts``
        more attempts from the next library postures plus a jitter drawn from ``rng``. The result of
        a target depends only on the target, its seed and ``rng``'s state, not on the rest of the
        batch.

        Returns ``IKResult`` with ``q (N, n)`` (the best attempt, always within limits),
        ``ok = err <= tol``, ``reason``: ``"ok"``, ``"ik_unreachable"`` or ``"joint_limit"`` (failed
        while a joint sat on a limit), and ``err (N,)`` m.
        """
        a = self.arm(arm)
        p_W = _check_points(p_W)
        N, n = len(p_W), a.dof
        if q_seed is not None:
            q_seed = np.clip(_check_q(a, q_seed, N), a.lower, a.upper)
        if rng is None:
            rng = np.random.default_rng(0)
        prm = self.ik_params
        # Drawn before anything else and with a size independent of N, so that a target's result
        # does not depend on its batch.
        jitter = rng.normal(0.0, prm.restart_jitter, (max(restarts, 0), n))
        q = np.broadcast_to(a.q_rest, (N, n)).copy()
        err = np.full(N, np.inf)
        reach = np.linalg.norm(p_W - a.reach_centre, axis=1) <= a.reach_radius
        idx = np.flatnonzero(reach)
        if len(idx):
            q_lib = self._library(arm)[0]
            # The library neighbours are only needed to seed the first attempt or a restart.
            ranked = self._ranked_neighbours(arm, p_W[idx]) if q_seed is None or restarts > 0 else None
            seed = q_seed[idx] if q_seed is not None else q_lib[ranked[:, 0]]
            first = 0 if q_seed is not None else 1
            q[idx], err[idx] = self._solve_parallel(a, p_W[idx], seed, tol)
            for r in range(restarts):
                still = err[idx] > tol
                if not still.any():
                    break
                sub = idx[still]
                k = ranked.shape[1]
                seed = np.clip(q_lib[ranked[still, (first + r) % k]] + jitter[r], a.lower, a.upper)
                q_r, err_r = self._solve_parallel(a, p_W[sub], seed, tol)
                better = err_r < err[sub]
                q[sub[better]], err[sub[better]] = q_r[better], err_r[better]
        far = ~reach
        if far.any():  # not attempted: report the distance from the rest posture's ball
            err[far] = np.linalg.norm(p_W[far] - self.eef_position(arm, q[far]), axis=1)
        ok = err <= tol
        at_limit = np.any((q <= a.lower + 1e-9) | (q >= a.upper - 1e-9), axis=1)
        code = np.where(ok, 0, np.where(reach & at_limit, 2, 1))
        return IKResult(q=q, ok=ok, reason=np.asarray(IK_REASONS)[code], err=err)

    def ik_trajectory(self, arm: str, p_W: np.ndarray, q0: np.ndarray, tol: float = 1e-3,
                      max_joint_step: float = 0.5, batch: bool = False) -> IKResult:
        """Continuous joint paths through a sequence of targets.

        ``p_W (T, 3)`` with ``q0 (n,)``, or ``p_W (T, N, 3)`` with ``q0 (N, n)`` for N paths at once.
        Each step is seeded with the previous step's solution and never restarted, so the path stays
        on one IK branch; a step whose largest joint change exceeds ``max_joint_step`` (rad) is marked
        ``"joint_jump"``. Returns ``IKResult`` with ``q (T, [N,] n)`` and the rest ``(T, [N])``.

        ``batch``: first solve every step at once, each seeded with ``q0`` (one vectorized solve instead
        of T small ones, for few paths of many steps); kept when every step converges and no step
        jumps, else the step-by-step solve runs.
        """
        a = self.arm(arm)
        p_W = np.asarray(p_W, dtype=float)
        single = p_W.ndim == 2
        if single:
            p_W = p_W[:, None, :]
            q0 = np.asarray(q0, dtype=float)[None, :]
        if p_W.ndim != 3 or p_W.shape[2] != 3:
            raise ValueError(f"p_W must be (T, 3) or (T, N, 3), got {p_W.shape}")
        T, N, n = p_W.shape[0], p_W.shape[1], a.dof
        q_prev = np.clip(_check_q(a, q0, N), a.lower, a.upper)
        if batch and T:
            q_b, err_b = _dls(a, _check_points(p_W.reshape(T * N, 3)), np.tile(q_prev, (T, 1)), tol, self.ik_params)
            q_b, err_b = q_b.reshape(T, N, n), err_b.reshape(T, N)
            steps = np.abs(np.diff(np.concatenate([q_prev[None], q_b]), axis=0)).max(axis=2)
            if np.all(err_b <= tol) and np.all(steps <= max_joint_step):
                res = IKResult(q=q_b, ok=np.ones((T, N), bool), reason=np.full((T, N), IK_REASONS[0]), err=err_b)
                return IKResult(q=res.q[:, 0], ok=res.ok[:, 0], reason=res.reason[:, 0], err=res.err[:, 0]) \
                    if single else res
        q = np.zeros((T, N, n))
        err = np.zeros((T, N))
        code = np.zeros((T, N), dtype=int)
        for t in range(T):
            q_t, err_t = _dls(a, _check_points(p_W[t]), q_prev, tol, self.ik_params)
            jump = np.max(np.abs(q_t - q_prev), axis=1, initial=0.0) > max_joint_step
            at_limit = np.any((q_t <= a.lower + 1e-9) | (q_t >= a.upper - 1e-9), axis=1)
            code[t] = np.where(err_t > tol, np.where(at_limit, 2, 1), np.where(jump, 3, 0))
            q[t], err[t], q_prev = q_t, err_t, q_t
        res = IKResult(q=q, ok=code == 0, reason=np.asarray(IK_REASONS)[code], err=err)
        if single:
            res = IKResult(q=res.q[:, 0], ok=res.ok[:, 0], reason=res.reason[:, 0], err=res.err[:, 0])
        return res

    def library_seeds(self, arm: str, p_W: np.ndarray, rank: int) -> np.ndarray:
        """Seed-library postures ``(N, n)`` for the targets ``p_W (N, 3)``: the entry of rank ``rank``
        among each target's library neighbours, ranked as ``ik`` ranks them (within ``seed_slack`` of
        the nearest first, then by comfort). Rank 0 seeds ``ik``'s first attempt, ranks 1, 2, ... its
        restarts; ranks wrap around after ``IKParams.neighbours``."""
        a = self.arm(arm)
        p_W = _check_points(p_W)
        if len(p_W) == 0:
            return np.zeros((0, a.dof))
        ranked = self._ranked_neighbours(arm, p_W)
        return self._library(arm)[0][ranked[:, rank % ranked.shape[1]]]

    def _ranked_neighbours(self, arm: str, p_W: np.ndarray) -> np.ndarray:
        """Library indices ``(N, k)`` of each target's ``k = IKParams.neighbours`` nearest entries (by
        ball position): those within ``seed_slack`` of the nearest first, then by comfort."""
        prm = self.ik_params
        q_lib, cost_lib, tree = self._library(arm)
        k = min(prm.neighbours, len(q_lib))
        d, nn = tree.query(p_W, k=k, workers=prm.threads)
        d, nn = d.reshape(len(p_W), k), nn.reshape(len(p_W), k)
        cost = cost_lib[nn] + np.where(d > d[:, :1] + prm.seed_slack, 1e6, 0.0)
        return np.take_along_axis(nn, np.argsort(cost, axis=1, kind="stable"), axis=1)

    def prepare_ik(self) -> None:
        """Build the IK seed libraries of both arms now rather than at the first ``ik`` call (a setup
        cost of about 0.1 s per arm, paid once per robot)."""
        for arm in self.arms:
            self._library(arm)

    def _solve_parallel(self, a: Arm, p: np.ndarray, seed: np.ndarray, tol: float):
        prm = self.ik_params
        chunks = min(prm.threads, len(p) // prm.min_chunk)
        if chunks <= 1:
            return _dls(a, p, seed, tol, prm)
        parts = np.array_split(np.arange(len(p)), chunks)
        with ThreadPoolExecutor(chunks) as pool:
            out = list(pool.map(lambda s: _dls(a, p[s], seed[s], tol, prm), parts))
        return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])

    def _library(self, arm: str):
        """Seed library of ``arm``: postures ``(M, n)``, their distance from the rest posture ``(M,)``
        (rms rad) and a k-d tree of their ball centres. Postures in collision with the arm itself, the
        trunk or the other arm at rest are left out."""
        q, cost = _derived(self, ("library", arm), lambda: self._library_postures(arm))
        key = ("library_tree", arm)
        if key not in self._cache:
            self._cache[key] = (q, cost, cKDTree(self.eef_position(arm, q)))
        return self._cache[key]

    def _library_postures(self, arm: str) -> tuple[np.ndarray, np.ndarray]:
        """The seed library's postures ``(M, n)`` and their costs ``(M,)`` (:meth:`_library`)."""
        a, prm = self.arm(arm), self.ik_params
        rng = np.random.default_rng(prm.library_seed)
        M = prm.library_size
        n_uni = int(round(prm.library_uniform * M))
        span = a.upper - a.lower
        near = a.q_rest + rng.normal(0.0, prm.library_sigma, (M - n_uni, a.dof)) * span
        uni = rng.uniform(a.lower, a.upper, (n_uni, a.dof))
        q = np.clip(np.concatenate([near, uni]), a.lower, a.upper)
        other = next(b for name, b in self.arms.items() if name != arm)
        rest = np.broadcast_to(other.q_rest, (M, other.dof))
        check = make_collision_fn(self)
        q = q[check(q, rest)[0] if arm == "left" else check(rest, q)[0]]
        cost = np.sqrt(np.mean((q - a.q_rest) ** 2, axis=1))
        return q, cost


def _check_q(a: Arm, q: np.ndarray, n_rows: int | None = None) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != a.dof or (n_rows is not None and len(q) != n_rows):
        want = f"({n_rows if n_rows is not None else 'N'}, {a.dof})"
        raise ValueError(f"joint vectors for arm {a.name!r} must be {want}, got {q.shape}")
    return q


def _check_points(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {p.shape}")
    return p


# ----------------------------------------------------------------------------------------------------
# Kinematic kernels. Arrays are component-major, ``(3, m)`` for m rows, so that every numpy call works
# on contiguous rows. A rotation is kept as its three columns, so that the constant joint origins (signed
# permutations for the SDA5F) cost a relabelling instead of a matrix product.


def _combine(cols, w: np.ndarray):
    """``sum_i w[i] * cols[i]`` skipping structural zeros and multiplications by +-1."""
    out = None
    for i in range(3):
        wi = w[i]
        if abs(wi) < _ZERO:
            continue
        term = cols[i] if wi == 1.0 else (-cols[i] if wi == -1.0 else wi * cols[i])
        out = term if out is None else out + term
    return out if out is not None else np.zeros_like(cols[0])


def _fk_frames(a: Arm, qT: np.ndarray, upto: int | None = None, keep_rot: bool = True):
    """Per frame ``(cols, p, w)`` for joint vectors ``qT (n, m)``: rotation columns ``3 x (3, m)``,
    origin ``(3, m)`` and, for a movable joint, its world axis ``(3, m)`` (else None); the first
    ``upto`` frames."""
    m = qT.shape[1]
    cols = [np.broadcast_to(a.X_WR[:3, j, None], (3, m)) for j in range(3)]
    p = np.broadcast_to(a.X_WR[:3, 3, None], (3, m))
    out = []
    for k, (t, A) in enumerate(a.frame_origins[:upto]):
        if t is not None:
            p = p + _combine(cols, t)
        if A is not None:
            cols = [_combine(cols, A[:, j]) for j in range(3)]
        w = None
        j = a.joint[k]
        if j >= 0:
            ax = a.axis[k]
            w = _combine(cols, ax)
            if abs(abs(ax[2]) - 1.0) < _ZERO:  # +-z: rotate columns 0 and 1
                ang = qT[j] if ax[2] > 0 else -qT[j]
                c, s = np.cos(ang), np.sin(ang)
                cols = [c * cols[0] + s * cols[1], c * cols[1] - s * cols[0], cols[2]]
            else:  # general axis: R @ (I + s K + (1 - c) K K), column by column
                K = se3.skew(ax)
                c, s = np.cos(qT[j]), np.sin(qT[j])
                Kc = [_combine(cols, K[:, i]) for i in range(3)]
                KKc = [_combine(Kc, K[:, i]) for i in range(3)]
                cols = [cols[i] + s * Kc[i] + (1.0 - c) * KKc[i] for i in range(3)]
        out.append((cols if keep_rot else None, p, w))
    return out


def _dls(a: Arm, p_T: np.ndarray, q0: np.ndarray, tol: float, prm: IKParams):
    """Damped least squares from ``q0 (M, n)`` towards ``p_T (M, 3)``; returns ``q (M, n)``, ``err (M,)``.

    Step ``dq = J^+ (e - J z) + z`` with ``J^+ = J^T (J J^T + lambda^2 I)^-1`` and the posture pull
    ``z = gain (q_rest - q)``: the task error e is met first and z acts in the null space of J. A
    null-space step still moves the ball to second order, so the pull fades as the error shrinks
    (``gain * min(1, e / posture_fade)^2``) and the last iterations are plain Gauss-Newton. Rows leave
    the active set once converged, so stragglers cost only their own work.
    """
    M, n = q0.shape
    q = np.array(q0, dtype=float).T.copy()  # (n, M)
    err = np.full(M, np.inf)
    if M == 0:
        return q.T, err
    stop = prm.stop_fraction * tol
    lam2 = prm.damping ** 2
    lo, hi, rest = a.lower[:, None], a.upper[:, None], a.q_rest[:, None]
    joint_frames = np.flatnonzero(a.joint[: a.eef_index + 1] >= 0)
    act = np.arange(M)
    qa, pa = q, np.ascontiguousarray(p_T.T)
    free = None  # (n, m) bool: 1 where the joint may move this step
    for it in range(prm.max_iter + 1):
        frames = _fk_frames(a, qa, upto=a.eef_index + 1, keep_rot=False)
        e = pa - frames[-1][1]  # (3, m)
        ea = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        q[:, act], err[act] = qa, ea
        keep = ea >= stop
        if it == prm.max_iter or not keep.any():
            break
        # Jacobian J (3, n, m): column j is w_j x (p_e - p_j), computed for all active rows (the few
        # converged ones are dropped after the step: cheaper than compacting every frame).
        W = np.stack([frames[k][2] for k in joint_frames], axis=1)  # (3, n, m)
        D = frames[-1][1][:, None, :] - np.stack([frames[k][1] for k in joint_frames], axis=1)
        Jx = W[1] * D[2] - W[2] * D[1]
        Jy = W[2] * D[0] - W[0] * D[2]
        Jz = W[0] * D[1] - W[1] * D[0]
        if free is not None:  # joints the last step pushed into a limit sit this step out
            Jx *= free
            Jy *= free
            Jz *= free
        scale = np.minimum(1.0, prm.max_err_step / np.maximum(ea, 1e-300))
        fade = prm.posture_gain * np.minimum(1.0, ea / prm.posture_fade) ** 2
        z = fade * (rest - qa)  # (n, m)
        v0 = e[0] * scale - np.einsum("jm,jm->m", Jx, z)
        v1 = e[1] * scale - np.einsum("jm,jm->m", Jy, z)
        v2 = e[2] * scale - np.einsum("jm,jm->m", Jz, z)
        # (J J^T + lambda^2 I) y = v, symmetric 3 x 3 solved by its adjugate.
        axx = np.einsum("jm,jm->m", Jx, Jx) + lam2
        ayy = np.einsum("jm,jm->m", Jy, Jy) + lam2
        azz = np.einsum("jm,jm->m", Jz, Jz) + lam2
        axy = np.einsum("jm,jm->m", Jx, Jy)
        axz = np.einsum("jm,jm->m", Jx, Jz)
        ayz = np.einsum("jm,jm->m", Jy, Jz)
        cxx, cyy, czz = ayy * azz - ayz * ayz, axx * azz - axz * axz, axx * ayy - axy * axy
        cxy, cxz, cyz = axz * ayz - axy * azz, axy * ayz - axz * ayy, axy * axz - axx * ayz
        inv_det = 1.0 / (axx * cxx + axy * cxy + axz * cxz)
        y0 = (cxx * v0 + cxy * v1 + cxz * v2) * inv_det
        y1 = (cxy * v0 + cyy * v1 + cyz * v2) * inv_det
        y2 = (cxz * v0 + cyz * v1 + czz * v2) * inv_det
        dq = Jx * y0 + Jy * y1 + Jz * y2 + z
        big = np.max(np.abs(dq), axis=0)
        dq *= np.minimum(1.0, prm.max_step / np.maximum(big, 1e-300))
        qa = qa + dq
        free = ((qa > lo) | (dq > 0)) & ((qa < hi) | (dq < 0))
        qa = np.clip(qa, lo, hi)
        if not keep.all():
            act, qa, pa, free = act[keep], qa[:, keep], pa[:, keep], free[:, keep]
    return q.T.copy(), err


def ik_pose(robot: Robot, arm: str, p_t: np.ndarray, R_t: np.ndarray, q0: np.ndarray, iters: int = 30):
    """Joints ``(T, n)`` putting the ball centre of ``arm`` on ``p_t (T, 3)`` and, in the null space of
    that, turning the ball towards ``R_t (T, 3, 3)`` (W): task-priority IK (Siciliano and Slotine's
    two-task scheme: damped least squares on the position, the orientation error as a rotation
    vector solved in the position task's null space), ``iters`` steps from ``q0 (T, n)``, each capped
    at 0.2 rad per joint, joint limits by clamping. A ball is a sphere, so its orientation is free:
    ``stages.trajectory`` uses it to turn a stick off the object with the contact kept. Also returns
    the position errors ``(T,)`` (m): near a singular posture or a clamped joint the position task can
    be lost (17-25 % of random postures asked for a 15 deg turn), so callers keep only rows within
    their tolerance."""
    a = robot.arm(arm)
    q = np.clip(np.array(q0, dtype=float), a.lower, a.upper)
    moving = np.flatnonzero(a.joint[: a.eef_index + 1] >= 0)
    lam2 = 1e-6
    n = a.dof
    for _ in range(iters):
        F = robot.fk(arm, q)
        p, R = F[:, a.eef_index, :3, 3], F[:, a.eef_index, :3, :3]
        w = np.einsum("tkij,kj->tki", F[:, moving, :3, :3], a.axis[moving])  # (T, m, 3) world joint axes
        Jw = np.zeros((len(q), 3, n))
        Jw[:, :, a.joint[moving]] = np.swapaxes(w, 1, 2)
        Jp = np.zeros((len(q), 3, n))
        Jp[:, :, a.joint[moving]] = np.swapaxes(np.cross(w, p[:, None] - F[:, moving][:, :, :3, 3]), 1, 2)
        e_p = p_t - p
        e_r = Rotation.from_matrix(R_t @ np.swapaxes(R, 1, 2)).as_rotvec()
        Jp_pinv = np.swapaxes(Jp, 1, 2) @ np.linalg.inv(Jp @ np.swapaxes(Jp, 1, 2) + lam2 * np.eye(3))
        dq1 = (Jp_pinv @ e_p[:, :, None])[:, :, 0]
        N = np.eye(n) - Jp_pinv @ Jp
        JrN = Jw @ N
        rhs = e_r - (Jw @ dq1[:, :, None])[:, :, 0]
        y = np.linalg.solve(JrN @ np.swapaxes(JrN, 1, 2) + 1e-4 * np.eye(3), rhs[:, :, None])
        dq = dq1 + (N @ np.swapaxes(JrN, 1, 2) @ y)[:, :, 0]
        dq *= np.minimum(1.0, 0.2 / np.maximum(np.abs(dq).max(axis=1), 1e-12))[:, None]
        q = np.clip(q + dq, a.lower, a.upper)
    err = np.linalg.norm(p_t - robot.eef_position(arm, q), axis=1)
    return q, err


def follow_ik(robot: Robot, arm: str, targets: np.ndarray, X_WO: np.ndarray, keys: np.ndarray, n_O: np.ndarray,
              q0: np.ndarray, iters: int = 12, tol: float = 1e-3, max_jump: float = 0.5,
              both: bool = False) -> IKResult:
    """Joints that put ``arm``'s ball on ``targets (K, E, 3)`` (W, m) *and turn it with the object*, for
    E motions at once: row ``keys[k]`` of the object's poses ``X_WO (E, T, 4, 4)`` at target k.

    A ball on a turning object rolls across its face unless it turns with it (notes: "the ball turns
    with the object"): over a 90 deg tumble a ball that keeps its orientation rolls 3 cm, off a contact
    near the edge. Here the ball's rotation about the object's turning axis (its part tangent to the
    contact, outward normal ``n_O (E, 3)``, O) follows the object's, key to key (the ball turned by the
    object's turn since the previous key, about that axis only; both tangent parts with ``both``); spin
    about the normal and the stick's direction are left to the posture.
    Damped least squares with task priority (Nakamura's): the position, then that rotation error in
    its null space; geometric Jacobian, joint limits by clamping, ``iters`` iterations per key seeded
    from the previous key (one branch), from ``q0 (E, n)``. A motion's result depends on it alone.

    Returns ``IKResult`` ``(K, E)``: ``ik_unreachable`` (position error over ``tol`` m) or
    ``joint_jump`` (a key's largest joint change over ``max_jump`` rad), ``ok`` otherwise.
    """
    a = robot.arm(arm)
    K, E, n = targets.shape[0], targets.shape[1], a.dof
    R_rel = X_WO[:, :, :3, :3] @ np.swapaxes(X_WO[:, :1, :3, :3], -1, -2)  # (E, T, 3, 3)
    T = R_rel.shape[1]
    q = np.clip(np.asarray(q0, dtype=float), a.lower, a.upper)
    out, err = np.zeros((K, E, n)), np.zeros((K, E))
    code = np.zeros((K, E), dtype=int)
    axis = np.tile([1.0, 0.0, 0.0], (E, 1))
    for k, i in enumerate(np.asarray(keys).tolist()):  # a few dozen keys
        q_prev = q.copy()
        n_W = np.einsum("eij,ej->ei", X_WO[:, i, :3, :3], n_O)
        d = Rotation.from_matrix(R_rel[:, min(i + 1, T - 1)] @ np.swapaxes(R_rel[:, max(i - 1, 0)], -1, -2)).as_rotvec()
        dn = np.linalg.norm(d, axis=1)
        axis = np.where(dn[:, None] > 1e-9, d / np.maximum(dn, 1e-300)[:, None], axis)
        S = axis - np.einsum("ei,ei->e", axis, n_W)[:, None] * n_W
        S = (S / np.maximum(np.linalg.norm(S, axis=1), 1e-9)[:, None])[:, None]  # (E, 1, 3)
        if both:
            S = np.concatenate([S, np.cross(n_W, S[:, 0])[:, None]], axis=1)
        # Incrementally: the ball as it is, turned by the object's turn since the last key (an absolute
        # target would leak the free components' drift into the tracked one).
        turn = R_rel[:, i] @ np.swapaxes(R_rel[:, keys[k - 1] if k else i], -1, -2)
        q = _follow_key(a, targets[k], turn @ robot.fk(arm, q)[:, a.eef_index, :3, :3], S, q, iters)
        err[k] = np.linalg.norm(targets[k] - robot.eef_position(arm, q), axis=1)
        jump = np.abs(q - q_prev).max(axis=1) > max_jump if k else np.zeros(E, bool)
        code[k] = np.where(err[k] > tol, 1, np.where(jump, 3, 0))
        out[k] = q
    return IKResult(q=out, ok=code == 0, reason=np.asarray(IK_REASONS)[code], err=err)


def _follow_key(a: Arm, p_T: np.ndarray, R_T: np.ndarray, S: np.ndarray, q: np.ndarray, iters: int,
                lam2: float = 1e-6, max_dq: float = 0.2) -> np.ndarray:
    """:func:`follow_ik` at one key: ``iters`` task-priority steps from ``q (E, n)`` towards ball centres
    ``p_T (E, 3)`` and, in the position's null space, the rotation error to ``R_T (E, 3, 3)`` along the
    rows of ``S (E, s, 3)``; a motion stops once its position error is under 0.01 mm and its step under
    1 mrad. Returns the joints ``(E, n)``."""
    E, n = q.shape
    q = q.copy()
    moving = np.flatnonzero(a.joint[: a.eef_index + 1] >= 0)
    cols_of = a.joint[moving]
    free = np.ones((E, n), bool)
    act = np.arange(E)
    I_n, I_s = np.eye(n), np.eye(S.shape[1])
    for _ in range(iters):
        if not len(act):
            break
        fr = _fk_frames(a, q[act].T, upto=a.eef_index + 1, keep_rot=True)
        p = fr[-1][1].T
        R = np.stack([c.T for c in fr[-1][0]], axis=-1)  # (m, 3, 3), columns
        w = np.stack([fr[j][2].T for j in moving], axis=2)  # (m, 3, n') world joint axes
        o = np.stack([fr[j][1].T for j in moving], axis=2)
        Jw, Jp = np.zeros((len(act), 3, n)), np.zeros((len(act), 3, n))
        Jw[:, :, cols_of] = w
        Jp[:, :, cols_of] = np.cross(w, p[:, :, None] - o, axis=1)
        f = free[act][:, None, :]
        Jp, Jr = Jp * f, (S[act] @ Jw) * f  # a joint the last step pushed into a limit sits out
        e_p = p_T[act] - p
        e_r = np.einsum("esi,ei->es", S[act], Rotation.from_matrix(R_T[act] @ np.swapaxes(R, -1, -2)).as_rotvec())
        Jp_pinv = np.swapaxes(Jp, -1, -2) @ np.linalg.inv(Jp @ np.swapaxes(Jp, -1, -2) + lam2 * np.eye(3))
        dq1 = np.einsum("enk,ek->en", Jp_pinv, e_p)
        N = I_n - Jp_pinv @ Jp
        JrN = Jr @ N
        y = np.linalg.solve(JrN @ np.swapaxes(JrN, -1, -2) + lam2 * I_s,
                            (e_r - np.einsum("esn,en->es", Jr, dq1))[..., None])[..., 0]
        dq = dq1 + np.einsum("enm,esm,es->en", N, JrN, y)
        dq *= np.minimum(1.0, max_dq / np.maximum(np.abs(dq).max(axis=1), 1e-12))[:, None]
        q_new = q[act] + dq
        free[act] = ((q_new > a.lower) | (dq > 0)) & ((q_new < a.upper) | (dq < 0))
        q[act] = np.clip(q_new, a.lower, a.upper)
        act = act[~((np.linalg.norm(e_p, axis=1) < 1e-5) & (np.abs(dq).max(axis=1) < 1e-3))]
    return q


# ----------------------------------------------------------------------------------------------------
# Loading


def load_robot(urdf_path: str | Path, X_WB: np.ndarray | None = None,
               eef_links: tuple[str, str] = ("left_ball", "right_ball"), torso_angle: float = 0.0,
               q_rest: np.ndarray | None = None, ik_params: IKParams | None = None) -> Robot:
    """Read a dual-arm URDF into a ``Robot`` with arms ``"left"`` and ``"right"``.

    Parameters
    ----------
    urdf_path : path of the URDF file.
    X_WB : (4, 4) pose of the URDF root link in the world (default identity).
    eef_links : the left and right end-effector (ball) link names.
    torso_angle : rad; every movable joint shared by both arms (the torso) is held at this angle.
    q_rest : (n,) rest posture for both arms, the IK's secondary objective (default ``SDA5F_REST`` for
        7-joint arms, else mid-range), clipped into the limits.
    ik_params : IK settings (default ``IKParams()``).

    Robots loaded with the same inputs in one process share ``Robot._cache`` (self-collision pairs, IK
    seed libraries), which depends on nothing else.
    """
    path = Path(urdf_path)
    links, joints = _parse_urdf(path)
    X_WB = np.eye(4) if X_WB is None else np.asarray(X_WB, dtype=float)
    if X_WB.shape != (4, 4) or not np.all(np.isfinite(X_WB)):
        raise InputError(f"{path}: the base pose must be a finite (4, 4) transform")

    paths, n_common = _eef_chains(path, links, joints, eef_links)
    X_W, arm_links = _static_poses(path, joints, paths, n_common, X_WB, torso_angle)
    arms = {}
    for name, chain in zip(("left", "right"), paths, strict=True):
        arms[name] = _make_arm(path, name, chain[n_common - 1], chain[n_common:], links, joints, X_W,
                               q_rest)
    if arms["left"].dof != arms["right"].dof:
        raise InputError(f"{path}: the arms have {arms['left'].dof} and {arms['right'].dof} joints")

    static = _make_static(path, links, X_W, arm_links)
    ik_params = ik_params or IKParams()
    # What the robot derives from these inputs alone (self-collision pairs, IK seed libraries: a few
    # tenths of a second) is shared by every robot loaded with the same inputs in this process, so
    # stages run one after another in one process (``make bench``, the tests) derive it once.
    # It is also kept on disk (``stages.cache``), named by these inputs and this module's source, so
    # that every stage process after the first reads it instead of deriving it again.
    key = (hashlib.sha256(path.read_bytes()).hexdigest(), X_WB.tobytes(), tuple(eef_links), float(torso_angle),
           arms["left"].q_rest.tobytes(), arms["right"].q_rest.tobytes(),
           replace(ik_params, threads=1, min_chunk=0))  # how the work is split changes no result
    return Robot(urdf_path=path, X_WB=X_WB, torso_angle=float(torso_angle), arms=arms, static=static,
                 ik_params=ik_params, _cache=_shared_cache(key))


def _eef_chains(path: Path, links: dict, joints: dict, eef_links: tuple[str, str]) -> tuple[list[list[str]], int]:
    """Each end-effector's link chain from the URDF's root (root first) and how many links the two
    share (the trunk); refuses end-effectors that are missing, in two trees, or one on the other's
    chain, and a joint tree with a cycle."""
    def path_to(link: str) -> list[str]:
        if link not in links:
            raise InputError(f"{path}: end-effector link {link!r} is not in the URDF")
        chain = [link]
        while chain[-1] in joints:
            chain.append(joints[chain[-1]].parent)
            if len(chain) > len(links):
                raise InputError(f"{path}: the joint tree has a cycle")
        return chain[::-1]  # root first

    paths = [path_to(e) for e in eef_links]
    if paths[0][0] != paths[1][0]:
        raise InputError(f"{path}: the two end-effectors are not in one tree")
    n_common = 0
    while n_common < min(map(len, paths)) and paths[0][n_common] == paths[1][n_common]:
        n_common += 1
    if n_common == min(map(len, paths)):
        raise InputError(f"{path}: one end-effector link lies on the other's chain")
    return paths, n_common


def _static_poses(path: Path, joints: dict, paths: list[list[str]], n_common: int, X_WB: np.ndarray,
                  torso_angle: float) -> tuple[dict, set]:
    """World pose ``(4, 4)`` of every static link: those reached from the root through fixed joints
    or trunk joints (held at ``torso_angle`` rad, which must lie in their limits); movable branches
    that are neither trunk nor arm are ignored. Also the arms' link names."""
    trunk = set(paths[0][:n_common])
    X_W = {paths[0][0]: X_WB}
    arm_links = set(paths[0][n_common:]) | set(paths[1][n_common:])
    pending = [paths[0][0]]
    while pending:
        parent = pending.pop()
        for child, jt in joints.items():
            if jt.parent != parent or child in arm_links:
                continue
            if jt.kind != "fixed" and child not in trunk:
                continue
            X = X_W[parent] @ jt.X_PC
            if jt.kind != "fixed":
                if not jt.lower <= torso_angle <= jt.upper:
                    raise InputError(f"{path}: torso angle {torso_angle} rad is outside joint {jt.name}'s "
                                     f"limits [{jt.lower}, {jt.upper}]")
                X = X @ se3.make_transform(se3.rotation_about_axis(jt.axis, torso_angle), np.zeros(3))
            X_W[child] = X
            pending.append(child)
    return X_W, arm_links


@lru_cache(maxsize=8)
def _shared_cache(key: tuple) -> dict:
    """One cache dict per distinct robot (``load_robot``); a handful are kept. Its ``"disk"`` entry
    is the key's part of the on-disk entries' names (:func:`_derived`)."""
    return {"disk": (key, hashlib.sha256(Path(__file__).read_bytes()).hexdigest())}


def _derived(robot: Robot, key: tuple, derive) -> tuple[np.ndarray, ...]:
    """``derive()`` (a tuple of arrays derived from the robot alone), computed once per robot and
    process and kept on disk across processes (``stages.cache``: named by the robot's inputs, ``key``
    and this module's source, so never stale; the same arrays either way)."""
    from stages import cache

    if key not in robot._cache:
        disk = robot._cache.get("disk")  # None for a robot not made by load_robot: not kept on disk
        name = cache.entry_name("robot", disk, key) if disk is not None else ""
        stored = cache.load(name) if name else None
        if stored:
            robot._cache[key] = _unflatten(stored)
        else:
            robot._cache[key] = tuple(derive())
            if name:
                cache.save(name, _flatten(robot._cache[key]))
    return robot._cache[key]


def _flatten(items: tuple) -> dict[str, np.ndarray]:
    """Arrays and lists of arrays as named arrays: ``a<i>`` for an array, ``a<i>_<j>`` for list members."""
    out = {}
    for i, x in enumerate(items):
        if isinstance(x, list):
            out.update({f"a{i}_{j}": np.asarray(y) for j, y in enumerate(x)})
        else:
            out[f"a{i}"] = np.asarray(x)
    return out


def _unflatten(arrays: dict[str, np.ndarray]) -> tuple:
    """The inverse of :func:`_flatten`."""
    items: dict[int, object] = {}
    for name in sorted(arrays, key=lambda n: tuple(int(k) for k in n[1:].split("_"))):
        i, _, j = name[1:].partition("_")
        if j:
            items.setdefault(int(i), []).append(arrays[name])
        else:
            items[int(i)] = arrays[name]
    return tuple(items[i] for i in range(len(items)))


def _make_arm(path, name, root, chain, links, joints, X_W, q_rest) -> Arm:
    L = len(chain)
    origin_R, origin_t = np.zeros((L, 3, 3)), np.zeros((L, 3))
    joint, axis = np.full(L, -1), np.zeros((L, 3))
    jn, lo, hi, vel = [], [], [], []
    for k, link in enumerate(chain):
        jt = joints[link]
        origin_R[k], origin_t[k] = jt.X_PC[:3, :3], jt.X_PC[:3, 3]
        if jt.kind != "fixed":
            joint[k] = len(jn)
            axis[k] = jt.axis
            jn.append(jt.name)
            lo.append(jt.lower)
            hi.append(jt.upper)
            vel.append(jt.velocity)
    if not jn:
        raise InputError(f"{path}: the {name} arm has no movable joint")
    lower, upper = np.array(lo), np.array(hi)
    if q_rest is None:
        q_rest = np.array(SDA5F_REST) if len(jn) == len(SDA5F_REST) else (lower + upper) / 2
    q_rest = np.asarray(q_rest, dtype=float)
    if q_rest.shape != (len(jn),):
        raise InputError(f"{path}: the rest posture needs {len(jn)} joint values, got {q_rest.shape}")
    q_rest = np.clip(q_rest, lower, upper)

    cap_link, cap_a, cap_b, cap_r, cap_names = [], [], [], [], []
    for k, link in enumerate(chain):
        for g in links[link]:
            if g.kind != "capsule":
                raise InputError(f"{path}: link {link} of the {name} arm has a box collision; moving links "
                                 "take capsules, cylinders or spheres")
            cap_link.append(k)
            cap_a.append(g.dims[:3])
            cap_b.append(g.dims[3:6])
            cap_r.append(g.dims[6])
            cap_names.append(link)

    # Reach bound: the ball's distance from joint 2's origin depends on the later joints only and is
    # at most the sum of the later origin offsets plus the end-effector offset (triangle inequality).
    # Joint 2's origin moves on a circle about joint 1's axis, so centre the bound on that axis.
    movable = [k for k in range(L) if joint[k] >= 0]
    eef = L - 1
    arm = Arm(name=name, joint_names=tuple(jn), link_names=tuple(chain), eef_index=eef, X_WR=X_W[root],
              origin_R=origin_R, origin_t=origin_t, joint=joint, axis=axis, lower=lower, upper=upper,
              velocity=np.array(vel), q_rest=q_rest, cap_link=np.array(cap_link, dtype=int),
              cap_a=np.array(cap_a).reshape(-1, 3), cap_b=np.array(cap_b).reshape(-1, 3),
              cap_r=np.array(cap_r), cap_names=tuple(cap_names), reach_centre=np.zeros(3),
              reach_radius=math.inf)
    if len(movable) >= 2:
        k1, k2 = movable[0], movable[1]
        X0 = _fk_frames(arm, q_rest[:, None], upto=k2 + 1)
        p1, w1, p2 = X0[k1][1][:, 0], X0[k1][2][:, 0], X0[k2][1][:, 0]
        foot = p1 + np.dot(p2 - p1, w1) * w1  # joint 2's origin projected on joint 1's axis
        reach = np.linalg.norm(p2 - foot) + float(np.sum(np.linalg.norm(origin_t[k2 + 1:], axis=1)))
        arm = replace(arm, reach_centre=foot, reach_radius=reach + 1e-6)
    return arm


def _make_static(path, links, X_W, arm_links) -> Static:
    bn, bX, bh, cn, ca, cb, cr = [], [], [], [], [], [], []
    for link, X in X_W.items():
        if link in arm_links:
            continue
        for g in links[link]:
            if g.kind == "box":
                bn.append(link)
                bX.append(X @ g.X_LG)
                bh.append(g.dims)
            else:
                cn.append(link)
                ca.append(se3.transform_points(X, g.dims[:3]))
                cb.append(se3.transform_points(X, g.dims[3:6]))
                cr.append(g.dims[6])
    return Static(box_names=tuple(bn), box_X_W=np.array(bX).reshape(-1, 4, 4),
                  box_half=np.array(bh).reshape(-1, 3), cap_names=tuple(cn),
                  cap_a=np.array(ca).reshape(-1, 3), cap_b=np.array(cb).reshape(-1, 3), cap_r=np.array(cr))


# ----------------------------------------------------------------------------------------------------
# Collision kernels. Segments and points are component-major ``(3, K)``; every kernel returns ``(K,)``.


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _seg_seg_dist2(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Squared distances between segments ``p1 -> q1`` and ``p2 -> q2`` (closest points clamped to
    both segments; degenerate segments are points)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = _dot(d1, d1), _dot(d2, d2), _dot(d2, r)
    c, b = _dot(d1, r), _dot(d1, d2)
    tiny = 1e-18
    a_ok, e_ok = a > tiny, e > tiny
    denom = a * e - b * b
    # s on segment 1 minimizing the distance between the infinite lines, clamped; 0 when parallel.
    s = np.where(denom > tiny * np.maximum(a * e, tiny),
                 np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / np.where(e_ok, e, 1.0)
    # t out of [0, 1]: clamp it and recompute s for the clamped t.
    a_safe = np.where(a_ok, a, 1.0)
    s = np.where(t < 0.0, np.clip(-c / a_safe, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a_safe, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    # Degenerate cases: segment 2 a point (t = 0), segment 1 a point (s = 0).
    s = np.where(e_ok, s, np.clip(-c / a_safe, 0.0, 1.0))
    t = np.where(e_ok, t, 0.0)
    t = np.where(a_ok, t, np.clip(f / np.where(e_ok, e, 1.0), 0.0, 1.0) * e_ok)
    s = np.where(a_ok, s, 0.0)
    diff = (p1 + d1 * s) - (p2 + d2 * t)
    return _dot(diff, diff)


def _point_box_dist2(p: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Squared distances from points ``p (3, K)`` (box frame) to the box ``|x_i| <= h_i``."""
    ex = np.maximum(np.abs(p) - h, 0.0)
    return _dot(ex, ex)


def _seg_box_dist2(a: np.ndarray, b: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Squared distances from segments ``a -> b (3, K)`` (box frame) to the boxes ``|x_i| <= h_i``.

    ``g(t) = |p(t) - clamp(p(t))|^2`` is convex and piecewise quadratic in the segment parameter t,
    with breakpoints where a coordinate crosses a face plane; its derivative ``g'`` is continuous,
    piecewise linear and non-decreasing. The minimizer is 0, 1 or the zero of ``g'`` found by linear
    interpolation between the two sorted breakpoints that bracket it: exact, no iteration.
    """
    u = b - a
    K = a.shape[1]
    h = np.broadcast_to(h, a.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        tb = np.concatenate([(h - a) / u, (-h - a) / u], axis=0)  # (6, K)
    tb = np.where(np.isfinite(tb), np.clip(tb, 0.0, 1.0), 0.0)
    T = np.sort(np.concatenate([np.zeros((1, K)), tb, np.ones((1, K))], axis=0), axis=0)  # (8, K)

    def slope(t):  # g'(t) / 2 for t (J, K)
        p = a[:, None, :] + u[:, None, :] * t[None]
        ex = p - np.clip(p, -h[:, None, :], h[:, None, :])
        return np.sum(ex * u[:, None, :], axis=0)

    g = slope(T)
    j = np.argmax(g >= 0.0, axis=0)  # first breakpoint with g' >= 0 (0 if none: handled below)
    cols = np.arange(K)
    t_hi, g_hi = T[j, cols], g[j, cols]
    t_lo, g_lo = T[np.maximum(j - 1, 0), cols], g[np.maximum(j - 1, 0), cols]
    span = g_hi - g_lo
    t = np.where(span > 0, t_lo + (t_hi - t_lo) * (-g_lo) / np.where(span > 0, span, 1.0), t_hi)
    t = np.where(g[-1] < 0.0, 1.0, np.where(g[0] >= 0.0, 0.0, t))
    return _point_box_dist2(a + u * t, h)


def _point_cyl_dist(p: np.ndarray, radius: float, half_h: float) -> np.ndarray:
    """Distances from points ``p (3, K)`` (cylinder frame, axis z, centred) to a solid cylinder."""
    er = np.maximum(np.sqrt(p[0] * p[0] + p[1] * p[1]) - radius, 0.0)
    ez = np.maximum(np.abs(p[2]) - half_h, 0.0)
    return np.sqrt(er * er + ez * ez)


def _seg_cyl_dist(a: np.ndarray, b: np.ndarray, radius: float, half_h: float, iters: int = 48) -> np.ndarray:
    """Distances from segments ``a -> b (3, K)`` (cylinder frame) to a solid cylinder.

    The distance to a convex set is convex along the segment: golden-section search, whose bracket
    shrinks by 0.618 a step (48 steps: 1e-10 of the segment length).
    """
    u = b - a
    lo, hi = np.zeros(a.shape[1]), np.ones(a.shape[1])
    g = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = _point_cyl_dist(a + u * x1, radius, half_h), _point_cyl_dist(a + u * x2, radius, half_h)
    for _ in range(iters):
        left = f1 <= f2  # the minimum lies in [lo, x2]
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x_new = np.where(left, hi - g * (hi - lo), lo + g * (hi - lo))
        f_new = _point_cyl_dist(a + u * x_new, radius, half_h)
        x1, x2, f1, f2 = (np.where(left, x_new, x2), np.where(left, x1, x_new),
                          np.where(left, f_new, f2), np.where(left, f1, f_new))
    ends = np.minimum(_point_cyl_dist(a, radius, half_h), _point_cyl_dist(b, radius, half_h))
    return np.minimum(np.minimum(f1, f2), ends)


# ----------------------------------------------------------------------------------------------------
# Collision checking


@dataclass(frozen=True, eq=False)
class _Mesh:
    """A triangle mesh for collision: python-fcl BVH plus the numpy pre-filters (in the mesh frame)."""

    fcl_obj: object  # fcl.CollisionObject at the identity
    centre: np.ndarray  # (3,) bounding-sphere centre
    radius: float  # bounding-sphere radius
    lo: np.ndarray  # (3,) axis-aligned bounding box
    hi: np.ndarray  # (3,)
    planes: np.ndarray  # (F, 4) convex-hull face planes n . x <= d, unit n
    convex: bool  # the mesh is its own convex hull
    mesh: object  # trimesh.Trimesh, for inside tests of non-convex meshes
    coarse: object  # its simplification (stages.simplify.collision_mesh): the same inside answer for
    coarse_tol: float  # ... points farther than this (m) from the surface; 0 when it is the mesh
    coarse_fcl: object  # fcl.CollisionObject of ``coarse`` (None when it is the mesh)
    inner: np.ndarray  # (S, 4) spheres (centre, radius) inside the solid: a capsule reaching one hits
    few: np.ndarray  # (k,) ids of hull planes facing evenly spread directions: _mesh_hits' pre-filter


def _make_mesh(mesh, where: str) -> _Mesh:
    import trimesh

    from stages.simplify import CollisionMesh, collision_mesh

    if not isinstance(mesh, trimesh.Trimesh):
        try:
            v, f = mesh
            mesh = trimesh.Trimesh(np.asarray(v, dtype=float), np.asarray(f, dtype=np.int64), process=False)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{where}: expected a trimesh.Trimesh or (vertices, faces)") from exc
    if len(mesh.faces) == 0:
        raise InputError(f"{where}: the mesh has no faces")
    v = np.asarray(mesh.vertices, dtype=float)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    hull = mesh.convex_hull
    n = np.asarray(hull.face_normals)
    d = np.einsum("ij,ij->i", n, hull.triangles[:, 0])
    planes = np.unique(np.round(np.column_stack([n, d]), 9), axis=0)  # coplanar hull faces merged
    convex = bool(mesh.is_watertight and abs(mesh.volume - hull.volume) <= 1e-6 * hull.volume)
    coarse = collision_mesh(mesh) if not convex else CollisionMesh(mesh, 0.0)
    fcl_obj = _fcl_mesh(v, mesh.faces)
    inner = _inner_spheres(coarse.mesh, coarse.tolerance, fcl_obj) if mesh.is_watertight else np.zeros((0, 4))
    coarse_fcl = _fcl_mesh(coarse.mesh.vertices, coarse.mesh.faces) if coarse.tolerance > 0 else None
    return _Mesh(fcl_obj=fcl_obj, centre=centre, radius=float(np.linalg.norm(v - centre, axis=1).max()), lo=lo,
                 hi=hi, planes=planes, convex=convex, mesh=mesh, coarse=coarse.mesh, coarse_tol=coarse.tolerance,
                 coarse_fcl=coarse_fcl, inner=inner, few=_spread_planes(planes))


def _fcl_mesh(vertices, faces):
    """A python-fcl BVH of the triangles (``stages.fclmesh``), as a collision object at the identity."""
    import fcl

    from stages import fclmesh

    return fcl.CollisionObject(fclmesh.bvh(vertices, faces), fcl.Transform())


def _spread_planes(planes: np.ndarray, k: int = 96) -> np.ndarray:
    """Ids of the hull planes ``(F, 4)`` whose normals lie nearest ``k`` directions spread evenly over
    the sphere (a Fibonacci lattice), sorted: a coarse polytope around the hull, :func:`_mesh_hits`'
    separation filter."""
    i = np.arange(k) + 0.5
    z, phi = 1.0 - 2.0 * i / k, np.pi * (1.0 + 5.0 ** 0.5) * i
    u = np.stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z], axis=1)
    return np.unique(np.argmax(planes[:, :3] @ u.T, axis=0))


def _inner_spheres(coarse, tol: float, fcl_obj, cells: int = 12, most: int = 48) -> np.ndarray:
    """Up to ``most`` spheres ``(S, 4)`` (centre, radius; mesh frame, m) inside a closed mesh, for
    :func:`_mesh_hits`' exact early accept: a capsule that reaches one crosses or lies in the solid.

    Centres are the points of a ``cells``-per-longest-side grid that lie inside (the parity of their
    vertical ray's crossings of ``coarse``, the simplified surface, exact for points farther than
    ``tol`` from the true one); each radius is the centre's distance to the planning mesh (python-fcl
    on its BVH), shrunk by 1e-6 relative and 1e-7 m for rounding. Largest first, a centre inside 3/4
    of a chosen sphere's radius is skipped (a greedy cover, as a medial-axis sphere tree starts).
    """
    import fcl

    lo, hi = coarse.bounds
    h = float((hi - lo).max()) / cells
    # Columns off the grid's symmetry lines by an irrational fraction, so that no ray meets an edge.
    xs, ys, zs = (np.arange(lo[k] + h / 2, hi[k], h) + h * 1e-3 * np.sqrt(k + 2) for k in range(3))
    inside = _column_parity(np.asarray(coarse.triangles), xs, ys, zs)
    pts = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1)[inside]
    probe = fcl.CollisionObject(fcl.Sphere(1e-9), fcl.Transform())
    d = np.empty(len(pts))
    for i, p in enumerate(pts):
        probe.setTransform(fcl.Transform(p))
        d[i] = fcl.distance(probe, fcl_obj, fcl.DistanceRequest(), fcl.DistanceResult())
    r = d * (1 - 1e-6) - 1e-7
    good = (d > tol) & (r > 0)
    pts, r = pts[good], r[good]
    chosen: list[int] = []
    for i in np.argsort(-r, kind="stable"):
        if len(chosen) == most:
            break
        if not chosen or np.all(np.linalg.norm(pts[chosen] - pts[i], axis=1) >= 0.75 * r[chosen]):
            chosen.append(int(i))
    return np.column_stack([pts[chosen], r[chosen]]) if chosen else np.zeros((0, 4))


def _column_parity(tri: np.ndarray, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """Inside test ``(X, Y, Z)`` bool of the grid points of a closed mesh ``tri (F, 3, 3)``: an odd
    number of surface crossings above the point on its vertical line (Jordan parity). A column that
    passes within 1e-9 (barycentric) of a triangle's edge is reported outside throughout."""
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    px, py = X.ravel()[:, None], Y.ravel()[:, None]  # (Cn, 1)
    above = np.zeros((len(px), len(zs)), np.int64)
    grazing = np.zeros(len(px), bool)
    step = max(1, 1_000_000 // len(px))
    for s in range(0, len(tri), step):
        a, b, c = tri[s:s + step, 0], tri[s:s + step, 1], tri[s:s + step, 2]
        det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
        flat = np.abs(det) < 1e-15  # a vertical triangle: its neighbours count the crossing
        det = np.where(flat, 1.0, det)
        u = ((b[:, 0] - px) * (c[:, 1] - py) - (c[:, 0] - px) * (b[:, 1] - py)) / det
        v = ((c[:, 0] - px) * (a[:, 1] - py) - (a[:, 0] - px) * (c[:, 1] - py)) / det
        w = 1.0 - u - v
        bary = np.minimum(np.minimum(u, v), w)
        grazing |= np.any((np.abs(bary) <= 1e-9) & ~flat, axis=1)
        k, f = np.nonzero((bary > 0) & ~flat)
        zc = u[k, f] * a[f, 2] + v[k, f] * b[f, 2] + w[k, f] * c[f, 2]
        np.add.at(above, k, zc[:, None] > zs[None, :])
    inside = (above % 2 == 1) & ~grazing[:, None]
    return inside.reshape(len(xs), len(ys), len(zs))


def _capsules_W(a: Arm, qT: np.ndarray):
    """World endpoints ``A, B (3, C, m)`` of the arm's collision capsules at ``qT (n, m)``."""
    frames = _fk_frames(a, qT)
    C, m = len(a.cap_names), qT.shape[1]
    A, B = np.empty((3, C, m)), np.empty((3, C, m))
    for c, k in enumerate(a.cap_link):
        cols, p, _ = frames[k]
        A[:, c] = p + _combine(cols, a.cap_a[c])
        B[:, c] = p + _combine(cols, a.cap_b[c])
    return A, B


def _rigid_groups(a: Arm) -> np.ndarray:
    """Per frame of the arm: index of its rigid group (frames joined by fixed joints share one)."""
    return np.cumsum(a.joint >= 0) - 1


def _core_balls(a: Arm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Balls that lie inside a collision capsule of ``a`` at every posture.

    A capsule of the first movable link turns about the first joint's axis and nothing else moves it,
    so a ball centred on that axis at the point ``P`` nearest the capsule's segment, of radius the
    capsule radius minus that distance, lies inside it whatever ``q`` (rotations about the axis fix
    ``P``). Returns capsule ids ``(K,)``, centres ``(K, 3)`` (world) and radii ``(K,)`` (m, > 0).
    """
    grp = _rigid_groups(a)[a.cap_link]
    k1 = int(np.flatnonzero(a.joint >= 0)[0])
    frames = _fk_frames(a, a.q_rest[:, None], upto=k1 + 1)
    p1, w1 = frames[k1][1][:, 0], frames[k1][2][:, 0]
    A, B = _capsules_W(a, a.q_rest[:, None])
    ids, centres, radii = [], [], []
    for c in np.flatnonzero(grp == 0):
        u = B[:, c, 0] - A[:, c, 0]
        v0 = (A[:, c, 0] - p1) - np.dot(A[:, c, 0] - p1, w1) * w1  # segment minus its axial part
        v1 = u - np.dot(u, w1) * w1
        t = float(np.clip(-np.dot(v0, v1) / np.dot(v1, v1), 0.0, 1.0)) if np.dot(v1, v1) > 1e-18 else 0.0
        rho = a.cap_r[c] - np.linalg.norm(v0 + t * v1)
        if rho > 0.0:
            ids.append(c)
            centres.append(p1 + np.dot(A[:, c, 0] + t * u - p1, w1) * w1)
            radii.append(rho)
    return np.array(ids, dtype=int), np.array(centres).reshape(-1, 3), np.array(radii)


def _to_frame(X_inv: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Points ``P (3, ...)`` expressed in a frame whose inverse pose is ``X_inv (4, 4)``."""
    t = X_inv[:3, 3].reshape((3,) + (1,) * (P.ndim - 1))
    if np.array_equal(X_inv[:3, :3], np.eye(3)):  # axis-aligned boxes (the table, the trunk)
        return P + t
    return np.tensordot(X_inv[:3, :3], P, axes=1) + t


def _rows(X: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``X[..., rows]`` for sorted distinct ``rows``; ``X`` itself, not a copy, when they are all its rows."""
    return X if len(rows) == X.shape[-1] else X[..., rows]


def make_collision_fn(robot: Robot, table: tuple | None = None, obstacles=(), object_mesh=None,
                      margin: float = 0.0, table_depth: float = 1.0, threads: int = 1,
                      link_clearance: float = 0.0, tool_clearance: float | None = None) -> CollisionFn:
    """Build a batched collision checker for both arms of ``robot`` in a scene (paper §4.2).

    Parameters
    ----------
    robot : the robot (its trunk held at ``robot.torso_angle``).
    table : ``(size_xy, top_z)``: a box of footprint ``size_xy = (sx, sy)`` m centred on the world
        origin, from ``top_z - table_depth`` up to ``top_z`` (everything under the top counts as
        table). None: no table.
    obstacles : sequence of ``(kind, dims, X_W)`` or ``(kind, dims, X_W, name)``; kind ``"box"``
        (dims: full size ``(sx, sy, sz)``), ``"cylinder"`` (``(radius, height)``, axis z),
        ``"sphere"`` (``(radius,)``), ``"capsule"`` (``(radius, length)``, axis z) or ``"mesh"``
        (a trimesh.Trimesh or ``(vertices, faces)`` in its own frame); ``X_W (4, 4)`` its pose.
        Names default to ``obstacle_<i>``.
    object_mesh : trimesh.Trimesh of the object in its frame O, or None.
    margin : m; primitives closer than this count as colliding.
    link_clearance : m; the arms' links other than the ball end-effectors closer than this to the
        object (but not touching it, by ``margin``) fail with ``object_clearance:<link>/object``, and
        closer than this to the table or an obstacle with ``env_collision:<link>/<table or obstacle>``.
    tool_clearance : m; the same for the ball's parent link (the stick that carries it); None: as
        ``link_clearance``.
    threads : worker threads, each checking a slice of the rows (batches of at least 1024 rows); the
        numpy kernels release the GIL, python-fcl does not, and trimesh's inside test (not thread-safe)
        runs under a lock. Every row's answer depends on that row alone.

    Returns
    -------
    A ``CollisionFn``: ``check(q_left (N, n), q_right (N, n), X_WO (N, 4, 4) | None = None,
    touching (N, 2) bool | None = None) -> (ok (N,) bool, reason (N,) str)``.
    """
    return CollisionFn(robot, table, obstacles, object_mesh, margin, table_depth, threads,
                       (link_clearance, link_clearance if tool_clearance is None else tool_clearance))


class CollisionFn:
    """Batched collision test of both arms against the table, obstacles, the trunk, each other and
    the object; see ``make_collision_fn``.

    Calling it with ``q_left, q_right (N, n)``, optional object poses ``X_WO (N, 4, 4)`` and
    ``touching (N, 2)`` (the left/right ball is in contact with the object, so that ball, and only
    the ball, is exempt from the object test) returns ``ok (N,)`` and ``reason (N,)``. A reason names
    the first colliding pair found, in this order: ``env_collision:<link>/table``,
    ``env_collision:<link>/<obstacle>``, ``self_collision:<link>/<trunk link>``,
    ``self_collision:<left link>/<right link>``, ``self_collision:<link>/<link>`` (one arm),
    ``env_collision:<link>/object``, ``object_clearance:<link>/object`` (a link other than the ball
    within ``link_clearance``, or ``tool_clearance`` for the ball's parent link, of the object, the
    lowest such capsule); ``"ok"`` when free. Each stage
    only looks at the rows still free.
    With ``blame=True`` it also returns ``arms (N, 2)`` bool: the arms (left, right) whose links the
    reported pair names (both for a left/right pair; none for a free row).

    The self-collision pairs left out are described in ``_self_pairs`` (adjacent links, pairs
    touching at ``q = 0``, pairs that stay apart over random postures). The ball's contact with the
    object is taken as given: the contact sampler checks the ball itself. Everything is numpy over
    all rows and candidate pairs at once, each test behind a bounding-sphere (or bounding-box)
    pre-filter; python-fcl is called only for capsules near a mesh that no hull plane separates.
    """

    def __init__(self, robot: Robot, table, obstacles, object_mesh, margin: float, table_depth: float,
                 threads: int = 1, clearance: tuple[float, float] = (0.0, 0.0)):
        self.arms = (robot.arm("left"), robot.arm("right"))
        self.threads = int(threads)
        self.static = st = robot.static
        self.margin = float(margin)
        if not min(clearance) >= 0:
            raise ValueError(f"link and tool clearances must be >= 0 m, got {clearance}")
        #: m, of the object: links other than the ball and its parent link, and that parent link.
        self.link_clearance, self.tool_clearance = float(clearance[0]), float(clearance[1])
        self.boxes, self.caps, self.cyls, self.meshes = [], [], [], []
        if table is not None:
            (sx, sy), top_z = table
            X = se3.make_transform(np.eye(3), [0.0, 0.0, top_z - table_depth / 2])
            self.boxes.append(("table", se3.invert(X), np.array([sx / 2, sy / 2, table_depth / 2])))
        for i, ob in enumerate(obstacles):
            kind, dims, X_W = ob[0], ob[1], np.asarray(ob[2], dtype=float)
            name = ob[3] if len(ob) > 3 else f"obstacle_{i}"
            if X_W.shape != (4, 4):
                raise InputError(f"obstacle {name}: the pose must be a (4, 4) transform")
            if kind == "box":
                self.boxes.append((name, se3.invert(X_W), np.asarray(dims, dtype=float).reshape(3) / 2))
            elif kind == "cylinder":
                self.cyls.append((name, se3.invert(X_W), float(dims[0]), float(dims[1]) / 2))
            elif kind in ("sphere", "capsule"):
                h = float(dims[1]) / 2 if kind == "capsule" else 0.0
                a, b = se3.transform_points(X_W, np.array([[0, 0, -h], [0, 0, h]]))
                self.caps.append((name, a, b, float(dims[0])))
            elif kind == "mesh":
                self.meshes.append((name, se3.invert(X_W), _make_mesh(dims, f"obstacle {name}")))
            else:
                raise InputError(f"obstacle {name}: unknown kind {kind!r} (box, cylinder, sphere, capsule, "
                                 "mesh)")
        self.object = None if object_mesh is None else _make_mesh(object_mesh, "object mesh")
        # Bounding-sphere radius of each capsule (its segment does not change length), (C, 1).
        self.rho = [(np.linalg.norm(a.cap_b - a.cap_a, axis=1) / 2 + a.cap_r)[:, None] for a in self.arms]

        self.box_inv = (np.stack([se3.invert(X) for X in st.box_X_W]) if len(st.box_X_W)
                        else np.zeros((0, 4, 4)))
        self.trunk_box_pairs, self.trunk_cap_pairs, self.intra_pairs, self.lr_pairs = _self_pairs(robot)
        self.cores = [_core_balls(a) for a in self.arms]
        self.env_margin = [self._link_margins(a, self.margin) for a in self.arms]

    def _link_margins(self, a: Arm, mg: float) -> np.ndarray:
        """``(C,)`` m: each capsule's margin, ``mg`` for the ball, at least ``tool_clearance`` for its parent
        link (the stick) and ``link_clearance`` for the other links: the clearances the arm keeps from the
        object, the table and the obstacles alike (a link that grazes them in the plan touches them in
        physics, which tracks the joints only to a few mm)."""
        ball, tool = a.cap_link == a.eef_index, a.cap_link == a.eef_index - 1
        return np.where(ball, mg, np.maximum(mg, np.where(tool, self.tool_clearance, self.link_clearance)))

    def __call__(self, q_left: np.ndarray, q_right: np.ndarray, X_WO: np.ndarray | None = None,
                 touching: np.ndarray | None = None, *, blame: bool = False,
                 object_margin: float | None = None) -> tuple[np.ndarray, ...]:
        """``object_margin`` (m): the object test's margin for this call, when larger than the checker's."""
        N = len(q_left)
        mg_obj = self.margin if object_margin is None else max(self.margin, float(object_margin))
        chunks = min(self.threads, N // 1024)
        if chunks <= 1:
            out = self._check(q_left, q_right, X_WO, touching, mg_obj)
        else:
            def part(rows):
                return self._check(q_left[rows], q_right[rows], None if X_WO is None else X_WO[rows],
                                   None if touching is None else touching[rows], mg_obj)

            with ThreadPoolExecutor(chunks) as pool:
                parts = list(pool.map(part, np.array_split(np.arange(N), chunks)))
            out = tuple(np.concatenate(x) for x in zip(*parts, strict=True))
        return out if blame else out[:2]

    def _check(self, q_left, q_right, X_WO, touching, mg_obj: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        arms = self.arms
        qs = [_check_q(arms[0], q_left), _check_q(arms[1], q_right, len(q_left))]
        N = len(qs[0])
        if X_WO is not None:
            X_WO = np.asarray(X_WO, dtype=float)
            if X_WO.shape != (N, 4, 4):
                raise ValueError(f"X_WO must be ({N}, 4, 4), got {X_WO.shape}")
        touch = np.zeros((N, 2), bool) if touching is None else np.asarray(touching, dtype=bool)
        if touch.shape != (N, 2):
            raise ValueError(f"touching must be ({N}, 2), got {touch.shape}")
        st = _Rows(N)
        ends = [_capsules_W(a, np.ascontiguousarray(q.T)) for a, q in zip(arms, qs, strict=True)]
        mids = [(A + B) / 2 for A, B in ends]
        self._env_test(st, ends, mids)
        self._trunk_test(st, ends, mids)
        self._left_right_test(st, ends, mids)
        self._intra_test(st, ends, mids)

        # The object; a touching ball is exempt.
        if self.object is not None and X_WO is not None:
            for s in range(len(arms)):
                self._object_test(st, s, ends[s], X_WO, touch, mg_obj)
        return st.alive, st.reason.astype(str), st.blame

    def _env_test(self, st: _Rows, ends: list, mids: list) -> None:
        """The arms' capsules (``ends``, per arm their ends A, B; ``mids``, their middles) against the
        environment on the live rows of ``st``: the table (the first box), then boxes, capsules and
        spheres, cylinders, meshes, each within ``env_margin`` -> ``env_collision``."""
        arms, emg, rho = self.arms, self.env_margin, self.rho
        names = [np.asarray(a.cap_names) for a in arms]
        for name, Xi, h in self.boxes:
            for s, a in enumerate(arms):
                (A, B), rows = ends[s], st.live()
                c, k = np.nonzero(_point_box_dist2(_to_frame(Xi, _rows(mids[s], rows)), h[:, None, None])
                                  <= (rho[s] + emg[s][:, None]) ** 2)
                r = rows[k]
                hit = _seg_box_dist2(_to_frame(Xi, A[:, c, r]), _to_frame(Xi, B[:, c, r]), h[:, None]) \
                    < (a.cap_r[c] + emg[s][c]) ** 2
                st.fail(r[hit], "env_collision", names[s][c[hit]], name, s)
        for name, ea, eb, er in self.caps:
            for s, a in enumerate(arms):
                (A, B), rows = ends[s], st.live()
                erho = np.linalg.norm(eb - ea) / 2 + er
                dm = _rows(mids[s], rows) - ((ea + eb) / 2)[:, None, None]
                c, k = np.nonzero(_dot(dm, dm) <= (rho[s] + erho + emg[s][:, None]) ** 2)
                r = rows[k]
                ones = np.ones(len(c))
                hit = _seg_seg_dist2(A[:, c, r], B[:, c, r], ea[:, None] * ones, eb[:, None] * ones) \
                    < (a.cap_r[c] + er + emg[s][c]) ** 2
                st.fail(r[hit], "env_collision", names[s][c[hit]], name, s)
        for name, Xi, rad, hh in self.cyls:
            for s, a in enumerate(arms):
                (A, B), rows = ends[s], st.live()
                Pm = _to_frame(Xi, _rows(mids[s], rows))
                dm = _point_cyl_dist(Pm.reshape(3, -1), rad, hh).reshape(Pm.shape[1:])
                c, k = np.nonzero(dm <= rho[s] + emg[s][:, None])
                r = rows[k]
                hit = _seg_cyl_dist(_to_frame(Xi, A[:, c, r]), _to_frame(Xi, B[:, c, r]), rad, hh) \
                    < a.cap_r[c] + emg[s][c]
                st.fail(r[hit], "env_collision", names[s][c[hit]], name, s)
        for name, Xi, msh in self.meshes:
            for s, a in enumerate(arms):
                (A, B), rows = ends[s], st.live()
                k, c = _mesh_hits(msh, np.broadcast_to(Xi, (len(rows), 4, 4)), _rows(A, rows), _rows(B, rows),
                                  a.cap_r, emg[s], np.ones((len(a.cap_r), len(rows)), bool))
                st.fail(rows[k], "env_collision", names[s][c], name, s)

    def _trunk_test(self, st: _Rows, ends: list, mids: list) -> None:
        """Each arm's capsules against the trunk's boxes and capsules (the pairs that can meet), within
        ``margin`` -> ``self_collision``."""
        arms, mg, rho = self.arms, self.margin, self.rho
        trunk = self.static
        for s, a in enumerate(arms):
            (A, B), M, rh, r_c = ends[s], mids[s], rho[s], a.cap_r
            for kb in range(len(self.box_inv)):  # a handful of trunk boxes, each against its capsules
                cc = self.trunk_box_pairs[s][self.trunk_box_pairs[s][:, 0] == kb, 1]
                if not len(cc):
                    continue
                rows, Xi, h = st.live(), self.box_inv[kb], trunk.box_half[kb]
                p, k = np.nonzero(_point_box_dist2(_to_frame(Xi, _rows(M[:, cc], rows)), h[:, None, None])
                                  <= (rh[cc] + mg) ** 2)
                r, c = rows[k], cc[p]
                hit = _seg_box_dist2(_to_frame(Xi, A[:, c, r]), _to_frame(Xi, B[:, c, r]), h[:, None]) \
                    < (r_c[c] + mg) ** 2
                st.fail(r[hit], "self_collision", np.asarray(a.cap_names)[c[hit]], trunk.box_names[kb], s)
            if len(self.trunk_cap_pairs[s]):
                rows = st.live()
                kk, cc = self.trunk_cap_pairs[s].T
                p, k = np.nonzero(np.ones((len(kk), len(rows)), bool))
                r = rows[k]
                hit = _seg_seg_dist2(trunk.cap_a[kk[p]].T, trunk.cap_b[kk[p]].T, A[:, cc[p], r], B[:, cc[p], r]) \
                    < (trunk.cap_r[kk[p]] + r_c[cc[p]] + mg) ** 2
                st.fail(r[hit], "self_collision", np.asarray(a.cap_names)[cc[p[hit]]],
                        np.asarray(trunk.cap_names)[kk[p[hit]]], s)

    def _left_right_test(self, st: _Rows, ends: list, mids: list) -> None:
        """The left arm against the right, only on rows whose arms' bounding boxes overlap, within
        ``margin`` -> ``self_collision``."""
        arms, mg, rho = self.arms, self.margin, self.rho
        rows = st.live()
        box = [(np.min(_rows(np.minimum(A, B), rows) - a.cap_r[:, None], axis=1),
                np.max(_rows(np.maximum(A, B), rows) + a.cap_r[:, None], axis=1))
               for a, (A, B) in zip(arms, ends, strict=True)]
        rows = rows[np.all((box[0][0] <= box[1][1] + mg) & (box[1][0] <= box[0][1] + mg), axis=0)]
        if len(rows) and len(self.lr_pairs):
            i, j = self.lr_pairs.T
            dm = _rows(mids[0], rows)[:, i] - _rows(mids[1], rows)[:, j]
            p, k = np.nonzero(_dot(dm, dm) <= (rho[0][i] + rho[1][j] + mg) ** 2)
            r = rows[k]
            (Al, Bl), (Ar, Br) = ends
            hit = _seg_seg_dist2(Al[:, i[p], r], Bl[:, i[p], r], Ar[:, j[p], r], Br[:, j[p], r]) \
                < (arms[0].cap_r[i[p]] + arms[1].cap_r[j[p]] + mg) ** 2
            st.fail(r[hit], "self_collision", np.asarray(arms[0].cap_names)[i[p[hit]]],
                    np.asarray(arms[1].cap_names)[j[p[hit]]], None)

    def _intra_test(self, st: _Rows, ends: list, mids: list) -> None:
        """Within one arm: the capsule pairs of ``intra_pairs``, within ``margin`` -> ``self_collision``."""
        arms, mg, rho = self.arms, self.margin, self.rho
        for s, a in enumerate(arms):
            if not len(self.intra_pairs[s]):
                continue
            rows = st.live()
            (A, B), M, rh = ends[s], mids[s], rho[s]
            i, j = self.intra_pairs[s].T
            Mr = _rows(M, rows)
            dm = Mr[:, i] - Mr[:, j]
            p, k = np.nonzero(_dot(dm, dm) <= (rh[i] + rh[j] + mg) ** 2)
            r = rows[k]
            hit = _seg_seg_dist2(A[:, i[p], r], B[:, i[p], r], A[:, j[p], r], B[:, j[p], r]) \
                < (a.cap_r[i[p]] + a.cap_r[j[p]] + mg) ** 2
            st.fail(r[hit], "self_collision", np.asarray(a.cap_names)[i[p[hit]]],
                    np.asarray(a.cap_names)[j[p[hit]]], s)

    def _object_test(self, st: _Rows, s: int, ends, X_WO: np.ndarray, touch: np.ndarray, mg_obj: float) -> None:
        """Arm ``s``'s capsules against the object on the live rows: a link (the touching ball exempt)
        within ``mg_obj`` fails as ``env_collision``, then one (not a ball) within ``link_clearance``
        (its parent link: ``tool_clearance``) of the object, on the rows left, as ``object_clearance``."""
        a = self.arms[s]
        ball = a.cap_link == a.eef_index
        wide = self._link_margins(a, mg_obj)
        names = np.asarray(a.cap_names)
        for kind, margin in (("env_collision", mg_obj), ("object_clearance", wide)):
            rows = st.live()
            if not len(rows):
                return
            test = np.ones((len(a.cap_names), len(rows)), bool)
            test[ball] = ~touch[rows, s]
            if kind == "object_clearance":
                if not np.any(wide > mg_obj):
                    return
                test &= (wide > mg_obj)[:, None]
            k, c = _mesh_hits(self.object, se3.invert(X_WO[rows]), _rows(ends[0], rows), _rows(ends[1], rows),
                              a.cap_r, margin, test)
            st.fail(rows[k], kind, names[c], "object", s)

    def object_blocks_arm(self, X_WO: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Object poses at which some posture-independent part of an arm (``_core_balls``) overlaps the
        object, so that every posture of that arm collides with it (the margin only adds to that).

        Returns ``blocked (N, 2)`` bool (left, right) and ``reason (N,)`` str: the collision the
        checker would report, ``env_collision:<link>/object`` for the first blocked arm, else ``"ok"``.
        """
        X_WO = np.asarray(X_WO, dtype=float).reshape(-1, 4, 4)
        N = len(X_WO)
        blocked = np.zeros((N, 2), bool)
        reason = np.full(N, "ok", dtype=object)
        if self.object is None or N == 0:
            return blocked, reason.astype(str)
        X_OW = se3.invert(X_WO)
        for s, (a, (ids, centres, radii)) in enumerate(zip(self.arms, self.cores, strict=True)):
            if not len(ids):
                continue
            P = np.broadcast_to(centres.T[:, :, None], (3, len(ids), N))
            k, c = _mesh_hits(self.object, X_OW, P, P, radii, 0.0, np.ones((len(ids), N), bool))
            blocked[k, s] = True
            fresh = reason[k] == "ok"
            reason[k[fresh]] = "env_collision:" + np.asarray(a.cap_names, dtype=object)[ids[c[fresh]]] + "/object"
        return blocked, reason.astype(str)


def _self_pairs(robot: Robot, samples: int = 10000, never_clearance: float = 0.02):
    """Self-collision pairs worth testing, per arm: trunk box vs capsule ``(P, 2)``, trunk capsule vs
    capsule ``(P, 2)``, capsule vs capsule of one arm ``(P, 2)``; and left vs right capsules ``(P, 2)``.

    Left out, as MoveIt's setup assistant does: links of one rigid group or of adjacent groups (the
    trunk is one group); pairs already in contact at ``q = 0`` (the fitted capsules are fat); pairs
    that stayed more than ``never_clearance`` (m) apart over ``samples`` random in-limit postures
    (fixed seed), e.g. the forearm and the ball, which the wrist's limits keep apart. Cached on the
    robot.
    """
    return _derived(robot, ("self_pairs", samples, never_clearance),
                    lambda: _derive_self_pairs(robot, samples, never_clearance))


def _derive_self_pairs(robot: Robot, samples: int, never_clearance: float) -> tuple[np.ndarray, ...]:
    """What :func:`_self_pairs` returns, derived from ``samples`` random postures."""
    arms, st = (robot.arm("left"), robot.arm("right")), robot.static
    rng = np.random.default_rng(0)
    box_inv = [se3.invert(X) for X in st.box_X_W]
    ends = []
    for a in arms:
        q = np.concatenate([np.zeros((1, a.dof)), rng.uniform(a.lower, a.upper, (samples, a.dof))])
        ends.append(_capsules_W(a, np.ascontiguousarray(q.T)))  # column 0 is q = 0

    def keep(clearance: np.ndarray) -> bool:
        return bool(clearance[0] >= 0.0 and clearance[1:].min() <= never_clearance)

    out: list[list] = [[], [], []]
    for s, a in enumerate(arms):
        (A, B), r = ends[s], a.cap_r
        grp = _rigid_groups(a)[a.cap_link]
        far = np.flatnonzero(grp >= 1)  # group 0 hangs on the trunk
        tb = [(k, c) for k in range(len(box_inv)) for c in far
              if keep(np.sqrt(_seg_box_dist2(_to_frame(box_inv[k], A[:, c]), _to_frame(box_inv[k], B[:, c]),
                                             st.box_half[k][:, None])) - r[c])]
        tc = [(k, c) for k in range(len(st.cap_names)) for c in far
              if keep(np.sqrt(_seg_seg_dist2(st.cap_a[k][:, None], st.cap_b[k][:, None], A[:, c], B[:, c]))
                      - st.cap_r[k] - r[c])]
        ia = [(i, j) for i in range(len(grp)) for j in range(i + 1, len(grp)) if abs(grp[i] - grp[j]) >= 2
              and keep(np.sqrt(_seg_seg_dist2(A[:, i], B[:, i], A[:, j], B[:, j])) - r[i] - r[j])]
        for lst, pairs in zip(out, (tb, tc, ia), strict=True):
            lst.append(np.array(pairs, dtype=int).reshape(-1, 2))
    (Al, Bl), (Ar, Br) = ends
    rl, rr = arms[0].cap_r, arms[1].cap_r
    lr = np.array([(i, j) for i in range(len(rl)) for j in range(len(rr))
                   if keep(np.sqrt(_seg_seg_dist2(Al[:, i], Bl[:, i], Ar[:, j], Br[:, j])) - rl[i] - rr[j])],
                  dtype=int).reshape(-1, 2)
    return (*out, lr)


class _Rows:
    """Per-call bookkeeping of ``CollisionFn``: which rows are still free, why the others are not, and
    which arms the reported pair involves."""

    def __init__(self, n: int):
        self.alive = np.ones(n, bool)
        self.reason = np.full(n, "ok", dtype=object)
        self.blame = np.zeros((n, 2), bool)

    def live(self) -> np.ndarray:
        return np.flatnonzero(self.alive)

    def fail(self, rows: np.ndarray, kind: str, first, second, arm: int | None) -> None:
        """Mark ``rows`` (candidate order, repeats allowed) as colliding between the links named
        ``first`` and ``second`` (arrays parallel to rows, or one name); a row keeps its first pair.
        ``arm``: index of the arm whose link collides, None for a pair of one link of each arm."""
        if len(rows) == 0:
            return
        rows, idx = np.unique(rows, return_index=True)
        new = self.alive[rows]
        first = np.broadcast_to(np.asarray(first, dtype=object), (len(idx),) if np.ndim(first) == 0 else
                                np.shape(first))
        second = np.broadcast_to(np.asarray(second, dtype=object), first.shape)
        self.reason[rows[new]] = kind + ":" + first[idx[new]] + "/" + second[idx[new]]
        self.blame[rows[new], :] = arm is None
        if arm is not None:
            self.blame[rows[new], arm] = True
        self.alive[rows] = False


#: Serializes ``trimesh.Trimesh.contains`` between the checker's worker threads.
_CONTAINS_LOCK = threading.Lock()


def _mesh_hits(msh: _Mesh, X_OW: np.ndarray, A: np.ndarray, B: np.ndarray, radius: np.ndarray,
               margin: float | np.ndarray, test: np.ndarray):
    """Capsules ``A, B (3, C, m)`` (world) against a mesh posed by ``X_OW (m, 4, 4)`` (world to mesh),
    each capsule inflated by ``margin`` (m; one for all, or ``(C,)``).

    Only ``test (C, m)`` pairs are examined. Numpy filters run before python-fcl: the mesh's bounding
    box (in the mesh frame, grown by the capsule radius), then separation from a coarse polytope
    around its convex hull (``_Mesh.few``, the hull planes facing spread directions: a capsule it
    separates misses the hull): the capsule's segment, clipped by those planes pushed out by the
    capsule radius (Cyrus–Beck), is empty. A capsule that reaches one of the spheres inside the solid
    (``_Mesh.inner``) collides, with no exact test. The rest, below a row's lowest such capsule, goes
    to ``fcl.collide`` (capsule inflated by the margin), capsule by capsule in index order; a row
    already hit by a lower capsule is not tested again; a fine mesh's simplification answers first
    where it can (:func:`_fcl_hits`). A capsule with no triangle contact can still lie wholly inside
    the mesh, so one of its points is tested for inclusion (every hull plane first, which decides for a
    convex mesh, then trimesh's ray test). Returns one hit per colliding row, its lowest colliding capsule, as
    ``(row, capsule)`` index arrays ordered by capsule then row.
    """
    # Every capsule in the mesh frame (R A + t per row, written out: einsum is slower here), then the
    # mesh's bounding box grown by the capsule radius.
    R, t = np.ascontiguousarray(np.moveaxis(X_OW[:, :3, :3], 0, -1)), np.ascontiguousarray(X_OW[:, :3, 3].T)
    rr = radius + margin

    def to_mesh(P):
        return np.stack([R[i, 0] * P[0] + R[i, 1] * P[1] + R[i, 2] * P[2] + t[i] for i in range(3)])

    Ao, Bo = to_mesh(A), to_mesh(B)
    grow = rr[:, None]
    near = test & np.all((np.minimum(Ao, Bo) <= msh.hi[:, None, None] + grow)
                         & (np.maximum(Ao, Bo) >= msh.lo[:, None, None] - grow), axis=0)
    c, k = np.nonzero(near)
    if not len(c):
        return k, c
    a, b, rc = Ao[:, c, k], Bo[:, c, k], rr[c]
    separated = _hull_separated(msh.planes[msh.few], a, b, rc)[0]
    c, k, a, b, rc = c[~separated], k[~separated], a[:, ~separated], b[:, ~separated], rc[~separated]
    # Exact early accept: a capsule that reaches a sphere inside the solid. Only capsules below a row's
    # lowest accepted one need python-fcl (each row reports its lowest colliding capsule).
    accept = _reaches_inner(msh.inner, a, b, rc)
    lowest = np.full(X_OW.shape[0], len(radius))
    np.minimum.at(lowest, k[accept], c[accept])
    hit = accept & (c == lowest[k])
    tested = _fcl_hits(msh, a, b, rc, c, k, c < lowest[k], hit, X_OW.shape[0])
    # Wholly inside: no triangle contact, yet the segment start is inside the mesh (first its hull).
    inside = tested & ~hit
    if inside.any():
        inside[inside] = np.all(msh.planes[:, :3] @ a[:, inside] <= msh.planes[:, 3:], axis=0)
    if inside.any() and not msh.convex:
        # fcl found no triangle within rc of the capsule, so its start is farther than rc from the
        # surface: a simplification that moved no surface by more than rc answers alike, faster.
        test_mesh = msh.coarse if msh.coarse_tol < rc[inside].min() else msh.mesh
        with _CONTAINS_LOCK:  # trimesh's ray test (its rtree, its caches) is not thread-safe
            inside[inside] = test_mesh.contains(a[:, inside].T)
    hit |= inside
    # One per row: its lowest colliding capsule (the hits are in capsule-major order).
    _, first = np.unique(k[hit], return_index=True)
    hit = np.flatnonzero(hit)[first]
    order = np.lexsort((k[hit], c[hit]))
    return k[hit][order], c[hit][order]


def _fcl_hits(msh: _Mesh, a: np.ndarray, b: np.ndarray, rc: np.ndarray, c: np.ndarray, k: np.ndarray,
              todo: np.ndarray, hit: np.ndarray, rows: int) -> np.ndarray:
    """:func:`_mesh_hits`' exact test: python-fcl on the capsules ``todo`` (segments ``a b (3, K)`` in the
    mesh frame, radii ``rc``, capsule ids ``c`` and rows ``k``), capsule-major, a row's capsules no more
    once one hits; ``hit (K,)`` is updated in place. A fine mesh's
    simplification, whose surface is within ``coarse_tol`` of the mesh's both ways, decides alone
    outside a band of +-tol about the capsule's radius (a miss grown by tol, a hit shrunk by it): the
    same answer as the mesh's, on a few hundred triangles instead of 10^5. Returns ``tested (K,)``."""
    import fcl

    tested = np.zeros(len(c), bool)
    req = fcl.CollisionRequest()
    u = b - a
    length = np.linalg.norm(u, axis=0)
    Rz = se3.rotation_between(np.array([0.0, 0.0, 1.0]), np.where(length > 1e-12, u, [[0.0], [0.0], [1.0]]).T)
    centre = ((a + b) / 2).T
    shapes: dict = {}  # one fcl object per capsule and radius (its length and radius do not change with q)

    def touches(i: int, r: float, target) -> bool:  # capsule i, radius r, posed, against ``target``
        key = (int(c[i]), r)
        if key not in shapes:
            shapes[key] = fcl.CollisionObject(fcl.Sphere(r) if length[i] <= 1e-12 else fcl.Capsule(r, length[i]),
                                              fcl.Transform())
        shapes[key].setTransform(fcl.Transform(Rz[i], centre[i]))
        return fcl.collide(shapes[key], target, req, fcl.CollisionResult()) > 0

    tol = msh.coarse_tol if msh.coarse_fcl is not None else 0.0
    row_hit = [False] * rows  # a row hit by fcl: its higher capsules are not tested
    for i in np.flatnonzero(todo).tolist():  # capsule-major (np.nonzero)
        ki = int(k[i])
        if row_hit[ki]:
            continue
        tested[i] = True
        if tol > 0.0 and rc[i] > tol:
            if not touches(i, rc[i] + tol, msh.coarse_fcl):
                continue
            if touches(i, rc[i] - tol, msh.coarse_fcl):
                hit[i] = row_hit[ki] = True
                continue
        if touches(i, rc[i], msh.fcl_obj):
            hit[i] = row_hit[ki] = True
    return tested


def _hull_separated(planes: np.ndarray, a: np.ndarray, b: np.ndarray, rc: np.ndarray,
                    chunk: int = 1 << 22) -> tuple[np.ndarray, np.ndarray]:
    """Cyrus–Beck clipping of segments ``a b (3, K)`` (mesh frame) by the convex polytope's face planes
    ``planes (F, 4)`` (``n . x <= d``) pushed out by ``rc (K,)`` m: ``separated (K,)``, the clipped
    segment is empty (the inflated capsule misses the polytope), and ``start_in (K,)``, ``a`` lies
    inside every plane. Columns in slices of about ``chunk // F``, so memory stays bounded on fine
    hulls. A subset of a hull's planes bounds a larger polytope: what it separates, the hull does."""
    K = a.shape[1]
    n, d = planes[:, :3], planes[:, 3]
    separated, start_in = np.zeros(K, bool), np.zeros(K, bool)
    step = max(1, chunk // max(len(planes), 1))
    for s in range(0, K, step):
        sl = slice(s, s + step)
        sa, sb = n @ a[:, sl] - d[:, None], n @ b[:, sl] - d[:, None]  # (F, k) signed distances
        # Parameters t in [0, 1] of the segment within every plane pushed out by rc: sa + t (sb - sa) <= rc.
        ds = sb - sa
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = (rc[sl] - sa) / ds
        lo = np.max(np.where(ds < 0, bound, 0.0), axis=0, initial=0.0)
        hi = np.min(np.where(ds > 0, bound, 1.0), axis=0, initial=1.0)
        separated[sl] = (lo > hi) | np.any((ds == 0) & (sa > rc[sl]), axis=0)
        start_in[sl] = np.all(sa <= 0.0, axis=0)
    return separated, start_in


def _reaches_inner(inner: np.ndarray, a: np.ndarray, b: np.ndarray, rc: np.ndarray) -> np.ndarray:
    """``(K,)`` bool: segment ``a b (3, K)`` (mesh frame) within ``rc (K,)`` plus the radius of one of
    the spheres ``inner (S, 4)``, so that the inflated capsule overlaps the solid."""
    out = np.zeros(a.shape[1], bool)
    if not len(inner) or not a.shape[1]:
        return out
    u = b - a
    uu = np.maximum(_dot(u, u), 1e-300)
    step = max(1, 2_000_000 // len(inner))
    for s in range(0, a.shape[1], step):
        sl = slice(s, s + step)
        w = inner[:, :3, None] - a[None, :, sl]  # (S, 3, k)
        t = np.clip(np.einsum("sik,ik->sk", w, u[:, sl]) / uu[sl], 0.0, 1.0)
        d = w - t[:, None, :] * u[None, :, sl]
        reach = inner[:, 3, None] + rc[None, sl]
        out[sl] = np.any(np.einsum("sik,sik->sk", d, d) < reach * reach, axis=0)
    return out
