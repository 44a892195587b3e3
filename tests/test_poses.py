"""Pose sampling (§5.1): pivot steps and tumbles on a box, SP/USP near the table edge, obstacles."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from stages import analyze, connect, poses, se3
from stages.scene import ObstacleGeometry

BOX = (0.2, 0.3, 0.4)


def box_model(size=BOX, mesh=None) -> poses.ObjectModel:
    mesh = trimesh.creation.box(size) if mesh is None else mesh
    r = analyze.compute(mesh, 2.0, analyze.Params())
    is_v = r.hull["kind"] == "vertex"
    return poses.ObjectModel(
        vertices=np.stack([r.hull["x0"][is_v], r.hull["y0"][is_v], r.hull["z0"][is_v]], 1),
        edges=np.stack([r.hull["v0"][~is_v], r.hull["v1"][~is_v]], 1),
        edge_faces=np.stack([r.hull["face_a"][~is_v], r.hull["face_b"][~is_v]], 1),
        edge_angle=r.hull["angle"][~is_v],
        normals=np.stack([r.placements["nx"], r.placements["ny"], r.placements["nz"]], 1),
        X_TO=se3.matrix_from_columns(r.placements),
        support=list(r.placements["support_vertices"]),
        stable=r.placements["stable"],
        com=r.summary["com"],
        mesh_vertices=np.asarray(mesh.vertices),
        mesh_faces=np.asarray(mesh.faces),
    )


def upright(model, xy=(0.0, 0.0), yaw=0.0):
    g = int(np.argmax(model.normals @ np.array([0, 0, -1.0])))
    return se3.make_transform(se3.rot_z(yaw), np.array([*xy, 0.0])) @ model.X_TO[g], g


def test_pivot_steps_rotate_exactly_about_the_vertical_through_the_vertex():
    model = box_model()
    X0, g = upright(model)
    ps = poses.sample_poses(model, X0, g, (2.0, 2.0), (), poses.Params(max_poses=60))
    piv = np.flatnonzero((ps.primitive == "pivot") & (ps.status == "ok"))
    assert len(piv) > 20
    for i in piv:
        parent, v = ps.parent[i], ps.vertex[i]
        p_parent = se3.transform_points(ps.X_WO[parent], model.vertices[v])
        p_child = se3.transform_points(ps.X_WO[i], model.vertices[v])
        np.testing.assert_allclose(p_child, p_parent, atol=1e-12)  # the vertex does not move
        R = ps.X_WO[i][:3, :3] @ ps.X_WO[parent][:3, :3].T
        np.testing.assert_allclose(R, se3.rot_z(ps.angle[i]), atol=1e-12)
        assert abs(ps.angle[i]) == pytest.approx(np.radians(15))
        assert p_child[2] == pytest.approx(0.0, abs=1e-12)


def test_tumbling_a_box_lands_on_the_adjacent_face():
    model = box_model()
    X0, g = upright(model)
    ps = poses.sample_poses(model, X0, g, (2.0, 2.0), (), poses.Params(max_poses=40))
    tum = np.flatnonzero((ps.primitive == "tumble") & (ps.status == "ok") & (ps.parent == 0))
    assert len(tum) == 4  # over each of the four bottom edges
    for i in tum:
        assert ps.angle[i] == pytest.approx(np.pi / 2)
        n_parent = model.normals[ps.placement[0]]
        assert abs(np.dot(model.normals[ps.placement[i]], n_parent)) < 1e-9  # adjacent, not opposite
        v = se3.transform_points(ps.X_WO[i], model.mesh_vertices)
        assert v[:, 2].min() == pytest.approx(0.0, abs=1e-9)
        # Lying on a side face its height is the box's 0.2 or 0.3 m size.
        assert v[:, 2].max() == pytest.approx(0.2, abs=1e-9) or v[:, 2].max() == pytest.approx(0.3, abs=1e-9)


@pytest.mark.parametrize("off_deg, lands", [(0.3, True), (2.0, False)])
def test_a_roll_onto_a_face_a_little_off_its_edge_settles_flat_on_it(off_deg, lands):
    # Merged hull faces meet at edges that are not exactly their planes' intersection: the side face's
    # normal turned by off_deg about the vertical. Within ROLL_ALIGN (1 deg) the roll lands and settles
    # on that face as the analysis rests it (a turn and shift of its X_TO, so that every pose of the
    # placement is a planar motion of every other); beyond, it does not land.
    from dataclasses import replace
    model = box_model()
    X0, g = upright(model)
    e = int(np.flatnonzero((model.edge_faces == g).any(axis=1))[0])
    g2 = int(model.edge_faces[e, 1] if model.edge_faces[e, 0] == g else model.edge_faces[e, 0])
    normals = model.normals.copy()
    normals[g2] = se3.rot_z(np.radians(off_deg)) @ normals[g2]
    off = replace(model, normals=normals)
    a, b = (int(x) for x in off.edges[e])
    if not lands:
        with pytest.raises(poses.InputError):
            poses.roll_segments(off, X0, a, b)
        return
    roll = poses.roll_segments(off, X0, a, b)
    assert roll.face == g2
    assert connect.planar_motion(off.X_TO[g2], roll.X_end) is not None
    sup = se3.transform_points(roll.X_end, off.vertices[np.asarray(off.support[g2])])
    assert sup[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    # The settling turn is the small misalignment, not another roll.
    R = roll.X_end[:3, :3] @ roll.poses([roll.total])[0][:3, :3].T
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) <= off_deg + 1e-6


def chamfered_box(size=(0.3, 0.2, 0.2), c=0.02):
    """A box whose four edges along y are cut by 45 deg chamfers ``c`` wide (m): a prism of octagonal
    section, every chamfer face too narrow to stand on."""
    hx, hz = size[0] / 2, size[2] / 2
    sec = [(hx - c, -hz), (hx, -hz + c), (hx, hz - c), (hx - c, hz), (-hx + c, hz), (-hx, hz - c),
           (-hx, -hz + c), (-hx + c, -hz)]
    pts = [(x, y, z) for x, z in sec for y in (-size[1] / 2, size[1] / 2)]
    return trimesh.convex.convex_hull(np.array(pts))


def test_a_roll_over_a_face_the_com_falls_back_from_is_pushed_on_over_its_far_edge():
    # The chamfered box rolled over a bottom edge along y turns 45 deg onto the chamfer, where its CoM
    # lies back over that edge (0.13 m in, 0.10 m up: -0.13 cos 45 + 0.10 sin 45 < 0); a pusher keeps
    # turning it over the chamfer's far edge, 45 deg more, onto the side face: 90 deg in two segments.
    model = box_model((0.3, 0.2, 0.2), chamfered_box())
    X0, g = upright(model)
    assert np.sum(~model.stable) == 4  # the four chamfers tip; the six faces of the box stand
    bottom_y = [e for e in np.flatnonzero((model.edge_faces == g).any(axis=1))
                if abs(np.diff(model.vertices[model.edges[e]][:, 1])[0]) > 0.1]
    assert len(bottom_y) == 2
    for e in bottom_y:
        roll = poses.roll_segments(model, X0, *model.edges[e])
        np.testing.assert_allclose(np.degrees(roll.angle), [45.0, 45.0], atol=1e-9)
        side = se3.rotate_vectors(roll.X_end, model.normals[roll.face])
        np.testing.assert_allclose(side, [0.0, 0.0, -1.0], atol=1e-12)
        x_side = np.sign(se3.transform_points(X0, model.vertices[model.edges[e]])[0, 0])
        assert abs(model.normals[roll.face] @ [x_side, 0.0, 0.0]) == pytest.approx(1.0)  # that x side
        # The second segment turns about the chamfer's far edge, which is on the table as it starts.
        far = se3.transform_points(roll.X_seg[1], model.vertices[roll.edge[1]])
        assert np.abs(far[:, 2]).max() < 1e-12
        assert poses._tumble(model, X0, g, e)[1] == roll.face


def test_a_roll_that_comes_back_onto_its_own_face_is_no_tumble(monkeypatch):
    # A roll that rocks onto a narrow face and falls back over another edge lands where it began.
    model = box_model()
    X0, g = upright(model)
    e = int(np.flatnonzero((model.edge_faces == g).any(axis=1))[0])
    assert poses._tumble(model, X0, g, e) is not None
    roll = poses.roll_segments(model, X0, *model.edges[e])
    monkeypatch.setattr(poses, "roll_segments", lambda *a, **k: poses.Roll(
        roll.X_seg, roll.p_axis, roll.a_axis, roll.angle, roll.edge, g, roll.X_end))
    assert poses._tumble(model, X0, g, e) is None


def test_overhang_at_the_table_edge_is_sp_until_the_com_passes_the_edge_then_usp():
    model = box_model()  # footprint 0.2 (x) x 0.3 (y)
    # Footprint x in [0.15, 0.35] on a table ending at x = 0.3: the table edge cuts the support, but the
    # CoM (x = 0.25) is 5 cm inside the part on the table: SP.
    X, g = upright(model, xy=(0.25, 0.0))
    ps = poses.sample_poses(model, X, g, (0.6, 0.6), (), poses.Params(max_poses=1))
    assert ps.status[0] == "ok" and ps.support[0] == "SP" and ps.margin[0] == pytest.approx(0.05, abs=1e-9)
    # CoM 3 cm beyond the edge (x = 0.33), 7 cm of footprint still on the table: USP.
    X, g = upright(model, xy=(0.33, 0.0))
    ps = poses.sample_poses(model, X, g, (0.6, 0.6), (), poses.Params(max_poses=1))
    assert ps.status[0] == "ok" and ps.support[0] == "USP" and ps.margin[0] == pytest.approx(-0.03, abs=1e-9)
    ps = poses.sample_poses(model, X, g, (0.6, 0.6), (), poses.Params(max_poses=1, usp=False))
    assert ps.status[0] == "unstable"
    # Resting on the table's edge line with the CoM 8 cm beyond it: still USP; 20 cm beyond: nothing
    # of the footprint is on the table any more.
    X, g = upright(model, xy=(0.38, 0.0))
    assert poses.sample_poses(model, X, g, (0.6, 0.6), (), poses.Params(max_poses=1)).support[0] == "USP"
    X, g = upright(model, xy=(0.5, 0.0))
    assert poses.sample_poses(model, X, g, (0.6, 0.6), (), poses.Params(max_poses=1)).status[0] == "off_table"


def test_a_com_between_the_sp_and_usp_margins_is_neither():
    """Issue 15's knife edge: with its CoM 1 cm past the table's edge the box is not SP (5 mm inside) and
    not USP (2 cm beyond): refused as unstable, with both margins in the reason; 0.3 mm past it too
    (Exp. 3's old USP pose); 2 cm past it, USP; with no USP margin the 1 cm pose is USP again."""
    model = box_model()
    for x in (0.31, 0.3003):
        X, g = upright(model, xy=(x, 0.0))
        status, why = poses.describe_pose(model, X, g, (0.6, 0.6), (), poses.Params())
        assert status == "unstable" and "between SP (0.005 m inside) and USP (0.02 m beyond)" in why, why
    X, g = upright(model, xy=(0.32, 0.0))
    assert poses.sample_poses(model, X, g, (0.6, 0.6), (), poses.Params(max_poses=1)).support[0] == "USP"
    X, g = upright(model, xy=(0.31, 0.0))
    ps = poses.sample_poses(model, X, g, (0.6, 0.6), (), poses.Params(max_poses=1, usp_margin=0.0))
    assert ps.status[0] == "ok" and ps.support[0] == "USP"


def test_table_support_is_the_footprint_clipped_to_the_table():
    model = box_model()
    X, g = upright(model, xy=(0.33, 0.1))
    poly = poses.table_support(model, X, g, np.array([0.3, 0.3]))
    np.testing.assert_allclose(np.sort(poly[:, 0]), [0.23, 0.23, 0.3, 0.3], atol=1e-12)
    np.testing.assert_allclose(np.sort(poly[:, 1]), [-0.05, -0.05, 0.25, 0.25], atol=1e-12)


def test_table_support_is_where_the_soles_touch_not_the_face_between_them():
    """A bench on two feet with one foot past the table's edge stands on the other foot alone: the
    support face's polygon clipped to the table would reach from that foot to the edge, over the gap."""
    feet = [trimesh.creation.box((0.05, 0.3, 0.1), se3.make_transform(np.eye(3), [x, 0.0, 0.05])) for x in (-0.2, 0.2)]
    top = trimesh.creation.box((0.5, 0.3, 0.1), se3.make_transform(np.eye(3), [0.0, 0.0, 0.15]))
    model = box_model(mesh=trimesh.util.concatenate([*feet, top]))
    X, g = upright(model, xy=(0.13, 0.0))  # feet at x -0.095..-0.045 (on) and 0.305..0.355 (off)
    poly = poses.table_support(model, X, g, np.array([0.3, 0.3]))
    np.testing.assert_allclose([poly[:, 0].min(), poly[:, 0].max()], [-0.095, -0.045], atol=1e-9)
    np.testing.assert_allclose([poly[:, 1].min(), poly[:, 1].max()], [-0.15, 0.15], atol=1e-9)
    X, g = upright(model, xy=(0.0, 0.0))  # both feet on: from the outer edge of one to the other's
    poly = poses.table_support(model, X, g, np.array([0.3, 0.3]))
    np.testing.assert_allclose([poly[:, 0].min(), poly[:, 0].max()], [-0.225, 0.225], atol=1e-9)


def test_poses_hitting_an_obstacle_are_rejected_and_never_expanded():
    model = box_model()
    X0, g = upright(model)
    wall = ObstacleGeometry(name="obstacles[0]", kind="box", X_WOb=se3.make_transform(np.eye(3), [0.25, 0, 0.2]),
                            size=(0.1, 2.0, 0.4))  # across the whole table: no way round
    ps = poses.sample_poses(model, X0, g, (2.0, 2.0), (wall,), poses.Params(max_poses=80))
    assert (ps.status == "obstacle").any()
    assert not np.isin(np.flatnonzero(ps.status == "obstacle"), ps.parent).any()
    ok = ps.status == "ok"
    v = np.einsum("nij,kj->nki", ps.X_WO[ok][:, :3, :3], model.mesh_vertices) + ps.X_WO[ok][:, None, :3, 3]
    assert (v[..., 0].max(axis=1) <= 0.2 + 1e-9).all()  # nothing kept reaches into the wall at x >= 0.2


def test_links_join_kept_poses_and_duplicates_merge():
    model = box_model()
    X0, g = upright(model)
    ps = poses.sample_poses(model, X0, g, (2.0, 2.0), (), poses.Params(max_poses=150))
    assert (ps.status[ps.links] == "ok").all()
    # Pivoting +15 then -15 about the same vertex returns to the parent: merged, so a link, no new pose.
    keys = np.round(np.c_[ps.X_WO[:, :3, 3], ps.placement], 4)
    ok = ps.status == "ok"
    assert len(np.unique(keys[ok], axis=0)) == ok.sum()
    assert len(ps.links) > ok.sum() - 1


def test_the_goals_placement_is_expanded_past_its_tumble_landings():
    """Each placement has its own queue: with a small cap, the goal's face (reached by one tumble)
    still gets pivots of its own, and the goal is joined to them."""
    model = box_model()
    X0, g = upright(model)
    side = int(np.argmax(model.normals @ np.array([1.0, 0, 0])))  # lying on the +x face
    Xg = se3.make_transform(se3.rot_z(0.3), np.array([0.35, 0.05, 0.0])) @ model.X_TO[side]
    ps = poses.sample_poses(model, X0, g, (2.0, 2.0), (), poses.Params(max_poses=80), goal=(Xg, side))
    ok = ps.status == "ok"
    on_side = ok & (ps.placement == side)
    n_side, n_start = np.count_nonzero(on_side & (ps.primitive == "pivot")), np.count_nonzero(ok & (ps.placement == g))
    assert n_side >= 10 and n_start >= 10
    assert n_side >= n_start / 2  # breadth first over all poses, the goal's face got only its landings
    assert ps.goal_id >= 0 and np.any(ps.links[:, 1] == ps.goal_id)


@pytest.mark.parametrize("gap, clearance, hits", [(0.02, 0.0, True), (0.04, 0.0, False), (0.04, 0.01, True)])
def test_a_pivot_is_swept_tilted_onto_its_vertex_and_keeps_the_clearance(gap, clearance, hits):
    """A wall beside the box's -x face, its bottom 20 cm up: turning the box flat by -15 deg about its
    (-x, -y) bottom corner clears it, but tilted 8 deg onto that corner the box's top leans 5.6 cm
    outward (0.4 m x sin 8 deg), into a wall 2 cm off; 4 cm off it clears, unless the motion keeps
    a 1 cm clearance. The lattice refuses the pivot's pose when the sweep hits."""
    from stages.scene import ObstacleGeometry

    model = box_model()
    X0, g = upright(model)
    V = se3.transform_points(X0, model.vertices)
    v = int(np.flatnonzero((V[:, 2] < 1e-9) & (V[:, 0] < 0) & (V[:, 1] < 0))[0])
    wall = ObstacleGeometry("wall", "box", se3.make_transform(np.eye(3), [V[v, 0] - gap - 0.005, 0.0, 0.3]),
                            size=(0.01, 0.3, 0.2))
    X1 = se3.transform_about_line(V[v], np.array([0.0, 0.0, 1.0]), np.radians(-15)) @ X0
    col = poses._make_object_collision_fn(model, [wall], clearance)
    assert not col(X0) and not col(X1)
    assert not poses._swept_hits(model, col, X0, X1, "pivot", v, (-1, -1), 0.0)
    assert poses._swept_hits(model, col, X0, X1, "pivot", v, (-1, -1), np.radians(8)) == hits
    ps = poses.sample_poses(model, X0, g, (2.0, 2.0), [wall], poses.Params(max_poses=5, sweep_clearance=clearance))
    child = np.flatnonzero((ps.parent == 0) & (ps.vertex == v) & np.isclose(ps.angle, np.radians(-15)))
    assert len(child) == 1 and ps.status[child[0]] == ("obstacle" if hits else "ok")


def test_the_robots_trunk_is_an_obstacle_for_the_object():
    from stages.robot import load_robot
    from stages.sample import trunk_obstacles
    from stages.scene import load_scene

    scene = load_scene(Path(__file__).resolve().parents[1] / "data" / "scenes" / "default.json")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    model = box_model()
    torso = next(ob for ob in trunk_obstacles(robot) if ob.name == "robot:torso_link")
    front = torso.X_WOb[0, 3] + torso.size[0] / 2
    X_in, g = upright(model, xy=(front, 0.0))  # half the box inside the torso's front face
    X_out, _ = upright(model, xy=(front + BOX[0] / 2 + 0.01, 0.0))
    for X, want in ((X_in, "obstacle"), (X_out, "ok")):
        ps = poses.sample_poses(model, X, g, (4.0, 4.0), trunk_obstacles(robot), poses.Params(max_poses=1))
        assert ps.status[0] == want


def test_held_com_moves_the_com_out_across_the_nearest_edge_of_the_table_contact():
    from stages.poses import held_com

    square = np.array([[0.0, 0.0], [0.2, 0.0], [0.2, 0.2], [0.0, 0.2]])
    # 3 mm inside the top edge: 5 mm out puts it 2 mm past; past the right edge: 5 mm further out.
    np.testing.assert_allclose(held_com(square, np.array([0.1, 0.197, 0.3]), 0.005), [0.1, 0.202, 0.3])
    np.testing.assert_allclose(held_com(square, np.array([[0.25, 0.1, 0.0]]), 0.005), [[0.255, 0.1, 0.0]])
    # Past a corner: along the diagonal away from it.
    out = held_com(square, np.array([0.23, 0.24, 0.0]), 0.005)
    np.testing.assert_allclose(out[:2] - [0.23, 0.24], 0.005 * np.array([0.03, 0.04]) / 0.05, atol=1e-12)


def _pose_graph_connects(ps) -> bool:
    import networkx as nx

    G = nx.Graph()
    G.add_nodes_from(range(len(ps.status)))
    G.add_edges_from(map(tuple, ps.links))
    return ps.goal_id >= 0 and nx.has_path(G, 0, ps.goal_id)


def test_a_goal_the_start_lattice_cannot_join_is_reached_by_a_lattice_grown_from_it():
    """A goal 0.45 m away turned 100°: the start's 30 poses lie too far for its three-pivot joins; grown
    from the goal as well, the two lattices meet and the goal is linked to the start."""
    model = box_model()
    X0, g = upright(model)
    Xg, _ = upright(model, xy=(0.45, 0.1), yaw=np.radians(100))
    prm = poses.Params(max_poses=30, goal_tree_share=0, goal_reach_share=0, walk_strides=0)
    alone = poses.sample_poses(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g))
    assert not _pose_graph_connects(alone)
    prm = poses.Params(max_poses=30, goal_tree_share=2, goal_reach_share=0, walk_strides=0)
    both = poses.sample_poses(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g))
    assert _pose_graph_connects(both)
    assert np.array_equal(both.X_WO[: len(alone.X_WO)], alone.X_WO)  # the start's lattice is unchanged
    for a, b in both.links:  # every join is an exact pivot about a vertex that stays on the table
        assert both.status[a] == "ok" and both.status[b] == "ok"


def test_a_goal_beyond_every_closed_form_join_is_reached_by_a_pivot_walk():
    """The same goal with the start's 30 poses alone: no three-pivot join reaches it; the last resort's
    pivot walks (:func:`poses.walk_lattice`) do, by exact pivots about corners on the table, each
    within the lattice's step, and without them (``walk_strides=0``) nothing is joined."""
    model = box_model()
    X0, g = upright(model)
    Xg, _ = upright(model, xy=(0.45, 0.1), yaw=np.radians(100))
    for strides, joins in ((0, False), (12, True)):
        prm = poses.Params(max_poses=30, goal_tree_share=0, goal_reach_share=0, walk_strides=strides)
        lat = poses.build_lattice(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g))
        assert not _pose_graph_connects(lat.pose_set())
        n0 = len(lat.rows)
        start_side = [i for i in range(n0) if i != lat.goal_id]
        assert (poses.walk_lattice(lat, start_side, [lat.goal_id]) > 0) == joins
        walked = lat.pose_set()
        assert _pose_graph_connects(walked) == joins
    pivots = walked.links[walked.link_primitive == "pivot"]
    for a, b in pivots[np.any(pivots >= n0, axis=1)]:
        assert walked.status[a] == "ok" and walked.status[b] == "ok"
        rel = connect.planar_motion(walked.X_WO[a], walked.X_WO[b])
        assert rel is not None and abs(rel[2]) <= max(prm.theta_t, prm.goal_max_angle) + 1e-9


def test_a_goal_on_an_uneven_base_face_joins_the_lattice():
    """The goal's pivots start from lattice poses whose support corners lie ~1e-4 m off the table (the
    face's own unevenness, :func:`tests.conftest.uneven_box`): that is no reason to refuse the scene."""
    from tests.conftest import uneven_box

    model = box_model(mesh=uneven_box())
    X0, g = upright(model, xy=(-0.15, 0.0))
    corners = se3.transform_points(X0, model.vertices[poses.pivot_corners(model, 0.03)[g]])
    assert 5e-5 < np.abs(corners[:, 2]).max() < 1e-3
    Xg, _ = upright(model, xy=(0.05, 0.03), yaw=np.radians(10.0))  # off the lattice: pivots must join it
    ps = poses.sample_poses(model, X0, g, (0.9, 0.6), (), poses.Params(max_poses=20), goal=(Xg, g))
    assert ps.goal_id >= 0 and ps.status[ps.goal_id] == "ok" and np.any(ps.links[:, 1] == ps.goal_id)


def test_the_table_contact_of_an_uneven_base_face_is_the_whole_face():
    # The lifted corner's triangles lie 0.3 mm off the support plane, beyond table_support's 0.1 mm: the
    # face's corners still touch the table, so the contact is the whole 0.3 x 0.2 m face, as the analysis
    # has it (without the corners it was 7/8 of it, and the CoM margin shrank with it).
    from scipy.spatial import ConvexHull

    from tests.conftest import uneven_box

    model = box_model(mesh=uneven_box())
    X, g = upright(model)
    poly = poses.table_support(model, X, g, np.array([0.45, 0.3]))
    assert ConvexHull(poly).volume == pytest.approx(0.3 * 0.2, rel=1e-4)  # 0.3 mm lift over 0.3 m: < 1e-4


def test_a_stable_face_smaller_than_min_usp_edge_is_sp_not_off_table():
    """min_usp_edge asks how much table a USP pose rests on; an object standing alone on a small face
    (4.2 cm across, the duck has such faces) is SP, not off the table."""
    model = box_model(size=(0.03, 0.03, 0.02))
    X, g = upright(model)
    ps = poses.sample_poses(model, X, g, (0.9, 0.6), (), poses.Params(max_poses=1))
    assert ps.status[0] == "ok" and ps.support[0] == "SP"


def test_describe_pose_names_the_obstacle_a_pose_hits_and_why_it_is_off_the_table():
    model = box_model()  # footprint 0.2 (x) x 0.3 (y), 0.4 high
    far = ObstacleGeometry(name="obstacles[0]", kind="box", X_WOb=se3.make_transform(np.eye(3), [0.0, 0.5, 0.1]),
                           size=(0.1, 0.1, 0.2))
    torso = ObstacleGeometry(name="robot:torso_link", kind="box", X_WOb=se3.make_transform(np.eye(3), [-0.2, 0, 0.2]),
                             size=(0.1, 0.4, 0.4))  # reaches x = -0.15
    X, g = upright(model, xy=(-0.02, 0.0))  # the box's back face at x = -0.12: clear of both
    assert poses.describe_pose(model, X, g, (0.9, 0.6), (far, torso), poses.Params()) == ("ok", "")
    X, g = upright(model, xy=(-0.1, 0.0))  # back face at x = -0.2: 5 cm into the torso only
    assert poses.describe_pose(model, X, g, (0.9, 0.6), (far, torso), poses.Params()) == (
        "obstacle", "it hits robot:torso_link")
    # CoM 3 cm past the table's edge at x = 0.3, USP not allowed; then 20 cm past it, nothing on the table.
    X, g = upright(model, xy=(0.33, 0.0))
    status, why = poses.describe_pose(model, X, g, (0.6, 0.6), (), poses.Params(usp=False))
    assert status == "unstable" and "0.030 m beyond its contact" in why and "USP" in why
    X, g = upright(model, xy=(0.5, 0.0))
    assert poses.describe_pose(model, X, g, (0.6, 0.6), (), poses.Params()) == (
        "off_table", "its support face is not on the table")


def test_nearness_is_the_least_distance_plus_weighted_heading_on_the_same_placement():
    p = poses.Params(yaw_weight=0.2)
    others = np.array([[0, 0.0, 0.0, 0.0], [1, 0.5, 0.0, 0.0], [1, 0.3, 0.4, np.pi / 2]])  # root first
    assert poses._nearness((1, 0.5, 0.1, 0.0), others, p) == pytest.approx(0.1)
    assert poses._nearness((1, 0.3, 0.4, 0.0), others, p) == pytest.approx(min(np.hypot(0.2, 0.4), 0.2 * np.pi / 2))
    assert poses._nearness((2, 0.3, 0.4, 1.0), others, p) == pytest.approx(0.5)  # no pose there: to the root


def test_the_goals_lattice_grown_toward_the_start_meets_it_where_breadth_first_does_not(monkeypatch):
    """A goal 0.55 m away turned 60°, 30 poses from the start and 60 from the goal: grown nearest first
    toward the start's lattice, the goal's lattice meets it; grown breadth first (every pose as near), not."""
    model = box_model()
    X0, g = upright(model)
    Xg, _ = upright(model, xy=(0.55, 0.0), yaw=np.radians(60))
    prm = poses.Params(max_poses=30, goal_tree_share=2, goal_reach_share=0, walk_strides=0)
    assert _pose_graph_connects(poses.sample_poses(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g)))
    monkeypatch.setattr(poses, "_nearness", lambda key, others, params: 0.0)
    assert not _pose_graph_connects(poses.sample_poses(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g)))


def test_the_starts_lattice_grown_on_toward_the_goal_by_weighted_a_star_reaches_it_where_breadth_first_does_not():
    """A goal 0.5 m away on the start's face and none of the goal's own lattice. 300 poses breadth first
    hold none within 0.25 m of it on that face, and the goal's three-pivot joins cannot reach them; 200
    breadth first and 100 more by weighted A* toward the goal reach out to it and the goal is joined,
    the breadth-first part and its joins unchanged."""
    model = box_model()
    X0, g = upright(model)
    Xg, _ = upright(model, xy=(0.5, 0.1))

    def sample(max_poses, share):
        prm = poses.Params(max_poses=max_poses, goal_tree_share=0, goal_reach_share=share, walk_strides=0)
        return poses.sample_poses(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g))

    def nearest(ps):  # the kept pose on the goal's face nearest the goal, CoM in plan view (m)
        ok = np.flatnonzero((ps.status == "ok") & (ps.placement == g) & (np.arange(len(ps.status)) != ps.goal_id))
        com = se3.transform_points(ps.X_WO[ok], model.com)[:, :2]
        return np.min(np.linalg.norm(com - se3.transform_points(Xg, model.com)[:2], axis=1))

    bfs, bfs200, astar = sample(300, 0.0), sample(200, 0.0), sample(200, 0.5)
    assert not _pose_graph_connects(bfs) and nearest(bfs) > 0.25
    assert _pose_graph_connects(astar) and nearest(astar) < 0.1
    assert np.array_equal(astar.X_WO[: len(bfs200.X_WO)], bfs200.X_WO)  # and its goal joins, first


def _prism_model(base_xy, height=0.2):
    """A uniform prism over the convex polygon ``base_xy (k, 2)`` (m), base on z = 0."""
    base = np.asarray(base_xy, float)
    pts = np.vstack([np.c_[base, np.zeros(len(base))], np.c_[base, np.full(len(base), height)]])
    return box_model(mesh=trimesh.convex.convex_hull(pts))


def _vertex_at(model, p_O):
    """The hull vertex id nearest to ``p_O`` (m, O: the mesh's own frame)."""
    return int(np.argmin(np.linalg.norm(model.vertices - np.asarray(p_O, float), axis=1)))


def test_the_tilt_direction_is_the_coms_where_every_other_vertex_rises():
    model = box_model()
    X, g = upright(model)
    for v in poses.pivot_corners(model, 0.03, np.radians(8))[g]:
        assert poses.tilt_direction(model, X, int(v), np.radians(8)) is None


def test_pivot_corners_are_found_per_placement_on_first_use():
    """``pivot_corners`` finds a placement's corners when first asked (a rounded mesh has hundreds of
    placements, a lattice visits a few); :meth:`PivotCorners.holding` cuts one placement's and leaves
    the others, and the corners it was made from, as they were."""
    model = box_model()
    X, g = upright(model)
    corners = poses.pivot_corners(model, 0.03, np.radians(8))
    assert len(corners) == len(model.support) == 6 and not corners._found
    assert len(corners[g]) == 4 and list(corners._found) == [g]
    other = (g + 1) % 6
    held = corners.holding(g, corners[g][:1])
    assert held[g].tolist() == corners[g][:1].tolist() and len(corners[g]) == 4
    assert held[other].tolist() == corners[other].tolist() and other in corners._found  # found once, shared
    table = corners.table([g, g])
    assert table.shape == (6, 4) and table[g].tolist() == corners[g].tolist()
    assert (np.delete(table, g, axis=0) == -1).all()  # only the placements asked for


def test_a_wide_corner_tilts_off_the_coms_direction_so_that_no_neighbour_sinks():
    # Base corner v = (0, 0) with neighbours (0.5, 0.03) and (-0.3, 0.03); the CoM lies at x ~ 0.1, so
    # tilting straight towards it would sink (-0.3, 0.03) by ~15 mm into the table.
    model = _prism_model([(0, 0), (0.5, 0.03), (0.5, 0.4), (-0.3, 0.4), (-0.3, 0.03)])
    g = int(np.argmax(model.normals @ np.array([0, 0, -1.0])))
    X, v, q = model.X_TO[g], _vertex_at(model, (0, 0, 0)), _vertex_at(model, (-0.3, 0.03, 0))
    assert np.allclose(model.vertices[[v, q]], [(0, 0, 0), (-0.3, 0.03, 0)])
    tilt = np.radians(8)
    d = poses.tilt_direction(model, X, v, tilt)
    assert d is not None and abs(d[2]) < 1e-12 and np.isclose(np.linalg.norm(d), 1.0)
    V = se3.transform_points(X, model.vertices)
    T = se3.transform_about_line(V[v], np.cross(d, [0, 0, 1.0]), tilt)
    z = se3.transform_points(T, V)[:, 2] - V[v, 2]
    assert z.min() >= -poses.TILT_TOLERANCE - 1e-9
    far = np.linalg.norm((V - V[v])[:, :2], axis=1) >= poses.TILT_CORNER_RADIUS
    assert z[far].min() >= poses.TILT_CLEARANCE - 1e-9
    # The nearest direction to the CoM's that keeps the neighbours the clearance above the table: the
    # limit is q, (q - v) . d sin(tilt) = clearance; the answer lies within the 0.5 deg search step.
    dc = (se3.transform_points(X, model.com) - V[v])[:2]
    dc /= np.linalg.norm(dc)
    qv = (V[q] - V[v])[:2]
    psi_q, psi_c = np.arctan2(qv[1], qv[0]), np.arctan2(dc[1], dc[0])
    half = np.arccos(poses.TILT_CLEARANCE / np.sin(tilt) / np.linalg.norm(qv))
    best = min(abs((psi_q + s * half - psi_c + np.pi) % (2 * np.pi) - np.pi) for s in (-1, 1))
    got = np.arccos(np.clip(d[:2] @ dc, -1, 1))
    assert best - 1e-9 <= got <= best + np.radians(0.5) + 1e-9


def test_a_nearly_straight_rim_tilts_where_its_neighbours_stay_highest():
    # Base corner v = (0, 0) on a nearly straight rim, neighbours (+-0.3, 0.005): tilting 8 deg
    # straight across the rim (+y) keeps both 0.7 mm up, the most any direction does (under
    # TILT_CLEARANCE). The top leans 1 cm to +x, so the CoM's direction would keep the left neighbour
    # above -TILT_TOLERANCE but below that: the object would drag it while turning. The tilt goes +y.
    model = _prism_model([(0, 0), (0.3, 0.005), (0.31, 0.4), (-0.29, 0.4), (-0.3, 0.005)])
    g = int(np.argmax(model.normals @ np.array([0, 0, -1.0])))
    X, v, left = model.X_TO[g], _vertex_at(model, (0, 0, 0)), _vertex_at(model, (-0.3, 0.005, 0))
    V = se3.transform_points(X, model.vertices)
    tilt = np.radians(8)
    dc = (se3.transform_points(X, model.com) - V[v])[:2]
    dc /= np.linalg.norm(dc)
    h_com = (V[left] - V[v])[:2] @ dc * np.sin(tilt)
    assert -poses.TILT_TOLERANCE < h_com < 0.005 * np.sin(tilt) - 1e-4   # the case: the CoM's drags
    d = poses.tilt_direction(model, X, v, tilt)
    across = X[:3, :3] @ np.array([0.0, 1.0, 0.0])
    assert d is not None and np.degrees(np.arccos(np.clip(d @ across, -1, 1))) <= 0.5 + 1e-9
    # Symmetric about the CoM, the CoM's direction is already the best one: the default stays.
    sym = _prism_model([(0, 0), (0.3, 0.005), (0.3, 0.4), (-0.3, 0.4), (-0.3, 0.005)])
    gs = int(np.argmax(sym.normals @ np.array([0, 0, -1.0])))
    assert poses.tilt_direction(sym, sym.X_TO[gs], _vertex_at(sym, (0, 0, 0)), tilt) is None


def test_a_corner_with_a_rounded_rim_around_it_is_no_pivot_corner():
    # A 0.4 m cube's base corner v = (0.2, 0.2, 0) with a rounded rim: hull vertices 3 cm out along
    # both edges' directions, 1.5 mm up. Any tilt onto v within 90 deg of the CoM's direction sinks one
    # of them by more than the tolerance (at 45 deg: 0.03 sin 45 sin 8 - 0.0015 = 1.45 mm).
    cube = np.array([(x, y, z) for x in (-0.2, 0.2) for y in (-0.2, 0.2) for z in (0.0, 0.4)])
    model = box_model(mesh=trimesh.convex.convex_hull(np.vstack([cube, (0.23, 0.2, 0.0015), (0.2, 0.23, 0.0015)])))
    g, v = int(np.argmax(model.normals @ np.array([0, 0, -1.0]))), _vertex_at(model, (0.2, 0.2, 0))
    assert v in poses.pivot_corners(model, 0.03)[g]
    assert v not in poses.pivot_corners(model, 0.03, np.radians(8))[g]
    assert len(poses.pivot_corners(model, 0.03, np.radians(8))[g]) == 3  # the other three corners
    with pytest.raises(poses.InputError):
        poses.tilt_direction(model, model.X_TO[g], v, np.radians(8))


def test_a_join_is_also_made_around_each_corner_it_pivots_about():
    """The goal 0.12 m away turned 40°, the start's lattice one pose: its closed-form join pivots about
    three corners; with ``join_alternatives`` the goal is also joined by the best sequence avoiding
    each of them where one exists (here around the first), so that one corner no reachable grasp
    holds does not cut it off; without, taking that corner's links out does."""
    import networkx as nx

    model = box_model()
    X0, g = upright(model)
    Xg, _ = upright(model, xy=(0.12, 0.05), yaw=np.radians(40))

    def without(ps, v):  # start and goal connected by links not about vertex v
        G = nx.Graph()
        G.add_nodes_from(range(len(ps.status)))
        G.add_edges_from(tuple(e) for e, lv in zip(ps.links, ps.link_vertex, strict=True) if lv != v)
        return nx.has_path(G, 0, ps.goal_id)

    base = dict(max_poses=1, goal_tree_share=0, goal_reach_share=0)
    one = poses.sample_poses(model, X0, g, (2.0, 2.0), (), poses.Params(**base, join_alternatives=0), goal=(Xg, g))
    alt = poses.sample_poses(model, X0, g, (2.0, 2.0), (), poses.Params(**base, join_alternatives=3), goal=(Xg, g))
    assert one.goal_id >= 0 and alt.goal_id >= 0
    first = int(one.link_vertex[np.flatnonzero(one.links[:, 0] == 0)[0]])
    assert not without(one, first) and without(alt, first)
    assert len(alt.links) > len(one.links)
    for a, b in alt.links:  # every alternative join is kept poses linked by exact pivots
        assert alt.status[a] == "ok" and alt.status[b] == "ok"


def test_extend_lattice_pivots_known_poses_only_about_the_corners_their_grasps_hold():
    """Grasp-aware reach: from a start whose grasps hold one corner alone, every pose grown from it
    pivots about that corner; new poses (grasps unknown) pivot about any, and the growth heads for
    the goal's side (its nearest pose comes nearer than the start)."""
    model = box_model()
    X0, g = upright(model)
    Xg, _ = upright(model, xy=(0.3, 0.0))
    prm = poses.Params(max_poses=1, goal_tree_share=0, goal_reach_share=0, join_alternatives=0, tree_joins=0,
                       walk_strides=0)
    lat = poses.build_lattice(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g))
    assert lat.goal_id >= 0
    held = int(poses.pivot_corners(model, prm.corner_cluster, prm.tilt)[g][0])
    n0 = len(lat.rows)
    poses.extend_lattice(lat, [0], [lat.goal_id], {0: np.array([held])}, budget=30)
    ps = lat.pose_set()
    assert len(ps.status) > n0
    out_of_start = [v for (a, _), v, p in zip(ps.links, ps.link_vertex, ps.link_primitive, strict=True)
                    if a == 0 and p == "pivot"]
    assert out_of_start and set(out_of_start) == {held}
    grown = np.flatnonzero(ps.parent >= n0)
    assert len(set(ps.vertex[grown].tolist()) - {-1}) > 1  # new poses pivot about the other corners too
    com = se3.transform_points(ps.X_WO, model.com)
    goal_com = se3.transform_points(Xg, model.com)
    d = np.linalg.norm(com[n0:, :2] - goal_com[:2], axis=1)
    assert d.min() < np.linalg.norm(com[0, :2] - goal_com[:2]) - 0.1


def test_extend_lattice_with_no_corner_held_pivots_nowhere_from_that_pose():
    model = box_model()
    X0, g = upright(model)
    Xg, _ = upright(model, xy=(0.3, 0.0))
    prm = poses.Params(max_poses=1, goal_tree_share=0, goal_reach_share=0, join_alternatives=0, tree_joins=0,
                       walk_strides=0)
    lat = poses.build_lattice(model, X0, g, (2.0, 2.0), (), prm, goal=(Xg, g))
    poses.extend_lattice(lat, [0], [lat.goal_id], {0: np.zeros(0, np.int64)}, budget=30)
    ps = lat.pose_set()
    assert not np.any((ps.links[:, 0] == 0) & (ps.link_primitive == "pivot"))


def test_a_box_tumbles_from_its_base_onto_a_side_and_the_route_to_its_top_takes_two():
    """The box's faces: one tumble from the base onto a side, two onto the top (no edge joins them)."""
    model = box_model()
    _, g = upright(model)
    down = se3.rotate_vectors(model.X_TO[g], model.normals) @ np.array([0.0, 0.0, -1.0])  # at rest on g
    top = int(np.argmin(down))  # the face whose outward normal points up at rest
    side = int(np.flatnonzero(np.abs(down) < 1e-9)[0])
    assert poses.face_route(model, g, g, 0.05) == [g]
    assert poses.face_route(model, g, side, 0.05) == [g, side]
    assert len(poses.face_route(model, g, top, 0.05)) == 3
    assert poses.face_route(model, g, side, 10.0) == []  # no support edge long enough: no tumble at all
