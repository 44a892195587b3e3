"""Scale (issue 20): fine meshes and large lattices give the answers the direct computations give."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from stages import objects, poses, se3, simplify
from tests.test_poses import box_model, upright

HALF = np.array([0.45, 0.3])


def clip_one(poly: np.ndarray, axis: int, sign: float, limit: float) -> np.ndarray:
    """Sutherland–Hodgman against one half-plane, one polygon (the reference for ``_clip_all``)."""
    d = sign * poly[:, axis] - limit
    out = []
    for i in range(len(poly)):
        a, b, da, db = poly[i], poly[(i + 1) % len(poly)], d[i], d[(i + 1) % len(poly)]
        if da <= 0:
            out.append(a)
        if (da < 0 < db) or (db < 0 < da):
            out.append(a + (b - a) * (da / (da - db)))
    return np.array(out).reshape(-1, 2)


def test_clip_all_equals_clipping_one_triangle_at_a_time(rng):
    T = rng.uniform(-0.7, 0.7, (500, 3, 2))
    P, n = T, np.full(len(T), 3)
    for axis in (0, 1):
        for sign in (1.0, -1.0):
            P, n = poses._clip_all(P, n, axis, sign, HALF[axis])
    for i, tri in enumerate(T):
        poly = tri
        for axis in (0, 1):
            for sign in (1.0, -1.0):
                poly = clip_one(poly, axis, sign, HALF[axis])
        assert np.array_equal(P[i, : n[i]], poly)  # same arithmetic, so bit for bit
    assert len(poses._clip_all(T[:0], n[:0], 0, 1.0, 0.45)[1]) == 0


def contact_by_scan(model, X, g):
    """The table contact the direct way: every support triangle of the mesh, clipped, hulled (Qhull)."""
    z = model.mesh_vertices @ model.X_TO[g][2, :3] + model.X_TO[g][2, 3]
    tri = model.mesh_faces[np.all(np.abs(z[model.mesh_faces]) < poses.SUPPORT_TOL, axis=1)]
    V = se3.transform_points(X, model.mesh_vertices[tri])[..., :2]
    pieces = [se3.transform_points(X, model.vertices[np.asarray(model.support[g])])[:, :2]]
    pieces[0] = pieces[0][np.all(np.abs(pieces[0]) <= HALF, axis=1)]
    for poly in V:
        for axis in (0, 1):
            for sign in (1.0, -1.0):
                poly = clip_one(poly, axis, sign, HALF[axis]) if len(poly) else poly
        pieces.append(poly)
    return np.concatenate(pieces)


@pytest.mark.parametrize("xy", [(0.0, 0.0), (0.35, 0.1), (0.44, -0.25), (0.6, 0.0)])
def test_table_support_of_a_fine_mesh_is_the_hull_of_all_its_clipped_support_triangles(xy):
    fine = objects.refine(trimesh.creation.box((0.2, 0.3, 0.4)), 12 * 16 + 40)  # subdivided, 20 centroid splits
    model = box_model(mesh=fine)
    X, g = upright(model, xy, yaw=0.3)
    got = poses.table_support(model, X, g, HALF)
    pts = contact_by_scan(model, X, g)
    if len(pts) < 3:
        assert len(got) < 3
        return
    want = ConvexHull(pts)
    assert len(model.supports[g].rim) < len(model.supports[g].vertices)  # the rim is a real reduction
    # table_support rounds to 1e-9 m before its hull: areas agree to ~1e-8, corners to 1e-9 m
    assert ConvexHull(got).volume == pytest.approx(want.volume, rel=1e-7)  # 2-D: the area
    gap = np.linalg.norm(got[:, None] - pts[want.vertices][None], axis=2)
    assert gap.min(axis=0).max() < 1e-8  # every corner is there ...
    assert np.abs((got @ want.equations[:, :2].T + want.equations[:, 2]).max(axis=1)).max() < 1e-8  # ... on the rim


def test_refine_reaches_the_exact_face_count_and_keeps_the_solid():
    piano = objects.make_mesh("toy_piano")
    fine = objects.refine(piano, 50_000)
    assert len(fine.faces) == 50_000
    assert fine.is_watertight and fine.is_winding_consistent and fine.body_count == 1
    assert fine.volume == pytest.approx(piano.volume, rel=1e-6)  # centroids rounded to 1 um
    assert np.allclose(fine.bounds, piano.bounds)
    with pytest.raises(Exception, match="cannot be reached"):
        objects.refine(piano, 50_001)


# ----------------------------------------------------------------------------------------------------
# Physics collision shape of a fine mesh (stages.execute)


def test_unsupported_faces_measures_only_hull_vertices_with_the_dense_answer():
    from stages import execute

    m = objects.refine(objects.make_mesh("l_block"), 4000)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    a = V[F[:, 0]]
    n = np.cross(V[F[:, 1]] - a, V[F[:, 2]] - a)
    ln = np.linalg.norm(n, axis=1)
    n, a, Fk = n / ln[:, None], a, F
    dense = Fk[((V @ n.T) - np.einsum("ij,ij->i", a, n)).max(axis=0) > 1e-6]  # the vertices x faces matrix
    got = execute._unsupported_faces(V, F, 1e-6)
    assert len(dense) > 0 and np.array_equal(got, dense)


def test_collision_mesh_simplifies_a_fine_mesh_within_its_recorded_bound():
    coarse = objects.make_mesh("l_block")
    fine = objects.refine(coarse, 6000)
    shape = simplify.collision_mesh(fine, max_faces=1000)
    assert len(shape.mesh.faces) <= 1000 and shape.mesh.is_watertight
    assert 0 < shape.tolerance <= 1e-4
    # Both ways within the bound: the simplified vertices on the fine surface, the fine ones on the simplified.
    assert np.abs(trimesh.proximity.signed_distance(fine, shape.mesh.vertices)).max() <= shape.tolerance
    assert np.abs(trimesh.proximity.signed_distance(shape.mesh, fine.vertices[::7])).max() <= shape.tolerance
    assert simplify.collision_mesh(coarse, max_faces=1000) == (coarse, 0.0)  # small meshes stay as they are


def test_a_200k_face_piano_decomposes_into_the_pieces_of_the_piano(tmp_path):
    from stages import execute

    piano = objects.make_mesh("toy_piano")
    shape = simplify.collision_mesh(objects.refine(piano, 200_000))
    parts, _, _ = execute.convex_parts(shape.mesh, tmp_path)
    want, _, _ = execute.convex_parts(piano, tmp_path)
    assert len(parts) == len(want)
    total = sum(trimesh.convex.convex_hull(V).volume for V in parts)
    assert total == pytest.approx(piano.volume, rel=1e-6)  # exact pieces, no V-HACD inflation


# ----------------------------------------------------------------------------------------------------
# Robot set-up kept on disk (stages.robot, stages.cache)


def _setup(urdf):
    from stages import robot as rb

    rb._shared_cache.cache_clear()  # a new process, as far as the robot is concerned
    r = rb.load_robot(urdf)
    return rb._self_pairs(r), r._library("left")[:2]


def test_robot_setup_is_read_back_from_disk_identical_and_keyed_by_the_urdf(tmp_path, monkeypatch):
    import shutil

    from tests.conftest import REPO

    urdf = tmp_path / "robot.urdf"
    shutil.copy(REPO / "data" / "robots" / "sda5f.urdf", urdf)
    monkeypatch.setenv("PIVOT_CACHE_DIR", str(tmp_path / "cache"))
    pairs, lib = _setup(urdf)
    entries = sorted((tmp_path / "cache").glob("robot-*.npz"))
    assert len(entries) == 2  # the pair table and the left arm's seed library
    mtimes = [e.stat().st_mtime_ns for e in entries]
    pairs2, lib2 = _setup(urdf)
    assert [e.stat().st_mtime_ns for e in entries] == mtimes  # read, not written again
    from stages.robot import _flatten

    one, two = _flatten((*pairs, *lib)), _flatten((*pairs2, *lib2))
    assert one.keys() == two.keys() and len(one) == 9  # 3 tables x 2 arms, the left-right pairs, q, cost
    for k in one:
        assert one[k].dtype == two[k].dtype and np.array_equal(one[k], two[k])
    urdf.write_text(urdf.read_text() + "\n<!-- edited -->\n")  # another URDF: new entries, never stale ones
    _setup(urdf)
    assert len(list((tmp_path / "cache").glob("robot-*.npz"))) == 4
    monkeypatch.setenv("PIVOT_CACHE_DIR", "")  # off: derived in the process, nothing written
    pairs3, _ = _setup(urdf)
    assert len(list((tmp_path / "cache").glob("robot-*.npz"))) == 4
    three = _flatten(pairs3)
    assert all(np.array_equal(one[k], three[k]) for k in three)


def test_cache_dir_follows_xdg_cache_home(tmp_path, monkeypatch):
    from stages import cache

    monkeypatch.delenv("PIVOT_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache.cache_dir() == tmp_path / "pivot"
    (tmp_path / "pivot").mkdir()
    (tmp_path / "pivot" / "robot-x.npz").write_bytes(b"not a zip")
    assert cache.load("robot-x.npz") is None  # unreadable: derived again


# ----------------------------------------------------------------------------------------------------
# Contact pairs searched per facet pair (stages.analyze)


def all_pairs(P, N, allowed, cos_t, min_width, best_only):
    """The squeeze test of every contact against every other (the quadratic reference)."""
    d = P[None] - P[:, None]
    dist = np.linalg.norm(d, axis=2)
    u = d / np.maximum(dist[..., None], 1e-12)
    score = np.minimum(-np.einsum("ijk,ik->ij", u, N), np.einsum("ijk,jk->ij", u, N))
    score = np.where(allowed & (dist > min_width), score, -np.inf)
    ok = score > cos_t
    if best_only:
        ok &= np.arange(len(P))[None] == np.argmax(score, axis=1)[:, None]
    return np.unique(np.sort(np.argwhere(ok), axis=1), axis=0)


def test_grouped_pair_search_finds_the_all_pairs_answer(rng):
    from stages import analyze

    C = 400
    P = rng.uniform(-0.2, 0.2, (C, 3))
    N = rng.normal(size=(C, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    fid = rng.integers(-1, 6, C)  # six facets and curved contacts (-1)
    opposite = np.zeros((6, 6), bool)
    opposite[[0, 1, 2, 3], [1, 0, 3, 2]] = True
    ids, curved = np.arange(C), fid < 0
    groups = [(ids[fid == f], np.sort(ids[np.isin(fid, np.flatnonzero(opposite[f]))])) for f in range(6)]
    allowed = opposite[np.maximum(fid, 0)][:, np.maximum(fid, 0)] & ~curved[:, None] & ~curved[None]
    for best in (True, False):
        got = analyze._antipodal_pairs(P, N, groups, 0.5, 0.04, best)
        assert len(got) > 10 and np.array_equal(got, all_pairs(P, N, allowed, 0.5, 0.04, best))
    cone = [(ids[curved], ids), (ids[~curved], ids[curved])]
    got = analyze._antipodal_pairs(P, N, cone, 0.5, 0.04, False)
    assert np.array_equal(got, all_pairs(P, N, curved[:, None] | curved[None], 0.5, 0.04, False))
