"""Write the toy piano mesh of the paper's experiments (§6): ``python make_toy_piano.py [OUT]``.

The paper's object is an upright toy piano, 0.425 m wide (x, along the keyboard), 0.205 m deep (y) and
0.45 m tall (z), 3.1 kg. This script builds a stand-in from boxes and cylinders and writes one
watertight, outward-oriented triangle mesh in metres to ``OUT`` (default ``toy_piano.obj`` next to this
script).

Object frame O: x along the width, y along the depth with the keyboard side at -y, z up; the origin is
the centre of the footprint and the four feet stand on z = 0. Parts (all dimensions in metres):

- the cabinet, one prism swept along x from its side profile: the lower cabinet under the keyboard,
  the keyboard ledge at mid height protruding at -y to the front of the bounding box (12.5 mm beyond
  the front panel below it), and the upper cabinet set back behind the keys up to the full height;
- four cylindrical legs (24 sides, radius 0.018, 0.09 tall) under the corners of the cabinet, inset
  2 mm from its sides so that no curved surface is tangent to a flat one;
- 14 white keys (boxes with 3 mm gaps) on the ledge between two end blocks (cheeks).

The parts overlap by a millimetre or more and no two of their faces are coplanar; they are joined by
a boolean union with ``manifold3d`` (the committed OBJ is what the pipeline reads). The result is
written canonically by ``stages.objects`` (so pivot must be installed) -- vertices rounded to 1e-6 m,
merged and sorted, each face rotated to start at its smallest index and the faces sorted -- so reruns
are byte-identical whatever order the boolean engine emits.
"""

from __future__ import annotations

import sys
from pathlib import Path

import manifold3d
import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from stages.objects import DECIMALS, canonical_arrays, mesh_problems, obj_text

WIDTH, DEPTH, HEIGHT = 0.425, 0.205, 0.45
LEG_RADIUS, LEG_HEIGHT, LEG_SECTIONS, LEG_INSET = 0.018, 0.09, 24, 0.002
#: Legs and cheeks reach this far into the cabinet: the union sees a real overlap, not touching faces.
OVERLAP = 0.005
FRONT_PANEL_Y = -0.090
LEDGE_Z = (0.210, 0.235)
UPPER_FRONT_Y = -0.030
KEY_COUNT, KEY_GAP, KEY_TOP = 14, 0.003, 0.250
KEY_FRONT_Y, KEY_BACK_Y = -0.100, -0.040
CHEEK_WIDTH, CHEEK_TOP = 0.025, 0.262
#: Keys and cheeks sink this far into the ledge (overlap for the union).
SINK = 0.001


def box(lo, hi) -> manifold3d.Manifold:
    """Axis-aligned box between corners ``lo`` and ``hi`` (3,) m."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    return manifold3d.Manifold.cube(tuple(hi - lo)).translate(tuple(lo))


def cabinet() -> manifold3d.Manifold:
    """Lower cabinet, keyboard ledge and upper cabinet as one prism: their side profile swept along x.

    One profile instead of three overlapping boxes keeps the flat sides free of the slivers a union of
    coplanar faces leaves behind.
    """
    hx, hy = WIDTH / 2, DEPTH / 2
    zl, zt = LEDGE_Z
    # (y, z) outline, counter-clockwise: bottom, back, top, down the upper front, the ledge, the panel.
    profile = np.array([
        (FRONT_PANEL_Y, LEG_HEIGHT), (hy, LEG_HEIGHT), (hy, HEIGHT), (UPPER_FRONT_Y, HEIGHT),
        (UPPER_FRONT_Y, zt), (-hy, zt), (-hy, zl), (FRONT_PANEL_Y, zl),
    ])
    prism = manifold3d.CrossSection([profile]).extrude(WIDTH)
    # The extrusion runs along its z; map (u, v, w) -> (x, y, z) = (w - hx, u, v), a proper rotation.
    M = np.array([[0.0, 0.0, 1.0, -hx], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    return prism.transform(M)


def make_parts() -> list[manifold3d.Manifold]:
    """The overlapping solids whose union is the piano, in frame O."""
    hx, hy = WIDTH / 2, DEPTH / 2
    parts = [cabinet()]
    # Legs: centred so that each stays LEG_INSET inside the cabinet's sides (front: the front panel).
    r = LEG_RADIUS
    for x in (-hx + LEG_INSET + r, hx - LEG_INSET - r):
        for y in (FRONT_PANEL_Y + LEG_INSET + r, hy - LEG_INSET - r):
            leg = manifold3d.Manifold.cylinder(LEG_HEIGHT + OVERLAP, r, circular_segments=LEG_SECTIONS)
            parts.append(leg.translate((x, y, 0.0)))
    # Cheeks at both ends of the keyboard (inset so that no face is coplanar with the cabinet's),
    # keys evenly between them with KEY_GAP on every side.
    top = LEDGE_Z[1]
    x_in = hx - LEG_INSET - CHEEK_WIDTH
    for xa, xb in ((-hx + LEG_INSET, -x_in), (x_in, hx - LEG_INSET)):
        parts.append(box((xa, KEY_FRONT_Y, top - SINK), (xb, UPPER_FRONT_Y + OVERLAP, CHEEK_TOP)))
    pitch = (2 * x_in - KEY_GAP) / KEY_COUNT
    for i in range(KEY_COUNT):
        xa = -x_in + KEY_GAP + i * pitch
        parts.append(box((xa, KEY_FRONT_Y, top - SINK), (xa + pitch - KEY_GAP, KEY_BACK_Y, KEY_TOP)))
    return parts


def build() -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(n, 3)`` m and faces ``(m, 3)`` of the piano, checked; raises SystemExit if broken."""
    solid = manifold3d.Manifold.batch_boolean(make_parts(), manifold3d.OpType.Add)
    out = solid.to_mesh()
    mesh = trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3], np.asarray(out.tri_verts), process=False)
    vertices, faces = canonical_arrays(mesh.vertices, mesh.faces)
    check = trimesh.Trimesh(vertices, faces, process=False)
    problems = mesh_problems(check)  # one watertight, outward body of a benchmark object's size
    if not np.allclose(check.extents, (WIDTH, DEPTH, HEIGHT), atol=10 ** -DECIMALS):
        problems.append(f"extents {check.extents}")
    if len(faces) > 4000:
        problems.append(f"{len(faces)} triangles")
    # Standing on its feet, the CoM (uniform density) must project inside the feet's convex hull.
    feet = vertices[vertices[:, 2] == 0.0, :2]
    hull = ConvexHull(feet)
    margin = -np.max(hull.equations[:, :2] @ check.center_mass[:2] + hull.equations[:, 2])
    if not margin > 0.05:
        problems.append(f"CoM only {margin:.3f} m inside the feet")
    if problems:
        raise SystemExit("toy piano mesh is broken: " + ", ".join(problems))
    return vertices, faces


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write an OBJ with fixed number formatting (1-based faces), atomically."""
    comment = "toy piano (pivot, data/objects/make_toy_piano.py); metres, object frame O"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(obj_text(vertices, faces, comment))
    tmp.replace(path)


def main(argv: list[str]) -> None:
    out = Path(argv[1]) if len(argv) > 1 else Path(__file__).with_name("toy_piano.obj")
    vertices, faces = build()
    write_obj(out, vertices, faces)
    print(f"{out}: {len(vertices)} vertices, {len(faces)} triangles")  # noqa: T201


if __name__ == "__main__":
    main(sys.argv)
