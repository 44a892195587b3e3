"""Grasp stability of an object held by table contacts and ball end-effectors (§4.3, eq. 1–4), batched.

Array forms. N candidates, each with ``k`` table contact points and ``e`` end-effector (EEF) contacts
(shapes fixed per call, unused slots masked out): ``com_W (N, 3)``, ``table_pts_W (N, k, 3)``,
``eef_pts_W (N, e, 3)``, ``eef_normals_W (N, e, 3)``, all in the world frame W (z up), SI units.

Contact model (eq. 2). Point contacts with Coulomb friction; each cone is replaced by the inscribed
pyramid with ``n_sides`` edges ``v_j = n + mu (cos th_j t1 + sin th_j t2)``, ``th_j = 2 pi j / n_sides``,
``n`` the inward unit normal (into the object). Every edge has normal component 1, so the coefficient
``lam_j >= 0`` of an edge is a normal force and a contact force is ``f = sum_j lam_j v_j``.
Tangent frame: ``t1 = n x z`` normalised (for the usual side contact ``t1`` is horizontal, ``t2 = -z``,
and for ``n_sides = 6`` the vertical falls on the middle of a pyramid face: the vertical friction a
side contact can give is ``mu cos(pi/6) f_n``, the inscribed radius, not ``mu f_n``); for a normal
within 1e-6 of vertical (every table contact) ``t1`` is the horizontal direction from the CoM to the
contact, so the model turns with the scene about z.

- Table contacts: normal ``+z`` (the table top), friction ``mu_table``, unilateral and unbounded.
- EEF contacts: friction ``mu_eef``; the force is bounded by ``sum_j lam_j <= f_max``, i.e. the
  **normal component** ``f_n <= f_max`` (so ``|f| <= f_max sqrt(1 + mu_eef^2)``). To bound ``|f|`` by a
  payload ``F`` instead, pass ``f_max = F / sqrt(1 + mu_eef^2)``.

Wrenches (eq. 1, 3) are taken about the CoM: a force ``f`` at ``p`` gives ``[f, (p - c) x f / L]``,
the torque divided by a characteristic length ``L`` (m; the caller passes e.g. the object's bounding
radius) so that all six rows are in newtons. Gravity ``w_g = [0, 0, -m g, 0, 0, 0]``; the contacts must
supply ``w* = -w_g``. With ``G`` the wrench matrix of all pyramid edges, the bounded grasp wrench space
is ``GWS = {G lam : lam >= 0, each EEF's sum <= f_max}``, a convex polyhedron containing 0, unbounded
along the table cones.

Stability: ``w*`` in GWS, decided by the ray LP ``alpha* = max {alpha <= 2 : alpha w* in GWS}``:
stable iff ``alpha* >= 1 - feas_tol`` (exact up to the LP tolerance).

Margin (replaces the paper's L2 distance of eq. 4, which needs a Minkowski sum and a convex hull): the
radius of the largest L1 ball (cross-polytope) centred at ``w*`` inside GWS,
``margin = min_k eps_k``, ``eps_k = max {eps : w* + eps d_k in GWS}`` over the 12 directions
``d_k = +-e_k`` (a ball lies in a convex set iff its 12 vertices do). In newtons: a disturbance wrench
``delta`` (force N, torque N m) is resisted whenever ``|delta_f|_1 + |delta_tau|_1 / L <= margin``. The
axes are those of W, or of a frame D given by ``R_WD`` (the L1 ball is not invariant under rotations:
pass the object's orientation to make the margin a property of the grasp, not of the heading). Each
``eps_k`` is capped at ``margin_cap`` weights (directions along which the unbounded table cones never
leave GWS). For rank-deficient contact sets (``rank < 6``: e.g. a two-point pinch cannot resist torque
about the line through its contacts) with ``w*`` in the span, the ball is taken inside the span: the
directions are ``P d_k / |P d_k|_1`` with ``P`` the projector onto the span of G (directions with
``|P d_k| < 1e-6`` are skipped); then the margin is the exact L1 radius when the null space is spanned
by coordinate axes, otherwise an upper bound of it. ``rank`` is reported so that callers can reject
such sets. A set whose span misses ``w*`` is unstable with reason ``"degenerate"``. The rays start
from ``min(1, alpha*) w*``, i.e. from ``w*`` shrunk by at most ``feas_tol`` so that the start is in GWS.
Unstable candidates get margin 0 (no signed distance).

Solver. All LPs have the same form, ``max t s.t. G lam - t d = b, group sums <= u, 0 <= t <= cap``
(feasibility: ``b = 0, d = w*``; margin: ``b = w*, d = d_k``), solved in bulk by a Mehrotra
predictor–corrector interior-point method on the normal equations, reduced by a Schur complement to
one ``(6, 6)`` system per LP. The 12 margin LPs of a candidate share its wrench matrix. Cheap exact
tests settle most feasibility questions first (CoM above the support polygon, torque and lift
capacity of the bounded EEF forces). LPs that the IPM does not converge are re-solved by HiGHS.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.optimize import linprog

from stages import tol
from stages.errors import PivotError

#: Reason codes of :class:`StabilityResult`.
REASONS = ("ok", "unstable", "degenerate", "low_margin")
#: Singular values of G below this fraction of the largest span no wrench direction (rank test).
RANK_RTOL = 1e-6
#: ``w*`` (unit length after scaling by the weight) is in the span of G if its residual is below this.
SPAN_TOL = 1e-6
#: Angular slack (rad) of the CoM-above-support-polygon test; closer calls go to the LP.
ANGLE_TOL = 1e-9
#: Cap of the feasibility ray ``alpha`` (multiples of the weight); only ``alpha >= 1`` matters.
ALPHA_CAP = 2.0

_EZ = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Params:
    """Stability parameters (SI units).

    Attributes
    ----------
    mu_eef, mu_table : float
        Coulomb friction coefficients ball–object and table–object.
    f_max : float
        Bound on the normal component of each EEF force (N); about the arm payload (5 kg).
    n_sides : int
        Edges of each inscribed friction pyramid (paper: 6).
    g : float
        Gravity (m/s^2).
    margin_min : float
        Stable also requires ``margin >= margin_min`` (N); 0 keeps the plain feasibility test.
    margin_cap : float
        Cap of each ray distance of the margin, in weights ``m g``.
    feas_tol : float
        Stable iff ``alpha* >= 1 - feas_tol``.
    lp_tol : float
        Relative primal, dual and complementarity tolerance of the interior-point method (in units
        of the weight: margins come out within about ``10 lp_tol m g``).
    max_iter : int
        Interior-point iterations before an LP is handed to HiGHS.
    chunk : int
        LPs per solver batch (bounds memory, keeps arrays in cache).
    """

    mu_eef: float = 0.5
    mu_table: float = 0.5
    f_max: float = 50.0
    n_sides: int = 6
    g: float = 9.81
    margin_min: float = 0.0
    margin_cap: float = 10.0
    feas_tol: float = 1e-6
    lp_tol: float = 1e-8
    max_iter: int = 60
    chunk: int = 8192

    def __post_init__(self):
        checks = {
            "mu_eef": self.mu_eef >= 0, "mu_table": self.mu_table >= 0, "f_max": self.f_max > 0,
            "n_sides": self.n_sides >= 3, "g": self.g > 0, "margin_min": self.margin_min >= 0,
            "margin_cap": self.margin_cap > 0, "feas_tol": 0 <= self.feas_tol < 1,
            "lp_tol": self.lp_tol > 0, "max_iter": self.max_iter >= 1, "chunk": self.chunk >= 1,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise PivotError(f"stability Params: invalid {', '.join(bad)}")


def normal_bound(magnitude: float, mu: float) -> float:
    """The bound (N) on an EEF's normal force that keeps its whole force, normal plus friction inside
    the friction cone of coefficient ``mu``, within ``magnitude`` (N): ``magnitude / sqrt(1 + mu^2)``,
    the :class:`Params` ``f_max`` of a test whose ball force is judged by its magnitude."""
    return float(magnitude / np.hypot(1.0, mu))


@dataclass(frozen=True)
class StabilityResult:
    """Per-candidate stability verdicts.

    Attributes
    ----------
    stable : (N,) bool
        Gravity can be balanced (and ``margin >= margin_min``).
    margin : (N,) float
        L1 wrench margin (N) around ``w*``, see the module docstring; 0 when not feasible, NaN when
        feasible but not computed (``compute_margin=False``).
    reason : (N,) str
        One of :data:`REASONS`.
    rank : (N,) int
        Rank of the contact wrench matrix (6 for a grasp that can resist any wrench direction).
    decided_by : (N,) str
        ``"rank"``, ``"filter"`` (closed-form test), ``"ipm"`` or ``"highs"`` (fallback); for the
        feasibility verdict.
    alpha : (N,) float
        The feasibility ray ``alpha*`` (inf where a closed-form test found the candidate stable, 0
        where one found it unstable or the set is degenerate); it does not depend on ``R_WD``.
    stats : dict
        Counts for benchmarks: candidates, degenerate, settled by pre-filters, feasibility LPs,
        margin LPs, HiGHS fallbacks.
    """

    stable: np.ndarray
    margin: np.ndarray
    reason: np.ndarray
    rank: np.ndarray
    decided_by: np.ndarray
    alpha: np.ndarray
    stats: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------------
# Contact model


def contact_frames(n_W: np.ndarray, r_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangents ``(t1, t2)`` of the friction pyramids, each ``(..., 3)``, W.

    ``t1 = n x z`` normalised; for a normal within 1e-6 of vertical, the horizontal CoM-to-contact
    direction (a contact straight below the CoM falls back to x). ``t2 = n x t1``. Both rules turn with
    the scene about z, so the model does too.

    Parameters
    ----------
    n_W : (..., 3) float
        Inward unit normals (into the object), W.
    r_W : (..., 3) float
        Contact point minus CoM (m), W.
    """
    n_W = np.asarray(n_W, dtype=float)
    nx, ny = n_W[..., 0], n_W[..., 1]
    t1 = np.stack([ny, -nx, np.zeros_like(nx)], axis=-1)
    s = np.hypot(nx, ny)
    vertical = s <= 1e-6
    if np.any(vertical):
        radial = np.asarray(r_W, dtype=float) * np.array([1.0, 1.0, 0.0])
        radial = radial - np.sum(radial * n_W, axis=-1, keepdims=True) * n_W
        ex = np.array([1.0, 0.0, 0.0]) - n_W[..., :1] * n_W
        alt = np.where((np.linalg.norm(radial, axis=-1) > tol.merge)[..., None], radial, ex)
        t1 = np.where(vertical[..., None], alt, t1)
        s = np.where(vertical, np.linalg.norm(alt, axis=-1), s)
    t1 = t1 / np.maximum(s, tol.zero)[..., None]
    return t1, np.cross(n_W, t1)


def edge_coefficients(mu: float, n_sides: int) -> np.ndarray:
    """``(3, n_sides)``: edge ``j`` of a pyramid is ``[n, t1, t2] @ C[:, j]`` (eq. 2).

    ``v_j = n + mu (cos th_j t1 + sin th_j t2)``, ``th_j = 2 pi j / n_sides``: normal component 1.
    """
    th = 2.0 * np.pi * np.arange(n_sides) / n_sides
    return np.stack([np.ones(n_sides), mu * np.cos(th), mu * np.sin(th)])


def contact_basis(r_W, n_W, t1_W, t2_W, mask, L) -> np.ndarray:
    """Wrenches about the CoM of the unit forces along ``n, t1, t2`` at each contact (eq. 1).

    Parameters
    ----------
    r_W : (N, c, 3) float
        Contact point minus CoM (m), W.
    n_W, t1_W, t2_W : (N, c, 3) float
        Normal and tangents, W.
    mask : (N, c) bool
        Active contacts (inactive ones give zeros).
    L : (N,) float
        Characteristic length (m) dividing the torques.

    Returns
    -------
    (N, c, 6, 3) float
        Columns ``[u, r x u / L]`` for ``u = n, t1, t2``. The pyramid edge wrenches are this times
        :func:`edge_coefficients`.
    """
    f = np.stack([n_W, t1_W, t2_W], axis=-1)                                     # (N, c, 3, 3)
    tau = np.cross(r_W[..., None, :], np.swapaxes(f, -1, -2)) / L[:, None, None, None]
    return np.concatenate([f, np.swapaxes(tau, -1, -2)], axis=-2) * mask[:, :, None, None]


def wrench_matrix(basis, mu, n_sides) -> np.ndarray:
    """Wrench columns ``(N, 6, c * n_sides)`` of all pyramid edges; contact-major (contact i owns
    columns ``i * n_sides ... (i + 1) * n_sides - 1``)."""
    N, c = basis.shape[:2]
    w = basis @ edge_coefficients(mu, n_sides)                                   # (N, c, 6, s)
    return np.ascontiguousarray(w.transpose(0, 2, 1, 3)).reshape(N, 6, c * n_sides)


def wrench_gram(basis, mu, n_sides) -> np.ndarray:
    """``G G^T (N, 6, 6)`` without forming G: the edge coefficients satisfy
    ``C C^T = diag(s, s mu^2 / 2, s mu^2 / 2)`` for ``s = n_sides >= 3``."""
    N, c = basis.shape[:2]
    w = np.sqrt([n_sides, n_sides * mu**2 / 2, n_sides * mu**2 / 2])
    X = np.ascontiguousarray((basis * w).transpose(0, 2, 1, 3)).reshape(N, 6, 3 * c)
    return X @ np.swapaxes(X, 1, 2)


# --------------------------------------------------------------------------------------------------
# Batched LP solver


def solve_ray_lps(G, b, d, u, cap, n_groups, group_size, colmask=None, lp_tol=1e-8, max_iter=60):
    """Solve many ray LPs ``max t`` of one shape by a batched primal–dual interior-point method.

    The LP, for each candidate ``i`` and each of its ``K`` right-hand sides ``q``::

        max t  s.t.  G_i lam - t d_iq = b_iq,  sum(lam[group g]) <= u_ig,  0 <= t <= cap_i,  lam >= 0

    The last ``n_groups * group_size`` columns of G form the bounded groups. Rows of ``G_i`` that are
    exactly zero are dropped with the matching entries of b and d (which are zeroed there).

    Parameters
    ----------
    G : (B, m, n) float
    b, d : (B, K, m) float
    u : (B, n_groups) float
        Group bounds (> 0).
    cap : (B,) float
        Upper bound of t (> 0).
    n_groups, group_size : int
    colmask : (B, n) bool, optional
        Inactive columns are fixed at zero.
    lp_tol : float
        Relative primal, dual and gap tolerance.
    max_iter : int

    Returns
    -------
    t : (B, K) float
        Optimal t (NaN where not converged).
    converged : (B, K) bool
    iterations : int
        Iterations of the last LP to finish.

    Notes
    -----
    Mehrotra predictor–corrector on the standard form ``A x = b_full, x >= 0`` with
    ``x = [lam, group slacks, t, cap slack]``. The normal matrix ``A D A^T`` has the group rows and
    the cap row on a diagonal block, eliminated by a Schur complement, which leaves one ``(m, m)``
    system per LP, factored by a Cholesky vectorised over the whole batch. Arrays are LP-major
    ``(B, K, ...)`` so that every reduction runs over contiguous memory.
    """
    G = np.asarray(G, dtype=float)
    B, m, n = G.shape
    K = np.shape(d)[1]
    ng, gs = n_groups, group_size
    nv = n + ng + 2
    it_t = n + ng
    t_out = np.full((B, K), np.nan)
    conv_out = np.zeros((B, K), bool)
    if B == 0 or K == 0:
        return t_out, conv_out, 0
    colmask = np.ones((B, n), bool) if colmask is None else np.asarray(colmask, bool)
    G = G * colmask[:, None, :]
    nullrow = ~np.any(G != 0, axis=2)                       # (B, m)
    b = np.where(nullrow[:, None, :], 0.0, np.broadcast_to(np.asarray(b, float), (B, K, m)))
    d = np.where(nullrow[:, None, :], 0.0, np.broadcast_to(np.asarray(d, float), (B, K, m)))
    u = np.asarray(u, float).reshape(B, ng)
    cap = np.broadcast_to(np.asarray(cap, float), (B,))
    # Objective min c.x: -t, plus a unit cost on inactive columns so that they settle at zero.
    c = np.zeros((B, 1, nv))
    c[:, 0, :n] = ~colmask
    c[:, 0, it_t] = -1.0
    bfull = np.concatenate([b, np.broadcast_to(u[:, None, :], (B, K, ng)),
                            np.broadcast_to(cap[:, None, None], (B, K, 1))], 2)

    idx = np.arange(B)
    st = _IpmState(G, d, nullrow, ng, gs)

    x, y, z = _starting_point(st, bfull, c)

    bscale = lp_tol * (1.0 + np.abs(bfull).max(2))
    cscale = lp_tol * (1.0 + np.abs(c).max(2))
    done = np.zeros((B, K), bool)
    last_it = 0
    for it in range(max_iter + 1):
        rp = bfull - st.A(x)
        rd = c - st.AT(y) - z
        pobj = np.einsum("bkn,bon->bk", x, c)
        xz = x * z
        # Complementarity as the gap: |c.x - b.y| also carries rp . y, which stalls near 1e-8 when
        # the normal equations are ill-conditioned at a degenerate optimum.
        gap = np.einsum("bkn->bk", xz)
        conv = ((np.abs(rp).max(2) <= bscale) & (np.abs(rd).max(2) <= cscale)
                & (gap <= lp_tol * (1.0 + np.abs(pobj))))
        bad = ~np.isfinite(gap + pobj + np.einsum("bkn->bk", y))
        newly = (conv | bad) & ~done
        if newly.any():
            rows, cols = np.nonzero(newly)
            ok = conv[rows, cols] & ~bad[rows, cols]
            t_out[idx[rows], cols] = np.where(ok, x[rows, cols, it_t], np.nan)
            conv_out[idx[rows], cols] = ok
            done |= newly
            last_it = it
        alive = ~done.all(1)
        if not alive.any() or it == max_iter:
            break
        if alive.mean() < 0.75:
            # Drop finished candidates so that stragglers do not carry the whole batch.
            keep = np.nonzero(alive)[0]
            idx, x, y, z, xz, gap, c, bfull, bscale, cscale, done, rp, rd = (
                a[keep] for a in (idx, x, y, z, xz, gap, c, bfull, bscale, cscale, done, rp, rd))
            st = st.take(keep)
        _mehrotra_step(st, x, y, z, xz, gap, rp, rd, done)
    return t_out, conv_out, last_it


def _starting_point(st: _IpmState, bfull, c):
    """Mehrotra's starting point of :func:`solve_ray_lps`: the least-norm ``x`` and least-squares
    ``(y, z)``, shifted into the interior and balanced by their complementarity."""
    B, K, nv = bfull.shape[0], bfull.shape[1], c.shape[2]
    fac = st.factor(np.ones((B, K, nv)))
    x = st.AT(st.solve(fac, bfull))
    y = st.solve(fac, st.A(np.broadcast_to(c, (B, K, nv))))
    z = c - st.AT(y)
    x = np.maximum(x + np.maximum(-1.5 * x.min(2, keepdims=True), 0.0), 1e-8)
    z = np.maximum(z + np.maximum(-1.5 * z.min(2, keepdims=True), 0.0), 1e-8)
    xz = np.sum(x * z, 2, keepdims=True)
    return x + 0.5 * xz / np.sum(z, 2, keepdims=True), y, z + 0.5 * xz / np.sum(x, 2, keepdims=True)


def _mehrotra_step(st: _IpmState, x, y, z, xz, gap, rp, rd, done) -> None:
    """One predictor–corrector step of :func:`solve_ray_lps` on ``x, y, z`` in place: the affine
    direction, the centring ``sigma = (mu_aff / mu)^3``, the corrected direction with its
    second-order term, and steps of 0.995 of the largest that keeps ``x, z`` positive; LPs already
    ``done`` ride along with a harmless scaling and do not move."""
    nv = x.shape[2]
    D = x / z
    # Finished LPs ride along with a harmless scaling (their extreme x/z would make M singular).
    D[done] = 1.0
    fac = st.factor(D)
    # Predictor (affine scaling).
    dx, dy, dz = st.newton(fac, D, x, z, rp, rd, -xz)
    ap = _step(x, dx)
    ad = _step(z, dz)
    mu = gap / nv
    mu_aff = np.einsum("bkn,bkn->bk", x + ap[..., None] * dx, z + ad[..., None] * dz) / nv
    sigma = np.clip(mu_aff / np.maximum(mu, 1e-300), 0.0, 1.0) ** 3
    # Corrector (centring plus second-order term).
    rc = (sigma * mu)[..., None] - xz - dx * dz
    dx, dy, dz = st.newton(fac, D, x, z, rp, rd, rc)
    live = ~done
    ap = (0.995 * live * _step(x, dx))[..., None]
    ad = (0.995 * live * _step(z, dz))[..., None]
    x += ap * dx
    y += ad * dy
    z += ad * dz


def _cholesky_soa(S, pair):
    """Cholesky factors of many SPD ``(m, m)`` matrices stored packed, batch last: ``S (pairs, N)``.

    Loops over the m(m+1)/2 entries with whole-batch vector operations, which beats a LAPACK call per
    6 x 6 matrix by about 5x. A pivot below 1e-14 of its diagonal entry, i.e. lost to cancellation (a
    degenerate LP optimum, where fewer than m columns stay basic), gets ``1 / L_jj = 0``: the solve
    then sets that component to zero, as LIPSOL does with its huge pivots.

    Returns
    -------
    L : list of lists of (N,) arrays
        ``L[i][j]`` for ``j < i``.
    inv : (m, N) float
        Reciprocal diagonal of L.
    """
    m = pair.shape[0]
    L = [[None] * m for _ in range(m)]
    inv = np.empty((m, S.shape[1]))
    for j in range(m):
        sjj = S[pair[j, j]]
        piv = sjj.copy()
        for k in range(j):
            piv -= L[j][k] * L[j][k]
        ok = piv > 1e-14 * sjj
        inv[j] = np.where(ok, 1.0 / np.sqrt(np.where(ok, piv, 1.0)), 0.0)
        for i in range(j + 1, m):
            v = S[pair[i, j]].copy()
            for k in range(j):
                v -= L[i][k] * L[j][k]
            L[i][j] = v * inv[j]
    return L, inv


def _cholesky_solve_soa(L, inv, r):
    """Solve with the factors of :func:`_cholesky_soa`; ``r (m, N)`` right-hand sides, batch last."""
    m = len(inv)
    y = [None] * m
    for j in range(m):
        v = r[j].copy()
        for k in range(j):
            v -= L[j][k] * y[k]
        y[j] = v * inv[j]
    for j in reversed(range(m)):
        v = y[j]
        for k in range(j + 1, m):
            v -= L[k][j] * y[k]
        y[j] = v * inv[j]
    return np.stack(y)


def _step(x, dx):
    """Largest step in (0, 1] keeping ``x + a dx >= 0``, per LP: ``(B, K)``."""
    worst = (dx / x).min(2)                      # x > 0: the most negative relative change
    with np.errstate(divide="ignore"):
        return np.where(worst < -1.0, -1.0 / worst, 1.0)


class _IpmState:
    """Per-batch constants of the ray LPs and the structured products with A (see solve_ray_lps)."""

    def __init__(self, G, d, nullrow, ng, gs, P=None, Ge=None):
        self.G, self.d, self.nullrow, self.ng, self.gs = G, d, nullrow, ng, gs
        B, m, n = G.shape
        self.m, self.n, self.n0 = m, n, n - ng * gs
        self.GT = np.ascontiguousarray(G.transpose(0, 2, 1))
        iu, ju = np.triu_indices(m)
        pair = np.zeros((m, m), int)
        pair[iu, ju] = pair[ju, iu] = np.arange(len(iu))
        self.pair, self.iu, self.ju = pair, iu, ju
        # Products of row pairs: G D G^T for all K diagonals D is then one (K, n) x (n, pairs) product.
        self.PT = np.ascontiguousarray((G[:, iu, :] * G[:, ju, :]).transpose(0, 2, 1)) if P is None else P
        self.GeT = (np.ascontiguousarray(G[:, :, self.n0:].reshape(B, m, ng, gs).transpose(0, 2, 3, 1))
                    if Ge is None else Ge)                    # (B, ng, gs, m)

    def take(self, keep):
        return _IpmState(self.G[keep], self.d[keep], self.nullrow[keep], self.ng, self.gs,
                         self.PT[keep], self.GeT[keep])

    def A(self, x):
        """``A x``: ``(B, K, nv) -> (B, K, m + ng + 1)``."""
        n, n0, ng, gs = self.n, self.n0, self.ng, self.gs
        B, K, _ = x.shape
        t = x[:, :, n + ng]
        rw = x[:, :, :n] @ self.GT - self.d * t[..., None]
        re = np.einsum("bkgs->bkg", x[:, :, n0:n].reshape(B, K, ng, gs)) + x[:, :, n:n + ng]
        rc = (t + x[:, :, n + ng + 1])[..., None]
        return np.concatenate([rw, re, rc], 2)

    def AT(self, y):
        """``A^T y``: ``(B, K, m + ng + 1) -> (B, K, nv)``."""
        m, n0, ng, gs = self.m, self.n0, self.ng, self.gs
        yw, ye, yc = y[:, :, :m], y[:, :, m:m + ng], y[:, :, m + ng:]
        al = yw @ self.G
        if ng:
            al[:, :, n0:] += np.repeat(ye, gs, axis=2)
        t = yc - np.einsum("bki,bki->bk", self.d, yw)[..., None]
        return np.concatenate([al, ye, t, yc], 2)

    def factor(self, D):
        """Schur-reduced normal matrix of ``A diag(D) A^T`` for ``D (B, K, nv)``, factored.

        The normal matrix is kept packed (upper triangle) with the batch last, ``(pairs, B K)``.
        """
        n, n0, ng, gs, m = self.n, self.n0, self.ng, self.gs, self.m
        iu, ju = self.iu, self.ju
        B, K, _ = D.shape
        Dl, Ds, Dt, Dst = D[:, :, :n], D[:, :, n:n + ng], D[:, :, n + ng], D[:, :, n + ng + 1]
        S = (Dl @ self.PT).reshape(B * K, len(iu)).T.copy()
        Dle = Dl[:, :, n0:].reshape(B, K, ng, gs)
        Mwe = [Dle[:, :, g, :] @ self.GeT[:, g] for g in range(ng)]   # ng x (B, K, m)
        Mee = np.einsum("bkgs->bkg", Dle) + Ds                # (B, K, ng)
        Mwc = -Dt[..., None] * self.d                          # (B, K, m)
        Mcc = Dt + Dst                                         # (B, K)
        # The t column (Dt d d^T) and the Schur term of the cap row combine: Dt Dst / Mcc d d^T.
        dT = self.d.reshape(B * K, m).T
        S += (Dt * Dst / Mcc).reshape(-1) * dT[iu] * dT[ju]
        for g, v in enumerate(Mwe):
            vT = v.reshape(B * K, m).T
            S -= (vT[iu] / Mee[:, :, g].reshape(-1)) * vT[ju]
        S[self.pair.diagonal()] += np.repeat(self.nullrow, K, axis=0).T   # dropped rows: dy = 0
        return _cholesky_soa(S, self.pair), Mwe, Mee, Mwc, Mcc

    def solve(self, fac, r):
        """``(A D A^T)^{-1} r`` for ``r (B, K, m + ng + 1)`` with the factor of :meth:`factor`."""
        (L, inv), Mwe, Mee, Mwc, Mcc = fac
        m, ng = self.m, self.ng
        B, K, _ = r.shape
        rw, re, rc = r[:, :, :m], r[:, :, m:m + ng], r[:, :, m + ng]
        q = re / Mee
        rhs = rw - Mwc * (rc / Mcc)[..., None]
        for g, v in enumerate(Mwe):
            rhs -= v * q[:, :, g, None]
        dyw = _cholesky_solve_soa(L, inv, rhs.reshape(B * K, m).T).T.reshape(B, K, m)
        out = np.empty(r.shape)
        out[:, :, :m] = dyw
        for g, v in enumerate(Mwe):
            out[:, :, m + g] = (re[:, :, g] - np.einsum("bki,bki->bk", v, dyw)) / Mee[:, :, g]
        out[:, :, m + ng] = (rc - np.einsum("bki,bki->bk", Mwc, dyw)) / Mcc
        return out

    def newton(self, fac, D, x, z, rp, rd, rc):
        """Newton step for ``A dx = rp, A^T dy + dz = rd, z dx + x dz = rc``."""
        h = rc / z - D * rd
        dy = self.solve(fac, rp - self.A(h))
        ATdy = self.AT(dy)
        return h + D * ATdy, dy, rd - ATdy


def solve_ray_lp_highs(G, b, d, u, cap, n_groups, group_size, colmask=None) -> float:
    """One ray LP of :func:`solve_ray_lps` (``G (m, n)``, ``b, d (m,)``) by HiGHS; NaN if infeasible."""
    m, n = G.shape
    nb = n_groups * group_size
    c = np.zeros(n + 1)
    c[-1] = -1.0
    A_eq = np.hstack([G, -np.asarray(d, float)[:, None]])
    A_ub = np.zeros((n_groups, n + 1))
    for g in range(n_groups):
        A_ub[g, n - nb + g * group_size:n - nb + (g + 1) * group_size] = 1.0
    active = np.ones(n, bool) if colmask is None else np.asarray(colmask, bool)
    bounds = [(0.0, None if a else 0.0) for a in active] + [(0.0, float(cap))]
    res = linprog(c, A_ub=A_ub if n_groups else None, b_ub=np.asarray(u, float) if n_groups else None,
                  A_eq=A_eq, b_eq=b, bounds=bounds, method="highs")
    return float(res.x[-1]) if res.status == 0 else np.nan


def _solve_with_fallback(G, b, d, u, cap, ng, gs, colmask, params):
    """:func:`solve_ray_lps` in chunks, HiGHS for the LPs the IPM leaves unconverged."""
    B, K = G.shape[0], d.shape[1]
    b = np.broadcast_to(b, d.shape)
    t = np.full((B, K), np.nan)
    conv = np.zeros((B, K), bool)
    chunk = max(1, params.chunk // K)
    for s in range(0, B, chunk):
        sl = slice(s, s + chunk)
        t[sl], conv[sl], _ = solve_ray_lps(G[sl], b[sl], d[sl], u[sl], cap[sl], ng, gs, colmask[sl],
                                           params.lp_tol, params.max_iter)
    rows, cols = np.nonzero(~conv)
    for i, q in zip(rows, cols, strict=True):
        t[i, q] = solve_ray_lp_highs(G[i], b[i, q], d[i, q], u[i], cap[i], ng, gs, colmask[i])
    return t, ~conv


# --------------------------------------------------------------------------------------------------
# Closed-form pre-filters


def _support_polygon_test(q_xy, p_xy, mask):
    """Is ``q`` strictly inside / strictly outside the convex hull of the active points ``p``?

    Uses the largest angular gap of the points seen from q: inside iff every gap is < pi. Calls within
    :data:`ANGLE_TOL`, and points coinciding with q, are left undecided.

    Returns
    -------
    inside, outside : (N,) bool
    """
    N, k = mask.shape
    if k == 0:
        z = np.zeros(N, bool)
        return z, z
    rel = p_xy - q_xy[:, None, :]
    ang = np.sort(np.where(mask, np.arctan2(rel[..., 1], rel[..., 0]), np.inf), axis=1)
    cnt = mask.sum(1)
    with np.errstate(invalid="ignore"):
        gaps = np.diff(ang, axis=1)
    gaps = np.where(np.arange(k - 1)[None, :] < (cnt[:, None] - 1), gaps, 0.0)
    last = ang[np.arange(N), np.maximum(cnt - 1, 0)]
    wrap = np.where(cnt > 0, ang[:, 0] + 2 * np.pi - np.where(cnt > 0, last, 0.0), 0.0)
    maxgap = np.maximum(gaps.max(1, initial=0.0), wrap)
    clear = (cnt > 0) & ~np.any(mask & (np.linalg.norm(rel, axis=-1) < tol.merge), axis=1)
    return clear & (maxgap < np.pi - ANGLE_TOL), clear & (maxgap > np.pi + ANGLE_TOL)


def _eef_range(a, eef_frames, eef_mask, mu, n_sides, f_max):
    """Range ``[lo, hi] (N,)`` of ``sum_i a_i . f_i`` over the bounded EEF force polytopes.

    Exact: a linear function on ``conv{0, f_max v_j}`` peaks at a vertex. ``a (N, e, 3)``.
    """
    vals = np.einsum("nea,neab->neb", a, eef_frames) @ edge_coefficients(mu, n_sides)  # (N, e, s)
    lo = f_max * np.minimum(vals.min(-1, initial=np.inf), 0.0)
    hi = f_max * np.maximum(vals.max(-1, initial=-np.inf), 0.0)
    return np.sum(lo * eef_mask, 1), np.sum(hi * eef_mask, 1)


def _prefilter(W, com_W, table_pts_W, table_mask, eef_pts_W, eef_mask, eef_frames, params):
    """Exact closed-form verdicts ``(stable, unstable)`` (N,) bool, both False where undecided.

    ``eef_frames (N, e, 3, 3)``: columns n, t1, t2 of each EEF contact, W.
    """
    N, k = table_mask.shape
    e = eef_mask.shape[1]
    p = params
    kact = table_mask.sum(1)
    eact = eef_mask.sum(1)
    inside, outside = _support_polygon_test(com_W[:, :2], table_pts_W[..., :2], table_mask)
    # Vertical forces at the table points alone hold the weight iff the CoM is above their hull; EEF
    # forces may then be zero, so the candidate is stable whatever its EEFs.
    stable = inside
    # With no EEF and coplanar table points, friction adds no torque about horizontal axes (its net
    # force is zero), so a CoM outside the hull falls.
    zt = table_pts_W[..., 2]
    ztop = np.max(np.where(table_mask, zt, -np.inf), 1, initial=-np.inf)
    zbot = np.min(np.where(table_mask, zt, np.inf), 1, initial=np.inf)
    flat = (kact == 0) | (ztop - zbot <= tol.merge)
    unstable = outside & (eact == 0) & flat
    slack = W * p.feas_tol
    if eef_mask.shape[1]:
        ez = np.broadcast_to(_EZ, eef_pts_W.shape)
        # No table: the EEFs must lift the whole weight.
        _, lift = _eef_range(ez, eef_frames, eef_mask, p.mu_eef, p.n_sides, p.f_max)
        unstable |= (kact == 0) & (lift < W - slack)
    if k and eef_mask.shape[1]:
        # One table point a (or two, a and b): the table force has no moment about a (about line ab),
        # so the EEF moments about that axis must cancel gravity's.
        first = np.argmax(table_mask, 1)
        second = k - 1 - np.argmax(table_mask[:, ::-1], 1)
        a = table_pts_W[np.arange(N), first]
        m_g = np.cross(com_W - a, -W[:, None] * _EZ)                   # gravity moment about a
        axis = np.where((kact == 2)[:, None], table_pts_W[np.arange(N), second] - a, m_g)
        ln = np.linalg.norm(axis, axis=1)
        check = ((kact == 1) | (kact == 2)) & (ln > tol.zero)
        axis = axis / np.maximum(ln, tol.zero)[:, None]
        need = -np.sum(m_g * axis, 1)
        # u . ((p - a) x f) = (u x (p - a)) . f
        lo, hi = _eef_range(np.cross(axis[:, None, :], eef_pts_W - a[:, None, :]), eef_frames,
                            eef_mask, p.mu_eef, p.n_sides, p.f_max)
        reach = np.linalg.norm(com_W - a, axis=1) + 1.0
        unstable |= check & ((need < lo - slack * reach) | (need > hi + slack * reach))
    if k >= 3 and e:
        # Coplanar table points all on one side of a line through two of them (an edge of their
        # hull): about that line the table's forces have a moment of one sign only (friction lies in
        # the table plane, which holds the line; the normal forces push up on one side), so the EEF
        # moments must make up at least the rest of gravity's.
        i, j = np.triu_indices(k, 1)
        a, b = table_pts_W[:, i], table_pts_W[:, j]                       # (N, P, 3)
        u = b - a
        ln = np.linalg.norm(u, axis=2)
        u = u / np.maximum(ln, tol.zero)[..., None]
        v = np.cross(_EZ, u)                                               # horizontal, across the line
        side = np.einsum("npa,nqa->npq", v, table_pts_W) - np.einsum("npa,npa->np", v, a)[..., None]
        others = table_mask[:, None, :] & (np.arange(k) != i[:, None]) & (np.arange(k) != j[:, None])
        below = np.all(~others | (side <= 0.0), axis=2)
        above = np.all(~others | (side >= 0.0), axis=2)
        # Orient the axis so that the table's moment about it is <= 0 (its points on the -v side).
        u = np.where(above[..., None], -u, u)
        live = (flat & (kact >= 3))[:, None] & table_mask[:, i] & table_mask[:, j] & (ln > tol.merge) & (below | above)
        m_g = np.einsum("npa,npa->np", np.cross(com_W[:, None, :] - a, -W[:, None, None] * _EZ), u)
        _, hi = _eef_range(np.cross(u[:, :, None, :], eef_pts_W[:, None] - a[:, :, None, :]).reshape(N * len(i), e, 3),
                           np.repeat(eef_frames, len(i), axis=0), np.repeat(eef_mask, len(i), axis=0), p.mu_eef,
                           p.n_sides, p.f_max)
        reach = np.linalg.norm(com_W[:, None, :] - a, axis=2) + 1.0
        unstable |= np.any(live & (hi.reshape(N, len(i)) < -m_g - slack[:, None] * reach), axis=1)
    return stable & ~unstable, unstable


# --------------------------------------------------------------------------------------------------
# Evaluation


def _as_mask(mask, shape, name):
    if mask is None:
        return np.ones(shape, bool)
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise PivotError(f"stability: {name} has shape {mask.shape}, expected {shape}")
    return mask.astype(bool)


def _per_candidate(x, N, name):
    x = np.asarray(x, float)
    if x.ndim == 0:
        x = np.full(N, float(x))
    if x.shape != (N,) or not np.all(np.isfinite(x)) or np.any(x <= 0):
        raise PivotError(f"stability: {name} must be a positive scalar or ({N},) array")
    return x


def _check_points(a, N, name):
    a = np.asarray(a, float)
    if a.ndim != 3 or a.shape[0] != N or a.shape[2] != 3:
        raise PivotError(f"stability: {name} has shape {a.shape}, expected ({N}, c, 3)")
    return a


def _rank_and_span(M, wstar):
    """Rank of ``G (N, 6, n)`` from ``M = G G^T`` and the eigenbasis that drops its null space.

    Most sets are certified full rank by ``lambda_min(M) >= 1 / trace(M^-1)`` (one batched inverse);
    only the rest get an eigen-decomposition.

    Returns
    -------
    rank : (N,) int
    U : (N, 6, 6) float
        Orthonormal basis (columns; identity for full rank).
    null : (N, 6) bool
        Columns of U spanning the null space of ``G^T``.
    in_span : (N,) bool
        ``w*`` lies in the span of G.
    """
    N = len(M)
    tr = np.trace(M, axis1=1, axis2=2)
    reg = 1e-10 * tr + tol.zero
    Minv = np.linalg.inv(M + reg[:, None, None] * np.eye(6))
    lower = 1.0 / np.trace(Minv, axis1=1, axis2=2) - reg
    full = lower > RANK_RTOL**2 * tr
    U = np.broadcast_to(np.eye(6), (N, 6, 6)).copy()
    null = np.zeros((N, 6), bool)
    rest = np.nonzero(~full)[0]
    if len(rest):
        lam, V = np.linalg.eigh(M[rest])
        smax = np.sqrt(np.maximum(lam[:, -1], 0.0))
        nl = np.sqrt(np.maximum(lam, 0.0)) <= RANK_RTOL * smax[:, None]
        U[rest] = V
        null[rest] = nl | (smax == 0.0)[:, None]
    coef = np.einsum("nji,nj->ni", U, wstar)
    in_span = np.linalg.norm(np.where(null, coef, 0.0), axis=1) <= SPAN_TOL
    return 6 - null.sum(1), U, null, in_span


class _Inputs(NamedTuple):
    """:func:`evaluate`'s inputs checked and cleaned (inactive slots harmless, normals unit)."""

    mass: np.ndarray
    com_W: np.ndarray
    table_pts_W: np.ndarray
    table_mask: np.ndarray
    eef_pts_W: np.ndarray
    eef_normals_W: np.ndarray
    eef_mask: np.ndarray
    L: np.ndarray


def _clean_inputs(mass, com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L) -> _Inputs:
    """:func:`evaluate`'s arguments checked (shapes, finite active entries, non-zero normals;
    :class:`PivotError` else); inactive slots, which may hold anything, replaced by harmless values."""
    com_W = np.asarray(com_W, float)
    if com_W.ndim != 2 or com_W.shape[1] != 3:
        raise PivotError(f"stability: com_W has shape {com_W.shape}, expected (N, 3)")
    N = com_W.shape[0]
    table_pts_W = _check_points(table_pts_W, N, "table_pts_W")
    eef_pts_W = _check_points(eef_pts_W, N, "eef_pts_W")
    eef_normals_W = _check_points(eef_normals_W, N, "eef_normals_W")
    if eef_normals_W.shape != eef_pts_W.shape:
        raise PivotError(f"stability: eef_normals_W has shape {eef_normals_W.shape}, "
                         f"expected {eef_pts_W.shape}")
    k, e = table_pts_W.shape[1], eef_pts_W.shape[1]
    table_mask = _as_mask(table_mask, (N, k), "table_mask")
    eef_mask = _as_mask(eef_mask, (N, e), "eef_mask")
    mass = _per_candidate(mass, N, "mass")
    L = _per_candidate(L, N, "L")
    if not np.all(np.isfinite(com_W)):
        raise PivotError("stability: com_W has non-finite entries")
    # Inactive slots may hold anything (NaN included): replace them by harmless values.
    table_pts_W = np.where(table_mask[..., None], table_pts_W, com_W[:, None, :] - _EZ)
    eef_pts_W = np.where(eef_mask[..., None], eef_pts_W, com_W[:, None, :] - _EZ)
    eef_normals_W = np.where(eef_mask[..., None], eef_normals_W, _EZ)
    nrm = np.linalg.norm(eef_normals_W, axis=-1)
    if not (np.all(np.isfinite(table_pts_W)) and np.all(np.isfinite(eef_pts_W))
            and np.all(np.isfinite(nrm))):
        raise PivotError("stability: active contact points or normals have non-finite entries")
    if np.any(nrm < 1e-9):
        raise PivotError("stability: an active EEF contact has a zero normal")
    eef_normals_W = eef_normals_W / nrm[..., None]
    return _Inputs(mass, com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L)


def _unit_wrenches(com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L, R_WD):
    """The contacts' unit wrench bases ``(N, k | e, 6, 3)`` about the CoM (torques over ``L``), in W or
    in the axes of ``R_WD``, the weight direction ``w* (N, 6)`` there (e_fz once divided by W), and
    the EEF contact frames ``(N, e, 3, 3)`` (normal, two tangents; W)."""
    N = com_W.shape[0]
    # Contact frames and unit wrenches (W, or D axes for the margin); w* = e_fz after dividing by W.
    r_t = table_pts_W - com_W[:, None, :]
    r_e = eef_pts_W - com_W[:, None, :]
    n_t = np.broadcast_to(_EZ, r_t.shape)
    t1_t, t2_t = contact_frames(n_t, r_t)
    t1_e, t2_e = contact_frames(eef_normals_W, r_e)
    basis_t = contact_basis(r_t, n_t, t1_t, t2_t, table_mask, L)
    basis_e = contact_basis(r_e, eef_normals_W, t1_e, t2_e, eef_mask, L)
    wstar = np.zeros((N, 6))
    wstar[:, 2] = 1.0
    if R_WD is not None:
        R_WD = np.asarray(R_WD, float)
        if R_WD.shape not in ((3, 3), (N, 3, 3)) or not np.all(np.isfinite(R_WD)):
            raise PivotError(f"stability: R_WD has shape {R_WD.shape}, expected (3, 3) or ({N}, 3, 3)")
        RT = np.broadcast_to(np.swapaxes(R_WD, -1, -2), (N, 3, 3))
        R6 = np.zeros((N, 1, 6, 6))
        R6[:, 0, :3, :3] = R6[:, 0, 3:, 3:] = RT
        basis_t, basis_e = R6 @ basis_t, R6 @ basis_e
        wstar[:, :3] = RT @ _EZ
    return basis_t, basis_e, wstar, np.stack([eef_normals_W, t1_e, t2_e], axis=-1)


def _lp_data(rows, basis_t, basis_e, U, null, rank, wstar, p: Params):
    """Wrench matrix rows of candidates ``rows`` in the eigenbasis ``U`` of their Gram matrix with the
    null rows dropped, and w* there."""
    gs = p.n_sides
    G = np.concatenate([wrench_matrix(basis_t[rows], p.mu_table, gs),
                        wrench_matrix(basis_e[rows], p.mu_eef, gs)], axis=2)
    Ur, nl = U[rows], null[rows]
    rot = rank[rows] < 6
    if np.any(rot):
        G[rot] = np.where(nl[rot][:, :, None], 0.0, np.swapaxes(Ur[rot], 1, 2) @ G[rot])
    b = np.where(nl, 0.0, np.einsum("nji,nj->ni", Ur, wstar[rows]))
    return G, b


def _l1_margins(G, b, U, null, alpha, u, colmask, W, ng: int, p: Params) -> tuple[np.ndarray, int]:
    """L1 wrench margins (N) of stable candidates (§4.3): the least of 12 ray LPs from the weight's
    wrench (scaled to ``min(alpha, 1)``) along +-e_k projected onto span(G) (identity when rank 6),
    unit L1 length, in the eigenbasis ``U``; with the HiGHS fallbacks' count."""
    Ur = np.where(null[:, None, :], 0.0, U)  # row k of Ur is U^T P e_k
    Pe = Ur @ np.swapaxes(U, 1, 2)                          # column k = P e_k
    valid = np.linalg.norm(Pe, axis=1) > 1e-6
    # A direction (almost) normal to the span is skipped: d = 0 runs t to the cap, ignored below.
    dk = np.where(valid[:, :, None], Ur / np.maximum(np.abs(Pe).sum(1), tol.zero)[:, :, None], 0.0)
    d12 = np.concatenate([dk, -dk], axis=1)                      # (S, 12, 6)
    centre = np.minimum(alpha, 1.0)[:, None, None] * b[:, None, :]
    t, fb = _solve_with_fallback(G, centre, d12, u, np.full(len(alpha), p.margin_cap), ng, p.n_sides, colmask, p)
    t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, p.margin_cap)
    t = np.where(np.concatenate([valid, valid], 1), t, p.margin_cap)
    return t.min(1) * W, int(fb.sum())


def _first_verdicts(s_pf, u_pf, degenerate, alpha, feas_tol: float):
    """What :func:`evaluate` knows before its feasibility LPs: ``(stable, decided, decided_by, alpha)``
    from the rank test (``degenerate``) and the prefilter's sure verdicts (``s_pf`` stable, ``u_pf``
    unstable), or, with ``alpha`` given (an earlier call's), every verdict from it."""
    N = len(degenerate)
    stable = s_pf.copy()
    decided = degenerate | s_pf | u_pf
    decided_by = np.full(N, "ipm", dtype="<U8")
    decided_by[degenerate] = "rank"
    decided_by[s_pf | u_pf] = "filter"
    if alpha is None:
        return stable, decided, decided_by, np.where(s_pf, np.inf, 0.0)
    alpha = np.asarray(alpha, float)
    if alpha.shape != (N,) or np.any(np.isnan(alpha)):
        raise PivotError(f"stability: alpha has shape {alpha.shape}, expected ({N},) without NaN")
    decided_by[:] = "given"
    return ~degenerate & (alpha >= 1.0 - feas_tol), np.ones(N, bool), decided_by, alpha


def _reasons(stable, degenerate, margin, margin_min: float):
    """``(stable, reason)``: ``ok``, ``unstable``, ``degenerate``, or ``low_margin`` for a stable
    candidate whose margin is under ``margin_min`` (N; 0: no such test), which is then not stable."""
    reason = np.full(len(stable), "ok", dtype="<U10")
    reason[~stable] = "unstable"
    reason[degenerate] = "degenerate"
    if margin_min > 0:
        low = stable & (margin < margin_min)
        stable = stable & ~low
        reason[low] = "low_margin"
    return stable, reason


def evaluate(mass, com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L,
             params: Params = Params(), *, R_WD=None, compute_margin: bool = True,
             alpha: np.ndarray | None = None) -> StabilityResult:
    """Grasp stability and L1 wrench margin of N candidates (§4.3, eq. 1–4).

    Parameters
    ----------
    mass : float or (N,) float
        Object mass (kg).
    com_W : (N, 3) float
        Centre of mass (m), W.
    table_pts_W : (N, k, 3) float
        Object points touching the table (m), W; table normal +z.
    table_mask : (N, k) bool or None
        Active table contacts (None: all).
    eef_pts_W : (N, e, 3) float
        EEF contact points on the object surface (m), W.
    eef_normals_W : (N, e, 3) float
        Inward surface normals at the EEF contacts (pointing into the object), W; normalised here.
    eef_mask : (N, e) bool or None
        Active EEF contacts (None: all).
    L : float or (N,) float
        Characteristic length (m) dividing the torques, e.g. the object's bounding radius.
    params : Params
    R_WD : (3, 3) or (N, 3, 3) float, optional
        Orientation of the frame D whose axes define the L1 margin ball (default W).
    compute_margin : bool
        Compute margins of the stable candidates (always done when ``params.margin_min > 0``).
    alpha : (N,) float, optional
        ``StabilityResult.alpha`` of an earlier call on the same candidates (any ``R_WD``): the
        feasibility LPs are skipped and the verdicts taken from it.

    Returns
    -------
    StabilityResult
    """
    c = _clean_inputs(mass, com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L)
    mass, com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L = c
    N, e = com_W.shape[0], eef_pts_W.shape[1]
    p = params
    W = mass * p.g

    basis_t, basis_e, wstar, eef_frames = _unit_wrenches(com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W,
                                                         eef_mask, L, R_WD)
    M = wrench_gram(basis_t, p.mu_table, p.n_sides) + wrench_gram(basis_e, p.mu_eef, p.n_sides)
    rank, U, null, in_span = _rank_and_span(M, wstar)
    degenerate = ~in_span

    s_pf, u_pf = _prefilter(W, com_W, table_pts_W, table_mask, eef_pts_W, eef_mask, eef_frames, p)
    s_pf, u_pf, known = s_pf & ~degenerate, u_pf & ~degenerate, alpha is not None
    stable, decided, decided_by, alpha = _first_verdicts(s_pf, u_pf, degenerate, alpha, p.feas_tol)
    todo = np.nonzero(~decided)[0]
    want_margin = compute_margin or p.margin_min > 0
    stats = {"n": N, "degenerate": int(degenerate.sum()), "prefilter": 0 if known else int((s_pf | u_pf).sum()),
             "feasibility_lps": len(todo), "margin_lps": 0, "highs_fallbacks": 0}
    ng, gs = e, p.n_sides
    colmask = np.repeat(np.concatenate([table_mask, eef_mask], 1), gs, axis=1)
    u = np.repeat((p.f_max / W)[:, None], e, 1)

    if len(todo):
        G, b = _lp_data(todo, basis_t, basis_e, U, null, rank, wstar, p)
        t, fb = _solve_with_fallback(G, np.zeros((len(todo), 1, 6)), b[:, None, :], u[todo],
                                     np.full(len(todo), ALPHA_CAP), ng, gs, colmask[todo], p)
        alpha[todo] = np.nan_to_num(t[:, 0], nan=0.0)
        stable[todo] = alpha[todo] >= 1.0 - p.feas_tol
        decided_by[todo[fb[:, 0]]] = "highs"
        stats["highs_fallbacks"] += int(fb.sum())

    margin = np.where(stable, np.nan, 0.0)
    sel = np.nonzero(stable)[0] if want_margin else np.zeros(0, int)
    if len(sel):
        G, b = _lp_data(sel, basis_t, basis_e, U, null, rank, wstar, p)
        margin[sel], fallbacks = _l1_margins(G, b, U[sel], null[sel], alpha[sel], u[sel], colmask[sel], W[sel], ng, p)
        stats["margin_lps"] = 12 * len(sel)
        stats["highs_fallbacks"] += fallbacks
    stable, reason = _reasons(stable, degenerate, margin, p.margin_min)
    return StabilityResult(stable=stable, margin=margin, reason=reason, rank=rank.astype(np.int64),
                           decided_by=decided_by, alpha=alpha, stats=stats)


def evaluate_threaded(mass, com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L,
                      params: Params = Params(), *, R_WD=None, compute_margin: bool = True, alpha=None,
                      threads: int = 2, min_rows: int = 1024) -> StabilityResult:
    """:func:`evaluate` on ``threads`` equal slices of the N candidates at once (numpy releases the GIL
    in the solver's kernels; ~1.4x on 2 cores). Each candidate's result depends only on its own
    inputs, so the answer equals :func:`evaluate`'s exactly."""
    com_W = np.asarray(com_W, float)
    N = len(com_W)
    if threads <= 1 or N < min_rows:
        return evaluate(mass, com_W, table_pts_W, table_mask, eef_pts_W, eef_normals_W, eef_mask, L, params,
                        R_WD=R_WD, compute_margin=compute_margin, alpha=alpha)
    from concurrent.futures import ThreadPoolExecutor

    def rows(v, idx):
        return v if v is None or np.ndim(v) == 0 or len(v) != N else np.asarray(v)[idx]

    def part(idx):
        return evaluate(rows(mass, idx), com_W[idx], rows(table_pts_W, idx), rows(table_mask, idx),
                        rows(eef_pts_W, idx), rows(eef_normals_W, idx), rows(eef_mask, idx), rows(L, idx), params,
                        R_WD=None if R_WD is None or np.ndim(R_WD) == 2 else np.asarray(R_WD)[idx],
                        compute_margin=compute_margin, alpha=rows(alpha, idx))

    with ThreadPoolExecutor(threads) as pool:
        parts = list(pool.map(part, np.array_split(np.arange(N), threads)))
    stats = {k: sum(p.stats.get(k, 0) for p in parts) for k in parts[0].stats}
    return StabilityResult(*(np.concatenate([getattr(p, f) for p in parts])
                             for f in ("stable", "margin", "reason", "rank", "decided_by", "alpha")), stats=stats)


def least_eef_forces(mass, com_W, table_pts_W, eef_pts_W, eef_normals_W, params: Params = Params()):
    """The smallest EEF forces that hold the object still on its table contacts (eq. 1–3, one LP).

    The forces ``f_i`` of the EEFs and of the table points, each in its friction pyramid (``mu_eef``,
    ``mu_table``; an EEF's normal force at most ``f_max``), balance gravity (``Σ f = m g ẑ``, ``Σ r × f
    = 0`` about the CoM), and the EEFs' total normal force is least. What a ball that holds an object
    alone in USP (§4.3: two table vertices and one EEF) must push with, fed forward in execution.

    Parameters
    ----------
    mass : float (kg)
    com_W : (3,) CoM (m), W.
    table_pts_W : (k, 3) where the object touches the table (m), W; the table's normal is +z.
    eef_pts_W, eef_normals_W : (e, 3) EEF contact points (m) and inward normals, W.

    Returns ``(f_eef (e, 3), f_table (k, 3))`` in N, W (forces on the object), or None when no forces
    hold it.
    """
    com_W = np.asarray(com_W, float)
    pts = np.concatenate([np.asarray(table_pts_W, float).reshape(-1, 3), np.asarray(eef_pts_W, float).reshape(-1, 3)])
    k, e = len(pts) - len(np.asarray(eef_pts_W).reshape(-1, 3)), len(np.asarray(eef_pts_W).reshape(-1, 3))
    n = np.concatenate([np.tile([0.0, 0.0, 1.0], (k, 1)), np.asarray(eef_normals_W, float).reshape(-1, 3)])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t1, t2 = contact_frames(n, pts - com_W)
    s = params.n_sides
    mu = np.r_[np.full(k, params.mu_table), np.full(e, params.mu_eef)]
    C = np.stack([edge_coefficients(m, s) for m in mu])                            # (c, 3, s)
    edges = np.einsum("cij,cik->cjk", C, np.stack([n, t1, t2], axis=1))           # (c, s, 3) unit-normal edges
    E = edges.reshape(-1, 3)
    r = np.repeat(pts - com_W, s, axis=0)
    A_eq = np.vstack([E.T, np.cross(r, E).T])                                     # (6, c s)
    b_eq = np.r_[0.0, 0.0, mass * params.g, 0.0, 0.0, 0.0]
    cost = np.r_[np.zeros(k * s), np.ones(e * s)]                                # the EEFs' normal force
    A_ub = np.zeros((e, (k + e) * s))
    for i in range(e):  # each EEF's normal force within the payload bound
        A_ub[i, (k + i) * s:(k + i + 1) * s] = 1.0
    res = linprog(cost, A_ub=A_ub, b_ub=np.full(e, params.f_max), A_eq=A_eq, b_eq=b_eq, bounds=(0, None),
                  method="highs")
    if res.status != 0:
        return None
    f = (res.x.reshape(k + e, s)[:, :, None] * edges).sum(axis=1)
    return f[k:], f[:k]
