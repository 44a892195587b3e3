"""The squeeze tumble (``stages.squeeze``): statics, profile, candidates, the plan's check and physics.

The case: a 0.3 x 0.3 x 0.25 m box of 3 kg on the default table, rolled over its bottom edge away
from the robot (+x, W) onto its +x face, both balls on its +-y faces 10 cm behind its centre and 9 cm
above it: farther from the edge than the CoM, so that lifting there turns the box about its edge.
"""

from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np
import pytest
import trimesh

from stages import analyze, graph, mpc, squeeze, stability, trajectory
from stages.objectmodel import load_object_model
from stages.poses import roll_segments
from stages.sample import placement_pose
from stages.scene import load_scene
from tests.conftest import write_scene

BOX = (0.3, 0.3, 0.25)
MASS = 3.0


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """The box's scene, model, analysis tables, start pose, far bottom edge, roll and grasp contacts."""
    tmp = tmp_path_factory.mktemp("squeeze")
    mesh = tmp / "box.stl"
    trimesh.creation.box(BOX).export(mesh)
    path = write_scene(tmp, "box", **{"object.mesh": str(mesh), "object.mass": MASS, "start.xy": [-0.1, 0.0],
                                      "start.yaw_deg": 0, "goal.xy": [0.2, 0.0], "goal.yaw_deg": 0})
    analyze.run(mesh, tmp / "analysis", MASS, analyze.Params())
    scene = load_scene(path)
    model, tables = load_object_model(tmp / "analysis")
    X, _ = placement_pose(scene.start, model, "start")
    on_floor = np.abs((model.vertices @ X[:3, :3].T + X[:3, 3])[:, 2]) < 1e-6
    x = (model.vertices @ X[:3, :3].T + X[:3, 3])[:, 0]
    far = np.flatnonzero(on_floor & (x > x.max() - 1e-6))
    roll = roll_segments(model, X, int(far[0]), int(far[1]))
    con = tables["contacts"]
    p = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    n = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    contacts = []
    for side in (1.0, -1.0):  # left ball on +y (W), right on -y
        want = model.com + X[:3, :3].T @ np.array([-0.1, side * BOX[1] / 2, 0.09])
        ok = (n @ (X[:3, :3].T @ [0.0, side, 0.0])) > 0.99
        contacts.append(int(np.flatnonzero(ok)[np.argmin(np.linalg.norm(p[ok] - want, axis=1))]))
    return {"scene": scene, "model": model, "tables": tables, "X": X, "edge": (int(far[0]), int(far[1])),
            "roll": roll, "c": contacts, "p": p[contacts], "n": n[contacts], "dir": tmp}


def _holds(box, mu: float, f_max: float, angles=None) -> np.ndarray:
    roll = box["roll"]
    th = squeeze.sample_angles(roll, 9) if angles is None else np.asarray(angles)
    A = len(th)
    return squeeze.squeeze_holds(MASS, box["model"].com, roll.poses(th), squeeze.edge_points(box["model"], roll, th),
                                 np.repeat(box["p"][None], A, 0), np.repeat(box["n"][None], A, 0), 0.3,
                                 stability.Params(mu_eef=mu, mu_table=0.5, f_max=f_max))


def test_the_box_rolls_a_quarter_turn_about_its_far_edge(box):
    roll = box["roll"]
    assert len(roll.angle) == 1 and roll.total == pytest.approx(np.pi / 2)
    th = squeeze.sample_angles(roll, 9)
    edge = squeeze.edge_points(box["model"], roll, th)
    np.testing.assert_allclose(edge[:, :, 2], 0.0, atol=1e-9)  # the edge stays on the table, where it was
    np.testing.assert_allclose(edge, np.broadcast_to(edge[:1], edge.shape), atol=1e-9)
    assert np.all(np.diff(th) > 0) and th[0] > 0 and th[-1] == pytest.approx(roll.total - 1e-3)


def test_two_balls_hold_the_box_on_its_edge_by_friction_within_the_force_bound(box):
    """The balls' normals lie along the roll axis: only their friction turns the box about its edge.
    At the start its weight acts 0.15 m from the edge, the balls lift 0.25 m from it: 8.8 N each,
    which friction 0.4 (0.35 in the inscribed pyramid) gives with 25 N of squeeze."""
    assert _holds(box, 0.4, 45.0).all()
    assert not _holds(box, 0.0, 45.0).any()  # no friction: no torque about the edge at any angle
    assert not _holds(box, 0.4, 5.0)[:3].any()  # 5 N cannot lift it off its face
    # Exactly over the edge (the CoM above it, atan(0.15 / 0.125)) it balances with no help at all.
    assert _holds(box, 0.0, 45.0, [np.arctan2(BOX[0] / 2, BOX[2] / 2)]).all()


def test_the_profile_grips_then_rolls_to_the_landing_at_rest(box):
    P = squeeze.SqueezeParams()
    t, th = squeeze.squeeze_profile(box["roll"], P, 1.0 / 24.0)
    assert np.all(th[t < P.grip_time] == 0.0) and th[-1] == pytest.approx(np.pi / 2)
    assert np.all(np.diff(th) >= -1e-12)
    assert t[-1] == pytest.approx(P.grip_time + P.time_per_rad * np.pi / 2, abs=1.0 / 24.0)
    assert th[-2] == pytest.approx(th[-1], abs=1e-3)  # it arrives at rest


def test_squeeze_candidates_pair_the_grasps_with_the_same_contacts():
    links = {"primitive": np.array(["pivot", "tumble", "tumble"]), "pose_a": np.array([0, 0, 2]),
             "pose_b": np.array([1, 2, 3])}
    support = np.array(["SP", "SP", "SP", "USP"])
    by_pose = {0: {(1, 2): 10, (3, 4): 11}, 1: {(1, 2): 12}, 2: {(1, 2): 13, (5, 6): 14}, 3: {(5, 6): 15}}
    cand = graph.squeeze_candidates(links, support, by_pose)
    # the pivot link is not a tumble; 0 -> 2 shares (1, 2); 2 -> 3 (into USP) shares (5, 6)
    np.testing.assert_array_equal(cand, [[10, 13, 1], [14, 15, 2]])
    support[2] = "USP"  # out of USP the grasp would have to lift the object off its holding ball
    np.testing.assert_array_equal(graph.squeeze_candidates(links, support, by_pose), [[10, 13, 1]])


def _box_mpc(box, mu: float):
    P = squeeze.SqueezeParams()
    m = squeeze.squeeze_motion(box["model"], box["X"], box["edge"], P, 1.0 / 24.0)
    inertia = np.asarray(box["tables"]["summary"]["inertia"])
    mp = mpc.Params(dt=1.0 / 24.0, mu_eef=mu, mu_table=0.4, f_max=50.0)
    return trajectory.tumble_mpc(MASS, inertia, box["model"], m.roll, m.theta, m.t, m.X_ref, np.ones(len(m.t), bool),
                                 box["p"], box["n"], mp)


def test_the_tumbling_mpc_rolls_the_box_with_both_balls(box):
    out = _box_mpc(box, 0.4)
    assert not isinstance(out, str), out
    X, f, _, errs = out
    assert np.max(np.linalg.norm(f, axis=2)) < 50.0 and max(errs) < 5e-3
    np.testing.assert_allclose(X[-1], box["roll"].X_end, atol=2e-3)
    assert isinstance(_box_mpc(box, 0.02), str)  # with next to no friction the balls cannot turn it


@pytest.mark.slow
def test_the_squeezed_box_lands_on_its_face_in_physics(box):
    """``stages.trajectory.compute`` of a grasp (a transit of each arm from home) and a squeeze
    tumble, then PyBullet: the box lands on its +x face where the plan put it; seeds perturb it."""
    from stages import execute, se3, transit
    from stages.robot import load_robot
    from stages.sample import make_scene_collision_fn

    scene, X = box["scene"], box["X"]
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), scene.robot.eef_links)
    collide = make_scene_collision_fn(scene, robot, box["tables"]["mesh"])
    home = np.zeros(robot.arm("left").dof)
    paths, q = {}, {"left": home, "right": home}
    for k, arm in enumerate(("left", "right")):
        ball = se3.transform_points(X, box["p"][k] + scene.robot.ball_radius * box["n"][k])
        q_goal = robot.ik(arm, ball[None]).q[0]
        res = transit.plan_transit(robot, collide, arm, home, q_goal, q["right" if arm == "left" else "left"], X,
                                   n_goal=se3.rotate_vectors(X, box["n"][k]))
        assert res.status == "ok", res.reason
        paths[arm], q[arm] = res.path.tolist(), res.path[-1]
    pose = se3.columns_from_matrix
    c = {"left": box["c"][0], "right": box["c"][1]}
    steps = [{"primitive": "regrasp", "support": "SP", "arms": ["left", "right"], "transit": paths, "contacts": c,
              "X_WO_from": pose(X), "X_WO_to": pose(X)},
             {"primitive": "tumble", "mode": "squeeze", "support": "SP", "edge": list(box["edge"]), "contacts": c,
              "squeeze": asdict(squeeze.SqueezeParams()), "X_WO_from": pose(X), "X_WO_to": pose(box["roll"].X_end)}]
    cols, stats = trajectory.compute(scene, box["dir"] / "analysis", {"status": "ok", "steps": steps},
                                     trajectory.Params())
    assert stats["status"] == "ok", stats
    assert stats["tumbles"][0]["mode"] == "squeeze"
    summ = box["tables"]["summary"]

    def run(sc, seed):
        return execute.simulate(sc, box["dir"] / "analysis" / "object.ply", MASS, np.asarray(summ["com"]),
                                np.asarray(summ["inertia"]), cols, box["roll"].X_end,
                                execute.Params(seed=seed, cache_dir=str(box["dir"] / "convex"))).metrics

    for seed in (0, 1):
        m = run(scene, seed)
        assert m["success"], (seed, m)
        assert m["max_edge_slip"] < 0.01 and m["max_tilt_deviation_deg"] < 2.0 and not m["fell"]
    # The balls turn it by their friction (their normals lie along the axis): on a slippery box the
    # same rows do not land it.
    m = run(replace(scene, object=replace(scene.object, friction=0.05)), 0)
    assert not m["success"], m


def test_a_plan_step_of_a_squeeze_names_its_contacts_edge_and_parameters_not_a_pusher():
    from stages import provenance
    from stages.errors import ArtifactError

    pose = {"x": 0.0, "y": 0.0, "z": 0.1, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0}
    step = {"primitive": "tumble", "mode": "squeeze", "support": "SP", "edge": [0, 1],
            "contacts": {"left": 3, "right": 4}, "squeeze": {}, "X_WO_from": pose, "X_WO_to": pose}
    provenance.check_plan_steps("plan.json", {"steps": [step]}, 8, 10)
    for key, bad in (("contacts", None), ("edge", None), ("squeeze", None), ("edge", [0, 9])):
        broken = {k: v for k, v in step.items() if k != key} if bad is None else {**step, key: bad}
        with pytest.raises(ArtifactError, match="step 0"):
            provenance.check_plan_steps("plan.json", {"steps": [broken]}, 8, 10)
    with pytest.raises(ArtifactError, match="pusher"):  # a pusher's tumble still needs its pusher
        provenance.check_plan_steps("plan.json", {"steps": [{**step, "mode": "push"}]}, 8, 10)
