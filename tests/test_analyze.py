"""Object analysis (§4.1) against cases with known answers."""

import numpy as np
import pytest
import trimesh

from stages import analyze, se3
from stages.errors import InputError
from tests.conftest import PIANO, l_prism

P = analyze.Params()


def test_box_hull_has_8_vertices_12_edges_6_sp_placements_6_segments():
    r = analyze.compute(trimesh.creation.box((0.3, 0.2, 0.4)), 2.0, P)
    c = r.summary["counts"]
    assert (c["pivot_vertices"], c["tumble_edges"], c["placements"], c["facets"]) == (8, 12, 6, 6)
    assert r.placements["stable"].all()
    # Tumbling a box about any edge turns it by 90 degrees.
    edges = r.hull["kind"] == "edge"
    np.testing.assert_allclose(r.hull["angle"][edges], np.pi / 2, atol=1e-9)


def test_box_contact_pairs_lie_exactly_on_its_three_pairs_of_opposite_faces():
    box = trimesh.creation.box((0.3, 0.2, 0.4))
    r = analyze.compute(box, 2.0, P)
    assert len(r.pairs["pair_id"]) > 20
    seg_n = np.stack([r.segments["nx"], r.segments["ny"], r.segments["nz"]], 1)
    na, nb = seg_n[r.pairs["facet_a"]], seg_n[r.pairs["facet_b"]]
    np.testing.assert_allclose(np.einsum("ij,ij->i", na, nb), -1.0, atol=1e-9)
    axes = {int(np.argmax(np.abs(n))) for n in na}
    assert axes == {0, 1, 2}
    # Along the face normal the two contacts are the box's size apart; the squeeze line is within
    # the pair angle of the normal.
    sizes = np.array([0.3, 0.2, 0.4])
    p = np.stack([r.contacts["px"], r.contacts["py"], r.contacts["pz"]], 1)
    d = p[r.pairs["contact_b"]] - p[r.pairs["contact_a"]]
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", d, na)), sizes[np.argmax(np.abs(na), axis=1)], atol=1e-9)
    assert (r.pairs["angle"] <= np.radians(P.pair_angle_deg) + 1e-12).all()


def test_box_contacts_keep_boundary_margin_and_spacing():
    r = analyze.compute(trimesh.creation.box((0.3, 0.2, 0.4)), 2.0, P)
    p = np.stack([r.contacts["px"], r.contacts["py"], r.contacts["pz"]], 1)
    half = np.array([0.15, 0.1, 0.2])
    # On a box the facet boundary is the face rectangle: at least two coordinates are inside by the margin.
    inside = (half - np.abs(p)) >= P.boundary_margin - 1e-9
    assert (inside.sum(axis=1) >= 2).all()
    for f in np.unique(r.contacts["facet_id"]):
        q = p[r.contacts["facet_id"] == f]
        d = np.linalg.norm(q[:, None] - q[None], axis=2) + np.eye(len(q))
        assert d.min() >= P.sample_spacing - 1e-12


def test_cylinder_side_splits_by_the_angle_threshold():
    sections = 36
    cyl = trimesh.creation.cylinder(0.1, 0.3, sections=sections)
    for angle in (10.0, 20.0, 45.0):
        r = analyze.compute(cyl, 1.0, analyze.Params(segment_angle_deg=angle))
        n = np.stack([r.segments["nx"], r.segments["ny"], r.segments["nz"]], 1)
        side = np.abs(n[:, 2]) < 0.5
        assert (~side).sum() == 2  # the two caps
        # Each side facet spans the side strips whose normals are within `angle` of its seed's,
        # i.e. at most 2*angle/step + 1 strips; seeds are uncovered strips, so facets cover all strips.
        step = 360.0 / sections
        strips = np.array([len(t) // 2 for t in np.asarray(r.segments["triangles"], dtype=object)[side]])
        assert strips.max() <= 2 * np.floor(angle / step) + 1
        covered = np.unique(np.concatenate(list(np.asarray(r.segments["triangles"], dtype=object)[side])))
        assert len(covered) == 2 * sections
        assert side.sum() >= np.ceil(sections / (2 * np.floor(angle / step) + 1))


def test_l_prism_has_a_placement_that_is_not_sp():
    r = analyze.compute(l_prism(), 1.0, P)
    n = np.stack([r.placements["nx"], r.placements["ny"], r.placements["nz"]], 1)
    end_face = np.argmax(n @ np.array([1.0, 0, 0]))
    assert not r.placements["stable"][end_face]
    # CoM (x=0.1, z=0.15) projects 0.05 m beyond the end face's top edge at z = 0.1.
    assert r.placements["margin"][end_face] == pytest.approx(-0.05, abs=1e-9)
    bottom = np.argmax(n @ np.array([0, 0, -1.0]))
    assert r.placements["stable"][bottom]


def test_resting_transform_puts_the_face_on_the_table_with_the_com_above_the_origin():
    mesh = l_prism()
    r = analyze.compute(mesh, 1.0, P)
    X = se3.matrix_from_columns(r.placements)
    com = r.summary["com"]
    for X_TO in X:
        v = se3.transform_points(X_TO, mesh.vertices)
        assert v[:, 2].min() == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose(se3.transform_points(X_TO, com)[:2], 0.0, atol=1e-9)


def test_counts_and_relative_geometry_invariant_under_a_rigid_transform(rng):
    mesh = trimesh.creation.box((0.3, 0.2, 0.4))
    R = se3.matrix_from_quat(rng.normal(size=4))
    moved = mesh.copy()
    moved.apply_transform(se3.make_transform(R, rng.normal(size=3) * 0.3))
    a, b = analyze.compute(mesh, 2.0, P), analyze.compute(moved, 2.0, P)
    for k in ("pivot_vertices", "tumble_edges", "placements", "stable_placements", "facets"):
        assert a.summary["counts"][k] == b.summary["counts"][k]
    np.testing.assert_allclose(np.sort(a.placements["margin"]), np.sort(b.placements["margin"]), atol=1e-9)
    np.testing.assert_allclose(np.sort(a.segments["area"]), np.sort(b.segments["area"]), atol=1e-9)
    # Sampling depends on the triangle order, so pair counts may shift a little but not collapse.
    assert abs(a.summary["counts"]["pairs"] - b.summary["counts"]["pairs"]) <= 0.25 * a.summary["counts"]["pairs"]


def test_toy_piano_has_flat_and_curved_facets_sp_on_its_legs_and_pairs():
    mesh = analyze.load_mesh(PIANO)
    np.testing.assert_allclose(mesh.extents, [0.425, 0.205, 0.45], atol=1e-6)
    r = analyze.compute(mesh, 3.1, P)
    c = r.summary["counts"]
    assert c["facets"] > 30 and c["pairs"] > 30 and c["contacts"] > 100
    n = np.stack([r.placements["nx"], r.placements["ny"], r.placements["nz"]], 1)
    feet = np.argmax(n @ np.array([0, 0, -1.0]))
    assert r.placements["stable"][feet]
    assert len(r.placements["support_vertices"][feet]) >= 4


def test_balls_at_concave_corners_collide():
    # Two contacts inside an L's inner corner: a ball touching the foot right next to the upright hits it.
    mesh = l_prism()
    centres = np.array([[0.11, 0.0, 0.1 + 0.02], [0.25, 0.0, 0.1 + 0.02]])
    free = analyze._balls_free(mesh, centres, 0.02)
    assert free.tolist() == [False, True]


def test_mesh_errors_are_one_line_input_errors(tmp_path):
    cases = {
        "missing.obj": None,
        "empty.obj": "",
        "garbage.stl": "solid x\nthis is not a mesh\n",
        "nan.obj": "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n",
        "flat.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\nf 1 3 2\nf 2 3 4\n",
        "huge.obj": "v 0 0 0\nv 100 0 0\nv 0 100 0\nv 0 0 100\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
        "mesh.xyz": "1 2 3\n",
    }
    for name, text in cases.items():
        p = tmp_path / name
        if text is not None:
            p.write_text(text)
        with pytest.raises(InputError) as e:
            analyze.load_mesh(p)
        assert str(p) in str(e.value) and "\n" not in str(e.value), name
    with pytest.raises(InputError, match="--scale"):
        analyze.load_mesh(tmp_path / "huge.obj")


def test_open_mesh_is_repaired_when_trimesh_can(tmp_path):
    box = trimesh.creation.box((0.2, 0.2, 0.2))
    holed = trimesh.Trimesh(box.vertices, box.faces[1:])  # one triangle missing
    p = tmp_path / "holed.stl"
    holed.export(p)
    m = analyze.load_mesh(p)
    assert m.is_watertight and m.volume == pytest.approx(0.008)


# ---------------------------------------------------------------------------------- curved contacts
def test_area_in_sphere_matches_closed_forms():
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    cases = [  # (centre, radius, area)
        ((0.2, 0.2, 0.0), 0.1, np.pi * 0.1**2),  # the disk lies inside the triangle
        ((0.2, 0.2, 0.06), 0.1, np.pi * (0.1**2 - 0.06**2)),  # the sphere cuts the plane in a smaller disk
        ((0.3, 0.3, 0.0), 5.0, 0.5),  # the whole triangle inside
        ((0.0, 0.0, 0.0), 0.1, np.pi * 0.1**2 / 4),  # a quarter disk at the right-angled corner
        ((0.5, 0.0, 0.0), 0.1, np.pi * 0.1**2 / 2),  # a half disk on an edge
        ((0.5, -0.1, 0.0), 0.1, 0.0),  # tangent to an edge from outside
        ((3.0, 3.0, 0.0), 0.1, 0.0),
    ]
    for centre, radius, area in cases:
        got = analyze.area_in_sphere(tri[None], np.array([centre]), radius)
        assert got == pytest.approx([area], abs=1e-12), centre  # exact formula: rounding only


def test_area_in_sphere_batch_equals_loop_and_monte_carlo(rng):
    T = rng.normal(size=(6, 3, 3)) * 0.02
    c = rng.normal(size=(6, 3)) * 0.01
    batch = analyze.area_in_sphere(T, c, 0.02)
    assert analyze.area_in_sphere(T[:0], c[:0], 0.02).shape == (0,)
    u, v = rng.random((2, 200_000))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    for k in range(len(T)):
        assert analyze.area_in_sphere(T[k:k + 1], c[k:k + 1], 0.02)[0] == batch[k]
        pts = T[k, 0] + u[:, None] * (T[k, 1] - T[k, 0]) + v[:, None] * (T[k, 2] - T[k, 0])
        area = np.linalg.norm(np.cross(T[k, 1] - T[k, 0], T[k, 2] - T[k, 0])) / 2
        mc = area * np.mean(np.linalg.norm(pts - c[k], axis=1) <= 0.02)
        # Monte Carlo with 2e5 samples: standard error <= area * 0.5 / sqrt(2e5) ~ 1.1e-3 area.
        assert batch[k] == pytest.approx(mc, abs=5e-3 * area)


def _footprint_areas(mesh: trimesh.Trimesh, p, rho: float) -> tuple[float, float, float]:
    """Footprint area (m^2) at ``p`` on faces facing +z, sideways and -z."""
    p = np.array([p])
    fp = analyze.footprint(mesh, p, mesh.nearest.on_surface(p)[2], rho)
    nz = mesh.face_normals[fp.triangle, 2]
    return fp.area[nz > 0.99].sum(), fp.area[np.abs(nz) < 0.01].sum(), fp.area[nz < -0.99].sum()


def test_footprint_covers_a_disk_turns_a_right_angled_edge_and_skips_a_thin_plate_far_side():
    rho, d = 0.01, 0.004
    box = trimesh.creation.box((0.2, 0.2, 0.2))
    # The whole disk on a face (exact formula: rounding only).
    assert _footprint_areas(box, (0.0, 0.0, 0.1), rho) == pytest.approx((np.pi * rho**2, 0, 0), abs=1e-15)
    # d from an edge: the disk minus the circular segment beyond it, and half a disk on the side face.
    h = np.arccos(d / rho)
    segment = rho**2 * (h - np.sin(h) * np.cos(h))
    expected = (np.pi * rho**2 - segment, np.pi * (rho**2 - d**2) / 2, 0)
    assert _footprint_areas(box, (0.1 - d, 0.0, 0.1), rho) == pytest.approx(expected, abs=1e-15)
    # On a 5 mm plate near its rim the bottom face is within reach around the rim but faces away.
    top, side, bottom = _footprint_areas(trimesh.creation.box((0.2, 0.2, 0.005)), (0.1 - d, 0.0, 0.0025), rho)
    assert top == pytest.approx(expected[0], abs=1e-15) and side > 0 and bottom == 0
