"""Read an object's mesh file as one watertight, outward-facing rigid body in metres (frame O).

Every way a file can be ambiguous is bad input with one line naming the file (issue 17):

- not a mesh (binary garbage, a truncated binary STL whose size disagrees with its triangle count,
  an unreadable file): refused, saying which;
- NaN, infinite or stray vertices (one vertex at 1e308 among a 0.3 m object): refused, naming the
  vertex, rather than scaled or dropped silently;
- the wrong unit (largest extent outside [MIN_EXTENT, MAX_EXTENT]): refused, suggesting ``--scale``;
- flat or open beyond repair (a zero-height box): refused with its extents;
- several bodies: parts whose bounding boxes touch or nest (an inner shell, a handle modelled as its
  own shell) are one rigid object; bodies apart from each other are refused unless all but the
  largest hold less than ``DEBRIS_VOLUME`` of the volume (scan debris), which are dropped with a
  warning saying how many and how much.

Numerical warnings of the checks (overflow, division by a zero volume) never reach the user.
"""

from __future__ import annotations

import logging
import struct
import warnings
from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse.csgraph import connected_components

from stages import tol
from stages.errors import InputError

log = logging.getLogger("pivot.mesh")

MESH_SUFFIXES = {".obj", ".stl", ".ply", ".off", ".glb", ".gltf"}
MAX_EXTENT = 5.0  # m: beyond this the mesh is surely in mm or cm
MIN_EXTENT = 0.01  # m
DEBRIS_VOLUME = 0.01  # fraction of the total volume below which separate bodies are debris
TOUCH = 1e-3  # m: bodies whose bounding boxes come this close are parts of one object


def load_mesh(path: str | Path, scale: float = 1.0) -> trimesh.Trimesh:
    """Load a mesh file as one watertight, outward-facing rigid body in metres (module docstring).

    Raises ``InputError`` (one line naming the file) for a missing, unreadable, empty, NaN-bearing,
    wrongly scaled, unrepairable, zero-volume or several-bodied mesh.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such mesh file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{path}: unsupported mesh format '{path.suffix}' (use OBJ, STL, PLY, OFF or GLB)")
    if not np.isfinite(scale) or scale <= 0:
        raise InputError(f"{path}: --scale must be a positive number (got {scale})")
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        loaded = _read(path)
        vertices = np.asarray(loaded.vertices, dtype=float) * scale
        _check_vertices(path, vertices, np.unique(np.asarray(loaded.faces)))
        mesh = trimesh.Trimesh(vertices, np.asarray(loaded.faces), process=True, validate=True)
        if len(mesh.faces) == 0:
            raise InputError(f"{path}: mesh has no non-degenerate triangles")
        if not mesh.is_watertight:
            trimesh.repair.fill_holes(mesh)
            if not mesh.is_watertight:
                open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
                raise InputError(f"{path}: mesh is not watertight ({open_edges} open edges) and cannot be repaired")
        if not mesh.is_winding_consistent:
            trimesh.repair.fix_winding(mesh)
        if not np.isfinite(mesh.volume) or abs(mesh.volume) < tol.zero * 1e3:
            e = mesh.extents
            raise InputError(f"{path}: mesh encloses zero volume (extents {e[0]:.3g} x {e[1]:.3g} x {e[2]:.3g} m)")
        if mesh.volume < 0:
            mesh.invert()
        return _one_body(path, mesh)


def _read(path: Path) -> trimesh.Trimesh:
    """The file's triangles; a file that is not a mesh of its suffix is refused in one line."""
    if path.suffix.lower() == ".stl":
        _check_stl(path)
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for bad files
        if isinstance(e, ImportError):  # a decoder trimesh falls back on for text it cannot parse
            raise InputError(f"{path}: cannot read mesh: not a valid {path.suffix.lstrip('.').upper()} file") from e
        raise InputError(f"{path}: cannot read mesh ({type(e).__name__}: {str(e).splitlines()[0][:120]})") from e
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise InputError(f"{path}: mesh is empty (no triangles)")
    return loaded


def _check_stl(path: Path) -> None:
    """An STL is ASCII (``solid`` ... text) or binary (84-byte header, then 50 bytes per triangle)."""
    data = path.read_bytes()
    if len(data) >= 84:
        n = struct.unpack("<I", data[80:84])[0]
        if len(data) == 84 + 50 * n:
            return
    if data.lstrip()[:5].lower() == b"solid":
        try:
            data.decode("ascii")
            return
        except UnicodeDecodeError:
            pass
    if len(data) < 84:
        raise InputError(f"{path}: not an STL file ({len(data)} bytes, and not ASCII STL)")
    raise InputError(f"{path}: not a valid STL file: not ASCII, and as binary STL its header gives {n} triangles "
                     f"({84 + 50 * n} bytes) but the file has {len(data)} bytes (truncated or not STL)")


def _check_vertices(path: Path, vertices: np.ndarray, used: np.ndarray) -> None:
    """Refuse NaN, infinite or stray vertices (of those the triangles ``used``) and a mesh in another
    unit than metres."""
    V = vertices[used]
    if not np.isfinite(V).all():
        raise InputError(f"{path}: mesh has NaN or infinite vertex coordinates")
    extent = float(np.max(np.ptp(V, axis=0)))
    if np.isfinite(extent) and MIN_EXTENT <= extent <= MAX_EXTENT:
        return
    centre = np.median(V, axis=0)
    d = np.max(np.abs(V - centre), axis=1)
    near = d <= MAX_EXTENT
    few = (~near).sum() <= max(1, 0.1 * len(V))
    if few and near.any() and not near.all():  # a few vertices far from all the others
        i = int(np.argmax(d))
        raise InputError(f"{path}: {int((~near).sum())} stray vertices lie over {MAX_EXTENT} m from the rest "
                         f"(vertex {used[i]} at {V[i][0]:.3g}, {V[i][1]:.3g}, {V[i][2]:.3g}); remove them")
    raise InputError(f"{path}: largest extent is {extent:g} m, outside [{MIN_EXTENT}, {MAX_EXTENT}] m; the mesh is "
                     f"taken in metres: pass --scale (e.g. --scale 0.001 for millimetres)")


def _one_body(path: Path, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The rigid object in ``mesh``: its connected shells grouped where their boxes touch or nest."""
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    k = int(labels.max()) + 1
    if k == 1:
        return mesh
    lo = np.full((k, 3), np.inf)
    hi = np.full((k, 3), -np.inf)
    tri = mesh.triangles
    np.minimum.at(lo, labels, tri.min(axis=1))
    np.maximum.at(hi, labels, tri.max(axis=1))
    touch = np.all((lo[:, None] <= hi[None] + TOUCH) & (lo[None] <= hi[:, None] + TOUCH), axis=2)
    n_bodies, body = connected_components(touch, directed=False)
    if n_bodies == 1:
        return mesh
    # Signed volume of each body from its triangles (divergence theorem), shells of a body summed.
    t = body[labels]
    v = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    volume = np.bincount(t, weights=v, minlength=n_bodies)
    big = int(np.argmax(volume))
    rest = float(volume.sum() - volume[big]) / float(volume.sum())
    if rest >= DEBRIS_VOLUME:
        sizes = ", ".join(f"{x * 1e3:.3g}" for x in np.sort(volume)[::-1][:4])
        raise InputError(f"{path}: mesh holds {n_bodies} separate bodies (volumes {sizes} L); pivot moves one "
                         f"rigid object: keep one body per file")
    log.warning("%s: dropped %d small separate bodies (%.2g%% of the volume); kept the largest", path,
                n_bodies - 1, 100 * rest)
    kept = mesh.submesh([np.flatnonzero(t == big)], append=True)
    return kept
