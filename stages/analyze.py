"""Object analysis (§4.1, Fig. 4, Table 1): hull, superimposed segments, placements, contacts, pairs.

Works on one watertight triangle mesh in its own frame ``O`` (metres). Outputs, all in ``O``:

- **hull** (§4.1): the convex hull's corner vertices (pivot candidates: incident to three or more
  non-coplanar hull faces) and its edges between two non-coplanar hull faces (tumble axes), with the
  angle between the two faces' normals (how far a tumble about that edge turns the object).
- **segments** (§4.1, superimposed segments [4]): region growing from seed triangles taken in order
  of decreasing area; a triangle joins the seed's facet when it is connected to the seed through
  triangles whose normals are all within ``segment_angle_deg`` of the *seed's* normal. A new seed is
  any triangle no facet covers yet, but growth ignores coverage, so facets overlap.
- **placements**: the faces of the hull with coplanar triangles merged. Each rests the object on the
  table with the resting transform ``X_TO`` (face normal onto −z, face on z = 0, CoM projection at the
  origin); it is SP when the CoM's vertical projection lies inside the support polygon by at least
  ``sp_margin`` (signed distance to the polygon boundary, recorded as ``margin``).
- **contacts** (§4.1): points sampled uniformly by area over the whole surface and thinned to a
  minimum spacing. On a flat facet (large enough to touch) a point is distributed onto every such
  facet holding its triangle, with the facet's normal, and dropped nearer than ``boundary_margin``
  to the facet's boundary. Elsewhere (curved surfaces) it is one contact of its own, ``facet_id``
  -1, whose normal is averaged over the ball's footprint (a disk of ``boundary_margin``), dropped
  when that footprint reaches a flat facet, and kept only if a pair uses it. Either is dropped
  when a ball of ``ball_radius`` touching there would intersect the object (python-fcl).
- **pairs** (§4.2): an antipodal squeeze, the line between two contacts inside the friction cone at
  both, the segment between them inside the object. Two contacts on flat facets pair when the
  facets' normals are opposite within ``pair_angle_deg`` (the paper's rule; each keeps its best
  partner); a pair with a curved contact, or two flat ones that rule did not pair (a slanted
  squeeze across a block, our addition: its couple helps lift a pivot's far side), is judged by the
  contacts' own normals and the cone of ``cone_angle_deg`` (Nguyen's antipodal condition), the
  candidates spread over the object by farthest-point sampling up to ``max_pairs``. Pairs are
  unordered.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import fcl
import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from stages import artifacts, fclmesh, se3, stagelog, tol
from stages.artifacts import Field
from stages.errors import InputError
from stages.meshfile import load_mesh


@dataclass(frozen=True)
class Params:
    """Analysis parameters (lengths in m, angles in degrees as the option names say)."""

    #: Region growing joins triangles whose normal is within this angle of the seed's (§4.1).
    segment_angle_deg: float = 20.0
    #: Facets smaller than this (m^2) carry no contact points: a 4 cm ball needs room.
    min_facet_area: float = 1e-3
    #: Minimum distance between sampled contact points (m).
    sample_spacing: float = 0.035
    #: Raw area-uniform samples per m^2 before thinning to ``sample_spacing``.
    sample_density: float = 6000.0
    #: Contacts nearer than this to their facet's boundary are dropped (m).
    boundary_margin: float = 0.01
    #: Radius of the ball end-effector (m); the paper's ball is 4 cm across.
    ball_radius: float = 0.02
    #: Facet pairs (§4.2): paired flat facets' normals opposite within this angle, the squeeze line
    #: within it of both contact normals (the paper's rule; the flat-face pairs as they were).
    pair_angle_deg: float = 15.0
    #: Cone pairs: half-angle of the friction cone the squeeze line must lie in at both contacts,
    #: atan(0.8 x 0.5): the object's friction is a scene parameter (0.5 in every scene), taken here
    #: with a safety factor of 0.8 on mu; grasp stability (§4.3) later checks the scene's own mu.
    cone_angle_deg: float = 21.8
    #: A contact facet is flat when every triangle's normal is within this angle of the facet's: a
    #: planar panel's agree to rounding, a curved surface's facets spread up to ``segment_angle_deg``.
    flat_facet_deg: float = 1.0
    #: At most this many pairs: facet pairs are all kept, cone pairs fill the rest (grasp refinement
    #: downstream costs poses x pairs; the toy piano has 122 facet pairs).
    max_pairs: int = 150
    #: A placement is SP when the CoM projection is at least this far inside its support polygon (m).
    sp_margin: float = 0.005
    #: Hull faces whose normals differ by less than this angle merge into one placement face.
    hull_coplanar_deg: float = 0.5
    #: Seed of the sampling generator.
    seed: int = 0


@dataclass(frozen=True)
class Analysis:
    """Everything ``compute`` finds; struct-of-arrays tables keyed by column name (frame O)."""

    hull: dict
    segments: dict
    placements: dict
    contacts: dict
    pairs: dict
    summary: dict
    timings: dict


# --------------------------------------------------------------------------------------------- mesh
def mass_properties(mesh: trimesh.Trimesh, mass: float) -> dict:
    """CoM ``p_OCm (3,)`` and inertia about the CoM ``I_Cm (3, 3)`` (kg m^2) for uniform density."""
    density = mass / mesh.volume
    props = trimesh.triangles.mass_properties(mesh.triangles, density=density)
    return {"com": np.asarray(props.center_mass), "inertia": np.asarray(props.inertia), "volume": mesh.volume}


# --------------------------------------------------------------------------------------------- hull
class _HullFaces(NamedTuple):
    """The convex hull's triangles merged into coplanar faces (the placement faces), frame O:
    ``group (F,)`` each triangle's face, ``area (G,)`` m^2, unit outward ``normal (G, 3)`` and
    ``vg (K, 2)`` the distinct (hull vertex, face) incidences, sorted by vertex."""

    group: np.ndarray
    area: np.ndarray
    normal: np.ndarray
    vg: np.ndarray


def analyze_hull(mesh: trimesh.Trimesh, com: np.ndarray, params: Params) -> tuple[dict, dict]:
    """Hull vertices/edges (pivot and tumble candidates) and placements, frame O.

    Returns ``(hull, placements)`` column dicts.
    """
    hull = mesh.convex_hull
    faces = _merged_faces(hull, params)
    hull_cols, remap = _hull_features(hull, faces)
    return hull_cols, _placements(np.asarray(hull.vertices), faces, remap, com, params)


def _merged_faces(hull: trimesh.Trimesh, params: Params) -> _HullFaces:
    """Adjacent hull triangles whose normals agree within ``hull_coplanar_deg`` merged into faces."""
    F, N, adj = np.asarray(hull.faces), np.asarray(hull.face_normals), np.asarray(hull.face_adjacency)
    cos_tol = np.cos(np.radians(params.hull_coplanar_deg))
    same = np.einsum("ij,ij->i", N[adj[:, 0]], N[adj[:, 1]]) > cos_tol
    graph = sp.coo_matrix((np.ones(same.sum()), (adj[same, 0], adj[same, 1])), shape=(len(F), len(F)))
    _, group = connected_components(graph, directed=False)
    group = _renumber_by_first(group)
    n_groups = group.max() + 1
    areas = hull.area_faces
    g_area = np.bincount(group, weights=areas, minlength=n_groups)
    g_normal = np.zeros((n_groups, 3))
    np.add.at(g_normal, group, N * areas[:, None])
    g_normal /= np.linalg.norm(g_normal, axis=1, keepdims=True)
    vg = np.unique(np.stack([F.ravel(), np.repeat(group, 3)], axis=1), axis=0)
    return _HullFaces(group, g_area, g_normal, vg)


def _hull_features(hull: trimesh.Trimesh, faces: _HullFaces) -> tuple[dict, np.ndarray]:
    """The hull table: corner vertices (incident to >= 3 merged faces; the pivot candidates) then
    edges between two merged faces (the tumble candidates) with the angle between their normals.
    Returns its columns and ``remap (V,)``, hull vertex -> corner id (-1: not a corner)."""
    V, adj, group, g_normal = np.asarray(hull.vertices), np.asarray(hull.face_adjacency), faces.group, faces.normal
    corner = np.bincount(faces.vg[:, 0], minlength=len(V)) >= 3
    edge_mask = group[adj[:, 0]] != group[adj[:, 1]]
    e_verts = np.sort(np.asarray(hull.face_adjacency_edges)[edge_mask], axis=1)
    e_faces = np.stack([group[adj[edge_mask, 0]], group[adj[edge_mask, 1]]], axis=1)
    e_angle = np.arccos(np.clip(np.einsum("ij,ij->i", g_normal[e_faces[:, 0]], g_normal[e_faces[:, 1]]), -1, 1))
    order = np.lexsort((e_verts[:, 1], e_verts[:, 0]))
    e_verts, e_faces, e_angle = e_verts[order], np.sort(e_faces[order], axis=1), e_angle[order]
    # Hull vertex ids are renumbered to the corner list; edges keep only corner endpoints' ids.
    corner_ids = np.flatnonzero(corner)
    remap = -np.ones(len(V), dtype=np.int64)
    remap[corner_ids] = np.arange(len(corner_ids))
    n_v, n_e = len(corner_ids), len(e_verts)
    pv = V[corner_ids]
    ea, eb = V[e_verts[:, 0]], V[e_verts[:, 1]]
    none = -np.ones(n_v, dtype=np.int64)
    cols = {
        "hull_id": np.arange(n_v + n_e),
        "kind": np.array(["vertex"] * n_v + ["edge"] * n_e),
        "v0": np.concatenate([np.arange(n_v), remap[e_verts[:, 0]]]),
        "v1": np.concatenate([none, remap[e_verts[:, 1]]]),
        **{f"{c}0": np.concatenate([pv[:, i], ea[:, i]]) for i, c in enumerate("xyz")},
        **{f"{c}1": np.concatenate([pv[:, i], eb[:, i]]) for i, c in enumerate("xyz")},
        "face_a": np.concatenate([none, e_faces[:, 0]]),
        "face_b": np.concatenate([none, e_faces[:, 1]]),
        "angle": np.concatenate([np.zeros(n_v), e_angle]),
    }
    return cols, remap


def _placements(V: np.ndarray, faces: _HullFaces, remap: np.ndarray, com: np.ndarray, params: Params) -> dict:
    """One placement per merged face: its resting pose ``X_TO``, support polygon, CoM margin (SP when
    at least ``sp_margin``), CoM height and support corners (ids of :func:`_hull_features`).

    Each face's vertices are rotated into its table frame T (face on z = 0, outward normal down), then
    ordered by angle about their centroid: a convex face's vertices are all extreme, so that order is
    its counter-clockwise support polygon."""
    g_normal, n_groups = faces.normal, len(faces.area)
    R = se3.rotation_between(g_normal, np.array([0.0, 0.0, -1.0]))  # (G, 3, 3) R_TO
    pg, pv_id = faces.vg[:, 1], faces.vg[:, 0]  # (group, hull vertex) pairs, sorted by vertex
    p_T = np.einsum("kij,kj->ki", R[pg], V[pv_id])
    com_T = np.einsum("gij,j->gi", R, com)
    counts = np.bincount(pg, minlength=n_groups)
    z_mean = np.bincount(pg, weights=p_T[:, 2], minlength=n_groups) / counts
    shift = np.stack([-com_T[:, 0], -com_T[:, 1], -z_mean], axis=1)
    X_TO = se3.make_transform(R, shift)
    xy = p_T[:, :2] + shift[pg, :2]
    centre = np.stack([np.bincount(pg, weights=xy[:, i], minlength=n_groups) for i in (0, 1)], axis=1)
    centre /= counts[:, None]
    ang = np.arctan2(*(xy - centre[pg])[:, ::-1].T)
    order = np.lexsort((ang, pg))
    pg, pv_id, xy = pg[order], pv_id[order], xy[order]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    nxt = np.arange(len(pg)) + 1
    nxt[np.cumsum(counts) - 1] = starts  # wrap to each polygon's first vertex
    margins = _polygon_margins(xy, xy[nxt], pg, n_groups)
    return {
        "placement_id": np.arange(n_groups),
        "nx": g_normal[:, 0], "ny": g_normal[:, 1], "nz": g_normal[:, 2],
        "area": faces.area,
        **se3.columns_from_matrix(X_TO),
        "stable": margins >= params.sp_margin,
        "margin": margins,
        "com_height": com_T[:, 2] + shift[:, 2],
        "support_vertices": [np.sort(v[v >= 0]) for v in np.split(remap[pv_id], np.cumsum(counts)[:-1])],
        "polygon": [p.ravel() for p in np.split(xy, np.cumsum(counts)[:-1])],
    }


def _renumber_by_first(labels: np.ndarray) -> np.ndarray:
    """Relabel so labels appear in increasing order of first occurrence (deterministic ids)."""
    _, first = np.unique(labels, return_index=True)
    order = np.argsort(first)
    new = np.empty_like(order)
    new[order] = np.arange(len(order))
    return new[labels]


def _polygon_margins(a: np.ndarray, b: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """Signed distance ``(G,)`` from the origin to CCW convex polygons given as edges a→b per group.

    Positive inside (distance to the nearest edge line), negative outside (minus the distance to
    the nearest edge segment). A polygon with fewer than three vertices has no inside.
    """
    e = b - a
    length = np.linalg.norm(e, axis=1)
    ok = length > tol.zero
    inward = np.stack([-e[:, 1], e[:, 0]], axis=1) / np.where(ok, length, 1.0)[:, None]
    side = np.where(ok, np.einsum("ij,ij->i", -a, inward), np.inf)
    t = np.clip(np.einsum("ij,ij->i", -a, e) / np.maximum(length**2, tol.zero), 0, 1)
    seg_dist = np.linalg.norm(a + t[:, None] * e, axis=1)
    inside_d = np.full(n_groups, np.inf)
    np.minimum.at(inside_d, group, side)
    outside_d = np.full(n_groups, np.inf)
    np.minimum.at(outside_d, group, seg_dist)
    n_vert = np.bincount(group, minlength=n_groups)
    inside = (inside_d >= 0) & (n_vert >= 3)
    return np.where(inside, inside_d, -outside_d)


# ----------------------------------------------------------------------------------------- segments
def superimposed_segments(mesh: trimesh.Trimesh, params: Params) -> dict:
    """Superimposed segments (§4.1): overlapping facets grown from seeds by normal difference.

    Returns columns ``facet_id, seed, triangles (list), nx ny nz, area, cx cy cz, boundary (list of
    vertex-id pairs, flattened)``; ``contact_surface`` marks facets with area >= ``min_facet_area``.
    """
    normals = np.asarray(mesh.face_normals)
    areas = np.asarray(mesh.area_faces)
    adj = np.asarray(mesh.face_adjacency)
    n_f = len(normals)
    cos_t = np.cos(np.radians(params.segment_angle_deg))
    seeds = np.lexsort((np.arange(n_f), -np.round(areas, 12)))  # largest first, ties by index
    neighbors = _face_neighbors(adj, n_f)
    covered = np.zeros(n_f, dtype=bool)
    facets, seed_of = [], []
    for s in seeds:  # one iteration per facet: tens to a few hundred
        if covered[s]:
            continue
        similar = normals @ normals[s] > cos_t
        similar = np.append(similar, False)  # index -1 pads the neighbour table
        similar[s] = True
        members = _grow(s, similar, neighbors)
        covered[members] = True
        facets.append(members)
        seed_of.append(s)
    tri_area = [areas[m] for m in facets]
    f_area = np.array([a.sum() for a in tri_area])
    f_normal = np.array([(normals[m] * a[:, None]).sum(0) for m, a in zip(facets, tri_area, strict=True)])
    f_normal /= np.linalg.norm(f_normal, axis=1, keepdims=True)
    centers = np.asarray(mesh.triangles_center)
    f_centroid = np.array([(centers[m] * a[:, None]).sum(0) / a.sum() for m, a in zip(facets, tri_area, strict=True)])
    boundary = [_facet_boundary(mesh.faces[m]) for m in facets]
    return {
        "facet_id": np.arange(len(facets)),
        "seed": np.array(seed_of, dtype=np.int64),
        "triangles": [np.sort(m) for m in facets],
        "nx": f_normal[:, 0], "ny": f_normal[:, 1], "nz": f_normal[:, 2],
        "area": f_area,
        "cx": f_centroid[:, 0], "cy": f_centroid[:, 1], "cz": f_centroid[:, 2],
        "contact_surface": f_area >= params.min_facet_area,
        "boundary": [b.ravel() for b in boundary],
    }


def _face_neighbors(adj: np.ndarray, n_f: int) -> np.ndarray:
    """Neighbour table ``(n_f, k)`` of face ids from face adjacency pairs, padded with -1."""
    both = np.concatenate([adj, adj[:, ::-1]])
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    counts = np.bincount(both[:, 0], minlength=n_f)
    k = max(int(counts.max()) if len(counts) else 0, 1)
    table = -np.ones((n_f, k), dtype=np.int64)
    rank = np.arange(len(both)) - np.repeat(np.cumsum(counts) - counts, counts)
    table[both[:, 0], rank] = both[:, 1]
    return table


def _grow(seed: int, allowed: np.ndarray, neighbors: np.ndarray) -> np.ndarray:
    """Sorted face ids reachable from ``seed`` through faces with ``allowed`` (breadth first)."""
    visited = np.zeros(len(allowed), dtype=bool)
    visited[seed] = True
    visited[-1] = True  # the padding id never joins
    frontier = np.array([seed])
    while len(frontier):
        cand = neighbors[frontier].ravel()
        cand = np.unique(cand[allowed[cand] & ~visited[cand]])
        visited[cand] = True
        frontier = cand
    visited[-1] = False
    return np.flatnonzero(visited[:-1])


def _facet_boundary(faces: np.ndarray) -> np.ndarray:
    """Vertex-id pairs ``(k, 2)`` of the edges used by exactly one triangle of ``faces``."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    return uniq[counts == 1]


# ----------------------------------------------------------------------------------------- contacts
def sample_contacts(mesh: trimesh.Trimesh, segments: dict, params: Params) -> dict:
    """Contact points (§4.1): even sampling over the surface, then facet contacts and curved contacts.

    - **facet contacts** (the paper's): each sample on a flat contact facet (``_flat_facets``) is
      distributed onto every such facet holding its triangle, and dropped nearer than
      ``boundary_margin`` to that facet's boundary; its normal is its triangle's (the facet's).
    - **curved contacts**: each sample on no flat contact facet is one contact with ``facet_id = -1``
      and its own normal: the area-weighted normal of the surface under the ball's footprint, a disk
      of ``boundary_margin`` (``footprint``), so that a faceted mesh's noise averages out. It is
      dropped when that footprint reaches a flat contact facet (the boundary margin, seen from the
      curved side: a ball there would also touch the flat face's edge).
    - both: dropped when a ball of ``ball_radius`` touching there (centre p + r n, where grasping
      puts it) intersects the object; on a curved contact this also refuses a crease, whose averaged
      normal tilts the ball into the face the point lies on.

    Returns columns ``contact_id, facet_id, triangle, px py pz, nx ny nz`` (outward unit normal,
    frame O), facet contacts first (by sample, then facet), then curved contacts (by sample), and the
    counts of samples and of each filter's drops under ``_stats``. ``compute`` then drops the curved
    contacts no pair uses (``drop_unpaired_curved_contacts``).
    """
    pts, tri = _sample_surface(mesh, params)
    flat = _flat_facets(mesh, segments, params.flat_facet_deg)
    facet = _facet_contacts(mesh, segments, flat, pts, tri, params)
    curved = _curved_contacts(mesh, segments, flat, pts, tri, params)
    p = np.concatenate([facet.p, curved.p])
    n = np.concatenate([facet.n, curved.n])
    return {
        "contact_id": np.arange(len(p)),
        "facet_id": np.concatenate([facet.facet, curved.facet]).astype(np.int64),
        "triangle": np.concatenate([facet.triangle, curved.triangle]).astype(np.int64),
        "px": p[:, 0], "py": p[:, 1], "pz": p[:, 2],
        "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2],
        "_stats": {"samples": len(pts), **facet.dropped, **curved.dropped},
    }


class _Contacts(NamedTuple):
    """One kind of contact: points ``p (C, 3)`` m and unit normals ``n (C, 3)`` (frame O), ``facet
    (C,)`` (-1: curved), ``triangle (C,)`` and the counts each filter dropped."""

    p: np.ndarray
    n: np.ndarray
    facet: np.ndarray
    triangle: np.ndarray
    dropped: dict


def _sample_surface(mesh: trimesh.Trimesh, params: Params) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform samples thinned to ``sample_spacing``: points ``(S, 3)`` (frame O), triangles ``(S,)``."""
    rng = np.random.default_rng(params.seed)
    areas = np.asarray(mesh.area_faces)
    n_raw = max(int(np.ceil(params.sample_density * mesh.area)), 16)
    # Triangle by cumulative area, point by uniform barycentrics.
    cdf = np.cumsum(areas) / areas.sum()
    tri = np.minimum(np.searchsorted(cdf, rng.random(n_raw), side="right"), len(areas) - 1)
    u, v = rng.random((2, n_raw))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    T = np.asarray(mesh.triangles)[tri]
    pts = T[:, 0] + u[:, None] * (T[:, 1] - T[:, 0]) + v[:, None] * (T[:, 2] - T[:, 0])
    keep = _thin(pts, params.sample_spacing)
    return pts[keep], tri[keep]


def _flat_facets(mesh: trimesh.Trimesh, segments: dict, flat_deg: float) -> np.ndarray:
    """``(F,)`` True for contact facets whose triangles' normals are all within ``flat_deg`` of the facet's."""
    members = segments["triangles"]
    facet = np.repeat(np.arange(len(members)), [len(t) for t in members])
    tris = np.concatenate(list(members)) if len(members) else np.zeros(0, dtype=np.int64)
    fn = np.stack([segments["nx"], segments["ny"], segments["nz"]], axis=1)
    cos_min = np.ones(len(members))
    np.minimum.at(cos_min, facet, np.einsum("ij,ij->i", np.asarray(mesh.face_normals)[tris], fn[facet]))
    return np.asarray(segments["contact_surface"]) & (cos_min >= np.cos(np.radians(flat_deg)))


def _facet_contacts(mesh: trimesh.Trimesh, segments: dict, flat: np.ndarray, pts: np.ndarray, tri: np.ndarray,
                    params: Params) -> _Contacts:
    """Samples ``pts (S, 3)`` on triangles ``tri (S,)`` distributed onto every facet with ``flat (F,)``
    holding their triangle, then filtered (§4.1); see ``sample_contacts``."""
    n_facets = len(segments["facet_id"])
    members = [t for f, t in enumerate(segments["triangles"]) if flat[f]]
    rows = np.concatenate(members or [np.zeros(0, int)])
    cols = np.repeat(np.flatnonzero(flat), [len(t) for t in members])
    membership = sp.csr_matrix((np.ones(len(rows), dtype=bool), (rows, cols)), shape=(len(mesh.faces), n_facets))
    m = membership[tri].tocoo()
    order = np.lexsort((m.col, m.row))
    sample_idx, facet_idx = m.row[order], m.col[order]
    p, t_idx = pts[sample_idx], tri[sample_idx]
    n = np.asarray(mesh.face_normals)[t_idx]
    far = _boundary_distance(mesh, segments, p, facet_idx) >= params.boundary_margin
    free = _balls_free(mesh, p + params.ball_radius * n, params.ball_radius)
    keep = far & free
    dropped = {"distributed": int(len(keep)), "near_boundary": int((~far).sum()),
               "ball_collision": int((far & ~free).sum())}
    return _Contacts(p[keep], n[keep], facet_idx[keep], t_idx[keep], dropped)


def _curved_contacts(mesh: trimesh.Trimesh, segments: dict, flat: np.ndarray, pts: np.ndarray, tri: np.ndarray,
                     params: Params) -> _Contacts:
    """Samples ``pts (S, 3)`` on triangles ``tri (S,)`` in no facet with ``flat (F,)``, with their
    footprint normals, filtered; see ``sample_contacts``."""
    on_flat = np.zeros(len(mesh.faces), dtype=bool)
    on_flat[np.concatenate([t for f, t in enumerate(segments["triangles"]) if flat[f]] or [np.zeros(0, int)])] = True
    cand = np.flatnonzero(~on_flat[tri])
    fp = footprint(mesh, pts[cand], tri[cand], params.boundary_margin)
    n = np.zeros((len(cand), 3))
    np.add.at(n, fp.contact, fp.area[:, None] * np.asarray(mesh.face_normals)[fp.triangle])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), tol.zero)
    near_flat = np.bincount(fp.contact, weights=on_flat[fp.triangle] & (fp.area > 0), minlength=len(cand)) > 0
    p = pts[cand]
    free = _balls_free(mesh, p + params.ball_radius * n, params.ball_radius)
    keep = ~near_flat & free
    dropped = {"curved_samples": int(len(cand)), "curved_near_flat": int(near_flat.sum()),
               "curved_ball_collision": int((~near_flat & ~free).sum())}
    return _Contacts(p[keep], n[keep], np.full(int(keep.sum()), -1), tri[cand][keep], dropped)


class Footprint(NamedTuple):
    """Triangles under a ball's footprint, one row per (contact, triangle): ``contact (K,)``,
    ``triangle (K,)`` ids and ``area (K,)`` m^2 of the triangle inside the footprint."""

    contact: np.ndarray
    triangle: np.ndarray
    area: np.ndarray


def footprint(mesh: trimesh.Trimesh, points: np.ndarray, triangles: np.ndarray, radius: float) -> Footprint:
    """The surface within ``radius`` of each point ``(C, 3)`` (frame O) lying on triangle ``(C,)``.

    Grown over face adjacency from the point's own triangle through triangles within ``radius`` of
    the point whose normals are within 120 deg of its own: a right-angled neighbour (a box's edge, a
    cylinder's cap) is under the ball's footprint, the far side of a part thinner than the footprint
    (180 deg) is not. Breadth first, all points at once. Each triangle's area inside the sphere of
    ``radius`` about the point is ``area_in_sphere``'s. Rows sorted by (contact, triangle).
    """
    normals, T = np.asarray(mesh.face_normals), np.asarray(mesh.triangles)
    n_f = len(normals)
    neighbors = _face_neighbors(np.asarray(mesh.face_adjacency), n_f)
    triangles = np.asarray(triangles)
    c, t = np.arange(len(points)), triangles
    tested = found = c * n_f + t  # (contact, triangle) keys: sorted, as c is
    while len(c):  # one pass per ring of triangles within the radius: a few
        nb = neighbors[t]
        ok = nb >= 0  # -1 pads the neighbour table
        key = np.setdiff1d(np.repeat(c, nb.shape[1])[ok.ravel()] * n_f + nb[ok], tested)
        tested = np.union1d(tested, key)
        c, t = key // n_f, key % n_f
        near = np.einsum("ij,ij->i", normals[t], normals[triangles[c]]) > -0.5  # cos 120 deg
        near &= np.linalg.norm(trimesh.triangles.closest_point(T[t], points[c]) - points[c], axis=1) <= radius
        c, t = c[near], t[near]
        found = np.union1d(found, c * n_f + t)
    c, t = found // n_f, found % n_f
    return Footprint(c, t, area_in_sphere(T[t], points[c], radius))


def area_in_sphere(triangles: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """Area ``(K,)`` m^2 of each triangle ``(K, 3, 3)`` inside the sphere of ``radius`` about ``centres (K, 3)``.

    The sphere cuts the triangle's plane in a disk; the triangle-disk intersection area is the sum,
    over the triangle's edges, of the signed area the disk's centre sweeps along the edge: a
    triangle where the edge runs inside the circle, a circular sector where it runs outside (the
    polygon-circle intersection of computational geometry, exact).
    """
    v1, v2 = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    n = np.cross(v1, v2)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), tol.zero)
    d = np.einsum("ij,ij->i", centres - triangles[:, 0], n)
    r2 = radius**2 - d**2  # squared radius of the disk in the plane
    A = triangles - (centres - d[:, None] * n)[:, None, :]  # (K, 3, 3) vertices about the disk's centre
    B = np.roll(A, -1, axis=1)
    e = B - A
    a = np.maximum(np.einsum("kij,kij->ki", e, e), tol.zero)
    b = np.einsum("kij,kij->ki", A, e)
    disc = b**2 - a * (np.einsum("kij,kij->ki", A, A) - np.maximum(r2, 0)[:, None])
    root = np.sqrt(np.maximum(disc, 0))
    s = np.where(disc > 0, np.clip((-b - root) / a, 0, 1), 0.0)  # the edge is inside the circle on [s, t]
    t = np.where(disc > 0, np.clip((-b + root) / a, 0, 1), 0.0)
    P, Q = A + s[..., None] * e, A + t[..., None] * e

    def cross(x, y):
        return np.einsum("kij,kj->ki", np.cross(x, y), n)

    def angle(x, y):
        return np.arctan2(cross(x, y), np.einsum("kij,kij->ki", x, y))

    swept = 0.5 * np.maximum(r2, 0)[:, None] * (angle(A, P) + angle(Q, B)) + 0.5 * cross(P, Q)
    return np.where(r2 > 0, np.maximum(swept.sum(axis=1), 0.0), 0.0)


def _thin(points: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of a greedy subset of ``points`` (in order) with pairwise distances >= ``spacing``."""
    tree = cKDTree(points)
    pairs = tree.query_pairs(spacing, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(len(points))
    pairs = np.sort(pairs, axis=1)
    # Greedy in index order: a point survives unless an earlier survivor is within spacing.
    order = np.argsort(pairs[:, 1], kind="stable")
    later, earlier = pairs[order, 1], pairs[order, 0]
    starts = np.searchsorted(later, np.arange(len(points)))
    ends = np.searchsorted(later, np.arange(len(points)), side="right")
    alive = np.ones(len(points), dtype=bool)
    for i in np.flatnonzero(ends > starts):  # points with an earlier neighbour only
        if alive[earlier[starts[i]:ends[i]]].any():
            alive[i] = False
    return np.flatnonzero(alive)


def _boundary_distance(mesh, segments: dict, p: np.ndarray, facet_idx: np.ndarray) -> np.ndarray:
    """Distance ``(C,)`` from each point to the nearest boundary edge of its facet (m)."""
    bounds = [np.asarray(b).reshape(-1, 2) for b in segments["boundary"]]
    counts = np.array([len(b) for b in bounds])
    offsets = np.concatenate([[0], np.cumsum(counts)])
    allb = np.concatenate(bounds) if len(bounds) else np.zeros((0, 2), int)
    A, B = mesh.vertices[allb[:, 0]], mesh.vertices[allb[:, 1]]
    reps = counts[facet_idx]
    c_idx = np.repeat(np.arange(len(p)), reps)
    starts = np.repeat(offsets[facet_idx], reps)
    seg = starts + np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps)
    a, e = A[seg], B[seg] - A[seg]
    t = np.clip(np.einsum("ij,ij->i", p[c_idx] - a, e) / np.maximum(np.einsum("ij,ij->i", e, e), tol.zero), 0, 1)
    d = np.linalg.norm(a + t[:, None] * e - p[c_idx], axis=1)
    out = np.full(len(p), np.inf)
    np.minimum.at(out, c_idx, d)
    return out


def _fcl_mesh(mesh: trimesh.Trimesh) -> fcl.CollisionObject:
    """The mesh as an fcl collision object at the identity. Its hierarchy (seconds at 200k triangles)
    is built once per mesh content: the facet contacts, the curved contacts and the pair search share it."""
    v = np.ascontiguousarray(mesh.vertices, dtype=float)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    key = hashlib.sha256(v.tobytes() + b"|" + f.tobytes()).hexdigest()
    if key not in _BVH:
        _BVH.clear()  # the last mesh's only: one analysis at a time
        _BVH[key] = fclmesh.bvh(v, f)
    return fcl.CollisionObject(_BVH[key], fcl.Transform())


#: The fcl hierarchy of the last mesh :func:`_fcl_mesh` saw, by the sha256 of its arrays.
_BVH: dict[str, fcl.BVHModel] = {}


def _balls_free(mesh: trimesh.Trimesh, centres: np.ndarray, radius: float) -> np.ndarray:
    """``(C,)`` True where a ball at ``centres`` (shrunk by 2 % so tangency is not a hit) misses the mesh."""
    obj = _fcl_mesh(mesh)
    ball = fcl.CollisionObject(fcl.Sphere(radius * 0.98), fcl.Transform())
    req = fcl.CollisionRequest()
    free = np.ones(len(centres), dtype=bool)
    for i, c in enumerate(centres):  # one fcl call per contact (a few hundred; ~10 µs each)
        ball.setTranslation(c)
        free[i] = not fcl.collide(ball, obj, req, fcl.CollisionResult())
    return free


# -------------------------------------------------------------------------------------------- pairs
def find_contact_pairs(mesh: trimesh.Trimesh, segments: dict, contacts: dict, params: Params) -> dict:
    """Antipodal contact pairs (§4.2) for two ball end-effectors, unordered, ``contact_a < contact_b``.

    One squeeze test, two rules. The test: the line between the two contacts lies inside the friction
    cone about the inward normal at both (Nguyen's antipodal condition for force closure with two
    point contacts with friction), the contacts are more than a ball's diameter apart and the open
    segment between them stays inside the object. **Facet pairs** (the paper's): two facet contacts
    on flat facets whose normals are opposite within ``pair_angle_deg``, the cone's half-angle too;
    each contact keeps its best partner, as before. **Cone pairs**: any two contacts of which at least
    one is curved (``facet_id = -1``), judged by their own normals alone with the cone of
    ``cone_angle_deg``; every pair that passes is a candidate, and they fill what ``max_pairs`` leaves
    after the facet pairs, spread over the object (``_spread_pairs``). Two flat contacts on facets
    whose normals are opposite within the cone are cone pairs too when the rule above did not pair
    them (**slanted pairs**): a squeeze line across a block at an angle, one ball higher than the
    other, whose couple helps lift the far side in a pivot (§5.2.1), where a straight one needs the
    friction alone to hold the object up.

    Returns columns ``pair_id, contact_a, contact_b, facet_a, facet_b`` (-1: curved), ``width`` (m),
    ``angle`` (rad, the larger angle between the line and an inward normal: the cone's half-angle
    minus it is the margin), ``mx my mz`` (midpoint, frame O); facet pairs first, each rule's by (a, b);
    and ``_facet_pairs``, how many the facet rule made (for the summary, not a column).
    """
    P = np.stack([contacts["px"], contacts["py"], contacts["pz"]], axis=1)
    N = np.stack([contacts["nx"], contacts["ny"], contacts["nz"]], axis=1)
    fid = np.asarray(contacts["facet_id"])
    curved = fid < 0
    FN = np.stack([segments["nx"], segments["ny"], segments["nz"]], axis=1)
    opposite = FN @ FN.T < -np.cos(np.radians(params.pair_angle_deg))  # (nf, nf) facets with opposite normals

    ids = np.arange(len(P))
    flat_by_facet = {int(f): ids[~curved & (fid == f)] for f in np.unique(fid[~curved])}
    # Facet pairs: both flat, on opposite facets. Cone pairs: at least one curved.
    facet_groups = [(rows, np.sort(np.concatenate([flat_by_facet[g] for g in flat_by_facet if opposite[f, g]]
                                                  + [ids[:0]])))
                    for f, rows in flat_by_facet.items()]
    # Cone pairs: a curved contact with any other; two flat ones across facets whose normals are
    # opposite within the cone (a squeeze line slanted across a block, not only straight through).
    slanted = FN @ FN.T < -np.cos(np.radians(params.cone_angle_deg))
    cone_groups = [(ids[curved], ids), (ids[~curved], ids[curved])] + [
        (rows, np.sort(np.concatenate([flat_by_facet[g] for g in flat_by_facet if slanted[f, g]] + [ids[:0]])))
        for f, rows in flat_by_facet.items()]

    inside = make_segments_inside_fn(mesh)
    width = 2 * params.ball_radius
    facet_ab = _antipodal_pairs(P, N, facet_groups, np.cos(np.radians(params.pair_angle_deg)), width, True)
    facet_ab = facet_ab[inside(P[facet_ab[:, 0]], P[facet_ab[:, 1]])]
    cone_ab = _antipodal_pairs(P, N, cone_groups, np.cos(np.radians(params.cone_angle_deg)), width, False)
    cone_ab = cone_ab[~_rows_in(cone_ab, facet_ab)]
    keep = _spread_pairs(P[cone_ab[:, 0]], P[cone_ab[:, 1]], _squeeze_angle(P, N, cone_ab),
                         max(params.max_pairs - len(facet_ab), 0), inside)
    ab = np.concatenate([facet_ab, cone_ab[keep]])
    pa, pb = P[ab[:, 0]], P[ab[:, 1]]
    mid = 0.5 * (pa + pb)
    return {
        "pair_id": np.arange(len(ab)),
        "contact_a": ab[:, 0].astype(np.int64),
        "contact_b": ab[:, 1].astype(np.int64),
        "facet_a": fid[ab[:, 0]].astype(np.int64),
        "facet_b": fid[ab[:, 1]].astype(np.int64),
        "width": np.linalg.norm(pb - pa, axis=1),
        "angle": _squeeze_angle(P, N, ab),
        "mx": mid[:, 0], "my": mid[:, 1], "mz": mid[:, 2],
        "_facet_pairs": len(facet_ab),
    }


def _antipodal_pairs(P: np.ndarray, N: np.ndarray, groups, cos_t: float, min_width: float,
                     best_only: bool) -> np.ndarray:
    """Unique sorted pairs ``(K, 2)`` passing the squeeze test between the contacts each group allows.

    ``P, N (C, 3)``: contact points and outward normals (frame O). ``groups``: ``(rows, cols)`` index
    arrays, ``cols`` ascending: each contact of ``rows`` may pair with those of ``cols`` only (the
    rule's partners: for facet pairs the contacts on opposite facets, so the search costs the sum of
    the facet pairs' products instead of every contact against every other). The test: the
    min-cosine between the line and the two inward normals exceeds ``cos_t`` and the contacts are
    more than ``min_width`` apart (m). ``best_only``: each contact keeps only its partner of largest
    min-cosine (ties: the lowest id) among its group's.
    """
    found = [np.zeros((0, 2), dtype=np.int64)]
    for rows, cols in groups:
        if not len(rows) or not len(cols):
            continue
        Pc, Nc = P[cols], N[cols]
        chunk = max(1, 2**18 // len(cols))  # rows per block: the (chunk, cols, 3) block stays small
        for s in range(0, len(rows), chunk):
            a = rows[s : s + chunk]
            d = Pc[None, :, :] - P[a, None, :]
            dist = np.linalg.norm(d, axis=2)
            u = d / np.maximum(dist[..., None], tol.zero)
            ca = -np.einsum("ijk,ik->ij", u, N[a])  # cos between a->b and a's inward normal
            cb = np.einsum("ijk,jk->ij", u, Nc)  # cos between b->a and b's inward normal
            score = np.where((dist > min_width) & (cols[None, :] != a[:, None]), np.minimum(ca, cb), -np.inf)
            ok = score > cos_t
            if best_only:
                j = np.argmax(score, axis=1)
                ok &= np.arange(len(cols))[None, :] == j[:, None]
            i, j = np.nonzero(ok)
            found.append(np.stack([a[i], cols[j]], axis=1))
    ab = np.sort(np.concatenate(found), axis=1)
    return np.unique(ab, axis=0) if len(ab) else ab


def _rows_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(len(a),)`` whether each row of the sorted pairs ``a (K, 2)`` is a row of ``b (M, 2)``."""
    if not len(a) or not len(b):
        return np.zeros(len(a), dtype=bool)
    n = int(max(a.max(), b.max())) + 1
    return np.isin(a[:, 0] * n + a[:, 1], b[:, 0] * n + b[:, 1])


def _squeeze_angle(P: np.ndarray, N: np.ndarray, ab: np.ndarray) -> np.ndarray:
    """``(K,)`` rad: the larger angle between the line a->b of each pair and an inward contact normal."""
    u = P[ab[:, 1]] - P[ab[:, 0]]
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), tol.zero)
    cos = np.minimum(-np.einsum("ij,ij->i", u, N[ab[:, 0]]), np.einsum("ij,ij->i", u, N[ab[:, 1]]))
    return np.arccos(np.clip(cos, -1, 1))


def _spread_pairs(pa: np.ndarray, pb: np.ndarray, angle: np.ndarray, n_keep: int, valid) -> np.ndarray:
    """Sorted indices of at most ``n_keep`` pairs that ``valid`` accepts, spread over the object.

    Farthest-point sampling in pair space: ``pa, pb (K, 3)`` are the pairs' contacts (frame O), and
    the distance between two unordered pairs is the larger displacement of a contact under the better
    matching of their ends (m). The first pair is the one of smallest squeeze ``angle (K,)`` rad (the
    largest margin), each next one the farthest from those kept (the first on ties): coverage serves
    grasp refinement more than margin does, every candidate being inside the cone already.
    ``valid(a (1, 3), b (1, 3)) -> (1,) bool`` (``make_segments_inside_fn``) is asked only of the pair
    about to be taken; a refused pair is dropped and the next one taken instead.
    """
    K = len(pa)
    taken, refused = np.zeros(K, dtype=bool), np.zeros(K, dtype=bool)
    dist = np.full(K, np.inf)
    n_taken = 0
    while n_taken < n_keep and not (taken | refused).all():  # n_keep + refusals steps, each O(K)
        free = ~taken & ~refused
        i = int(np.argmax(np.where(free, dist, -np.inf)) if n_taken else np.argmin(np.where(free, angle, np.inf)))
        if not valid(pa[i:i + 1], pb[i:i + 1])[0]:
            refused[i] = True
            continue
        taken[i] = True
        n_taken += 1
        straight = np.maximum(np.linalg.norm(pa - pa[i], axis=1), np.linalg.norm(pb - pb[i], axis=1))
        crossed = np.maximum(np.linalg.norm(pa - pb[i], axis=1), np.linalg.norm(pb - pa[i], axis=1))
        dist = np.minimum(dist, np.minimum(straight, crossed))
    return np.flatnonzero(taken)


def drop_unpaired_curved_contacts(contacts: dict, pairs: dict) -> tuple[dict, dict, int]:
    """Drop the curved contacts (``facet_id`` -1) that no pair uses; renumber contacts and pairs.

    Curved contacts are sampled for squeezing; downstream every contact is also a candidate for a
    single ball (tumble pushers, USP catchers and holds), a use nothing here vets (a hold on the toy
    piano's legs failed in physics). Facet contacts keep their ids (they come first). Returns
    ``(contacts, pairs, number dropped)``.
    """
    used = np.zeros(len(contacts["contact_id"]), dtype=bool)
    used[pairs["contact_a"]] = used[pairs["contact_b"]] = True
    keep = used | (np.asarray(contacts["facet_id"]) >= 0)
    new_id = np.cumsum(keep) - 1  # increasing: pairs stay ordered, contact_a < contact_b
    contacts = {k: v[keep] for k, v in contacts.items()}
    contacts["contact_id"] = np.arange(int(keep.sum()))
    pairs = {**pairs, "contact_a": new_id[pairs["contact_a"]], "contact_b": new_id[pairs["contact_b"]]}
    return contacts, pairs, int((~keep).sum())


def make_segments_inside_fn(mesh: trimesh.Trimesh, inset: float = 0.002):
    """A callable ``(a (K, 3), b (K, 3)) -> (K,)`` True where the segment a->b (frame O, m), shortened
    by ``inset`` at both ends, misses the surface: the squeeze passes through the object only.

    The object's BVH is built once here; each segment is one python-fcl call (0.1-0.2 ms with its
    set-up).
    """
    obj = _fcl_mesh(mesh)
    req = fcl.CollisionRequest()

    def inside(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        out = np.ones(len(a), dtype=bool)
        for i in range(len(a)):  # one fcl call per pair (a few hundred)
            d = b[i] - a[i]
            length = np.linalg.norm(d)
            if length <= 2 * inset:
                out[i] = False
                continue
            R = se3.rotation_between(np.array([0.0, 0.0, 1.0]), d / length)
            seg = fcl.CollisionObject(fcl.Cylinder(1e-5, length - 2 * inset),
                                      fcl.Transform(R, 0.5 * (a[i] + b[i])))
            out[i] = not fcl.collide(seg, obj, req, fcl.CollisionResult())
        return out

    return inside


# ------------------------------------------------------------------------------------------ compute
def compute(mesh: trimesh.Trimesh, mass: float, params: Params) -> Analysis:
    """Run the whole analysis on a loaded mesh (frame O, metres) of ``mass`` kg."""
    timings = {}
    t0 = time.perf_counter()
    props = mass_properties(mesh, mass)
    hull, placements = analyze_hull(mesh, props["com"], params)
    t1 = time.perf_counter()
    segments = superimposed_segments(mesh, params)
    t2 = time.perf_counter()
    contacts = sample_contacts(mesh, segments, params)
    stats = contacts.pop("_stats")
    t3 = time.perf_counter()
    pairs = find_contact_pairs(mesh, segments, contacts, params)
    n_facet = pairs.pop("_facet_pairs")
    contacts, pairs, stats["curved_unpaired"] = drop_unpaired_curved_contacts(contacts, pairs)
    t4 = time.perf_counter()
    timings.update(hull=t1 - t0, segments=t2 - t1, sampling=t3 - t2, pairs=t4 - t3, total=t4 - t0)
    summary = {
        "mass": mass,
        "volume": float(props["volume"]),
        "com": props["com"],
        "inertia": props["inertia"],
        "extents": np.asarray(mesh.extents),
        "triangles": int(len(mesh.faces)),
        "counts": {
            "pivot_vertices": int((hull["kind"] == "vertex").sum()),
            "tumble_edges": int((hull["kind"] == "edge").sum()),
            "placements": int(len(placements["placement_id"])),
            "stable_placements": int(placements["stable"].sum()),
            "facets": int(len(segments["facet_id"])),
            "contact_facets": int(segments["contact_surface"].sum()),
            "samples": stats["samples"],
            "contacts": int(len(contacts["contact_id"])),
            "curved_contacts": int((contacts["facet_id"] < 0).sum()),
            "pairs": int(len(pairs["pair_id"])),
            "cone_pairs": int(((pairs["facet_a"] < 0) | (pairs["facet_b"] < 0)).sum()),
            "slanted_pairs": int(((pairs["facet_a"] >= 0) & (pairs["facet_b"] >= 0)).sum()) - n_facet,
        },
        "filtered": {k: v for k, v in stats.items() if k != "samples"},
    }
    return Analysis(hull, segments, placements, contacts, pairs, summary, timings)


# ---------------------------------------------------------------------------------------------- run
HULL_FIELDS = [
    Field("hull_id", "id"), Field("kind"), Field("v0", "id"), Field("v1", "id"),
    *[Field(c, "m", "O") for c in ("x0", "y0", "z0", "x1", "y1", "z1")],
    Field("face_a", "id"), Field("face_b", "id"), Field("angle", "rad"),
]
PLACEMENT_FIELDS = [
    Field("placement_id", "id"), *[Field(c, "1", "O") for c in ("nx", "ny", "nz")], Field("area", "m^2"),
    *[Field(c, "m", "T") for c in ("x", "y", "z")], *[Field(c, "1", "T") for c in ("qx", "qy", "qz", "qw")],
    Field("stable"), Field("margin", "m"), Field("com_height", "m", "T"),
    Field("support_vertices", "id"), Field("polygon", "m", "T"),
]
SEGMENT_FIELDS = [
    Field("facet_id", "id"), Field("seed", "id"), Field("triangles", "id"),
    *[Field(c, "1", "O") for c in ("nx", "ny", "nz")], Field("area", "m^2"),
    *[Field(c, "m", "O") for c in ("cx", "cy", "cz")], Field("contact_surface"), Field("boundary", "id"),
]
CONTACT_FIELDS = [
    Field("contact_id", "id"), Field("facet_id", "id"), Field("triangle", "id"),
    *[Field(c, "m", "O") for c in ("px", "py", "pz")], *[Field(c, "1", "O") for c in ("nx", "ny", "nz")],
]
PAIR_FIELDS = [
    Field("pair_id", "id"), Field("contact_a", "id"), Field("contact_b", "id"), Field("facet_a", "id"),
    Field("facet_b", "id"), Field("width", "m"), Field("angle", "rad"),
    *[Field(c, "m", "O") for c in ("mx", "my", "mz")],
]
OUTPUTS = ("hull", "placements", "segments", "contacts", "pairs")


def run(mesh_path: str | Path, out_dir: str | Path, mass: float, params: Params, scale: float = 1.0,
        producer: str = "analyze") -> Analysis:
    """Load ``mesh_path``, analyse it and write the analysis artifacts into ``out_dir``.

    Writes ``hull.parquet``, ``placements.parquet``, ``segments.parquet``, ``contacts.parquet``,
    ``pairs.parquet``, ``object.ply`` (the loaded, scaled, repaired mesh that later stages use) and,
    last, ``analysis.json`` (summary); timings go to ``analysis.json.timings.json``.
    """
    if not np.isfinite(mass) or mass <= 0:
        raise InputError(f"{mesh_path}: --mass must be a positive number of kg (got {mass})")
    t0 = time.perf_counter()
    mesh = load_mesh(mesh_path, scale)
    t_load = time.perf_counter() - t0
    result = compute(mesh, mass, params)
    out = Path(out_dir)
    meta_params = {**asdict(params), "mass": mass, "scale": scale}
    inputs = {"mesh": mesh_path}
    with artifacts.atomic_path(out / "object.ply") as tmp:
        tmp.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary"))
    tables = dict(zip(OUTPUTS, (result.hull, result.placements, result.segments, result.contacts, result.pairs),
                      strict=True))
    fields = dict(zip(OUTPUTS, (HULL_FIELDS, PLACEMENT_FIELDS, SEGMENT_FIELDS, CONTACT_FIELDS, PAIR_FIELDS),
                      strict=True))
    for name in OUTPUTS:
        meta = artifacts.make_meta(name, meta_params, inputs, producer)
        artifacts.write_table(out / f"{name}.parquet", tables[name], fields[name], meta)
    meta = artifacts.make_meta("analysis", meta_params, inputs, producer)
    artifacts.write_json(out / "analysis.json", result.summary, meta)
    artifacts.write_timings(out / "analysis.json", {**result.timings, "load": t_load})
    stagelog.log_analysis(result.summary)
    return result
