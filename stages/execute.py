"""Execution in physics (DESIGN.md, Execution; paper §6): a planned trajectory run in PyBullet.

The world is the scene's table (a box from the floor to the top at z = 0), its obstacles, the robot
from its URDF on its base pose (fixed base; its cylinders loaded as exact cylinders,
``URDF_USE_IMPLICIT_CYLINDER``: PyBullet's default convex-mesh cylinder with its 1 mm margin makes the
8 mm sticks 1 mm fatter than the URDF and the planner say) and the object as a free rigid body. The robot follows
the plan with **compliance at the ball** (notes/pybullet-pivoting.md: stiff position control slides
the pivot vertex or lifts the object); the object moves only through its contacts with the balls and
the table: it is placed once at the plan's first pose and never reset, teleported or constrained.

Trajectory table (input)
------------------------
A struct of arrays, one row per control step, rows ``Params.dt`` or a whole multiple of it apart (the
MPC stage writes it as ``trajectories.parquet``; :data:`TRAJECTORY_FIELDS` lists the columns with
units): ``t`` (s), ``primitive`` (int), ``kind`` ("pivot", "tumble", "transit", "hold"), the planned
object pose ``x y z qx qy qz qw`` (W), the planned ball centres ``lx ly lz`` and ``rx ry rz`` (W),
the planned contact flags ``left_contact``, ``right_contact``, the planned ball forces on the object
``flx fly flz`` and ``frx fry frz`` (N, W) and the planned joint angles ``q_left``, ``q_right``
``(T, n)`` (rad; a list column of length-n arrays is accepted too).

Controller (every physics step)
-------------------------------
Both arms run in ``TORQUE_CONTROL`` (their velocity motors disabled) with an operational-space
impedance of the ball's centre (``Params.task = "position"``, 3 task coordinates) and the planned
joints as a posture in its null space::

    tau = J^T W + N (Kq (q* - q) + Dq (q*' - q')) + h(q, q')
    W   = K_eff e + D e',   e = x* - x,   W += w F_plan,   |W| <= F_clip
    F_clip = max(F_c - g max(F_sensed - F_c, 0), F_c / 2),   F_c = (1 - force_margin) F_max

``J`` is the 3 x n Jacobian of the ball centre, ``h`` gravity and Coriolis torques
(``calculateInverseDynamics``), ``N = I - J^T Jbar^T`` the dynamically consistent null-space
projector (``Jbar = M^-1 J^T Lam``, ``Lam = (J M^-1 J^T)^-1``, ``M`` from ``calculateMassMatrix``), so
the joint PD towards the planned joints only uses the arm's redundancy, which holds the ball's
orientation (the planned joints' orientation) too. ``K_eff`` and ``D`` come from the desired
``K = kp I`` mode by mode (:func:`_modal_gains`): every mode of ``(K, Lam)`` is damped at
``damping_ratio`` (the notes' ``D ~ 1.4 sqrt(K m)``) and modes faster than ``0.5 / dt`` rad/s are
softened to that frequency: torques computed once per step from the state at its start cannot hold
them stiffly (fixed gains diverge within 0.25 s). The posture gains ``Kq, Dq`` are modal in the same
way, for ``kq I`` against the arm's mass matrix ``M``: a fixed joint damping (formerly 2 N m s/rad)
is an explicit-step instability on the light wrist joints, which the null space of a 3-D task
contains. With the default gains the translational modes keep ``kp`` = 5,000 N/m.

``task = "pose"`` adds the ball's orientation to the task (6 coordinates, ``e = [x* - x ;
log(R* R^T)]``, ``K = diag(kp, kp, kp, kr, kr, kr)``; the null space is then the elbow's self-motion
alone). It is not the default: near the wrist singularity (the SDA5F's joint 6 near 0, joints 5 and
7 aligned) the 6-D task is nearly singular, and the joint motion along its weak direction counts as
task, so the null-space posture cannot hold it while the orientation stiffness barely does: on
Exp. 1 the left arm's joints 5 and 7 ran 1.1 rad from the plan and its elbow (link 3) hit the table
(0.27-0.38 rad on the same pivot with continuous plan joints, against 0.07 rad with the 3-D task).
Joint torques are clipped to the URDF efforts.

Where the plan has both balls in contact, ``x*`` is pushed ``w_l w_r c * squeeze`` toward the other
ball (``kp * squeeze`` = 25 N, the notes' 20-30 N; ``c`` how far the two normals oppose,
:func:`_squeeze_weights`: a ball alone must not push; along the line between the balls, the grasp's
internal force, :func:`_squeeze_lines`, not along each contact normal, which on a curved object's
contact pair lifted the duck off its pivot vertex) and ``F_plan`` is fed forward; ``w``
rises from 0 to 1 over ``Params.ramp_time`` after the flag turns on and falls back before it turns
off (minimum-jerk), so contacts are made and broken smoothly. The contact normal is the direction from
the planned ball centre to the nearest point of the mesh in the planned object pose. A ball that
holds the object alone between primitives (USP, the other ball in transit; :func:`_hold_weights`)
aims at its planned contact moved by the object's drift from the plan, measured once when that hold
begins: the object then lies a few mm off its plan, out of reach of the feed-forward's offset. The torso joint
is held at the planning angle by a stiff position motor.

Force bound: ``F_max`` is the scene's ``robot.max_eef_force`` (50 N, the arm's payload), the bound
the planner's stability check and the MPC put on each ball (the MPC on the normal component; the
plan and the pivots' trajectories keep the force's magnitude within ``mpc_max_force``, 0.9 of it,
about the clip below). The commanded force,
feed-forward and squeeze included, is clipped below it (``force_margin``), and lowered further at the
next step by the excess of the ball's sensed force over that clip (``force_feedback``: the outer loop
of a force limiter on the wrist sensor's reading, which contact transients would otherwise carry past
the bound); the squeeze is made
shallower where the planned force leaves it no room (:func:`_squeeze_depth`). The ball's measured
force on the object (normal plus friction) is judged against ``F_max`` itself.

Perception
----------
The controller reads the robot's own state (joint positions and velocities, hence the ball centres
and velocities) every step. The object's pose is the one input from outside the robot, read only
when a lone hold begins (above): an explicit perception model, the simulated pose ``perception_latency``
s old (0.1 s: a camera frame plus processing) with Gaussian noise of ``perception_noise`` (1 mm per
axis) and ``perception_noise_deg`` (0.5 deg about each axis), what a fiducial-marker tracker at 1 m
gives; drawn from the run's seed, so a run stays deterministic. No other ground truth reaches the
controller; the simulator's state is read otherwise only to log and judge the run.

Yaw servo
---------
A pivot vertex slides and the balls roll a little on the object, so a plan run open loop ends a few
mm and degrees off per pivot, and the errors add up over a gait. While the object stands tilted on its
vertex with both balls on it (:func:`_servo_rows`), an integral servo on the object's yaw turns both
balls' targets about the vertical through the perceived pivot vertex, from the perception model's
frames (``servo_period``, with its noise and latency; :class:`_YawServo`). It aims as a pivoting gait
would (:func:`_servo_aims`): on a pivot followed by another, at putting the next pivot's vertex on the
ray to where the plan has it, so that the next pivot, about the right place, turns the object back
to the planned yaw; on the last pivot before a tumble or the end, at the CoM and the yaw, weighed by
the success tolerances. A vertex that slid cannot be moved back by a turn; the gait carries what is
left to the next pivot.

Release and success
-------------------
A robot's run ends with its hands off the object: :func:`with_release` appends the release (the
forces ramp out, the balls back off along their contact normals) and ``settle_time`` s of waiting.
``success`` needs every criterion, each a field of the metrics (``failures`` lists the codes of
:data:`FAILURES` that fail): not ``fell``, no ``collision``, ``within_force_bound``, ``released``
(no ball touches at the end), ``retreated`` (each ball at least ``retreat_clearance`` from the
object), ``tilt_ok`` (up axis within ``success_tilt_deg`` of the goal's: the right face down, flat),
``at_rest`` (still for at least ``settle_time`` since the release, lowest point on the table),
``position_ok`` and ``yaw_ok`` (CoM projection and yaw to the goal at the end of the run).

Ball rotation (notes: a ball that only translates turns the object ``(L + 2r) / L`` times the
command). With sticking friction the ball's material point at the contact moves with the object's,
so the centre's velocity relative to the object's point it was planned on is
``(omega_o - omega_ball) x r n`` (``n`` the inward normal). By default (``ball_orientation = "plan"``)
the ball keeps the orientation of the planned joints (position-only IK) and its target is shifted by
that integral, accumulated in the object frame over each contact with the measured ball angular
velocity and faded out after the contact (``unwind_time``): the ball rolls on the object by exactly
what its rotation requires (up to 12 mm of shift on the test pivot, whose planned joints turn the
left ball 11 deg one way while the object yaws 15 deg the other). Measured on that piano pivot:
0.2-0.9 mm / < 0.05 deg final error, against 3.7-5.5 mm / 1.6-2.0 deg without the shift (the notes'
effect; the spread is round-off: the contacts amplify it, every variant is deterministic).
``ball_orientation = "object"`` instead turns the ball with the object over each contact
(``R*(t) = R_WO(t) R_WO(t_on)^T R*(t_on)``, unwound after); from joints planned without orientation
that takes the SDA5F's left arm 1.4-2.1 rad away from the planned joints and its wrist to within
0.2 rad of a limit (0.4-3 mm final error, the wrist torque sometimes saturating), so it is not the
default. A planner whose IK turned the
tool with the object would make the two modes agree.

Object body
-----------
Mass, CoM ``com_O`` and inertia ``inertia_O`` (about the CoM, O axes) are the caller's (the scene's
mass, the mesh's inertia). The PyBullet base frame is the principal frame P of the inertia (origin at
the CoM, axes the eigenvectors, right-handed): ``localInertiaDiagonal`` is then the eigenvalues, set
together with ``mass=`` (``changeDynamics`` with the diagonal alone zeroes a body's mass). Poses
reported in O are ``X_WO = X_WP X_PO``. The collision shape is a compound of convex hulls that
follows the mesh exactly where the mesh is a union of convex pieces (see :func:`decompose_convex`)
and within a few mm of its surface elsewhere (CoACD, :func:`_coacd_parts`);
a mesh of more than ``stages.simplify.COLLISION_MAX_FACES`` triangles is simplified first, with its
error bound in the metrics (:func:`stages.simplify.collision_mesh`). The pieces are cached as an OBJ
(one object per hull) keyed by the mesh's sha256; the hulls' collision margin is
``Params.object_margin`` (Bullet's default of 1 mm would float the object 1 mm).

Friction: Bullet multiplies the two bodies' coefficients, so the table, the obstacles and every
robot link get 1 and the object the scene's ``object.friction`` (the object/table and object/ball
coefficient); ``table.friction`` is therefore not used here. The object's contacts use Bullet's friction
anchors: without them a resting object creeps (0.007 deg/s of yaw on its four feet), with them it
stays put (the pivot's slip, 0.5-1.3 mm, is the same either way).

Log and metrics
---------------
The log has one entry per trajectory row, the release's rows (kind ``"release"``) included
(:data:`LOG_FIELDS`), sampled after the row's physics
steps (the controller itself runs every step, targets interpolated between rows): the object pose
``x..qw`` and the planned one ``plan_x..plan_qw``; ``com_error`` (m, CoM distance), ``rot_error``
(rad, rotation angle) and ``tilt_error`` (rad, angle between the actual and planned up axes) from the
plan; ``pivot_x/y/z`` and ``pivot_slip`` (the support vertex, below) and ``lowest_z`` (lowest hull
vertex, m); per ball the magnitude of its force on the object, normal plus friction,
``left_force``/``right_force`` (N) and
whether it touches, ``left_touch``/``right_touch`` (``getContactPoints`` between ball link and
object); ``table_force`` (N); ``left_ball_error``/``right_ball_error`` (m, ball centre from its
planned position, which includes the squeeze and the rolling shift); ``joint_error`` (rad, largest
over both arms); ``penetration`` (m, deepest contact of the object); ``torque_saturated``; and the
measured joints ``q_left``/``q_right`` ``(T, n)``. The support vertex of a stretch of rows with the
same ``primitive`` and ``kind`` is the hull vertex that the plan keeps most nearly fixed on the table
(the pivot vertex of a pivot, an end of a tumble's edge); its slip is its horizontal displacement since
the stretch began. A tumble turns about an edge, so its ``pivot_slip`` is the edge's: the larger
slip of the edge's two ends (``pivot_x/y/z`` stay the first end). ``support_rotation_slip`` (rad) is
the rotation the object made since its stretch began that the plan did not make (a pivot's planned
turn is not slip; a hold's or a regrasp's turn is). Collisions (robot-table,
robot-obstacle, robot-object other than the balls, object-obstacle) are checked at every physics step.
Metrics are deterministic (same inputs and seed give the same numbers, also across processes);
wall-clock figures live in ``Execution.timings`` and must stay out of artifacts.

The convex-decomposition cache is the only file this module writes: a build product keyed by
content, not an artifact.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import math
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pybullet as p
import trimesh
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation, Slerp
from trimesh.intersections import slice_faces_plane

from stages import artifacts, provenance, se3, stagelog
from stages.analyze import load_mesh
from stages.artifacts import Field, atomic_path
from stages.errors import InputError, about
from stages.robot import load_robot
from stages.scene import load_scene
from stages.simplify import collision_mesh

#: Kinds of trajectory rows.
KINDS = ("pivot", "tumble", "transit", "hold")

#: Columns of the trajectory table with their units and frames (``q_left``/``q_right`` are (T, n)).
TRAJECTORY_FIELDS = [
    Field("t", "s"), Field("primitive", "id"), Field("kind"),
    *[Field(c, "m" if c in "xyz" else "1", "W") for c in se3.POSE_COLUMNS],
    *[Field(c, "m", "W") for c in ("lx", "ly", "lz", "rx", "ry", "rz")],
    Field("left_contact"), Field("right_contact"),
    *[Field(c, "N", "W") for c in ("flx", "fly", "flz", "frx", "fry", "frz")],
    Field("q_left", "rad"), Field("q_right", "rad"),
]

#: Entries of ``Execution.log`` (one value per trajectory row) with their units and frames.
LOG_FIELDS = [
    Field("t", "s"), Field("primitive", "id"), Field("kind"),
    *[Field(c, "m" if c in "xyz" else "1", "W") for c in se3.POSE_COLUMNS],
    *[Field("plan_" + c, "m" if c in "xyz" else "1", "W") for c in se3.POSE_COLUMNS],
    Field("com_error", "m"), Field("rot_error", "rad"), Field("tilt_error", "rad"),
    Field("pivot_x", "m", "W"), Field("pivot_y", "m", "W"), Field("pivot_z", "m", "W"),
    Field("pivot_slip", "m"), Field("support_rotation_slip", "rad"), Field("lowest_z", "m", "W"),
    Field("left_force", "N"), Field("right_force", "N"), Field("left_touch"), Field("right_touch"),
    Field("table_force", "N"),
    Field("left_ball_error", "m"), Field("right_ball_error", "m"), Field("joint_error", "rad"),
    Field("penetration", "m"), Field("torque_saturated"), Field("q_left", "rad"), Field("q_right", "rad"),
]

#: Version of :func:`convex_parts` (its cuts and its fallback); part of the cache key.
DECOMPOSITION_VERSION = 3

@dataclass(frozen=True)
class Params:
    """Simulation and controller settings (SI units; degrees only where the name says so).

    dt : physics step (s); trajectory rows must be a whole multiple of it apart.
    solver_iterations : Bullet's constraint-solver iterations per step (notes: barely matters).
    task : "position": the impedance holds the ball centre (3 task coordinates) and the planned
        joints, the ball's orientation with them, are a posture in its null space; "pose": the ball's
        orientation is a task too (6 coordinates, stiffness ``kr``). See the module docstring.
    kp : translational stiffness at the ball (N/m; notes: 3,000-10,000 N/m).
    kr : rotational stiffness of the ball orientation (N m/rad; task "pose").
    damping_ratio : damping of every task and posture mode (notes: D ~ 1.4 sqrt(K m), i.e. 0.7).
    max_frequency : task and posture modes stiffer than this natural frequency (rad/s) are softened
        to it (0: ``0.5 / dt``), see :func:`_modal_gains`.
    kq : null-space joint stiffness (N m/rad) towards the planned joints, damped mode by mode.
    kj, dj : joint tracking gains of free motion (1/s^2, 1/s: computed torque, 30 rad/s, damping 0.7).
    squeeze : depth (m) of the contact target inside the surface; ``kp * squeeze`` is the squeeze force.
    squeeze_share : the squeeze is made shallower where the planned force plus ``kp * squeeze`` would
        exceed this share of the force bound (:func:`_squeeze_depth`; the rest is the feedback's).
    ramp_time : time (s) over which a contact's squeeze and force feed-forward rise and fall.
    ball_orientation : "plan": the ball keeps the orientation of the planned joints and its target
        is corrected for rolling (module docstring); "object" (task "pose" only): the ball's
        orientation follows the object's rotation over each contact.
    roll_compensation : shift each ball's target by the rolling its rotation relative to the object
        causes (off: the notes' (L + 2r) / L over-rotation returns, for measuring it).
    unwind_time : longest time (s) over which, after a contact ends, the rolling correction fades
        (and, with ``ball_orientation = "object"``, the orientation returns to the planned joints').
    force_limit : bound (N) on each ball's commanded Cartesian force, feed-forward included; 0: the
        scene's ``robot.max_eef_force``, the bound the planner's stability check and the MPC put on
        each ball (the arm's payload), so that execution does not push harder than the plan assumed.
    force_margin : the commanded force is clipped at ``(1 - force_margin)`` times the bound: the
        measured force (averaged over ``force_window``) overshoots a command at the clip by up to
        about 9 % (contact dynamics), which the margin must cover.
    force_tolerance : the measured ball force (normal plus friction, on the object, averaged over
        ``force_window``) may exceed the bound by this fraction before ``within_force_bound`` fails.
    force_window : the measured ball force is judged averaged over this time (s): a wrist force
        sensor's bandwidth (50 Hz); single solver steps spike (up to 64 N on Exp. 2, where the
        20 ms average stays within 2 % of the bound). ``max_ball_force_step`` keeps the raw peak.
    force_feedback : gain of the force limiter's outer loop: where a ball's sensed force (the wrist
        sensor's reading at the last step) exceeds the commanded clip, the next step's clip is lowered
        by this times the excess (down to half), so that contact transients do not carry the measured
        force past the bound; 0: the clip alone.
    clip_effort : clip joint torques to the URDF's ``effort`` limits.
    model_period : physics steps between refreshes of the arms' dynamics model: Jacobian, mass
        matrix, task inertia, task gains and null-space map (60 Hz by default; the arms turn
        < 0.01 rad in that time); the posture gains, which depend on the mass matrix alone, every 4
        refreshes. Gravity, Coriolis and the errors are refreshed every step.
    object_margin : Bullet collision margin of the object's hulls (m).
    fall_tilt_deg : the object fell when its up axis deviates from the plan's by more than this (deg;
        in a tumble from the nearest pose of its planned roll, :func:`path_tilt`).
    fall_distance : ... or when its CoM is off the table where the plan's is more than ``success_pos``
        inside its edge, or this far (m) from the plan's overhanging one (USP) or on the edge
        (:func:`off_the_table`).
    success_pos, success_yaw_deg : final CoM-projection (m) and yaw (deg) tolerances for ``success``,
        measured ``settle_time`` after the release.
    success_tilt_deg : final tilt tolerance (deg): the angle between the object's up axis and the
        goal placement's (the right face down, flat on the table).
    release : end the run as a robot would: when the plan ends with a ball on the object, the balls
        let go (the squeeze and the feed-forward ramp out over ``ramp_time`` with the object still)
        and back off ``retreat_distance`` (m) along the outward contact normal in ``retreat_time``
        (s, joints by position IK); then the robot waits ``settle_time`` (s) so that the object's
        rest can be judged (:func:`with_release`).
    retreat_clearance : a ball has retreated when its surface is at least this far (m) from the
        object at the end of the run.
    rest_drift, rest_rotation_deg : the object is at rest when, from the release to the end of the
        run (at least ``settle_time``), its CoM moved at most ``rest_drift`` (m) and it turned at most
        ``rest_rotation_deg`` (deg), and its lowest point lies on the table (within 2 mm).
    seed : 0 runs the nominal physics; N > 0 perturbs it, drawn from ``default_rng(N)``: friction by
        +-friction_jitter (relative), the CoM by +-com_jitter (m per axis), the principal inertias by
        +-inertia_jitter and the mass by +-mass_jitter (relative), the object's initial position by
        +-pose_jitter (m along x and y), uniformly; the plan keeps the nominal values, as a robot does
        not know the true ones. The seed also draws the perception noise (seed 0 included).
    perception_noise, perception_noise_deg, perception_latency : the one input from outside the
        robot (module docstring, Perception): the object's pose, measured with Gaussian noise of
        this standard deviation per axis (m; deg about each axis) and this latency (s).
    servo_gain, servo_period, servo_min_tilt, servo_max : the yaw servo on a pivot
        (module docstring, Yaw servo): its rate (1/s), the perception frame period (s), the
        planned tilt, as a fraction of the pivot's largest, above which it acts, and the largest
        shift (m) of a ball's target it may build up; ``servo_gain = 0`` turns it off.
    cache_dir : folder of the convex-decomposition cache ("" = ``<system temp>/pivot-convex``).
    width, height : rendered frames (pixels); the camera is chosen from the scene (:func:`scene_camera`).
    """

    dt: float = 1.0 / 240.0
    solver_iterations: int = 50
    kp: float = 5000.0
    kr: float = 30.0
    damping_ratio: float = 0.7
    max_frequency: float = 0.0
    kq: float = 20.0
    kj: float = 900.0
    dj: float = 42.0
    squeeze: float = 0.005
    squeeze_share: float = 0.9
    ramp_time: float = 0.3
    unwind_time: float = 2.0
    ball_orientation: str = "plan"
    task: str = "position"
    roll_compensation: bool = True
    force_limit: float = 0.0
    force_margin: float = 0.11
    force_tolerance: float = 0.0
    force_window: float = 0.02
    force_feedback: float = 1.0
    clip_effort: bool = True
    model_period: int = 4
    object_margin: float = 1e-4
    fall_tilt_deg: float = 30.0
    fall_distance: float = 0.05
    success_pos: float = 0.01
    success_yaw_deg: float = 2.0
    success_tilt_deg: float = 2.0
    release: bool = True
    retreat_distance: float = 0.03
    retreat_time: float = 1.0
    settle_time: float = 2.0
    retreat_clearance: float = 0.01
    rest_drift: float = 0.002
    rest_rotation_deg: float = 0.5
    seed: int = 0
    friction_jitter: float = 0.2
    com_jitter: float = 0.01
    inertia_jitter: float = 0.1
    mass_jitter: float = 0.15
    pose_jitter: float = 0.003
    perception_noise: float = 0.001
    perception_noise_deg: float = 0.5
    perception_latency: float = 0.1
    servo_gain: float = 2.0
    servo_period: float = 1.0 / 30.0
    servo_min_tilt: float = 0.5
    servo_max: float = 0.03
    cache_dir: str = ""
    width: int = 480
    height: int = 360


@dataclass(frozen=True, eq=False)
class Execution:
    """Result of :func:`simulate`.

    log : dict of ``(T,)`` arrays, one entry per trajectory row (:data:`LOG_FIELDS`).
    metrics : JSON-able dict of deterministic figures (see :func:`simulate`).
    frames : ``(height, width, 3)`` uint8 RGB images spread over the run.
    timings : wall-clock figures (s, and ``sim_speed`` in simulated s per wall s); never in artifacts.
    """

    log: dict[str, np.ndarray]
    metrics: dict
    frames: list[np.ndarray] = field(default_factory=list)
    timings: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------
# Trajectory table


@dataclass(frozen=True, eq=False)
class Plan:
    """A validated trajectory table as arrays (:func:`check_trajectory`); W frame, SI units."""

    t: np.ndarray  # (T,) s
    primitive: np.ndarray  # (T,) int
    kind: np.ndarray  # (T,) str
    X_WO: np.ndarray  # (T, 4, 4)
    p_ball: np.ndarray  # (T, 2, 3) m, W
    contact: np.ndarray  # (T, 2) bool
    f_ball: np.ndarray  # (T, 2, 3) N, W
    q: np.ndarray  # (T, 2, n) rad
    substeps: int  # physics steps per row


def check_trajectory(traj, dt: float, dof: int | None = None) -> Plan:
    """Validate a trajectory table (mapping of columns) and return it as arrays.

    Raises :class:`~stages.errors.InputError` naming the column for a missing or non-finite column,
    wrong lengths, unknown kinds, fewer than two rows, or rows not a whole multiple of ``dt`` apart.
    """

    def col(name):
        try:
            return traj[name]
        except (KeyError, IndexError):
            raise InputError(f"trajectory: missing column {name!r}") from None

    t = np.asarray(col("t"), dtype=float)
    T = len(t)
    if t.ndim != 1 or T < 2:
        raise InputError(f"trajectory: need at least two rows, got {T}")

    def num(name, width=None):
        a = col(name)
        if width is not None and np.asarray(a).dtype == object:  # a list column from Parquet
            a = np.stack([np.asarray(r, dtype=float) for r in a]) if len(a) else np.zeros((0, width))
        a = np.asarray(a, dtype=float)
        want = (T,) if width is None else (T, width if width > 0 else a.shape[-1])
        if a.shape != want:
            raise InputError(f"trajectory: column {name!r} must have shape {want}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"trajectory: column {name!r} has non-finite values")
        return a

    num("t")
    steps = np.diff(t) / dt
    k = int(round(steps[0]))
    if k < 1 or np.abs(steps - k).max() > 1e-6:
        raise InputError(f"trajectory: rows must be a constant whole multiple of dt = {dt} s apart")
    kind = np.asarray(col("kind")).astype(str)
    if kind.shape != (T,) or not np.all(np.isin(kind, KINDS)):
        bad = sorted(set(kind.tolist()) - set(KINDS)) if kind.ndim == 1 else kind.shape
        raise InputError(f"trajectory: column 'kind' must hold {KINDS}, got {bad}")
    pose = {c: num(c) for c in se3.POSE_COLUMNS}
    quat = np.stack([pose[c] for c in se3.POSE_COLUMNS[3:]], axis=1)
    if np.abs(np.linalg.norm(quat, axis=1) - 1.0).max() > 1e-6:
        raise InputError("trajectory: the object quaternions (qx, qy, qz, qw) must be unit")
    q_left = num("q_left", dof or -1)
    q_right = num("q_right", q_left.shape[1])
    contact = np.stack([np.asarray(col("left_contact")), np.asarray(col("right_contact"))], axis=1)
    if contact.shape != (T, 2):
        raise InputError("trajectory: contact flags must be (T,) each")
    return Plan(
        t=t, primitive=num("primitive").astype(int), kind=kind, X_WO=se3.matrix_from_columns(pose),
        p_ball=np.stack([np.stack([num(c) for c in ("lx", "ly", "lz")], axis=1),
                         np.stack([num(c) for c in ("rx", "ry", "rz")], axis=1)], axis=1),
        contact=contact.astype(bool),
        f_ball=np.stack([np.stack([num(c) for c in ("flx", "fly", "flz")], axis=1),
                         np.stack([num(c) for c in ("frx", "fry", "frz")], axis=1)], axis=1),
        q=np.stack([q_left, q_right], axis=1), substeps=k)


# ----------------------------------------------------------------------------------------------------
# Convex decomposition


def _hull_volume(V: np.ndarray) -> float:
    try:
        return float(ConvexHull(V).volume)
    except (QhullError, ValueError):  # flat or too few points
        return 0.0


def _unsupported_faces(V: np.ndarray, F: np.ndarray, tol: float) -> np.ndarray:
    """Faces ``(k, 3)`` whose plane has a vertex of the piece more than ``tol`` (m) outside it.

    Slivers (twice the area below 1e-8 m^2) are skipped: their normals are noise. A linear function
    is largest over ``V`` at a vertex of its convex hull, so only the hull's vertices are measured,
    ``chunk`` faces at a time: memory stays bounded (a 200k-triangle mesh asked for a 109 GiB
    vertices x faces matrix).
    """
    a = V[F[:, 0]]
    n = np.cross(V[F[:, 1]] - a, V[F[:, 2]] - a)
    ln = np.linalg.norm(n, axis=1)
    ok = ln > 2e-8
    n, a, F = n[ok] / ln[ok, None], a[ok], F[ok]
    try:
        H = V[ConvexHull(V).vertices]
    except (QhullError, ValueError):  # flat or too few points: measure them all
        H = V
    d = np.einsum("ij,ij->i", a, n)
    chunk = max(1, 2**22 // max(len(H), 1))  # 32 MiB of float64 per block
    out = np.concatenate([(H @ n[s : s + chunk].T).max(axis=0, initial=-np.inf)
                          for s in range(0, len(F), chunk)] or [np.zeros(0)]) - d
    return F[out > tol]


def _cut(V, F, ax: int, v: float):
    """The two halves ``[(V+, F+), (V-, F-)]`` of an open surface cut by the plane ``x[ax] = v``."""
    n = np.zeros(3)
    n[ax] = 1.0
    return [slice_faces_plane(V, F, s * n, n * v)[:2] for s in (1.0, -1.0)]


def decompose_convex(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-6, max_depth: int = 24,
                     max_parts: int = 64) -> list[np.ndarray]:
    """Convex pieces of a watertight mesh, found by cutting it with axis-aligned planes.

    A piece is the solid inside an axis-aligned cell; it is accepted as convex when every mesh face
    in the cell supports the piece (no vertex more than ``tol`` m outside its plane). Otherwise the
    cell is cut: preferably by the plane holding the longest total length of concave mesh edges (a
    union of boxes and prisms, like the toy piano, falls apart along its seams), else through a
    vertex of an offending face, choosing the cut that leaves the least total hull volume. The
    vertices of a piece are those of the cut surface plus the cell's corners that lie inside the
    solid (the corners of the caps, which the open surface does not hold). Pieces stay approximate
    (their hull, which is larger) below ``max_depth`` cuts or once ``max_parts`` pieces exist; an
    organic mesh with no flat seams is cut at a few evenly spread coordinates per axis, so it ends
    as ``max_parts`` hulls after a few seconds.

    Parameters
    ----------
    vertices : (n, 3) float, m.
    faces : (m, 3) int, outward-oriented triangles of a watertight mesh.

    Returns
    -------
    list of (k_i, 3) float: the vertices of each convex piece's hull, in a deterministic order.
    """
    solid = trimesh.Trimesh(np.asarray(vertices, dtype=float), np.asarray(faces, dtype=int), process=True)
    out: list[np.ndarray] = []
    stack = [(solid.vertices, solid.faces, np.full(3, -np.inf), np.full(3, np.inf), 0)]
    while stack:
        V, F, lo, hi, depth = stack.pop()
        bad = _unsupported_faces(V, F, tol)
        cut = None
        if len(bad) and depth < max_depth and len(out) + len(stack) + 2 <= max_parts:
            cut = _choose_cut(V, F, bad)
        if cut is None:
            axes = [[c for c in (lo[k], hi[k]) if np.isfinite(c)] for k in range(3)]
            C = np.array(list(itertools.product(*axes))).reshape(-1, 3)
            if len(C):
                C = C[solid.contains(C)]
            P = np.concatenate([V, C])
            if _hull_volume(P) > 1e-12:
                out.append(P[ConvexHull(P).vertices])
            continue
        ax, v, halves = cut
        for sign, (Vh, Fh) in zip((1.0, -1.0), halves, strict=True):
            piece = trimesh.Trimesh(Vh, Fh, process=True)
            lo2, hi2 = lo.copy(), hi.copy()
            if sign > 0:
                lo2[ax] = v
            else:
                hi2[ax] = v
            stack.append((piece.vertices, piece.faces, lo2, hi2, depth + 1))
    return out


def _choose_cut(V, F, bad, max_candidates: int = 8):
    """``(axis, value, halves)`` of the next cut of a non-convex piece, or None."""
    inside_lo, inside_hi = V.min(axis=0) + 1e-6, V.max(axis=0) - 1e-6
    piece = trimesh.Trimesh(V, F, process=False)
    if len(piece.face_adjacency):
        E = piece.face_adjacency_edges[piece.face_adjacency_projections > 1e-7]  # concave edges
        a, b = V[E[:, 0]], V[E[:, 1]]
        length = np.linalg.norm(b - a, axis=1)
        totals: dict[tuple[int, float], float] = {}
        for ax in range(3):
            flat = np.abs(a[:, ax] - b[:, ax]) < 1e-9  # the edge lies in a plane x[ax] = const
            for v, ln in zip(np.round(a[flat, ax], 9).tolist(), length[flat].tolist(), strict=True):
                totals[(ax, v)] = totals.get((ax, v), 0.0) + ln
        for (ax, v), _ in sorted(totals.items(), key=lambda kv: (-round(kv[1], 9), kv[0])):
            if inside_lo[ax] < v < inside_hi[ax]:
                halves = _cut(V, F, ax, v)
                if all(len(h[1]) for h in halves):
                    return ax, v, halves
    best = None
    W = V[np.unique(bad)]
    for ax in range(3):
        cand = np.unique(np.round(W[:, ax], 9))
        cand = cand[(cand > inside_lo[ax]) & (cand < inside_hi[ax])]
        if len(cand) > max_candidates:  # an organic mesh: try evenly spread coordinates only
            cand = cand[np.round(np.linspace(0, len(cand) - 1, max_candidates)).astype(int)]
        for v in cand.tolist():
            halves = _cut(V, F, ax, v)
            if not all(len(h[1]) for h in halves):
                continue
            score = sum(_hull_volume(h[0]) for h in halves)
            if best is None or score < best[0] - 1e-15:
                best = (score, ax, v, halves)
    return None if best is None else best[1:]


def _write_parts_obj(path: Path, parts: list[np.ndarray]) -> None:
    lines, offset = [f"# convex decomposition v{DECOMPOSITION_VERSION} (stages.execute), metres, frame O"], 1
    for i, P in enumerate(parts):
        hull = ConvexHull(P)
        lines.append(f"o hull_{i}")
        lines += [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in P]
        for s, eq in zip(hull.simplices, hull.equations, strict=True):
            a, b, c = P[s]
            if np.dot(np.cross(b - a, c - a), eq[:3]) < 0:  # outward winding
                s = s[::-1]
            lines.append("f " + " ".join(str(int(j) + offset) for j in s))
        offset += len(P)
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _read_parts_obj(path: Path) -> list[np.ndarray]:
    parts: list[list[list[float]]] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("o "):
            parts.append([])
        elif line.startswith("v ") and parts:
            parts[-1].append([float(c) for c in line.split()[1:4]])
    return [np.asarray(P) for P in parts]


def convex_parts(mesh: trimesh.Trimesh, cache_dir: str | Path = "",
                 max_excess: float = 0.02) -> tuple[list[np.ndarray], Path, bool]:
    """Convex pieces of ``mesh`` (:func:`decompose_convex`), cached as an OBJ file.

    When the pieces' hulls exceed the mesh's volume by more than ``max_excess`` (relative; an organic
    shape that axis-aligned cuts do not resolve, such as the bunny: +64 %), CoACD's pieces are used
    instead (:func:`_coacd_parts`).

    The file is ``<cache_dir>/<sha256 of the mesh arrays>-v<version>.obj`` (one ``o`` object per
    hull, frame O), written atomically; ``cache_dir`` "" means ``<system temp>/pivot-convex``.
    Returns the pieces ``[(k_i, 3)]``, the file's path and whether it was already there.
    """
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    folder = Path(cache_dir) if cache_dir else Path(tempfile.gettempdir()) / "pivot-convex"
    path = folder / f"{h.hexdigest()}-v{DECOMPOSITION_VERSION}.obj"
    if path.is_file():
        parts = _read_parts_obj(path)
        if parts and all(len(P) >= 4 for P in parts):
            return parts, path, True
    parts = decompose_convex(mesh.vertices, mesh.faces)
    if not parts:
        raise InputError("object mesh: no convex pieces (is the mesh a closed volume?)")
    if sum(_hull_volume(P) for P in parts) > (1.0 + max_excess) * mesh.volume:
        parts = _coacd_parts(mesh)  # an organic shape: CoACD follows it where axis-aligned cuts do not
    _write_parts_obj(path, parts)
    return parts, path, False


def _coacd_parts(mesh: trimesh.Trimesh, concavity: float = 0.03) -> list[np.ndarray]:
    """Convex pieces from CoACD (Wei et al., SIGGRAPH 2022: cuts chosen by Monte-Carlo tree search
    until every piece's collision-aware concavity is below ``concavity``, relative to the mesh's size).

    The balls press on the planning mesh itself, so the pieces must not bulge past it where they
    touch: V-HACD's hulls bridge concave regions by centimetres. A closed, consistently wound mesh is
    cut as it is (remeshing first would shift its surface); seed 0 makes the pieces reproducible."""
    import coacd  # only organic meshes need it (it takes seconds to a minute; the result is cached)

    coacd.set_log_level("error")
    solid = mesh.is_watertight and mesh.is_winding_consistent
    with _quiet_stdout():
        out = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)),
                              threshold=concavity, preprocess_mode="off" if solid else "on", seed=0,
                              mcts_iterations=60, mcts_max_depth=2, mcts_nodes=10)
    parts = [np.asarray(V, dtype=float) for V, _ in out]
    return [P[ConvexHull(P).vertices] for P in parts if len(P) >= 4 and _hull_volume(P) > 1e-12]


@contextlib.contextmanager
def _quiet_stdout():
    """Silence C-level stdout (a native library printing its progress there)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


# ----------------------------------------------------------------------------------------------------
# Plan -> controller targets


#: ``kind`` of the rows :func:`with_release` appends (the execution's own, never in a trajectory table).
RELEASE = "release"


def with_release(plan: Plan, mesh: trimesh.Trimesh, robot, params: Params) -> Plan:
    """The plan followed by the robot letting go of the object and waiting (rows of kind ``"release"``).

    When the plan's last row has a ball on the object: a pause of ``ramp_time`` with the contact flags
    still on (the squeeze and the feed-forward ramp out, :func:`_contact_weights`, the object still),
    then each touching ball backs off ``retreat_distance`` (m) along :func:`retreat_direction`, the
    outward normal at its contact unless that leads into a concave corner (minimum jerk,
    ``retreat_time`` s; the joints by :meth:`Robot.ik_trajectory` from the last planned ones, so
    the joint tracking that takes over after the contact agrees with it; an arm
    whose IK fails stays where it is, and the run then fails ``released``). Then ``settle_time`` s
    more of the last state, over which the object's rest is judged. The planned object pose stays
    the plan's last; the primitive id is the last plus one. Rows keep the plan's spacing.
    """
    dt_row = float(plan.t[1] - plan.t[0])
    last = plan.contact[-1]
    n_hold = int(math.ceil(params.ramp_time / dt_row)) + 1 if last.any() else 0
    n_back = int(math.ceil(params.retreat_time / dt_row)) if last.any() else 0
    n = n_hold + n_back + int(math.ceil(params.settle_time / dt_row)) + 1
    p_ball, q = np.repeat(plan.p_ball[-1:], n, axis=0), np.repeat(plan.q[-1:], n, axis=0)
    contact, f = np.zeros((n, 2), dtype=bool), np.zeros((n, 2, 3))
    contact[:n_hold], f[:n_hold] = last, plan.f_ball[-1]
    if n_back:
        out = -_contact_normals(mesh, plan.X_WO[-1:], plan.p_ball[-1:], last[None])[0]  # (2, 3) outward
        s = _min_jerk(np.arange(1, n_back + 1) / n_back)[:, None]
        back = slice(n_hold, n_hold + n_back)
        for a, arm in enumerate(("left", "right")):
            if not last[a]:
                continue
            d = retreat_direction(mesh, plan.X_WO[-1], plan.p_ball[-1, a], out[a], params.retreat_distance)
            path = plan.p_ball[-1, a] + s * params.retreat_distance * d  # (n_back, 3)
            ik = robot.ik_trajectory(arm, path, plan.q[-1, a])
            if ik.ok.all():
                p_ball[back, a], q[back, a] = path, ik.q
                p_ball[n_hold + n_back:, a], q[n_hold + n_back:, a] = path[-1], ik.q[-1]
    return Plan(
        t=np.concatenate([plan.t, plan.t[-1] + dt_row * np.arange(1, n + 1)]),
        primitive=np.concatenate([plan.primitive, np.full(n, plan.primitive[-1] + 1)]),
        kind=np.concatenate([plan.kind, np.full(n, RELEASE)]),
        X_WO=np.concatenate([plan.X_WO, np.repeat(plan.X_WO[-1:], n, axis=0)]),
        p_ball=np.concatenate([plan.p_ball, p_ball]), contact=np.concatenate([plan.contact, contact]),
        f_ball=np.concatenate([plan.f_ball, f]), q=np.concatenate([plan.q, q]), substeps=plan.substeps)


def retreat_direction(mesh: trimesh.Trimesh, X_WO: np.ndarray, p_ball: np.ndarray, out: np.ndarray,
                      distance: float, gain: float = 0.8) -> np.ndarray:
    """Unit direction (W) in which a ball at ``p_ball (3,)`` (W) leaves the object at ``X_WO``.

    The outward contact normal ``out (3,)`` (W) first; in a concave corner (an L-block's inner
    corner) that normal points at the other wing, and a ball backed off along it ends a few mm from
    the object (the run then fails ``not_retreated``). So the first of: the normal, the normal
    tilted 45 deg up, straight up, the normal tilted 45 deg to either side, whose end point
    ``distance`` (m) away lies at least ``gain * distance`` farther from the mesh than the ball
    does; else the one that ends farthest (trimesh's closest-point query, in O)."""
    up = np.array([0.0, 0.0, 1.0])
    side = np.cross(up, out)
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-9 else np.array([1.0, 0.0, 0.0])
    cands = np.stack([out, out + up, up, out + side, out - side])
    cands /= np.linalg.norm(cands, axis=1, keepdims=True)
    pts = se3.transform_points(se3.invert(X_WO), np.vstack([p_ball, p_ball + distance * cands]))
    _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
    gained = dist[1:] - dist[0]
    good = np.flatnonzero(gained >= gain * distance)
    return cands[good[0] if len(good) else int(np.argmax(gained))]


def _min_jerk(s):
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` row ranges where ``flags (T,)`` is True."""
    d = np.diff(np.concatenate([[0], flags.astype(int), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def _contact_weights(t: np.ndarray, contact: np.ndarray, ramp: float) -> np.ndarray:
    """``(T, 2)`` weights in [0, 1]: 0 out of contact, rising and falling over ``ramp`` s inside."""
    w = np.zeros(contact.shape)
    for a in range(2):
        for s, e in _runs(contact[:, a]):
            t_off = t[e] if e < len(t) else np.inf
            up = (t[s:e] - t[s]) / ramp
            down = (t_off - t[s:e]) / ramp
            w[s:e, a] = _min_jerk(np.minimum(up, down))
    return w


def _squeeze_weights(weight: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``(T, 2)`` weights of the squeeze: an internal force of the two balls, so only while both hold
    (the product of their contact weights ``(T, 2)``) and as far as their inward normals ``(T, 2, 3)``
    oppose each other. A ball alone on the object (the other arm on its way in a regrasp) would push
    it across the table with the whole squeeze (on Exp. 1: 11 N against 13 N of table friction, the
    piano slid 1.5 mm and turned 0.5 deg at each regrasp); it carries only its planned force."""
    opposed = np.clip(-np.einsum("ti,ti->t", normals[:, 0], normals[:, 1]), 0.0, 1.0)
    w = weight[:, 0] * weight[:, 1] * opposed
    return np.stack([w, w], axis=1)


def _squeeze_lines(p_ball: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``(T, 2, 3)`` unit direction of each ball's squeeze: toward the other ball's centre
    ``p_ball (T, 2, 3)`` (m, W), the two-contact grasp's internal force (the grasp map's null space:
    equal and opposite along the line joining the contacts, so no net force or moment on the object),
    where the two inward ``normals`` (T, 2, 3) are not collinear (a curved surface's contact pair); the
    normal itself where the balls coincide."""
    d = p_ball[:, ::-1] - p_ball
    n = np.linalg.norm(d, axis=2, keepdims=True)
    return np.where(n > 1e-9, d / np.maximum(n, 1e-12), normals)


def _hold_weights(weight: np.ndarray, kind: np.ndarray, f_ball: np.ndarray) -> np.ndarray:
    """``(T, 2)`` weights of a ball holding the object alone between primitives (``kind`` transit or
    hold, the other ball off, a planned force ``f_ball (T, 2, 3)`` on it): its target is then moved
    by the object's drift from the plan measured when the lone hold begins (and held there, so the
    ball stays stiff against the object tipping further). The planned centre is where the ball
    touches the planned object; one that has drifted a few mm since (2.8 mm after a tumble into USP)
    lies beyond the reach of the feed-forward force's impedance offset (``|F| / kp``: 1.1 mm for
    5.6 N), so the ball never touched and the object tipped as the other ball let go."""
    between = np.isin(kind, ("transit", "hold"))[:, None]
    pressing = np.linalg.norm(f_ball, axis=2) > 1e-6
    return np.where(between & pressing, weight * (1.0 - weight[:, ::-1]), 0.0)


def _contact_normals(mesh: trimesh.Trimesh, X_WO: np.ndarray, p_ball: np.ndarray,
                     contact: np.ndarray) -> np.ndarray:
    """Inward unit normals ``(T, 2, 3)`` (W) at the planned contacts, zero out of contact."""
    n_W = np.zeros(p_ball.shape)
    rows, arms = np.nonzero(contact)
    if not len(rows):
        return n_W
    X_OW = se3.invert(X_WO[rows])
    p_O = se3.transform_points(X_OW, p_ball[rows, arms])
    c_O, dist, tri = trimesh.proximity.closest_point(mesh, p_O)
    n_O = -mesh.face_normals[tri]
    far = dist > 1e-3  # clearly outside: the direction to the nearest point (exact at edges, too)
    n_O[far] = (c_O[far] - p_O[far]) / dist[far, None]
    n_W[rows, arms] = se3.rotate_vectors(X_WO[rows], n_O)
    return n_W


def _rotation_targets(t, X_WO, R_plan, contact, unwind_time) -> np.ndarray:
    """Ball orientation targets ``(T, 2, 3, 3)``: carried by the object in contact, unwound outside."""
    T = len(t)
    R_tgt = np.zeros((T, 2, 3, 3))
    for a in range(2):
        on = contact[:, a]
        starts = np.flatnonzero(on & ~np.concatenate([[False], on[:-1]]))
        delta = np.eye(3)
        R_on = X_on = None
        rv_off, t_off, dur = np.zeros(3), 0.0, 1.0
        for i in range(T):
            if on[i]:
                if i == 0 or not on[i - 1]:
                    R_on, X_on = delta @ R_plan[i, a], X_WO[i, :3, :3]
                R_tgt[i, a] = X_WO[i, :3, :3] @ X_on.T @ R_on
                delta = R_tgt[i, a] @ R_plan[i, a].T
            else:
                if i > 0 and on[i - 1]:
                    rv_off, t_off = Rotation.from_matrix(delta).as_rotvec(), t[i]
                    nxt = starts[starts > i]
                    t_end = t[nxt[0]] if len(nxt) else t[-1]
                    dur = max(min(t_end - t_off, unwind_time), t[1] - t[0])
                if i > 0:
                    s = 1.0 - _min_jerk((t[i] - t_off) / dur)
                    delta = Rotation.from_rotvec(s * rv_off).as_matrix()
                R_tgt[i, a] = delta @ R_plan[i, a]
    return R_tgt


def _support_vertices(plan: Plan, hull_O: np.ndarray, edge_tol: float = 2e-3) -> tuple[np.ndarray, np.ndarray]:
    """Per row the support vertices ``(T, 2)`` (indices into ``hull_O``) and the row where their stretch
    began.

    A stretch is a run of rows with the same primitive and kind; its first vertex is the hull vertex
    the plan keeps most nearly fixed on the table (largest horizontal travel plus largest height):
    the pivot vertex of a pivot. A tumble turns about an edge: its second vertex is the one farthest
    from the first among those the plan keeps within ``edge_tol`` (m) as still, the edge's other end;
    elsewhere the second is the first.
    """
    T = len(plan.t)
    key = np.array([f"{p}|{k}" for p, k in zip(plan.primitive.tolist(), plan.kind.tolist(), strict=True)])
    change = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    vertex, start = np.zeros((T, 2), dtype=int), np.zeros(T, dtype=int)
    for s, e in zip(change.tolist(), np.concatenate([change[1:], [T]]).tolist(), strict=True):
        P = se3.transform_points(plan.X_WO[s:e, None], hull_O[None])  # (n, H, 3)
        travel = np.linalg.norm(P[:, :, :2] - P[:1, :, :2], axis=2).max(axis=0)
        score = travel + np.abs(P[:, :, 2]).max(axis=0)
        v = int(np.argmin(score))
        w = v
        if plan.kind[s] == "tumble":
            still = np.flatnonzero(score <= score[v] + edge_tol)
            w = int(still[np.argmax(np.linalg.norm(hull_O[still] - hull_O[v], axis=1))])
        vertex[s:e], start[s:e] = (v, w), s
    return vertex, start


def _contact_force(c) -> tuple[float, float, float]:
    """Force (N, W) of one ``getContactPoints`` row on body A: normal plus both friction components."""
    n, d1, d2, fn, f1, f2 = c[7], c[11], c[13], c[9], c[10], c[12]
    return (fn * n[0] + f1 * d1[0] + f2 * d2[0], fn * n[1] + f1 * d1[1] + f2 * d2[1],
            fn * n[2] + f1 * d1[2] + f2 * d2[2])


def _force_clip(f_sensed: list[float], f_command: float, gain: float) -> list[float]:
    """Each ball's clip (N) on its commanded Cartesian force for the next step: a force limiter's outer
    loop on the wrist sensor's reading ``f_sensed`` (N, this step): the command's clip ``f_command``
    lowered by ``gain`` times the sensed excess over it, never below half of it."""
    return [max(f_command - gain * max(f - f_command, 0.0), 0.5 * f_command) for f in f_sensed]


class _ForceMonitor:
    """Each ball's force on the object at every physics step against the bound ``f_bound`` (N).

    Records the raw peak (one step of the contact solver's impulses, spikes included), the peak of
    the force averaged over ``window`` steps (what a wrist force sensor of that bandwidth reads, and
    what the bound is judged on), the time (s) the averaged force exceeds the bound, and the steps
    whose commanded force was clipped to it (the controller at its bound)."""

    def __init__(self, f_bound: float, dt: float, window: int):
        self.bound, self.dt = f_bound, dt
        self.peak, self.peak_avg = [0.0, 0.0], [0.0, 0.0]
        self.over_steps = [0, 0]
        self.clipped_steps = [0, 0]
        self.recent = [[0.0] * max(window, 1), [0.0] * max(window, 1)]
        self.i = 0

    def add(self, f: list[float]) -> None:
        k = self.i % len(self.recent[0])
        self.i += 1
        for a in range(2):
            self.recent[a][k] = f[a]
            avg = sum(self.recent[a]) / len(self.recent[a])
            self.peak[a] = max(self.peak[a], f[a])
            self.peak_avg[a] = max(self.peak_avg[a], avg)
            if avg > self.bound:
                self.over_steps[a] += 1

    def metrics(self, tolerance: float) -> dict:
        return {"force_bound": self.bound, "max_ball_force": max(self.peak_avg),
                "max_ball_force_step": max(self.peak),
                "time_over_force_bound": self.dt * max(self.over_steps),
                "time_at_force_bound": self.dt * max(self.clipped_steps),
                "within_force_bound": bool(max(self.peak_avg) <= self.bound * (1.0 + tolerance))}


class _Perception:
    """The object's pose as the controller sees it: the simulated pose ``X_WO`` of ``latency`` s ago
    plus Gaussian noise (position per axis, rotation vector per axis), drawn from a generator seeded
    by ``(seed, 1)`` so that a run stays deterministic. Recorded every physics step, read only when a
    lone hold begins (module docstring, Perception)."""

    def __init__(self, S: int, X_PO: np.ndarray, params: Params):
        self.pose = np.zeros((S, 7))
        self.X_PO = X_PO
        self.lag = int(round(params.perception_latency / params.dt))
        self.sigma = (params.perception_noise, math.radians(params.perception_noise_deg))
        self.rng = np.random.default_rng([params.seed, 1])

    def record(self, j: int, obj: int, cid: int) -> None:
        pos, orn = p.getBasePositionAndOrientation(obj, physicsClientId=cid)
        self.pose[j, :3], self.pose[j, 3:] = pos, orn

    def measure(self, j: int) -> np.ndarray:
        """``X_WO (4, 4)`` as seen at step ``j``."""
        x = self.pose[max(j - self.lag, 0)]
        X = se3.make_transform(se3.matrix_from_quat(x[3:]), x[:3]) @ self.X_PO
        noise = self.rng.normal(0.0, 1.0, 6)
        R = Rotation.from_rotvec(self.sigma[1] * noise[3:]).as_matrix()
        return se3.make_transform(R @ X[:3, :3], X[:3, 3] + self.sigma[0] * noise[:3])


def _stretches(plan: Plan) -> list[tuple[int, int]]:
    """``(first, end)`` rows of each run of one primitive and kind, in order."""
    key = plan.primitive.astype(np.int64) * 8 + np.unique(plan.kind, return_inverse=True)[1].reshape(-1)
    change = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    return list(zip(change.tolist(), np.concatenate([change[1:], [len(plan.t)]]).tolist(), strict=True))


def _servo_rows(plan: Plan, sup_vertex: np.ndarray, min_tilt: float) -> np.ndarray:
    """``(T,)`` bool: the rows where the yaw servo acts (module docstring): pivot rows with both balls on
    the object and the planned tilt (the angle between the object's up axis and its up axis at the
    pivot's first row) at least ``min_tilt`` times the pivot's largest, so that the object stands on its
    pivot vertex (``sup_vertex (T, 2)``, :func:`_support_vertices`) and not on a face."""
    on = np.zeros(len(plan.t), bool)
    for s, e in _stretches(plan):
        if plan.kind[s] != "pivot":
            continue
        up = plan.X_WO[s, 2, :3]  # the world's z in O at the pivot's start: the object's up axis
        tilt = np.arccos(np.clip(np.einsum("tj,j->t", plan.X_WO[s:e, 2, :3], up), -1.0, 1.0))
        on[s:e] = (tilt >= min_tilt * tilt.max()) & (tilt.max() > 0) & plan.contact[s:e].all(axis=1)
    return on


class ServoAim(NamedTuple):
    """What the yaw servo steers on each row (:func:`_servo_aims`): ``point_O (T, 3)`` m, a point of the
    object (frame O) to bring onto its planned position, and ``yaw_weight (T,)``, how much the planned
    yaw counts against it (0: the point alone)."""

    point_O: np.ndarray
    yaw_weight: np.ndarray


def _servo_aims(plan: Plan, sup_vertex: np.ndarray, hull_O: np.ndarray, com_O: np.ndarray) -> ServoAim:
    """The pivoting gait's aim (module docstring): on a pivot followed by another pivot, the next pivot's
    vertex, to be put where the plan has it (that pivot then turns the object back to the planned yaw
    about the right place); on the last pivot before a tumble or the end, the CoM and the yaw together."""
    T = len(plan.t)
    point, weight = np.tile(com_O, (T, 1)), np.ones(T)
    moves = [(s, e) for s, e in _stretches(plan) if plan.kind[s] in ("pivot", "tumble")]
    for (s, e), nxt in zip(moves, moves[1:] + [None], strict=False):  # the last has no next
        if plan.kind[s] == "pivot" and nxt is not None and plan.kind[nxt[0]] == "pivot":
            point[s:e], weight[s:e] = hull_O[sup_vertex[nxt[0], 0]], 0.0
    return ServoAim(point, weight)


class _YawServo:
    """The object's yaw servo on a pivot (module docstring). Every perception frame, from the pose then
    perceived against the plan's at that time, a turn ``delta`` about the vertical through the perceived
    pivot vertex: the least-squares mean of ``theta``, the turn that puts the aim's point
    (:func:`_servo_aims`) on the ray to its planned position, and the yaw error, weighed as
    ``(L theta / tol_pos)^2`` against ``(yaw / tol_yaw)^2`` (``L`` the point's lever, the success
    tolerances). Both balls' targets turn about that vertical by ``gain * period * delta`` more, integrated
    in the planned object frame (as the rolling correction) so that the shift turns with the object,
    faded with it after a contact, capped at ``servo_max``: an integral controller with the tracker's
    latency inside the loop."""

    def __init__(self, plan: Plan, sup_vertex: np.ndarray, hull_O: np.ndarray, com_O: np.ndarray, params: Params):
        k = plan.substeps
        S = (len(plan.t) - 1) * k + 1
        row = np.minimum(np.arange(S) // k, len(plan.t) - 1)
        self.on = _servo_rows(plan, sup_vertex, params.servo_min_tilt)[row]
        self.vertex = hull_O[sup_vertex[row, 0]]
        self.aim = _servo_aims(plan, sup_vertex, hull_O, com_O)
        self.row = row
        self.X_plan = plan.X_WO
        self.every = max(int(round(params.servo_period / params.dt)), 1)
        self.step = params.servo_gain * self.every * params.dt
        self.tol = (params.success_pos, math.radians(params.success_yaw_deg))
        self.cap = params.servo_max
        self.shift_O = np.zeros((2, 3))

    def turn(self, X: np.ndarray, j_m: int) -> tuple[float, np.ndarray]:
        """``(delta rad, pivot vertex (3,) W)`` from the perceived pose ``X`` at step ``j_m``."""
        r = self.row[j_m]
        Xp = self.X_plan[r]
        p_v = X[:3, :3] @ self.vertex[j_m] + X[:3, 3]
        w_act = (X[:3, :3] @ self.aim.point_O[r] + X[:3, 3] - p_v)[:2]
        w_pln = (Xp[:3, :3] @ self.aim.point_O[r] + Xp[:3, 3] - p_v)[:2]
        theta = math.atan2(w_act[0] * w_pln[1] - w_act[1] * w_pln[0], w_act @ w_pln)  # onto the planned ray
        R = Xp[:3, :3] @ X[:3, :3].T
        a = float(w_act @ w_act) / self.tol[0] ** 2  # the point's arc L theta against its tolerance
        b = self.aim.yaw_weight[r] / self.tol[1] ** 2
        return (a * theta + b * math.atan2(R[1, 0], R[0, 0])) / max(a + b, 1e-12), p_v

    def update(self, j: int, seen: _Perception, R_plan: np.ndarray, balls, contact_start) -> None:
        """Before step ``j``: a new contact starts with no shift; on a frame of a servoed step, the turn
        from the latest perceived pose ``seen.measure(j - 1)`` adds to the shift of the balls' centres
        ``balls (2, 3)`` (W); ``R_plan (S, 3, 3)`` the planned orientations."""
        for a in range(2):
            if contact_start[a]:
                self.shift_O[a] = 0.0
        if self.step <= 0.0 or not self.on[j] or j % self.every:
            return
        delta, p_v = self.turn(seen.measure(j - 1), max(j - 1 - seen.lag, 0))
        d = self.step * delta * np.cross([0.0, 0.0, 1.0], np.asarray(balls) - p_v) @ R_plan[j]  # planned O frame
        self.shift_O = self.shift_O + d
        n = np.linalg.norm(self.shift_O, axis=1, keepdims=True)
        self.shift_O *= np.minimum(1.0, self.cap / np.maximum(n, 1e-12))

    def offset(self, j: int, R_plan: np.ndarray, keep) -> np.ndarray:
        """``(2, 3)`` the targets' shift at step ``j`` (W), faded by ``keep (2,)``."""
        return np.asarray(keep)[:, None] * (self.shift_O @ R_plan[j].T)


@dataclass(frozen=True, eq=False)
class _Targets:
    """Controller targets at every physics step (index j = row * substeps + sub)."""

    x: np.ndarray  # (S, 2, 3) ball centre (m, W), with the squeeze
    v: np.ndarray  # (S, 2, 3) m/s
    R: np.ndarray  # (S, 2, 3, 3) ball orientation
    w: np.ndarray  # (S, 2, 3) rad/s
    f: np.ndarray  # (S, 2, 3) N, force feed-forward
    q: np.ndarray  # (S, 2, n) rad
    qd: np.ndarray  # (S, 2, n) rad/s
    R_o: np.ndarray  # (S, 3, 3) planned object orientation
    w_o: np.ndarray  # (S, 3) planned object angular velocity (rad/s, W)
    n: np.ndarray  # (S, 2, 3) inward contact normal (W), zero out of contact
    contact: np.ndarray  # (S, 2) bool, the plan's flag of the row being executed
    keep: np.ndarray  # (S, 2) weight of the rolling correction: 1 in contact, fading to 0 after
    qdd: np.ndarray  # (S, 2, n) rad/s^2
    compliance: np.ndarray  # (S, 2) 1: impedance at the ball (contact), 0: joint tracking (free motion)
    follow: np.ndarray  # (S, 2) weight of the drift correction of a ball holding the object alone
    p_o: np.ndarray  # (S, 3) planned object origin (m, W)


def _release_fade(t: np.ndarray, contact: np.ndarray, fade_time: float) -> np.ndarray:
    """``(T, 2)``: 1 in contact, then a minimum-jerk fall to 0 over the gap to the next contact (at most
    ``fade_time`` s), 0 before the first contact."""
    keep = contact.astype(float)
    for a in range(2):
        runs = _runs(contact[:, a])
        for i, (_, e) in enumerate(runs):
            if e >= len(t):
                continue
            t_end = t[runs[i + 1][0]] if i + 1 < len(runs) else t[-1]
            dur = max(min(t_end - t[e - 1], fade_time), t[1] - t[0])
            stop = runs[i + 1][0] if i + 1 < len(runs) else len(t)
            keep[e:stop, a] = 1.0 - _min_jerk((t[e:stop] - t[e - 1]) / dur)
    return keep


def _upsample_rotations(R: np.ndarray, k: int, S: int) -> np.ndarray:
    """Rotations ``(T, 3, 3)`` given per row, slerped to ``S`` physics steps (``k`` per row)."""
    if k == 1:
        return R.copy()
    return Slerp(np.arange(len(R)), Rotation.from_matrix(R))(np.minimum(np.arange(S) / k, len(R) - 1)).as_matrix()


def _angular_velocity(R: np.ndarray, dt: float) -> np.ndarray:
    """World angular velocities ``(S, 3)`` (rad/s) of rotations ``(S, 3, 3)`` sampled every ``dt``."""
    w = np.zeros((len(R), 3))
    if len(R) > 1:
        w[:-1] = (Rotation.from_matrix(R[1:]) * Rotation.from_matrix(R[:-1]).inv()).as_rotvec() / dt
        w[-1] = w[-2]
    return w


def _squeeze_depth(f_ball: np.ndarray, f_bound: float, params: Params) -> np.ndarray:
    """``(T, 2)`` depth (m) of each ball's squeeze target: ``params.squeeze``, less where the planned
    force ``f_ball (T, 2, 3)`` (N) and the squeeze's ``kp * depth`` would exceed ``squeeze_share`` of
    the force bound ``f_bound`` (N): the plan's forces already hold the object within its friction
    cones, the squeeze is a margin on top, and it must not take the ball past what the arm may push."""
    room = params.squeeze_share * f_bound - np.linalg.norm(f_ball, axis=2)
    return np.clip(room / params.kp, 0.0, params.squeeze)


def _make_targets(plan: Plan, R_plan: np.ndarray, normals: np.ndarray, params: Params, f_bound: float) -> _Targets:
    weight = _contact_weights(plan.t, plan.contact, params.ramp_time)
    depth = _squeeze_depth(plan.f_ball, f_bound, params)
    squeeze = (_squeeze_weights(weight, normals) * depth)[..., None]
    x_row = plan.p_ball + squeeze * _squeeze_lines(plan.p_ball, normals)
    f_row = weight[..., None] * plan.f_ball
    if params.ball_orientation == "object":
        R_row = _rotation_targets(plan.t, plan.X_WO, R_plan, plan.contact, params.unwind_time)
    else:
        R_row = R_plan
    k, T, dt = plan.substeps, len(plan.t), params.dt
    S = (T - 1) * k + 1
    j = np.arange(S)
    r0 = np.minimum(j // k, T - 2)
    s = ((j - r0 * k) / k)[:, None, None]

    def lerp(a):
        return a[r0] + s * (a[r0 + 1] - a[r0])

    x, f, q, n = lerp(x_row), lerp(f_row), lerp(plan.q), lerp(normals)
    R = np.stack([_upsample_rotations(R_row[:, a], k, S) for a in range(2)], axis=1)
    R_o = _upsample_rotations(plan.X_WO[:, :3, :3], k, S)
    row = np.minimum(j // k, T - 1)
    keep = lerp(_release_fade(plan.t, plan.contact, params.unwind_time)[..., None])[..., 0]
    return _Targets(x=x, v=np.gradient(x, dt, axis=0), R=R,
                    w=np.stack([_angular_velocity(R[:, a], dt) for a in range(2)], axis=1), f=f, q=q,
                    qd=np.gradient(q, dt, axis=0), R_o=R_o, w_o=_angular_velocity(R_o, dt), n=n,
                    contact=plan.contact[row], keep=keep, qdd=np.gradient(np.gradient(q, dt, axis=0), dt, axis=0),
                    compliance=lerp(_compliance(plan.t, plan.contact, params.ramp_time)[..., None])[..., 0],
                    follow=lerp(_hold_weights(weight, plan.kind, plan.f_ball)[..., None])[..., 0],
                    p_o=lerp(plan.X_WO[:, None, :3, 3])[:, 0])


def _compliance(t: np.ndarray, contact: np.ndarray, ramp: float) -> np.ndarray:
    """``(T, 2)`` blend between joint tracking (0) and ball impedance (1) per arm.

    Free motion (transits, an arm waiting) tracks the planned joints with computed torque: the
    operational-space law has nothing to hold on to there and blows up near singular postures (the
    arms' zero posture is one). The impedance takes over ``ramp`` s before a contact starts, while
    the ball is still on its approach, and hands back ``ramp`` s after it ends.
    """
    w = np.zeros(contact.shape)
    for a in range(contact.shape[1]):  # per arm, over its contact stretches
        for i0, i1 in _runs(contact[:, a]):
            t0, t1 = t[i0] - ramp, t[i1 - 1] + ramp
            w[:, a] = np.maximum(w[:, a], _min_jerk(np.clip(np.minimum(t - t0, t1 - t) / ramp, 0.0, 1.0)))
    return w


# ----------------------------------------------------------------------------------------------------
# The PyBullet world


@contextlib.contextmanager
def _connect(gui: bool):
    cid = p.connect(p.GUI if gui else p.DIRECT)
    if cid < 0:
        raise RuntimeError("pybullet: cannot connect")
    try:
        yield cid
    finally:
        p.disconnect(physicsClientId=cid)


def _quat(R: np.ndarray) -> list[float]:
    return se3.quat_from_matrix(R).tolist()


def _static_box(cid, half, X, rgba, friction):
    col = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half), physicsClientId=cid)
    vis = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half), rgbaColor=rgba, physicsClientId=cid)
    body = p.createMultiBody(0.0, col, vis, basePosition=X[:3, 3].tolist(), baseOrientation=_quat(X[:3, :3]),
                             physicsClientId=cid)
    p.changeDynamics(body, -1, lateralFriction=friction, physicsClientId=cid)
    return body


def _add_obstacle(cid, geom, friction) -> int:
    X = geom.X_WOb
    rgba = [0.55, 0.4, 0.3, 1.0]
    if geom.kind == "box":
        return _static_box(cid, np.asarray(geom.size) / 2, X, rgba, friction)
    if geom.kind == "cylinder":
        col = p.createCollisionShape(p.GEOM_CYLINDER, radius=geom.radius, height=geom.height, physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_CYLINDER, radius=geom.radius, length=geom.height, rgbaColor=rgba,
                                  physicsClientId=cid)
    else:
        V, F = np.asarray(geom.vertices, dtype=float).tolist(), np.asarray(geom.faces, dtype=int).ravel().tolist()
        col = p.createCollisionShape(p.GEOM_MESH, vertices=V, indices=F, flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
                                     physicsClientId=cid)
        vis = p.createVisualShape(p.GEOM_MESH, vertices=V, indices=F, rgbaColor=rgba, physicsClientId=cid)
    body = p.createMultiBody(0.0, col, vis, basePosition=X[:3, 3].tolist(), baseOrientation=_quat(X[:3, :3]),
                             physicsClientId=cid)
    p.changeDynamics(body, -1, lateralFriction=friction, physicsClientId=cid)
    return body


def _modal_gains(sqrt_k: np.ndarray, A: np.ndarray, zeta: float, w_max: float):
    """Task stiffness and damping for the desired diagonal stiffness ``K = diag(sqrt_k^2)``, in modes.

    ``A (..., 6, 6) = J M^-1 J^T`` is the inverse of the task inertia ``Lam``. The modes of
    ``K v = lambda Lam v`` (eigenvectors ``W`` of ``K^1/2 A K^1/2``, natural frequencies
    ``sqrt(lambda)``) keep their stiffness unless their frequency exceeds ``w_max`` (rad/s), where it
    is lowered to ``w_max``: torques are computed once per physics step from the state at its start,
    which cannot hold a light mode (the wrist) stiffly. Each mode is damped at the ratio ``zeta`` (the
    notes' ``D ~ 1.4 sqrt(K m)`` for every direction at once)::

        K_eff = U diag(k_m) U^T,  D = U diag(d_m) U^T,  U = K^1/2 W,
        k_m = min(lambda, w_max^2) / lambda,  d_m = 2 zeta sqrt(min(lambda, w_max^2)) / lambda

    Returns ``U (..., 6, 6)``, ``k_m (..., 6)``, ``d_m (..., 6)``: the wrench is then
    ``U (k_m * U^T e + d_m * U^T e')`` with two matrix-vector products (see :func:`_dense_gains`).
    """
    lam, W = np.linalg.eigh(sqrt_k[:, None] * A * sqrt_k)
    lam = np.maximum(lam, 1e-12)
    capped = np.minimum(lam, w_max * w_max)
    return sqrt_k[:, None] * W, capped / lam, 2.0 * zeta * np.sqrt(capped) / lam


def _dense_gains(U: np.ndarray, k_m: np.ndarray, d_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``K_eff, D (..., 6, 6)`` from the modal form of :func:`_modal_gains`."""
    Ut = np.swapaxes(U, -1, -2)
    return (U * k_m[..., None, :]) @ Ut, (U * d_m[..., None, :]) @ Ut


def _quat_error(qt, qc) -> tuple[float, float, float]:
    """Rotation vector (rad, W) of ``R_t R_c^T`` from scalar-last quaternions (plain floats: fast)."""
    tx, ty, tz, tw = qt
    cx, cy, cz, cw = -qc[0], -qc[1], -qc[2], qc[3]
    w = tw * cw - tx * cx - ty * cy - tz * cz
    x = tw * cx + tx * cw + ty * cz - tz * cy
    y = tw * cy - tx * cz + ty * cw + tz * cx
    z = tw * cz + tx * cy - ty * cx + tz * cw
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    n = math.sqrt(x * x + y * y + z * z)
    f = 2.0 * math.atan2(n, w) / n if n > 1e-12 else 2.0
    return f * x, f * y, f * z


def _principal_frame(com_O, inertia_O) -> tuple[np.ndarray, np.ndarray]:
    """``X_OP (4, 4)``: the CoM with the principal axes (right-handed), and the moments ``(3,)``."""
    lam, R = np.linalg.eigh(0.5 * (inertia_O + inertia_O.T))
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    return se3.make_transform(R, com_O), lam


# ----------------------------------------------------------------------------------------------------
# Simulation


def _checked_inputs(mass, com_O, inertia_O, X_WO_goal, params: Params, frames: int):
    """:func:`simulate`'s object and parameters checked (:class:`InputError` else): ``(com_O (3,),
    inertia_O (3, 3), X_WO_goal (4, 4))`` as float arrays."""
    com_O = np.asarray(com_O, dtype=float).reshape(3)
    inertia_O = np.asarray(inertia_O, dtype=float).reshape(3, 3)
    X_WO_goal = np.asarray(X_WO_goal, dtype=float)
    if not (np.isfinite(mass) and mass > 0):
        raise InputError(f"simulate: mass must be positive, got {mass}")
    if X_WO_goal.shape != (4, 4) or not np.all(np.isfinite(X_WO_goal)):
        raise InputError("simulate: X_WO_goal must be a finite (4, 4) pose")
    if np.linalg.eigvalsh(0.5 * (inertia_O + inertia_O.T)).min() <= 0:
        raise InputError("simulate: inertia_O must be positive definite")
    if params.ball_orientation not in ("plan", "object") or params.task not in ("position", "pose") \
            or (params.ball_orientation == "object" and params.task != "pose") or not params.dt > 0 or frames < 0:
        raise InputError(f"simulate: invalid parameters (ball_orientation {params.ball_orientation!r} needs task "
                         f"'pose', task {params.task!r}, dt {params.dt}, frames {frames})")
    if params.seed < 0:
        raise InputError(f"simulate: seed must be >= 0 (0: the nominal physics), got {params.seed}")
    return com_O, inertia_O, X_WO_goal


class _Body(NamedTuple):
    """The object as physics simulates it (:func:`_perturbed_body`): friction ``mu``, ``mass`` (kg),
    its principal frame ``X_OP`` (4, 4; origin at the true CoM) and moments ``lam`` (3,) kg m^2,
    the initial offset ``d_pose`` (3,) m (W) and what a seed drew (``perturbation``)."""

    mu: float
    mass: float
    X_OP: np.ndarray
    lam: np.ndarray
    d_pose: np.ndarray
    perturbation: dict


def _perturbed_body(mu: float, mass: float, com_O, inertia_O, params: Params) -> _Body:
    """The body's principal frame (:func:`_principal_frame`), and with ``params.seed`` > 0 the
    seeded perturbations: friction, CoM, inertia and mass (the inertia scales with it: same shape,
    uniform density) and the initial position, each uniform within its jitter."""
    rng = np.random.default_rng(params.seed)
    X_OP, lam = _principal_frame(com_O, inertia_O)
    d_pose = np.zeros(3)
    if params.seed <= 0:
        return _Body(mu, mass, X_OP, lam, d_pose, {})
    f_mu = rng.uniform(1 - params.friction_jitter, 1 + params.friction_jitter)
    d_com = rng.uniform(-params.com_jitter, params.com_jitter, 3)
    f_lam = rng.uniform(1 - params.inertia_jitter, 1 + params.inertia_jitter, 3)
    # Drawn last, so that a seed's other perturbations are the ones it drew before mass was jittered.
    f_m = rng.uniform(1 - params.mass_jitter, 1 + params.mass_jitter)
    X_OP = se3.make_transform(X_OP[:3, :3], com_O + d_com)
    d_pose[:2] = rng.uniform(-params.pose_jitter, params.pose_jitter, 2)
    perturbation = {"friction_factor": float(f_mu), "com_offset": d_com.tolist(),
                    "inertia_factors": f_lam.tolist(), "mass_factor": float(f_m),
                    "initial_offset": d_pose[:2].tolist()}
    return _Body(mu * f_mu, mass * f_m, X_OP, lam * f_lam * f_m, d_pose, perturbation)


def _load_table(cid: int, scene, params: Params) -> tuple[int, dict]:
    """A fresh PyBullet world (fixed step ``params.dt``, deterministic pairs, gravity) with the
    scene's table (its top at z = 0) and obstacles: ``(table id, obstacle id -> name)``."""
    p.resetSimulation(physicsClientId=cid)
    p.setPhysicsEngineParameter(fixedTimeStep=params.dt, numSolverIterations=params.solver_iterations,
                                deterministicOverlappingPairs=1, physicsClientId=cid)
    p.setGravity(0.0, 0.0, -9.81, physicsClientId=cid)
    sx, sy = scene.table.size
    h = scene.table.height
    table = _static_box(cid, (sx / 2, sy / 2, h / 2), se3.make_transform(np.eye(3), [0.0, 0.0, -h / 2]),
                        [0.8, 0.75, 0.65, 1.0], 1.0)
    return table, {_add_obstacle(cid, g, 1.0): g.name for g in scene.obstacle_geometries()}


class _RobotBody(NamedTuple):
    """The robot in PyBullet (:func:`_load_robot`): its body id, link names by index, the movable
    joints, each arm's columns among them, joint effort limits ``(2, n)`` (N m; inf when not
    clipped), the balls' link ids and their centres in the links' inertial frames, every arm joint."""

    body: int
    link_name: dict
    movable: list
    arm_cols: list
    effort: np.ndarray
    balls: list
    ball_local: list
    all_arm: list


def _load_robot(cid: int, scene, robot, arms, q0: np.ndarray, params: Params) -> _RobotBody:
    """The scene's URDF on its base (fixed, exact cylinders), the arms at ``q0 (2, n)`` and torque
    controlled (velocity motors off), the torso held at its angle by a position motor."""
    X_WB = scene.base_transform()
    body = p.loadURDF(str(scene.robot.urdf_path), X_WB[:3, 3].tolist(), _quat(X_WB[:3, :3]), useFixedBase=True,
                      flags=p.URDF_USE_INERTIA_FROM_FILE | p.URDF_USE_IMPLICIT_CYLINDER, physicsClientId=cid)
    info = [p.getJointInfo(body, j, physicsClientId=cid) for j in range(p.getNumJoints(body, physicsClientId=cid))]
    joint_index = {i[1].decode(): i[0] for i in info}
    link_index = {i[12].decode(): i[0] for i in info}
    link_name = {i[0]: i[12].decode() for i in info}
    link_name[-1] = "base"
    movable = [i[0] for i in info if i[2] != p.JOINT_FIXED]
    col_of = {j: c for c, j in enumerate(movable)}
    arm_joints = [[joint_index[n] for n in a.joint_names] for a in arms]
    arm_cols = [np.array([col_of[j] for j in js]) for js in arm_joints]
    others = [j for j in movable if j not in arm_joints[0] + arm_joints[1]]  # the torso
    effort = np.array([[info[j][10] for j in js] for js in arm_joints])
    effort = np.where(effort > 0, effort, np.inf) if params.clip_effort else np.full(effort.shape, np.inf)
    balls = [link_index[n] for n in scene.robot.eef_links]
    ball_local = []
    for b in balls:  # calculateJacobian wants the point in the link's inertial frame
        d = p.getDynamicsInfo(body, b, physicsClientId=cid)
        R_LI = se3.matrix_from_quat(np.asarray(d[4]))
        ball_local.append((-(R_LI.T @ np.asarray(d[3]))).tolist())
    for j in range(-1, len(info)):
        p.changeDynamics(body, j, lateralFriction=1.0, physicsClientId=cid)
    for a in range(2):
        for c, j in enumerate(arm_joints[a]):
            p.resetJointState(body, j, float(q0[a, c]), 0.0, physicsClientId=cid)
    for j in others:
        p.resetJointState(body, j, robot.torso_angle, 0.0, physicsClientId=cid)
        p.setJointMotorControl2(body, j, p.POSITION_CONTROL, targetPosition=robot.torso_angle,
                                force=10.0 * max(info[j][10], 100.0), physicsClientId=cid)
    all_arm = arm_joints[0] + arm_joints[1]
    p.setJointMotorControlArray(body, all_arm, p.VELOCITY_CONTROL, forces=[0.0] * len(all_arm), physicsClientId=cid)
    return _RobotBody(body, link_name, movable, arm_cols, effort, balls, ball_local, all_arm)


def _load_object(cid: int, parts_path, visual_mesh, X_OP: np.ndarray, X_WO0: np.ndarray, d_pose: np.ndarray,
                 mass: float, lam: np.ndarray, mu: float, params: Params) -> int:
    """The object's body: base frame P at the (true) CoM with the principal axes ``X_OP``, the convex
    parts of ``parts_path`` as its collision shape, at ``X_WO0`` shifted by ``d_pose`` (m, W), with its
    mass, principal moments ``lam`` and friction ``mu``, never asleep; drawn with ``visual_mesh`` (the
    collision mesh: PyBullet refuses a visual shape of a 200k-triangle mesh) when not None."""
    X_PO = se3.invert(X_OP)
    col = p.createCollisionShape(p.GEOM_MESH, fileName=str(parts_path), collisionFramePosition=X_PO[:3, 3].tolist(),
                                 collisionFrameOrientation=_quat(X_PO[:3, :3]), physicsClientId=cid)
    vis = -1
    if visual_mesh is not None:
        vis = p.createVisualShape(p.GEOM_MESH, vertices=np.asarray(visual_mesh.vertices).tolist(),
                                  indices=np.asarray(visual_mesh.faces).ravel().tolist(),
                                  rgbaColor=[0.2, 0.45, 0.8, 1.0],
                                  visualFramePosition=X_PO[:3, 3].tolist(),
                                  visualFrameOrientation=_quat(X_PO[:3, :3]), physicsClientId=cid)
    X_WP0 = X_WO0 @ X_OP
    X_WP0[:3, 3] += d_pose
    obj = p.createMultiBody(mass, col, vis, basePosition=X_WP0[:3, 3].tolist(),
                            baseOrientation=_quat(X_WP0[:3, :3]), physicsClientId=cid)
    p.changeDynamics(obj, -1, mass=mass, localInertiaDiagonal=lam.tolist(), lateralFriction=mu,
                     spinningFriction=0.0, rollingFriction=0.0, frictionAnchor=1, restitution=0.0,
                     linearDamping=0.0, angularDamping=0.0, collisionMargin=params.object_margin,
                     activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=cid)
    return obj


class _Recorder:
    """What :func:`simulate` records of the PyBullet world: per plan row (``sample``) the object's pose,
    the balls' and the table's contact forces, the deepest penetration, the balls' centres, the arms'
    joints and, on ``frames`` rows spread evenly, a rendered image (``render()``); per step
    (``contacts``) each collision pair of the robot with the object (links other than the balls), the
    table and the obstacles, and of the object with the obstacles, with the time of its first contact."""

    def __init__(self, T: int, n_arm: int, frames: int, cid: int, body: int, obj: int, table: int, obstacles: dict,
                 balls: list, arm_cols: list, link_name: dict, render):
        self.raw = {"pos_P": np.zeros((T, 3)), "quat_P": np.zeros((T, 4)), "ball": np.zeros((T, 2, 3)),
                    "q": np.zeros((T, 2, n_arm)), "f_ball": np.zeros((T, 2)), "touch": np.zeros((T, 2), dtype=bool),
                    "f_table": np.zeros(T), "pen": np.zeros(T), "sat": np.zeros(T, dtype=bool)}
        self.collisions = {"robot_table": set(), "robot_obstacle": set(), "robot_object": set(),
                           "object_obstacle": set()}
        self.first_hit: dict[str, float] = {}  # "kind:name" -> time (s) of the first contact
        self.images: list[np.ndarray] = []
        self.frame_rows = set(np.round(np.linspace(0, T - 1, frames)).astype(int).tolist()) if frames > 0 else set()
        self.cid, self.body, self.obj, self.table, self.obstacles = cid, body, obj, table, obstacles
        self.balls, self.arm_cols, self.link_name, self.render = balls, arm_cols, link_name, render

    def sample(self, r: int, states) -> None:
        """Row ``r``'s record, ``states`` the joint states after its step."""
        raw, cid, obj, body, balls = self.raw, self.cid, self.obj, self.body, self.balls
        pos, orn = p.getBasePositionAndOrientation(obj, physicsClientId=cid)
        raw["pos_P"][r], raw["quat_P"][r] = pos, orn
        f_table, pen = 0.0, 0.0
        f_vec = np.zeros((2, 3))
        for c in p.getContactPoints(bodyA=obj, physicsClientId=cid):
            pen = max(pen, -c[8])
            if c[2] == body and c[4] in balls:
                a = balls.index(c[4])
                f_vec[a] += _contact_force(c)
                raw["touch"][r, a] = True
            elif c[2] == self.table:
                f_table += c[9]
        raw["f_ball"][r] = np.linalg.norm(f_vec, axis=1)
        raw["f_table"][r], raw["pen"][r] = f_table, pen
        ls = p.getLinkStates(body, balls, computeForwardKinematics=1, physicsClientId=cid)
        raw["ball"][r] = [ls[0][4], ls[1][4]]
        q_now = np.array([s[0] for s in states])
        raw["q"][r] = [q_now[self.arm_cols[0]], q_now[self.arm_cols[1]]]
        if r in self.frame_rows:
            self.images.append(self.render())

    def contacts(self, t_now: float) -> list[float]:
        """Record the collisions of this step (at ``t_now`` s); returns each ball's force on the object (N)."""
        collisions, first_hit, link_name, obstacles = self.collisions, self.first_hit, self.link_name, self.obstacles

        def hit(kind: str, name: str) -> None:
            if name not in collisions[kind]:
                collisions[kind].add(name)
                first_hit.setdefault(f"{kind}:{name}", t_now)

        f_vec = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
        for c in p.getContactPoints(bodyA=self.body, physicsClientId=self.cid):
            other = c[2]
            if other == self.obj:
                if c[3] not in self.balls:
                    hit("robot_object", link_name.get(c[3], str(c[3])))
                else:
                    fa, fc = f_vec[self.balls.index(c[3])], _contact_force(c)
                    fa[0], fa[1], fa[2] = fa[0] + fc[0], fa[1] + fc[1], fa[2] + fc[2]
            elif other == self.table:
                hit("robot_table", link_name.get(c[3], str(c[3])))
            elif other in obstacles:
                hit("robot_obstacle", f"{link_name.get(c[3], str(c[3]))}/{obstacles[other]}")
        if obstacles:
            for c in p.getContactPoints(bodyA=self.obj, physicsClientId=self.cid):
                if c[2] in obstacles:
                    hit("object_obstacle", obstacles[c[2]])
        return [math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]) for f in f_vec]


def simulate(scene, mesh_path, mass: float, com_O, inertia_O, traj, X_WO_goal, params: Params = Params(),
             gui: bool = False, frames: int = 0) -> Execution:
    """Run a trajectory table in PyBullet and measure how the object really moved (paper §6).

    Parameters
    ----------
    scene : :class:`stages.scene.Scene` (table, obstacles, robot URDF, base pose, ball links, object
        friction).
    mesh_path : the object mesh in metres in frame O (the analysis stage's ``object.ply``; no scale
        is applied).
    mass : float, kg.
    com_O : (3,) float, the CoM in O (m).
    inertia_O : (3, 3) float, inertia about the CoM in O axes (kg m^2).
    traj : mapping of trajectory columns (module docstring, :data:`TRAJECTORY_FIELDS`).
    X_WO_goal : (4, 4) float, the goal pose of the object.
    params : :class:`Params`.
    gui : open PyBullet's GUI instead of DIRECT (for a person watching; results are the same).
    frames : number of RGB frames to render, spread evenly over the rows (0: none).

    Returns
    -------
    Execution with ``metrics``: ``final_position_error`` (m, horizontal, of the CoM projection) and
    ``final_yaw_error_deg`` to ``X_WO_goal``; the same to the plan's last pose,
    ``final_plan_position_error`` and ``final_plan_yaw_error_deg`` (the physics alone, when a partial
    plan stops short of the goal); ``max_com_deviation`` (m) and ``max_rotation_deviation_deg``
    from the planned object path; ``max_tilt_deviation_deg`` (:func:`path_tilt`);
    ``max_pivot_slip`` (m, over pivot rows) and ``max_edge_slip`` (m, of
    the support edge over tumble rows);
    the support's slip per stretch and the worst (:func:`_slip_metrics`);
    ``max_penetration`` (m); the force bound's figures (``force_bound``, ``max_ball_force`` averaged
    over ``force_window``, ``max_ball_force_step``, ``time_over_force_bound``, ``time_at_force_bound``
    (s, commanded force clipped), ``within_force_bound``; :class:`_ForceMonitor`) and
    ``max_planned_ball_force`` (N, the plan's largest force magnitude); ``max_joint_error`` (rad);
    ``fell`` and ``fell_reason``; ``robot_table_contacts``, ``robot_obstacle_contacts``,
    ``robot_object_contacts`` (links other than the balls), ``object_obstacle_contacts`` (sorted
    names); ``collision``; ``collision_times`` (``"<kind>:<name>"`` -> time in s of that pair's first
    contact, to find it in the log); ``torque_saturation`` (fraction of steps with a clipped joint
    torque); the release's figures (:func:`_release_metrics`); ``position_ok``, ``yaw_ok``;
    ``failures`` (codes of :data:`FAILURES`) and ``success`` (none); ``planned_rows`` (rows of the
    plan before the release); ``convex_parts``; ``collision_shape`` (``triangles`` of the mesh the
    hulls come from, the planning mesh's ``mesh_triangles``, and the simplification's error bound
    ``tolerance`` in m, 0 when the planning mesh itself: :func:`stages.simplify.collision_mesh`);
    ``perturbation`` (what a seed N > 0 drew); ``steps``,
    ``duration`` (s).
    """
    wall0 = time.perf_counter()
    com_O, inertia_O, X_WO_goal = _checked_inputs(mass, com_O, inertia_O, X_WO_goal, params, frames)
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    arms = (robot.arm("left"), robot.arm("right"))
    plan = check_trajectory(traj, params.dt, arms[0].dof)
    mesh = load_mesh(mesh_path)
    n_planned = len(plan.t)
    if params.release:
        plan = with_release(plan, mesh, robot, params)
    f_bound = params.force_limit if params.force_limit > 0 else float(scene.robot.max_eef_force)
    t_dec = time.perf_counter()
    shape = collision_mesh(mesh)
    parts, parts_path, cache_hit = convex_parts(shape.mesh, params.cache_dir)
    t_dec = time.perf_counter() - t_dec

    mu, mass, X_OP, lam, d_pose, perturbation = _perturbed_body(float(scene.object.friction), mass, com_O,
                                                                inertia_O, params)
    X_PO = se3.invert(X_OP)

    # Targets from the plan.
    R_plan = np.stack([robot.eef_rotation(a.name, plan.q[:, i]) for i, a in enumerate(arms)], axis=1)
    normals = _contact_normals(mesh, plan.X_WO, plan.p_ball, plan.contact)
    tg = _make_targets(plan, R_plan, normals, params, f_bound)
    hull_O = np.asarray(mesh.convex_hull.vertices)
    sup_vertex, sup_start = _support_vertices(plan, hull_O)

    T, k = len(plan.t), plan.substeps
    S = (T - 1) * k + 1
    n_arm = arms[0].dof
    quat_tgt = se3.quat_from_matrix(tg.R).tolist()  # (S, 2, 4) nested lists: fast scalar access
    saturated_steps = 0

    with _connect(gui) as cid:
        table, obstacles = _load_table(cid, scene, params)
        body, link_name, movable, arm_cols, effort, balls, ball_local, all_arm = _load_robot(cid, scene, robot, arms,
                                                                                             plan.q[0], params)
        obj = _load_object(cid, parts_path, shape.mesh if frames > 0 or gui else None, X_OP, plan.X_WO[0], d_pose,
                           mass, lam, mu, params)
        camera = scene_camera(scene, plan.X_WO[0], X_WO_goal, com_O)
        if frames > 0 or gui:  # the goal's footprint, drawn only: no collision shape, no mass
            _add_goal_footprint(mesh, X_WO_goal, cid)

        zeros = [0.0] * len(movable)
        nt = 6 if params.task == "pose" else 3  # task coordinates per ball
        sqrt_k = np.sqrt(np.array([params.kp] * 3 + [params.kr] * 3))[:nt]
        w_max = params.max_frequency if params.max_frequency > 0 else 0.5 / params.dt
        reg = 1e-9 * np.eye(nt)
        sqrt_kq = np.full(n_arm, math.sqrt(params.kq))
        model_period = max(int(params.model_period), 1)
        n_mov = len(movable)

        rec = _Recorder(T, n_arm, frames, cid, body, obj, table, obstacles, balls, arm_cols, link_name,
                        lambda: _render(cid, params, camera))
        raw, collisions, first_hit, images = rec.raw, rec.collisions, rec.first_hit, rec.images
        sample, check_collisions = rec.sample, rec.contacts

        t_loop, c_loop = time.perf_counter(), time.process_time()
        states = p.getJointStates(body, movable, physicsClientId=cid)
        sample(0, states)
        cols2 = np.stack(arm_cols)  # (2, n) columns of each arm in the full joint vector
        i_arm, i_row, i_col = np.arange(2)[:, None, None], np.arange(nt)[None, :, None], cols2[:, None, :]
        m_row, m_col = cols2[:, :, None], cols2[:, None, :]
        delta_O = np.zeros((2, 3))  # rolling correction of each ball's target, object frame
        r_ball, dt, roll = scene.robot.ball_radius, params.dt, params.roll_compensation
        w_o, normals_s, contact_s = tg.w_o.tolist(), tg.n.tolist(), tg.contact.tolist()
        compliance_s = tg.compliance.tolist()
        follow_s = tg.follow.tolist()
        drift: list = [None, None]  # per ball: the object's drift from the plan when its lone hold began
        f_command = (1.0 - params.force_margin) * f_bound
        f_clip = [f_command, f_command]  # this step's clip per ball: the force limiter's (force_feedback)
        force = _ForceMonitor(f_bound, dt, int(round(params.force_window / dt)))
        seen = _Perception(S, X_PO, params)
        servo = _YawServo(plan, sup_vertex, hull_O, com_O, params)
        seen.record(0, obj, cid)
        eye_n = np.eye(n_arm)
        for j in range(1, S):
            # Torques for the step from j - 1 to j, from the state at j - 1 and the targets at j.
            ql, qdl = [s[0] for s in states], [s[1] for s in states]
            q, qd = np.array(ql), np.array(qdl)
            ls = p.getLinkStates(body, balls, computeLinkVelocity=1, computeForwardKinematics=1,
                                 physicsClientId=cid)
            h_all = np.asarray(p.calculateInverseDynamics(body, ql, qdl, zeros, physicsClientId=cid))
            refresh = (j - 1) % model_period == 0
            if refresh:
                JL = p.calculateJacobian(body, balls[0], ball_local[0], ql, qdl, zeros, physicsClientId=cid)
                JR = p.calculateJacobian(body, balls[1], ball_local[1], ql, qdl, zeros, physicsClientId=cid)
                rows = JL[0] + JL[1] + JR[0] + JR[1] if nt == 6 else JL[0] + JR[0]
                J = np.fromiter(itertools.chain.from_iterable(rows), float,
                                2 * nt * n_mov).reshape(2, nt, n_mov)[i_arm, i_row, i_col]  # (2, nt, n)
                JT = J.transpose(0, 2, 1)
            x_t, v_t = tg.x[j], tg.v[j]
            if roll and (contact_s[j][0] or contact_s[j][1]):
                # No slip at the contact: the centre must move by (w_o - w_ball) x r n relative to the
                # object, accumulated in the object frame while the plan has contact.
                R_o = tg.R_o[j]
                for a in range(2):
                    if contact_s[j][a]:
                        if not contact_s[j - 1][a]:
                            delta_O[a] = 0.0
                        wb, wo, n = ls[a][7], w_o[j], normals_s[j][a]
                        r0, r1, r2 = wo[0] - wb[0], wo[1] - wb[1], wo[2] - wb[2]
                        n0, n1, n2 = r_ball * n[0], r_ball * n[1], r_ball * n[2]
                        c = np.array((r1 * n2 - r2 * n1, r2 * n0 - r0 * n2, r0 * n1 - r1 * n0))
                        delta_O[a] += dt * (c @ R_o)
                x_t = x_t + tg.keep[j][:, None] * (delta_O @ R_o.T)
            elif roll:
                x_t = x_t + tg.keep[j][:, None] * (delta_O @ tg.R_o[j].T)
            servo.update(j, seen, tg.R_o, (ls[0][4], ls[1][4]),
                         (contact_s[j][0] and not contact_s[j - 1][0], contact_s[j][1] and not contact_s[j - 1][1]))
            if servo.shift_O.any():
                x_t = x_t + servo.offset(j, tg.R_o, tg.keep[j])
            for a in range(2):
                if follow_s[j][a] <= 0.0:
                    drift[a] = None
                    continue
                if drift[a] is None:  # a lone hold begins: where the object is seen, against the plan
                    X_act = seen.measure(j - 1)
                    R_d = X_act[:3, :3] @ tg.R_o[j].T
                    drift[a] = (R_d, X_act[:3, 3] - R_d @ tg.p_o[j])
                R_d, p_d = drift[a]
                x_t = x_t.copy()
                x_t[a] += follow_s[j][a] * (R_d @ x_t[a] + p_d - x_t[a])
            if nt == 6:
                e = np.concatenate([x_t - (ls[0][4], ls[1][4]),
                                    (_quat_error(quat_tgt[j][0], ls[0][5]), _quat_error(quat_tgt[j][1], ls[1][5]))],
                                   axis=1)
                e_dot = np.concatenate([v_t - (ls[0][6], ls[1][6]), tg.w[j] - (ls[0][7], ls[1][7])], axis=1)
            else:
                ball = np.array((ls[0][4], ls[1][4], ls[0][6], ls[1][6]))  # centres, then velocities
                e, e_dot = x_t - ball[:2], v_t - ball[2:]
            if refresh:
                # The arm's dynamics model, refreshed every model_period steps (it changes slowly):
                # mass matrix, task inertia, the task and posture gains (dense, from their modes) and
                # the null-space map N = I - J^T Jbar^T (Jbar^T = Lam J M^-1), applied to the posture.
                M_all = np.fromiter(itertools.chain.from_iterable(p.calculateMassMatrix(body, ql, physicsClientId=cid)),
                                    float, n_mov * n_mov).reshape(n_mov, n_mov)
                M_arm = M_all[m_row, m_col]  # (2, n, n)
                M_inv = np.linalg.inv(M_arm)
                MJ = M_inv @ JT  # (2, n, nt)
                A = J @ MJ  # (2, nt, nt): the inverse task inertia
                K_task, D_task = _dense_gains(*_modal_gains(sqrt_k, A, params.damping_ratio, w_max))
                JbarT = np.linalg.solve(A + reg, MJ.transpose(0, 2, 1))  # (2, nt, n)
                N = eye_n - JT @ JbarT
                if (j - 1) % (4 * model_period) == 0:  # the posture's gains depend on M alone: slower still
                    K_q, D_q = _dense_gains(*_modal_gains(sqrt_kq, M_inv, params.damping_ratio, w_max))
                NK_q, ND_q = N @ K_q, N @ D_q
            W = (K_task @ e[:, :, None] + D_task @ e_dot[:, :, None])[:, :, 0]
            W[:, :3] += tg.f[j]
            for a in range(2):
                fx, fy, fz = W[a, :3].tolist()
                nF = math.sqrt(fx * fx + fy * fy + fz * fz)
                if nF > f_clip[a]:
                    W[a, :3] *= f_clip[a] / nF
                    force.clipped_steps[a] += 1
            # The posture in the null space: N (Kq e_q + Dq e_q').
            e_q, e_qd = tg.q[j] - q[cols2], tg.qd[j] - qd[cols2]
            h = h_all[cols2]
            c0, c1 = compliance_s[j]
            if c0 > 0.0 or c1 > 0.0:
                tau_imp = (JT @ W[:, :, None] + NK_q @ e_q[:, :, None] + ND_q @ e_qd[:, :, None])[:, :, 0] + h
            if c0 < 1.0 or c1 < 1.0:
                # Free motion: computed-torque joint tracking, blended with the impedance around contacts.
                acc = tg.qdd[j] + params.kj * e_q + params.dj * e_qd
                tau_joint = (M_arm @ acc[:, :, None])[:, :, 0] + h
            if c0 == 1.0 and c1 == 1.0:
                tau = tau_imp
            elif c0 == 0.0 and c1 == 0.0:
                tau = tau_joint
            else:
                c = tg.compliance[j][:, None]
                tau = c * tau_imp + (1.0 - c) * tau_joint
            saturated = bool((np.abs(tau) > effort).any())
            if saturated:
                tau = np.clip(tau, -effort, effort)
            saturated_steps += saturated
            p.setJointMotorControlArray(body, all_arm, p.TORQUE_CONTROL, forces=tau.ravel().tolist(),
                                        physicsClientId=cid)
            p.stepSimulation(physicsClientId=cid)
            f_sensed = check_collisions(float(plan.t[0]) + j * dt)
            force.add(f_sensed)
            f_clip = _force_clip(f_sensed, f_command, params.force_feedback)
            seen.record(j, obj, cid)
            states = p.getJointStates(body, movable, physicsClientId=cid)
            if j % k == 0:
                raw["sat"][j // k] = saturated
                sample(j // k, states)
        t_loop, c_loop = time.perf_counter() - t_loop, time.process_time() - c_loop
        clearance = [min([c[8] for c in p.getClosestPoints(body, obj, 1.0, linkIndexA=b, physicsClientId=cid)],
                         default=1.0) for b in balls]

    log = _make_log(plan, raw, X_PO, com_O, hull_O, sup_vertex, sup_start)
    metrics = _metrics(plan, log, X_WO_goal, com_O, scene, params, collisions)
    metrics.update(force.metrics(params.force_tolerance))
    metrics["max_planned_ball_force"] = float(np.linalg.norm(plan.f_ball, axis=2).max())
    metrics.update(_release_metrics(log, com_O, X_WO_goal, clearance, params))
    metrics.update(_slip_metrics(log))
    metrics["failures"] = _failures(metrics)
    metrics["success"] = not metrics["failures"]
    metrics["planned_rows"] = n_planned
    metrics["collision_times"] = {k: round(v, 6) for k, v in sorted(first_hit.items())}
    metrics.update({
        "torque_saturation": saturated_steps / max(S - 1, 1),
        "convex_parts": len(parts),
        "collision_shape": {"triangles": len(shape.mesh.faces), "mesh_triangles": len(mesh.faces),
                            "tolerance": shape.tolerance},
        "perturbation": perturbation,
        "steps": S - 1,
        "duration": float(plan.t[-1] - plan.t[0]),
    })
    wall = time.perf_counter() - wall0
    duration = float(plan.t[-1] - plan.t[0])
    timings = {"total_s": wall, "loop_s": t_loop, "loop_cpu_s": c_loop, "decomposition_s": t_dec,
               "decomposition_cached": cache_hit, "sim_speed": duration / max(t_loop, 1e-9),
               "sim_speed_cpu": duration / max(c_loop, 1e-9), "sim_speed_total": duration / max(wall, 1e-9)}
    return Execution(log=log, metrics=metrics, frames=images, timings=timings)


def _make_log(plan: Plan, raw: dict, X_PO, com_O, hull_O, sup_vertex, sup_start) -> dict[str, np.ndarray]:
    """The per-row log (:data:`LOG_FIELDS`) from the raw samples of the loop, vectorized."""
    X_WP = se3.make_transform(se3.matrix_from_quat(raw["quat_P"]), raw["pos_P"])
    X = X_WP @ X_PO
    Xp = plan.X_WO
    log: dict[str, np.ndarray] = {"t": plan.t.copy(), "primitive": plan.primitive.copy(), "kind": plan.kind.copy()}
    log.update(se3.columns_from_matrix(X))
    log.update({"plan_" + c: v for c, v in se3.columns_from_matrix(Xp).items()})
    log["com_error"] = np.linalg.norm(se3.transform_points(X, com_O) - se3.transform_points(Xp, com_O), axis=1)
    R_rel = X[:, :3, :3] @ np.swapaxes(Xp[:, :3, :3], 1, 2)
    log["rot_error"] = np.linalg.norm(Rotation.from_matrix(R_rel).as_rotvec(), axis=1)
    up, up_plan = X[:, 2, :3], Xp[:, 2, :3]  # world z in O: the object's view of "up"
    log["tilt_error"] = np.arccos(np.clip(np.sum(up * up_plan, axis=1), -1.0, 1.0))
    H = se3.transform_points(X[:, None], hull_O[None])  # (T, n, 3)
    rows = np.arange(len(X))
    v = H[rows, sup_vertex[:, 0]]
    log["pivot_x"], log["pivot_y"], log["pivot_z"] = v[:, 0].copy(), v[:, 1].copy(), v[:, 2].copy()
    slip = [np.linalg.norm(H[rows, sup_vertex[:, i], :2] - H[sup_start, sup_vertex[:, i], :2], axis=1)
            for i in range(2)]
    log["pivot_slip"] = np.maximum(*slip)
    # The rotation the object made since its stretch began that the plan did not: 0 for a pivot
    # that turns as planned, the whole turn for a hold that should not turn at all.
    R_act = X[:, :3, :3] @ np.swapaxes(X[sup_start, :3, :3], 1, 2)
    R_pln = Xp[:, :3, :3] @ np.swapaxes(Xp[sup_start, :3, :3], 1, 2)
    log["support_rotation_slip"] = Rotation.from_matrix(R_act @ np.swapaxes(R_pln, 1, 2)).magnitude()
    log["lowest_z"] = H[:, :, 2].min(axis=1)
    log["left_force"], log["right_force"] = raw["f_ball"][:, 0].copy(), raw["f_ball"][:, 1].copy()
    log["left_touch"], log["right_touch"] = raw["touch"][:, 0].copy(), raw["touch"][:, 1].copy()
    log["table_force"] = raw["f_table"]
    err = np.linalg.norm(raw["ball"] - plan.p_ball, axis=2)
    log["left_ball_error"], log["right_ball_error"] = err[:, 0].copy(), err[:, 1].copy()
    log["joint_error"] = np.abs(raw["q"] - plan.q).max(axis=(1, 2))
    log["penetration"] = raw["pen"]
    log["torque_saturated"] = raw["sat"]
    log["q_left"], log["q_right"] = raw["q"][:, 0].copy(), raw["q"][:, 1].copy()
    return {f.name: log[f.name] for f in LOG_FIELDS}


@dataclass(frozen=True)
class Camera:
    """Where the rendered frames look from: ``target`` (3,) m in W, ``distance`` m, ``yaw_deg`` and
    ``pitch_deg`` in PyBullet's convention (the eye lies along (sin yaw, -cos yaw) from the target)."""

    target: tuple[float, float, float]
    distance: float
    yaw_deg: float
    pitch_deg: float


def scene_camera(scene, X_WO_start, X_WO_goal, com_O, swing_deg: float = 35.0) -> Camera:
    """The camera for a scene's frames: from the far side of the table from the robot, so that its torso
    and arms are behind the object, not in front of it (a fixed camera behind the robot lost the object
    behind the torso in Exp. 3), swung by ``swing_deg`` toward the side the object moves to, and far
    enough to frame the table. Aimed at the middle of the start's and the goal's CoM, 0.1 m up."""
    c0, c1 = se3.transform_points(X_WO_start, com_O), se3.transform_points(X_WO_goal, com_O)
    target = (c0 + c1) / 2
    away = target[:2] - scene.base_transform()[:2, 3]
    move = c1[:2] - c0[:2]
    side = 1.0 if away[0] * move[1] - away[1] * move[0] >= 0 else -1.0
    phi = math.atan2(away[1], away[0]) + side * math.radians(swing_deg)
    return Camera((float(target[0]), float(target[1]), float(target[2]) + 0.1),
                  0.9 + 0.8 * float(max(scene.table.size)), math.degrees(phi) + 90.0, -35.0)


def _add_goal_footprint(mesh, X_WO_goal, cid) -> None:
    """A gold plate 1 mm thick on the table where the goal's convex footprint lies (visual only)."""
    from scipy.spatial import ConvexHull

    xy = se3.transform_points(X_WO_goal, np.asarray(mesh.vertices))[:, :2]
    ring = xy[ConvexHull(xy).vertices]
    n = len(ring)
    v = np.concatenate([np.c_[ring, np.full(n, 2e-4)], np.c_[ring, np.full(n, 1.2e-3)]])
    tri = [(0, i + 1, i) for i in range(1, n - 1)] + [(n, n + i, n + i + 1) for i in range(1, n - 1)]
    tri += [(i, (i + 1) % n, n + (i + 1) % n) for i in range(n)] + [(i, n + (i + 1) % n, n + i) for i in range(n)]
    vis = p.createVisualShape(p.GEOM_MESH, vertices=v.tolist(), indices=np.asarray(tri).ravel().tolist(),
                              rgbaColor=[1.0, 0.75, 0.1, 1.0], physicsClientId=cid)
    p.createMultiBody(0.0, -1, vis, physicsClientId=cid)


def _render(cid, params: Params, camera: Camera) -> np.ndarray:
    """One ``(height, width, 3)`` uint8 RGB frame from ``camera`` (tiny renderer: works headless)."""
    view = p.computeViewMatrixFromYawPitchRoll(list(camera.target), camera.distance, camera.yaw_deg,
                                               camera.pitch_deg, 0.0, 2, physicsClientId=cid)
    proj = p.computeProjectionMatrixFOV(50.0, params.width / params.height, 0.05, 10.0, physicsClientId=cid)
    img = p.getCameraImage(params.width, params.height, view, proj, renderer=p.ER_TINY_RENDERER,
                           physicsClientId=cid)[2]
    return np.asarray(img, dtype=np.uint8).reshape(params.height, params.width, 4)[:, :, :3].copy()


def off_the_table(scene, com, com_plan, com_error, fall_distance: float, edge_band: float) -> np.ndarray:
    """Rows ``(T,)`` where the object has left the table: its CoM ``com (T, 3)`` beyond the table's edge
    where the plan's ``com_plan`` lies on the table more than ``edge_band`` (m) inside it, or beyond it
    and ``fall_distance`` from the plan's (``com_error (T,)``; in USP the plan itself holds the CoM
    overhanging, held by a ball, and a plan within ``edge_band`` of the edge, a catch or a pivot at a USP
    pose whose CoM lies on the edge, is judged the same way: tracking it, the CoM crosses the edge by
    a fraction of a millimetre without falling), or below the top."""
    err = np.asarray(com_error)
    return (~scene.on_table(com) & (scene.on_table(com_plan, margin=edge_band) | (err > fall_distance))) \
        | (com[:, 2] < 0.0)


def path_tilt(plan: Plan, X_WO: np.ndarray) -> np.ndarray:
    """Per row, the angle (rad) between the object's up axis in the executed poses ``X_WO (T, 4, 4)``
    and in the plan's: the same row's, but in a tumble the nearest of that tumble's planned poses. A
    roll follows its path at gravity's pace, not the plan's clock (a drop tips early when its CoM
    lies off the nominal one), so an object on the planned roll ahead of time or behind has not
    fallen; one that leaves the roll, rolls back or goes beyond it has."""
    up, up_plan = X_WO[:, 2, :3], plan.X_WO[:, 2, :3]  # world z seen in O
    cos = np.sum(up * up_plan, axis=1)
    for s, e in _stretches(plan):
        if plan.kind[s] == "tumble":
            cos[s:e] = (up[s:e] @ up_plan[s:e].T).max(axis=1)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _metrics(plan: Plan, log, X_WO_goal, com_O, scene, params: Params, collisions) -> dict:
    """The deterministic metrics of :func:`simulate` from the log and the collisions seen."""
    X_end = se3.matrix_from_columns({c: log[c][-1:] for c in se3.POSE_COLUMNS})[0]
    c_end = se3.transform_points(X_end, com_O)
    c_goal = se3.transform_points(X_WO_goal, com_O)
    yaw = float(se3.yaw_of(X_end[:3, :3] @ X_WO_goal[:3, :3].T))
    X_all = se3.matrix_from_columns({c: log[c] for c in se3.POSE_COLUMNS})
    com_all = se3.transform_points(X_all, com_O)
    tilt = float(np.degrees(path_tilt(plan, X_all).max()))
    com_plan = se3.transform_points(plan.X_WO, com_O)
    off_table = off_the_table(scene, com_all, com_plan, log["com_error"], params.fall_distance, params.success_pos)
    fell_reason = ""
    if tilt > params.fall_tilt_deg:
        fell_reason = f"tilted {tilt:.1f} deg from the plan"
    elif off_table.any():
        fell_reason = f"left the table at t = {plan.t[np.argmax(off_table)]:.3f} s"
    pivot, tumble = plan.kind == "pivot", plan.kind == "tumble"
    c_plan = se3.transform_points(plan.X_WO[-1], com_O)
    yaw_plan = float(se3.yaw_of(X_end[:3, :3] @ plan.X_WO[-1, :3, :3].T))
    out = {
        "final_position_error": float(np.linalg.norm(c_end[:2] - c_goal[:2])),
        "final_yaw_error_deg": abs(math.degrees(yaw)),
        "final_plan_position_error": float(np.linalg.norm(c_end[:2] - c_plan[:2])),
        "final_plan_yaw_error_deg": abs(math.degrees(yaw_plan)),
        "max_com_deviation": float(log["com_error"].max()),
        "max_rotation_deviation_deg": float(np.degrees(log["rot_error"].max())),
        "max_tilt_deviation_deg": tilt,
        "max_pivot_slip": float(log["pivot_slip"][pivot].max()) if pivot.any() else 0.0,
        "max_edge_slip": float(log["pivot_slip"][tumble].max()) if tumble.any() else 0.0,
        "max_penetration": float(log["penetration"].max()),
        "max_ball_force": float(max(log["left_force"].max(), log["right_force"].max())),
        "max_joint_error": float(log["joint_error"].max()),
        "fell": bool(fell_reason),
        "fell_reason": fell_reason,
        "robot_table_contacts": sorted(collisions["robot_table"]),
        "robot_obstacle_contacts": sorted(collisions["robot_obstacle"]),
        "robot_object_contacts": sorted(collisions["robot_object"]),
        "object_obstacle_contacts": sorted(collisions["object_obstacle"]),
    }
    out["collision"] = bool(out["robot_table_contacts"] or out["robot_obstacle_contacts"]
                            or out["robot_object_contacts"] or out["object_obstacle_contacts"])
    out["position_ok"] = bool(out["final_position_error"] <= params.success_pos)
    out["yaw_ok"] = bool(out["final_yaw_error_deg"] <= params.success_yaw_deg)
    return out


#: Failure codes of an execution, in the order :func:`_failures` lists them (the first is the headline).
FAILURES = ("fell", "collision", "over_force_bound", "not_released", "not_retreated", "tilted", "not_at_rest",
            "missed_position", "missed_yaw")


def _failures(m: dict) -> list[str]:
    """The criteria an execution's metrics ``m`` fail, as codes of :data:`FAILURES` (empty: success)."""
    failed = {"fell": m["fell"], "collision": m["collision"], "over_force_bound": not m["within_force_bound"],
              "not_released": not m["released"], "not_retreated": not m["retreated"], "tilted": not m["tilt_ok"],
              "not_at_rest": not m["at_rest"], "missed_position": not m["position_ok"], "missed_yaw": not m["yaw_ok"]}
    return [k for k in FAILURES if failed[k]]


def _release_metrics(log: dict, com_O, X_WO_goal, clearance: list[float], params: Params) -> dict:
    """Whether the robot let go and the object stayed put, from the log's last rows.

    ``released``: no ball touches the object at the last row; ``release_time`` (s): the first row
    after the last one where a ball touched; ``final_ball_clearance`` (m, left and right: the ball
    surface's distance to the object at the end) and ``retreated`` (both at least
    ``retreat_clearance``); ``rest_duration`` (s, from the release to the end); over the last
    ``settle_time`` s of the run (from the release at the earliest) ``rest_drift`` (m, the CoM's
    largest displacement) and ``rest_rotation_deg`` (its largest rotation); ``at_rest``: released at
    least ``settle_time`` before the end, still over that window within ``rest_drift`` and
    ``rest_rotation_deg``, the lowest point on the table (within 2 mm): the object came to rest after
    the release and stayed so (a placement that ends with a short drop, as a tumble's slide, settles
    first); ``final_tilt_error_deg``: the angle between the object's up axis and the goal's (W z seen
    in O), and ``tilt_ok``.
    """
    X = se3.matrix_from_columns({c: log[c] for c in se3.POSE_COLUMNS})
    touch = np.asarray(log["left_touch"], dtype=bool) | np.asarray(log["right_touch"], dtype=bool)
    hits = np.flatnonzero(touch)
    r0 = int(hits[-1]) + 1 if len(hits) else 0
    released = r0 < len(X)
    r0 = min(r0, len(X) - 1)
    t = np.asarray(log["t"], dtype=float)
    w0 = max(r0, int(np.searchsorted(t, t[-1] - params.settle_time - 1e-9)))
    com = se3.transform_points(X[w0:], com_O)
    turn = Rotation.from_matrix(X[w0:, :3, :3] @ X[w0, :3, :3].T).magnitude()
    duration = float(t[-1] - t[r0]) if released else 0.0
    drift = float(np.linalg.norm(com - com[0], axis=1).max())
    rot = float(np.degrees(turn.max()))
    on_table = abs(float(log["lowest_z"][-1])) <= 0.002
    tilt = math.degrees(math.acos(float(np.clip(X[-1, 2, :3] @ X_WO_goal[2, :3], -1.0, 1.0))))
    return {"released": bool(released), "release_time": float(log["t"][r0]) if released else None,
            "final_ball_clearance": [float(c) for c in clearance],
            "retreated": bool(min(clearance) >= params.retreat_clearance),
            "rest_duration": duration, "rest_drift": drift, "rest_rotation_deg": rot,
            "at_rest": bool(released and duration >= params.settle_time - 1e-9 and drift <= params.rest_drift
                            and rot <= params.rest_rotation_deg and on_table),
            "final_tilt_error_deg": tilt, "tilt_ok": bool(tilt <= params.success_tilt_deg)}


def _slip_metrics(log: dict) -> dict:
    """Slip of the support per stretch (primitive and kind): ``slip`` lists ``primitive``, ``kind``,
    ``translation`` (m, the largest ``pivot_slip``) and ``rotation_deg`` (the largest
    ``support_rotation_slip``); ``max_support_slip`` (m) and ``max_support_rotation_slip_deg`` are
    the worst over all stretches, with the stretch (``worst_slip_primitive``,
    ``worst_rotation_slip_primitive``)."""
    prim, kind = np.asarray(log["primitive"]), np.asarray(log["kind"]).astype(str)
    change = np.flatnonzero(np.concatenate([[True], (prim[1:] != prim[:-1]) | (kind[1:] != kind[:-1])]))
    ends = np.concatenate([change[1:], [len(prim)]])
    rows = [{"primitive": int(prim[s]), "kind": str(kind[s]),
             "translation": float(np.max(log["pivot_slip"][s:e])),
             "rotation_deg": float(np.degrees(np.max(log["support_rotation_slip"][s:e])))}
            for s, e in zip(change.tolist(), ends.tolist(), strict=True)]
    i = int(np.argmax([r["translation"] for r in rows]))
    k = int(np.argmax([r["rotation_deg"] for r in rows]))
    return {"slip": rows, "max_support_slip": rows[i]["translation"], "worst_slip_primitive": rows[i]["primitive"],
            "max_support_rotation_slip_deg": rows[k]["rotation_deg"],
            "worst_rotation_slip_primitive": rows[k]["primitive"]}


# ----------------------------------------------------------------------------------------------------
# Stage I/O


def run(scene_path, analysis_dir, trajectories_path, out_dir, params: Params = Params(), frames: int | None = 0,
        gui: bool = False, producer: str = "execute") -> Execution:
    """``pivot execute``: simulate ``trajectories.parquet`` and write the execution artifacts.

    Reads the scene, the analysis (``analysis.json`` for mass, CoM and inertia, ``object.ply``, and the
    placements for the goal pose ``X_WO_goal`` of the scene's goal) and the trajectories; writes into
    ``out_dir``: ``execution.parquet`` (the log, :data:`LOG_FIELDS`), ``execution.json`` (the metrics)
    with ``execution.json.timings.json`` (wall-clock, kept apart) and, when ``frames > 0`` (None: one
    per second of motion), ``frames.npz`` (``frames (k, height, width, 3)`` uint8, for ``pivot show
    execution``; a stale one is removed otherwise). Returns the :class:`Execution`.
    """
    from stages.objectmodel import load_object_model
    from stages.sample import placement_pose

    scene = load_scene(scene_path)
    a = Path(analysis_dir)
    summary = artifacts.read_json(a / "analysis.json", "analysis")
    model, _ = load_object_model(a)
    X_goal, _ = placement_pose(scene.goal, model, "goal")
    table = artifacts.read_table(trajectories_path, "trajectories", required=[f.name for f in TRAJECTORY_FIELDS])
    provenance.check_made_from(trajectories_path, table.meta, scene, a)
    if frames is None:  # one frame per second of motion
        frames = max(2, round(float(table["t"][-1]) - float(table["t"][0])))
    with about(trajectories_path):
        ex = simulate(scene, a / "object.ply", float(summary["mass"]), np.asarray(summary["com"], dtype=float),
                      np.asarray(summary["inertia"], dtype=float), table.columns, X_goal, params, gui=gui,
                      frames=frames)
    # Two figures for the report: the CoM's error along x to the goal (Table 2 measures reach along x)
    # and the rotation about z achieved from the first to the last row (Exp. 2).
    X = se3.matrix_from_columns({k: np.asarray(ex.log[k])[[0, -1]] for k in se3.POSE_COLUMNS})
    com = np.asarray(summary["com"], dtype=float)
    metrics = {**ex.metrics,
               "final_com_error_x": float(se3.transform_points(X[1], com)[0] - se3.transform_points(X_goal, com)[0]),
               "achieved_yaw_deg": float(np.degrees(se3.yaw_of(X[1, :3, :3] @ X[0, :3, :3].T)))}
    out = Path(out_dir)
    inputs = {"scene": scene_path, "analysis": a / "analysis.json", "object": a / "object.ply",
              "trajectories": trajectories_path}
    meta_params = {**asdict(params), "frames": frames}
    cols = {k: (list(v) if np.ndim(v) == 2 else v) for k, v in ex.log.items()}  # joints as list columns
    artifacts.write_table(out / "execution.parquet", cols, LOG_FIELDS,
                          artifacts.make_meta("execution", meta_params, inputs, producer))
    frames_path = out / "frames.npz"  # before the target (execution.json), which vouches for it
    if ex.frames:
        with atomic_path(frames_path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, frames=np.stack(ex.frames))
    elif frames_path.exists():
        frames_path.unlink()
    artifacts.write_json(out / "execution.json", metrics,
                         artifacts.make_meta("execution_metrics", meta_params, inputs, producer))
    artifacts.write_timings(out / "execution.json", {"wall": ex.timings["total_s"], **{
        k: v for k, v in ex.timings.items() if k != "total_s"}})
    stagelog.log_execution(metrics, ex.log)
    return ex


def run_seeds(scene_path, analysis_dir, trajectories_path, out_dir, params: Params, seeds: int,
              producer: str = "execute", required_share: float = 0.9) -> dict:
    """``pivot execute --seeds K``: robustness as a distribution (issue 15).

    Runs :func:`run` with seeds ``1..seeds`` (each perturbed, see :class:`Params`; everything else as
    ``params``) into ``<out_dir>/seeds/seed<k>/`` and writes ``<out_dir>/robustness.json``: ``seeds``,
    ``succeeded``, ``required`` (``ceil(required_share * seeds)``: 9 of 10), ``failures`` (code ->
    number of seeds failing it) and per seed ``runs``: ``seed``, ``success``, ``failures``,
    ``final_position_error`` (m), ``final_yaw_error_deg``, ``final_tilt_error_deg``, ``max_ball_force``
    (N), ``max_support_slip`` (m), ``max_support_rotation_slip_deg`` and ``perturbation``. Returns it.
    """
    from dataclasses import replace

    out = Path(out_dir)
    runs = []
    for k in range(1, seeds + 1):
        m = run(scene_path, analysis_dir, trajectories_path, out / "seeds" / f"seed{k}", replace(params, seed=k),
                frames=0, producer=f"{producer} --seed {k}").metrics
        runs.append({"seed": k, **{key: m[key] for key in (
            "success", "failures", "final_position_error", "final_yaw_error_deg", "final_tilt_error_deg",
            "max_ball_force", "max_support_slip", "max_support_rotation_slip_deg", "perturbation")}})
    counts: dict[str, int] = {}
    for r in runs:
        for f in r["failures"]:
            counts[f] = counts.get(f, 0) + 1
    summary = {"seeds": seeds, "succeeded": sum(r["success"] for r in runs),
               "required": math.ceil(required_share * seeds - 1e-9), "failures": counts, "runs": runs}
    inputs = {"scene": scene_path, "analysis": Path(analysis_dir) / "analysis.json",
              "trajectories": trajectories_path}
    artifacts.write_json(out / "robustness.json", summary,
                         artifacts.make_meta("robustness", {**asdict(params), "seeds": seeds}, inputs, producer))
    return summary

