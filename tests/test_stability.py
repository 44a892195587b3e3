"""Tests of stages.stability: closed forms, HiGHS agreement, batch/loop and rigid-motion invariance."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import linprog

from stages import se3, stability
from stages.errors import PivotError
from stages.stability import (
    Params,
    contact_basis,
    contact_frames,
    evaluate,
    solve_ray_lp_highs,
    solve_ray_lps,
    wrench_matrix,
)

REPO = Path(__file__).resolve().parents[1]
G0 = 9.81
C30 = np.cos(np.pi / 6)  # inscribed radius of the unit hexagon: vertical friction of a side contact

# ----------------------------------------------------------------------------------------------------
# Scenes


def pinch(mu=0.5, f_max=50.0, mass=2.0, a=0.1, L=0.17):
    """A 0.2 m cube held in the air by two EEFs at the centres of its opposite x faces."""
    com = np.array([[0.0, 0.0, 0.3]])
    eef = np.array([[[a, 0.0, 0.3], [-a, 0.0, 0.3]]])
    nrm = np.array([[[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    kw = dict(mass=mass, com_W=com, table_pts_W=np.zeros((1, 0, 3)), table_mask=np.zeros((1, 0), bool),
              eef_pts_W=eef, eef_normals_W=nrm, eef_mask=np.ones((1, 2), bool), L=L)
    return kw, Params(mu_eef=mu, f_max=f_max)


def pinch_margin(mu, f_max, mass=2.0, a=0.1, L=0.17):
    """Closed-form L1 margin of :func:`pinch` (N): the smallest of its ray distances.

    The grasp cannot resist torque about x (rank 5), so the ball lies in the span: directions
    +-fx, +-fy, +-fz, +-ty, +-tz. Each EEF's friction lies in a hexagon of circumradius R = mu N with a
    vertex along the horizontal tangent, so the vertical reach is cos(pi/6) R and the side edge through
    (R, 0) is sqrt(3) x + y = sqrt(3) R; the weight splits evenly (torques about y and z balanced).
    """
    W = mass * G0
    R = mu * f_max
    lift = 2 * C30 * R                           # largest total vertical friction
    side = R - W / (2 * np.sqrt(3))              # largest horizontal friction per EEF carrying W / 2
    eps = {
        "fx": f_max - W / (2 * mu * C30),        # squeeze imbalance; each N >= W / (2 mu cos 30)
        "fy": 2 * side,
        "+fz": lift - W,
        "-fz": lift + W,
        "ty": (lift - W) * a / L,                # fz2 - fz1 = eps L / a
        "tz": 2 * side * a / L,                  # fy1 - fy2 = eps L / a
    }
    return min(eps.values())


def tilted_cube_on_vertex(theta_deg=10.0, a=0.2):
    """Pose X_WO of a cube [0, a]^3 (O) standing on its corner O-origin, tilted about the horizontal
    axis perpendicular to the corner-to-CoM direction so that the other corners leave the table."""
    axis = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    return se3.make_transform(se3.rotation_about_axis(axis, np.deg2rad(theta_deg)), np.zeros(3))


def pivot_scene(f_max=50.0, mu=0.5, theta_deg=10.0, a=0.2, mass=2.0):
    """The tilted cube on one table vertex, pinched on its x faces high up, beyond the CoM."""
    X = tilted_cube_on_vertex(theta_deg, a)
    p_O = np.array([[0.0, 0.6 * a, 0.8 * a], [a, 0.6 * a, 0.8 * a]])
    n_O = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    kw = dict(mass=mass, com_W=se3.transform_points(X, np.full(3, a / 2))[None],
              table_pts_W=np.zeros((1, 1, 3)), table_mask=np.ones((1, 1), bool),
              eef_pts_W=se3.transform_points(X, p_O)[None], eef_normals_W=se3.rotate_vectors(X, n_O)[None],
              eef_mask=np.ones((1, 2), bool), L=a * np.sqrt(3) / 2)
    return kw, Params(mu_eef=mu, f_max=f_max)


def edge_hold(f_max=50.0, mu_eef=0.0, with_eef=True, mass=2.0):
    """USP hold: an object resting on a table edge (two points on x = 0), CoM 5 cm beyond it, one EEF
    pressing straight down 10 cm on the other side of the edge (an L-shaped prism's foot)."""
    kw = dict(mass=mass, com_W=np.array([[0.05, 0.0, 0.15]]),
              table_pts_W=np.array([[[0.0, -0.1, 0.0], [0.0, 0.1, 0.0]]]), table_mask=np.ones((1, 2), bool),
              eef_pts_W=np.array([[[-0.1, 0.0, 0.2]]]), eef_normals_W=np.array([[[0.0, 0.0, -1.0]]]),
              eef_mask=np.full((1, 1), with_eef), L=0.2)
    return kw, Params(mu_eef=mu_eef, f_max=f_max)


def random_scenes(rng, n, k, e, mask_prob=0.15):
    """Generic candidates: table points in a 0.2 m disc on z = 0, CoM above, EEF points on a sphere
    around the CoM with inward normals tilted by up to about 35 degrees, random masks."""
    com = np.column_stack([rng.uniform(-0.08, 0.08, (n, 2)), rng.uniform(0.1, 0.3, n)])
    ang = rng.uniform(0, 2 * np.pi, (n, k))
    rad = 0.2 * np.sqrt(rng.uniform(0.05, 1, (n, k)))
    table = np.stack([rad * np.cos(ang), rad * np.sin(ang), np.zeros((n, k))], -1)
    d = rng.normal(size=(n, e, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    eef = com[:, None, :] + 0.15 * d
    nrm = -d + 0.4 * rng.uniform(-1, 1, (n, e, 3))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    return dict(mass=rng.uniform(0.5, 4.0), com_W=com, table_pts_W=table,
                table_mask=rng.random((n, k)) > mask_prob, eef_pts_W=eef, eef_normals_W=nrm,
                eef_mask=rng.random((n, e)) > mask_prob, L=0.2)


CASES = [(4, 0), (4, 2), (1, 2), (2, 1), (3, 1), (0, 2), (6, 2)]


@pytest.fixture(params=["filters", "lp_only"])
def route(request, monkeypatch):
    """Run a test twice: as shipped, and with the closed-form pre-filters off (every verdict by LP)."""
    if request.param == "lp_only":
        import stages.stability as st
        monkeypatch.setattr(st, "_prefilter", lambda W, com, *a: (np.zeros(len(com), bool),) * 2)
    return request.param


# ----------------------------------------------------------------------------------------------------
# Independent reference: wrench columns by explicit loops, LPs by HiGHS.


def reference_columns(kw, i, p):
    """Wrench columns (about the CoM, torque / L, in W) and EEF groups of candidate i."""
    c = kw["com_W"][i]
    L = kw["L"]
    cols, groups = [], []
    th = 2 * np.pi * np.arange(p.n_sides) / p.n_sides
    contacts = [(q, np.array([0.0, 0.0, 1.0]), p.mu_table, None)
                for q, m in zip(kw["table_pts_W"][i], kw["table_mask"][i], strict=True) if m]
    contacts += [(q, nn / np.linalg.norm(nn), p.mu_eef, j) for j, (q, nn, m) in
                 enumerate(zip(kw["eef_pts_W"][i], kw["eef_normals_W"][i], kw["eef_mask"][i], strict=True))
                 if m]
    for q, nn, mu, grp in contacts:
        r = q - c
        t1, t2 = contact_frames(nn, r)            # the pyramid orientation rule is part of the model
        for tj in th:
            v = nn + mu * (np.cos(tj) * t1 + np.sin(tj) * t2)
            cols.append(np.concatenate([v, np.cross(r, v) / L]))
            groups.append(grp)
    G = np.array(cols).T.reshape(6, -1)
    return G, groups


def reference_ray(G, groups, f_max, centre, direction, cap):
    """max t s.t. G lam = centre + t direction, lam >= 0, each EEF's sum <= f_max, t <= cap (HiGHS)."""
    n = G.shape[1]
    ids = sorted({g for g in groups if g is not None})
    A_ub = np.array([[1.0 if g == j else 0.0 for g in groups] + [0.0] for j in ids]).reshape(len(ids), n + 1)
    res = linprog(np.r_[np.zeros(n), -1.0], A_ub=A_ub if ids else None,
                  b_ub=np.full(len(ids), f_max) if ids else None,
                  A_eq=np.hstack([G, -direction[:, None]]), b_eq=centre,
                  bounds=[(0, None)] * n + [(0, cap)], method="highs")
    return res.x[-1] if res.status == 0 else -np.inf


# ----------------------------------------------------------------------------------------------------
# Closed forms


def test_pinch_holds_above_analytic_friction_threshold_and_slips_below(route):
    kw, p = pinch()
    mu_star = kw["mass"] * G0 / (2 * p.f_max * C30)
    # The load factor alpha is mu / mu_star here; +-1e-4 is 100x the decision tolerance feas_tol.
    hold = evaluate(**kw, params=Params(mu_eef=mu_star * 1.0001, f_max=p.f_max))
    slip = evaluate(**kw, params=Params(mu_eef=mu_star * 0.9999, f_max=p.f_max))
    assert hold.stable[0] and hold.reason[0] == "ok" and hold.decided_by[0] == "ipm"
    assert not slip.stable[0] and slip.reason[0] == "unstable"
    assert hold.rank[0] == 5                     # two point contacts: a free hinge about their line


def test_pinch_load_factor_from_the_batched_lp_is_the_friction_ratio():
    # The ray LP alone: alpha* = 2 mu cos30 f_max / (m g) (capped at 2). The IPM's residuals are
    # 1e-8 of the weight, so alpha* is exact to ~1e-8; 1e-7 relative.
    kw, p = pinch()
    W = kw["mass"] * G0
    r = kw["eef_pts_W"] - kw["com_W"][:, None]
    t1, t2 = contact_frames(kw["eef_normals_W"], r)
    mus = np.array([0.15, 0.2, 0.3, 0.6])
    G = np.concatenate([wrench_matrix(contact_basis(r, kw["eef_normals_W"], t1, t2, kw["eef_mask"],
                                                    np.array([kw["L"]])), mu, 6) for mu in mus])
    assert np.all(G[:, 3] == 0)                  # no torque about the grasp line: that row is dropped
    b = np.zeros((len(mus), 1, 6))
    d = np.broadcast_to([0, 0, 1.0, 0, 0, 0], (len(mus), 1, 6))
    t, conv, _ = solve_ray_lps(G, b, d, np.full((len(mus), 2), p.f_max / W), np.full(len(mus), 2.0), 2, 6)
    assert conv.all()
    np.testing.assert_allclose(t[:, 0], np.minimum(2.0, 2 * mus * C30 * p.f_max / W), rtol=1e-7)


def test_pinch_margin_matches_closed_form():
    # The IPM stops at residuals and complementarity of 1e-8 in units of the weight m g, which leaves
    # the optimum within ~1e-7 m g (observed <= 9e-8 m g): 1e-6 m g absolute, 1e-6 relative.
    for mu, f_max in [(0.5, 50.0), (1.0, 50.0), (0.3, 40.0), (0.8, 25.0)]:
        kw, p = pinch(mu, f_max)
        res = evaluate(**kw, params=p)
        assert res.stable[0]
        assert res.margin[0] == pytest.approx(pinch_margin(mu, f_max), rel=1e-6, abs=1e-6 * 2.0 * G0)


def test_pinch_margin_shrinks_with_f_max_and_vanishes_at_the_limit(route):
    kw, _ = pinch()
    W = kw["mass"] * G0
    f_star = W / (2 * 0.5 * C30)                 # 2 mu cos30 f_max = m g
    fs = np.linspace(60.0, f_star * 1.0001, 12)
    m = np.array([evaluate(**kw, params=Params(mu_eef=0.5, f_max=f)).margin[0] for f in fs])
    assert np.all(np.diff(m) < 0)
    np.testing.assert_allclose(m, [pinch_margin(0.5, f) for f in fs], rtol=1e-6, atol=1e-6 * 2.0 * G0)
    # 1e-4 above the limit the margin is (2 mu cos30 f - m g) a / L ~ 1e-3 N.
    assert 0 < m[-1] < 2e-3
    below = evaluate(**kw, params=Params(mu_eef=0.5, f_max=f_star * 0.9999))
    assert not below.stable[0] and below.margin[0] == 0.0


def test_normal_bound_keeps_the_whole_force_in_the_pyramid_within_the_magnitude():
    """3-4-5: with mu = 0.75 a normal force of 40 N and friction at the cone's edge (30 N) make 50 N."""
    assert stability.normal_bound(50.0, 0.75) == pytest.approx(40.0)
    assert stability.normal_bound(50.0, 0.0) == 50.0
    n = stability.normal_bound(45.0, 0.4)
    assert np.hypot(n, 0.4 * n) == pytest.approx(45.0) and n < 45.0


def test_cube_on_one_vertex_falls_without_eef():
    kw, p = pivot_scene()
    kw.update(eef_pts_W=np.zeros((1, 0, 3)), eef_normals_W=np.zeros((1, 0, 3)), eef_mask=np.zeros((1, 0), bool))
    res = evaluate(**kw, params=p)
    # One point cannot exert torque about itself (rank 3) and gravity has a moment about it.
    assert not res.stable[0] and res.reason[0] == "degenerate" and res.rank[0] == 3


def test_cube_on_one_vertex_held_by_two_eefs_needs_enough_force(route):
    kw, p = pivot_scene()
    res = evaluate(**kw, params=p)
    assert res.stable[0] and res.rank[0] == 6 and res.margin[0] > 0
    # Required moment about the vertex is m g times the CoM's horizontal offset (~2.4 N m); 1 N per EEF
    # at most sqrt(1 + mu^2) N at ~0.25 m cannot give it.
    weak = evaluate(**kw, params=Params(mu_eef=p.mu_eef, f_max=1.0))
    assert not weak.stable[0] and weak.reason[0] == "unstable"


def test_box_resting_on_its_face_is_stable_without_eef(route):
    corners = np.array([[[x, y, 0.0] for x, y in ((-0.1, -0.1), (0.1, -0.1), (0.1, 0.1), (-0.1, 0.1))]])
    kw = dict(mass=2.0, com_W=np.array([[0.02, -0.01, 0.1]]), table_pts_W=corners,
              table_mask=np.ones((1, 4), bool), eef_pts_W=np.zeros((1, 0, 3)),
              eef_normals_W=np.zeros((1, 0, 3)), eef_mask=np.zeros((1, 0), bool), L=0.17)
    res = evaluate(**kw)
    assert res.stable[0] and res.rank[0] == 6
    assert res.decided_by[0] == ("filter" if route == "filters" else "ipm")
    # Pulling up by more than the weight lifts it: the -fz ray ends at exactly m g.
    assert 0 < res.margin[0] <= 2.0 * G0 * (1 + 1e-6)
    off = dict(kw, com_W=np.array([[0.13, 0.0, 0.1]]))
    assert not evaluate(**off).stable[0]
    # Every ray is longer than 1% of the weight, so a cap there is the margin (to LP accuracy).
    capped = evaluate(**kw, params=Params(margin_cap=0.01))
    assert capped.margin[0] == pytest.approx(0.01 * 2.0 * G0, rel=1e-6)


def test_overhanging_l_prism_falls_without_eef_and_one_eef_on_the_foot_holds_it(route):
    # L-shaped prism: its foot (x in [-0.2, 0]) rests on the table, the CoM is 5 cm beyond the foot.
    foot = np.array([[[x, y, 0.0] for x, y in ((-0.2, -0.1), (0.0, -0.1), (0.0, 0.1), (-0.2, 0.1))]])
    kw, p = edge_hold()
    kw.update(table_pts_W=foot, table_mask=np.ones((1, 4), bool))
    alone = evaluate(**dict(kw, eef_mask=np.zeros((1, 1), bool)), params=p)
    assert not alone.stable[0] and alone.reason[0] == "unstable"
    held = evaluate(**kw, params=p)
    assert held.stable[0] and held.margin[0] > 0


@pytest.mark.parametrize("flip", [False, True])
def test_usp_edge_hold_threshold_is_the_lever_rule(route, flip):
    # Frictionless EEF pressing down at 0.1 m from the edge, CoM 0.05 m beyond it: f_max >= m g / 2.
    # With mu_eef = 0.5 a pyramid edge points along -x (t1 is the radial direction for a vertical
    # normal) and friction adds 0.2 m of lever per newton: f_max >= 0.05 m g / (0.1 + 0.2 mu).
    # The load factor is f_max / f_star; +-1e-4 is 100x feas_tol. ``flip`` reverses the edge.
    W = 2.0 * G0
    for mu, f_star in ((0.0, W / 2), (0.5, 0.05 * W / (0.1 + 0.2 * 0.5))):
        kw, _ = edge_hold(mu_eef=mu)
        if flip:
            kw["table_pts_W"] = kw["table_pts_W"][:, ::-1]
        ok = evaluate(**kw, params=Params(mu_eef=mu, f_max=f_star * 1.0001))
        ko = evaluate(**kw, params=Params(mu_eef=mu, f_max=f_star * 0.9999))
        assert ok.stable[0] and ok.rank[0] == 6
        assert not ko.stable[0]
    kw, p = edge_hold(with_eef=False)
    res = evaluate(**kw, params=p)
    assert not res.stable[0] and res.reason[0] == "degenerate" and res.rank[0] == 5


def test_degenerate_contact_sets_are_reported_not_raised():
    kw, p = pinch()
    off = dict(kw, com_W=np.array([[0.0, 0.05, 0.3]]))      # CoM off the grasp line: gravity twists
    res = evaluate(**off, params=p)
    assert not res.stable[0] and res.reason[0] == "degenerate" and res.rank[0] == 5
    none = evaluate(**dict(kw, eef_mask=np.zeros((1, 2), bool)), params=p)
    assert none.reason[0] == "degenerate" and none.rank[0] == 0 and none.margin[0] == 0.0


def test_margin_min_turns_thin_grasps_into_low_margin():
    kw, _ = pinch()
    m = pinch_margin(0.5, 50.0)
    res = evaluate(**kw, params=Params(mu_eef=0.5, margin_min=m * 1.01))
    assert not res.stable[0] and res.reason[0] == "low_margin"
    assert evaluate(**kw, params=Params(mu_eef=0.5, margin_min=m * 0.99)).stable[0]


def test_bad_input_raises_pivot_error_and_masked_slots_may_be_nan():
    kw, p = pinch()
    with pytest.raises(PivotError):
        evaluate(**dict(kw, eef_mask=np.ones((1, 3), bool)), params=p)
    with pytest.raises(PivotError):
        evaluate(**dict(kw, mass=-1.0), params=p)
    with pytest.raises(PivotError):
        evaluate(**dict(kw, eef_normals_W=np.zeros((1, 2, 3))), params=p)
    with pytest.raises(PivotError):
        Params(f_max=0.0)
    kw3 = dict(kw, eef_pts_W=np.concatenate([kw["eef_pts_W"], np.full((1, 1, 3), np.nan)], 1),
               eef_normals_W=np.concatenate([kw["eef_normals_W"], np.full((1, 1, 3), np.nan)], 1),
               eef_mask=np.array([[True, True, False]]))
    a, b = evaluate(**kw3, params=p), evaluate(**kw, params=p)
    assert a.stable[0] == b.stable[0] and a.margin[0] == pytest.approx(b.margin[0], rel=1e-9)


# ----------------------------------------------------------------------------------------------------
# Solver agreement with HiGHS


def test_batched_ipm_matches_highs_on_random_lps():
    rng = np.random.default_rng(7)
    B, m, n, ng, gs, K = 150, 6, 30, 2, 6, 3
    G = rng.standard_normal((B, m, n))
    G[:, 0, :] = np.abs(G[:, 0, :]) + 0.2      # unbounded columns span a pointed cone
    b = rng.standard_normal((B, K, m)) * rng.choice([0.3, 3.0], (B, K, 1))   # some infeasible
    d = rng.standard_normal((B, K, m))
    u = rng.random((B, ng)) + 0.5
    cap = np.full(B, 5.0)
    t, conv, _ = solve_ray_lps(G, b, d, u, cap, ng, gs)
    ref = np.array([[solve_ray_lp_highs(G[i], b[i, q], d[i, q], u[i], cap[i], ng, gs) for q in range(K)]
                    for i in range(B)])
    assert 0 < np.isnan(ref).sum() < ref.size
    # Infeasible LPs never converge; feasible ones must (HiGHS would otherwise take over).
    np.testing.assert_array_equal(conv, ~np.isnan(ref))
    # IPM residuals are 1e-8 relative to |b| + 1 ~ 10; optima agree to 1e-6 absolute.
    np.testing.assert_allclose(t[conv], ref[conv], atol=1e-6)


@pytest.mark.parametrize("k,e", CASES)
def test_feasibility_and_margin_agree_with_highs(k, e):
    rng = np.random.default_rng(100 + 10 * k + e)
    kw = random_scenes(rng, 60, k, e)
    if k == 0:
        # Pinches: put the CoM on the grasp line (otherwise gravity twists them: degenerate).
        s = rng.uniform(0.5, 1.5, 60)[:, None]
        kw["eef_pts_W"][:, 1] = kw["com_W"] - s * (kw["eef_pts_W"][:, 0] - kw["com_W"])
    p = Params(f_max=float(rng.uniform(5, 60)), mu_eef=0.4, mu_table=0.6)
    res = evaluate(**kw, params=p)
    assert res.stats["highs_fallbacks"] == 0     # the batched IPM, not its fallback, is under test
    W = kw["mass"] * G0
    wstar = np.array([0, 0, W, 0, 0, 0.0])
    n_margin = 0
    for i in range(60):
        G, groups = reference_columns(kw, i, p)
        alpha = reference_ray(G, groups, p.f_max, np.zeros(6), wstar, 2.0) if G.size else -np.inf
        if abs(alpha - 1.0) < 1e-5:
            continue                              # on the boundary within solver tolerances
        assert res.stable[i] == (alpha >= 1.0), (i, alpha, res.reason[i])
        if res.stable[i] and res.rank[i] == 6 and n_margin < 8:
            n_margin += 1
            eps = [reference_ray(G, groups, p.f_max, wstar, s * np.eye(6)[j], p.margin_cap * W)
                   for j in range(6) for s in (1.0, -1.0)]
            # LP optima to 1e-8 relative residuals of a problem scaled by m g: 1e-6 m g absolute.
            assert res.margin[i] == pytest.approx(min(eps), rel=1e-6, abs=1e-6 * W)
    assert res.stable.any()


def test_prefilters_agree_with_the_lp(monkeypatch):
    # The same candidates with the closed-form filters bypassed (feasibility via one LP each).
    import stages.stability as st
    rng = np.random.default_rng(3)
    scenes = [(random_scenes(rng, 80, k, e), Params(f_max=f)) for k, e in CASES for f in (8.0, 20.0, 60.0)]
    # USP-like: the CoM beyond the table points (their disc has radius 0.2 m), held by one or two EEFs.
    for k, e in [(3, 1), (5, 1), (4, 2)]:
        for f in (8.0, 20.0, 60.0):
            kw = random_scenes(rng, 80, k, e)
            shift = np.array([0.22, 0.0, 0.0])
            kw["com_W"] = kw["com_W"] + shift
            kw["eef_pts_W"] = kw["eef_pts_W"] + shift
            scenes.append((kw, Params(f_max=f)))
    ref = [evaluate(**kw, params=p, compute_margin=False) for kw, p in scenes]
    monkeypatch.setattr(st, "_prefilter", lambda W, com, *a: (np.zeros(len(com), bool),) * 2)
    lp = [evaluate(**kw, params=p, compute_margin=False) for kw, p in scenes]
    assert sum((r.decided_by == "filter").sum() for r in ref) > 300
    for r, q in zip(ref, lp, strict=True):
        np.testing.assert_array_equal(r.stable, q.stable)


# ----------------------------------------------------------------------------------------------------
# Batch structure and invariance


@pytest.mark.parametrize("n", [0, 1, 25])
def test_batch_equals_loop(n):
    rng = np.random.default_rng(n)
    for k, e in [(4, 2), (1, 2), (2, 1)]:
        kw = random_scenes(rng, n, k, e)
        kw["mass"] = rng.uniform(0.5, 4.0, n)      # per-candidate masses
        batch = evaluate(**kw)
        assert batch.stable.shape == batch.margin.shape == batch.reason.shape == (n,)
        for i in range(n):
            one = evaluate(**{key: (v[i:i + 1] if isinstance(v, np.ndarray) else v) for key, v in kw.items()})
            assert one.stable[0] == batch.stable[i] and one.reason[0] == batch.reason[i]
            assert one.rank[0] == batch.rank[i]
            # Same arithmetic per LP; only BLAS blocking may differ.
            assert one.margin[0] == pytest.approx(batch.margin[i], rel=1e-9, abs=1e-12)


def test_invariant_under_rigid_motion_about_z():
    rng = np.random.default_rng(11)
    for k, e in CASES:
        kw = random_scenes(rng, 40, k, e)
        n = len(kw["com_W"])
        R0 = se3.rot_z(rng.uniform(-np.pi, np.pi, n))          # an object heading per candidate
        base = evaluate(**kw, R_WD=R0)
        X = se3.make_transform(se3.rot_z(rng.uniform(-np.pi, np.pi)), np.r_[rng.uniform(-1, 1, 2), 0.0])
        moved = dict(kw, com_W=se3.transform_points(X, kw["com_W"]),
                     table_pts_W=se3.transform_points(X, kw["table_pts_W"]),
                     eef_pts_W=se3.transform_points(X, kw["eef_pts_W"]),
                     eef_normals_W=se3.rotate_vectors(X, kw["eef_normals_W"]))
        res = evaluate(**moved, R_WD=X[:3, :3] @ R0)
        np.testing.assert_array_equal(res.stable, base.stable)
        np.testing.assert_array_equal(res.reason, base.reason)
        np.testing.assert_array_equal(res.rank, base.rank)
        # Rounding of the rotated inputs (1e-16) through LPs solved to 1e-8: 1e-6 relative.
        np.testing.assert_allclose(res.margin, base.margin, rtol=1e-6, atol=1e-9)


def test_margins_from_a_given_alpha_equal_a_full_evaluation():
    """The feasibility ray of a call without R_WD seeds the margins of a call with it."""
    rng = np.random.default_rng(21)
    for k, e in [(1, 2), (4, 2), (3, 1)]:
        kw = random_scenes(rng, 40, k, e)
        R = se3.rotation_about_axis(np.array([0.0, 0.0, 1.0]), rng.uniform(-np.pi, np.pi, 40))
        full = evaluate(**kw, R_WD=R)
        first = evaluate(**kw, compute_margin=False)
        given = evaluate(**kw, R_WD=R, alpha=first.alpha)
        np.testing.assert_array_equal(given.stable, full.stable)
        np.testing.assert_array_equal(given.reason, full.reason)
        assert given.stats["feasibility_lps"] == 0
        # Same LPs from the same start; BLAS blocking may differ with the batch.
        np.testing.assert_allclose(given.margin, full.margin, rtol=1e-9, atol=1e-12)


def test_threaded_evaluation_equals_the_serial_one():
    # By path: bench/ is not a package on sys.path under the plain `pytest` entry point.
    spec = importlib.util.spec_from_file_location("bench_stability", REPO / "bench" / "bench_stability.py")
    bs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bs)

    for case in bs.make_candidates(3000, 1).values():
        args = [case[k] for k in ("mass", "com_W", "table_pts_W", "table_mask", "eef_pts_W", "eef_normals_W",
                                  "eef_mask", "L")]
        a = stability.evaluate(*args, R_WD=case["R_WD"])
        b = stability.evaluate_threaded(*args, R_WD=case["R_WD"], min_rows=10)
        for f in ("stable", "margin", "reason", "rank"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_least_eef_force_holding_an_overhang_is_the_lever_rule():
    """A 2 kg box resting on the table over x in [-0.3, 0] (the table's edge at x = 0), its CoM 5 cm past
    the edge: a frictionless ball pressing down on its top at x = -0.2 must carry m g 0.05 / 0.2 (torques
    about the edge), the edge the rest; a ball pressing down past the edge cannot hold it."""
    m, g = 2.0, 9.81
    com = np.array([0.05, 0.0, 0.1])
    table = np.array([[0.0, -0.1, 0.0], [0.0, 0.1, 0.0], [-0.3, -0.1, 0.0], [-0.3, 0.1, 0.0]])
    prm = stability.Params(mu_eef=1e-9, mu_table=0.5, f_max=50.0)
    f, f_table = stability.least_eef_forces(m, com, table, np.array([[-0.2, 0.0, 0.2]]), np.array([[0, 0, -1.0]]),
                                            prm)
    np.testing.assert_allclose(f[0], [0.0, 0.0, -m * g * 0.05 / 0.2], atol=1e-6)
    np.testing.assert_allclose(f_table.sum(axis=0) + f[0], [0.0, 0.0, m * g], atol=1e-6)
    assert stability.least_eef_forces(m, com, table, np.array([[0.1, 0.0, 0.2]]), np.array([[0, 0, -1.0]]),
                                      prm) is None
    # More than the payload bound: not held either (the ball would have to carry m g 0.05 / 0.001).
    assert stability.least_eef_forces(m, com, table, np.array([[-0.001, 0.0, 0.2]]), np.array([[0, 0, -1.0]]),
                                      prm) is None


def test_a_ball_on_the_inboard_side_holds_an_overhang_only_by_its_friction():
    """The box of the lever-rule test (CoM 5 mm past the table's edge at x = 0): a ball on its inboard
    side face (x = -0.3, pushing +x, 5 cm up) turns it back onto the table only by dragging that face
    down, which needs friction: held with the ball's friction at 0.4, not at 0.15 (0.3 of 0.5, the
    sampler's and graph's ``hold_eef_friction``); a ball pressing down on the top inboard holds it with
    none."""
    m = 2.0
    com = np.array([0.005, 0.0, 0.1])
    table = np.array([[0.0, -0.1, 0.0], [0.0, 0.1, 0.0], [-0.3, -0.1, 0.0], [-0.3, 0.1, 0.0]])[None]
    side = (np.array([[[-0.3, 0.0, 0.05]]]), np.array([[[1.0, 0.0, 0.0]]]))
    top = (np.array([[[-0.2, 0.0, 0.2]]]), np.array([[[0.0, 0.0, -1.0]]]))

    def held(ball, mu_eef):
        prm = stability.Params(mu_eef=mu_eef, mu_table=0.4, f_max=50.0)
        return bool(stability.evaluate(m, com[None], table, None, *ball, None, 0.3, prm,
                                       compute_margin=False).stable[0])

    assert held(side, 0.4) and not held(side, 0.15)
    assert held(top, 1e-9)
