"""Model-predictive control of pivoting and tumbling (§5.2, eq. 5–11, Fig. 12–14).

The object rotates about a fixed support on the table: one vertex ``p0`` (pivoting, eq. 5) or an
edge, the line through two of its vertices (tumbling, §5.2.2). Two ball end-effectors (EEFs) push
on it; the table supplies the rest of the wrench. Arrays are float64 in SI units; poses are
``(..., 4, 4)`` homogeneous transforms (``stages.se3``), names in monogram notation.

Model (eq. 7–10)
----------------
Reduced coordinates ``omega_W = P nu``: ``P = I_3`` about a vertex (3 DOF), ``P = a_W`` (the unit
edge direction, 1 DOF) about an edge. The state is ``x = [eps, nu]`` with
``eps = P^T log(R_WO R_WO_ref^T)``, the rotation error about the reference as a world-frame
rotation vector, in place of the paper's Euler angles: no gimbal singularity, zero on the
reference, and ``eps' = nu - nu_ref + P^T [omega_ref] P eps`` to first order, so the paper's
``W`` becomes the identity plus a coupling term the discretisation keeps. The rotational dynamics
about the support point ``A`` (eq. 7, parallel-axis inertia ``I_A = R I_com R^T + m([r]^T[r])``)
are linearised along the reference (poses, angular velocity) and, at every MPC step, about the
forces of the previous plan for the bilinear lever-arm terms; the current state enters through
``x0``. The step is the paper's constant-acceleration step (the ``T^2/2`` terms of eq. 9–10)
plus the torque's rate over the step (``T^3/6``), see :func:`linearize_rotation`.

Input. ``u = [f1_O, f2_O]``: each EEF's contact force on the object, held constant *in the object
frame* over a step (zero-order hold) and reported in W as well. The paper writes the forces in W;
holding them in O is what a contact-force controller whose ball turns with the object does
(notes: "the ball turns with the object"), it keeps the friction pyramids constant, and it removes
a modelling artefact: a force frozen in W while the object yaws at 0.4 rad/s turns its lever arm
enough to change the acceleration by ~0.5 rad/s^2 per 20 ms step.

Optimisation (eq. 11)
---------------------
``sum_j alpha/2 |eps_j|^2 + alpha_rate/2 |nu_j - nu_ref_j|^2 + beta/2 |u_j|^2`` over the horizon
``N_p`` (``alpha_rate = alpha`` is the paper's single weight), condensed onto the inputs. The
forces are interpolated linearly between knots every ``Params.block`` steps (move blocking: 6
knots give a dense QP of 36 unknowns instead of 120; ``block = 1`` is the paper's full
parametrisation). Piecewise-*constant* blocks would be cheaper still but lag a ramping force
need by ~2 mrad; the knot at stage 0 is the force applied now. Constraints:

- each EEF force inside its contact's six-sided inscribed friction pyramid
  (:func:`friction_pyramid_halfspaces`, normal = the inward surface normal, rows fixed in O) with
  ``f_min <= n . f <= f_max``, at every knot a touching stage uses (linear in O, so the forces
  between two feasible knots are feasible; an EEF out of contact has no constraint, no effect);
- the table reaction from the Newton–Euler balance ``f0 = m a_com - m g - f1 - f2`` inside the
  table's pyramid (normal +z; its rows imply ``f0_z >= 0``), so the support neither slips nor
  lifts, at each knot. At knot 0 it is exact at the current state (:func:`support_reactions`,
  affine in the forces), so the force applied satisfies every constraint exactly; at later knots
  ``a_com`` is the prediction's (affine in the unknowns), which equals the reference's when
  tracking is exact. About an edge the reaction is split between its two end vertices: the
  moment balance fixes the components across the edge, one unknown per knot the (statically
  indeterminate) component along it, and each vertex's force must lie in the pyramid;
- ``|eps_i| <= max_error`` after each knot interval. With ``max_error`` below the smallest tilt
  the planner uses (notes: 5–12 deg) the other support points stay off the table; it is also what
  makes a pivot infeasible when the EEFs cannot hold the gravity torque (the object would fall).

The QP is solved by piqp's dense interface, centred on the previous plan (an interior-point
method takes no primal warm start; centring keeps the numbers small). A failed solve is data
(``status = "mpc_infeasible"`` with ``fail_step``), not an exception. The applied first input is
integrated through the nonlinear rotational dynamics (RK4 on the rotation group), not through the
linear model. Solve times live in :class:`MPCTimings`, apart from the deterministic arrays, and
must not go into artifacts.

Pyramid convention: six sides, inscribed (edge rays on the cone), tangents as
``stages.stability.contact_frames`` (:func:`tangent_basis`), so the MPC and the stability check
agree on which forces are allowed. The frames are taken at the primitive's first reference pose:
the EEF pyramids then stay fixed in O (they turn with the object), the table's in W.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import numpy as np
import piqp
from scipy.spatial.transform import Rotation

from stages import se3, stability
from stages.errors import InputError

#: Statuses of an MPC run.
STATUS_OK = "ok"
STATUS_INFEASIBLE = "mpc_infeasible"

#: Number of sides of the inscribed friction pyramids (§4.3).
PYRAMID_SIDES = 6

#: A reference must keep its support point(s) fixed to within this distance (m).
SUPPORT_TOL = 1e-6

_Z = np.array([0.0, 0.0, 1.0])


def _cross(a, b) -> np.ndarray:
    """``a x b`` over the last axis, broadcasting (np.cross is slow on tiny arrays)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape == (3,) and b.shape == (3,):
        a0, a1, a2 = a.tolist()
        b0, b1, b2 = b.tolist()
        return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


@dataclass(frozen=True)
class Params:
    """MPC parameters (SI units).

    dt : control and prediction step (s); the reference must be sampled at this step.
    horizon : prediction horizon ``N_p`` (steps).
    block : steps between the knots of the piecewise-linear force input; 1 = a force per step.
    alpha : weight on the rotation error (1/rad^2), eq. 11. The force cost biases the error by
        about ``beta F dF/d eps / alpha`` (~1e-4 rad at 1e7 with ~15 N and ~100 N/rad).
    alpha_rate : weight on the angular-velocity error (s^2/rad^2); eq. 11 uses ``alpha`` for both,
        which with these units over-damps (the rate error is ~eps / 0.1 s).
    beta : weight on the EEF forces (1/N^2), eq. 11.
    mu_eef, mu_table : friction coefficients of the ball contacts and of the table.
    f_max : upper bound on each EEF's normal force (N); the SDA5F arm carries 5 kg.
    f_min : lower bound on a touching EEF's normal force (N): the squeeze that keeps contact.
    g : gravity (m/s^2), along -z of W.
    max_error : bound on each component of the predicted rotation error (rad).
    max_iter : piqp iteration limit.
    """

    dt: float = 0.02
    horizon: int = 20
    block: int = 4
    alpha: float = 1e7
    alpha_rate: float = 1e4
    beta: float = 1.0
    mu_eef: float = 0.5
    mu_table: float = 0.5
    f_max: float = 50.0
    f_min: float = 2.0
    g: float = 9.81
    max_error: float = 0.05
    max_iter: int = 100


# --------------------------------------------------------------------------------------------
# References
# --------------------------------------------------------------------------------------------


def min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk profile ``10 s^3 - 15 s^4 + 6 s^5`` of ``s (...)`` clipped to [0, 1]."""
    s = np.clip(np.asarray(s, dtype=float), 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _phase_progress(t: np.ndarray, start: float, duration: float) -> np.ndarray:
    if duration <= 0.0:
        return (t >= start).astype(float)
    return min_jerk((t - start) / duration)


def _sample_times(total: float, dt: float) -> np.ndarray:
    """Uniform samples from 0 covering ``total`` (the last one at or just past it, at rest)."""
    if not (dt > 0.0 and np.isfinite(total) and total > 0.0):
        raise InputError(f"reference: need dt > 0 and a positive duration, got dt={dt}, duration={total}")
    return np.arange(int(np.ceil(total / dt - 1e-9)) + 1) * dt


def _as_pose(X, name: str) -> np.ndarray:
    X = np.asarray(X, dtype=float)
    if X.shape != (4, 4):
        raise InputError(f"{name}: expected a (4, 4) pose, got shape {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InputError(f"{name}: the (4, 4) pose has non-finite entries")
    return X


def pivot_reference(X_WO_start, X_WO_goal, p0_W, tilt: float, dt: float, durations, p_com_O=None, tilt_dir=None):
    """Tilt–rotate–lower reference for one pivoting step (§5.2.1, Fig. 12).

    The goal must differ from the start by a rotation about the vertical through the table vertex
    ``p0_W``. The object is tilted by ``tilt`` about the horizontal axis through ``p0_W``
    perpendicular to the horizontal direction ``d`` from ``p0_W`` to the CoM, in the sense that
    raises the CoM side (axis ``d x z``, positive angle): every other support point ``q`` with
    ``(q - p0) . d > 0`` rises by ``sin(tilt) (q - p0) . d``, which for a vertex of a convex base
    whose CoM projects inside it is every other vertex of a box-like base; where a wide angle or a
    curved rim at ``p0`` would keep a vertex behind ``p0`` down, ``tilt_dir`` replaces ``d``.
    The object then yaws about the vertical through ``p0_W`` by the start-to-goal angle (in
    (-pi, pi]; physics wants <= 30 deg per step) and is lowered by the reverse tilt about the
    yawed axis. Each phase follows a minimum-jerk profile, so velocity and acceleration are zero
    at phase boundaries. Samples are uniform; when the total duration is not a multiple of
    ``dt`` the last sample falls just past it, at the goal.

    Parameters
    ----------
    X_WO_start, X_WO_goal : (4, 4) float
        Start and goal poses of the object, resting on the table.
    p0_W : (3,) float
        The shared table vertex (m, W).
    tilt : float
        Tilt angle (rad); the notes' working range is 5–12 deg.
    dt : float
        Sample step (s).
    durations : (3,) float
        Durations of the tilt, rotate and lower phases (s); rotate may be 0.
    p_com_O : (3,) float, optional
        CoM in the object frame (m, O); the origin of O when omitted.
    tilt_dir : (3,) float, optional
        The horizontal unit direction ``d`` that rises (W), when not the CoM's: a corner whose
        neighbours would sink into the table at the CoM's (``stages.poses.tilt_direction``).

    Returns
    -------
    t : (T,) float
        Sample times (s), step ``dt``.
    X_WO_ref : (T, 4, 4) float
        Reference poses.
    phase : (T,) str
        ``"tilt"``, ``"rotate"`` or ``"lower"`` per sample.
    """
    X_s = _as_pose(X_WO_start, "pivot_reference X_WO_start")
    p0_W = np.asarray(p0_W, dtype=float).reshape(3)
    durations = np.asarray(durations, dtype=float).reshape(3)
    if durations[0] <= 0.0 or durations[2] <= 0.0 or durations[1] < 0.0:
        raise InputError(f"pivot_reference: durations must be tilt > 0, rotate >= 0, lower > 0: {durations}")
    yaw, tilt_axis = pivot_axes(X_s, X_WO_goal, p0_W, p_com_O, tilt_dir)
    t = _sample_times(float(durations.sum()), dt)
    t1, t2, t3 = durations
    s_tilt = _phase_progress(t, 0.0, t1)
    s_yaw = _phase_progress(t, t1, t2)
    s_lower = _phase_progress(t, t1 + t2, t3)
    X_yaw = se3.transform_about_line(p0_W, _Z, yaw * s_yaw)
    X_tilt = se3.transform_about_line(p0_W, tilt_axis, tilt * (s_tilt - s_lower))
    X_WO_ref = X_yaw @ X_tilt @ X_s
    phase = np.where(t < t1, "tilt", np.where(t < t1 + t2, "rotate", "lower"))
    return t, X_WO_ref, phase


def pivot_axes(X_WO_start, X_WO_goal, p0_W, p_com_O=None, tilt_dir=None) -> tuple[float, np.ndarray]:
    """The yaw (rad) and the tilt axis (W, unit) of :func:`pivot_reference`'s pivot from ``X_WO_start``
    to ``X_WO_goal`` about the vertical through ``p0_W`` (§5.2.1, Fig. 12); ``InputError`` when the goal
    is not such a rotation of the start, or the tilt direction is undefined (arguments as there)."""
    X_s = _as_pose(X_WO_start, "pivot_reference X_WO_start")
    X_g = _as_pose(X_WO_goal, "pivot_reference X_WO_goal")
    p0_W = np.asarray(p0_W, dtype=float).reshape(3)
    p_com_O = np.zeros(3) if p_com_O is None else np.asarray(p_com_O, dtype=float).reshape(3)
    R_rel = X_g[:3, :3] @ X_s[:3, :3].T
    yaw = float(np.arctan2(R_rel[1, 0], R_rel[0, 0]))
    X_goal_expected = se3.transform_about_line(p0_W, _Z, yaw) @ X_s
    if np.abs(X_goal_expected[:3, :3] - X_g[:3, :3]).max() > 1e-6 or \
            np.abs(X_goal_expected[:3, 3] - X_g[:3, 3]).max() > SUPPORT_TOL:
        raise InputError("pivot_reference: the goal is not a rotation of the start about the vertical "
                         f"through p0_W={p0_W.tolist()}")
    d = se3.transform_points(X_s, p_com_O) - p0_W if tilt_dir is None else np.array(tilt_dir, dtype=float)
    d[2] = 0.0
    if np.linalg.norm(d) < 1e-9:
        raise InputError("pivot_reference: the CoM is above p0_W, the tilt direction is undefined")
    return yaw, _cross(d / np.linalg.norm(d), _Z)


def tumble_reference(X_WO_start, axis_point_W, axis_dir_W, angle: float, dt: float, duration: float):
    """Rotation about a table edge (tumbling, §5.2.2) with a minimum-jerk profile.

    Parameters
    ----------
    X_WO_start : (4, 4) float
        Start pose.
    axis_point_W, axis_dir_W : (3,) float
        A point on the edge and its direction (W); the rotation is right-handed about it.
    angle : float
        Total rotation (rad), e.g. pi/2 to land on the adjacent face.
    dt, duration : float
        Sample step and duration (s).

    Returns
    -------
    t : (T,) float
    X_WO_ref : (T, 4, 4) float
    phase : (T,) str, all ``"tumble"``.
    """
    X_s = _as_pose(X_WO_start, "tumble_reference X_WO_start")
    axis = np.asarray(axis_dir_W, dtype=float).reshape(3)
    if not np.linalg.norm(axis) > 1e-12:
        raise InputError("tumble_reference: the axis direction is zero")
    t = _sample_times(float(duration), dt)
    X = se3.transform_about_line(np.asarray(axis_point_W, dtype=float).reshape(3), axis,
                                 angle * min_jerk(t / duration)) @ X_s
    return t, X, np.full(t.shape, "tumble")


def roll_poses(X_WO_seg, p_axis_W, a_axis_W, angles, theta) -> np.ndarray:
    """Poses ``(T, 4, 4)`` along a roll over successive edges (a tumble whose axis switches, §5.2.2).

    A roll is K segments: segment k starts at pose ``X_WO_seg[k]`` and turns by ``angles[k]`` (rad,
    > 0) right-handedly about the line through ``p_axis_W[k]`` along the unit ``a_axis_W[k]`` (W).
    ``theta (T,)`` is the cumulative angle from the start of segment 0, clipped to ``[0, sum(angles)]``;
    a legged body turns about its foot line first and about its body edge once that touches the
    table (notes: "the rotation axis switches from the foot line to the body edge mid-tumble").

    Parameters
    ----------
    X_WO_seg : (K, 4, 4); p_axis_W, a_axis_W : (K, 3); angles : (K,); theta : (T,) rad.
    """
    angles = np.asarray(angles, dtype=float)
    start = np.concatenate([[0.0], np.cumsum(angles)])
    theta = np.clip(np.asarray(theta, dtype=float), 0.0, start[-1])
    k = np.clip(np.searchsorted(start, theta, side="right") - 1, 0, len(angles) - 1)
    X = se3.transform_about_line(np.asarray(p_axis_W)[k], np.asarray(a_axis_W)[k], theta - start[k])
    return X @ np.asarray(X_WO_seg)[k]


def knot_profile(knots, durations, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """A scalar through ``knots (K + 1,)`` with a minimum-jerk move of ``durations (K,)`` s each
    (a duration may be 0 only between equal knots: a pause), at rest at every knot; sampled every ``dt``.

    Returns ``t (T,)`` and the values ``(T,)``; the last sample falls at or just past the end.
    """
    knots = np.asarray(knots, dtype=float)
    durations = np.asarray(durations, dtype=float)
    ends = np.concatenate([[0.0], np.cumsum(durations)])
    t = _sample_times(float(ends[-1]), dt)
    v = np.full(len(t), knots[-1])
    for i in range(len(durations)):  # a handful of pieces
        inside = (t >= ends[i]) & (t < ends[i + 1])
        s = min_jerk((t[inside] - ends[i]) / durations[i]) if durations[i] > 0 else 0.0
        v[inside] = knots[i] + (knots[i + 1] - knots[i]) * s
    return t, v


# --------------------------------------------------------------------------------------------
# Friction pyramids
# --------------------------------------------------------------------------------------------


def tangent_basis(n: np.ndarray, radial=None) -> tuple[np.ndarray, np.ndarray]:
    """Tangents ``t1, t2 (..., 3)`` of the friction pyramids at unit normals ``n (..., 3)`` (W).

    The convention of ``stages.stability.contact_frames``: ``t1 = unit(n x z)`` (horizontal for a
    side contact, ``t2 = n x t1`` then points down); for a normal within 1e-6 of vertical (a table
    contact) ``t1`` is the horizontal part of ``radial (..., 3)``, the contact minus the CoM (the x
    axis when that is zero or not given). Both rules turn with the scene about z.
    """
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return stability.contact_frames(n, np.zeros(n.shape) if radial is None else radial)


def friction_pyramid_rays(n: np.ndarray, mu: float, radial=None) -> np.ndarray:
    """Edge rays ``(..., 6, 3)`` of the six-sided pyramid inscribed in the friction cone (§4.3).

    Ray ``k`` is ``n + mu (cos(k pi/3) t1 + sin(k pi/3) t2)`` (normal component 1) with ``t1, t2``
    from :func:`tangent_basis` (``radial`` as there): the rays lie on the cone, the faces inside.
    ``n`` is the unit normal along which the contact pushes (inward for an EEF on the object, +z
    for the table on the object); it is normalised here. The same edges as ``stages.stability``.
    """
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    t1, t2 = tangent_basis(n, radial)
    ang = np.arange(PYRAMID_SIDES) * (2.0 * np.pi / PYRAMID_SIDES)
    return n[..., None, :] + mu * (np.cos(ang)[:, None] * t1[..., None, :]
                                   + np.sin(ang)[:, None] * t2[..., None, :])


def friction_pyramid_halfspaces(n: np.ndarray, mu: float, radial=None) -> np.ndarray:
    """Rows ``H (..., 6, 3)`` with ``H f <= 0`` exactly when ``f`` is in the inscribed pyramid.

    Face ``k`` lies between rays ``k`` and ``k + 1`` of :func:`friction_pyramid_rays`; its row is
    ``(cos((2k+1) pi/6) t1 + sin((2k+1) pi/6) t2) - mu cos(pi/6) n``. Summing the six rows gives
    ``-6 mu cos(pi/6) n``, so the rows imply ``n . f >= 0`` (for ``mu > 0``). ``n`` is normalised.
    """
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    t1, t2 = tangent_basis(n, radial)
    ang = (2.0 * np.arange(PYRAMID_SIDES) + 1.0) * (np.pi / PYRAMID_SIDES)
    return (np.cos(ang)[:, None] * t1[..., None, :] + np.sin(ang)[:, None] * t2[..., None, :]
            - mu * np.cos(np.pi / PYRAMID_SIDES) * n[..., None, :])


# --------------------------------------------------------------------------------------------
# Rotational model about a fixed support (eq. 7–10)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RotationModel:
    """A rigid object rotating about a fixed support point ``A`` (for an edge, also about ``B``).

    mass : float (kg).
    I_A_O : (3, 3) inertia about A in O axes (kg m^2), by the parallel-axis theorem.
    r_com_O : (3,) CoM minus A (m, O).
    r_eef_O : (2, 3) EEF contact points minus A (m, O).
    n_eef_O : (2, 3) unit inward surface normals at the contacts (O).
    p_A_O : (3,) the support point A (m, O).
    edge_O : (3,) B minus A (m, O) for an edge support, None for a vertex.
    g : float (m/s^2).
    P_O : (3, n_rot) reduced-coordinate basis in O (I_3, or the unit edge direction).
    K_O : (n_rot, 3) ``(P^T I_A P)^-1 P^T`` in O: body torque to reduced acceleration.
    S6_O : (3, 6) ``[[r_1]x, [r_2]x]``: torque about A of the EEF forces ``[f1_O, f2_O]`` (in O).
    """

    mass: float
    I_A_O: np.ndarray
    r_com_O: np.ndarray
    r_eef_O: np.ndarray
    n_eef_O: np.ndarray
    p_A_O: np.ndarray
    edge_O: np.ndarray | None
    g: float
    P_O: np.ndarray
    K_O: np.ndarray
    S6_O: np.ndarray

    @property
    def n_rot(self) -> int:
        """Rotational degrees of freedom: 3 about a vertex, 1 about an edge."""
        return self.P_O.shape[1]

    @property
    def n_support(self) -> int:
        """Table contacts carrying the reaction: 1 (vertex) or 2 (edge)."""
        return 1 if self.edge_O is None else 2

    @cached_property
    def step_constants(self) -> dict:
        """Products of the fields that every MPC step uses, computed once per model."""
        return {
            # integrate_rotation, as nested lists: body torque to body angular acceleration, the
            # inertia about A, and the gravity torque per unit of the body-frame vertical.
            "M": (self.P_O @ self.K_O).tolist(), "I_A": self.I_A_O.tolist(),
            "S_g": (se3.skew(self.r_com_O) * (-self.mass * self.g)).tolist(),
            # _reaction_map
            "mg": np.array([0.0, 0.0, -self.mass * self.g]), "KS6": self.K_O @ self.S6_O,
        }


def make_rotation_model(mass, I_com_O, p_com_O, p_contacts_O, n_contacts_O, p_support_O,
                        g: float = 9.81) -> RotationModel:
    """Validate the inputs and build a :class:`RotationModel`.

    Parameters
    ----------
    mass : float (kg).
    I_com_O : (3, 3) inertia about the CoM in O axes (kg m^2).
    p_com_O : (3,) CoM (m, O).
    p_contacts_O : (2, 3) EEF contact points (m, O).
    n_contacts_O : (2, 3) inward surface normals at the contacts (O); normalised here.
    p_support_O : (1, 3) a vertex, or (2, 3) an edge's end vertices (m, O).
    g : gravity (m/s^2).
    """
    mass = float(mass)
    I_com_O = np.asarray(I_com_O, dtype=float)
    p_com_O = np.asarray(p_com_O, dtype=float)
    p_c = np.asarray(p_contacts_O, dtype=float)
    n_c = np.asarray(n_contacts_O, dtype=float)
    p_s = np.asarray(p_support_O, dtype=float).reshape(-1, 3)
    if not (np.isfinite(mass) and mass > 0.0):
        raise InputError(f"mpc: mass must be positive, got {mass}")
    if I_com_O.shape != (3, 3) or not np.all(np.isfinite(I_com_O)) or \
            not np.allclose(I_com_O, I_com_O.T, atol=1e-12) or np.linalg.eigvalsh(I_com_O).min() <= 0.0:
        raise InputError("mpc: I_com_O must be a finite symmetric positive-definite (3, 3) matrix")
    if p_com_O.shape != (3,) or p_c.shape != (2, 3) or n_c.shape != (2, 3) or len(p_s) not in (1, 2):
        raise InputError("mpc: expected p_com_O (3,), p_contacts_O (2, 3), n_contacts_O (2, 3) and "
                         f"one or two support points, got {p_com_O.shape}, {p_c.shape}, {n_c.shape}, "
                         f"{p_s.shape}")
    if not all(np.all(np.isfinite(v)) for v in (p_com_O, p_c, n_c, p_s)):
        raise InputError("mpc: non-finite object or contact data")
    nn = np.linalg.norm(n_c, axis=1)
    if np.any(nn < 1e-9):
        raise InputError("mpc: zero contact normal")
    r_com = p_com_O - p_s[0]
    I_A = I_com_O + mass * (r_com @ r_com * np.eye(3) - np.outer(r_com, r_com))
    edge = None
    P = np.eye(3)
    if len(p_s) == 2:
        edge = p_s[1] - p_s[0]
        if np.linalg.norm(edge) < 1e-6:
            raise InputError("mpc: the support edge has zero length")
        P = (edge / np.linalg.norm(edge))[:, None]
    K = np.linalg.solve(P.T @ I_A @ P, P.T)
    return RotationModel(mass=mass, I_A_O=I_A, r_com_O=r_com, r_eef_O=p_c - p_s[0],
                         n_eef_O=n_c / nn[:, None], p_A_O=p_s[0].copy(), edge_O=edge, g=float(g),
                         P_O=P, K_O=K, S6_O=np.concatenate(list(se3.skew(p_c - p_s[0])), axis=1))


def _nominal_terms(model: RotationModel, R_bar: np.ndarray, omega_bar: np.ndarray) -> dict[str, np.ndarray]:
    """The parts of the stage models that depend only on the nominal points, ``(N, ...)`` each.

    Apart from the nominal forces so that a run computes them once for the whole reference.
    ``ca`` is the constant of the linearised gyroscopic term: ``omega x I omega ~ J omega -
    omega_bar x I omega_bar`` with ``J = [omega_bar] I - [I omega_bar]``.
    """
    R_bar = np.asarray(R_bar, dtype=float)
    omega_bar = np.asarray(omega_bar, dtype=float)
    Rt = np.swapaxes(R_bar, -1, -2)
    I_W = R_bar @ model.I_A_O @ Rt
    r_eef = np.einsum("nij,kj->nki", R_bar, model.r_eef_O)
    r_com = R_bar @ model.r_com_O
    # K = (P^T I_W P)^-1 P^T maps a world torque to the reduced acceleration (world nu).
    if model.edge_O is None:
        P = np.broadcast_to(np.eye(3), R_bar.shape)
        K = R_bar @ model.K_O @ Rt
    else:
        P = R_bar @ model.P_O
        K = model.K_O @ Rt
    Pt = np.swapaxes(P, -1, -2)
    mg = np.array([0.0, 0.0, -model.mass * model.g])
    S_rR = se3.skew(r_eef) @ R_bar[:, None]  # torque of an O-frame force: [r_i] R f_i
    Mg = se3.skew(mg) @ se3.skew(r_com)  # d(r_com x m g)/d delta
    Iw = np.einsum("nij,nj->ni", I_W, omega_bar)
    J = se3.skew(omega_bar) @ I_W - se3.skew(Iw)  # d(omega x I omega)/d omega
    T_u = se3.skew(omega_bar)[:, None] @ S_rR  # rate of [r_i] R f_i as the object turns
    return {
        "R": R_bar, "omega": omega_bar, "I_W": I_W, "r_com": r_com, "S_rR": S_rR, "P": P, "Pt": Pt,
        "K": K,
        "KMgP": K @ Mg @ P,
        "M_nu": -(K @ J @ P),
        "Na": K @ np.concatenate([S_rR[:, 0], S_rR[:, 1]], axis=-1),
        "ca": np.einsum("nij,nj->ni", K, _cross(r_com, mg) + _cross(omega_bar, Iw)),
        "KTu": K @ np.concatenate([T_u[:, 0], T_u[:, 1]], axis=-1),
    }


@dataclass(frozen=True, eq=False)
class LinearStages:
    """Affine stage models ``x+ = A x + B u + D`` and accelerations ``nu' = Ma x + Na u + ca``.

    A : (N, nx, nx); B : (N, nx, 6); D : (N, nx); Ma : (N, nr, nx); Na : (N, nr, 6); ca : (N, nr).
    ``u = [f1_O, f2_O]`` (N, object frame); ``nx = 2 nr``.
    """

    A: np.ndarray
    B: np.ndarray
    D: np.ndarray
    Ma: np.ndarray
    Na: np.ndarray
    ca: np.ndarray


def _base_stages(terms: dict[str, np.ndarray], phi_ref, dt: float, state_dependent):
    """Stage matrices without the nominal-force terms; also ``Q = P^T (I + [phi_ref]/2) P``."""
    K, P, Pt = terms["K"], terms["P"], terms["Pt"]
    N, nr = K.shape[0], K.shape[1]
    sd = np.asarray(state_dependent, dtype=float)[:, None, None]
    KMgP = terms["KMgP"]
    M_eps = KMgP * sd
    M_nu, Na, ca, KTu = terms["M_nu"], terms["Na"], terms["ca"], terms["KTu"]
    S_phi = se3.skew(phi_ref)
    Q = Pt @ (np.eye(3) + 0.5 * S_phi) @ P
    eye = np.eye(nr)
    h2, h3 = 0.5 * dt * dt, dt**3 / 6.0
    A = np.empty((N, 2 * nr, 2 * nr))
    A[:, :nr, :nr] = eye + Pt @ S_phi @ P + h2 * Q @ M_eps
    A[:, :nr, nr:] = Q @ (dt * eye + h2 * M_nu + h3 * KMgP)
    A[:, nr:, :nr] = dt * M_eps
    A[:, nr:, nr:] = eye + dt * M_nu + h2 * KMgP
    B = np.concatenate([Q @ (h2 * Na + h3 * KTu), dt * Na + h2 * KTu], axis=1)
    D = np.concatenate([np.einsum("nij,nj->ni", Q, h2 * ca) - np.einsum("nij,nj->ni", Pt, phi_ref), dt * ca],
                       axis=1)
    return LinearStages(A=A, B=B, D=D, Ma=np.concatenate([M_eps, M_nu], axis=-1), Na=Na, ca=ca), Q


def _force_term_tensors(terms: dict[str, np.ndarray], Q: np.ndarray, dt: float):
    """How the stage matrices change per unit of nominal EEF force ``f_bar = [f1_O, f2_O]`` (6,).

    The forces turn with the object, so their torque ``tau_eef = S f_bar`` changes with the
    rotation error as ``-[tau_eef] delta`` and over a step as ``-[tau_eef] omega``; both enter
    through ``KMfP = -K [tau_eef] P = sum_l f_bar_l L_l``, linear in ``f_bar``. Returns ``TA
    (N, 6, nx, nx)``, ``TD (N, 6, nx)``, ``TMa (N, 6, nr, nx)`` with e.g. ``A = A_base + sum_l
    f_bar_l TA_l`` (the ``D`` part is the linearisation's constant ``-KMfP nu_bar``).
    """
    K, P = terms["K"], terms["P"]
    N, nr = K.shape[0], Q.shape[-1]
    S6 = np.concatenate([terms["S_rR"][:, 0], terms["S_rR"][:, 1]], axis=-1)  # (N, 3, 6)
    Lf = -(K[:, None] @ se3.skew(np.swapaxes(S6, 1, 2)) @ P[:, None])  # (N, 6, nr, nr)
    nu_bar = np.einsum("nji,nj->ni", P, terms["omega"])
    KTc = -np.einsum("nlij,nj->nli", Lf, nu_bar)  # (N, 6, nr)
    QL = Q[:, None] @ Lf
    h2, h3 = 0.5 * dt * dt, dt**3 / 6.0
    TA = np.empty((N, 6, 2 * nr, 2 * nr))
    TA[..., :nr, :nr] = h2 * QL
    TA[..., :nr, nr:] = h3 * QL
    TA[..., nr:, :nr] = dt * Lf
    TA[..., nr:, nr:] = h2 * Lf
    TD = np.concatenate([h3 * np.einsum("nij,nlj->nli", Q, KTc), h2 * KTc], axis=-1)
    TMa = np.zeros((N, 6, nr, 2 * nr))
    TMa[..., :nr] = Lf
    return TA, TD, TMa


def _with_force_terms(base: LinearStages, tensors, f_bar) -> LinearStages:
    """Add the nominal-force terms (:func:`_force_term_tensors`) for ``f_bar (N, 2, 3)`` (O)."""
    TA, TD, TMa = tensors
    f6 = np.asarray(f_bar, dtype=float).reshape(-1, 6)
    return LinearStages(A=base.A + np.einsum("nl,nlij->nij", f6, TA), B=base.B,
                        D=base.D + np.einsum("nl,nli->ni", f6, TD),
                        Ma=base.Ma + np.einsum("nl,nlij->nij", f6, TMa), Na=base.Na, ca=base.ca)


def _assemble_stages(terms: dict[str, np.ndarray], f_bar, phi_ref, dt: float, state_dependent) -> LinearStages:
    """Stage matrices from :func:`_nominal_terms`, the nominal forces and the reference increments."""
    base, Q = _base_stages(terms, phi_ref, dt, state_dependent)
    sd = np.asarray(state_dependent, dtype=bool)
    if not sd.any():
        return base
    f_bar = np.asarray(f_bar, dtype=float) * sd[:, None, None]
    return _with_force_terms(base, _force_term_tensors(terms, Q, dt), f_bar)


def linearize_rotation(model: RotationModel, R_bar, omega_bar, f_bar_O, phi_ref, dt: float,
                       state_dependent=None) -> LinearStages:
    """Linear prediction model ``x+ = A x + B u + D`` (eq. 8–10) at ``N`` nominal points.

    Parameters
    ----------
    model : :class:`RotationModel`.
    R_bar : (N, 3, 3) nominal rotations R_WO (the reference, or the state itself).
    omega_bar : (N, 3) nominal angular velocities (rad/s, W).
    f_bar_O : (N, 2, 3) nominal EEF forces (N, O) for the bilinear lever-arm terms.
    phi_ref : (N, 3) reference increments ``log(R_ref[j+1] R_ref[j]^T)`` (rad, W).
    dt : step (s).
    state_dependent : (N,) bool, optional (all True by default)
        False where the nominal point is the state itself: the deviation is then zero,
        so the terms in ``eps`` vanish and the torque rate is exact in the forces.

    Returns
    -------
    LinearStages

    Notes
    -----
    With ``delta = P eps`` the world rotation error, the torque about the support is
    ``tau ~ sum [r_i] R f_i - [tau_eef] delta + [m g][r_com] delta + r_com x m g`` (forces held
    in O turn with the object) and ``omega x I omega`` is linearised about ``omega_bar``. Over a
    step the torque changes as the object turns, at the rate
    ``tau' = [omega] sum [r_i] R f_i + [m g][r_com] omega``, which enters through ``dt^2/2``
    (velocity) and ``dt^3/6`` (rotation). The error kinematics follow from
    ``log(exp(phi) exp(delta) exp(-phi_ref))`` to first order in the deviations:
    ``delta+ = (I + [phi_ref]) delta + (I + [phi_ref]/2)(phi - phi_ref)`` with
    ``phi = dt omega + dt^2/2 omega' + dt^3/6 omega''``. Dropped: the change of ``I_A`` with
    ``delta`` and over the step (both multiply the small net angular acceleration).
    """
    R_bar = np.asarray(R_bar, dtype=float)
    if state_dependent is None:
        state_dependent = np.ones(len(R_bar), dtype=bool)
    terms = _nominal_terms(model, R_bar, omega_bar)
    return _assemble_stages(terms, np.asarray(f_bar_O, dtype=float), np.asarray(phi_ref, dtype=float), dt,
                            state_dependent)


def _skew3(v) -> np.ndarray:
    x, y, z = v.tolist()
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


_I3 = np.eye(3)
_I3.flags.writeable = False


def _exp_so3(v: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for one rotation vector ``v (3,)``."""
    th = float(np.sqrt(v @ v))
    S = _skew3(v)
    if th < 1e-8:
        return _I3 + S + 0.5 * (S @ S)
    return _I3 + (np.sin(th) / th) * S + ((1.0 - np.cos(th)) / th**2) * (S @ S)


def _log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` of one rotation away from pi (errors and small increments)."""
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    if c < -0.99:  # near pi the skew part loses the axis
        return Rotation.from_matrix(R).as_rotvec()
    th = np.arccos(min(1.0, c))
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * (th / np.sin(th) if th > 1e-8 else 1.0 + th * th / 6.0)


def _body_acceleration(model: RotationModel, R: np.ndarray, nu_B: np.ndarray, f_O: np.ndarray):
    """Reduced acceleration and ``omega_B`` in O axes at one state (eq. 7 in the body frame).

    ``nu_B`` is ``omega_B`` about a vertex and the rate about the edge for an edge. In O the
    inertia, the projection and the EEF torque are constant; only gravity turns.
    """
    omega_B = model.P_O @ nu_B
    g_B = R[2] * (-model.mass * model.g)  # R^T (0, 0, -m g)
    tau = (_cross(model.r_eef_O, f_O).sum(axis=0) + _cross(model.r_com_O, g_B)
           - _cross(omega_B, model.I_A_O @ omega_B))
    nu_dot = model.K_O @ tau
    return nu_dot, omega_B, model.P_O @ nu_dot


def rotation_acceleration(model: RotationModel, R: np.ndarray, nu: np.ndarray, f_O: np.ndarray):
    """Exact accelerations (eq. 7) at one state.

    Parameters
    ----------
    R : (3, 3) R_WO; nu : (n_rot,) reduced angular velocity (rad/s, W); f_O : (2, 3) (N, O).

    Returns
    -------
    nu_dot : (n_rot,) (rad/s^2, W); omega : (3,) (rad/s, W); omega_dot : (3,) (rad/s^2, W).
    """
    nu = np.asarray(nu, dtype=float)
    vertex = model.edge_O is None
    nu_dot, omega_B, omega_dot_B = _body_acceleration(model, R, nu @ R if vertex else nu,
                                                      np.asarray(f_O, dtype=float))
    omega_dot = R @ omega_dot_B
    return (omega_dot if vertex else nu_dot), R @ omega_B, omega_dot


def _mv3(M, v):
    """``M v`` for a 3x3 nested list and a 3-tuple (plain floats: numpy is slow at this size)."""
    return (M[0][0] * v[0] + M[0][1] * v[1] + M[0][2] * v[2],
            M[1][0] * v[0] + M[1][1] * v[1] + M[1][2] * v[2],
            M[2][0] * v[0] + M[2][1] * v[1] + M[2][2] * v[2])


def _cr3(a, b):
    """``a x b`` for 3-tuples."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def integrate_rotation(model: RotationModel, R: np.ndarray, nu: np.ndarray, f_O: np.ndarray,
                       dt: float, substeps: int = 1):
    """Integrate the nonlinear rotation about the support over ``dt`` (eq. 7).

    RK4 on ``R = R0 exp(psi)`` in the body frame (a Runge–Kutta–Munthe-Kaas step):
    ``psi' = dexp_inv(psi) omega_B``, ``omega_B' = P K (tau_eef + r_com x R^T m g - omega_B x I
    omega_B)``; the EEF forces are held constant in O, so in O only gravity turns. Written with
    plain floats: this runs once per MPC step and numpy's per-call cost dominates at 3x3.

    Parameters
    ----------
    R : (3, 3) R_WO; nu : (n_rot,) reduced angular velocity (rad/s, W); f_O : (2, 3) (N, O);
    dt : step (s); substeps : RK4 steps per ``dt``.

    Returns
    -------
    R_next : (3, 3); nu_next : (n_rot,).
    """
    h = dt / substeps
    vertex = model.edge_O is None
    nu = np.asarray(nu, dtype=float)
    w = tuple((nu @ R if vertex else model.P_O @ nu).tolist())  # omega_B
    const = model.step_constants
    M = const["M"]  # body torque to body angular acceleration
    I_A = const["I_A"]
    S_g = const["S_g"]  # r_com x (-m g v) = S_g v
    te = (model.S6_O @ np.asarray(f_O, dtype=float).reshape(6)).tolist()  # EEF torque, fixed in O

    for _ in range(substeps):
        ez = R[2].tolist()  # R0^T e_z

        def rhs(psi, w, ez=ez):
            th2 = psi[0] * psi[0] + psi[1] * psi[1] + psi[2] * psi[2]
            if th2 < 1e-12:  # series limits
                a, b, c = 1.0, 0.5, 1.0 / 12.0
            else:
                th = math.sqrt(th2)
                sn, cs = math.sin(th), math.cos(th)
                a, b, c = sn / th, (1.0 - cs) / th2, 1.0 / th2 - (1.0 + cs) / (2.0 * th * sn)
            p1 = _cr3(psi, ez)
            p2 = _cr3(psi, p1)
            up = (ez[0] - a * p1[0] + b * p2[0], ez[1] - a * p1[1] + b * p2[1],
                  ez[2] - a * p1[2] + b * p2[2])  # exp(-psi) R0^T e_z
            g = _mv3(S_g, up)
            gy = _cr3(w, _mv3(I_A, w))
            w_dot = _mv3(M, (te[0] + g[0] - gy[0], te[1] + g[1] - gy[1], te[2] + g[2] - gy[2]))
            q1 = _cr3(psi, w)
            q2 = _cr3(psi, q1)  # dexp_inv(psi) w = w + psi x w / 2 + c psi x (psi x w)
            return (w[0] + 0.5 * q1[0] + c * q2[0], w[1] + 0.5 * q1[1] + c * q2[1],
                    w[2] + 0.5 * q1[2] + c * q2[2]), w_dot

        def step(k, f, w=w):
            return ((f * k[0][0], f * k[0][1], f * k[0][2]),
                    (w[0] + f * k[1][0], w[1] + f * k[1][1], w[2] + f * k[1][2]))

        k1 = rhs((0.0, 0.0, 0.0), w)
        k2 = rhs(*step(k1, 0.5 * h))
        k3 = rhs(*step(k2, 0.5 * h))
        k4 = rhs(*step(k3, h))
        psi = [h / 6.0 * (k1[0][i] + 2.0 * k2[0][i] + 2.0 * k3[0][i] + k4[0][i]) for i in range(3)]
        w = tuple(w[i] + h / 6.0 * (k1[1][i] + 2.0 * k2[1][i] + 2.0 * k3[1][i] + k4[1][i]) for i in range(3))
        R = R @ _exp_so3(np.array(psi))
    w = np.array(w)
    return R, (R @ w if vertex else model.P_O.T @ w)


def _reaction_terms(model: RotationModel, R: np.ndarray, omega: np.ndarray):
    """Table reactions as affine maps of the reduced acceleration and the EEF forces, batched.

    At rotations ``R (n, 3, 3)`` and angular velocities ``omega (n, 3)`` (W), the reactions on
    the object are ``G_nu nu' + G_u u + g_0 + s e`` with ``G_nu (n, nv, 3, nr)``, ``G_u (n, nv, 3,
    6)``, ``g_0 (n, nv, 3)``, ``e (n, nv, 3)`` (``nv`` = 1 vertex or 2 edge vertices; ``u = [f1_O,
    f2_O]``; ``s`` the along-edge part of vertex B's reaction, ``e = 0`` for a vertex).
    Newton–Euler: ``f0 = m a_com - m g - f1 - f2`` with ``a_com = omega' x r + omega x (omega x
    r)``; about an edge the moment balance about A fixes vertex B's force across the edge,
    ``L x f_B = m_req = I omega' + omega x I omega - tau_eef - r x m g``, so
    ``f_B = m_req x L / |L|^2 + s e_L`` and A takes the rest.
    """
    R = np.asarray(R, dtype=float)
    omega = np.asarray(omega, dtype=float)
    n = len(R)
    mg = np.array([0.0, 0.0, -model.mass * model.g])
    r_com = R @ model.r_com_O
    P = np.broadcast_to(np.eye(3), R.shape) if model.edge_O is None else R @ model.P_O
    G_nu = -model.mass * se3.skew(r_com) @ P
    G_u = -np.concatenate([R, R], axis=-1)
    g_0 = model.mass * _cross(omega, _cross(omega, r_com)) - mg
    if model.edge_O is None:
        return G_nu[:, None], G_u[:, None], g_0[:, None], np.zeros((n, 1, 3))
    I_W = R @ model.I_A_O @ np.swapaxes(R, -1, -2)
    S6 = R @ model.S6_O  # torque of u: [R r_i] R f_i = R [r_i] f_i
    L = R @ model.edge_O
    SL = se3.skew(L) / np.einsum("ni,ni->n", L, L)[:, None, None]  # m x L / |L|^2 = -SL m
    B_nu = -SL @ I_W @ P
    B_u = SL @ S6
    B_0 = -np.einsum("nij,nj->ni", SL, _cross(omega, np.einsum("nij,nj->ni", I_W, omega)) - _cross(r_com, mg))
    e_L = L / np.linalg.norm(L, axis=-1, keepdims=True)
    return (np.stack([G_nu - B_nu, B_nu], axis=1), np.stack([G_u - B_u, B_u], axis=1),
            np.stack([g_0 - B_0, B_0], axis=1), np.stack([-e_L, e_L], axis=1))


def _reaction_map(model: RotationModel, R: np.ndarray, nu: np.ndarray):
    """Exact table reactions at one state as ``F_u u + F_c + s e`` (``(nv, 3, 6)``, ``(nv, 3)``).

    The same balance as :func:`_reaction_terms` with eq. 7's acceleration at the state,
    ``nu' = K (R [r_i] f_i + r x m g - omega x I omega)``, affine in ``u = [f1_O, f2_O]``.
    Written out for one state (it runs at every MPC step).
    """
    nu = np.asarray(nu, dtype=float)
    vertex = model.edge_O is None
    const = model.step_constants
    mg = const["mg"]
    omega = nu if vertex else R @ (model.P_O @ nu)
    omega_B = omega @ R
    r_com = R @ model.r_com_O
    Iw = R @ (model.I_A_O @ omega_B)
    tau_c = _cross(r_com, mg) - _cross(omega, Iw)
    # omega' = W_u u + W_c in W.
    if vertex:
        W_u = R @ const["KS6"]
        W_c = R @ (model.K_O @ (tau_c @ R))
    else:
        a = R @ model.P_O[:, 0]
        W_u = np.outer(a, const["KS6"])
        W_c = a * (model.K_O[0] @ (tau_c @ R))
    Sc = _skew3(r_com)
    F_u = -model.mass * (Sc @ W_u) - np.concatenate([R, R], axis=1)
    F_c = -model.mass * (Sc @ W_c) + model.mass * _cross(omega, _cross(omega, r_com)) - mg
    if vertex:
        return F_u[None], F_c[None], np.zeros((1, 3))
    L = R @ model.edge_O
    SL = _skew3(L) / (L @ L)
    I_W = R @ model.I_A_O @ R.T
    fB_u = -SL @ (I_W @ W_u - R @ model.S6_O)
    fB_c = -SL @ (I_W @ W_c - tau_c)
    e_L = L / np.sqrt(L @ L)
    return np.stack([F_u - fB_u, fB_u]), np.stack([F_c - fB_c, fB_c]), np.stack([-e_L, e_L])


def support_reactions(model: RotationModel, R: np.ndarray, nu: np.ndarray, f_O: np.ndarray,
                      s_edge: float = 0.0) -> np.ndarray:
    """Table reactions ``(n_support, 3)`` (N, W) on the object from the Newton–Euler balance.

    ``f0 = m a_com - m g - f1 - f2`` with ``a_com = omega' x r + omega x (omega x r)``. About an
    edge, the moment balance about A fixes the part of B's force across the edge; ``s_edge`` (N)
    is the statically indeterminate part along the edge (A gets the rest).

    Parameters
    ----------
    R : (3, 3) R_WO; nu : (n_rot,) (rad/s, W); f_O : (2, 3) EEF forces (N, O); s_edge : float.
    """
    F_u, F_c, e = _reaction_map(model, np.asarray(R, dtype=float), nu)
    return F_u @ np.asarray(f_O, dtype=float).reshape(6) + F_c + s_edge * e


# --------------------------------------------------------------------------------------------
# MPC
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MPCTimings:
    """Wall-clock figures, kept apart from the deterministic result (never in artifacts).

    solve_time_s : (T,) piqp setup + solve per QP (s), NaN where none ran.
    total_s : the whole run (s).
    """

    solve_time_s: np.ndarray
    total_s: float


@dataclass(frozen=True, eq=False)
class MPCResult:
    """Closed-loop MPC run over the reference samples (arrays over time, index = sample).

    t : (T,) (s).
    X_WO : (T, 4, 4) object pose simulated with the nonlinear dynamics; NaN after a failure.
    omega_W : (T, 3) its angular velocity (rad/s, W).
    X_WO_ref : (T, 4, 4) the reference.
    f_eef_W : (T, 2, 3) EEF forces on the object at ``t_k`` (N, W); held in O over the step.
    f_eef_O : (T, 2, 3) the same in O (N), the MPC's input.
    p_eef_W : (T, 2, 3) EEF contact points (m, W).
    contact_mask : (T, 2) bool, whether each EEF touches the object.
    f_table_W : (T, 3) total table reaction on the object at ``t_k`` (N, W).
    f_support_W : (T, n_support, 3) reaction per table vertex (N, W).
    tracking_error : (T,) rotation angle between the pose and the reference (rad).
    pyramid_eef_O : (2, 6, 3) rows ``H`` of the EEF friction pyramids, ``H f_O <= 0`` (O).
    pyramid_table_W : (n_support, 6, 3) rows of the table pyramid at each support vertex (W).
    n_iter : (T,) piqp iterations per QP (-1 where none ran).
    status : ``"ok"`` or ``"mpc_infeasible"``.
    fail_step : index of the failed QP, -1 when ok.
    fail_reason : piqp's status for the failed QP, ``""`` when ok.
    timings : :class:`MPCTimings`, wall-clock only: keep it out of artifacts.
    """

    t: np.ndarray
    X_WO: np.ndarray
    omega_W: np.ndarray
    X_WO_ref: np.ndarray
    f_eef_W: np.ndarray
    f_eef_O: np.ndarray
    p_eef_W: np.ndarray
    contact_mask: np.ndarray
    f_table_W: np.ndarray
    f_support_W: np.ndarray
    tracking_error: np.ndarray
    pyramid_eef_O: np.ndarray
    pyramid_table_W: np.ndarray
    n_iter: np.ndarray
    status: str
    fail_step: int
    fail_reason: str
    timings: MPCTimings = field(repr=False)

    @property
    def ok(self) -> bool:
        """True when every QP was solved."""
        return self.status == STATUS_OK


def _check_reference(t, X_WO_ref, params: Params):
    t = np.asarray(t, dtype=float)
    X = np.asarray(X_WO_ref, dtype=float)
    if t.ndim != 1 or len(t) < 2 or X.shape != (len(t), 4, 4):
        raise InputError(f"mpc: expected t (T,) and X_WO_ref (T, 4, 4) with T >= 2, got {t.shape}, {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InputError("mpc: X_WO_ref has non-finite entries")
    if np.abs(np.diff(t) - params.dt).max() > 1e-9:
        raise InputError(f"mpc: the reference must be sampled at Params.dt = {params.dt} s")
    if params.horizon < 1 or params.block < 1 or params.f_max < params.f_min or params.f_min < 0.0:
        raise InputError(f"mpc: invalid parameters {params}")
    return t, X


def _mask_over_time(contact_mask, T: int) -> np.ndarray:
    m = np.asarray(contact_mask, dtype=bool)
    if m.shape == (2,):
        m = np.broadcast_to(m, (T, 2))
    if m.shape != (T, 2):
        raise InputError(f"mpc: contact_mask must be (2,) or (T, 2) = ({T}, 2), got {m.shape}")
    return m.copy()


def run_pivot_mpc(mass, I_com_O, p_com_O, p_contacts_O, n_contacts_O, p0_W, t, X_WO_ref,
                  params: Params = Params(), contact_mask=(True, True)) -> MPCResult:
    """Track a pivoting reference about the table vertex ``p0_W`` (§5.2.1, eq. 8–11).

    Parameters
    ----------
    mass : float (kg).
    I_com_O : (3, 3) inertia about the CoM in O axes (kg m^2).
    p_com_O : (3,) CoM (m, O).
    p_contacts_O : (2, 3) EEF contact points (m, O).
    n_contacts_O : (2, 3) inward surface normals at the contacts (O).
    p0_W : (3,) the table vertex (m, W); every reference pose must keep it in place.
    t : (T,) sample times (s), step ``params.dt``.
    X_WO_ref : (T, 4, 4) reference poses (e.g. from :func:`pivot_reference`); the run starts at
        rest at ``X_WO_ref[0]``.
    params : :class:`Params`.
    contact_mask : (2,) or (T, 2) bool, which EEFs touch the object at each sample.

    Returns
    -------
    MPCResult
    """
    t, X_ref = _check_reference(t, X_WO_ref, params)
    p0_W = np.asarray(p0_W, dtype=float).reshape(3)
    p0_O = se3.transform_points(se3.invert(X_ref[0]), p0_W)
    model = make_rotation_model(mass, I_com_O, p_com_O, p_contacts_O, n_contacts_O, p0_O[None], params.g)
    return _run_mpc(model, p0_W[None], t, X_ref, params, _mask_over_time(contact_mask, len(t)))


def run_tumble_mpc(mass, I_com_O, p_com_O, p_contacts_O, n_contacts_O, p_edge_W, t, X_WO_ref,
                   params: Params = Params(), contact_mask=(True, True), catch_time: float | None = None,
                   release_time: float | None = None) -> MPCResult:
    """Track a rotation about a table edge (tumbling, §5.2.2, Fig. 14; also a USP hold).

    The object turns about the line through the edge's end vertices ``p_edge_W (2, 3)`` (1 DOF);
    both vertices share the table reaction, each inside the table's friction pyramid. One or two
    EEFs push. ``catch_time`` (s) switches EEF 2 on from that time (the catching arm of Fig. 14,
    off before), ``release_time`` (s) switches EEF 1 off from that time; both edit
    ``contact_mask``, and the MPC sees the schedule over its horizon. Holding an object in USP on
    an edge with one EEF (the DS gait) is the same call with a one-EEF mask.

    Other parameters as :func:`run_pivot_mpc`.
    """
    t, X_ref = _check_reference(t, X_WO_ref, params)
    p_edge_W = np.asarray(p_edge_W, dtype=float)
    if p_edge_W.shape != (2, 3):
        raise InputError(f"run_tumble_mpc: p_edge_W must be (2, 3), got {p_edge_W.shape}")
    p_edge_O = se3.transform_points(se3.invert(X_ref[0]), p_edge_W)
    model = make_rotation_model(mass, I_com_O, p_com_O, p_contacts_O, n_contacts_O, p_edge_O, params.g)
    mask = _mask_over_time(contact_mask, len(t))
    if catch_time is not None:
        mask[:, 1] = t >= catch_time - 1e-9
    if release_time is not None:
        mask[t >= release_time - 1e-9, 0] = False
    return _run_mpc(model, p_edge_W, t, X_ref, params, mask)


class _Layout:
    """Index bookkeeping of the condensed QP.

    The forces are interpolated linearly between knots at stages ``0, block, 2 block, ...`` and
    ``N - 1`` (first-order-hold move blocking: a ramp is representable, and the force applied now
    is the first knot itself). Unknowns ``z = [v_0 .. v_{nk-1}, s_0 .. s_{nk-1}]``:
    ``v_b = [f1_O, f2_O]`` at knot ``b``; ``s_b`` (edge only) the along-edge part of vertex B's
    reaction at knot ``b``. ``u_j = U_j z``, masked by contact.
    """

    def __init__(self, N: int, block: int, edge: bool):
        self.N = N
        self.knots = np.unique(np.r_[np.arange(0, N, block), N - 1])
        self.nk = len(self.knots)
        self.nz = 6 * self.nk + (self.nk if edge else 0)
        self.edge = edge
        # Interpolation weights (N, nk): stage j between knots b and b + 1.
        j = np.arange(N)
        b = np.clip(np.searchsorted(self.knots, j, side="right") - 1, 0, max(self.nk - 2, 0))
        w = np.zeros((N, self.nk))
        if self.nk == 1:
            w[:, 0] = 1.0
        else:
            frac = (j - self.knots[b]) / (self.knots[b + 1] - self.knots[b])
            w[j, b] = 1.0 - frac
            w[j, b + 1] = frac
        self.weights = w
        # Predicted states at which the error bound applies: after each knot interval, and at N.
        self.err_idx = np.unique(np.r_[self.knots[1:], N])

    def input_maps(self, mask: np.ndarray) -> np.ndarray:
        """``U (N, 6, nz)`` with ``u_j = U_j z`` for the contact mask ``(N, 2)``."""
        U = np.zeros((self.N, 6, self.nz))
        m6 = np.repeat(mask, 3, axis=1).astype(float)  # (N, 6)
        for c in range(6):
            U[:, c, c:6 * self.nk:6] = self.weights * m6[:, c:c + 1]
        return U

    def knot_active(self, mask: np.ndarray) -> np.ndarray:
        """``(nk, 2)`` bool: the EEF touches at some stage that knot b's value reaches."""
        return ((self.weights > 0.0).T.astype(float) @ mask.astype(float)) > 0.0


class _Reference(NamedTuple):
    """The reference padded by ``N + 1`` copies of its last pose (§5.2, eq. 7-10 along it): rotations
    ``R (T + N + 1, 3, 3)`` (W), the nominal terms, the stage matrices without the force terms
    (``base``) and their change per unit force (``tensors``), the rates ``nu`` in the model's
    coordinates, and the table rows' terms along it (``G``: :func:`_reaction_terms`, framed by
    ``H_table``)."""

    R: np.ndarray
    terms: dict
    base: LinearStages
    tensors: tuple
    nu: np.ndarray
    G: list


def _reference(model: RotationModel, p_support_W, X_ref, H_table, params: Params) -> _Reference:
    """:class:`_Reference` of ``X_ref (T, 4, 4)``; refuses a reference that moves the table support."""
    N, dt = params.horizon, params.dt
    p_sup_O = se3.transform_points(se3.invert(X_ref[0]), p_support_W)
    drift = np.abs(se3.transform_points(X_ref[:, None], p_sup_O[None]) - p_support_W).max()
    if drift > SUPPORT_TOL:
        raise InputError(f"mpc: the reference moves the table support by {drift:.3g} m")
    # Increments and central-difference rates (W).
    R_ref = np.concatenate([X_ref[:, :3, :3], np.broadcast_to(X_ref[-1, :3, :3], (N + 1, 3, 3))])
    phi_ref = np.zeros((len(R_ref), 3))
    phi_ref[:-1] = Rotation.from_matrix(R_ref[1:] @ np.swapaxes(R_ref[:-1], -1, -2)).as_rotvec()
    omega_ref = np.empty_like(phi_ref)
    omega_ref[0] = phi_ref[0] / dt
    omega_ref[1:] = 0.5 * (phi_ref[:-1] + phi_ref[1:]) / dt
    # Stage models along the whole reference, once; per step only the nominal-force terms change.
    terms = _nominal_terms(model, R_ref, omega_ref)
    base, Q = _base_stages(terms, phi_ref, dt, np.ones(len(R_ref), dtype=bool))
    nu = np.einsum("nji,nj->ni", terms["P"], omega_ref)
    # Table rows along the reference: H_table (G_nu nu' + G_u u + g_0 + s e) <= 0.
    G = [np.einsum("vri,nvi...->nvr...", H_table, g) for g in _reaction_terms(model, R_ref, omega_ref)]
    return _Reference(R_ref, terms, base, _force_term_tensors(terms, Q, dt), nu, G)


def _pyramids(model: RotationModel, X0, p_support_W, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """Friction pyramids framed at the first reference pose ``X0`` (as the stability check frames
    them): the table's per support vertex ``(nv, 6, 3)`` (W), and the EEFs' rows ``(2, 7, 3)`` (O):
    the pyramid (6 rows <= 0) and the normal force row (``f_min <= n . f <= f_max``)."""
    com0_W = se3.transform_points(X0, model.p_A_O + model.r_com_O)
    H_table = friction_pyramid_halfspaces(np.broadcast_to(_Z, p_support_W.shape), params.mu_table,
                                          radial=p_support_W - com0_W)
    H_eef_W = friction_pyramid_halfspaces(se3.rotate_vectors(X0, model.n_eef_O), params.mu_eef,
                                          radial=se3.rotate_vectors(X0, model.r_eef_O - model.r_com_O))
    return H_table, np.concatenate([H_eef_W @ X0[:3, :3], model.n_eef_O[:, None, :]], axis=1)


class _Schedules(NamedTuple):
    """What the contact schedule of each step's horizon fixes (:func:`_schedules`): ``keys[k]`` names
    step k's schedule, ``by_key`` its input maps ``U``, input cost, EEF rows and their bounds and
    ``U_0``; ``BBU``, ``NaU``, ``HuU`` the products of ``U`` with the reference's stage matrices
    (``B_j U_j`` of each stage, ``Na U`` and the table rows' u part at the later knots)."""

    keys: list
    by_key: dict
    BBU: np.ndarray
    NaU: np.ndarray
    HuU: np.ndarray


def _schedules(lay: _Layout, ref: _Reference, mask_pad, j0, H_eef, T: int, n_tab: int, params: Params) -> _Schedules:
    """:class:`_Schedules` for the ``T`` steps, each distinct schedule once, the products for all
    steps at once."""
    N, nx, nr = params.horizon, ref.base.A.shape[1], ref.nu.shape[1]
    hl_eef1, hu_eef1 = np.r_[np.full(6, -np.inf), params.f_min], np.r_[np.zeros(6), params.f_max]
    kj = np.arange(T)[:, None] + j0
    Na_kj, Gu_kj = ref.base.Na[kj], ref.G[1][kj]
    windows = [mask_pad[k:k + N] for k in range(T)]
    keys = [m.tobytes() for m in windows]
    by_key: dict = {}
    BBU = np.empty((T, N, nx, lay.nz))
    NaU = np.empty((T, len(j0), nr, lay.nz))
    HuU = np.empty((T, len(j0), Gu_kj.shape[2], 6, lay.nz))
    for key in dict.fromkeys(keys):  # each distinct schedule, once
        ks = np.array([k for k in range(T) if keys[k] == key])
        m_st = windows[ks[0]]
        U = lay.input_maps(m_st)
        U2 = U.reshape(N * 6, lay.nz)
        # EEF rows at every knot whose value a touching stage uses (linear in O, so the
        # interpolated forces between two feasible knots are feasible).
        bb, ii = np.nonzero(lay.knot_active(m_st))
        G_eef = np.zeros((len(bb), 7, lay.nz))
        cols = (6 * bb + 3 * ii)[:, None] + np.arange(3)
        G_eef[np.arange(len(bb))[:, None, None], np.arange(7)[None, :, None], cols[:, None, :]] = H_eef[ii]
        by_key[key] = (U, params.beta * (U2.T @ U2), G_eef.reshape(-1, lay.nz),
                       np.concatenate([np.tile(hl_eef1, len(bb)), np.full(n_tab, -np.inf)]),
                       np.tile(hu_eef1, len(bb)), U[0])
        BBU[ks] = ref.base.B[ks[:, None] + np.arange(N)] @ U
        NaU[ks] = Na_kj[ks] @ U[j0]
        HuU[ks] = Gu_kj[ks] @ U[j0][:, None]
    return _Schedules(keys, by_key, BBU, NaU, HuU)


class _StepQP:
    """The QP of each MPC step (§5.2.2): the dynamics (eq. 7-10) linearised along the reference with
    the previous plan's forces for the lever-arm terms, condensed onto the move-blocked forces ``z``
    (:class:`_Layout`), with the EEF and table friction rows and the tracking-error bound. Built from
    what :func:`_run_mpc` fixes once; the condensing buffers are reused from step to step."""

    def __init__(self, model: RotationModel, ref: _Reference, lay: _Layout, sched: _Schedules, H_table, T: int,
                 params: Params):
        N, nr = params.horizon, model.n_rot
        self.model, self.ref, self.lay, self.sched, self.H_table, self.params = model, ref, lay, sched, H_table, params
        self.j0 = lay.knots[1:]  # knots after the first: the table rows along the prediction
        kj = np.arange(T)[:, None] + self.j0  # what step k needs at its later knots' stages k + j0
        _, _, TMa = ref.tensors
        self.Ma_kj, self.TMa_kj, self.ca_kj = ref.base.Ma[kj], TMa[kj], ref.base.ca[kj]
        self.G_kj = [G[kj] for G in ref.G]
        self.W_cost = np.tile(np.concatenate([np.full(nr, params.alpha), np.full(nr, params.alpha_rate)]), N)
        self.Ss = np.empty((N + 1, 2 * nr, lay.nz + 1))  # [S_j | s_j] with x_j = S_j z + s_j
        self.Ss[0] = 0.0
        self.BU = np.empty((N, 2 * nr, lay.nz + 1))
        self.Ss_j, self.BU_j = list(self.Ss), list(self.BU)  # views of each stage
        self.diag = np.arange(lay.nz) * (lay.nz + 1)  # flat indices of the QP's diagonal

    def condense(self, k: int, delta0, nu, f_prev):
        """Step k's prediction ``S_all, s_all`` and cost ``P_qp, c_qp`` from the state (``delta0``,
        ``nu``), the stages linearised with the previous plan's forces ``f_prev (N, 2, 3)`` (O; the
        accelerations at the knots only: ``Ma_j0``)."""
        ref, lay, p, N, nr = self.ref, self.lay, self.params, self.params.horizon, self.model.n_rot
        TA, TD, _ = ref.tensors
        sl = slice(k, k + N)
        f6 = f_prev.reshape(-1, 6)
        lin_A = ref.base.A[sl] + np.einsum("nl,nlij->nij", f6, TA[sl])
        lin_D = ref.base.D[sl] + np.einsum("nl,nli->ni", f6, TD[sl])
        Ma_j0 = self.Ma_kj[k] + np.einsum("nl,nlij->nij", f6[self.j0], self.TMa_kj[k])
        self.BU[:, :, :-1] = self.sched.BBU[k]
        self.BU[:, :, -1] = lin_D
        self.Ss[0, :nr, -1] = ref.terms["Pt"][k] @ delta0  # x0
        self.Ss[0, nr:, -1] = nu
        for j in range(N):
            S_next = self.Ss_j[j + 1]
            np.matmul(lin_A[j], self.Ss_j[j], out=S_next)
            S_next += self.BU_j[j]
        S_all, s_all = self.Ss[:, :, :-1], self.Ss[:, :, -1]
        x_ref = np.concatenate([np.zeros((N, nr)), ref.nu[k + 1:k + N + 1]], axis=1)
        Sx = S_all[1:].reshape(N * 2 * nr, lay.nz)
        WSx = self.W_cost[:, None] * Sx
        P_qp = Sx.T @ WSx + self.sched.by_key[self.sched.keys[k]][1]
        c_qp = WSx.T @ (s_all[1:] - x_ref).reshape(N * 2 * nr)
        # A token weight keeps the value of a knot that no touching stage uses at zero (and the
        # along-edge reaction parts bounded).
        P_qp.flat[self.diag] += 1e-6 * p.beta + 1e-9
        return S_all, s_all, P_qp, c_qp, Ma_j0

    def table_rows(self, k: int, R, nu, S_all, s_all, Ma_j0, U_0):
        """The table's friction rows ``G_tab z <= hu_tab`` at each knot's stage: knot 0 (the force
        applied now) exact at the state ``R, nu``; the later ones along the reference, through the
        predicted ``nu'_j = Ma x_j + Na u_j + ca``. Also the reaction map at the state."""
        H_table, lay = self.H_table, self.lay
        F_u, F_c, e_s = _reaction_map(self.model, R, nu)  # (nv, 3, 6), (nv, 3), (nv, 3)
        G_tab = [np.einsum("vri,vin->vrn", H_table, F_u @ U_0)[None]]
        hu_tab = [-np.einsum("vri,vi->vr", H_table, F_c)[None]]
        if len(self.j0):
            H_nu, h_0 = self.G_kj[0][k], self.G_kj[2][k]
            nud_z = Ma_j0 @ S_all[self.j0] + self.sched.NaU[k]  # (nj, nr, nz)
            nud_c = np.einsum("bij,bj->bi", Ma_j0, s_all[self.j0]) + self.ca_kj[k]
            G_tab.append(H_nu @ nud_z[:, None] + self.sched.HuU[k])
            hu_tab.append(-(np.einsum("bvrj,bj->bvr", H_nu, nud_c) + h_0))
        G_tab = np.concatenate(G_tab)  # (nk, nv, 6, nz)
        hu_tab = np.concatenate(hu_tab).reshape(-1)
        if lay.edge:  # the along-edge split, one unknown per knot
            He = np.concatenate([np.einsum("vri,vi->vr", H_table, e_s)[None], self.G_kj[3][k]])
            G_tab[np.arange(lay.nk), :, :, 6 * lay.nk + np.arange(lay.nk)] += He
        return G_tab.reshape(-1, lay.nz), hu_tab, (F_u, F_c, e_s)

    def solve(self, k: int, R, nu, delta0, f_prev):
        """Step k's QP solved with PIQP's dense interior-point method for the change from the
        previous plan (the free response falls far from the reference under gravity, so centring on
        a nominal keeps the numbers small): ``(status, z, iterations, seconds, U, reaction map)``."""
        lay, p = self.lay, self.params
        S_all, s_all, P_qp, c_qp, Ma_j0 = self.condense(k, delta0, nu, f_prev)
        U, _, G_eef, hl_pre, hu_eef, U_0 = self.sched.by_key[self.sched.keys[k]]
        G_tab, hu_tab, reaction = self.table_rows(k, R, nu, S_all, s_all, Ma_j0, U_0)
        # Tracking-error bound.
        G_err = S_all[lay.err_idx, :self.model.n_rot].reshape(-1, lay.nz)
        s_err = s_all[lay.err_idx, :self.model.n_rot].reshape(-1)
        G = np.asfortranarray(np.concatenate([G_eef, G_tab, G_err]))
        h_l = np.concatenate([hl_pre, -p.max_error - s_err])
        h_u = np.concatenate([hu_eef, hu_tab, p.max_error - s_err])
        z_bar = np.zeros(lay.nz)
        z_bar[:6 * lay.nk] = f_prev[lay.knots].reshape(-1)
        G_bar = G @ z_bar
        t0 = time.perf_counter()
        solver = piqp.DenseSolver()
        solver.settings.max_iter = p.max_iter
        # Ruiz scaling costs a third more iterations on these (already SI-scaled) problems.
        solver.settings.preconditioner_iter = 0
        solver.setup(np.asfortranarray(P_qp), c_qp + P_qp @ z_bar, None, None, G, h_l - G_bar, h_u=h_u - G_bar)
        st = solver.solve()
        return st, z_bar + solver.result.x, solver.result.info.iter, time.perf_counter() - t0, U, reaction


def _run_mpc(model: RotationModel, p_support_W, t, X_ref, params: Params, mask) -> MPCResult:
    """The receding-horizon loop (§5.2.2) of :func:`run_pivot_mpc` and :func:`run_tumble_mpc`: at each
    step the QP of :class:`_StepQP`, its first force applied through the model (eq. 7-10,
    :func:`integrate_rotation`); stops at the first step whose QP PIQP does not solve."""
    t_start = time.perf_counter()
    T, N = len(t), params.horizon
    H_table, H_eef = _pyramids(model, X_ref[0], p_support_W, params)
    ref = _reference(model, p_support_W, X_ref, H_table, params)
    lay = _Layout(N, params.block, model.edge_O is not None)
    mask_pad = np.concatenate([mask, np.broadcast_to(mask[-1], (N + 1, 2))])
    sched = _schedules(lay, ref, mask_pad, lay.knots[1:], H_eef, T, lay.nk * model.n_support * 6, params)
    qp = _StepQP(model, ref, lay, sched, H_table, T, params)
    X_WO, omega_W = np.full((T, 4, 4), np.nan), np.full((T, 3), np.nan)
    f_O, f_sup = np.full((T, 2, 3), np.nan), np.full((T, model.n_support, 3), np.nan)
    err, solve_time = np.full(T, np.nan), np.full(T, np.nan)
    n_iter = np.full(T, -1, dtype=np.int64)
    status, fail_step, fail_reason = STATUS_OK, -1, ""
    R, nu = ref.R[0].copy(), np.zeros(model.n_rot)
    f_prev = np.zeros((N, 2, 3))  # previous solution's forces, shifted by one stage (O)
    p_A_W = p_support_W[0]
    for k in range(T):
        X_WO[k, :3, :3] = R
        X_WO[k, :3, 3] = p_A_W - R @ model.p_A_O
        X_WO[k, 3] = (0.0, 0.0, 0.0, 1.0)
        delta0 = _log_so3(R @ ref.R[k].T)
        err[k] = np.sqrt(delta0.dot(delta0))  # np.linalg.norm's own formula
        omega_W[k] = R @ model.P_O @ nu if lay.edge else nu  # nu is omega_W itself about a vertex
        st, z, n_iter[k], solve_time[k], U, (F_u, F_c, e_s) = qp.solve(k, R, nu, delta0, f_prev)
        if st != piqp.PIQP_SOLVED:
            status, fail_step, fail_reason = STATUS_INFEASIBLE, k, str(st).split(".")[-1]
            break
        u = np.einsum("nij,j->ni", U, z).reshape(N, 2, 3)
        f_O[k] = u[0]
        f_sup[k] = F_u @ u[0].reshape(6) + F_c + (z[6 * lay.nk] * e_s if lay.edge else 0.0)  # Newton-Euler
        f_prev[:-1] = u[1:]  # linearise the next step about this plan
        f_prev[-1] = u[-1]
        if k + 1 < T:
            R, nu = integrate_rotation(model, R, nu, u[0], dt=params.dt)
    f_W = np.einsum("tij,tkj->tki", X_WO[:, :3, :3], f_O)
    p_eef = se3.transform_points(X_WO[:, None], model.r_eef_O[None] + model.p_A_O)
    return MPCResult(t=t, X_WO=X_WO, omega_W=omega_W, X_WO_ref=X_ref, f_eef_W=f_W, f_eef_O=f_O, p_eef_W=p_eef,
                     contact_mask=mask, f_table_W=f_sup.sum(axis=1), f_support_W=f_sup, tracking_error=err,
                     pyramid_eef_O=H_eef[:, :6].copy(), pyramid_table_W=H_table, n_iter=n_iter,
                     status=status, fail_step=fail_step, fail_reason=fail_reason,
                     timings=MPCTimings(solve_time_s=solve_time, total_s=time.perf_counter() - t_start))
