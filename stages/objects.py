"""Object families for the general-object benchmark (issue 13): one deterministic mesh generator each.

Every family's ``make()`` returns one watertight, outward-oriented, single-body triangle mesh in metres,
in the object frame O: z up, resting on z = 0 in its natural upright placement (on the face of its
convex hull it settles onto from its modelled pose), origin at the centre of its footprint (the
bounding rectangle of its vertical projection onto the table). The mesh is already canonical: vertices
rounded to ``DECIMALS`` (1e-6 m), merged and sorted, each face rotated to start at its smallest index
and the faces sorted, so that ``write_mesh`` writes the same bytes on every run whatever order a
boolean engine or a file loader emits. Largest extent 0.35-0.5 m, at most ``MAX_FACES`` triangles.

Solids (box, cabinet, drum, L and T blocks) are prisms extruded with ``manifold3d``; the organic ones
come from ``pybullet_data`` (duck, teddy, bunny: curved surfaces, few flat faces) and the toy piano is
the committed ``data/objects/toy_piano.obj``. ``python -m stages.objects OUT_DIR [NAME ...]`` writes
``OUT_DIR/<name>.obj`` for every family (or the named ones). ``data/objects/README.md`` tabulates them.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import manifold3d
import numpy as np
import pybullet_data
import trimesh
from scipy.spatial import ConvexHull

from stages import artifacts
from stages.errors import InputError, PivotError

#: Vertices are rounded to this many decimals of a metre (1 micrometre) in the canonical form.
DECIMALS = 6
#: Bounds every family's mesh must meet (issue 13): a largest extent (m) near the paper's 0.45 m piano,
#: and a triangle count that keeps ``pivot analyze`` well under a second.
EXTENT_RANGE = (0.35, 0.5)
MAX_FACES = 6000
PIANO = Path(__file__).resolve().parents[1] / "data" / "objects" / "toy_piano.obj"
#: Rotation of a y-up model (glTF, Blender and Stanford convention) to z up: Rx(+90 deg), (x, y, z) -> (x, -z, y).
R_ZUP_FROM_YUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: Each V-HACD hull of the teddy grows by this fraction about its centroid before the union: hulls that
#: only touch (lower and upper body, a foot, an ear: four bodies ungrown) then overlap and the union is
#: one body. 1% already joins them; 2% leaves room for the float32 vertices of the boolean engine.
TEDDY_HULL_GROWTH = 0.02
PYBULLET_DATA = "pybullet_data (ships with pybullet, zlib licence)"


@dataclass(frozen=True)
class ObjectFamily:
    """One benchmark object: its mesh generator and the physical figures a scene gives it.

    ``size`` is the approximate extent (m) along O's x, y, z of the mesh ``make()`` returns (to the
    millimetre, for docs and tests); ``mass`` (kg) and ``friction`` (Coulomb coefficient) are the
    defaults a benchmark scene uses; ``why`` says in one line what capability of the planner the object
    exercises and ``source`` where the geometry comes from and under which licence.
    """

    name: str
    mass: float
    friction: float
    size: tuple[float, float, float]
    why: str
    source: str
    make: Callable[[], trimesh.Trimesh]


# ------------------------------------------------------------------------------------ canonical form
def canonical_arrays(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical vertices ``(n, 3)`` m and faces ``(m, 3)``: rounded, merged, sorted, winding kept.

    Vertices are rounded to ``DECIMALS`` and merged when equal, then sorted lexicographically; faces
    that collapse are dropped, each face is cyclically shifted (keeping its orientation) to start at its
    smallest index, and the faces are sorted. Two meshes that differ only in vertex order, face order,
    face start or sub-micrometre noise get the same arrays.
    """
    v = np.round(np.asarray(vertices, dtype=float), DECIMALS) + 0.0  # + 0.0 turns -0.0 into 0.0
    v_unique, inverse = np.unique(v, axis=0, return_inverse=True)
    f = inverse.reshape(-1)[np.asarray(faces)]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    shift = np.argmin(f, axis=1)
    f = np.take_along_axis(f, (shift[:, None] + np.arange(3)) % 3, axis=1)
    f = f[np.lexsort(f.T[::-1])]
    # Drop vertices no face uses any more (a collapsed face can orphan one), renumbering in order.
    used = np.unique(f)
    return v_unique[used], np.searchsorted(used, f)


def obj_text(vertices: np.ndarray, faces: np.ndarray, comment: str) -> str:
    """Wavefront OBJ text with fixed number formatting: one ``# comment`` line, ``v`` lines, 1-based ``f``."""
    lines = [f"# {comment}"]
    lines += [f"v {x:.{DECIMALS}f} {y:.{DECIMALS}f} {z:.{DECIMALS}f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def canonical_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` in canonical form (see ``canonical_arrays``), unprocessed so that no order changes."""
    v, f = canonical_arrays(mesh.vertices, mesh.faces)
    return trimesh.Trimesh(v, f, process=False)


def mesh_problems(mesh: trimesh.Trimesh) -> list[str]:
    """What keeps ``mesh`` from being a benchmark object (empty when it is one)."""
    problems = []
    if not mesh.is_watertight:
        problems.append("not watertight")
    if not mesh.is_winding_consistent:
        problems.append("winding not consistent")
    if mesh.body_count != 1:
        problems.append(f"{mesh.body_count} bodies")
    if not mesh.volume > 0:
        problems.append(f"volume {mesh.volume:g} m^3 (inward normals?)")
    extent = float(mesh.extents.max())
    if not EXTENT_RANGE[0] <= extent <= EXTENT_RANGE[1]:
        problems.append(f"largest extent {extent:.3f} m outside {EXTENT_RANGE} m")
    if len(mesh.faces) > MAX_FACES:
        problems.append(f"{len(mesh.faces)} triangles > {MAX_FACES}")
    return problems


# ------------------------------------------------------------------------------------------ placing
def settle(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Rotate ``mesh`` onto the convex-hull face it comes to rest on from its current pose (z up).

    Quasi-static rolling on a flat table: the face below is the hull face through which the vertical
    ray from the CoM (uniform density) leaves the hull; while that face's normal is not the downward
    direction, the object tips onto it. Each tip lowers the CoM (its distance to the new face is
    shorter than to the old one along the ray), so this ends on a stable face. Coplanar hull triangles
    share their plane, so resting on any of them is resting on the merged face. The last rotation is
    the smallest one that takes that face's outward normal onto -z; a mesh already resting on a face
    is returned unrotated.
    """
    hull = ConvexHull(mesh.vertices)
    n, d = hull.equations[:, :3], hull.equations[:, 3]  # n . p + d <= 0 inside, |n| = 1
    height = -(n @ mesh.center_mass + d)  # distance (m) of the CoM to each face plane, > 0
    down = np.array([0.0, 0.0, -1.0])
    for _ in range(len(n) + 1):
        cos = n @ down
        t = np.where(cos > 1e-12, height / np.where(cos > 1e-12, cos, 1.0), np.inf)
        face = int(np.argmin(t))
        if n[face] @ down > 1.0 - 1e-12:
            break
        down = n[face]
    if down[2] < -1.0 + 1e-12:
        return mesh.copy()
    # The smallest rotation taking ``down`` onto -z: about their common perpendicular (x if opposite).
    axis = np.cross(down, [0.0, 0.0, -1.0])
    axis = axis if np.linalg.norm(axis) > 1e-12 else np.array([1.0, 0.0, 0.0])
    angle = np.arccos(np.clip(-down[2], -1.0, 1.0))
    return mesh.copy().apply_transform(trimesh.transformations.rotation_matrix(angle, axis))


def place(mesh: trimesh.Trimesh, extent: float | None = None) -> trimesh.Trimesh:
    """Scale ``mesh`` uniformly to a largest extent of ``extent`` m (if given), then translate it so that
    it stands on z = 0 with its footprint's bounding rectangle centred on the origin of O."""
    out = mesh.copy()
    if extent is not None:
        out.apply_scale(extent / float(out.extents.max()))
    lo, hi = out.bounds
    out.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return out


# ----------------------------------------------------------------------------------------- builders
def _from_manifold(solid: manifold3d.Manifold) -> trimesh.Trimesh:
    """Triangle mesh of a manifold3d solid (vertices as the boolean engine emits them)."""
    out = solid.to_mesh()
    return trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3], np.asarray(out.tri_verts), process=False)


def _to_manifold(mesh: trimesh.Trimesh) -> manifold3d.Manifold:
    """manifold3d solid of a closed, outward-oriented triangle mesh."""
    solid = manifold3d.Manifold(manifold3d.Mesh(np.asarray(mesh.vertices, dtype=np.float32),
                                                np.asarray(mesh.faces, dtype=np.uint32)))
    if solid.status() != manifold3d.Error.NoError:
        raise PivotError(f"objects: a part is not an oriented 2-manifold ({solid.status()})")
    return solid


def prism(outline: np.ndarray, height: float) -> trimesh.Trimesh:
    """Right prism: the counter-clockwise polygon ``outline`` (n, 2) m in the xy plane swept up ``height`` m."""
    return _from_manifold(manifold3d.CrossSection([np.asarray(outline, dtype=float)]).extrude(height))


def regular_polygon(sides: int, radius: float) -> np.ndarray:
    """Counter-clockwise ``(sides, 2)`` vertices (m) of a regular polygon of circumradius ``radius``,
    the first on +x."""
    a = 2 * np.pi * np.arange(sides) / sides
    return radius * np.stack([np.cos(a), np.sin(a)], axis=1)


def rectangle(sx: float, sy: float) -> np.ndarray:
    """Counter-clockwise ``(4, 2)`` corners (m) of an ``sx`` by ``sy`` rectangle centred on the origin."""
    return np.array([(-sx / 2, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2), (-sx / 2, sy / 2)])


def load_pybullet_mesh(filename: str) -> trimesh.Trimesh:
    """A mesh of ``pybullet_data`` as its file has it, vertices merged by position (the duck's file splits
    them at its texture seams, which leaves it open as shipped)."""
    path = Path(pybullet_data.getDataPath()) / filename
    if not path.is_file():
        raise InputError(f"{path}: missing from pybullet_data (reinstall pybullet)")
    raw = trimesh.load(path, force="mesh", process=False)
    return trimesh.Trimesh(np.asarray(raw.vertices, dtype=float), np.asarray(raw.faces), process=True)


def union_of_parts(mesh: trimesh.Trimesh, growth: float) -> trimesh.Trimesh:
    """One solid from a mesh made of several closed parts (convex hulls): each part scaled by
    ``1 + growth`` about its centroid, then all unioned with manifold3d."""
    solids = []
    for part in mesh.split(only_watertight=False):
        if part.volume < 0:
            part.invert()
        c = part.centroid
        part.vertices = (part.vertices - c) * (1.0 + growth) + c
        solids.append(_to_manifold(part))
    return _from_manifold(manifold3d.Manifold.batch_boolean(solids, manifold3d.OpType.Add))


# ------------------------------------------------------------------------------------------ families
def build_toy_piano() -> trimesh.Trimesh:
    """The paper's toy piano as committed (made by ``data/objects/make_toy_piano.py``), unchanged."""
    if not PIANO.is_file():
        raise InputError(f"{PIANO}: the toy piano mesh is missing (write it with data/objects/make_toy_piano.py)")
    return trimesh.load(PIANO, force="mesh", process=False)


def build_box() -> trimesh.Trimesh:
    """A 0.40 x 0.30 x 0.25 m box."""
    return place(prism(rectangle(0.40, 0.30), 0.25))


def build_cabinet() -> trimesh.Trimesh:
    """A tall, narrow 0.22 x 0.18 x 0.48 m box."""
    return place(prism(rectangle(0.22, 0.18), 0.48))


def build_drum() -> trimesh.Trimesh:
    """A regular 20-sided prism, circumradius 0.18 m (0.36 m across its corners), 0.30 m tall."""
    return place(prism(regular_polygon(20, 0.18), 0.30))


def build_l_block() -> trimesh.Trimesh:
    """An upright L, 0.20 m deep (y): a 0.40 x 0.12 m foot (x, z) with a 0.12 m wide post at -x up to 0.36 m."""
    profile = np.array([(-0.20, 0.0), (0.20, 0.0), (0.20, 0.12), (-0.08, 0.12), (-0.08, 0.36), (-0.20, 0.36)])
    solid = prism(profile, 0.20)  # drawn in x, z and extruded along z, then stood up: z -> -y, y -> z
    solid.vertices = solid.vertices @ R_ZUP_FROM_YUP.T
    return place(solid)


def build_t_block() -> trimesh.Trimesh:
    """A T lying flat (as in Push-T), 0.15 m tall: a 0.40 x 0.10 m bar at +y on a 0.10 x 0.30 m stem."""
    outline = np.array([(-0.05, -0.20), (0.05, -0.20), (0.05, 0.10), (0.20, 0.10), (0.20, 0.20), (-0.20, 0.20),
                        (-0.20, 0.10), (-0.05, 0.10)])
    return place(prism(outline, 0.15))


def build_pybullet_object(filename: str, extent: float, hull_growth: float | None = None) -> trimesh.Trimesh:
    """A y-up ``pybullet_data`` model stood up (z up), settled on the table and scaled to ``extent`` m.

    With ``hull_growth`` the file is a set of convex hulls, unioned into one solid first (``union_of_parts``).
    The duck and the bunny settle within 0.1 deg of their modelled pose; the teddy, whose modelled pose
    is not stable, leans 33 deg onto three points of its underside.
    """
    mesh = load_pybullet_mesh(filename)
    if hull_growth is not None:
        mesh = union_of_parts(mesh, hull_growth)
    mesh.vertices = mesh.vertices @ R_ZUP_FROM_YUP.T
    return place(settle(mesh), extent)


def refine(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """``mesh`` with exactly ``faces`` triangles (``faces - len(mesh.faces)`` even) and the same surface:
    a fine CAD or scan stand-in for the scale benchmark (issue 20).

    Midpoint (4-to-1) subdivision while the count stays at or below ``faces``, then the largest
    triangles (ties by index) are split 1-to-3 at their centroid, two triangles more each; both keep
    the mesh watertight and every point where it was (to the canonical 1 µm rounding). Canonical form
    (``canonical_mesh``), so that the same mesh and count give the same bytes.
    """
    v, f = np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)
    if faces < len(f) or (faces - len(f)) % 2:
        raise InputError(f"refine: {faces} triangles cannot be reached from {len(f)} by splitting")
    while 4 * len(f) <= faces:
        v, f = trimesh.remesh.subdivide(v, f)
    while len(f) < faces:  # at most twice: each round can split every triangle
        k = min((faces - len(f)) // 2, len(f))
        area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        split = np.lexsort((np.arange(len(f)), -np.round(area, 15)))[:k]
        c = len(v) + np.arange(k)
        a, b, d = f[split, 0], f[split, 1], f[split, 2]
        v = np.concatenate([v, v[f[split]].mean(axis=1)])
        new = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1), np.stack([d, a, c], 1)])
        f = np.concatenate([np.delete(f, split, axis=0), new])
    return canonical_mesh(trimesh.Trimesh(v, f, process=False))


def _finished(name: str, build: Callable[[], trimesh.Trimesh]) -> trimesh.Trimesh:
    """``build()`` in canonical form, checked; raises ``PivotError`` naming the family if it is broken."""
    mesh = canonical_mesh(build())
    problems = mesh_problems(mesh)
    if problems:
        raise PivotError(f"objects: the {name} mesh is broken: {', '.join(problems)}")
    return mesh


def _family(name: str, mass: float, size: tuple[float, float, float], why: str, source: str,
            build: Callable[[], trimesh.Trimesh], friction: float = 0.5) -> ObjectFamily:
    """An ``ObjectFamily`` whose ``make`` returns ``build()`` in canonical form, checked."""
    return ObjectFamily(name, mass, friction, size, why, source, functools.partial(_finished, name, build))


SOLID = "generated by stages/objects.py (pivot); no third-party content"
FAMILIES: dict[str, ObjectFamily] = {f.name: f for f in [
    _family("toy_piano", 3.1, (0.425, 0.205, 0.45),
            "the paper's object (§6): the reference every other family is compared with",
            "data/objects/toy_piano.obj, built by data/objects/make_toy_piano.py (pivot) from the paper's "
            "published dimensions; no third-party content", build_toy_piano),
    _family("box", 3.0, (0.40, 0.30, 0.25),
            "the easy case: eight pivot vertices, six stable faces, many parallel face pairs", SOLID, build_box),
    _family("cabinet", 4.0, (0.22, 0.18, 0.48),
            "tall and narrow: its CoM stands high over a small footprint, so it tips easily", SOLID, build_cabinet),
    _family("drum", 3.0, (0.36, 0.36, 0.30),
            "a 20-sided prism: many pivot vertices and shallow 18 deg tumbles from side face to side face",
            SOLID, build_drum),
    _family("l_block", 3.5, (0.40, 0.20, 0.36),
            "non-convex, CoM off the footprint centre: unstable hull faces and uneven pivot loads",
            SOLID, build_l_block),
    _family("t_block", 3.5, (0.40, 0.40, 0.15),
            "flat and non-convex (Push-T shape): concave corners the balls must avoid, CoM off centre",
            SOLID, build_t_block),
    _family("duck", 3.0, (0.45, 0.313, 0.419),
            "smooth and curved: few flat facets for contacts, a rounded base with many hull faces",
            f"duck.obj of {PYBULLET_DATA}: the COLLADA/glTF sample model 'Duck', (c) Sony Computer "
            "Entertainment Inc., SCEA Shared Source License 1.0; vertices merged at its texture seams",
            functools.partial(build_pybullet_object, "duck.obj", 0.45)),
    _family("teddy", 3.0, (0.423, 0.393, 0.45),
            "an organic outline with head, limbs and ears: a leaning rest and few antipodal contact pairs",
            f"teddy2_VHACD_CHs.obj of {PYBULLET_DATA}: 15 V-HACD convex hulls of a teddy bear whose origin "
            "pybullet_data does not state; hulls grown 2% and unioned with manifold3d",
            functools.partial(build_pybullet_object, "teddy2_VHACD_CHs.obj", 0.45, TEDDY_HULL_GROWTH)),
    _family("bunny", 3.0, (0.188, 0.40, 0.292),
            "a scanned organic shape (coarse): narrow, curved, with ears that stick out",
            f"bunny.obj of {PYBULLET_DATA}: a coarse (902-triangle) Stanford Bunny, Stanford 3D Scanning "
            "Repository (free for research use with credit to Stanford)",
            functools.partial(build_pybullet_object, "bunny.obj", 0.40)),
]}


def make_mesh(name: str) -> trimesh.Trimesh:
    """The canonical mesh (frame O, metres) of the family ``name``; ``InputError`` for an unknown name."""
    if name not in FAMILIES:
        raise InputError(f"unknown object family '{name}' (known: {', '.join(FAMILIES)})")
    return FAMILIES[name].make()


def write_mesh(name: str, path: str | Path) -> Path:
    """Write family ``name``'s canonical mesh as an OBJ at ``path`` (atomically); returns the path.

    The bytes depend only on the mesh: every rerun (and every machine with the same inputs and library
    versions) writes the same file, so Make and golden copies can track it.
    """
    return _write_obj(name, make_mesh(name), Path(path))


def _write_obj(name: str, mesh: trimesh.Trimesh, path: Path) -> Path:
    """Write the canonical ``mesh`` of family ``name`` to ``path`` atomically."""
    text = obj_text(mesh.vertices, mesh.faces, f"{name} (pivot, stages/objects.py); metres, object frame O, z up")
    with artifacts.atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def main(argv: list[str] | None = None) -> int:
    """``python -m stages.objects OUT_DIR [NAME ...]``: write ``OUT_DIR/<name>.obj`` for each family."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0].startswith("-"):
        sys.stderr.write(f"usage: python -m stages.objects OUT_DIR [NAME ...]  (names: {', '.join(FAMILIES)})\n")
        return 2
    out_dir, names = Path(args[0]), args[1:] or list(FAMILIES)
    try:
        for name in names:
            mesh = make_mesh(name)
            path = _write_obj(name, mesh, out_dir / f"{name}.obj")
            sys.stdout.write(f"{path}: {len(mesh.faces)} triangles, extents {np.round(mesh.extents, 3).tolist()} m\n")
    except PivotError as e:
        sys.stderr.write(f"error: {e}\n")
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
