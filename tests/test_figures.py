"""Figures a person wants: the plan over a faint lattice with the goal; the execution filmed from the
far side of the robot, the goal marked, at a frame rate that shows the motion."""

from pathlib import Path

import numpy as np

from stages import se3
from stages.execute import scene_camera
from stages.plots import GIF_SPEEDUP, _draw_lattice, gif_frame_ms
from stages.scene import load_scene

REPO = Path(__file__).resolve().parents[1]


def _eye(cam) -> np.ndarray:
    """The camera's eye in W (PyBullet's yaw/pitch: the eye lies along (sin yaw, -cos yaw) from the target)."""
    y, pt = np.radians(cam.yaw_deg), np.radians(cam.pitch_deg)
    return np.asarray(cam.target) + cam.distance * np.array([np.sin(y) * np.cos(pt), -np.cos(y) * np.cos(pt),
                                                              -np.sin(pt)])


def test_exp3_camera_looks_from_the_far_side_of_the_robot_toward_where_the_piano_goes():
    scene = load_scene(REPO / "data/scenes/exp3_obstacle.json")
    X0 = se3.matrix_from_columns({"x": [0.0], "y": [-0.1], "z": [0.0], "qx": [0.0], "qy": [0.0], "qz": [0.0],
                                  "qw": [1.0]})[0]
    X1 = X0.copy()
    X1[:2, 3] = [-0.016, -0.213]
    cam = scene_camera(scene, X0, X1, np.zeros(3))
    eye, base = _eye(cam), scene.base_transform()[:3, 3]
    # The target lies between the eye and the torso: nothing of the robot stands in front of the piano.
    assert eye[0] > cam.target[0] > base[0]
    assert eye[1] < cam.target[1]  # swung toward -y, where the piano is tumbled over the table's edge
    assert eye[2] > cam.target[2]  # looking down onto the table


def test_gif_plays_the_motion_at_a_fixed_speed_up_whatever_the_frame_count():
    # 57 s of motion in 57 frames (the CLI's default: one per second of motion): 8 frames a second.
    assert gif_frame_ms(57.0, 58) == round(1000 / GIF_SPEEDUP)
    assert gif_frame_ms(57.0, 24) == round(1000 * 57 / 23 / GIF_SPEEDUP)
    assert gif_frame_ms(0.5, 200) == 40 and gif_frame_ms(600.0, 2) == 1000


def test_plan_lattice_draws_one_line_per_pair_of_poses_not_per_edge():
    import matplotlib.pyplot as plt

    p = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]])
    pose = np.array([0, 0, 0, 1, 1, 2])  # six nodes on three poses
    edges = {"node_a": np.array([0, 1, 2, 3, 4]), "node_b": np.array([3, 4, 3, 5, 0]),
             "primitive": np.array(["pivot"] * 4 + ["tumble"]), "status": np.array(["ok"] * 5)}
    fig, ax = plt.subplots()
    _draw_lattice(ax, p, pose, edges, edges["status"] == "ok")
    lines = {c.get_label(): len(c.get_segments()) for c in ax.collections if c.get_label().startswith(("pivot",
                                                                                                       "tumble"))}
    plt.close(fig)
    assert lines == {"pivot: 4 edges, 2 pose pairs": 2, "tumble: 1 edges, 1 pose pairs": 1}
