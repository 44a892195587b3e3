"""Rolling of a ball on the object (stages.rolling): the shift of rolling without slip, and where a
rolled contact leaves the surface it was planned on, against known answers on a box and a sphere."""

import numpy as np
import trimesh

from stages import se3
from stages.rolling import RollLimits, rolled_off, rolling_shift


class _FixedBall:
    """A robot whose ball keeps one orientation whatever the joints (q is ignored)."""

    def __init__(self, R: np.ndarray):
        self.R = R

    def eef_rotation(self, arm, q):
        return np.broadcast_to(self.R, (len(q), 3, 3)).copy()


class _TurningBall:
    """A robot whose ball turns with the object: joint 0 is the object's yaw."""

    def eef_rotation(self, arm, q):
        return se3.rot_z(np.asarray(q)[:, 0])[:, :3, :3]


def _yawing(theta: np.ndarray) -> np.ndarray:
    X = np.tile(np.eye(4), (len(theta), 1, 1))
    X[:, :3, :3] = se3.rot_z(theta)[:, :3, :3]
    return X


def test_a_ball_that_keeps_its_orientation_rolls_r_theta_along_the_face():
    """The object yaws by theta under a ball on its -x face that does not turn: the contact moves r theta
    along the face (the centre's velocity relative to the object is (omega_o - 0) x r n_in)."""
    r, theta = 0.02, np.linspace(0.0, 0.5, 51)
    q = np.zeros((len(theta), 7))
    shift = rolling_shift(_FixedBall(np.eye(3)), "left", q, _yawing(theta), np.array([-1.0, 0.0, 0.0]), r)
    assert np.allclose(shift[-1], [0.0, r * 0.5, 0.0], atol=1e-9)
    turning = np.c_[theta, np.zeros((len(theta), 6))]
    still = rolling_shift(_TurningBall(), "left", turning, _yawing(theta), np.array([-1.0, 0.0, 0.0]), r)
    assert np.allclose(still, 0.0, atol=1e-12)


R, MU = 0.02, 0.4  # ball radius (m); friction: the normal may turn by atan(0.4) = 21.8 deg


def _box_face_shifts(ends: list[float]) -> np.ndarray:
    """Shifts along +y (O) of a contact at the centre of a 0.2 m cube's -x face, ending at ``ends`` (m)."""
    return np.array([[0.0, 0.0, 0.0]] + [[0.0, e, 0.0] for e in ends])


def test_a_contact_that_rolls_within_its_face_stays_on():
    box = trimesh.creation.box((0.2, 0.2, 0.2))
    p, n = np.array([-0.1, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])
    assert rolled_off(box, p, n, R, _box_face_shifts([0.02, 0.05, 0.095]), MU) == -1  # the edge is at y = 0.1
    assert rolled_off(box, p, n, R, np.zeros((5, 3)), MU) == -1


def test_a_ball_that_rolls_past_its_faces_edge_is_off_at_that_row():
    """The edge lies at y = 0.1. The ball's normal turns by atan(o / r) for its centre o past the edge:
    21.8 deg at o = 8 mm. Rolled to y = 0.104, the ball 5 mm ahead (the margin) is 9 mm past: off; with
    no margin it is 4 mm past (11 deg): on; rolled to 0.12, off whatever the margin."""
    box = trimesh.creation.box((0.2, 0.2, 0.2))
    p, n = np.array([-0.1, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])
    assert rolled_off(box, p, n, R, _box_face_shifts([0.05, 0.104, 0.05]), MU) == 2
    assert rolled_off(box, p, n, R, _box_face_shifts([0.05, 0.104]), MU, RollLimits(margin=0.0)) == -1
    assert rolled_off(box, p, n, R, _box_face_shifts([0.05, 0.08, 0.12]), MU, RollLimits(margin=0.0)) == 3


def test_a_ball_that_rolls_into_a_concave_corner_is_off():
    """An L-prism's inside corner: the ball rolling along the floor of the L towards its wall presses
    into the wall once its centre is nearer to it than r - max_gap."""
    from tests.conftest import l_prism

    L = l_prism()  # the foot's top at z = 0.1 for x in [0.1, 0.3], the upright's wall at x = 0.1
    p, n = np.array([0.2, 0.0, 0.1]), np.array([0.0, 0.0, 1.0])
    towards_wall = np.array([[0.0, 0.0, 0.0], [-0.05, 0.0, 0.0], [-0.07, 0.0, 0.0], [-0.09, 0.0, 0.0]])
    assert rolled_off(L, p, n, R, towards_wall[:3], MU) == -1  # 5 mm ahead its centre is 25 mm from the wall
    assert rolled_off(L, p, n, R, towards_wall, MU) == 3  # ahead, 5 mm from the wall: it presses into it


def test_on_a_curved_surface_a_short_roll_stays_on_and_a_long_one_turns_off():
    """A sphere of radius 0.2 m: a roll s along the tangent plane moves the ball's centre off the
    sphere by about s^2 / 2(R + r) and turns its normal by s / (R + r); 1 cm stays on, 6 cm (16 deg
    with the margin, but 8 mm off the surface) is off."""
    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.2)
    p, n = np.array([0.2, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    assert rolled_off(ball, p, n, R, np.array([[0.0, 0.0, 0.0], [0.0, 0.01, 0.0]]), MU) == -1
    assert rolled_off(ball, p, n, R, np.array([[0.0, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.06, 0.0]]), MU) == 2
