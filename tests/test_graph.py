"""Graph edges on hand-made grasp tables whose answers can be counted by hand, and the pushers of tumbles
in closed form (stages.graph)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages import graph, plan, poses, se3


def _grasps(rows):
    """Grasp table from ``(pose, left contact, right contact, hold_left, hold_right)`` rows."""
    pose, cl, cr, hl, hr = (np.array(c) for c in zip(*rows, strict=True))
    return {"pose_id": pose, "contact_left": cl, "contact_right": cr, "hold_left": hl.astype(bool),
            "hold_right": hr.astype(bool)}


def _collide(blocked):
    """A checker that knows each arm's grasp by its first joint and refuses the (left, right) pairs named."""
    def collide(q_left, q_right, X_WO, touching):
        assert touching.all()  # both balls are on the object in the intermediate configuration
        bad = np.array([(int(a), int(b)) in blocked for a, b in zip(q_left[:, 0], q_right[:, 0], strict=True)],
                       dtype=bool).reshape(-1)
        return ~bad, np.where(bad, "self_collision:left_ball/right_ball", "ok")
    return collide


def _edges(rows, blocked=()):
    gr = _grasps(rows)
    G = len(rows)
    q = np.zeros((G, 2, 7))
    q[:, 0, 0] = q[:, 1, 0] = np.arange(G)  # joint 0 names the grasp
    out = graph.usp_regrasp_edges(gr, np.arange(G), q, np.repeat(np.eye(4)[None], 3, axis=0), _collide(blocked), 0.5)
    return {(a, b): (st, arm) for a, b, prim, w, st, *_, arm in out if prim == "regrasp" and w == 0.5}


def test_usp_regrasp_moves_one_ball_while_the_other_holds_alone():
    # grasp: 0 = (1, 2), 1 = (1, 3): the left ball stays on contact 1 and must hold alone.
    assert _edges([(0, 1, 2, True, False), (0, 1, 3, True, False)]) == {(0, 1): ("ok", "right")}
    assert _edges([(0, 1, 2, False, True), (0, 1, 3, False, True)]) == {(0, 1): ("unstable", "right")}
    # The right ball stays on contact 2.
    assert _edges([(0, 1, 2, False, True), (0, 4, 2, False, True)]) == {(0, 1): ("ok", "left")}


def test_usp_regrasp_of_both_balls_goes_in_the_order_whose_holds_and_arms_allow_it():
    # (1, 2) -> (4, 5): the right first needs hold_left of (1, 2) and hold_right of (4, 5), the arms at (1, 5).
    assert _edges([(0, 1, 2, True, False), (0, 4, 5, False, True)]) == {(0, 1): ("ok", "right,left")}
    # The left first needs hold_right of (1, 2) and hold_left of (4, 5), the arms at (4, 2).
    assert _edges([(0, 1, 2, False, True), (0, 4, 5, True, False)]) == {(0, 1): ("ok", "left,right")}
    # No order in which one ball always holds: refused.
    assert _edges([(0, 1, 2, True, False), (0, 4, 5, True, False)]) == {(0, 1): ("unstable", "right,left")}
    # Both orders hold; the right-first arms (grasp 0's left, grasp 1's right) collide, the left-first do not.
    rows = [(0, 1, 2, True, True), (0, 4, 5, True, True)]
    assert _edges(rows) == {(0, 1): ("ok", "right,left")}
    assert _edges(rows, blocked={(0, 1)}) == {(0, 1): ("ok", "left,right")}
    st, _ = _edges(rows, blocked={(0, 1), (1, 0)})[(0, 1)]
    assert st == "self_collision:left_ball/right_ball"


def test_usp_regrasp_pairs_only_grasps_of_one_pose():
    rows = [(0, 1, 2, True, True), (2, 4, 5, True, True), (0, 6, 7, True, True), (2, 1, 2, True, True)]
    assert set(_edges(rows)) == {(0, 2), (1, 3)}


def test_plan_walks_a_usp_regrasp_backwards_in_the_reverse_order():
    edges = {"arm": np.array(["right,left", "left"]), "node_a": np.array([10, 10]), "node_b": np.array([11, 12])}
    assert plan.movers(edges, 0, 10) == ["right", "left"]
    assert plan.movers(edges, 0, 11) == ["left", "right"]
    assert plan.movers(edges, 1, 12) == ["left"]


def _handover(catch_rows, grasp_rows, blocked=()):
    """Hand-over edges from catches ``(pose, arm, contact)`` to grasps ``(pose, left, right, hold_l, hold_r)``."""
    gr = _grasps(grasp_rows)
    G = len(grasp_rows)
    q = np.zeros((G, 2, 7))
    q[:, 0, 0] = q[:, 1, 0] = np.arange(G)
    pose, arm, contact = (np.array(c) for c in zip(*catch_rows, strict=True))
    C = len(catch_rows)
    catches = {"node_id": 100 + np.arange(C), "pose_id": pose, "arm": arm, "contact": contact,
               "status": np.full(C, "ok"), "q": np.full((C, 7), 50.0 + np.arange(C)[:, None])}
    out = graph.handover_edges(catches, gr, q, np.repeat(np.eye(4)[None], 2, axis=0), _collide(blocked), 0.5)
    return {(a, b): (st, arm) for a, b, prim, w, st, *_, arm in out}


def test_handover_from_a_catch_moves_the_pusher_then_the_catcher_while_the_pusher_holds():
    # The right ball caught on contact 9 of pose 0. Grasp 0 = (1, 9): its right contact is the catch's,
    # only the left (the pusher) moves. Grasp 1 = (2, 3): the left takes 2, then the right leaves 9 for 3
    # while the left alone holds; grasp 2 = (4, 5) cannot (its left ball does not hold alone).
    grasps = [(0, 1, 9, False, False), (0, 2, 3, True, False), (0, 4, 5, False, True), (1, 6, 7, True, True)]
    edges = _handover([(0, "right", 9)], grasps)
    assert edges == {(100, 0): ("ok", "left"), (100, 1): ("ok", "left,right"), (100, 2): ("unstable", "left,right")}
    # The arms at the pusher's grasp configuration and the catch's (the catch's joints: 50) must be free.
    assert _handover([(0, "right", 9)], grasps, blocked={(1, 50)})[(100, 1)][0] == "self_collision:left_ball/right_ball"
    # A left catcher: the right ball is the pusher, and must hold alone before the left one moves.
    edges = _handover([(0, "left", 1)], grasps)
    assert edges == {(100, 0): ("ok", "right"), (100, 1): ("unstable", "right,left"), (100, 2): ("ok", "right,left")}


def _hold_edges(catch_rows, hold_rows, grasp_rows, blocked=()):
    """Hand-over edges through holds: catches and holds ``(pose, arm, contact, status)``, grasps as above.
    Joint 0 names the configuration: grasp g's arms g, catch i's 50 + i, hold j's 70 + j."""
    gr = _grasps(grasp_rows)
    G = len(grasp_rows)
    q = np.zeros((G, 2, 7))
    q[:, 0, 0] = q[:, 1, 0] = np.arange(G)

    def table(rows, first_node, first_q):
        pose, arm, contact, status = (np.array(c) for c in zip(*rows, strict=True))
        n = len(rows)
        return {"node_id": first_node + np.arange(n), "pose_id": pose, "arm": arm, "contact": contact,
                "status": status, "q": np.full((n, 7), first_q + np.arange(n)[:, None], dtype=float)}

    out = graph.hold_edges(table(catch_rows, 100, 50.0), table(hold_rows, 200, 70.0), gr, q,
                           np.repeat(np.eye(4)[None], 2, axis=0), _collide(blocked), 0.5)
    assert all(prim == "regrasp" and w == 0.25 for _, _, prim, w, *_ in out)  # half a regrasp each
    return {(a, b): (st, arm) for a, b, prim, w, st, *_, arm in out}


def test_handover_through_a_hold_moves_each_ball_while_the_other_holds_alone():
    # The right ball caught (catch 100, pose 0); the left (the pusher) may hold alone on top at contact
    # 11 (hold 200) but not at 12 (hold 201, unstable); hold 202 is the right arm's, and 203 another pose's.
    catches = [(0, "right", 9, "ok")]
    holds = [(0, "left", 11, "ok"), (0, "left", 12, "unstable"), (0, "right", 13, "ok"), (1, "left", 14, "ok")]
    # Grasps of pose 0: (2, 3) whose right ball holds alone, (4, 5) whose right ball does not.
    grasps = [(0, 2, 3, False, True), (0, 4, 5, True, False), (1, 6, 7, True, True)]
    edges = _hold_edges(catches, holds, grasps)
    # catch -> hold: the pusher onto the hold's contact while the catcher holds; a refused hold's reason.
    assert edges[(100, 200)] == ("ok", "left") and edges[(100, 201)] == ("unstable", "left")
    assert (100, 202) not in edges and (100, 203) not in edges  # only the other arm's holds on its pose
    # hold -> grasp: the catcher onto its grasp contact while the pusher holds, then the pusher onto its
    # own while the catcher's ball holds alone (hold_right of the grasp).
    assert edges[(200, 0)] == ("ok", "right,left") and edges[(200, 1)] == ("unstable", "right,left")
    assert (200, 2) not in edges and not any(a == 201 for a, _ in edges)  # its pose only; ok holds only
    # The right arm's hold 202 hands over to the left ball: the left moves first (hold_left of the grasp).
    assert edges[(202, 0)] == ("unstable", "left,right") and edges[(202, 1)] == ("ok", "left,right")
    # The arms at the catch and the hold (joints 50, 70), or at the hold and the catcher's grasp contact
    # (70, 0), must be free of each other.
    hit = "self_collision:left_ball/right_ball"
    assert _hold_edges(catches, holds, grasps, blocked={(70, 50)})[(100, 200)][0] == hit
    assert _hold_edges(catches, holds, grasps, blocked={(70, 0)})[(200, 0)][0] == hit


# --- Pushers of a tumble (graph.push_levers, graph.release_angle, graph.pusher_motion) ------------------

def test_push_levers_are_the_moment_of_the_best_push_in_the_friction_cone(rng):
    """A box w = 0.30 deep, H = 0.25 high, tipping over its edge along y at the origin (x in [-w, 0]): the
    contact moves along a x (p - p_axis) = (z, 0, x_dist). On the far side face the best push, tilted up
    by the friction, has moment z + mu w per unit normal force (its normal alone is atan(w / z) = 52 deg
    off the motion at z = 0.23: the old 50 deg cone refused it); on the top face x from the edge,
    -x + mu H (friction pulling toward the edge against the ball's press); on the landing face (x = 0),
    -z: it can only resist the turn. Invariant under a rigid transform; a batch is its rows."""
    w, H, mu = 0.30, 0.25, 0.4
    p = np.array([[-w, 0.05, 0.23], [-w, -0.1, 0.1], [-0.05, 0.0, H], [-0.2, 0.1, H], [0.0, 0.0, 0.12]])
    n = np.array([[-1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0]])
    a, p0 = np.array([0.0, 1.0, 0.0]), np.zeros(3)
    want = [0.23 + mu * w, 0.1 + mu * w, -0.05 + mu * H, -0.2 + mu * H, -0.12]
    np.testing.assert_allclose(graph.push_levers(p, n, p0, a, mu), want, atol=1e-12)
    assert np.degrees(np.arctan2(w, 0.23)) > 50.0
    X = se3.make_transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
    moved = graph.push_levers(se3.transform_points(X, p), se3.rotate_vectors(X, n), se3.transform_points(X, p0),
                              se3.rotate_vectors(X, a), mu)
    np.testing.assert_allclose(moved, want, atol=1e-12)
    for i in range(len(p)):
        assert graph.push_levers(p[i:i + 1], n[i:i + 1], p0, a, mu)[0] == pytest.approx(want[i], abs=1e-12)
    assert graph.push_levers(p[:0], n[:0], p0, a, mu).shape == (0,)


def _lying_box(size=(0.40, 0.30, 0.25), yaw=np.pi / 2):
    """The benchmark's box lying flat, its 0.30 side along x (yaw 90 deg), and its bottom edge farthest
    from the robot (+x): ``(model, X, edge)``."""
    from tests.test_poses import box_model, upright

    model = box_model(size)
    X, g = upright(model, yaw=yaw)
    on_face = np.isin(model.edges, np.asarray(model.support[g])).all(axis=1)
    mid_x = se3.transform_points(X, model.vertices[model.edges].mean(axis=1))[:, 0]
    e = np.flatnonzero(on_face)[np.argmax(np.where(on_face, mid_x, -np.inf)[on_face])]
    return model, X, tuple(int(v) for v in model.edges[e])


def test_release_angle_is_past_the_tip_over_and_never_before_the_push_angle():
    """``stages.trajectory`` lets the pusher go ``release_past_tip`` past the angle where the CoM crosses
    the axis, and the graph checks the push up to there: tipping the lying box (w 0.30, H 0.25) over its
    edge, atan(w / H) = 50.2 deg + 10 deg (to the 0.125 deg grid); the box standing on its 0.20 x 0.30 end
    (H 0.40) over its 0.30 edge tips at atan(0.2 / 0.4) = 26.6 deg: the push still goes to ``push_angle``."""
    gp = graph.Params()
    model, X, (e0, e1) = _lying_box()
    roll = poses.roll_segments(model, X, e0, e1)
    assert graph.release_angle(model, roll, gp) == pytest.approx(np.arctan2(0.30, 0.25) + gp.release_past_tip,
                                                                 abs=np.radians(0.13))
    model, X, (e0, e1) = _lying_box((0.30, 0.20, 0.40))
    assert graph.release_angle(model, poses.roll_segments(model, X, e0, e1), gp) == pytest.approx(gp.push_angle)


def _tip_inputs(model, X, roll, pc, nc):
    """``tip_holds``' inputs for every contact of the object at ``X`` tumbling along ``roll``."""
    n, edge = len(pc), se3.transform_points(roll.X_seg[0], model.vertices[roll.edge[0]])
    return (np.repeat(se3.transform_points(X, model.com)[None], n, 0), np.repeat(edge[None], n, 0),
            se3.transform_points(X, pc), se3.rotate_vectors(X, nc))


def test_a_lying_box_tipped_away_from_the_robot_is_pushed_on_its_near_face(tmp_path):
    """The benchmark's box (0.40 x 0.30 x 0.25 m, 3 kg) lying flat at the table's centre, its 0.30 side
    along x, tipped over its far bottom edge: a ball pushes on the near side face (facing the robot),
    high up, where its best push lifts the box within the force bound (the old 50 deg cone about the
    contact's motion found no contact), and its joints follow the roll to the release angle with the
    ball on its contact; the best in line with the CoM. No push starts the tip alone on the scene's
    table (:func:`graph.tip_holds`), on a rubber mat those that do rank first. With a 5 N force bound
    no contact's push lifts the box."""
    import trimesh

    from stages import analyze
    from stages.robot import load_robot
    from stages.sample import make_scene_collision_fn
    from stages.scene import load_scene
    from tests.conftest import write_scene

    mesh_path = tmp_path / "box.stl"
    trimesh.creation.box((0.40, 0.30, 0.25)).export(mesh_path)
    scene = load_scene(write_scene(tmp_path, "box", **{"object.mesh": str(mesh_path), "object.mass": 3.0}))
    mesh = trimesh.load(mesh_path)
    con = analyze.compute(mesh, 3.0, analyze.Params()).contacts
    pc = np.stack([con["px"], con["py"], con["pz"]], axis=1)
    nc = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
    model, X, (e0, e1) = _lying_box()
    roll = poses.roll_segments(model, X, e0, e1)
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    collide = make_scene_collision_fn(scene, robot, mesh)
    gp, r = graph.Params(), scene.robot.ball_radius
    limits = graph.push_limits(scene, gp)
    assert limits == (0.8 * 0.5, 50.0, pytest.approx(3.0 * 9.81), 0.8 * 0.5)
    # On the scene's table (0.8 x 0.5) few pushes start the tip alone: the horizontal part of a push
    # that lifts the CoM 0.15 m from the edge exceeds what the edge's friction holds (a catcher may
    # take it); on a rubber mat (1.0) more do, and they rank first.
    hits = [graph.tip_holds(*_tip_inputs(model, X, roll, pc, nc), lim)
            for lim in (limits, limits._replace(mu_table=1.0))]
    assert hits[1].sum() > hits[0].sum()
    mat = graph._push_candidates(model, X[None], roll.X_end[None], np.array([[e0, e1]]), pc, nc, gp,
                                 limits._replace(mu_table=1.0), ("left", "right")).rows
    first = mat[mat[:, 3] == 0, 2]
    assert len(first) and hits[1][first].all()
    arm, c, q = graph.pusher_motion(robot, collide, model, X, roll.X_end, e0, e1, pc, nc, r, gp, limits)
    assert arm is not None, c
    p_W, n_W = se3.transform_points(X, pc[c]), se3.rotate_vectors(X, nc[c])
    assert n_W[0] < -0.99 and p_W[2] > 0.15  # the near side face, its upper part
    lever = graph.push_levers(p_W[None], n_W[None], roll.p_axis[0], roll.a_axis[0], limits.mu)[0]
    assert lever * limits.f_max > limits.weight * 0.15  # the weight's moment: 0.15 m from the axis
    # Followed to the release angle (60.2 deg) at most push_step apart: 9 rows, the last at the release.
    th_r = graph.release_angle(model, roll, gp)
    assert len(q) == int(np.ceil(th_r / gp.push_step)) + 1 == 9
    balls = robot.eef_position(arm, q)
    want = se3.transform_points(roll.poses(np.linspace(0.0, th_r, len(q))), pc[c] + r * nc[c])
    np.testing.assert_allclose(balls, want, atol=gp.ik_tol)
    # The ball turns with the box about the roll's axis, as stages.trajectory pushes: it does not roll
    # on the face (position-only IK keeps its orientation: 61 deg of rolling over the 60 deg roll).
    from scipy.spatial.transform import Rotation

    R_O = roll.poses(np.linspace(0.0, th_r, len(q)))[:, :3, :3]
    rel = np.einsum("tji,tjk->tik", R_O, robot.eef_rotation(arm, q))  # the ball's orientation in O
    rolled = Rotation.from_matrix(rel @ rel[0].T).as_rotvec() @ (R_O[0].T @ roll.a_axis[0])
    assert np.abs(np.degrees(rolled)).max() < 20.0
    # Best first: the moment less half the offset from the CoM along the axis. With no collisions (the
    # wrists meet the tilting box at the first few), the right arm's first is high and in line (2.4 cm),
    # not the one with the largest moment (0.349 against 0.347 N m/N, 8.7 cm off the line).
    def free(ql, qr, X_WO, touching):
        return np.ones(len(ql), bool), np.full(len(ql), "ok")

    arm, c, _ = graph.pusher_motion(robot, free, model, X, roll.X_end, e0, e1, pc, nc, r, gp, limits, ("right",))
    p_W = se3.transform_points(X, pc[c])
    assert arm == "right" and p_W[2] > 0.22 and abs((p_W - se3.transform_points(X, model.com)) @ roll.a_axis[0]) < 0.04
    weak = limits._replace(f_max=5.0)
    assert graph.pusher_motion(robot, collide, model, X, roll.X_end, e0, e1, pc, nc, r, gp, weak) == \
        (None, "no_pusher_contact", None)


def test_pivot_edges_are_the_same_whatever_the_batch_size(small_build, tmp_path):
    """Pivot edges are checked in fixed-size batches (memory); each edge's verdict is its own."""
    from dataclasses import replace

    from stages import artifacts, graph

    scene, b = small_build
    graph.run(scene, b / "analysis", b / "sample", tmp_path / "ref", replace(graph.Params(), pivot_arms=True))
    graph.run(scene, b / "analysis", b / "sample", tmp_path / "graph",
              replace(graph.Params(), pivot_arms=True, pivot_chunk=7))
    ref = artifacts.read_table(tmp_path / "ref" / "edges.parquet", "edges")
    got = artifacts.read_table(tmp_path / "graph" / "edges.parquet", "edges")
    assert (ref["primitive"] == "pivot").sum() > 7  # more than one batch
    assert (got["status"] == ref["status"]).all() and (got["node_a"] == ref["node_a"]).all()


def test_spread_takes_the_best_and_then_candidates_evenly_down_the_ranking():
    from stages.graph import spread

    ranked = np.arange(100, 120)
    assert spread(ranked, 5).tolist() == [100, 105, 110, 114, 119]
    assert spread(ranked[:3], 5).tolist() == [100, 101, 102]  # fewer than asked: all of them


def test_eef_normal_angle_change_is_the_turn_of_the_tool_against_the_normal():
    """§5.1's check: arms fixed in their zero posture (the tool axis straight up, W z) while the object
    turns 30 deg about W x: a contact whose inward normal starts along the tool axis ends 30 deg from it.
    A turn about W z, which keeps the angle to the vertical, changes nothing."""
    from stages.robot import load_robot
    from stages.scene import load_scene
    from tests.conftest import REPO

    scene = load_scene(REPO / "data" / "scenes" / "default.json")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    T, n = 7, robot.arm("left").dof
    q = np.zeros((T, 1, 2, n))
    n_O = np.array([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]])  # outward down: inward along the tool
    turn = np.linspace(0.0, np.radians(30.0), T)
    about_x = np.stack([se3.make_transform(Rotation.from_rotvec([a, 0.0, 0.0]).as_matrix(), np.zeros(3))
                        for a in turn])[None]
    about_z = np.stack([se3.make_transform(Rotation.from_rotvec([0.0, 0.0, a]).as_matrix(), np.zeros(3))
                        for a in turn])[None]
    assert graph.eef_normal_angle_change(robot, q, about_x, n_O)[0] == pytest.approx(np.radians(30.0), abs=1e-6)
    assert graph.eef_normal_angle_change(robot, q, about_z, n_O)[0] == pytest.approx(0.0, abs=1e-6)  # arccos at 1


def test_pivot_edges_whose_balls_turn_too_far_against_the_normal_are_refused(small_build, tmp_path):
    """With the arms checked in the graph (``pivot_arms``) and a 5 deg bound on the change of the
    ball-normal angle, pivot edges whose motion the default bound passes are refused with the reason
    code ``eef_normal_angle``; the others keep their verdict (but squeeze tumbles, which the same
    bound refuses)."""
    from dataclasses import replace

    from stages import artifacts

    scene, b = small_build
    graph.run(scene, b / "analysis", b / "sample", tmp_path / "ref", replace(graph.Params(), pivot_arms=True))
    ref = artifacts.read_table(tmp_path / "ref" / "edges.parquet", "edges")
    graph.run(scene, b / "analysis", b / "sample", tmp_path / "graph",
              replace(graph.Params(), pivot_arms=True, max_eef_normal_change=np.radians(5.0)))
    got = artifacts.read_table(tmp_path / "graph" / "edges.parquet", "edges")
    piv = ref["primitive"] == "pivot"
    turned = piv & (got["status"] == "eef_normal_angle")
    # Refused before the equilibrium check, which the default run may have failed them on after.
    assert turned.any() and np.isin(ref["status"][turned], ["ok", "unstable"]).all()
    assert (ref["status"][turned] == "ok").any()
    squeezed = (ref["arm"] == "both") & (ref["primitive"] == "tumble") & (got["status"] == "eef_normal_angle") \
        & (ref["status"] != "eef_normal_angle")
    assert (ref["status"][squeezed] == "ok").all()
    same = ~turned & ~squeezed
    assert (got["status"][same] == ref["status"][same]).all()


def test_the_graph_leaves_a_pivots_arm_motion_to_the_plan(small_build, tmp_path):
    """LazySP: by default a pivot edge's arms are not checked in the graph (``Params.pivot_arms``): the
    edges the arm checks refuse are kept (``ok``, or ``unstable`` by the equilibrium check they then
    reach), and every other verdict is the arm-checked graph's."""
    from dataclasses import replace

    from stages import artifacts

    scene, b = small_build
    lazy = artifacts.read_table(b / "graph" / "edges.parquet", "edges")
    graph.run(scene, b / "analysis", b / "sample", tmp_path / "graph", replace(graph.Params(), pivot_arms=True))
    full = artifacts.read_table(tmp_path / "graph" / "edges.parquet", "edges")
    piv = full["primitive"] == "pivot"
    armed = piv & ~np.isin(full["status"], ["ok", "unstable", "not_a_pivot"])
    assert armed.any() and (lazy["status"][armed] == "ok").any()
    assert np.isin(lazy["status"][armed], ["ok", "unstable"]).all()
    assert (lazy["status"][~armed] == full["status"][~armed]).all()


def test_the_plan_refuses_a_pivot_whose_balls_turn_too_far_against_the_normal(small_build, tmp_path, monkeypatch):
    """At a 5 deg bound on §5.1's ``eef_normal_angle`` the graph (not checking a pivot's arms) keeps
    the pivot edges it would refuse; the plan refuses them with the graph's own arm checks on each
    path it finds (``_graph_arm_checks``, logged ``graph_check``, not backtracks), for the reason the
    arm-checked graph gives; and, without those, its walk refuses them from the robot's actual joints."""
    from dataclasses import replace

    from stages import artifacts, plan, stagelog

    scene, b = small_build
    strict = replace(graph.Params(), max_eef_normal_change=np.radians(5.0))
    graph.run(scene, b / "analysis", b / "sample", tmp_path / "graph", strict)
    graph.run(scene, b / "analysis", b / "sample", tmp_path / "armed", replace(strict, pivot_arms=True))
    edges = artifacts.read_table(tmp_path / "graph" / "edges.parquet", "edges")
    armed = artifacts.read_table(tmp_path / "armed" / "edges.parquet", "edges")
    assert "eef_normal_angle" not in edges["status"][edges["primitive"] == "pivot"]
    prm = replace(plan.Params(), check_mpc=False, max_removals=20)
    out = plan.run(scene, b / "analysis", b / "sample", tmp_path / "graph", tmp_path / "plan.json", prm)
    deferred = [e for e in out["log"] if e.get("graph_check")]
    assert any(e["reason"] == "eef_normal_angle" for e in deferred)
    assert all(e["reason"] == armed["status"][e["edge_id"]] != "ok" for e in deferred)
    assert stagelog.backtracks(out) == len(out["log"]) - len(deferred)
    monkeypatch.setattr(plan, "_graph_arm_checks", lambda *args: [])
    out = plan.run(scene, b / "analysis", b / "sample", tmp_path / "graph", tmp_path / "plan.json", prm)
    assert any(e["reason"] == "eef_normal_angle" and not e.get("graph_check") for e in out["log"])


def _pivot_past_the_wrist():
    """The SDA5F of the default scene holding a 0.3 x 0.4 x 0.2 m box by the centres of its side faces
    while it pivots 10 deg about a bottom corner (9 samples), and the left wrist's capsule (``(3,)``
    first end and axis, O, at the middle sample) with its radius: ``(robot, X_traj, p_O, n_O, q0, wrist)``.
    The checkers have no table: holding the box 10 cm up, the right wrist comes within the links' table
    clearance, which is not what these tests are about."""
    import trimesh

    from stages.robot import _capsules_W, load_robot, make_collision_fn
    from stages.scene import load_scene
    from tests.conftest import REPO

    scene = load_scene(REPO / "data" / "scenes" / "default.json")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    r, size, v = scene.robot.ball_radius, np.array([0.3, 0.4, 0.2]), np.array([-0.15, -0.2, -0.1])
    X0 = se3.make_transform(np.eye(3), [0.0, 0.0, 0.1])
    turns = [Rotation.from_rotvec([0.0, 0.0, a]).as_matrix() for a in np.linspace(0.0, np.radians(10.0), 9)]
    X_traj = np.stack([X0 @ se3.make_transform(R, v - R @ v) for R in turns])[None]
    p_O, n_O = np.array([[[0.0, 0.2, 0.0], [0.0, -0.2, 0.0]]]), np.array([[[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]])
    q0 = np.stack([robot.ik(arm, se3.transform_points(X0, p_O[0, k] + r * n_O[0, k])[None],
                            rng=np.random.default_rng(0)).q[0] for k, arm in enumerate(("left", "right"))])[None]
    box = make_collision_fn(robot, None, object_mesh=trimesh.creation.box(size), link_clearance=0.007)
    ok, _, q = graph.check_arm_motion(robot, box, X_traj, p_O, n_O, q0, r, graph.Params())
    assert ok[0]  # the box alone keeps clear of the arms
    a = robot.arm("left")
    c = list(a.cap_names).index("left_link_6_b")
    A, B = _capsules_W(a, q[4, 0, 0][:, None])
    X_OW = se3.invert(X_traj[0, 4])
    ends = se3.transform_points(X_OW, np.stack([A[:, c, 0], B[:, c, 0]]))
    return robot, X_traj, p_O, n_O, q0, (ends[0], ends[1] - ends[0], a.cap_r[c]), size, r


@pytest.mark.parametrize("gap, reason", [(0.003, "object_clearance:left_link_6_b/object"), (0.015, "ok")])
def test_a_pivot_whose_wrist_passes_within_a_few_mm_of_the_object_is_refused(gap, reason):
    """The box of :func:`_pivot_past_the_wrist` with a 1 cm knob ``gap`` m under the left wrist at the
    pivot's middle sample: 3 mm is within the 7 mm arm clearance (``stages.sample.Params.arm_clearance``)
    and refused, although nothing touches (the check without the clearance passes it); 15 mm passes."""
    import trimesh

    from stages.robot import make_collision_fn

    robot, X_traj, p_O, n_O, q0, (A, u, rad), size, r = _pivot_past_the_wrist()
    u = u / np.linalg.norm(u)
    down = np.array([0.0, 0.0, -1.0]) + u[2] * u  # perpendicular to the axis: its first end is the nearest
    down /= np.linalg.norm(down)
    knob = trimesh.creation.icosphere(subdivisions=3, radius=0.005)
    knob.apply_translation(A + down * (rad + gap + 0.005))
    mesh = trimesh.util.concatenate([trimesh.creation.box(size), knob])
    checks = {cl: make_collision_fn(robot, None, object_mesh=mesh, link_clearance=cl)
              for cl in (0.0, 0.007)}
    ok, why, _ = graph.check_arm_motion(robot, checks[0.007], X_traj, p_O, n_O, q0, r, graph.Params())
    assert why.tolist() == [reason] and ok[0] == (reason == "ok")
    assert graph.check_arm_motion(robot, checks[0.0], X_traj, p_O, n_O, q0, r, graph.Params())[0][0]


def test_the_later_stages_check_with_the_samplers_clearances(small_build):
    """``grasps.parquet`` records the clearances its grasps were checked with; the graph and the plan
    build their checkers with them, and ``plan.json`` passes them on to the motion stage."""
    from stages import artifacts, sample

    _, b = small_build
    want = (sample.Params().arm_clearance, sample.Params().stick_clearance)
    assert want[0] > want[1] > 0
    grasps = artifacts.read_table(b / "sample" / "grasps.parquet", "grasps")
    assert sample.clearance_of(grasps.meta["params"]) == want
    assert sample.clearance_of(artifacts.read_json(b / "plan.json", "plan")["meta"]["params"]) == want


def test_tip_holds_needs_the_edge_friction_that_balances_the_push():
    """A 0.2 m cube of 1 kg tipped over its edge x = +0.1 by a frictionless ball pushing +x on the far
    face at 0.18 m: at the tip's start the push is m g 0.1 / 0.18 = 0.556 m g, all of it held by the
    edge's friction, so the table needs mu >= 0.556 (0.64 for the inscribed six-sided pyramid's worst
    direction); a ball pushing at 0.18 m within a 5 N bound cannot."""
    from stages import graph

    com, edge = np.array([[0.0, 0.0, 0.1]]), np.array([[[0.1, -0.1, 0.0], [0.1, 0.1, 0.0]]])
    p, n = np.array([[-0.1, 0.0, 0.18]]), np.array([[-1.0, 0.0, 0.0]])
    lim = graph.PushLimits(mu=0.0, f_max=50.0, weight=9.81, mu_table=0.5)
    assert not graph.tip_holds(com, edge, p, n, lim)[0]
    assert graph.tip_holds(com, edge, p, n, lim._replace(mu_table=0.7))[0]
    assert not graph.tip_holds(com, edge, p, n, lim._replace(mu_table=0.7, f_max=5.0))[0]


def test_pushers_checked_in_waves_are_the_first_that_work_in_order(monkeypatch):
    """``pusher_motions`` checks a tumble's candidates 1, 2, 4, ... at a time until one works: it picks
    the first that works in order (left before right, best rank first), whatever order the rows come
    in, checks fewer rows than all, and a tumble with none checks all and reports the most common
    failure."""
    # (tumble, arm (0 left), contact, rank) -> the check's outcome, rows shuffled.
    outcome = {(0, 0, 10, 0): "ik_unreachable", (0, 0, 11, 1): "env_collision:left_link_6_b/object",
               (0, 0, 12, 2): "ok", (0, 0, 13, 3): "ok", (0, 1, 20, 0): "ok", (0, 1, 21, 1): "ok",
               (1, 1, 30, 0): "joint_limit", (1, 1, 31, 1): "joint_limit", (1, 1, 32, 2): "ok",
               (2, 0, 40, 0): "env_collision:left_stick/object", (2, 0, 41, 1): "ik_unreachable",
               (2, 1, 50, 0): "ik_unreachable"}
    rows = np.array(list(outcome))[np.random.default_rng(1).permutation(len(outcome))]
    K = 3
    monkeypatch.setattr(graph, "_push_candidates", lambda *a, **k: graph._PushRows(
        rows, np.zeros((K, 1, 4, 4)), np.full(K, "no_pusher_contact", dtype=object)))
    checked = []

    def check(robot, collide, cand, sel, pc, nc, r, params, status, q_path):
        for i in sel.tolist():
            checked.append(i)
            status[i] = outcome[tuple(cand.rows[i].tolist())]
            q_path[i] = np.full((2, 1), float(cand.rows[i, 2])) if status[i] == "ok" else None

    monkeypatch.setattr(graph, "_check_pushers", check)
    out = graph.pusher_motions(None, None, None, np.zeros((K, 4, 4)), np.zeros((K, 4, 4)), np.zeros((K, 2), int),
                               None, None, 0.02, graph.Params(), None)
    assert [(arm, c) for arm, c, _ in out] == [("left", 12), ("right", 32), (None, "ik_unreachable")]
    assert out[0][2][0, 0] == 12.0 and out[2][2] is None
    assert len(checked) == len(set(checked)) < len(rows)  # no row twice, and not all of them
