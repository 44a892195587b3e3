"""Transit motions for regrasping (§5.2.2, §5.3): RRT-Connect paths of one arm, and their timing."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from stages import se3, transit
from stages.robot import load_robot, make_collision_fn
from stages.sample import make_scene_collision_fn
from stages.scene import load_scene
from tests.conftest import PIANO, REPO

TABLE = ((0.9, 0.6), 0.0)
BALL = 0.02
Q_AWAY = np.zeros(7)  # upper arm sideways, forearm up: far from the table and the other arm


@pytest.fixture(scope="module")
def scene():
    return load_scene(REPO / "data" / "scenes" / "default.json")


@pytest.fixture(scope="module")
def robot(scene):
    return load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))


@pytest.fixture(scope="module")
def table_only(robot):
    return make_collision_fn(robot, TABLE, [], None, table_depth=0.75)


@pytest.fixture(scope="module")
def wall(robot):
    """A 2 cm thick wall, 25 cm tall, across the left arm's way along x at y = 0.3."""
    box = ("box", (0.02, 0.3, 0.25), se3.make_transform(np.eye(3), [-0.15, 0.3, 0.125]), "wall")
    return make_collision_fn(robot, TABLE, [box], None, table_depth=0.75)


def free_ik(robot, collide, arm, p_W, q_other, X_WO=None, touching=False, tries=30):
    """An IK solution for the ball centre ``p_W`` that is collision-free with the other arm at ``q_other``
    (the position IK returns one branch; other seeds find others)."""
    a = robot.arm(arm)
    rng = np.random.default_rng(0)
    for k in range(tries):
        seed = None if k == 0 else np.clip(a.q_rest + rng.normal(0.0, 0.7, a.dof), a.lower, a.upper)[None]
        res = robot.ik(arm, np.asarray(p_W, dtype=float)[None], q_seed=seed, rng=rng)
        if not res.ok[0]:
            continue
        q = res.q[0]
        ok, _ = check_states(collide, arm, q[None], q_other, X_WO, touching)
        if ok[0]:
            return q
    raise AssertionError(f"no collision-free IK for {p_W}")


def check_states(collide, arm, Q, q_other, X_WO=None, ball_touching=False):
    """The checker on the moving arm's states ``Q (N, 7)``, the other arm still (its ball exempt)."""
    N = len(Q)
    other = np.broadcast_to(q_other, Q.shape)
    touching = np.ones((N, 2), bool)
    touching[:, 0 if arm == "left" else 1] = ball_touching
    X = None if X_WO is None else np.broadcast_to(X_WO, (N, 4, 4))
    return collide(Q, other, X, touching) if arm == "left" else collide(other, Q, X, touching)


def dense(robot, arm, path, factor=4):
    """States along ``path`` ``factor`` times finer than the planner checked them."""
    return transit.densify(path, transit.lever_arms(robot.arm(arm)), transit.Params().resolution / factor)[0]


def wall_query(robot, wall):
    qs = free_ik(robot, wall, "left", [-0.35, 0.3, 0.1], Q_AWAY)
    qg = free_ik(robot, wall, "left", [0.0, 0.3, 0.1], Q_AWAY)
    return qs, qg


# ------------------------------------------------------------------------------------------ geometry


def test_densify_bounds_the_motion_of_every_point_of_the_arm(robot):
    # The lever-arm bound: between consecutive states no capsule end point moves more than the step.
    a = robot.arm("left")
    rng = np.random.default_rng(1)
    path = rng.uniform(a.lower, a.upper, (4, a.dof))
    step = 0.01
    states, seg = transit.densify(path, transit.lever_arms(a), step)
    Q = np.concatenate([path[:1], states])
    X = robot.fk("left", Q)[:, a.cap_link]  # (M, C, 4, 4)
    for p in (a.cap_a, a.cap_b):
        P = np.einsum("mcij,cj->mci", X[:, :, :3, :3], p) + X[:, :, :3, 3]
        assert np.linalg.norm(np.diff(P, axis=0), axis=2).max() <= step
    # Segment ends are the waypoints, exactly.
    ends = np.flatnonzero(np.diff(np.append(seg, len(path) - 1)))
    np.testing.assert_array_equal(states[ends], path[1:])


def test_shortcut_of_a_zigzag_in_free_space_is_one_segment(robot, table_only):
    qs = free_ik(robot, table_only, "left", [-0.3, 0.25, 0.3], Q_AWAY)
    qg = free_ik(robot, table_only, "left", [-0.2, 0.15, 0.35], Q_AWAY)
    line = qs + np.linspace(0, 1, 6)[:, None] * (qg - qs)
    zig = line + 0.02 * (np.arange(6) % 2)[:, None] * np.r_[1, 0, 0, 0, 0, 0, 0]
    zig[0], zig[-1] = qs, qg
    assert check_states(table_only, "left", dense(robot, "left", zig), Q_AWAY)[0].all()  # the input is free

    def check(Q):
        return check_states(table_only, "left", Q, Q_AWAY)

    out = transit.shortcut(zig, check, transit.lever_arms(robot.arm("left")), 0.01)
    np.testing.assert_array_equal(out, np.stack([qs, qg]))


# ------------------------------------------------------------------------------------------ planning


def test_free_space_transit_succeeds_and_is_collision_free_four_times_finer(robot, table_only):
    qs = free_ik(robot, table_only, "left", [-0.35, 0.25, 0.15], Q_AWAY)
    qg = free_ik(robot, table_only, "left", [-0.05, 0.1, 0.4], Q_AWAY)
    res = transit.plan_transit(robot, table_only, "left", qs, qg, Q_AWAY, None)
    assert res.status == "ok", res.reason
    np.testing.assert_array_equal(res.path[0], qs)
    np.testing.assert_array_equal(res.path[-1], qg)
    a = robot.arm("left")
    assert np.all(res.path >= a.lower) and np.all(res.path <= a.upper)
    ok, why = check_states(table_only, "left", dense(robot, "left", res.path), Q_AWAY)
    assert ok.all(), set(why[~ok])


def test_regrasp_on_the_piano_backs_off_along_the_normals_and_touches_it_only_there(robot, scene):
    mesh = trimesh.load(PIANO, force="mesh")
    collide = make_scene_collision_fn(scene, robot, mesh)
    X_WO = se3.make_transform(se3.rot_z(np.radians(-90)), [-0.18, 0.0, 0.0])  # the scene's start pose
    # Right ball holds the -y side face; the left ball moves from the +y side face to the top face.
    q_r = free_ik(robot, collide, "right", [-0.2, -0.2125 - BALL, 0.35], Q_AWAY, X_WO, True)
    n_s, n_g = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    p_s, p_g = np.array([-0.2, 0.2125, 0.35]), np.array([-0.12, 0.10, 0.45])  # contacts on the faces
    q_s = free_ik(robot, collide, "left", p_s + BALL * n_s, q_r, X_WO, True)
    q_g = free_ik(robot, collide, "left", p_g + BALL * n_g, q_r, X_WO, True)
    prm = transit.Params()
    res = transit.plan_transit(robot, collide, "left", q_s, q_g, q_r, X_WO, prm, n_s, n_g)
    assert res.status == "ok", res.reason
    P = robot.eef_position("left", res.path)
    K, r, ap = len(res.path), res.n_retreat, res.n_approach
    assert r == ap == prm.retreat_steps
    # Retreat and approach: 3 cm straight out along the normals (IK tolerance 1 mm per waypoint).
    s = prm.retreat * np.arange(r + 1) / r
    np.testing.assert_allclose(P[: r + 1], P[0] + s[:, None] * n_s, atol=2e-3)
    np.testing.assert_allclose(P[K - 1 - ap:], P[-1] + s[::-1, None] * n_g, atol=2e-3)
    # Between the retreat and approach configurations the ball is tested against the object too.
    middle = res.path[r: K - ap]
    ok, why = check_states(collide, "left", np.concatenate([middle[:1], dense(robot, "left", middle)]), q_r, X_WO)
    assert ok.all(), set(why[~ok])
    # On the retreat and approach segments only the ball may touch the object.
    ends = np.concatenate([dense(robot, "left", res.path[: r + 1]), dense(robot, "left", res.path[K - 1 - ap:])])
    ok, why = check_states(collide, "left", ends, q_r, X_WO, ball_touching=True)
    assert ok.all(), set(why[~ok])


def test_goal_inside_the_table_is_goal_in_collision(robot, table_only):
    qs = free_ik(robot, table_only, "left", [-0.3, 0.25, 0.2], Q_AWAY)
    ik = robot.ik("left", np.array([[-0.25, 0.2, -0.05]]))  # 5 cm under the table top
    assert ik.ok[0]
    res = transit.plan_transit(robot, table_only, "left", qs, ik.q[0], Q_AWAY, None)
    assert res.status == "goal_in_collision"
    assert "table" in res.reason and res.path.shape == (0, 7)
    back = transit.plan_transit(robot, table_only, "left", ik.q[0], qs, Q_AWAY, None)
    assert back.status == "start_in_collision" and "table" in back.reason


def test_retreat_out_of_reach_is_ik_unreachable(robot, table_only):
    a = robot.arm("left")
    qs = free_ik(robot, table_only, "left", [-0.3, 0.25, 0.2], Q_AWAY)
    qg = free_ik(robot, table_only, "left", [-0.1, 0.2, 0.3], Q_AWAY)
    p_g = robot.eef_position("left", qg[None])[0]
    away = (p_g - a.reach_centre) / np.linalg.norm(p_g - a.reach_centre)
    # Backing off 1.5 m away from the reach centre leaves the reach sphere: no IK can exist.
    res = transit.plan_transit(robot, table_only, "left", qs, qg, Q_AWAY, None, transit.Params(retreat=1.5),
                               n_goal=away)
    assert res.status == "ik_unreachable" and res.reason.startswith("approach")


def test_wall_forces_a_collision_free_detour(robot, wall):
    qs, qg = wall_query(robot, wall)
    straight = dense(robot, "left", np.stack([qs, qg]), factor=1)
    ok, why = check_states(wall, "left", straight, Q_AWAY)
    assert not ok.all() and any("wall" in w for w in why[~ok])  # the straight way is blocked
    # ... the planner goes round it (the found path, checked densely below, is the proof that one exists).
    res = transit.plan_transit(robot, wall, "left", qs, qg, Q_AWAY, None)
    assert res.status == "ok", res.reason
    assert res.stats["planner"] == "rrt_connect" and len(res.path) >= 3
    ok, why = check_states(wall, "left", dense(robot, "left", res.path), Q_AWAY)
    assert ok.all(), set(why[~ok])


def test_the_way_between_retreat_and_approach_keeps_the_clearance(robot):
    # A "thin wall" the checker sees only with an object margin: joint 1 of the left arm within 0.05 rad of 0.5.
    # The states between the ends are tested with Params.clearance, the ends without: with a clearance
    # the way from joint 1 at 0 to 1 (which must pass 0.5) is blocked, without one it is free; and when
    # an end itself lies within the clearance the transit keeps none.
    def collide(q_left, q_right, X_WO, touching, object_margin=0.0):
        bad = (object_margin > 0) & (np.abs(q_left[:, 0] - 0.5) < 0.05)
        return ~bad, np.where(bad, "env_collision:left_link_1_s/wall", "ok")

    a = robot.arm("left")
    qs, qg = a.q_rest.copy(), a.q_rest.copy()
    qs[0], qg[0] = 0.0, 1.0
    prm = transit.Params(max_iterations=20)
    assert prm.clearance > 0
    assert transit.plan_transit(robot, collide, "left", qs, qg, Q_AWAY, None, prm).status == "no_transit_path"
    res = transit.plan_transit(robot, collide, "left", qs, qg, Q_AWAY, None, replace(prm, clearance=0.0))
    assert res.status == "ok" and res.stats["planner"] == "direct"
    qg[0] = 0.52  # the goal inside the margin: no clearance kept
    res = transit.plan_transit(robot, collide, "left", qs, qg, Q_AWAY, None, prm)
    assert res.status == "ok" and res.stats["planner"] == "direct"


def test_same_seed_gives_the_same_path(robot, wall):
    qs, qg = wall_query(robot, wall)
    prm = transit.Params(seed=3)
    first = transit.plan_transit(robot, wall, "left", qs, qg, Q_AWAY, None, prm)
    transit.plan_transit(robot, wall, "left", qs, qg, Q_AWAY, None, transit.Params(seed=4))  # RNG in between
    again = transit.plan_transit(robot, wall, "left", qs, qg, Q_AWAY, None, prm)
    assert first.status == again.status == "ok"
    assert first.stats["planner"] == "rrt_connect"  # the random part ran
    np.testing.assert_array_equal(first.path, again.path)


def test_ball_caged_behind_a_hole_smaller_than_it_has_no_transit_path(robot, table_only):
    # The goal puts the ball in a closed box whose lid has a 3 cm square hole around the stick (the
    # ball is 4 cm across): the goal is free but no path leads out.
    q_g = free_ik(robot, table_only, "left", [-0.1, 0.25, 0.15], Q_AWAY)
    X = robot.fk("left", q_g[None])[0]
    names = robot.arm("left").link_names
    c = X[names.index("left_ball"), :3, 3]
    u = X[names.index("left_tool0"), :3, 3] - c  # along the stick
    X_WC = se3.make_transform(se3.rotation_between(np.array([0.0, 0.0, 1.0]), u / np.linalg.norm(u)), c)
    h, t, hole = 0.03, 0.01, 0.015  # inner half size, wall thickness, hole half width
    parts = [((0, 0, -h - t / 2), (2 * h + 2 * t, 2 * h + 2 * t, t))]
    for s in (-1, 1):
        parts += [((s * (h + t / 2), 0, 0), (t, 2 * h + 2 * t, 2 * h)), ((0, s * (h + t / 2), 0), (2 * h, t, 2 * h)),
                  ((s * (hole + (h + t - hole) / 2), 0, h + t / 2), (h + t - hole, 2 * h + 2 * t, t)),
                  ((0, s * (hole + (h + t - hole) / 2), h + t / 2), (2 * hole, h + t - hole, t))]
    cage = [("box", size, X_WC @ se3.make_transform(np.eye(3), centre), f"cage_{i}")
            for i, (centre, size) in enumerate(parts)]
    collide = make_collision_fn(robot, TABLE, cage, None, table_depth=0.75)
    q_s = free_ik(robot, collide, "left", [-0.3, 0.3, 0.3], Q_AWAY)
    assert check_states(collide, "left", np.stack([q_s, q_g]), Q_AWAY)[0].all()  # both ends are free
    prm = transit.Params(max_iterations=15, time_limit=60.0)
    res = transit.plan_transit(robot, collide, "left", q_s, q_g, Q_AWAY, None, prm)
    assert res.status == "no_transit_path"
    assert "15 iterations (iteration limit)" in res.reason and "cage_" in res.reason


def test_moving_arm_goes_around_the_still_arm(robot, table_only):
    # The left ball's straight way from q_s to q_g; the right ball is put where the left ball passes
    # half way, so the straight way hits the right arm and the planner must go round it.
    q_s = free_ik(robot, table_only, "left", [-0.04, 0.38, 0.32], Q_AWAY)
    q_g = free_ik(robot, table_only, "left", [-0.2, 0.15, 0.21], Q_AWAY)
    mid = robot.eef_position("left", (0.5 * (q_s + q_g))[None])[0]
    q_r = free_ik(robot, table_only, "right", mid, q_s)
    ok, why = check_states(table_only, "left", dense(robot, "left", np.stack([q_s, q_g]), factor=1), q_r)
    assert not ok.all() and all(w.startswith("self_collision:left_") and "/right_" in w for w in why[~ok])
    res = transit.plan_transit(robot, table_only, "left", q_s, q_g, q_r, None)
    assert res.status == "ok", res.reason
    ok, why = check_states(table_only, "left", dense(robot, "left", res.path), q_r)
    assert ok.all(), set(why[~ok])


def test_bad_inputs_raise(robot, table_only):
    q = np.zeros(7)
    with pytest.raises(ValueError, match="q_goal"):
        transit.plan_transit(robot, table_only, "left", q, np.zeros(6), q, None)
    with pytest.raises(ValueError, match="arm"):
        transit.plan_transit(robot, table_only, "middle", q, q, q, None)
    with pytest.raises(ValueError, match="limits"):
        transit.plan_transit(robot, table_only, "left", q, np.full(7, 5.0), q, None)
    with pytest.raises(ValueError, match="normal"):
        transit.plan_transit(robot, table_only, "left", q, q, q, None, n_start=np.zeros(3))
    with pytest.raises(ValueError):
        transit.Params(resolution=0.0)


# ------------------------------------------------------------------------------------------ timing


def test_time_parameterization_respects_the_limits_and_stops_on_every_waypoint():
    rng = np.random.default_rng(2)
    path = rng.uniform(-1.5, 1.5, (6, 7))
    path[3] = path[2]  # a repeated waypoint is skipped
    v = np.array([1.7, 1.7, 1.7, 1.7, 1.7, 2.0, 3.0])
    a_max, dt = 2.0, 0.02
    t, q = transit.time_parameterize(path, v, a_max, dt)
    np.testing.assert_allclose(np.diff(t), dt, rtol=1e-12)
    vel = np.diff(q, axis=0) / dt
    acc = np.diff(q, 2, axis=0) / dt**2
    # Finite differences average the continuous profile, so they obey its bounds (+ rounding).
    assert np.all(np.abs(vel) <= v * (1 + 1e-9))
    assert np.all(np.abs(acc) <= a_max * (1 + 1e-9))
    for w in path:  # every waypoint is a sample, where the arm stops
        k = np.flatnonzero(np.all(q == w, axis=1))
        assert len(k)
    np.testing.assert_array_equal(q[0], path[0])
    np.testing.assert_array_equal(q[-1], path[-1])
    # Zero velocity at the ends: the first and last steps are pure acceleration, at most a dt^2 / 2.
    assert np.abs(q[1] - q[0]).max() <= 0.5 * a_max * dt**2 + 1e-12
    assert np.abs(q[-1] - q[-2]).max() <= 0.5 * a_max * dt**2 + 1e-12


def test_time_parameterization_of_one_joint_matches_the_closed_form():
    # 1 rad at v = 1 rad/s, a = 2 rad/s^2: trapezoid, 0.5 s up, 0.5 s cruise, 0.5 s down = 1.5 s.
    t, q = transit.time_parameterize(np.array([[0.0], [1.0]]), 1.0, 2.0, 0.02)
    assert t[-1] == pytest.approx(1.5, abs=1e-12)
    assert np.diff(q[:, 0]).max() / 0.02 == pytest.approx(1.0, abs=1e-9)  # cruising at the limit
    np.testing.assert_allclose(q[list(t).index(0.5) if 0.5 in t else np.argmin(abs(t - 0.5)), 0], 0.25, atol=1e-12)
    # 0.1 rad: triangle, 2 sqrt(0.1 / 2) = 0.447 s, rounded up to 23 periods.
    t, q = transit.time_parameterize(np.array([[0.0], [0.1]]), 1.0, 2.0, 0.02)
    assert len(t) == 24 and t[-1] == pytest.approx(0.46)
    assert q[-1, 0] == 0.1


def test_retreat_that_jumps_in_coarse_steps_is_solved_again_in_finer_ones(robot):
    """A left-arm grasp configuration of the lying piano by the table's edge (Exp. 3), joint 2 18 mm from
    its limit, the contact normal pointing away from the robot: backing the ball off 3 cm in 1 cm steps,
    the damped least-squares step swings the arm 0.7 rad (a joint jump the transit refused); in 2.5 mm
    steps the same straight retreat moves no joint more than 0.05 rad a step."""
    q = np.array([3.81, -1.88, -1.64, 0.78, -1.57, 0.61, 0.64])
    n = np.array([0.87, 0.5, 0.0])
    prm = transit.Params()
    coarse = transit._leave_contacts(robot, "left", [q], [n], replace(prm, retreat_refine=1))[0]
    assert isinstance(coarse, str) and coarse.startswith("joint_jump")
    fine = transit._leave_contacts(robot, "left", [q], [n], prm)[0]
    assert fine.shape == (prm.retreat_steps * prm.retreat_refine + 1, 7)
    assert np.abs(np.diff(fine, axis=0)).max() < 0.05
    p = robot.eef_position("left", fine)
    np.testing.assert_allclose(np.linalg.norm(p[-1] - p[0]), prm.retreat, atol=1e-3)
