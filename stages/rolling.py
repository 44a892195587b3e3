"""Rolling of a ball end-effector on the object (paper §5.1; DESIGN.md, Execution).

A ball held at the orientation its arm's joints give it rolls on the object whenever the object turns
relative to it: with sticking friction its centre moves relative to the object by ``(omega_o -
omega_ball) x r n_in`` (rolling without slip), and the contact point moves on the surface with it.
``stages.execute`` shifts each ball's target by that integral; the planner must therefore check that
where the contact rolls to is still on the surface it was planned on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from stages import se3


def rolling_shift(robot, arm: str, q: np.ndarray, X_WO: np.ndarray, n_O: np.ndarray, r: float) -> np.ndarray:
    """Where a ball that keeps the orientation of its planned joints rolls to on the object, ``(T, 3)`` (m, O).

    Without slip, its centre moves relative to the object by ``(omega_o - omega_ball) x r n_in`` (the
    controller of ``stages.execute`` shifts its target the same way), accumulated over the rows of
    ``q (T, n)`` and ``X_WO (T, 4, 4)`` from the first; ``n_O`` is the contact's outward normal (O).
    """
    R_b = robot.eef_rotation(arm, q)
    R_o = X_WO[:, :3, :3]
    d_o = Rotation.from_matrix(R_o[1:] @ np.swapaxes(R_o[:-1], 1, 2)).as_rotvec()
    d_b = Rotation.from_matrix(R_b[1:] @ np.swapaxes(R_b[:-1], 1, 2)).as_rotvec()
    n_in = -se3.rotate_vectors(X_WO[:-1], n_O)
    step_W = np.cross(d_o - d_b, r * n_in)
    step_O = np.einsum("tji,tj->ti", R_o[:-1], step_W)
    return np.concatenate([np.zeros((1, 3)), np.cumsum(step_O, axis=0)])


@dataclass(frozen=True)
class RollLimits:
    """How far a rolled ball may stray from the surface its contact was planned on.

    margin : the rolled ball, and the ball this far (m) beyond it in the direction it rolls, must both
        still sit on that surface (the tumbles' catcher keeps its contact 5 mm inside its face).
    max_gap : largest difference (m) between the ball centre's distance to the object's surface and the
        ball radius: a curved surface bends away by about ``s^2 / 2(R + r)`` after a roll ``s``; into a
        concave corner the ball would press into the next face.

    The contact normal there (from the ball's closest point on the mesh to its centre) may turn from the
    planned one by at most the friction cone's half-angle ``atan(mu)``: the planned force, along the
    planned normal, then still sticks. Past a face's edge the normal turns by ``atan(o / r)`` for the
    centre ``o`` past it, so the ball may not wrap an edge by more.
    """

    margin: float = 0.005
    max_gap: float = 0.003


def rolled_off(mesh: trimesh.Trimesh, p_O: np.ndarray, n_O: np.ndarray, r: float, shift: np.ndarray, mu: float,
               limits: RollLimits = RollLimits()) -> int:
    """The first row of ``shift (T, 3)`` (m, O: :func:`rolling_shift`) at which a ball of radius ``r`` on
    the contact ``p_O`` with outward normal ``n_O`` (O), rolled by it, has left its surface
    (``limits``; ``mu`` the ball-object friction coefficient), or -1 when it never does. The ball's
    centre, and the centre ``margin`` ahead of it, against their closest points on the mesh
    (``trimesh.proximity.closest_point``): the contact a ball sees, smooth across a mesh's facets."""
    shift = np.asarray(shift, dtype=float)
    moved = np.linalg.norm(shift, axis=1)
    rows = np.flatnonzero(moved > 1e-6)
    if not len(rows):
        return -1
    centre = p_O + r * np.asarray(n_O, dtype=float) + shift[rows]
    pts = np.concatenate([centre, centre + limits.margin * shift[rows] / moved[rows, None]])
    closest, dist, _ = trimesh.proximity.closest_point(mesh, pts)
    cos_turn = np.einsum("ij,j->i", pts - closest, n_O) / np.maximum(dist, 1e-12)
    bad = (np.abs(dist - r) > limits.max_gap) | (cos_turn < np.cos(np.arctan(mu)))
    bad = bad[: len(rows)] | bad[len(rows):]
    return int(rows[np.argmax(bad)]) if bad.any() else -1
