"""Pivot connections (§5.3): closed-form 1-, 2- and 3-pivot sequences between poses of one placement."""

import numpy as np
import pytest

from stages import connect, se3
from stages.errors import InputError

# Rectangle 0.42 x 0.20 m, corners counter-clockwise from (+x, +y).
RECT = np.array([[0.21, 0.10], [-0.21, 0.10], [-0.21, -0.10], [0.21, -0.10]])
P = connect.Params()
# Replayed end poses are exact up to round-off (~1e-16 m); the connection's own acceptance tolerance is
# tol_xy = 1e-6 m, tol_yaw = 1e-8 rad, so we check against those.
TOL_XY, TOL_YAW = P.tol_xy, P.tol_yaw
# Costs within 1e-9 rad count as equal in the ranking (connect._TIE), so "not worse" allows that much.
TIE = 1e-9


def random_sequence(rng, n, amax=np.radians(25.0), k=4):  # noqa: B008 (a float, evaluated once)
    """``n`` pivots about random corners, none twice in a row, angles uniform in [-amax, amax]."""
    ids = [int(rng.integers(k))]
    while len(ids) < n:
        c = int(rng.integers(k))
        if c != ids[-1]:
            ids.append(c)
    return np.array(ids), rng.uniform(-amax, amax, n)


def random_pose(rng):
    return rng.uniform([-0.3, -0.2, -np.pi], [0.3, 0.2, np.pi])


def assert_valid(c, pose_a, pose_b, corners=RECT, params=P):
    """A connection reaches b, respects the bounds and keeps each pivot corner where it was."""
    assert c.ok and c.reason == ""
    m = c.n_pivots
    assert c.poses.shape == (m + 1, 3) and c.angles.shape == (m,) and c.corners.shape == (m,)
    np.testing.assert_array_equal(c.poses[0], pose_a)
    np.testing.assert_allclose(c.poses, connect.apply_pivots(pose_a, corners, c.corners, c.angles), atol=1e-15)
    assert np.linalg.norm(c.poses[-1, :2] - pose_b[:2]) <= params.tol_xy
    assert abs(connect.wrap_angle(c.poses[-1, 2] - pose_b[2])) <= params.tol_yaw
    assert np.all(np.abs(c.angles) <= params.max_angle)
    assert c.cost == pytest.approx(np.abs(c.angles).sum(), abs=1e-15)
    if params.alternate:
        assert np.all(c.corners[1:] != c.corners[:-1])
    w = connect.corner_positions(c.poses, corners)  # (m + 1, k, 2)
    for i, ci in enumerate(c.corners):
        np.testing.assert_allclose(w[i + 1, ci], w[i, ci], atol=1e-14)  # the pivot corner stays put
        np.testing.assert_allclose(c.poses[i + 1, 2] - c.poses[i, 2], c.angles[i], atol=1e-15)


def test_a_20_degree_pivot_is_solved_back_as_that_single_pivot():
    pose_a = np.array([0.1, -0.05, 0.3])
    for corner in range(4):
        for angle in (np.radians(20.0), -np.radians(20.0)):
            pose_b = connect.apply_pivots(pose_a, RECT, [corner], [angle])[-1]
            c = connect.connect_planar(pose_a, pose_b, RECT, P)
            assert_valid(c, pose_a, pose_b)
            assert c.corners.tolist() == [corner]
            assert c.angles[0] == pytest.approx(angle, abs=1e-14)


def test_an_exact_max_angle_pivot_is_accepted_despite_round_off():
    # The wrapped yaw difference misses 30 deg by an ulp in about 7 % of these poses.
    rng = np.random.default_rng(6)
    for _ in range(100):
        pose_a = random_pose(rng)
        corner, angle = int(rng.integers(4)), rng.choice([-1.0, 1.0]) * P.max_angle
        pose_b = connect.apply_pivots(pose_a, RECT, [corner], [angle])[-1]
        c = connect.connect_planar(pose_a, pose_b, RECT, P)
        assert_valid(c, pose_a, pose_b)
        assert c.corners.tolist() == [corner]


def test_the_same_pose_connects_with_no_pivot_even_a_full_turn_apart():
    pose = np.array([0.2, 0.1, 0.5])
    c = connect.connect_planar(pose, pose + [0, 0, 2 * np.pi], RECT, P)
    assert c.ok and c.n_pivots == 0 and c.cost == 0.0 and c.poses.shape == (1, 3)


def test_two_pivot_targets_take_exactly_two_pivots_at_most_their_cost():
    rng = np.random.default_rng(1)
    for _ in range(50):
        pose_a = random_pose(rng)
        ids, angles = random_sequence(rng, 2)
        pose_b = connect.apply_pivots(pose_a, RECT, ids, angles)[-1]
        c = connect.connect_planar(pose_a, pose_b, RECT, P)
        assert_valid(c, pose_a, pose_b)
        # One pivot would need a corner with the same place in a and b: not the case for generic angles.
        assert c.n_pivots == 2
        assert c.cost <= np.abs(angles).sum() + TIE


def test_random_three_pivot_targets_are_reached_with_at_most_three_bounded_pivots():
    rng = np.random.default_rng(2)
    counts = np.zeros(4, int)
    n_tied = 0
    for _ in range(200):
        pose_a = random_pose(rng)
        ids, angles = random_sequence(rng, 3)
        pose_b = connect.apply_pivots(pose_a, RECT, ids, angles)[-1]
        c = connect.connect_planar(pose_a, pose_b, RECT, P)
        assert_valid(c, pose_a, pose_b)
        assert 1 <= c.n_pivots <= 3
        counts[c.n_pivots] += 1
        # The generating sequence is a candidate, so the chosen one is never worse.
        if c.n_pivots == 3:
            assert c.cost <= np.abs(angles).sum() + TIE
        # Same-sign angles cost exactly |dyaw|, the least possible: the tie goes to the most even split.
        if np.all(angles > 0) or np.all(angles < 0):
            assert c.cost == pytest.approx(abs(angles.sum()), abs=TIE)
            assert np.sum(c.angles**2) <= np.sum(angles**2) + TIE
            n_tied += 1
    # Two pivots reach only a surface of the (x, y, yaw) space: random 3-pivot targets need all three.
    assert counts[3] == 200
    assert n_tied > 30


def newton_roots(pose_a, pose_b, seqs, starts, iters=40):
    """Roots ``(S, G, 3)`` of the 3-pivot equations from ``G`` starts ``(a1, a2)`` per sequence, NaN if none.

    Plain Newton on (a1, a2) with a3 = dyaw - a1 - a2 (the yaw equation), central-difference Jacobian.
    """
    dyaw = connect.wrap_angle(pose_b[2] - pose_a[2])
    ids = np.broadcast_to(seqs[:, None, :], (len(seqs), len(starts), 3))

    def residual(x):
        a = np.concatenate([x, dyaw - x.sum(-1, keepdims=True)], -1)
        return connect.apply_pivots(pose_a, RECT, ids, a)[..., -1, :2] - pose_b[:2]

    x = np.broadcast_to(starts, ids.shape[:2] + (2,)).copy()
    h = 1e-6
    for _ in range(iters):
        J = np.stack([(residual(x + h * e) - residual(x - h * e)) / (2 * h) for e in np.eye(2)], -1)
        step = np.linalg.solve(J + 1e-12 * np.eye(2), residual(x)[..., None])[..., 0]
        x -= np.clip(step, -0.5, 0.5)  # damped: far starts would otherwise jump between branches
    a = connect.wrap_angle(np.concatenate([x, dyaw - x.sum(-1, keepdims=True)], -1))
    return np.where((np.linalg.norm(residual(x), axis=-1) < 1e-12)[..., None], a, np.nan)


def test_closed_form_finds_every_root_of_the_three_pivot_equations():
    """Newton from a grid of starts over the whole circle finds no root that the circle intersection misses."""
    rng = np.random.default_rng(3)
    seqs = connect.corner_sequences(4, 3)
    assert len(seqs) == 4 * 3 * 3
    grid = np.linspace(-np.pi, np.pi, 8, endpoint=False)
    starts = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)
    n_roots = 0
    for _ in range(3):
        pose_a = random_pose(rng)
        ids, angles = random_sequence(rng, 3)
        pose_b = connect.apply_pivots(pose_a, RECT, ids, angles)[-1]
        closed = connect.solve_pivot_angles(pose_a, pose_b, RECT, seqs)  # (36, 2, 3)
        roots = newton_roots(pose_a, pose_b, seqs, starts)  # (36, 64, 3)
        found = ~np.isnan(roots[..., 0])
        n_roots += found.sum()
        # Distance of every Newton root to the nearer of its sequence's two closed-form candidates.
        gap = np.abs(connect.wrap_angle(roots[:, :, None, :] - closed[:, None, :, :])).max(-1).min(-1)
        assert np.all(gap[found] < 1e-8)
        # The generating sequence is among the closed-form candidates.
        s = int(np.flatnonzero((seqs == ids).all(1))[0])
        assert np.abs(closed[s] - angles).max(axis=-1).min() < 1e-9
    assert n_roots > 1000  # Newton did converge from most starts: the check above is not vacuous


def test_a_target_one_metre_away_is_unreachable():
    pose_a = np.array([0.0, 0.0, 0.0])
    c = connect.connect_planar(pose_a, np.array([1.0, 0.0, 0.0]), RECT, P)
    assert not c.ok and c.reason == connect.NO_SEQUENCE
    assert c.n_pivots == 0 and c.cost == np.inf
    np.testing.assert_array_equal(c.poses, pose_a[None])


def test_max_pivots_one_refuses_a_two_pivot_target():
    pose_a = np.array([0.0, 0.0, 0.0])
    pose_b = connect.apply_pivots(pose_a, RECT, [0, 1], np.radians([15.0, -10.0]))[-1]
    c = connect.connect_planar(pose_a, pose_b, RECT, connect.Params(max_pivots=1))
    assert not c.ok and c.reason == connect.NO_SEQUENCE
    assert connect.connect_planar(pose_a, pose_b, RECT, connect.Params(max_pivots=2)).n_pivots == 2


def test_a_turn_beyond_max_angle_about_one_corner_splits_only_without_alternation():
    # 50 deg about corner 0 with at most 30 deg per pivot: two 25 deg pivots about corner 0 when allowed.
    pose_a = np.array([0.0, 0.0, 0.0])
    pose_b = connect.apply_pivots(pose_a, RECT, [0], [np.radians(50.0)])[-1]
    params = connect.Params(alternate=False)
    c = connect.connect_planar(pose_a, pose_b, RECT, params)
    assert_valid(c, pose_a, pose_b, params=params)
    assert c.corners.tolist() == [0, 0]
    np.testing.assert_allclose(c.angles, np.radians([25.0, 25.0]), atol=1e-14)
    c = connect.connect_planar(pose_a, pose_b, RECT, P)
    if c.ok:  # alternation needs three pivots about different corners (or none)
        assert_valid(c, pose_a, pose_b)
        assert c.n_pivots == 3
    else:
        assert c.reason == connect.NO_SEQUENCE


def test_connection_is_invariant_under_a_planar_rigid_motion():
    rng = np.random.default_rng(4)
    for _ in range(20):
        pose_a = random_pose(rng)
        ids, angles = random_sequence(rng, 3)
        pose_b = connect.apply_pivots(pose_a, RECT, ids, angles)[-1]
        c = connect.connect_planar(pose_a, pose_b, RECT, P)
        phi, t = rng.uniform(-np.pi, np.pi), rng.uniform(-1, 1, 2)
        R = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])

        def move(p, R=R, t=t, phi=phi):
            return np.array([*(R @ p[:2] + t), p[2] + phi])

        d = connect.connect_planar(move(pose_a), move(pose_b), RECT, P)
        assert d.corners.tolist() == c.corners.tolist()
        np.testing.assert_allclose(d.angles, c.angles, atol=1e-9)


def lying_box():
    """A 0.42 x 0.15 x 0.20 box lying on its y = -0.075 face: O's y axis points up, corners on the table."""
    R = se3.rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # y_O -> z_W
    X_a = se3.make_transform(se3.rot_z(0.4) @ R, np.array([0.1, -0.05, 0.075]))
    corners_O = np.array([[0.21, -0.075, 0.10], [-0.21, -0.075, 0.10], [-0.21, -0.075, -0.10],
                          [0.21, -0.075, -0.10]])
    return X_a, corners_O


def pivot_3d(X, corners_O, ids, angles):
    for c, a in zip(ids, angles, strict=True):
        X = se3.transform_about_line(se3.transform_points(X, corners_O[c]), np.array([0, 0, 1.0]), a) @ X
    return X


def test_connect_poses_reaches_the_goal_and_keeps_each_pivot_corner_on_the_table():
    rng = np.random.default_rng(5)
    X_a, corners_O = lying_box()
    for _ in range(20):
        ids, angles = random_sequence(rng, 3)
        X_b = pivot_3d(X_a, corners_O, ids, angles)
        c = connect.connect_poses(X_a, X_b, corners_O, P)
        assert c.ok and c.poses.shape == (c.n_pivots + 1, 4, 4) and c.n_pivots == 3
        assert np.all(np.abs(c.angles) <= P.max_angle)
        np.testing.assert_array_equal(c.poses[0], X_a)
        np.testing.assert_allclose(c.poses[-1, :3, 3], X_b[:3, 3], atol=TOL_XY)
        np.testing.assert_allclose(c.poses[-1, :3, :3], X_b[:3, :3], atol=TOL_YAW)
        p_W = se3.transform_points(c.poses[:, None], corners_O)  # (m + 1, k, 3)
        np.testing.assert_allclose(p_W[..., 2], 0.0, atol=1e-14)  # all corners stay on the table
        for i, ci in enumerate(c.corners):
            np.testing.assert_allclose(p_W[i + 1, ci], p_W[i, ci], atol=1e-14)
            np.testing.assert_allclose(c.poses[i + 1, :3, :3] @ c.poses[i, :3, :3].T, se3.rot_z(c.angles[i]),
                                       atol=1e-14)


def test_connect_poses_refuses_another_placement():
    X_a, corners_O = lying_box()
    tumbled = se3.transform_about_line(np.array([0.3, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.pi / 2) @ X_a
    lifted = se3.make_transform(np.eye(3), np.array([0.0, 0.0, 0.01])) @ X_a
    tilted = se3.transform_about_line(np.zeros(3), np.array([1.0, 0.0, 0.0]), 1e-4) @ X_a
    for X_b in (tumbled, lifted, tilted):
        c = connect.connect_poses(X_a, X_b, corners_O, P)
        assert not c.ok and c.reason == connect.DIFFERENT_PLACEMENT and c.poses.shape == (1, 4, 4)
    # A yaw of the same placement is not refused for round-off in the tilt.
    X_b = se3.transform_about_line(np.array([0.1, 0.2, 0.0]), np.array([0.0, 0.0, 1.0]), 0.2) @ X_a
    assert connect.connect_poses(X_a, X_b, corners_O, P).reason != connect.DIFFERENT_PLACEMENT


def test_bad_input_raises_input_error():
    X_a, corners_O = lying_box()
    with pytest.raises(InputError, match="off the table"):
        connect.connect_poses(X_a, X_a, corners_O + [0, 0.01, 0], P)
    with pytest.raises(InputError, match="coincide"):
        connect.connect_planar(np.zeros(3), np.ones(3), np.vstack([RECT, RECT[:1]]), P)
    with pytest.raises(InputError, match="max_pivots"):
        connect.connect_planar(np.zeros(3), np.ones(3), RECT, connect.Params(max_pivots=4))
    with pytest.raises(InputError, match="pose_b"):
        connect.connect_planar(np.zeros(3), np.ones(2), RECT, P)


def test_corners_as_uneven_as_a_merged_hull_face_connect_and_far_off_ones_are_refused():
    # A placement face merges hull triangles up to 0.5 deg apart, so its corners lie off its plane by up
    # to tan(0.5 deg) x its spread (0.465 m here: 4.1 mm); organic meshes measured 0.2 mm. Pivots are
    # about verticals, so corners 0.1 mm off reach the same end pose; 1 cm off (2 % of the face) is not a
    # placement of that face at all.
    X_a, corners_O = lying_box()
    X_b = pivot_3d(X_a, corners_O, [0, 2], [0.3, -0.2])
    uneven = corners_O + np.array([[0, 1e-4, 0], [0, -1e-4, 0], [0, 1e-4, 0], [0, -1e-4, 0]])  # y_O is up
    c = connect.connect_poses(X_a, X_b, uneven, P)
    assert c.ok
    np.testing.assert_allclose(c.poses[-1], X_b, atol=TOL_XY)
    assert connect.on_table_tolerance(corners_O, P) == pytest.approx(1e-6 + np.tan(np.radians(0.5)) * 0.465, rel=1e-3)
    with pytest.raises(InputError, match="off the table"):
        connect.connect_poses(X_a, X_b, corners_O + np.array([[0, 0.01, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]), P)
    # The tolerance scales with the face: 1 mm is within a 0.465 m face's flatness, not a 4.65 cm one's.
    one_mm = np.array([[0, 1e-3, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]])
    assert connect.connect_poses(X_a, X_a, corners_O + one_mm, P).ok
    small = corners_O * 0.1 + [0.0, -0.0675, 0.0]  # the same box a tenth the size, still on y = -0.075
    assert connect.connect_poses(X_a, X_a, small, P).ok
    with pytest.raises(InputError, match="off the table"):
        connect.connect_poses(X_a, X_a, small + one_mm, P)


def test_some_corners_of_a_face_get_the_whole_faces_flatness():
    """A join about a subset of a face's corners (those a grasp holds) is judged against the face's
    flatness, not the subset's: one corner alone has no spread, and 0.1 mm off would be refused."""
    X_a, corners_O = lying_box()
    X_b = pivot_3d(X_a, corners_O, [0], [0.3])
    one = corners_O[:1] + np.array([[0, 1e-4, 0]])  # y_O is up
    with pytest.raises(InputError, match="off the table"):
        connect.connect_poses(X_a, X_b, one, P)
    c = connect.connect_poses(X_a, X_b, one, P, face_O=corners_O)
    assert c.ok and c.n_pivots == 1


def test_a_pivot_walk_reaches_what_three_pivots_cannot_with_bounded_pivots():
    """A triangle base 0.1 m across, a goal 0.3 m away turned 60°: beyond the closed form (three pivots
    of at most 30° move it a few cm); the walk reaches it exactly by exact pivots within the bound."""
    c = np.array([[0.05, 0.03], [-0.05, 0.03], [0.0, -0.05]])
    goal = np.array([0.3, 0.05, np.radians(60.0)])
    assert not connect.connect_planar(np.zeros(3), goal, c).ok
    walk = connect.walk_planar(np.zeros(3), goal, c, strides=12)
    assert walk.ok and walk.n_pivots > 3
    assert np.all(np.abs(walk.angles) <= connect.Params().max_angle + 1e-12)
    end = connect.apply_pivots(np.zeros(3), c, walk.corners, walk.angles)[-1]
    assert np.allclose(end[:2], goal[:2], atol=1e-6) and abs(connect.wrap_angle(end[2] - goal[2])) <= 1e-8
    assert not connect.walk_planar(np.zeros(3), goal, c, strides=2).ok  # too few strides: refused
