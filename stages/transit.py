"""Transit motions for regrasping (§5.2.2, §5.3): collision-free joint paths of one arm.

A regrasp moves one ball end-effector from its contact on the object to a new contact while the other
arm stays still, holding the object or not (§5.2.2: in USP "the left EEF moves to the desired position
while the right EEF maintains contact with the object and vice versa"; §5.3: "we use RRT to sample the
space considering grasp configurations"). ``plan_transit`` returns a joint path ``(K, n)`` (rad) of the
moving arm in three parts:

1. *retreat*: from the start configuration, whose ball touches the object, straight out along the start
   contact normal ``n_start`` by ``Params.retreat`` (m), by position IK on a few waypoints
   (``Robot.ik_trajectory``, one IK branch);
2. *transit*: from the retreat configuration to the approach configuration; first the straight
   joint-space segment, and only when that collides OMPL's RRT-Connect, then shortcutting;
3. *approach*: the retreat of the goal contact, reversed, ending in the goal configuration.

Collision rules. Every state is tested with the batched checker of ``stages.robot``
(``make_collision_fn``) against the table, obstacles, the trunk, the still arm and the object at its
fixed pose ``X_WO``. The moving ball is exempt from the object test only on the retreat and approach
segments (it starts and ends in contact and moves along the normal there); the retreat and approach
configurations themselves, 3 cm off the surface, and everything between them are tested in full,
between them with the object's margin raised to ``Params.clearance`` (kept only when the retreat and
approach configurations pass it). The still arm's ball is always exempt from the object test: it does
not move, and whether it may touch the object is the grasp's business, not the transit's. The arms'
other links keep the checker's own clearances from the object everywhere, the contact ends, retreat and
approach included (``stages.sample.Params.arm_clearance``: physics touches what grazes).

Motion checking. A straight joint-space segment is checked at states spaced so that no point of the
moving arm moves more than ``Params.resolution`` (m) between two of them: with ``L_j`` a bound on the
distance from joint j's axis to any point of the collision shapes downstream (triangle inequality over
the chain offsets), a point moves at most ``sum_j L_j |dq_j|``. A call of the checker costs about 6 ms
plus 0.1 ms a state (the SDA5F with the toy piano, 2 cores), so calls are few and large: the two ends,
the retreat, the approach and the direct segment go in one call; each OMPL motion check sends all of
its segment's states in one call (OMPL's state validity checker only enforces the bounds, since every
tree edge passes the motion validator, which checks both of its ends); the shortcutting screens all
candidate segments from a waypoint in one coarse call. The RRT-Connect part is re-checked as a whole
at the end, so every state of a returned path has passed the checker at ``Params.resolution``.

Determinism. OMPL's RNG is seeded (``ompl.util.RNG.setSeed``) before the planner, its sampler and the
state space are created, and the planner stops after ``Params.max_iterations`` iterations (a
termination condition counting its own calls) rather than on a clock, so equal inputs and seed give
equal paths. ``Params.time_limit`` is only a safety stop; a query that hits it instead of finding a path
or exhausting its iterations is reported as such (its outcome then depends on the machine's speed).
Shortcutting is deterministic (greedy, no random choices).

``time_parameterize`` turns a path into a trajectory that stops at every waypoint: the arm follows the
checked straight segments exactly, with a minimum-time trapezoidal (or triangular) velocity profile on
each one under the joint velocity and acceleration limits.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

#: Status values of ``TransitResult.status``.
TRANSIT_STATUS = ("ok", "no_transit_path", "start_in_collision", "goal_in_collision", "ik_unreachable")


@dataclass(frozen=True)
class Params:
    """Transit planning and timing parameters (rad, m, s)."""

    #: RRT-Connect extension length (rad, Euclidean in joint space).
    range: float = 0.4
    #: Largest displacement (m) of any point of the moving arm between two checked states of a segment.
    resolution: float = 0.01
    #: Safety stop of one RRT-Connect query (s); ``max_iterations`` is the deterministic limit.
    time_limit: float = 5.0
    #: RRT-Connect iterations (one sample, one extension, one connection attempt each).
    max_iterations: int = 100
    #: Shorten the RRT-Connect path by greedy shortcutting with the batched checker.
    simplify: bool = True
    #: Seed of OMPL's random number generator.
    seed: int = 0
    #: Clearance (m) the arm keeps from the object between the retreat and the approach (the
    #: collision checker's margin for the object there): a path that grazes the object at the check's
    #: resolution touches it in physics, where the object lies a few mm from its planned pose (Exp. 3's
    #: hand-over: the left stick brushed the piano's top edge). The transit keeps none when the
    #: retreat's or the approach's end lies closer than that.
    clearance: float = 0.005
    #: Distance (m) the ball backs off its contact along the contact normal before transit, and the
    #: distance off the new contact from which it approaches.
    retreat: float = 0.03
    #: IK waypoints along a retreat or approach; a retreat whose step-to-step IK jumps (a damped
    #: least-squares step near a joint limit can swing the arm round) is solved again with
    #: ``retreat_refine`` times as many.
    retreat_steps: int = 3
    retreat_refine: int = 4
    #: Fraction of each joint's velocity limit used by ``time_parameterize`` (see ``velocity_limits``).
    max_vel_scale: float = 0.5
    #: Joint acceleration limit (rad/s^2) for ``time_parameterize``.
    max_acc: float = 2.0
    #: Sampling period (s) of ``time_parameterize`` (50 Hz).
    dt: float = 0.02

    def __post_init__(self):
        for name in ("range", "resolution", "time_limit", "max_vel_scale", "max_acc", "dt"):
            if not getattr(self, name) > 0:
                raise ValueError(f"transit Params.{name} must be positive, got {getattr(self, name)}")
        if self.retreat <= 0 or self.retreat_steps < 1 or self.retreat_refine < 1 or self.max_iterations < 1:
            raise ValueError("transit Params: retreat > 0, retreat_steps >= 1, retreat_refine >= 1 and "
                             "max_iterations >= 1 required")


@dataclass(frozen=True)
class TransitResult:
    """Outcome of ``plan_transit``.

    ``status`` is one of ``TRANSIT_STATUS``; ``path (K, n)`` rad holds the moving arm's waypoints from
    the start to the goal configuration (empty ``(0, n)`` unless ``status == "ok"``), joined by straight
    joint-space segments: ``path[:n_retreat + 1]`` is the retreat, ``path[K - 1 - n_approach:]`` the
    approach. ``reason`` says why in words (the colliding pair, the IK outcome, ...). ``stats`` holds
    counts and times (``planner``: ``"direct"`` or ``"rrt_connect"``, ``iterations`` and ``stop``, why
    RRT-Connect stopped, ``checks``, the number of batched checker calls, ``states`` checked, ``time``
    s); they are not part of any artifact.
    """

    status: str
    path: np.ndarray
    reason: str
    n_retreat: int = 0
    n_approach: int = 0
    stats: dict = field(default_factory=dict)


def velocity_limits(robot, arm: str, params: Params) -> np.ndarray:
    """Joint velocity limits ``(n,)`` rad/s for ``time_parameterize``: the URDF limits scaled by
    ``params.max_vel_scale``."""
    return np.asarray(robot.arm(arm).velocity, dtype=float) * params.max_vel_scale


def lever_arms(arm_model) -> np.ndarray:
    """``L (n,)`` m: a bound on the distance from each joint's axis to any point of the collision
    shapes it moves, from the chain offsets by the triangle inequality.

    A joint step ``dq`` therefore moves no point of the arm by more than ``sum_j L_j |dq_j|``.
    """
    a = arm_model
    step = np.linalg.norm(a.origin_t, axis=1)  # (L,) offset of frame k from frame k - 1
    reach = np.maximum(np.linalg.norm(a.cap_a, axis=1), np.linalg.norm(a.cap_b, axis=1)) + a.cap_r  # (C,)
    L = np.zeros(a.dof)
    for k in np.flatnonzero(a.joint >= 0):
        down = a.cap_link >= k
        if down.any():
            # Distance from frame k's origin (on the joint axis) to frame f is at most the offsets k+1..f.
            offsets = np.array([step[k + 1: f + 1].sum() for f in a.cap_link[down]])
            L[a.joint[k]] = float(np.max(offsets + reach[down]))
    return L


def densify(path: np.ndarray, weights: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """States along the straight segments of ``path (K, n)``, spaced so that ``sum_j w_j |dq_j| <= step``.

    Returns ``states (M, n)`` (each segment's interior states and its end, not ``path[0]``) and
    ``segment (M,)`` int, the segment each state lies on (segment i joins ``path[i]`` and ``path[i + 1]``).
    """
    path = np.asarray(path, dtype=float)
    if len(path) < 2:
        return np.zeros((0, path.shape[1])), np.zeros(0, dtype=int)
    d = np.diff(path, axis=0)  # (K-1, n)
    m = np.maximum(1, np.ceil(np.abs(d) @ weights / step - 1e-9)).astype(int)  # subdivisions per segment
    seg = np.repeat(np.arange(len(d)), m)
    first = np.concatenate([[0], np.cumsum(m)[:-1]])
    k = np.arange(len(seg)) - np.repeat(first, m) + 1  # 1 .. m_i within segment i
    t = k / np.repeat(m, m)
    states = path[seg] + t[:, None] * d[seg]
    states[np.cumsum(m) - 1] = path[1:]  # segment ends exactly, not up to rounding
    return states, seg


class _Checker:
    """The moving arm's states against everything, the still arm at ``q_other``, the object at ``X_WO``.

    ``check(Q (N, n), ball_exempt (N,) bool) -> (ok (N,), reason (N,))``; counts calls and states.
    """

    def __init__(self, collide, moving: int, q_other: np.ndarray, X_WO: np.ndarray | None,
                 margin: float | None = None):
        self.collide, self.moving, self.q_other, self.X_WO = collide, moving, q_other, X_WO
        self.margin = margin
        self.calls = 0
        self.states = 0
        self.reasons: Counter = Counter()

    def __call__(self, Q: np.ndarray, ball_exempt: np.ndarray | bool = False) -> tuple[np.ndarray, np.ndarray]:
        Q = np.atleast_2d(np.asarray(Q, dtype=float))
        N = len(Q)
        if N == 0:
            return np.ones(0, bool), np.zeros(0, dtype=str)
        other = np.broadcast_to(self.q_other, Q.shape)
        q_left, q_right = (Q, other) if self.moving == 0 else (other, Q)
        touching = np.ones((N, 2), bool)  # the still arm's ball is always exempt (module docstring)
        touching[:, self.moving] = np.broadcast_to(ball_exempt, (N,))
        X = None if self.X_WO is None else np.broadcast_to(self.X_WO, (N, 4, 4))
        ok, reason = (self.collide(q_left, q_right, X, touching) if self.margin is None else
                      self.collide(q_left, q_right, X, touching, object_margin=self.margin))
        self.calls += 1
        self.states += N
        self.reasons.update(reason[~ok].tolist())
        return ok, reason


def _fail(status: str, reason: str, n: int, stats: dict) -> TransitResult:
    return TransitResult(status=status, path=np.zeros((0, n)), reason=reason, stats=stats)


def _leave_contacts(robot, arm: str, qs: list, normals: list, params: Params) -> list:
    """Per end ``(q (n,), n_W (3,) | None)``: the waypoints ``(retreat_steps + 1, n)`` from ``q`` backing
    the ball off along ``n_W`` by ``params.retreat`` (first row ``q``; just ``q[None]`` when ``n_W`` is
    None), or a string saying why the IK failed. One batched IK call for all ends."""
    out: list = [q[None] for q in qs]
    idx = [i for i, nw in enumerate(normals) if nw is not None]
    if not idx:
        return out
    u = []
    for i in idx:
        nw = np.asarray(normals[i], dtype=float).reshape(3)
        norm = np.linalg.norm(nw)
        if not np.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"contact normal must be a non-zero (3,) vector, got {nw}")
        u.append(nw / norm)
    q0 = np.stack([qs[i] for i in idx])
    p0 = robot.eef_position(arm, q0)  # (E, 3)
    u = np.array(u)
    todo = np.arange(len(idx))
    for steps in (params.retreat_steps, params.retreat_steps * params.retreat_refine):
        s = params.retreat * np.arange(1, steps + 1) / steps  # (T,)
        res = robot.ik_trajectory(arm, p0[todo][None] + s[:, None, None] * u[todo][None], q0[todo])  # (T, E', ...)
        jumped = []
        for j, e in enumerate(todo.tolist()):
            good = res.ok[:, j]
            if good.all():
                out[idx[e]] = np.concatenate([q0[e][None], res.q[:, j]])
                continue
            k = int(np.argmin(good))
            out[idx[e]] = (f"{res.reason[k, j]} at {s[k] * 100:.1f} cm off the contact "
                           f"(error {res.err[k, j] * 1000:.1f} mm)")
            if res.reason[k, j] == "joint_jump":
                jumped.append(e)
        todo = np.array(jumped, dtype=np.int64)
        if not len(todo) or params.retreat_refine <= 1:
            break
    return out


def _inputs(a, q_start, q_goal, q_other, X_WO):
    """:func:`plan_transit`'s inputs checked: finite ``(n,)`` joint vectors of arm ``a``, the start and
    goal within its limits (to 1e-9 rad, then clipped), ``X_WO`` (4, 4) or None; ``ValueError`` else."""
    n, vecs = a.dof, {}
    for name, v in (("q_start", q_start), ("q_goal", q_goal), ("q_other", q_other)):
        v = np.asarray(v, dtype=float)
        if v.shape != (n,) or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite ({n},) joint vector, got shape {v.shape}")
        vecs[name] = v
    qs, qg, qo = vecs["q_start"], vecs["q_goal"], vecs["q_other"]
    for name, v in (("q_start", qs), ("q_goal", qg)):
        if np.any(v < a.lower - 1e-9) or np.any(v > a.upper + 1e-9):
            raise ValueError(f"{name} is outside the joint limits of the {a.name} arm")
    qs, qg = np.clip(qs, a.lower, a.upper), np.clip(qg, a.lower, a.upper)
    if X_WO is not None:
        X_WO = np.asarray(X_WO, dtype=float)
        if X_WO.shape != (4, 4):
            raise ValueError(f"X_WO must be (4, 4), got {X_WO.shape}")
    return qs, qg, qo, X_WO


def _middle(check, wide, a, w, q_from, q_to, d_states, params: Params, stats: dict):
    """The joint path ``(K, n)`` from the retreat's end ``q_from`` to the approach's start ``q_to``
    (:func:`plan_transit`'s step 2): the straight segment ``d_states`` when it passes (with the
    clearance ``wide`` checks where both ends keep it), else OMPL's RRT-Connect (then shortcut); or
    ``(status, reason)`` when none is found. Records the planner used in ``stats``."""
    way = wide(np.concatenate([d_states, q_to[None]]))[0] if params.clearance > 0 else None  # q_from ... q_to
    mid = wide if way is not None and way[0] and way[-1] else check
    direct = way.all() if mid is wide else check(d_states)[0].all()
    if direct:
        stats["planner"] = "direct"
        return np.stack([q_from, q_to])
    stats["planner"] = "rrt_connect"
    middle, info = _rrt_connect(mid, a.lower, a.upper, w, q_from, q_to, params)
    stats.update(info)
    if middle is None:
        common = ", ".join(f"{k} ({v})" for k, v in mid.reasons.most_common(3))
        return ("no_transit_path", f"RRT-Connect found no path in {info['iterations']} iterations "
                f"({info['stop']}); most frequent collisions: {common}")
    if params.simplify:
        middle = shortcut(middle, mid, w, params.resolution)
    states, seg = densify(middle, w, params.resolution)
    ok, reason = mid(states)
    if not ok.all():  # cannot happen with the same checker and resolution; kept as a guard
        k = int(np.argmin(ok))
        return ("no_transit_path", f"dense re-check failed on segment {seg[k]}: {reason[k]}")
    return middle


def plan_transit(robot, collide, arm: str, q_start, q_goal, q_other, X_WO, params: Params = Params(),
                 n_start=None, n_goal=None) -> TransitResult:
    """Collision-free joint path of ``arm`` from ``q_start`` to ``q_goal`` with the other arm still.

    Parameters
    ----------
    robot : ``stages.robot.Robot``.
    collide : its batched collision checker (``make_collision_fn`` or ``make_scene_collision_fn``).
    arm : ``"left"`` or ``"right"``, the arm that moves.
    q_start, q_goal : (n,) rad, the moving arm's configurations at the old and the new contact.
    q_other : (n,) rad, the still arm.
    X_WO : (4, 4) object pose in W, fixed during the transit (None: no object).
    params : ``Params``.
    n_start, n_goal : (3,) outward contact normals (W) at the start and goal contacts; the ball backs
        off along them (module docstring). None: that end is not in contact, so it is tested in full
        and has no retreat.

    Returns
    -------
    ``TransitResult``; ``status`` ``"start_in_collision"`` / ``"goal_in_collision"`` also when the
    retreat / approach segment collides, ``"ik_unreachable"`` when its IK fails, ``"no_transit_path"``
    when RRT-Connect finds no path within its iterations.
    """
    t0 = time.perf_counter()
    a = robot.arm(arm)
    n = a.dof
    qs, qg, qo, X_WO = _inputs(a, q_start, q_goal, q_other, X_WO)
    check = _Checker(collide, ("left", "right").index(arm), qo, X_WO)
    wide = _Checker(collide, ("left", "right").index(arm), qo, X_WO, params.clearance)
    w = lever_arms(a)
    stats = {"planner": "", "iterations": 0}

    def done(**extra):
        stats.update(checks=check.calls + wide.calls, states=check.states + wide.states,
                     time=time.perf_counter() - t0, **extra)
        return stats

    # Retreat and approach by IK.
    R, A = _leave_contacts(robot, arm, [qs, qg], [n_start, n_goal], params)
    if isinstance(R, str):
        return _fail("ik_unreachable", f"retreat from the start contact: {R}", n, done())
    if isinstance(A, str):
        return _fail("ik_unreachable", f"approach to the goal contact: {A}", n, done())
    A = A[::-1]

    # One batched call: both ends and the retreat and approach segments. The balls are exempt at the
    # contact ends and inside the retreat/approach segments; the retreat and approach configurations
    # themselves (R[-1], A[0]) are tested in full. Then the direct segment between them, with its ends,
    # with the clearance (without it when an end does not keep the clearance).
    r_states = densify(R, w, params.resolution)[0]
    a_states = densify(A, w, params.resolution)[0][:-1]  # its last state is q_goal, tested below
    d_states = densify(np.stack([R[-1], A[0]]), w, params.resolution)[0][:-1]  # ... and A[0]
    blocks = [  # (states, ball exempt, status, what)
        (qs[None], np.array([n_start is not None]), "start_in_collision", "start configuration"),
        (r_states, np.arange(len(r_states)) < len(r_states) - 1, "start_in_collision",
         "retreat from the start contact"),
        (qg[None], np.array([n_goal is not None]), "goal_in_collision", "goal configuration"),
        (A[:1] if len(A) > 1 else A[:0], np.zeros(min(len(A) - 1, 1), bool), "goal_in_collision",
         "approach to the goal contact"),
        (a_states, np.ones(len(a_states), bool), "goal_in_collision", "approach to the goal contact"),
    ]
    ok, reason = check(np.concatenate([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks]))
    ends = np.cumsum([len(b[0]) for b in blocks])
    for (states, _, status, what), e in zip(blocks, ends, strict=True):
        bad = np.flatnonzero(~ok[e - len(states): e])
        if len(bad):
            return _fail(status, f"{what}: {reason[e - len(states) + bad[0]]}", n, done())

    middle = _middle(check, wide, a, w, R[-1], A[0], d_states, params, stats)
    if isinstance(middle, tuple):
        return _fail(*middle, n, done())
    path = np.concatenate([R, middle[1:-1], A])
    return TransitResult(status="ok", path=path, reason="ok", n_retreat=len(R) - 1, n_approach=len(A) - 1,
                         stats=done())


def shortcut(path: np.ndarray, check, weights: np.ndarray, step: float, coarse: int = 4) -> np.ndarray:
    """Greedy shortcutting of ``path (K, n)``: from each kept waypoint, jump to the farthest later
    waypoint joined to it by a free straight segment.

    From waypoint i, every candidate segment ``i -> j`` (j > i + 1) is first checked at ``coarse``
    times the step in one call; then the farthest survivors are checked at the full step, one call
    each, until one is free (``i -> i + 1`` is a checked edge of the input). ``check(Q) -> (ok,
    reason)`` tests states in full. Deterministic; the result keeps a subset of the waypoints in order,
    and each of its segments has been checked at ``step``.
    """
    path = np.asarray(path, dtype=float)
    out = [path[0]]
    i, K = 0, len(path)
    while i < K - 1:
        nxt = i + 1
        js = list(range(K - 1, i + 1, -1))  # farthest first
        if js:
            segs = [densify(np.stack([path[i], path[j]]), weights, step * coarse)[0] for j in js]
            ok, _ = check(np.concatenate(segs))
            ends = np.cumsum([len(x) for x in segs])
            for j, x, e in zip(js, segs, ends, strict=True):
                if ok[e - len(x): e].all():
                    fine = densify(np.stack([path[i], path[j]]), weights, step)[0]
                    if check(fine)[0].all():
                        nxt = j
                        break
        out.append(path[nxt])
        i = nxt
    return np.array(out)


_MV_CLASS = None


def _motion_validator_class():
    """An ``ompl.base.MotionValidator`` that checks a whole segment with one batched call (made once,
    after importing OMPL)."""
    global _MV_CLASS
    if _MV_CLASS is None:
        import ompl.base as ob

        class BatchedMotionValidator(ob.MotionValidator):
            def __init__(self, si, n, test):
                super().__init__(si)
                self.n, self.test = n, test

            def checkMotion(self, s1, s2):  # noqa: N802 (OMPL's name)
                return self.test(np.array(s1[0: self.n]), np.array(s2[0: self.n]))

        _MV_CLASS = BatchedMotionValidator
    return _MV_CLASS


def _rrt_connect(check: _Checker, lower, upper, weights, qa, qb, params: Params):
    """OMPL RRT-Connect from ``qa`` to ``qb`` (both free). Returns ``(path (K, n) | None, info)``."""
    import ompl.base as ob
    import ompl.geometric as og
    import ompl.util as ou

    n = len(qa)
    level = ou.getLogLevel()
    # Silence OMPL: setSeed logs an error on every call after the first (the reseeding works: same seed,
    # same path), and the planner logs two info lines a query.
    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    try:
        ou.RNG.setSeed(int(params.seed) % 2_000_000_000 + 1)  # OMPL refuses seed 0
        space = ob.RealVectorStateSpace(n)
        bounds = ob.RealVectorBounds(n)
        for j in range(n):
            bounds.setLow(j, float(lower[j]))
            bounds.setHigh(j, float(upper[j]))
        space.setBounds(bounds)
        si = ob.SpaceInformation(space)
        # Every tree edge of RRT-Connect passes the motion validator, which checks both of its ends
        # (known-free states cached) and the states between in one batched call; the state validity
        # checker therefore only enforces the bounds, saving one checker call per goal-tree extension.
        free: set[bytes] = {np.asarray(qa, dtype=float).tobytes(), np.asarray(qb, dtype=float).tobytes()}

        def motion_ok(q1: np.ndarray, q2: np.ndarray) -> bool:
            states, _ = densify(np.stack([q1, q2]), weights, params.resolution)
            if q1.tobytes() not in free:
                states = np.concatenate([q1[None], states])
            if q2.tobytes() in free:
                states = states[:-1]
            if len(states) and not check(states)[0].all():
                return False
            free.update((q1.tobytes(), q2.tobytes()))
            return True

        lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)

        def in_bounds(s) -> bool:
            q = np.array(s[0:n])
            return bool(np.all(q >= lo) and np.all(q <= hi))

        si.setStateValidityChecker(in_bounds)
        si.setMotionValidator(_motion_validator_class()(si, n, motion_ok))
        si.setup()
        pdef = ob.ProblemDefinition(si)
        start, goal = space.allocState(), space.allocState()
        for j in range(n):
            start[j], goal[j] = float(qa[j]), float(qb[j])
        pdef.setStartAndGoalStates(start, goal)
        planner = og.RRTConnect(si)
        planner.setRange(params.range)
        planner.setProblemDefinition(pdef)
        planner.setup()
        count = [0]
        t_end = time.perf_counter() + params.time_limit
        stop = [""]

        def terminate() -> bool:
            count[0] += 1
            if count[0] > params.max_iterations:
                stop[0] = "iteration limit"
                return True
            if time.perf_counter() > t_end:
                stop[0] = f"time limit {params.time_limit} s"
                return True
            return False

        planner.solve(ob.PlannerTerminationCondition(terminate))
        info = {"iterations": min(count[0], params.max_iterations), "stop": stop[0] or "solved"}
        if not pdef.hasExactSolution():
            return None, info
        p = pdef.getSolutionPath()
        path = np.array([p.getState(i)[0:n] for i in range(p.getStateCount())])
        return path, info
    finally:
        ou.setLogLevel(level)


def time_parameterize(path, v_max, a_max, dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-time trajectory along ``path (K, n)`` stopping at every waypoint, sampled every ``dt`` s.

    Each straight segment ``q_i -> q_i+1`` is traversed as ``q_i + s(t) (q_i+1 - q_i)`` with a trapezoidal
    (or, when short, triangular) profile of ``s``: the fastest one for which every joint keeps
    ``|dq_j/dt| <= v_max_j`` and ``|d2q_j/dt2| <= a_max_j``. Its duration is then rounded up to a whole
    number of periods (the profile is slowed uniformly, which keeps both limits), so that the samples
    fall on every waypoint.

    Parameters
    ----------
    path : (K, n) rad waypoints.
    v_max : (n,) or scalar rad/s.
    a_max : (n,) or scalar rad/s^2.
    dt : s sampling period.

    Returns
    -------
    t : (M,) s from 0, step ``dt``; q : (M, n) rad, ``q[0] = path[0]``, ``q[-1] = path[-1]``, zero velocity
    at both ends (and at every waypoint).
    """
    path = np.asarray(path, dtype=float)
    if path.ndim != 2 or len(path) == 0:
        raise ValueError(f"path must be (K, n) with K >= 1, got {path.shape}")
    n = path.shape[1]
    v = np.broadcast_to(np.asarray(v_max, dtype=float), (n,))
    acc = np.broadcast_to(np.asarray(a_max, dtype=float), (n,))
    if not (np.all(v > 0) and np.all(acc > 0) and dt > 0):
        raise ValueError("v_max, a_max and dt must be positive")
    t_out, q_out = [np.zeros(1)], [path[:1]]
    t0 = 0.0
    for q0, q1 in zip(path[:-1], path[1:], strict=True):
        d = np.abs(q1 - q0)
        if not d.any():
            continue
        # Limits on s' and s'' from every joint moving d_j: s' <= v_j / d_j, s'' <= a_j / d_j.
        sd = float(np.min(v[d > 0] / d[d > 0]))
        sdd = float(np.min(acc[d > 0] / d[d > 0]))
        if sd * sd / sdd >= 1.0:  # triangle: accelerate over half the segment, decelerate over the other
            ta = math.sqrt(1.0 / sdd)
            T = 2 * ta
        else:
            ta = sd / sdd
            T = 1.0 / sd + ta
        m = int(math.ceil(T / dt - 1e-9))
        k = T / (m * dt)  # <= 1: slow the profile uniformly to last m periods
        tau = np.arange(1, m + 1) * dt * k  # profile time of each sample
        s = _trapezoid(tau, T, ta, sd if sd * sd / sdd < 1.0 else sdd * ta, sdd)
        s[-1] = 1.0
        t_out.append(t0 + np.arange(1, m + 1) * dt)
        seg = q0 + s[:, None] * (q1 - q0)
        seg[-1] = q1  # the waypoint itself, not up to rounding
        q_out.append(seg)
        t0 += m * dt
    return np.concatenate(t_out), np.concatenate(q_out)


def _trapezoid(tau: np.ndarray, T: float, ta: float, v: float, a: float) -> np.ndarray:
    """Position ``s(tau)`` in [0, 1] of a profile accelerating at ``a`` for ``ta``, cruising at ``v`` and
    decelerating for ``ta``, of total duration ``T``."""
    up = 0.5 * a * tau ** 2
    cruise = 0.5 * a * ta ** 2 + v * (tau - ta)
    down = 1.0 - 0.5 * a * (T - tau) ** 2
    return np.where(tau < ta, up, np.where(tau <= T - ta, cruise, down))
