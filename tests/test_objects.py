"""Object families of the general-object benchmark (stages/objects.py): every mesh is a valid benchmark
object in its canonical form, written byte-identically; the canonical form and the settling are exact."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from stages import objects
from stages.errors import InputError
from stages.objects import FAMILIES, canonical_arrays, make_mesh, settle, write_mesh

#: Vertices are rounded to 1e-6 m, so a bound or a centre computed from them is off by at most that.
ROUNDING = 1e-6


@pytest.fixture(scope="module")
def meshes() -> dict[str, trimesh.Trimesh]:
    """Every family's mesh, made once for the module (the organic ones take ~0.1 s each)."""
    return {name: make_mesh(name) for name in FAMILIES}


def test_standard_set_has_the_issue_13_families_in_order():
    assert list(FAMILIES)[:6] == ["toy_piano", "box", "cabinet", "drum", "l_block", "t_block"]
    assert {"duck", "teddy", "bunny"} <= set(FAMILIES)
    for name, family in FAMILIES.items():
        assert family.name == name and name.replace("_", "").isalnum()
        assert family.why and family.source and 0 < family.friction <= 1


@pytest.mark.parametrize("name", list(FAMILIES))
def test_family_is_one_closed_outward_body_of_benchmark_size(name, meshes):
    mesh, family = meshes[name], FAMILIES[name]
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.body_count == 1
    assert mesh.volume > 0  # outward normals
    assert 0.35 <= mesh.extents.max() <= 0.5
    assert 2.0 <= family.mass <= 6.0
    assert len(mesh.faces) <= objects.MAX_FACES
    # ``size`` is documented to the millimetre: half a millimetre of rounding.
    np.testing.assert_allclose(mesh.extents, family.size, atol=5e-4)


@pytest.mark.parametrize("name", list(FAMILIES))
def test_family_rests_on_z0_with_the_origin_at_its_footprint_centre(name, meshes):
    mesh = meshes[name]
    lo, hi = mesh.bounds
    assert lo[2] == 0.0  # placed with the lowest vertex on z = 0, and 0.0 survives the rounding exactly
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=ROUNDING)
    # Resting, not balancing: the vertices on the table span a polygon that holds the CoM's projection.
    # The resting face is made horizontal before rounding, so its vertices are at z <= ROUNDING. A
    # curved base rests on one small hull face (the duck's is a triangle 1.2 mm around the CoM's
    # projection), so only the sign is asserted; the flat bases hold it 8 cm or more inside.
    feet = mesh.vertices[mesh.vertices[:, 2] <= ROUNDING, :2]
    eq = ConvexHull(feet).equations
    assert -np.max(eq[:, :2] @ mesh.center_mass[:2] + eq[:, 2]) > 0


def test_write_mesh_is_byte_identical_across_runs_and_reloads_as_made(tmp_path, meshes):
    assert objects.main([str(tmp_path / "a")]) == 0
    for name, mesh in meshes.items():
        first = (tmp_path / "a" / f"{name}.obj").read_bytes()
        assert write_mesh(name, tmp_path / "b.obj") == tmp_path / "b.obj"
        assert (tmp_path / "b.obj").read_bytes() == first
        back = trimesh.load(tmp_path / "b.obj", force="mesh", process=False)
        np.testing.assert_array_equal(back.faces, mesh.faces)
        np.testing.assert_allclose(back.vertices, mesh.vertices, atol=0.5 * ROUNDING)


def test_toy_piano_family_is_the_committed_mesh_unchanged(tmp_path):
    # The piano script writes the same canonical form: only the comment line may differ.
    written = write_mesh("toy_piano", tmp_path / "piano.obj").read_text().splitlines()
    assert written[1:] == objects.PIANO.read_text().splitlines()[1:]


def test_unknown_family_raises_input_error():
    with pytest.raises(InputError, match="unknown object family 'spoon'"):
        make_mesh("spoon")


def test_canonical_arrays_ignore_vertex_order_face_order_and_face_start(rng):
    box = trimesh.creation.box((0.3, 0.2, 0.1))
    perm = rng.permutation(len(box.vertices))
    inverse = np.argsort(perm)
    faces = np.roll(inverse[box.faces], rng.integers(3), axis=1)[rng.permutation(len(box.faces))]
    v0, f0 = canonical_arrays(box.vertices, box.faces)
    v1, f1 = canonical_arrays(box.vertices[perm] + 1e-9, faces)  # noise far below the 1e-6 m rounding
    np.testing.assert_array_equal(v0, v1)
    np.testing.assert_array_equal(f0, f1)
    assert trimesh.Trimesh(v1, f1, process=False).volume > 0  # windings kept


@pytest.mark.parametrize(("tilt_deg", "extents"), [(10.0, (0.3, 0.2, 0.1)), (-70.0, (0.3, 0.1, 0.2))])
def test_settle_tips_a_tilted_box_onto_the_face_below_its_com(tilt_deg, extents):
    # A 0.3 x 0.2 x 0.1 m box turned about x. At 10 deg the CoM's vertical still leaves through the
    # bottom face (it takes atan(0.1 / 0.05) = 63 deg to carry the CoM over an edge): it rocks back.
    # At -70 deg the vertical leaves through the +y side, now 20 deg from flat: the box falls onto it.
    box = trimesh.creation.box((0.3, 0.2, 0.1))
    box.apply_transform(trimesh.transformations.rotation_matrix(np.radians(tilt_deg), [1, 0, 0]))
    np.testing.assert_allclose(settle(box).extents, extents, atol=1e-12)  # exact up to float round-off
