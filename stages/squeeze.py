"""The squeeze tumble: both balls keep their grasp's contacts and roll the object over a support edge.

§5.2.2 tumbles with one ball pushing and the other catching (Fig. 14); where no pusher or no catcher
works (the object tips away from the robot, or the landing face lies out of reach) the grasp that
pivoted the object can often roll it itself: the two balls squeeze it from both sides, as in a
pivot, and turn it about the support edge (:func:`stages.poses.roll_segments`: over successive hull
edges onto the next stable face) all the way to the landing, carrying its weight past the tip.
The object then lands on its new face with the same grasp, which is a grasp node of the landing
pose: pivots follow without a regrasp.

What it needs, checked by ``stages.graph`` (necessary) and ``stages.plan`` (along the motion the
trajectory stage follows):

- **statics** (:func:`squeeze_holds`): at sampled angles of the roll (:func:`sample_angles`, every
  segment's end included, where the gravity torque about the edge is largest past the tip), the
  object on its support edge with both balls is in equilibrium within the friction cones and the
  force bound (the stability LP of §4.3, eq. 1-4, with the table contact reduced to the edge's two
  vertices);
- **kinematics**: IK of both balls along the roll, no collision, the tool axes turning against the
  contact normals within §5.1's bound (``stages.graph.check_arm_motion``);
- **dynamics**: the tumbling MPC (``stages.mpc.run_tumble_mpc``, eq. 5-11 about an edge) with both
  balls on for the whole roll, one run per roll segment, along :func:`squeeze_profile`.

Both the statics and the MPC use ``SqueezeParams.friction`` of the scene's frictions (:func:`mpc_params`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from stages import mpc, se3, stability
from stages.poses import Roll, roll_segments


@dataclass(frozen=True)
class SqueezeParams:
    """Timing (s, s/rad) and checks of a squeeze tumble."""

    #: Both balls press at the start pose this long before the roll (the contacts ramp in).
    grip_time: float = 0.6
    #: Each roll segment takes ``time_per_rad`` per radian, at least ``min_segment_time``, minimum
    #: jerk, at rest at every axis switch (a 90 deg roll: 5.5 s, as a pivot's rotation).
    time_per_rad: float = 3.5
    min_segment_time: float = 1.0
    #: Angles at which the statics are checked, evenly inside the roll (plus every segment's end).
    samples: int = 9
    #: The share of the object's (ball) and the table's friction the statics and the MPC may use:
    #: below the pivots' 0.8, because physics perturbs friction by up to 20 % and a squeeze leans on
    #: both frictions to the end of the roll (with 0.8, the box of the benchmark's box-05 slid 7 cm on
    #: the table and tipped 13 deg in two perturbed runs of three).
    friction: float = 0.65
    #: Each ball presses at least this hard (N, normal) throughout: the MPC minimises the forces, and
    #: near the tip, where the object needs next to none, balls pressing 2 N let a cabinet slide
    #: 7 cm on its edge as it went over.
    min_force: float = 10.0


def recorded(params: dict) -> SqueezeParams:
    """The squeeze parameters recorded in an artifact's ``params`` (the graph's, or a plan step's
    ``squeeze``), so that the plan and the trajectory stage use what the graph checked."""
    return SqueezeParams(**params)


class SqueezeMotion(NamedTuple):
    """A squeeze tumble's reference: the roll, times ``t (T,)`` (s), angles ``theta (T,)`` (rad) and
    object poses ``X_ref (T, 4, 4)`` (W)."""

    roll: Roll
    t: np.ndarray
    theta: np.ndarray
    X_ref: np.ndarray


def squeeze_profile(roll: Roll, P: SqueezeParams, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(t, theta)`` every ``dt`` s: a pause of ``grip_time`` at 0, then each segment of the roll by
    a minimum-jerk move (``stages.mpc.knot_profile``), at rest at every axis switch and at the end."""
    knots = np.r_[roll.switches, roll.total]
    durations = np.maximum(roll.angle * P.time_per_rad, P.min_segment_time)
    return mpc.knot_profile([0.0, 0.0, *knots], [P.grip_time, *durations], dt)


def squeeze_motion(model, X_WO: np.ndarray, edge: tuple[int, int], P: SqueezeParams, dt: float) -> SqueezeMotion:
    """The roll from ``X_WO`` over hull edge ``edge`` (``stages.poses.roll_segments``; raises its
    ``InputError`` when that is no roll) sampled along :func:`squeeze_profile`."""
    roll = roll_segments(model, X_WO, int(edge[0]), int(edge[1]))
    t, theta = squeeze_profile(roll, P, dt)
    return SqueezeMotion(roll, t, theta, roll.poses(theta))


def mpc_params(mp: mpc.Params, P: SqueezeParams, mu_object: float, mu_table: float, f_max: float) -> mpc.Params:
    """The MPC settings ``mp`` of a squeeze: ``P.friction`` of the object's and the table's friction,
    each ball's normal force between ``P.min_force`` and ``f_max`` (N)."""
    return replace(mp, mu_eef=P.friction * mu_object, mu_table=P.friction * mu_table, f_max=f_max,
                   f_min=min(P.min_force, f_max))


def sample_angles(roll: Roll, n: int) -> np.ndarray:
    """Roll angles (rad) where the statics are checked: ``n`` evenly inside ``(0, total)`` and 1 mrad
    before every segment's end (the object still on that segment's edge alone), sorted."""
    inside = np.linspace(0.0, roll.total, n + 2)[1:-1]
    ends = np.cumsum(roll.angle) - 1e-3
    return np.unique(np.r_[inside, ends[ends > 0]])


def edge_points(model, roll: Roll, theta: np.ndarray) -> np.ndarray:
    """The support edge's two vertices ``(A, 2, 3)`` (W) at roll angles ``theta (A,)``."""
    seg = np.array([roll.segment_of(th) for th in theta], dtype=np.int64)
    return se3.transform_points(roll.poses(theta)[:, None], model.vertices[roll.edge[seg]])


def squeeze_holds(mass: float, com_O: np.ndarray, X: np.ndarray, edge_W: np.ndarray, p_O: np.ndarray,
                  n_O: np.ndarray, L: float, params: stability.Params, threads: int = 1) -> np.ndarray:
    """``(N,)`` bool: whether two balls hold the object in equilibrium on its support edge.

    ``X (N, 4, 4)`` object poses (W), ``edge_W (N, 2, 3)`` the support edge's vertices (W, the table
    contacts), ``p_O, n_O (N, 2, 3)`` the balls' contact points and outward normals (O), ``com_O``
    the centre of mass (O), ``L`` (m) the torque scale; the stability LP of §4.3 (eq. 1-4,
    ``stability.evaluate``) with ``params``' friction and force bound; ``threads`` share the LPs (the
    same answer for any number)."""
    if len(X) == 0:
        return np.zeros(0, bool)
    res = stability.evaluate_threaded(mass, se3.transform_points(X, com_O), edge_W, None,
                                      se3.transform_points(X[:, None], p_O), -se3.rotate_vectors(X[:, None], n_O),
                                      None, L, params, compute_margin=False, threads=threads)
    return np.asarray(res.stable, bool)
