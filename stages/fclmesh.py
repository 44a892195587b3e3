"""Triangle meshes as python-fcl bounding-volume hierarchies: the one builder the stages share."""

from __future__ import annotations

import fcl
import numpy as np


def bvh(vertices, faces) -> fcl.BVHModel:
    """A python-fcl BVH of the triangles ``faces (F, 3)`` (vertex ids) over ``vertices (V, 3)`` (m, the
    mesh's own frame). Building it is the costly part (seconds at 200k triangles): callers keep it
    and wrap it in a ``fcl.CollisionObject`` per use."""
    model = fcl.BVHModel()
    model.beginModel(len(vertices), len(faces))
    model.addSubModel(np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int32))
    model.endModel()
    return model
