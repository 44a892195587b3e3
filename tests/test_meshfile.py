"""Ambiguous meshes (issue 17): each is refused in one line naming the file, or, for scan debris,
taken with one warning line; no numerical warning reaches the user."""

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from pivotcli.app import app
from stages import meshfile
from stages.errors import InputError

runner = CliRunner()
BOX = (0.3, 0.2, 0.25)


def _two_bodies(path):
    far = trimesh.creation.box((0.1, 0.1, 0.1))
    far.apply_translation((0.5, 0, 0))
    trimesh.util.concatenate([trimesh.creation.box(BOX), far]).export(path)


def _huge_vertex(path):
    m = trimesh.creation.box(BOX)
    v = m.vertices.copy()
    v[3] = [1e308, 0, 0]
    trimesh.Trimesh(v, m.faces, process=False).export(path)


def _flat_box(path):
    m = trimesh.creation.box(BOX)
    v = m.vertices.copy()
    v[:, 2] = 0
    trimesh.Trimesh(v, m.faces, process=False).export(path)


def _garbage(path):
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())


def _truncated(path):
    trimesh.creation.box(BOX).export(path)
    path.write_bytes(path.read_bytes()[:400])


CASES = {  # file, writer, what the line says
    "two_bodies": ("two.stl", _two_bodies, "2 separate bodies"),
    "huge_vertex": ("huge.obj", _huge_vertex, "1 stray vertices lie over 5.0 m from the rest (vertex 3 at 1e+308"),
    "zero_height": ("flat.obj", _flat_box, "encloses zero volume (extents 0.3 x 0.2 x 0 m)"),
    "garbage_stl": ("garbage.stl", _garbage, "not a valid STL file"),
    "truncated_stl": ("cut.stl", _truncated, "header gives 12 triangles (684 bytes) but the file has 400 bytes"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_an_ambiguous_mesh_is_one_line_exit_2_naming_it(tmp_path, case):
    name, write, says = CASES[case]
    write(tmp_path / name)
    r = runner.invoke(app, ["analyze", str(tmp_path / name), "--out", str(tmp_path / "out")])
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert r.exit_code == 2 and len(lines) == 1, r.output  # no RuntimeWarning lines before it
    assert name in lines[0] and says in lines[0], lines[0]
    assert not (tmp_path / "out").exists()


def test_parts_that_touch_or_nest_are_one_object(tmp_path):
    box = trimesh.creation.box(BOX)
    inner = trimesh.creation.box((0.1, 0.1, 0.1))
    inner.invert()  # a cavity: the hollow box weighs less than the solid one
    handle = trimesh.creation.box((0.05, 0.05, 0.05))
    handle.apply_translation((0.17, 0, 0))  # overlaps the box's +x face
    # STL stores float32 coordinates: the volume agrees to ~1e-7 relative.
    for name, parts, volume in (("hollow.stl", [box, inner], 0.015 - 0.001), ("handle.stl", [box, handle], None)):
        trimesh.util.concatenate(parts).export(tmp_path / name)
        m = meshfile.load_mesh(tmp_path / name)
        assert len(m.faces) == 24
        if volume is not None:
            assert m.volume == pytest.approx(volume, rel=1e-6)


def test_scan_debris_is_dropped_with_one_warning_line(tmp_path, caplog):
    debris = trimesh.creation.box((0.01, 0.01, 0.01))
    debris.apply_translation((0.4, 0, 0))  # 1e-6 m^3 beside 0.015 m^3: under DEBRIS_VOLUME
    trimesh.util.concatenate([trimesh.creation.box(BOX), debris]).export(tmp_path / "scan.stl")
    m = meshfile.load_mesh(tmp_path / "scan.stl")
    assert len(m.faces) == 12 and m.volume == pytest.approx(0.015)
    warned = [r.getMessage() for r in caplog.records if r.name == "pivot.mesh"]
    assert len(warned) == 1 and "scan.stl: dropped 1 small separate bodies" in warned[0]


def test_a_body_of_two_percent_is_not_debris(tmp_path):
    side = (0.02 * 0.015) ** (1 / 3) * 1.01  # just over DEBRIS_VOLUME of the total
    other = trimesh.creation.box((side, side, side))
    other.apply_translation((0.4, 0, 0))
    trimesh.util.concatenate([trimesh.creation.box(BOX), other]).export(tmp_path / "two.stl")
    with pytest.raises(InputError, match="2 separate bodies"):
        meshfile.load_mesh(tmp_path / "two.stl")
