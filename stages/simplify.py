"""Simplified collision shapes of fine meshes (issue 20): fewer triangles, with a bound on the error.

Users bring CAD and scanned meshes of 50k-500k triangles. Planning keeps the mesh; what only needs
the solid's shape up to a known tolerance (the physics collision shape, inside tests far from the
surface) uses its simplification by manifold3d, whose edge collapses move every surface by less
than the tolerance asked for (``Manifold.simplify``).
"""

from __future__ import annotations

from typing import NamedTuple

import trimesh

from stages import objects
from stages.errors import PivotError


class CollisionMesh(NamedTuple):
    """The mesh the object's physics collision shape is decomposed from (:func:`collision_mesh`).

    mesh : the planning mesh itself, or its simplification (frame O, m).
    tolerance : bound (m) on how far any point of the simplified surface lies from the planning
        mesh's surface, and the reverse (0 when it is the planning mesh).
    """

    mesh: trimesh.Trimesh
    tolerance: float


#: Planning meshes with more triangles than this collide in physics through a simplification
#: (:func:`collision_mesh`): the convex decomposition's cuts and hulls grow with the triangle count.
COLLISION_MAX_FACES = 5000
#: What :func:`collision_mesh` adds to manifold3d's tolerance for its float32 vertices (~3e-8 m at
#: 0.5 m) and the canonical 1e-6 m rounding (up to 0.87e-6 m).
_ROUNDING_BOUND = 1e-6


def collision_mesh(mesh: trimesh.Trimesh, max_faces: int = COLLISION_MAX_FACES, tolerance: float = 1e-5,
                   max_tolerance: float = 2e-3) -> CollisionMesh:
    """The mesh physics collides with: ``mesh`` itself up to ``max_faces`` triangles, else its
    simplification by manifold3d's ``Manifold.simplify`` (edge collapses that move every surface by
    less than the tolerance, keeping a subset of the vertices and a closed 2-manifold), at the first of
    ``tolerance * 4**k`` (m) up to ``max_tolerance`` that leaves at most ``max_faces`` triangles.

    A flat-faced CAD or subdivided mesh falls back to its few true faces at the first tolerance (the
    200k-triangle toy piano: 674 triangles, 0.6 s); a curved one needs a coarser tolerance. The
    result is in canonical form (``stages.objects.canonical_mesh``), so the same mesh gives the same
    bytes and the same decomposition cache key. A mesh manifold3d refuses (not closed or not
    oriented) is decomposed as it is. Returns the mesh and its error bound (:class:`CollisionMesh`).
    """
    if len(mesh.faces) <= max_faces:
        return CollisionMesh(mesh, 0.0)
    try:
        solid = objects._to_manifold(mesh)
    except PivotError:
        return CollisionMesh(mesh, 0.0)
    tol = tolerance
    simple = objects._from_manifold(solid.simplify(tol))
    while len(simple.faces) > max_faces and tol * 4 <= max_tolerance:
        tol *= 4
        simple = objects._from_manifold(solid.simplify(tol))
    return CollisionMesh(objects.canonical_mesh(simple), tol + _ROUNDING_BOUND)
