"""Robot model: the SDA5F URDF against the fact sheet and PyBullet, batched FK/IK, collision checks."""

import dataclasses
from pathlib import Path

import numpy as np
import pybullet
import pytest
import trimesh

from stages import robot as rb
from stages import se3
from stages.errors import InputError
from stages.robot import load_robot, make_collision_fn

URDF = Path(__file__).resolve().parents[1] / "data" / "robots" / "sda5f.urdf"

#: A scene used by the collision tests: the robot base on the floor 0.75 m behind the table centre and
#: 0.75 m below the table top (shoulders 0.15 m above it, 0.1 m behind the table's near edge).
X_WB_SCENE = se3.make_transform(np.eye(3), [-0.75, 0.0, -0.75])
TABLE = ((0.9, 0.6), 0.0)


@pytest.fixture(scope="module")
def robot():
    return load_robot(URDF)


@pytest.fixture(scope="module")
def scene_robot():
    return load_robot(URDF, X_WB=X_WB_SCENE)


class _Bullet:
    """The URDF in a PyBullet DIRECT client; disconnects on exit."""

    def __init__(self, X_WB=None):
        self.X_WB = np.eye(4) if X_WB is None else X_WB

    def __enter__(self):
        self.cid = pybullet.connect(pybullet.DIRECT)
        pos, quat = self.X_WB[:3, 3], se3.quat_from_matrix(self.X_WB[:3, :3])
        # Without URDF_USE_IMPLICIT_CYLINDER PyBullet turns the stick's <cylinder> into a convex mesh.
        self.body = pybullet.loadURDF(str(URDF), pos.tolist(), quat.tolist(), useFixedBase=True,
                                      flags=pybullet.URDF_USE_IMPLICIT_CYLINDER, physicsClientId=self.cid)
        n = pybullet.getNumJoints(self.body, physicsClientId=self.cid)
        info = [pybullet.getJointInfo(self.body, j, physicsClientId=self.cid) for j in range(n)]
        self.joint = {i[1].decode(): i[0] for i in info}
        self.link = {i[12].decode(): i[0] for i in info}
        self.info = {i[1].decode(): i for i in info}
        return self

    def __exit__(self, *exc):
        pybullet.disconnect(physicsClientId=self.cid)

    def set_q(self, names, q):
        for name, value in zip(names, q, strict=True):
            pybullet.resetJointState(self.body, self.joint[name], float(value), physicsClientId=self.cid)

    def link_pose(self, name):
        s = pybullet.getLinkState(self.body, self.link[name], computeForwardKinematics=True,
                                  physicsClientId=self.cid)
        return se3.make_transform(se3.matrix_from_quat(np.array(s[5])), np.array(s[4]))


def _random_q(arm, n, rng):
    return rng.uniform(arm.lower, arm.upper, (n, arm.dof))


# ----------------------------------------------------------------------------------------------------
# URDF and forward kinematics


def test_urdf_joint_frames_at_zero_match_fact_sheet_in_our_fk_and_pybullet(robot):
    # Fact sheet, "Geometry at q = 0" (base frame on the floor), rounded to the millimetre there.
    sheet = {
        "left_link_1_s": (0.195, 0.101, 0.900), "right_link_1_s": (0.195, -0.101, 0.900),
        "left_link_2_l": (0.2145, 0.243, 0.900),
        "left_tool0": (0.195, 0.574, 1.453), "right_tool0": (0.195, -0.574, 1.453),
        # The sheet gives joint 2 at x = 0.2145 on both sides, but its own right-arm rule (joint 1 with
        # rpy (pi/2, pi, 0), all later origins as on the left) turns joint 2's 0.0195 m offset to the
        # other side: 0.195 - 0.0195. The joint table is the data; the summary is not exact here.
        "right_link_2_l": (0.1755, -0.243, 0.900),
    }
    fk = {}
    for name in ("left", "right"):
        X = robot.fk(name, np.zeros((1, 7)))[0]
        fk.update(zip(robot.arms[name].link_names, X, strict=True))
    with _Bullet() as pb:
        for link, p in sheet.items():
            # The chain sums to y = 0.101 + 0.142 + 0.165 + 0.105 + 0.060 = 0.573 at tool0, which the
            # sheet rounds to 0.574: 1.5 mm covers its rounding, nothing more.
            np.testing.assert_allclose(fk[link][:3, 3], p, atol=1.5e-3, err_msg=link)
            np.testing.assert_allclose(pb.link_pose(link)[:3, 3], p, atol=1.5e-3, err_msg=link)
        np.testing.assert_allclose(fk["left_tool0"][:3, 3], (0.195, 0.573, 1.453), atol=1e-12)
        np.testing.assert_allclose(fk["left_ball"][:3, 3], (0.195, 0.573, 1.573), atol=1e-12)


def test_urdf_limits_and_capsules_load_in_pybullet_as_parsed(robot):
    with _Bullet() as pb:
        for arm in robot.arms.values():
            for k, name in enumerate(arm.joint_names):
                info = pb.info[name]
                assert info[2] == pybullet.JOINT_REVOLUTE
                assert info[8] == pytest.approx(arm.lower[k]) and info[9] == pytest.approx(arm.upper[k])
                assert info[11] == pytest.approx(arm.velocity[k])
            for c, link in enumerate(arm.cap_names):
                shapes = pybullet.getCollisionShapeData(pb.body, pb.link[link], physicsClientId=pb.cid)
                assert len(shapes) == 1
                kind, dims = shapes[0][2], shapes[0][3]
                length = np.linalg.norm(arm.cap_b[c] - arm.cap_a[c])
                if link.endswith("_stick"):  # a cylinder in the URDF, its enclosing capsule for us
                    assert kind == pybullet.GEOM_CYLINDER
                    assert dims[0] == pytest.approx(length) and dims[1] == pytest.approx(arm.cap_r[c])
                elif link.endswith("_ball"):
                    assert kind == pybullet.GEOM_SPHERE and length == 0.0
                else:  # PyBullet reports (length, radius) for a capsule
                    assert kind == pybullet.GEOM_CAPSULE
                    assert dims[0] == pytest.approx(length) and dims[1] == pytest.approx(arm.cap_r[c])
    # Velocities and limits straight from the fact sheet's joint table.
    left = robot.arms["left"]
    np.testing.assert_allclose(left.lower, [-1.57, -1.90, -2.95, -1.57, -3.13, -1.90, -3.13])
    np.testing.assert_allclose(left.upper, [4.71, 1.90, 2.95, 2.00, 3.13, 1.90, 3.13])
    np.testing.assert_allclose(left.velocity, [3.48, 3.48, 3.48, 3.48, 3.48, 4.00, 6.10])


def test_fk_equals_pybullet_at_random_q_for_all_links_of_both_arms_under_a_random_base_pose():
    rng = np.random.default_rng(3)
    X_WB = se3.make_transform(se3.rotation_about_axis(rng.normal(size=3), 0.7), rng.normal(size=3))
    robot = load_robot(URDF, X_WB=X_WB, torso_angle=0.4)
    with _Bullet(X_WB) as pb:
        pb.set_q(["torso_b1"], [0.4])
        for arm in robot.arms.values():
            q = _random_q(arm, 12, rng)
            X = robot.fk(arm.name, q)
            assert X.shape == (12, len(arm.link_names), 4, 4)
            for i in range(len(q)):
                pb.set_q(arm.joint_names, q[i])
                for k, link in enumerate(arm.link_names):
                    # PyBullet's link states agree with ours to a few 1e-7 (it rounds somewhere in
                    # single precision); 1e-6 m / 1e-6 is far below anything the planner resolves.
                    np.testing.assert_allclose(pb.link_pose(link), X[i, k], atol=1e-6, err_msg=link)


def test_fk_batch_equals_loop_and_eef_position_and_rotation_are_the_ball_links(robot):
    rng = np.random.default_rng(0)
    arm = robot.arms["right"]
    for n in (0, 1, 17):
        q = _random_q(arm, n, rng)
        X = robot.fk("right", q)
        assert X.shape == (n, len(arm.link_names), 4, 4)
        for i in range(n):
            np.testing.assert_array_equal(X[i], robot.fk("right", q[i:i + 1])[0])
        np.testing.assert_allclose(robot.eef_position("right", q), X[:, arm.eef_index, :3, 3], atol=1e-15)
        np.testing.assert_array_equal(robot.eef_rotation("right", q), X[:, arm.eef_index, :3, :3])
        np.testing.assert_allclose(X[:, :, 3], np.broadcast_to([0, 0, 0, 1.0], X[:, :, 3].shape))


def test_right_arm_mirrors_left_ball_through_xz_plane(robot):
    q = _random_q(robot.arms["left"], 200, np.random.default_rng(1))
    p_left, p_right = robot.eef_position("left", q), robot.eef_position("right", q)
    np.testing.assert_allclose(p_right, p_left * [1.0, -1.0, 1.0], atol=1e-12)


# ----------------------------------------------------------------------------------------------------
# Inverse kinematics


def test_ik_round_trip_on_random_reachable_targets(robot):
    rng = np.random.default_rng(7)
    for name, arm in robot.arms.items():
        p = robot.eef_position(name, _random_q(arm, 600, rng))
        res = robot.ik(name, p, rng=np.random.default_rng(0))
        assert res.q.shape == (600, 7) and res.ok.shape == res.err.shape == res.reason.shape == (600,)
        assert np.mean(res.err <= 1e-3) >= 0.99
        assert np.all((res.q >= arm.lower) & (res.q <= arm.upper))
        # err is the true distance of the returned posture's ball from its target.
        np.testing.assert_allclose(res.err, np.linalg.norm(robot.eef_position(name, res.q) - p, axis=1),
                                   atol=1e-12)
        np.testing.assert_array_equal(res.ok, res.reason == "ok")
        assert set(res.reason) <= {"ok", "ik_unreachable", "joint_limit"}


def test_ik_pose_turns_the_ball_about_its_centre_and_keeps_it_there(robot):
    """Task-priority IK: the ball's orientation is the secondary task. From random postures, a target
    turned 15 deg about a random axis through the ball centre: on most rows the centre stays within
    0.1 mm and there the turn is reached within a degree; a row that loses its centre says so in its
    error (what callers check). A target at the posture's own orientation moves nothing."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    for name, arm in robot.arms.items():
        q0 = np.clip(_random_q(arm, 200, rng) * 0.6, arm.lower, arm.upper)
        p, R = robot.eef_position(name, q0), robot.eef_rotation(name, q0)
        axis = rng.normal(size=(200, 3))
        turn = Rotation.from_rotvec(np.radians(15.0) * axis / np.linalg.norm(axis, axis=1, keepdims=True))
        R_t = turn.as_matrix() @ R
        q, err = rb.ik_pose(robot, name, p, R_t, q0)
        left = Rotation.from_matrix(R_t @ np.swapaxes(robot.eef_rotation(name, q), 1, 2)).magnitude()
        kept = err <= 1e-4
        assert kept.mean() >= 0.7 and np.all((q >= arm.lower) & (q <= arm.upper))
        assert np.mean(np.degrees(left[kept]) <= 1.0) >= 0.95
        np.testing.assert_allclose(err, np.linalg.norm(robot.eef_position(name, q) - p, axis=1), atol=1e-12)
        q_same, err_same = rb.ik_pose(robot, name, p, R, q0)
        assert np.abs(q_same - np.clip(q0, arm.lower, arm.upper)).max() < 1e-6 and err_same.max() < 1e-9


def test_ik_batch_equals_loop_for_zero_one_and_many_targets(robot):
    rng = np.random.default_rng(11)
    arm = robot.arms["left"]
    p = robot.eef_position("left", _random_q(arm, 24, rng))
    p[3] = [3.0, 0.0, 1.0]  # out of reach
    p[5] = [0.2, 0.25, 0.9]  # beside the shoulder: inside the reach sphere, needs restarts or fails
    for n in (0, 1, 24):
        batch = robot.ik("left", p[:n], rng=np.random.default_rng(5))
        assert batch.q.shape == (n, 7)
        for i in range(n):
            one = robot.ik("left", p[i:i + 1], rng=np.random.default_rng(5))
            np.testing.assert_allclose(one.q[0], batch.q[i], atol=1e-9)
            assert one.reason[0] == batch.reason[i]
    assert batch.reason[3] == "ik_unreachable" and not batch.ok[3]
    assert batch.err[3] > 1.0


def test_ik_is_deterministic_given_the_seed_and_honours_a_seed_posture(robot):
    arm = robot.arms["right"]
    q_true = _random_q(arm, 50, np.random.default_rng(2))
    p = robot.eef_position("right", q_true)
    a = robot.ik("right", p, rng=np.random.default_rng(9))
    b = robot.ik("right", p, rng=np.random.default_rng(9))
    np.testing.assert_array_equal(a.q, b.q)
    # Seeded with the answer, the solver returns it untouched.
    exact = robot.ik("right", p, q_seed=q_true, restarts=0)
    np.testing.assert_array_equal(exact.q, q_true)
    # Seeded next to it, the solver stays nearby (the posture pull drifts it a little along the arm's
    # self-motion), while unseeded solutions land anywhere on the 4-dimensional solution set.
    near = robot.ik("right", p, q_seed=q_true + 0.01, restarts=0)
    assert near.ok.all()
    assert np.max(np.abs(near.q - q_true)) < 1.0
    assert np.median(np.max(np.abs(a.q - q_true), axis=1)) > 2.0


def test_ik_far_target_is_unreachable_without_iterating(robot):
    arm = robot.arms["left"]
    far = arm.reach_centre + [0.0, arm.reach_radius + 0.01, 0.0]
    res = robot.ik("left", far[None, :])
    assert res.reason[0] == "ik_unreachable"
    np.testing.assert_array_equal(res.q[0], arm.q_rest)  # untouched: the pre-filter answered


def test_ik_reach_bound_contains_every_reachable_ball_position(robot):
    for name, arm in robot.arms.items():
        p = robot.eef_position(name, _random_q(arm, 5000, np.random.default_rng(4)))
        assert np.linalg.norm(p - arm.reach_centre, axis=1).max() <= arm.reach_radius


def test_ik_trajectory_follows_a_line_continuously(robot):
    arm = robot.arms["left"]
    p0 = robot.eef_position("left", arm.q_rest[None])[0]
    line = p0 + np.linspace(0.0, 1.0, 41)[:, None] * np.array([0.10, -0.15, -0.10])
    res = robot.ik_trajectory("left", line, arm.q_rest)
    assert res.q.shape == (41, 7) and res.ok.all()
    assert np.max(np.abs(np.diff(res.q, axis=0))) < 0.1  # 5 mm steps: no branch flip
    np.testing.assert_allclose(robot.eef_position("left", res.q), line, atol=1e-3)
    # Many paths at once give the same answer as one at a time.
    lines = np.stack([line, line + [0.0, 0.0, 0.05]], axis=1)  # (T, 2, 3)
    both = robot.ik_trajectory("left", lines, np.stack([arm.q_rest, arm.q_rest]))
    np.testing.assert_allclose(both.q[:, 0], res.q, atol=1e-12)


def test_ik_trajectory_flags_a_jump(robot):
    arm = robot.arms["left"]
    p0 = robot.eef_position("left", arm.q_rest[None])[0]
    for batch in (False, True):  # the batched first try falls back to the step-by-step solve
        res = robot.ik_trajectory("left", np.stack([p0, p0 + [0.0, -0.3, 0.0]]), arm.q_rest, max_joint_step=0.05,
                                  batch=batch)
        assert res.reason[0] == "ok" and res.reason[1] == "joint_jump"


def test_ik_trajectory_batched_is_a_continuous_solution(robot):
    arm = robot.arms["left"]
    p0 = robot.eef_position("left", arm.q_rest[None])[0]
    line = p0 + np.linspace(0.0, 1.0, 21)[:, None] * np.array([0.05, -0.08, -0.05])
    res = robot.ik_trajectory("left", line, arm.q_rest, max_joint_step=0.2, batch=True)
    assert res.q.shape == (21, 7) and res.ok.all()
    assert np.max(np.abs(np.diff(np.vstack([arm.q_rest, res.q]), axis=0))) <= 0.2
    np.testing.assert_allclose(robot.eef_position("left", res.q), line, atol=1e-3)
    # An unreachable step: the same verdict as step by step.
    far = np.vstack([line, p0 + [2.0, 0.0, 0.0]])
    a, b = (robot.ik_trajectory("left", far, arm.q_rest, batch=x) for x in (False, True))
    np.testing.assert_array_equal(a.reason, b.reason)
    assert b.reason[-1] != "ok"


def test_follow_ik_turns_the_ball_with_the_object_and_one_motion_does_not_depend_on_the_others(scene_robot):
    """A block rolled 80 deg about the x axis with the ball on its side face: the ball turns with it about
    that axis (rolls on the face by under 10 deg; position-only IK keeps its orientation, so it rolls
    tens of degrees), on its targets; each motion's joints are the same solved alone or in a batch."""
    from scipy.spatial.transform import Rotation

    arm, T = "left", 17
    p_O, n_O = np.array([0.0, 0.1, 0.08]), np.array([0.0, 1.0, 0.0])
    X = np.zeros((3, T, 4, 4))
    targets = np.zeros((T, 3, 3))
    for e, x in enumerate((-0.05, 0.0, 0.05)):
        for t in range(T):
            R = Rotation.from_rotvec([np.radians(80.0) * t / (T - 1), 0.0, 0.0]).as_matrix()
            X[e, t] = se3.make_transform(R, [x, 0.1, 0.0]) @ se3.make_transform(np.eye(3), [0.0, -0.1, 0.0])
        targets[:, e] = se3.transform_points(X[e], p_O + 0.02 * n_O)

    def rolled(X_e, q):  # the ball's turn on the object about the roll's axis (x), deg
        rel = np.einsum("tji,tjk->tik", X_e[:, :3, :3], scene_robot.eef_rotation(arm, q))
        return np.degrees(np.abs(Rotation.from_matrix(rel @ rel[0].T).as_rotvec()[:, 0])).max()

    q0 = scene_robot.ik(arm, targets[0], rng=np.random.default_rng(0)).q
    res = rb.follow_ik(scene_robot, arm, targets, X, np.arange(T), np.repeat(n_O[None], 3, axis=0), q0)
    assert res.ok.all()
    for e in range(3):
        np.testing.assert_allclose(scene_robot.eef_position(arm, res.q[:, e]), targets[:, e], atol=1e-3)
        assert rolled(X[e], res.q[:, e]) < 10.0
        one = rb.follow_ik(scene_robot, arm, targets[:, e:e + 1], X[e:e + 1], np.arange(T), n_O[None], q0[e:e + 1])
        np.testing.assert_allclose(one.q[:, 0], res.q[:, e], atol=1e-9)
    assert rolled(X[0], scene_robot.ik_trajectory(arm, targets[:, 0], q0[0]).q) > 20.0


# ----------------------------------------------------------------------------------------------------
# Geometry kernels against dense sampling (the sampled minimum is an upper bound within one step)


def _sampled_min(points_fn, a, b, n=2001):
    t = np.linspace(0.0, 1.0, n)
    P = a[:, None, :] + (b - a)[:, None, :] * t[None, :, None]  # (3, n, K)
    return points_fn(P).min(axis=0), np.linalg.norm(b - a, axis=0) / (n - 1)


def test_segment_box_distance_matches_sampling():
    rng = np.random.default_rng(0)
    h = np.array([[0.3], [0.2], [0.5]])
    a, b = rng.normal(size=(3, 1000)), rng.normal(size=(3, 1000))
    d = np.sqrt(rb._seg_box_dist2(a, b, h))
    ref, step = _sampled_min(lambda P: np.linalg.norm(np.maximum(np.abs(P) - h[:, :, None], 0), axis=0), a, b)
    assert np.all(d <= ref + 1e-12) and np.all(d >= ref - step - 1e-12)
    assert 0.1 < np.mean(d == 0) < 0.9  # both crossing and missing segments were exercised


def test_segment_segment_distance_matches_sampling_including_points_and_parallels():
    rng = np.random.default_rng(1)
    p1, q1, p2 = rng.normal(size=(3, 3, 600))
    q2 = rng.normal(size=(3, 600))
    q1[:, :50] = p1[:, :50]  # segment 1 a point
    q2[:, 25:75] = p2[:, 25:75]  # segment 2 a point (both for 25 of them)
    q2[:, 100:150] = p2[:, 100:150] + (q1 - p1)[:, 100:150]  # parallel
    d = np.sqrt(rb._seg_seg_dist2(p1, q1, p2, q2))

    def to_segment_2(P):  # exact distance from points P (3, n, K) to segment 2
        u = (q2 - p2)[:, None, :]
        t = np.clip(np.sum((P - p2[:, None, :]) * u, axis=0) / np.maximum(np.sum(u * u, axis=0), 1e-300), 0, 1)
        return np.linalg.norm(P - p2[:, None, :] - u * t, axis=0)

    ref, step = _sampled_min(to_segment_2, p1, q1)
    assert np.all(d <= ref + 1e-12) and np.all(d >= ref - step - 1e-12)


def test_segment_cylinder_distance_matches_sampling():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(3, 2000)), rng.normal(size=(3, 2000))
    d = rb._seg_cyl_dist(a, b, 0.4, 0.3)
    ref, step = _sampled_min(lambda P: rb._point_cyl_dist(P.reshape(3, -1), 0.4, 0.3).reshape(P.shape[1:]),
                             a, b)
    assert np.all(d <= ref + 1e-9) and np.all(d >= ref - step)


# ----------------------------------------------------------------------------------------------------
# Collisions


def test_collision_free_rest_posture_is_ok(scene_robot):
    check = make_collision_fn(scene_robot, table=TABLE)
    q = scene_robot.arms["left"].q_rest[None]
    ok, reason = check(q, q)
    assert ok.tolist() == [True] and reason.tolist() == ["ok"]
    assert check(q, q, blame=True)[2].tolist() == [[False, False]]


def test_arm_folded_down_through_the_table_hits_the_table(scene_robot):
    check = make_collision_fn(scene_robot, table=TABLE)
    res = scene_robot.ik("left", np.array([[-0.1, 0.3, -0.12]]))  # 12 cm under the table top
    assert res.ok[0]
    q_right = scene_robot.arms["right"].q_rest[None]
    ok, reason = check(res.q, q_right)
    assert not ok[0] and reason[0].startswith("env_collision:left_") and reason[0].endswith("/table")
    assert check(res.q, q_right, blame=True)[2].tolist() == [[True, False]]  # only the left arm is to blame
    # Without the table the same posture is free.
    assert make_collision_fn(scene_robot)(res.q, q_right)[0][0]


def test_arms_crossed_into_each_other_collide_with_each_other(scene_robot):
    check = make_collision_fn(scene_robot)  # no table: it is checked first and could be hit first
    q_rest = scene_robot.arms["left"].q_rest[None]
    p = scene_robot.eef_position("left", q_rest)
    # Each ball where the other arm's ball rests.
    ql = scene_robot.ik("left", p * [1.0, -1.0, 1.0])
    qr = scene_robot.ik("right", p)
    assert ql.ok[0] and qr.ok[0]
    ok, reason = check(ql.q, qr.q)
    assert not ok[0] and reason[0].startswith("self_collision:left_") and "/right_" in reason[0]
    assert check(ql.q, qr.q, blame=True)[2].tolist() == [[True, True]]


@pytest.mark.parametrize("kind, dims", [("box", (0.02, 0.02, 0.02)), ("sphere", (0.01,)),
                                        ("cylinder", (0.01, 0.02)), ("capsule", (0.01, 0.02)),
                                        ("mesh", trimesh.creation.icosphere(radius=0.01))])
def test_small_obstacle_at_a_link_hits_that_link(scene_robot, kind, dims):
    arm = scene_robot.arms["left"]
    q = arm.q_rest[None]
    c = arm.cap_names.index("left_link_5_r")
    X = scene_robot.fk("left", q)[0, arm.cap_link[c]]
    # Link 5's segment midpoint at rest lies in no earlier capsule, so link 5 is the pair named.
    centre = se3.transform_points(X, (arm.cap_a[c] + arm.cap_b[c]) / 2)
    check = make_collision_fn(scene_robot, table=TABLE,
                              obstacles=[(kind, dims, se3.make_transform(np.eye(3), centre))])
    ok, reason = check(q, q)
    assert reason.tolist() == ["env_collision:left_link_5_r/obstacle_0"]
    # Moved 0.2 m above the arm's highest point it touches nothing.
    above = centre + [0.0, 0.0, 0.6]
    check = make_collision_fn(scene_robot, table=TABLE,
                              obstacles=[(kind, dims, se3.make_transform(np.eye(3), above), "lamp")])
    assert check(q, q)[0].tolist() == [True]


def test_object_only_the_touching_ball_may_touch_it(scene_robot):
    arm = scene_robot.arms["left"]
    q = arm.q_rest[None]
    p_ball = scene_robot.eef_position("left", q)[0]
    box = trimesh.creation.box((0.3, 0.3, 0.3))
    check = make_collision_fn(scene_robot, table=TABLE, object_mesh=box)
    # The box's +y face 1 cm into the ball: only the ball overlaps it.
    X_WO = se3.make_transform(np.eye(3), p_ball - [0.0, 0.16, 0.0])[None]
    assert check(q, q, X_WO, np.array([[True, False]]))[1].tolist() == ["ok"]
    assert check(q, q, X_WO, np.array([[False, False]]))[1].tolist() == ["env_collision:left_ball/object"]
    # 5 cm in, the stick enters the box too, and the exemption does not cover it.
    X_WO = se3.make_transform(np.eye(3), p_ball - [0.0, 0.12, 0.0])[None]
    ok, reason = check(q, q, X_WO, np.array([[True, False]]))
    assert not ok[0] and reason[0] == "env_collision:left_stick/object"
    # A ball wholly inside a large box touches no triangle, and still collides.
    big = make_collision_fn(scene_robot, object_mesh=trimesh.creation.box((1.2, 1.2, 1.2)))
    X_WO = se3.make_transform(np.eye(3), p_ball)[None]
    assert not big(q, q, X_WO, np.array([[False, False]]))[0][0]


def _ball_near_link(robot, arm: str, q: np.ndarray, link: str, gap: float, radius: float = 0.005,
                    end: int = 0):
    """A small sphere mesh (W) ``gap`` m from the surface of ``link``'s capsule at ``q``, off its
    ``end`` (0 first, 1 second), straight down as far as the capsule's axis allows."""
    a = robot.arm(arm)
    c = list(a.cap_names).index(link)
    A, B = rb._capsules_W(a, q[:, None])
    axis = (B[:, c, 0] - A[:, c, 0]) / np.linalg.norm(B[:, c, 0] - A[:, c, 0])
    down = np.array([0.0, 0.0, -1.0]) - axis * -axis[2]  # perpendicular to the axis: the end is the nearest
    down /= np.linalg.norm(down)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    ball.apply_translation((A, B)[end][:, c, 0] + down * (a.cap_r[c] + gap + radius))
    return ball


@pytest.mark.parametrize("gap, reason", [(-0.002, "env_collision:left_link_6_b/object"),
                                         (0.003, "object_clearance:left_link_6_b/object"), (0.012, "ok")])
def test_a_link_within_the_clearance_of_the_object_fails_as_object_clearance(scene_robot, gap, reason):
    """With a 7 mm link clearance, the wrist 2 mm into the object collides, 3 mm off it is refused for
    its clearance and 12 mm off it passes (the sphere's facets sit within 0.1 mm of the sphere)."""
    q = scene_robot.arms["left"].q_rest
    obj = _ball_near_link(scene_robot, "left", q, "left_link_6_b", gap)
    check = make_collision_fn(scene_robot, table=TABLE, object_mesh=obj, link_clearance=0.007)
    ok, why = check(q[None], q[None], np.eye(4)[None], np.array([[False, False]]))
    assert why.tolist() == [reason] and ok[0] == (reason == "ok")
    # Without the clearance only the overlap counts.
    ok0, why0 = make_collision_fn(scene_robot, table=TABLE, object_mesh=obj)(q[None], q[None], np.eye(4)[None])
    assert why0.tolist() == [reason if gap < 0 else "ok"]


@pytest.mark.parametrize("kind", ["mesh", "box"])
@pytest.mark.parametrize("gap, clear", [(0.003, False), (0.012, True)])
def test_a_link_keeps_its_clearance_from_the_table_and_obstacles_too(scene_robot, kind, gap, clear):
    """The links keep the same clearance (7 mm) from the table and the obstacles as from the object
    (the table is the checker's first box): an obstacle 3 mm under the wrist is refused as
    ``env_collision``, 12 mm under it passes; without the clearance, 3 mm passes."""
    q = scene_robot.arms["left"].q_rest
    sphere = _ball_near_link(scene_robot, "left", q, "left_link_6_b", gap)
    if kind == "mesh":
        ob = ("mesh", sphere, np.eye(4), "ob")
    else:  # a 1 cm cube with its top where the sphere's top is (gap m under the wrist)
        lo, hi = sphere.bounds
        ob = ("box", (0.01, 0.01, 0.01), se3.make_transform(np.eye(3), [*((lo + hi) / 2)[:2], hi[2] - 0.005]), "ob")
    check = make_collision_fn(scene_robot, obstacles=[ob], link_clearance=0.007)
    assert check(q[None], q[None])[1].tolist() == ["ok" if clear else "env_collision:left_link_6_b/ob"]
    assert make_collision_fn(scene_robot, obstacles=[ob])(q[None], q[None])[1].tolist() == ["ok"]


@pytest.mark.parametrize("gap, reason", [(0.003, "object_clearance:left_stick/object"), (0.005, "ok")])
def test_the_stick_keeps_its_own_clearance(scene_robot, gap, reason):
    """The ball's parent link (the stick) keeps ``tool_clearance`` (4 mm here), the other links 7 mm: a
    sphere 3 mm off the stick's end away from the ball is refused, 5 mm off passes."""
    a = scene_robot.arms["left"]
    q = a.q_rest
    c = list(a.cap_names).index("left_stick")
    A, B = rb._capsules_W(a, q[:, None])
    p_ball = scene_robot.eef_position("left", q[None])[0]
    far = int(np.linalg.norm(B[:, c, 0] - p_ball) > np.linalg.norm(A[:, c, 0] - p_ball))
    obj = _ball_near_link(scene_robot, "left", q, "left_stick", gap, end=far)
    check = make_collision_fn(scene_robot, table=TABLE, object_mesh=obj, link_clearance=0.007, tool_clearance=0.004)
    assert check(q[None], q[None], np.eye(4)[None], np.array([[False, False]]))[1].tolist() == [reason]


def test_the_touching_ball_is_exempt_from_the_clearance(scene_robot):
    """A box face tangent to the touching ball: its stick ends at the ball's centre, 12 mm (20 mm ball
    radius less 8 mm stick radius) or more off the face, so a 7 mm clearance passes it. A ball keeps
    no clearance (where it touches is the grasp's business): a face 2 mm off an untouching ball passes."""
    arm = scene_robot.arms["left"]
    q = arm.q_rest[None]
    p_ball = scene_robot.eef_position("left", q)[0]
    box = trimesh.creation.box((0.3, 0.3, 0.3))
    check = make_collision_fn(scene_robot, table=TABLE, object_mesh=box, link_clearance=0.007)
    X_WO = se3.make_transform(np.eye(3), p_ball - [0.0, 0.17, 0.0])[None]  # the +y face on the ball
    assert check(q, q, X_WO, np.array([[True, False]]))[1].tolist() == ["ok"]
    X_WO = se3.make_transform(np.eye(3), p_ball - [0.0, 0.172, 0.0])[None]  # 2 mm off the ball
    assert check(q, q, X_WO, np.array([[False, False]]))[1].tolist() == ["ok"]


def test_collision_batch_equals_loop(scene_robot):
    rng = np.random.default_rng(8)
    arm = scene_robot.arms["left"]
    n = 40
    ql = np.clip(arm.q_rest + rng.normal(0, 0.6, (n, 7)), arm.lower, arm.upper)
    qr = np.clip(arm.q_rest + rng.normal(0, 0.6, (n, 7)), arm.lower, arm.upper)
    X_WO = np.broadcast_to(se3.make_transform(np.eye(3), [0.1, 0.0, 0.2]), (n, 4, 4))
    touch = rng.random((n, 2)) < 0.5
    check = make_collision_fn(scene_robot, table=TABLE, object_mesh=trimesh.creation.box((0.3, 0.4, 0.4)),
                              obstacles=[("box", (0.2, 0.2, 0.2), se3.make_transform(np.eye(3), [0.2, 0.4, 0.2]))])
    ok, reason = check(ql, qr, X_WO, touch)
    assert 0 < ok.sum() < n  # the sample mixes free and colliding rows
    assert len({r.split(":")[0] for r in reason}) == 3  # ok, env_collision, self_collision
    for i in range(n):
        one = check(ql[i:i + 1], qr[i:i + 1], X_WO[i:i + 1], touch[i:i + 1])
        assert one[0][0] == ok[i] and one[1][0] == reason[i]
    empty = check(ql[:0], qr[:0], X_WO[:0], touch[:0])
    assert empty[0].shape == empty[1].shape == (0,)


def test_threaded_collision_check_equals_the_serial_one(scene_robot):
    rng = np.random.default_rng(9)
    arm = scene_robot.arms["left"]
    n = 2100  # two slices of at least 1024 rows
    ql = np.clip(arm.q_rest + rng.normal(0, 0.6, (n, 7)), arm.lower, arm.upper)
    qr = np.clip(arm.q_rest + rng.normal(0, 0.6, (n, 7)), arm.lower, arm.upper)
    X_WO = np.broadcast_to(se3.make_transform(np.eye(3), [0.1, 0.0, 0.2]), (n, 4, 4))
    touch = rng.random((n, 2)) < 0.5
    kw = dict(table=TABLE, object_mesh=trimesh.creation.box((0.3, 0.4, 0.4)))
    one = make_collision_fn(scene_robot, **kw)(ql, qr, X_WO, touch, blame=True)
    two = make_collision_fn(scene_robot, **kw, threads=2)(ql, qr, X_WO, touch, blame=True)
    assert 0 < one[0].sum() < n
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a, b)


def test_object_on_the_first_links_axis_blocks_the_arm_at_every_posture(scene_robot):
    """A small box around the left core ball (on the first joint's axis, inside link 1's capsule
    whatever q): blocked for the left arm, not the right, and every random left posture hits it."""
    check = make_collision_fn(scene_robot, object_mesh=trimesh.creation.box((0.04, 0.04, 0.04)))
    ids, centres, radii = check.cores[0]
    assert len(ids) == 1 and radii[0] > 0.04
    X_in = se3.make_transform(np.eye(3), centres[0])
    X_away = se3.make_transform(np.eye(3), centres[0] + [0.6, 0.0, 0.0])
    blocked, why = check.object_blocks_arm(np.stack([X_in, X_away]))
    assert blocked.tolist() == [[True, False], [False, False]]
    assert why.tolist() == [f"env_collision:{scene_robot.arms['left'].cap_names[ids[0]]}/object", "ok"]
    arm = scene_robot.arms["left"]
    rng = np.random.default_rng(5)
    ql = rng.uniform(arm.lower, arm.upper, (200, arm.dof))
    qr = np.broadcast_to(scene_robot.arms["right"].q_rest, (200, arm.dof))
    ok, _, blame = check(ql, qr, np.broadcast_to(X_in, (200, 4, 4)), np.ones((200, 2), bool), blame=True)
    assert not ok.any()
    assert blame[:, 0].all()  # the left arm is always involved


def test_inner_spheres_lie_inside_the_solid():
    """Each early-accept sphere's centre is inside the mesh and its radius at most the centre's
    distance to the surface; an open mesh has none (no inside)."""
    import trimesh

    from tests.conftest import l_prism

    mesh = l_prism()
    inner = rb._make_mesh(mesh, "L prism").inner
    assert 10 <= len(inner) <= 48
    _, d, _ = trimesh.proximity.closest_point(mesh, inner[:, :3])
    assert mesh.contains(inner[:, :3]).all() and np.all(inner[:, 3] <= d) and np.all(inner[:, 3] > 0)
    opened = trimesh.Trimesh(mesh.vertices, mesh.faces[1:], process=False)
    assert len(rb._make_mesh(opened, "open L prism").inner) == 0


def _fine_meshes():
    from tests.conftest import l_prism

    return {"L prism": l_prism, "icosphere": lambda: trimesh.creation.icosphere(subdivisions=3, radius=0.2),
            "torus": lambda: trimesh.creation.torus(0.2, 0.07)}


@pytest.mark.parametrize("name", ["L prism", "icosphere", "torus"])
def test_mesh_hits_finds_each_rows_lowest_colliding_capsule_as_brute_force_fcl(name):
    """The hull filters (bounding sphere, Cyrus-Beck clipping by the spread planes), the inner spheres'
    early accept and the early exit per row only skip work: each colliding row is reported once, with
    the first colliding capsule that a plain fcl test of all pairs finds; capsules wholly inside count.
    On a few-faced hull (the L prism), a fine convex one (the icosphere's 1,280 planes, of which
    ``_spread_planes`` keeps under 96) and a fine non-convex one (the torus, its hole inside the hull)."""
    import fcl

    mesh = _fine_meshes()[name]()
    msh = rb._make_mesh(mesh, name)
    rng = np.random.default_rng(3)
    C, m = 5, 60 if name == "L prism" else 200
    centre = mesh.bounds.mean(axis=0)
    A = centre[:, None, None] + rng.uniform(-0.35, 0.35, (3, C, m))
    u = rng.normal(0.0, 1.0, (3, C, m))
    length = np.r_[0.002, rng.uniform(0.02, 0.2, C - 1)]
    B = A + u / np.linalg.norm(u, axis=0) * length[:, None]  # a capsule keeps its length
    radius = rng.uniform(0.005, 0.04, C)
    # Rows whose first capsule (2 mm long) lies wholly inside, 5 mm from the surface at least: no
    # triangle contact; without the inner spheres' early accept, found by the inside test alone.
    deep = trimesh.sample.volume_mesh(mesh, 4000)
    deep = deep[trimesh.proximity.signed_distance(mesh, deep) > radius[0] + 0.005][:10]
    assert len(deep) >= 5
    B[:, 0, :len(deep)] += deep.T - A[:, 0, :len(deep)]
    A[:, 0, :len(deep)] = deep.T
    X_OW = np.broadcast_to(np.eye(4), (m, 4, 4))
    test = rng.random((C, m)) < 0.9
    k, c = rb._mesh_hits(msh, X_OW, A, B, radius, 0.0, test)
    assert len(np.unique(k)) == len(k)
    got = dict(zip(k.tolist(), c.tolist(), strict=True))
    k0, c0 = rb._mesh_hits(dataclasses.replace(msh, inner=np.zeros((0, 4))), X_OW, A, B, radius, 0.0, test)
    assert dict(zip(k0.tolist(), c0.tolist(), strict=True)) == got
    assert rb._reaches_inner(msh.inner, A[:, c, k], B[:, c, k], radius[c]).any()
    want = {}
    for ci in range(C):
        for ki in np.flatnonzero(test[ci]):
            a, b = A[:, ci, ki], B[:, ci, ki]
            u = b - a
            g = fcl.Capsule(radius[ci], np.linalg.norm(u))
            R = se3.rotation_between(np.array([0.0, 0.0, 1.0]), u / np.linalg.norm(u))
            o = fcl.CollisionObject(g, fcl.Transform(R, (a + b) / 2))
            hit = fcl.collide(o, msh.fcl_obj, fcl.CollisionRequest(), fcl.CollisionResult()) > 0
            hit = hit or bool(mesh.contains(a[None])[0])  # wholly inside
            if hit and ki not in want:
                want[int(ki)] = ci
    assert 5 < len(want) < m  # the sample mixes free and colliding rows
    assert all(want.get(k) == 0 for k in np.flatnonzero(test[0, :len(deep)]).tolist())
    assert got == want


def test_hull_clipping_knows_the_unit_cube_and_does_not_depend_on_its_slices():
    """Cyrus-Beck against the cube [-0.5, 0.5]^3: a segment 0.1 m beyond a face is separated at radius
    0.05 and not at 0.15; one through the cube is not; ``start_in`` is its start inside every plane.
    Slicing the columns (the memory bound on fine hulls) changes no answer."""
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    planes = np.column_stack([cube.face_normals, np.einsum("ij,ij->i", cube.face_normals,
                                                           cube.triangles[:, 0])])
    a = np.array([[0.6, -0.2, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    b = np.array([[0.6, 0.2, 0.0], [-0.6, -0.6, 2.0], [0.0, 0.0, 0.0]])
    sep, start_in = rb._hull_separated(planes, a.T, b.T, np.array([0.05, 0.05, 0.05]))
    assert sep.tolist() == [True, False, False] and start_in.tolist() == [False, True, True]
    assert not rb._hull_separated(planes, a.T[:, :1], b.T[:, :1], np.array([0.15]))[0][0]
    rng = np.random.default_rng(0)
    A, B, rc = rng.uniform(-1, 1, (3, 500)), rng.uniform(-1, 1, (3, 500)), rng.uniform(0, 0.2, 500)
    whole = rb._hull_separated(planes, A, B, rc)
    sliced = rb._hull_separated(planes, A, B, rc, chunk=len(planes) * 7)
    assert all(np.array_equal(x, y) for x, y in zip(whole, sliced, strict=True))
    assert 0 < whole[0].sum() < 500


def test_hull_clipping_by_the_spread_planes_separates_only_what_the_hull_separates():
    """On a fine hull (an icosphere's 1,280 faces) the planes facing spread directions
    (``_spread_planes``, ``_mesh_hits``' filter) bound a larger polytope: every segment they separate
    the whole hull separates, and they separate most of the segments the hull does."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    planes = rb._make_mesh(ball, "icosphere").planes
    few = rb._spread_planes(planes)
    assert 40 < len(few) <= 96 < len(planes)
    rng = np.random.default_rng(1)
    A, B, rc = rng.uniform(-0.4, 0.4, (3, 3000)), rng.uniform(-0.4, 0.4, (3, 3000)), rng.uniform(0, 0.05, 3000)
    sep = rb._hull_separated(planes, A, B, rc)[0]
    sep_f = rb._hull_separated(planes[few], A, B, rc)[0]
    assert np.all(sep[sep_f]) and 0.2 < sep.mean() < 0.9 and sep_f.sum() > 0.8 * sep.sum()


# ----------------------------------------------------------------------------------------------------
# Bad input


def test_missing_end_effector_link_names_the_file(tmp_path):
    with pytest.raises(InputError, match="sda5f.urdf.*left_hand"):
        load_robot(URDF, eef_links=("left_hand", "right_ball"))


def test_mesh_collision_geometry_is_rejected(tmp_path):
    bad = tmp_path / "bad.urdf"
    bad.write_text(URDF.read_text().replace('<sphere radius="0.02"/>', '<mesh filename="ball.stl"/>'))
    with pytest.raises(InputError, match="bad.urdf.*mesh"):
        load_robot(bad)


def test_a_fine_meshs_simplification_decides_its_collisions_as_the_mesh_would():
    """On a fine curved mesh (a torus of 9,216 triangles) :func:`_mesh_hits` asks its simplification
    (``_Mesh.coarse_fcl``, within ``coarse_tol`` of the mesh both ways) and the mesh only inside the
    band of +-tol about a capsule's radius: the same rows and capsules as the mesh alone, on random
    capsules and on capsules whose axis lies within the band of the surface."""
    from dataclasses import replace

    torus = trimesh.creation.torus(major_radius=0.2, minor_radius=0.06, major_sections=96, minor_sections=48)
    msh = rb._make_mesh(torus, "torus")
    tol = msh.coarse_tol
    assert msh.coarse_fcl is not None and tol > 0
    rng = np.random.default_rng(5)
    C, m = 4, 400
    p, face = trimesh.sample.sample_surface(torus, m, seed=5)
    n = torus.face_normals[face]
    radius = np.array([0.004, 0.01, 0.02, 0.03])
    t = np.cross(n, rng.normal(size=(m, 3)))
    t /= np.linalg.norm(t, axis=1)[:, None]
    mid = p[None] + n[None] * (radius[:, None, None] + rng.uniform(-tol, tol, (C, m, 1)))  # in the band
    A = np.moveaxis(mid - 0.005 * t[None], -1, 0)
    B = np.moveaxis(mid + 0.005 * t[None], -1, 0)
    A[:, :, ::2] = rng.uniform(-0.3, 0.3, (3, C, m // 2))  # and random ones
    B[:, :, ::2] = A[:, :, ::2] + rng.uniform(-0.05, 0.05, (3, C, m // 2))
    X_OW = np.broadcast_to(np.eye(4), (m, 4, 4))
    test = np.ones((C, m), bool)
    got = rb._mesh_hits(msh, X_OW, A, B, radius, 0.0, test)
    want = rb._mesh_hits(replace(msh, coarse_fcl=None), X_OW, A, B, radius, 0.0, test)
    assert 50 < len(want[0]) < m - 50
    assert all(np.array_equal(x, y) for x, y in zip(got, want, strict=True))
