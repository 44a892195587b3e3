"""Object analysis (§4.1) against cases with known answers."""

from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import trimesh

from stages import analyze, se3, stability
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
    # The facet rule's pairs (first) within the pair angle of the normal, the slanted ones within the cone.
    c = r.summary["counts"]
    facet = np.arange(c["pairs"]) < c["pairs"] - c["slanted_pairs"]
    assert c["slanted_pairs"] > 0 and c["cone_pairs"] == 0
    assert (r.pairs["angle"][facet] <= np.radians(P.pair_angle_deg) + 1e-12).all()
    assert (r.pairs["angle"] <= np.radians(P.cone_angle_deg) + 1e-12).all()
    assert r.pairs["angle"][~facet].max() > np.radians(P.pair_angle_deg)


def test_a_slanted_squeeze_lifts_a_bar_onto_its_corner_where_straight_ones_cannot():
    # A 0.4 x 0.1 x 0.15 m bar of 4.5 kg on the corner of one end, its balls on both ends with the
    # sampler's pivot bounds: straight across, friction alone would have to hold up the far end (55 N
    # of squeeze); a slanted squeeze, the far ball higher, adds the couple of its normal forces.
    bar = trimesh.creation.box((0.4, 0.1, 0.15))
    bar.apply_translation([0.0, 0.0, 0.075])
    r = analyze.compute(bar, 4.5, P)
    c = r.summary["counts"]
    p = np.stack([r.contacts["px"], r.contacts["py"], r.contacts["pz"]], 1)
    n = np.stack([r.contacts["nx"], r.contacts["ny"], r.contacts["nz"]], 1)
    a, b = r.pairs["contact_a"], r.pairs["contact_b"]
    ends = np.abs(n[a, 0]) > 0.5
    facet = np.arange(len(a)) < c["pairs"] - c["slanted_pairs"]
    mu = 0.4
    prm = stability.Params(mu_eef=mu, mu_table=mu, f_max=stability.normal_bound(0.9 * 50.0, mu))
    res = stability.evaluate(4.5, np.tile([0.0, 0.0, 0.075], (len(a), 1)), np.tile([-0.2, -0.05, 0.0], (len(a), 1, 1)),
                             None, np.stack([p[a], p[b]], 1), -np.stack([n[a], n[b]], 1), None, 0.25, prm,
                             compute_margin=False)
    assert (ends & facet).sum() >= 3 and not res.stable[ends & facet].any()
    assert res.stable[ends & ~facet].any()


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
    # Its only curved contacts, on the legs, pair with nothing and are dropped: its contacts and
    # pairs are the flat facets' alone.
    assert c["curved_contacts"] == 0 and c["cone_pairs"] == 0 and r.summary["filtered"]["curved_unpaired"] > 0
    assert (r.contacts["facet_id"] >= 0).all() and (r.pairs["facet_a"] >= 0).all()


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


def test_curved_contact_normals_are_closer_to_a_spheres_radii_than_face_normals():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.15)
    r = analyze.compute(sphere, 2.0, P)
    c = r.contacts
    assert (c["facet_id"] == -1).all() and len(c["facet_id"]) > 100
    p = np.stack([c["px"], c["py"], c["pz"]], 1)
    n = np.stack([c["nx"], c["ny"], c["nz"]], 1)
    radial = p / np.linalg.norm(p, axis=1, keepdims=True)
    dev = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, radial), -1, 1)))
    face_dev = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", sphere.face_normals[c["triangle"]], radial), -1, 1)))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    # Subdivision 3: a face's normal is up to 4.4 deg (mean 2.3) off the radius at a sample; the 1 cm
    # footprint averages the faces around it (measured: mean 0.4, max 0.8 deg).
    assert dev.mean() < 0.3 * face_dev.mean() and dev.max() < 1.5


# ------------------------------------------------------------------------------------------- pairs
def _wedge(apex_deg: float, height: float = 0.3, depth: float = 0.2) -> trimesh.Trimesh:
    """A prism along y whose cross-section is an isosceles triangle with its apex (``apex_deg``) on top."""
    half = height * np.tan(np.radians(apex_deg) / 2)
    prof = [(-half, 0.0), (half, 0.0), (0.0, height)]
    return trimesh.convex.convex_hull([(x, y, z) for x, z in prof for y in (-depth / 2, depth / 2)])


def _curved_contacts_at(p: np.ndarray, n: np.ndarray) -> dict:
    """A contacts table of curved contacts (``facet_id`` -1) at points ``p`` with normals ``n`` (C, 3)."""
    return {"contact_id": np.arange(len(p)), "facet_id": -np.ones(len(p), dtype=np.int64),
            "triangle": np.zeros(len(p), dtype=np.int64), "px": p[:, 0], "py": p[:, 1], "pz": p[:, 2],
            "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]}


def test_cone_pair_is_refused_when_the_squeeze_line_leaves_the_friction_cone():
    # On a wedge the level squeeze line makes half the apex angle with each face's normal: 30 deg
    # on a 60 deg wedge, outside the 21.8 deg cone; 15 deg on a 30 deg wedge, inside.
    for apex, expected in ((60.0, 0), (30.0, 1)):
        wedge = _wedge(apex)
        half = 0.1 * np.tan(np.radians(apex) / 2)  # the faces at z = 0.2 (0.1 below the apex)
        p = np.array([[-half, 0.0, 0.2], [half, 0.0, 0.2]])
        n = wedge.face_normals[wedge.nearest.on_surface(p)[2]]
        pairs = analyze.find_contact_pairs(wedge, analyze.superimposed_segments(wedge, P), _curved_contacts_at(p, n), P)
        assert len(pairs["pair_id"]) == expected, apex
        if expected:
            assert pairs["angle"][0] == pytest.approx(np.radians(apex / 2), abs=1e-9)
            assert (pairs["facet_a"] == -1).all() and (pairs["facet_b"] == -1).all()


def test_ellipsoid_gets_many_well_spread_cone_pairs_inside_the_cone():
    # The facet rule found 24 here: facet normals of a curved surface are rarely opposite within 15 deg.
    ell = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    ell.apply_scale((0.2, 0.13, 0.1))
    r = analyze.compute(ell, 2.0, P)
    c, pr = r.contacts, r.pairs
    assert len(pr["pair_id"]) == P.max_pairs and (pr["facet_a"] == -1).all() and (pr["facet_b"] == -1).all()
    p = np.stack([c["px"], c["py"], c["pz"]], 1)
    n = np.stack([c["nx"], c["ny"], c["nz"]], 1)
    u = p[pr["contact_b"]] - p[pr["contact_a"]]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    # Inside both cones (the line against each inward normal), as the angle column says.
    na, nb = n[pr["contact_a"]], n[pr["contact_b"]]
    ang = np.arccos(np.minimum(-np.einsum("ij,ij->i", u, na), np.einsum("ij,ij->i", u, nb)))
    np.testing.assert_allclose(pr["angle"], ang, atol=1e-12)
    assert (ang <= np.radians(P.cone_angle_deg)).all()
    assert (pr["width"] > 2 * P.ball_radius).all()
    # Spread: more than half the contacts are used, and squeezes run along each of the three axes.
    assert len(np.unique(np.concatenate([pr["contact_a"], pr["contact_b"]]))) > 0.5 * len(p)
    assert (np.abs(u).max(axis=0) > np.cos(np.radians(5))).all()


def test_cylinder_pairs_its_caps_by_facets_and_its_side_by_cones_off_the_caps_rims():
    h, r_cyl = 0.3, 0.1
    r = analyze.compute(trimesh.creation.cylinder(r_cyl, h, sections=64), 2.0, P)
    c, pr = r.contacts, r.pairs
    curved = c["facet_id"] < 0
    assert (np.abs(c["nz"][~curved]) == 1).all() and (np.abs(c["nz"][curved]) < 1e-9).all()
    # A curved contact keeps the boundary margin from the flat caps, as a cap's contacts keep it from the rim.
    assert np.abs(c["pz"][curved]).max() <= h / 2 - P.boundary_margin
    assert r.summary["filtered"]["curved_near_flat"] > 0
    facet = (pr["facet_a"] >= 0) & (pr["facet_b"] >= 0)
    assert facet.sum() > 5 and (~facet).sum() > 50
    p = np.stack([c["px"], c["py"], c["pz"]], 1)
    np.testing.assert_allclose(np.abs(p[pr["contact_b"][facet], 2] - p[pr["contact_a"][facet], 2]), h, atol=1e-9)
    assert (pr["facet_a"][~facet] == -1).all() and (pr["facet_b"][~facet] == -1).all()
    # Every curved contact kept is used by a pair, and the renumbered ids still point at curved contacts.
    used = np.unique(np.concatenate([pr["contact_a"][~facet], pr["contact_b"][~facet]]))
    np.testing.assert_array_equal(used, np.flatnonzero(curved))
    np.testing.assert_array_equal(c["contact_id"], np.arange(len(curved)))


def test_cube_keeps_exactly_its_opposite_face_pairs():
    r = analyze.compute(trimesh.creation.box((0.25, 0.25, 0.25)), 2.0, P)
    assert r.summary["counts"]["curved_contacts"] == 0 and r.summary["counts"]["cone_pairs"] == 0
    seg_n = np.stack([r.segments["nx"], r.segments["ny"], r.segments["nz"]], 1)
    na = seg_n[r.pairs["facet_a"]]
    np.testing.assert_allclose(np.einsum("ij,ij->i", na, seg_n[r.pairs["facet_b"]]), -1.0, atol=1e-9)
    p = np.stack([r.contacts["px"], r.contacts["py"], r.contacts["pz"]], 1)
    d = p[r.pairs["contact_b"]] - p[r.pairs["contact_a"]]
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", d, na)), 0.25, atol=1e-9)  # the cube's size apart


def test_cone_pairs_fill_max_pairs_but_facet_pairs_are_never_capped():
    sphere = analyze.compute(trimesh.creation.icosphere(subdivisions=3, radius=0.15), 2.0,
                             analyze.Params(max_pairs=30))
    assert sphere.summary["counts"]["pairs"] == 30
    box = analyze.compute(trimesh.creation.box((0.3, 0.2, 0.4)), 2.0, analyze.Params(max_pairs=10))
    full = analyze.compute(trimesh.creation.box((0.3, 0.2, 0.4)), 2.0, P).summary["counts"]
    assert box.summary["counts"]["slanted_pairs"] == 0 and full["slanted_pairs"] > 0
    assert box.summary["counts"]["pairs"] == full["pairs"] - full["slanted_pairs"] > 10


def test_spread_pairs_takes_one_per_cluster_from_the_best_and_skips_refused_pairs(rng):
    # 10 clusters of 5 nearly equal pairs (1 mm apart) whose clusters lie 0.1 m or more apart.
    centres = np.stack([np.arange(10) * 0.1, np.zeros(10), np.zeros(10)], 1)
    pa = np.repeat(centres, 5, axis=0) + rng.normal(size=(50, 3)) * 1e-3
    pb = pa + np.array([0.0, 0.0, 0.3])
    angle = rng.random(50)
    kept = analyze._spread_pairs(pa, pb, angle, 10, lambda a, b: np.ones(len(a), bool))
    assert sorted(kept // 5) == list(range(10))
    assert np.argmin(angle) in kept  # sampling starts at the largest margin
    # The same, ends swapped: pairs are unordered.
    odd = (np.arange(50) % 2 == 1)[:, None]
    swapped = analyze._spread_pairs(np.where(odd, pb, pa), np.where(odd, pa, pb), angle, 10,
                                    lambda a, b: np.ones(len(a), bool))
    assert sorted(swapped // 5) == list(range(10))
    # A validity check that refuses cluster 0 entirely: nine clusters, then a second pick elsewhere.
    refused = analyze._spread_pairs(pa, pb, angle, 10, lambda a, b: a[:, 0] > 0.05)
    assert len(refused) == 10 and not (refused < 5).any() and len(np.unique(refused // 5)) == 9
    assert len(analyze._spread_pairs(pa[:0], pb[:0], angle[:0], 10, lambda a, b: a[:, 0] > 0)) == 0


def test_bunny_gets_cone_pairs_with_room_for_both_balls_and_the_squeeze_inside():
    path = Path(pybullet_data.getDataPath()) / "bunny.obj"
    bunny = analyze.load_mesh(path, 0.45 / analyze.load_mesh(path).extents.max())
    r = analyze.compute(bunny, 3.0, P)
    c, pr = r.contacts, r.pairs
    assert len(pr["pair_id"]) >= 50  # the facet rule alone found 2
    assert r.summary["filtered"]["curved_ball_collision"] > 0  # bumps a ball cannot touch were refused
    p = np.stack([c["px"], c["py"], c["pz"]], 1)
    n = np.stack([c["nx"], c["ny"], c["nz"]], 1)
    # Every ball (centre p + r n) clears the surface: distance >= 0.98 r (_balls_free's tangency allowance).
    depth = trimesh.proximity.signed_distance(bunny, p + P.ball_radius * n)  # > 0 inside the mesh
    assert (-depth >= 0.98 * P.ball_radius - 1e-9).all()
    inside = analyze.make_segments_inside_fn(bunny)
    assert inside(p[pr["contact_a"]], p[pr["contact_b"]]).all()
    assert (pr["angle"] <= np.radians(P.cone_angle_deg)).all()
    # Deterministic: the same input gives the same tables.
    again = analyze.compute(bunny, 3.0, P)
    for table, other in ((c, again.contacts), (pr, again.pairs)):
        for k in table:
            assert np.array_equal(table[k], other[k]), k
