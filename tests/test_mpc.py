"""Tests of stages.mpc: references, friction pyramids, the rotation model, pivot and tumble MPC."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages import mpc, se3
from stages.errors import InputError
from tests.conftest import PIANO, REPO

A = 0.2  # box edge (m)
MASS = 2.0  # kg
I_COM = MASS * A * A / 6.0 * np.eye(3)  # solid cube about its centre
G = 9.81
# Box resting on its bottom face, O at its centre.
X_WO0 = se3.make_transform(np.eye(3), [0.0, 0.0, A / 2])
P0_O = np.array([-A / 2, -A / 2, -A / 2])  # the pivot vertex
P0_W = se3.transform_points(X_WO0, P0_O)
BOTTOM_O = np.array([[x, y, -A / 2] for x in (-A / 2, A / 2) for y in (-A / 2, A / 2)])
# Grasp on the two y faces, high and beyond the CoM away from p0 (notes: >= 0.85 of the height,
# 3-5 cm past the CoM). Inward normals.
P_C_O = np.array([[0.06, -A / 2, 0.09], [0.06, A / 2, 0.09]])
N_C_O = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
YAW = np.deg2rad(15.0)
TILT = np.deg2rad(8.0)
DURATIONS = (0.8, 1.2, 0.8)  # tilt, rotate, lower (s): 2.8 s per step (notes: >= 2.5 s)
# Constraint tolerance (N): piqp solves to 1e-8 relative; the recorded forces are the QP's own.
F_TOL = 1e-6


def _goal():
    return se3.transform_about_line(P0_W, [0.0, 0.0, 1.0], YAW) @ X_WO0


@pytest.fixture(scope="module")
def pivot_run():
    t, X_ref, phase = mpc.pivot_reference(X_WO0, _goal(), P0_W, TILT, 0.02, DURATIONS)
    res = mpc.run_pivot_mpc(MASS, I_COM, np.zeros(3), P_C_O, N_C_O, P0_W, t, X_ref, mpc.Params())
    return t, X_ref, phase, res


def _rot_angle(R_a, R_b):
    return np.linalg.norm(Rotation.from_matrix(R_a @ np.swapaxes(R_b, -1, -2)).as_rotvec(), axis=-1)


# ------------------------------------------------------------------------------------------
# References
# ------------------------------------------------------------------------------------------


def test_pivot_reference_tilts_rotates_lowers_about_fixed_vertex_to_goal():
    t, X, phase = mpc.pivot_reference(X_WO0, _goal(), P0_W, TILT, 0.02, DURATIONS)
    assert len(t) == round(sum(DURATIONS) / 0.02) + 1
    assert np.allclose(np.diff(t), 0.02)
    # Phases in order, each non-empty.
    labels = [p for i, p in enumerate(phase) if i == 0 or p != phase[i - 1]]
    assert labels == ["tilt", "rotate", "lower"]
    # The vertex stays put to rounding; start and goal are met exactly.
    assert np.abs(se3.transform_points(X, P0_O) - P0_W).max() < 1e-12
    assert np.allclose(X[0], X_WO0, atol=1e-12) and np.allclose(X[-1], _goal(), atol=1e-12)
    # Tilt (angle of the body z axis from vertical) peaks at the requested tilt while rotating.
    tilt = se3.tilt_of(X[:, :3, :3])
    assert np.allclose(tilt[phase == "rotate"], TILT, atol=1e-9)
    assert tilt.max() <= TILT + 1e-12
    # Raising the CoM side lifts the three other bottom vertices (by sin(tilt) * their distance
    # along p0 -> CoM: 0.141 m * sin 8 deg = 19.7 mm for the two neighbours).
    z = se3.transform_points(X[:, None], BOTTOM_O[None])[..., 2]
    others = np.sort(z[phase == "rotate"], axis=1)[:, 1:]
    assert others.min() == pytest.approx(A / np.sqrt(2) * np.sin(TILT), abs=1e-9)
    # Minimum-jerk: at rest at every phase boundary. The mean speed of a far vertex over the step
    # next to a boundary is ~5.3 tau^2 of the phase's peak (tau = dt / T_phase <= 0.025, so
    # <= 0.33 %); a profile that starts at speed would give tens of percent.
    far = se3.transform_points(X, np.array([A / 2, A / 2, A / 2]))
    speed = np.linalg.norm(np.diff(far, axis=0), axis=1) / 0.02
    for boundary in (0.0, 0.8, 2.0, 2.8):
        k = int(round(boundary / 0.02))
        assert speed[max(k - 1, 0):k + 1].max() < 0.005 * speed.max()


def test_pivot_reference_rejects_goal_that_is_not_a_rotation_about_the_vertical_through_p0():
    shifted = _goal().copy()
    shifted[0, 3] += 0.01
    with pytest.raises(InputError):
        mpc.pivot_reference(X_WO0, shifted, P0_W, TILT, 0.02, DURATIONS)


def test_pivot_axes_are_the_references_yaw_and_tilt_axis_and_refuse_what_it_refuses():
    """``pivot_axes`` (what ``pivot graph`` asks of a pivot link when it does not sample it): the yaw
    the reference turns by and the axis it tilts about (perpendicular to the CoM's direction, level);
    a goal off the rotation about p0's vertical is refused as ``pivot_reference`` refuses it."""
    yaw, axis = mpc.pivot_axes(X_WO0, _goal(), P0_W)
    assert yaw == pytest.approx(YAW, abs=1e-12)
    d = X_WO0[:3, 3] - P0_W
    assert abs(axis[2]) < 1e-12 and abs(axis[:2] @ d[:2]) < 1e-12 and np.linalg.norm(axis) == pytest.approx(1.0)
    _, X, phase = mpc.pivot_reference(X_WO0, _goal(), P0_W, TILT, 0.02, DURATIONS)
    tilted = X[np.argmax(phase == "rotate")]  # the tilt done, the turn not begun
    assert np.abs(tilted - se3.transform_about_line(P0_W, axis, TILT) @ X_WO0).max() < 1e-9
    shifted = _goal().copy()
    shifted[0, 3] += 0.01
    with pytest.raises(InputError):
        mpc.pivot_axes(X_WO0, shifted, P0_W)


def test_tumble_reference_turns_about_the_edge_by_the_angle():
    edge = np.array([[A / 2, -A / 2, 0.0], [A / 2, A / 2, 0.0]])
    t, X, phase = mpc.tumble_reference(X_WO0, edge[0], [0.0, 1.0, 0.0], np.pi / 2, 0.02, 2.0)
    assert set(phase) == {"tumble"}
    edge_O = se3.transform_points(se3.invert(X_WO0), edge)
    assert np.abs(se3.transform_points(X[:, None], edge_O[None]) - edge).max() < 1e-12
    assert _rot_angle(X[-1, :3, :3], X[0, :3, :3]) == pytest.approx(np.pi / 2, abs=1e-12)


# ------------------------------------------------------------------------------------------
# Friction pyramids
# ------------------------------------------------------------------------------------------


def test_friction_pyramid_rays_lie_on_the_cone_and_on_two_faces_each():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    mu = 0.5
    rays = mpc.friction_pyramid_rays(n, mu)  # (5, 6, 3)
    H = mpc.friction_pyramid_halfspaces(n, mu)  # (5, 6, 3)
    # On the cone: tangential part = mu * normal part.
    fn = np.einsum("kri,ki->kr", rays, n)
    ft = np.linalg.norm(rays - fn[..., None] * n[:, None], axis=-1)
    assert np.allclose(ft, mu * fn)
    # Each ray satisfies every face and makes exactly two of them tight (inscribed pyramid).
    vals = np.einsum("kfi,kri->krf", H, rays)
    assert vals.max() < 1e-12
    assert np.all(np.sum(np.abs(vals) < 1e-12, axis=-1) == 2)


def test_friction_pyramid_contains_the_inscribed_disc_and_excludes_outside_the_cone():
    n = np.array([0.0, 0.0, 1.0])
    mu = 0.5
    H = mpc.friction_pyramid_halfspaces(n, mu)
    ang = np.linspace(0.0, 2.0 * np.pi, 361)
    t = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
    inside = n + 0.999 * mu * np.cos(np.pi / 6) * t  # inside the hexagon's inscribed circle
    outside = n + 1.001 * mu * t  # just outside the cone
    assert (inside @ H.T).max() < 0.0
    assert np.all((outside @ H.T).max(axis=1) > 0.0)
    assert (-n @ H.T).max() > 0.0  # pulling is excluded


# ------------------------------------------------------------------------------------------
# Rotation model
# ------------------------------------------------------------------------------------------


def _model():
    return mpc.make_rotation_model(MASS, I_COM, np.zeros(3), P_C_O, N_C_O, P0_O[None], G)


def test_rotation_model_uses_parallel_axis_inertia_about_the_vertex():
    model = _model()
    r = -P0_O
    expected = I_COM + MASS * (r @ r * np.eye(3) - np.outer(r, r))
    assert np.allclose(model.I_A_O, expected)
    # About a cube's corner the inertia about the body diagonal is m a^2 / 6 (the diagonal
    # passes through the CoM), and 2 m a^2 / 3 about an edge.
    diag = np.ones(3) / np.sqrt(3)
    assert diag @ model.I_A_O @ diag == pytest.approx(MASS * A * A / 6)
    assert model.I_A_O[0, 0] == pytest.approx(2 * MASS * A * A / 3)


@pytest.mark.parametrize("dt", [0.02, 0.01])
def test_linear_prediction_matches_nonlinear_integration_for_a_small_step(dt):
    model = _model()
    R_bar = Rotation.from_rotvec([0.1, -0.1, 0.3]).as_matrix()
    omega_bar = np.array([0.05, -0.05, 0.4])
    phi_ref = omega_bar * dt
    # Forces that nearly hold the object (the closed loop's regime): least squares on nu' = 0.
    lin0 = mpc.linearize_rotation(model, R_bar[None], omega_bar[None], np.zeros((1, 2, 3)), phi_ref[None], dt)
    f = np.linalg.lstsq(lin0.Na[0], -lin0.ca[0], rcond=None)[0].reshape(2, 3)
    delta0 = np.array([1e-3, -2e-3, 5e-4])
    omega0 = omega_bar + np.array([0.01, -0.02, 0.03])
    lin = mpc.linearize_rotation(model, R_bar[None], omega_bar[None], f[None], phi_ref[None], dt)
    x1 = lin.A[0] @ np.r_[delta0, omega0] + lin.B[0] @ f.reshape(6) + lin.D[0]
    R0 = Rotation.from_rotvec(delta0).as_matrix() @ R_bar
    R1, omega1 = mpc.integrate_rotation(model, R0, omega0, f, dt, substeps=8)
    delta1 = Rotation.from_matrix(R1 @ (Rotation.from_rotvec(phi_ref).as_matrix() @ R_bar).T).as_rotvec()
    # Dropped terms: second order in the deviations (|delta| 2e-3 rad, |d omega| 0.04 rad/s give
    # torques ~ (f r + m g r) |delta|^2 ~ 2e-5 N m, i.e. ~1e-5 rad/s over a step for an inertia
    # of 0.07 kg m^2) and the turning of the inertia (|omega| |omega'| dt^2 / 2 <= 1e-5 rad/s).
    # The rotation error is a further factor dt smaller.
    assert np.abs(x1[:3] - delta1).max() < 1e-6
    assert np.abs(x1[3:] - omega1).max() < 5e-5
    # Without its deviation and force-rate terms the model is visibly worse, so the test bites:
    # the plain constant-acceleration step misses the turning lever arms.
    plain = (np.r_[delta0, omega0] + np.r_[dt * (omega0 - omega_bar), np.zeros(3)]
             + np.r_[0.5 * dt * dt * (lin0.Na[0] @ f.reshape(6) + lin0.ca[0]),
                     dt * (lin0.Na[0] @ f.reshape(6) + lin0.ca[0])])
    assert np.abs(plain[3:] - omega1).max() > 5 * np.abs(x1[3:] - omega1).max()


def test_integrate_rotation_conserves_energy_without_forces_or_gravity():
    model = mpc.make_rotation_model(MASS, np.diag([0.01, 0.02, 0.03]), np.zeros(3), P_C_O, N_C_O,
                                    np.zeros((1, 3)), g=0.0)
    R = np.eye(3)
    omega = np.array([1.0, 0.5, -0.7])
    e0 = 0.5 * omega @ model.I_A_O @ omega
    for _ in range(200):
        R, omega = mpc.integrate_rotation(model, R, omega, np.zeros((2, 3)), 0.01)
    I_W = R @ model.I_A_O @ R.T
    assert 0.5 * omega @ I_W @ omega == pytest.approx(e0, rel=1e-8)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)


# ------------------------------------------------------------------------------------------
# Pivot MPC
# ------------------------------------------------------------------------------------------


def test_pivot_mpc_box_reaches_the_15deg_reference(pivot_run):
    t, X_ref, phase, res = pivot_run
    assert res.ok and res.fail_step == -1
    err = res.tracking_error
    # Tolerances from the physics budget (notes: per-step pose error < 1 mm / 0.2 deg). With
    # p0 fixed, a rotation error e moves a point of the box at most e * 0.35 m (the farthest
    # vertex from p0). Along the way 1e-3 rad (0.35 mm, a third of the budget); at the goal,
    # where the reference comes to rest, 2e-4 rad (0.07 mm). Measured: ~2e-4 and ~5e-5; holding
    # the forces piecewise constant instead of piecewise linear gives ~2e-3 and fails.
    assert err.max() < 1e-3
    assert err[-1] < 2e-4
    assert np.abs(res.X_WO[-1] - _goal()).max() < 2e-4 * 0.35
    # The vertex does not move (the model rotates about it) and the others stay up while yawing.
    assert np.abs(se3.transform_points(res.X_WO, P0_O) - P0_W).max() < 1e-12
    z = se3.transform_points(res.X_WO[:, None], BOTTOM_O[None])[..., 2]
    assert np.sort(z[phase == "rotate"], axis=1)[:, 1].min() > 0.003  # notes: >= 3 mm


def _pyramids_at_start(X_WO, p_c_O, n_c_O, supports_W, mu_eef, mu_table):
    """The pyramids the MPC must use: framed at the first pose, EEFs fixed in O, table in W."""
    com_W = X_WO[:3, 3]  # the CoM is O's origin in these tests
    H_eef_W = mpc.friction_pyramid_halfspaces(se3.rotate_vectors(X_WO, n_c_O), mu_eef,
                                              radial=se3.transform_points(X_WO, p_c_O) - com_W)
    H_tab = mpc.friction_pyramid_halfspaces(np.broadcast_to([0.0, 0.0, 1.0], supports_W.shape), mu_table,
                                            radial=supports_W - com_W)
    return H_eef_W @ X_WO[:3, :3], H_tab


def test_pivot_mpc_forces_satisfy_every_constraint_at_every_step(pivot_run):
    _, X_ref, _, res = pivot_run
    p = mpc.Params()
    H_eef_O, H_tab = _pyramids_at_start(X_ref[0], P_C_O, N_C_O, P0_W[None], p.mu_eef, p.mu_table)
    assert np.allclose(res.pyramid_eef_O, H_eef_O) and np.allclose(res.pyramid_table_W, H_tab)
    # The EEF pyramids turn with the object (rows fixed in O).
    assert np.einsum("kfi,tki->tkf", H_eef_O, res.f_eef_O).max() < F_TOL
    # Hence inside the (round) friction cone too, and within the normal-force bounds.
    R = res.X_WO[:, :3, :3]
    n_W = np.einsum("tij,kj->tki", R, N_C_O)
    fn = np.einsum("tki,tki->tk", n_W, res.f_eef_W)
    ft = np.linalg.norm(res.f_eef_W - fn[..., None] * n_W, axis=-1)
    assert (ft - p.mu_eef * fn).max() < F_TOL
    assert fn.min() > p.f_min - F_TOL and fn.max() < p.f_max + F_TOL
    assert (res.f_table_W @ H_tab[0].T).max() < F_TOL
    assert res.f_table_W[:, 2].min() >= 0.0
    # The reported forces are the object-frame input turned into W.
    assert np.allclose(res.f_eef_W, np.einsum("tij,tkj->tki", R, res.f_eef_O))


def test_pyramid_tangents_follow_the_stability_module_convention():
    stability = pytest.importorskip("stages.stability")
    rng = np.random.default_rng(3)
    n = rng.normal(size=(20, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[:4] = [[0, 0, 1], [0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # table contacts and side contacts
    r = rng.normal(size=(20, 3))
    t1, t2 = mpc.tangent_basis(n, radial=r)
    s1, s2 = stability.contact_frames(n, r)
    assert np.allclose(t1, s1) and np.allclose(t2, s2)


def test_pivot_mpc_table_reaction_is_the_newton_euler_balance(pivot_run):
    t, _, _, res = pivot_run
    model = _model()
    for k in range(0, len(t), 7):
        f0 = mpc.support_reactions(model, res.X_WO[k, :3, :3], res.omega_W[k], res.f_eef_O[k])
        assert np.allclose(f0[0], res.f_table_W[k], atol=1e-9)
    # Momentum: the CoM's finite-difference acceleration matches the net force / m. The central
    # difference averages the acceleration over +-dt, so its error is bounded by how much the
    # net force changes in one step.
    p = res.X_WO[:, :3, 3]
    acc = (p[2:] - 2 * p[1:-1] + p[:-2]) / 0.02**2
    F = (res.f_table_W + res.f_eef_W.sum(axis=1) + np.array([0.0, 0.0, -MASS * G])) / MASS
    bound = np.abs(np.diff(F, axis=0)).max()
    assert np.abs(acc - F[1:-1]).max() <= bound


def test_pivot_mpc_is_deterministic(pivot_run):
    t, X_ref, _, res = pivot_run
    again = mpc.run_pivot_mpc(MASS, I_COM, np.zeros(3), P_C_O, N_C_O, P0_W, t, X_ref, mpc.Params())
    for name in ("X_WO", "omega_W", "f_eef_W", "f_eef_O", "p_eef_W", "f_table_W", "f_support_W",
                 "tracking_error", "n_iter", "contact_mask"):
        assert np.array_equal(getattr(res, name), getattr(again, name)), name
    assert (res.status, res.fail_step, res.fail_reason) == (again.status, again.fail_step, again.fail_reason)


def test_pivot_mpc_is_invariant_to_a_yaw_and_shift_of_the_scene():
    # Gravity is along -z, so the problem is the same after any rotation about z and translation.
    X_ref = np.repeat((se3.transform_about_line(P0_W, [1, -1, 0], TILT) @ X_WO0)[None], 15, axis=0)
    t = np.arange(15) * 0.02
    # The pyramids are framed from the normals, the vertical and the CoM, so they turn too.
    params = mpc.Params()
    res = mpc.run_pivot_mpc(MASS, I_COM, np.zeros(3), P_C_O, N_C_O, P0_W, t, X_ref, params)
    X_move = se3.make_transform(se3.rot_z(0.7), [0.3, -0.2, 0.0])
    moved = mpc.run_pivot_mpc(MASS, I_COM, np.zeros(3), P_C_O, N_C_O, se3.transform_points(X_move, P0_W), t,
                              X_move @ X_ref, params)
    assert res.ok and moved.ok
    assert np.allclose(moved.f_eef_O, res.f_eef_O, atol=1e-4)  # solver tolerance, not physics
    assert np.allclose(moved.X_WO, X_move @ res.X_WO, atol=1e-8)


def _cube_far_face_grasp():
    """Contacts on the two faces away from p0, mirror images across the plane x = y."""
    s, h = 0.05, 0.08
    p_c = np.array([[A / 2, s, h], [s, A / 2, h]])
    n_c = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return p_c, n_c


def _tilted_pose():
    return se3.transform_about_line(P0_W, [1.0, -1.0, 0.0], TILT) @ X_WO0


def _analytic_min_force(mu: float) -> float:
    """Smallest normal-force bound with which the EEFs hold the box at rest, tilted by TILT.

    Tilting about ``e = (1, -1, 0)/sqrt 2`` leaves the CoM ``h_d = a/sqrt2 cos - a/2 sin`` from the
    vertical through p0, so gravity needs ``m g h_d`` about e. Per unit normal force a contact
    gives at most ``max_k (r_i x ray_k) . e`` about e (a linear function over the pyramid peaks at
    an edge ray). The grasp and its pyramids are mirror images across x = y, which keeps e and
    flips the other torque components, so the two maximisers' other components cancel: the
    bound is attained, ``f_min = m g h_d / sum_i max_k (r_i x ray_k) . e``.
    """
    p_c, n_c = _cube_far_face_grasp()
    e = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    # The pyramids as the MPC frames them at the (tilted) pose, expressed in O.
    X_tilt = _tilted_pose()
    rays_W = mpc.friction_pyramid_rays(se3.rotate_vectors(X_tilt, n_c), mu, radial=se3.rotate_vectors(X_tilt, p_c))
    rays = rays_W @ X_tilt[:3, :3]
    swap = np.array([1, 0, 2])
    assert np.allclose(np.sort(rays[0][:, swap], axis=0), np.sort(rays[1], axis=0))  # mirror images
    lift = np.einsum("kri,i->kr", np.cross((p_c - P0_O)[:, None, :], rays), e).max(axis=1)
    h_d = A / np.sqrt(2) * np.cos(TILT) - A / 2 * np.sin(TILT)
    return MASS * G * h_d / lift.sum()


@pytest.mark.parametrize("factor, feasible", [(1.03, True), (0.97, False)])
def test_pivot_mpc_is_infeasible_exactly_below_the_analytic_force_limit(factor, feasible):
    mu = 0.5
    f_lim = _analytic_min_force(mu)
    assert 4.0 < f_lim < 6.0  # 4.65 N for this grasp, well above f_min = 2 N
    p_c, n_c = _cube_far_face_grasp()
    X_tilt = _tilted_pose()
    t = np.arange(50) * 0.02
    X_ref = np.repeat(X_tilt[None], len(t), axis=0)
    # A high table friction keeps the table out of it: the EEF bound alone decides.
    params = mpc.Params(f_max=factor * f_lim, mu_eef=mu, mu_table=2.0)
    res = mpc.run_pivot_mpc(MASS, I_COM, np.zeros(3), p_c, n_c, P0_W, t, X_ref, params)
    if feasible:
        assert res.ok
        assert res.tracking_error.max() < 1e-4
        fn = np.einsum("tki,ki->tk", res.f_eef_O, n_c)
        assert fn.max() <= params.f_max + F_TOL
        assert fn.max() > f_lim * (1 - 1e-3)  # it does need (nearly) the limit
    else:
        assert res.status == mpc.STATUS_INFEASIBLE
        assert 0 <= res.fail_step < len(t)
        assert res.fail_reason != ""
        assert np.all(np.isnan(res.f_eef_W[res.fail_step:]))
        assert np.all(np.isfinite(res.f_eef_W[:res.fail_step]))


def test_run_pivot_mpc_rejects_a_reference_that_moves_the_vertex():
    t, X, _ = mpc.pivot_reference(X_WO0, _goal(), P0_W, TILT, 0.02, DURATIONS)
    X = X.copy()
    X[5:, 0, 3] += 1e-3
    with pytest.raises(InputError):
        mpc.run_pivot_mpc(MASS, I_COM, np.zeros(3), P_C_O, N_C_O, P0_W, t, X)
    with pytest.raises(InputError):  # sampled at another step than Params.dt
        mpc.run_pivot_mpc(MASS, I_COM, np.zeros(3), P_C_O, N_C_O, P0_W, t * 2, X)


# ------------------------------------------------------------------------------------------
# Tumble MPC
# ------------------------------------------------------------------------------------------


def test_tumble_mpc_turns_the_box_onto_its_adjacent_face_with_a_catching_arm():
    edge_W = np.array([[A / 2, -A / 2, 0.0], [A / 2, A / 2, 0.0]])  # front bottom edge
    t, X_ref, _ = mpc.tumble_reference(X_WO0, edge_W[0], [0.0, 1.0, 0.0], np.pi / 2, 0.02, 3.0)
    # Pusher high on the back face; catcher high on the front face, switched on at 1 s (Fig. 14).
    p_c = np.array([[-A / 2, 0.0, 0.08], [A / 2, 0.0, 0.08]])
    n_c = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    params = mpc.Params()
    res = mpc.run_tumble_mpc(MASS, I_COM, np.zeros(3), p_c, n_c, edge_W, t, X_ref, params, catch_time=1.0)
    assert res.ok
    # Landed on the front face: its outward normal points down, the box sits on the table.
    R_end = res.X_WO[-1, :3, :3]
    assert np.allclose(R_end @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], atol=1e-4)
    corners = np.array([[x, y, z] for x in (-A / 2, A / 2) for y in (-A / 2, A / 2) for z in (-A / 2, A / 2)])
    z = se3.transform_points(res.X_WO[-1], corners)[:, 2]
    assert z.min() == pytest.approx(0.0, abs=1e-5) and z.max() == pytest.approx(A, abs=1e-5)
    assert res.tracking_error[-1] < 1e-4
    # The edge stays on the table; each of its vertices takes a reaction inside the table pyramid.
    edge_O = se3.transform_points(se3.invert(X_WO0), edge_W)
    assert np.abs(se3.transform_points(res.X_WO[:, None], edge_O[None]) - edge_W).max() < 1e-12
    _, H_tab = _pyramids_at_start(X_WO0, p_c, n_c, edge_W, params.mu_eef, params.mu_table)
    assert np.allclose(res.pyramid_table_W, H_tab)
    assert np.einsum("vfi,tvi->tvf", H_tab, res.f_support_W).max() < F_TOL
    assert np.allclose(res.f_support_W.sum(axis=1), res.f_table_W)
    # The catcher pushes nothing before the catch and at least the squeeze after it.
    before = res.t < 1.0 - 1e-9
    assert not res.contact_mask[before, 1].any() and res.contact_mask[~before, 1].all()
    assert np.all(res.f_eef_O[before, 1] == 0.0)
    fn = np.einsum("tki,ki->tk", res.f_eef_O, n_c)
    assert fn[~before, 1].min() > params.f_min - F_TOL
    assert fn[:, 0].min() > params.f_min - F_TOL
    # The edge split matches the Newton-Euler moment balance about the first vertex.
    model = mpc.make_rotation_model(MASS, I_COM, np.zeros(3), p_c, n_c, edge_O)
    for k in range(0, len(t), 13):
        f = mpc.support_reactions(model, res.X_WO[k, :3, :3], [res.omega_W[k] @ [0.0, 1.0, 0.0]],
                                  res.f_eef_O[k])
        assert np.allclose(f.sum(axis=0), res.f_table_W[k], atol=1e-9)
        L = edge_W[1] - edge_W[0]
        assert np.allclose(np.cross(L, f[1]), np.cross(L, res.f_support_W[k, 1]), atol=1e-8)


def test_linear_model_acceleration_at_the_state_is_the_exact_one():
    # At its own nominal point (state_dependent False) the model's acceleration is eq. 7 exactly.
    model = _model()
    R = Rotation.from_rotvec([0.2, 0.1, -0.4]).as_matrix()
    omega = np.array([0.3, -0.2, 0.5])
    f = np.array([[-1.0, 9.0, 4.0], [2.0, -11.0, 3.0]])
    lin = mpc.linearize_rotation(model, R[None], omega[None], np.zeros((1, 2, 3)), np.zeros((1, 3)), 0.02,
                                 state_dependent=[False])
    nu_dot = lin.Ma[0] @ np.r_[np.zeros(3), omega] + lin.Na[0] @ f.reshape(6) + lin.ca[0]
    assert np.allclose(nu_dot, mpc.rotation_acceleration(model, R, omega, f)[0], atol=1e-12)


def test_tumble_model_holds_a_usp_pose_on_an_edge_with_one_arm():
    # DS gait / USP: the box stands on its front edge tipped 30 deg forward, its CoM still behind
    # the edge; one EEF pushing high on the back face holds it (Fig. 14, right arm alone).
    edge_W = np.array([[A / 2, -A / 2, 0.0], [A / 2, A / 2, 0.0]])
    X_tip = se3.transform_about_line(edge_W[0], [0.0, 1.0, 0.0], np.deg2rad(30.0)) @ X_WO0
    t = np.arange(40) * 0.02
    X_ref = np.repeat(X_tip[None], len(t), axis=0)
    p_c = np.array([[-A / 2, 0.0, 0.08], [A / 2, 0.0, 0.08]])
    n_c = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    params = mpc.Params()
    res = mpc.run_tumble_mpc(MASS, I_COM, np.zeros(3), p_c, n_c, edge_W, t, X_ref, params,
                             contact_mask=(True, False))
    assert res.ok
    assert res.tracking_error.max() < 1e-4
    assert np.all(res.f_eef_O[:, 1] == 0.0)
    # Static balance about the edge: the pusher's torque equals gravity's, m g x_c / lever.
    r_com = X_tip[:3, 3] - edge_W[0]
    fn = res.f_eef_O[-1, 0] @ n_c[0]
    assert fn > params.f_min
    _, H_tab = _pyramids_at_start(X_tip, p_c, n_c, edge_W, params.mu_eef, params.mu_table)
    assert np.einsum("vfi,tvi->tvf", H_tab, res.f_support_W).max() < F_TOL
    torque_y = np.cross(res.p_eef_W[-1, 0] - edge_W[0], res.f_eef_W[-1, 0])[1]
    assert torque_y == pytest.approx(-np.cross(r_com, [0.0, 0.0, -MASS * G])[1], rel=1e-3)


# ------------------------------------------------------------------------------------------
# Rolling references (tumbles whose axis switches)
# ------------------------------------------------------------------------------------------


def test_knot_profile_moves_between_knots_and_rests_at_each():
    t, v = mpc.knot_profile([0.0, 0.0, 1.0, 1.0, 3.0], [0.5, 1.0, 0.4, 2.0], 0.02)
    assert np.allclose(np.diff(t), 0.02) and t[-1] == pytest.approx(3.9)
    assert v[0] == 0.0 and v[-1] == 3.0 and np.all(np.diff(v) >= -1e-12)  # monotone through the knots
    for tk, vk in ((0.5, 0.0), (1.5, 1.0), (1.9, 1.0)):
        k = int(round(tk / 0.02))
        assert v[k] == pytest.approx(vk, abs=1e-12)
        assert abs(v[k + 1] - v[k]) < 1e-3 and abs(v[k] - v[k - 1]) < 1e-3  # at rest there
    assert np.all(v[t < 0.5] == 0.0)  # the pause


def test_roll_poses_turn_about_each_segment_axis_in_turn():
    # The cube turns 30 deg about its front bottom edge, then 60 deg about a parallel line 5 cm ahead
    # (as a legged body switches from its foot line to its body edge).
    a = np.array([0.0, 1.0, 0.0])
    p0 = np.array([A / 2, -A / 2, 0.0])
    X1 = se3.transform_about_line(p0, a, np.radians(30.0)) @ X_WO0
    p1 = p0 + [0.05, 0.0, 0.0]
    th = np.radians(np.linspace(0.0, 90.0, 31))
    X = mpc.roll_poses(np.stack([X_WO0, X1]), np.stack([p0, p1]), np.stack([a, a]), np.radians([30.0, 60.0]), th)
    first, second = th <= np.radians(30.0) + 1e-12, th >= np.radians(30.0) - 1e-12
    P0_O = se3.transform_points(se3.invert(X_WO0), p0)
    P1_O = se3.transform_points(se3.invert(X1), p1)
    assert np.abs(se3.transform_points(X[first], P0_O) - p0).max() < 1e-12  # the first axis stays put
    assert np.abs(se3.transform_points(X[second], P1_O) - p1).max() < 1e-12  # then the second
    assert _rot_angle(X[-1, :3, :3], X_WO0[:3, :3]) == pytest.approx(np.pi / 2, abs=1e-12)
    assert np.allclose(mpc.roll_poses(np.stack([X_WO0, X1]), np.stack([p0, p1]), np.stack([a, a]),
                                      np.radians([30.0, 60.0]), [-1.0, 10.0])[[0, 1]], [X_WO0, X[-1]])


# ------------------------------------------------------------------------------------------
# The tumble's geometry in the MPC stage (stages.trajectory)
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def piano_model(tmp_path_factory):
    from stages import analyze
    from stages.objectmodel import load_object_model

    out = tmp_path_factory.mktemp("analysis")
    analyze.run(PIANO, out, 3.1, analyze.Params())
    return load_object_model(out)


def _upright_and_back_edge(model):
    """The piano upright at the origin, yawed 180 deg, and its back foot line (the edge to -y in W)."""
    g = int(np.argmin(model.normals[:, 2]))  # resting on its feet: outward normal -z
    X = se3.make_transform(se3.rot_z(np.pi), [0.0, 0.0, 0.0]) @ model.X_TO[g]
    on_face = np.isin(model.edges, np.asarray(model.support[g])).all(axis=1)
    mid_y = se3.transform_points(X, model.vertices[model.edges].mean(axis=1))[:, 1]
    e = np.flatnonzero(on_face)[np.argmin(mid_y[on_face])]
    return X, g, int(e)


def test_piano_rolls_about_its_foot_line_then_its_body_edge_onto_its_back(piano_model):
    from stages import poses, trajectory

    model, _ = piano_model
    X, g, e = _upright_and_back_edge(model)
    roll = trajectory.roll_segments(model, X, *model.edges[e])
    # Legs 9 cm long, inset 2 mm behind the back: 88.73 deg about the foot line (atan(0.09 / 0.002)),
    # then the body edge touches and it turns the last 1.27 deg about that.
    assert len(roll.angle) == 2
    assert np.degrees(roll.angle[0]) == pytest.approx(np.degrees(np.arctan2(0.09, 0.002)), abs=0.01)
    assert np.degrees(roll.total) == pytest.approx(90.0, abs=1e-9)
    # The pose sampler rolls the same way to the same pose (its back face down).
    X_s, g_s, total = poses._tumble(model, X, g, e)
    assert np.abs(roll.X_end - X_s).max() < 1e-12 and roll.face == g_s and total == pytest.approx(roll.total)
    assert se3.rotate_vectors(roll.X_end, model.normals[roll.face])[2] == pytest.approx(-1.0)
    # Along the roll each segment's axis stays on the table while the object turns about it.
    th = np.linspace(0.0, roll.total, 181)
    Xs = roll.poses(th)
    for k in range(2):
        inside = (th >= [0.0, *np.cumsum(roll.angle)][k] - 1e-12) & (th <= np.cumsum(roll.angle)[k] + 1e-12)
        ends = se3.transform_points(Xs[inside][:, None], model.vertices[roll.edge[k]][None])
        assert np.abs(ends - ends[:1]).max() < 1e-12 and np.abs(ends[..., 2]).max() < 1e-12
    # No hull vertex ever goes under the table.
    assert se3.transform_points(Xs[:, None], model.vertices[None])[..., 2].min() > -1e-9


def test_roll_segments_rejects_an_edge_off_the_resting_face(piano_model):
    from stages import trajectory

    model, _ = piano_model
    X, g, _ = _upright_and_back_edge(model)
    off = np.flatnonzero(~np.isin(model.edges, np.asarray(model.support[g])).all(axis=1))[0]
    with pytest.raises(InputError, match="not a hull edge of the resting face"):
        trajectory.roll_segments(model, X, *model.edges[off])


def test_a_ball_turned_with_the_object_does_not_roll_off_its_contact(piano_model):
    """Catching on the back face 5 cm below the top while the piano turns 84 deg: a ball keeping the
    orientation of position-only IK rolls centimetres along the face (stages.execute's rolling
    shift), one turned with the object (trajectory.ik_follow) not up the face; both reach the targets."""
    from stages import trajectory
    from stages.robot import load_robot
    from stages.scene import load_scene

    model, tables = piano_model
    scene = load_scene(REPO / "data" / "scenes" / "exp3_obstacle.json")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), scene.robot.eef_links)
    X, _, e = _upright_and_back_edge(model)
    X = se3.make_transform(np.eye(3), [-0.05, 0.14, 0.0]) @ X  # exp3's start: the right arm reaches the back
    roll = trajectory.roll_segments(model, X, *model.edges[e])
    Xs = roll.poses(np.radians(np.linspace(0.0, 84.0, 120)))
    con = tables["contacts"]
    p = np.array([0.0, 0.1025, 0.40])  # on the back face (y = 0.1025), 5 cm below the top
    n = np.array([0.0, 1.0, 0.0])
    targets = se3.transform_points(Xs, p + scene.robot.ball_radius * n)
    q0 = robot.ik("right", targets[:1]).q[0]
    q_plain = trajectory._ik_path(robot, "right", targets, q0, 1)
    q_follow, why = trajectory.ik_follow(robot, "right", targets, Xs, n, q0, 1)
    assert why == "ok" and len(con["px"]) > 0
    for q in (q_plain, q_follow):
        assert np.linalg.norm(robot.eef_position("right", q) - targets, axis=1).max() < 1e-3
    r = scene.robot.ball_radius
    plain = np.linalg.norm(trajectory.rolling_shift(robot, "right", q_plain, Xs, n, r)[-1])
    follow = trajectory.rolling_shift(robot, "right", q_follow, Xs, n, r)[-1]
    assert plain > 0.03  # measured 3.8 cm, 3.5 of them up the face (z_O)
    # Only the rotation about the turning axis (x of O) is followed: no roll up the face (z_O), nor off it.
    assert abs(follow[2]) < 1e-3 and abs(follow[1]) < 1e-9


def test_a_pivot_keeps_the_first_table_friction_whose_ball_forces_fit_the_plans_cap():
    """trajectory._pivot_forces: the box's pivot with the first table friction share that is feasible
    and keeps every ball force within the cap (the plan's ``mpc_max_force`` share of the bound); a
    cap the first solution exceeds moves it on to the next share, whose forces fit."""
    from types import SimpleNamespace

    from stages import trajectory

    t, X_ref, _ = mpc.pivot_reference(X_WO0, _goal(), P0_W, TILT, 0.02, DURATIONS)
    params = trajectory.Params(mpc=mpc.Params(dt=0.02), table_friction_tries=(0.3, 0.6))
    scene = SimpleNamespace(object=SimpleNamespace(mass=MASS, friction=0.5), table=SimpleNamespace(friction=0.5))
    env = SimpleNamespace(scene=scene, params=params, inertia=I_COM, model=SimpleNamespace(com=np.zeros(3)),
                          mp=mpc.Params(dt=0.02, mu_eef=0.4, mu_table=0.4))
    args = (P_C_O, N_C_O, P0_W, t, X_ref)

    def peak(res):
        return float(np.linalg.norm(res.f_eef_W, axis=2).max())

    first, share, floor = trajectory._pivot_forces(env, 1e3, *args)
    assert first.ok and share == 0.3 and floor == params.pivot_squeeze
    capped, share, floor = trajectory._pivot_forces(env, 0.99 * peak(first), *args)
    assert capped.ok and share == 0.6 and floor == params.pivot_squeeze and peak(capped) <= 0.99 * peak(first)


def test_a_pivot_squeezes_first_and_falls_back_to_the_plans_least_force():
    """trajectory._pivot_forces: each ball first presses at least ``pivot_squeeze`` (its normal force,
    along the inward normal); where no solution with that floor keeps the forces within the cap it
    falls back to the MPC's ``f_min``, the plan's own check."""
    from types import SimpleNamespace

    from stages import trajectory

    t, X_ref, _ = mpc.pivot_reference(X_WO0, _goal(), P0_W, TILT, 0.02, DURATIONS)
    scene = SimpleNamespace(object=SimpleNamespace(mass=MASS, friction=0.5), table=SimpleNamespace(friction=0.5))

    def run(floor, cap=1e3):
        params = trajectory.Params(mpc=mpc.Params(dt=0.02), pivot_squeeze=floor)
        env = SimpleNamespace(scene=scene, params=params, inertia=I_COM, model=SimpleNamespace(com=np.zeros(3)),
                              mp=mpc.Params(dt=0.02, mu_eef=0.4, mu_table=0.4))
        return trajectory._pivot_forces(env, cap, P_C_O, N_C_O, P0_W, t, X_ref)

    light, _, _ = run(2.0)  # this pivot needs ~20 N of each ball anyway
    res, _, f_min = run(30.0)
    normal = np.einsum("tki,tki->tk", res.f_eef_W, np.einsum("tij,kj->tki", res.X_WO[:, :3, :3], N_C_O))
    assert res.ok and f_min == 30.0 and normal.min() >= 30.0 - 1e-3
    assert light.ok and np.linalg.norm(light.f_eef_W, axis=2).min() < 25.0
    # A cap under what 30 N of squeeze needs: the plan's least force, on the first share that fits.
    res, share, f_min = run(30.0, cap=28.0)
    assert res.ok and f_min == mpc.Params().f_min and np.linalg.norm(res.f_eef_W, axis=2).max() <= 28.0
    assert run(1e3)[2] == mpc.Params().f_max  # a floor above the force bound is the bound
