"""The paper's three experiments (§6.3–6.5) as scenes under ``data/scenes/``: each needs the feature its
experiment shows, and the planner's ablations (``plan.Params(no_regrasp=, no_tumble=, no_usp=)``) lose it.

- ``exp1_reach`` (§6.3, Fig. 16, Table 2): the upright piano, keyboard toward the robot, goes 0.37 m
  forward (CoM x -0.10 -> +0.27, y 0 -> -0.025) with 30° pivots, the robot's base 0.29 m behind the
  table's near edge (x -0.74). The first grasp pivots it twice (CoM at x +0.132, y -0.025), where its
  next pivots fail (the MPC, or the right arm's link 5 in the table); the full plan regrasps (6 pivots,
  2 regrasps), and without regrasping it ends there: -13.8 cm along x and 0.0 cm along y, against
  Table 2's -12.5 cm along x for the graph MPC of [3] (``test_exp1_error_as_in_table_2``). That stop
  does not move with the goal: goals 1-3 cm further along x end there too (-12.8 to -15.8 cm), but
  the layout is not robust to the goal: 2 cm nearer (x +0.25), or 2 cm to the left, the first grasp
  reaches it, and 2 cm to the right the full planner finds no path.
- ``exp2_rotate`` (§6.4, Fig. 17): a -90° turn about z in place (yaw -90° -> -180°); the grasp that
  starts the turn cannot finish it, the plan regrasps twice (pivot, regrasp, pivot, regrasp, pivots).
- ``exp3_obstacle`` (§6.5, Fig. 18): the upright piano, turned 130°, on a narrow table (0.6 m deep,
  0.7 m wide), a pen holder in front of it (+x, at (0.22, 0.22)); the goal lies on the piano's front
  face by the table's right edge, at (-0.016, -0.213), yaw 130°. The paper's plan pivots it once, tumbles it
  over the right edge into USP onto the catcher's (right) ball waiting under the overhang, and
  regrasps there one ball at a time (Fig. 18 e-f), each move made while the other ball alone holds the
  piano by its normal force: the pusher (left) presses it onto the table from above, inboard (a hold
  node), while the catcher moves to the outboard face; then the pusher moves to its grasp contact
  while the catcher's ball holds alone. That grasp pivots it back into SP at the goal (USP regrasps:
  2); without tumbling or without USP it had no plan. One-ball holds are checked with 0.3 of the ball's
  friction (``hold_eef_friction``): the hand-overs found with 0.8 of it (the pusher on the inboard
  side face, holding by friction) tipped the piano in physics, the ball pressing as planned. In
  PyBullet the nominal run and seeds 1-10 succeeded by issue 15's criteria (released, at rest, within
  the 50 N bound) until its USP margin (2 cm) refused the USP pose this route needs, whose CoM lies
  0.31 mm past the table's edge (``EXP3_NO_USP_ROUTE``). The plan found instead stays in SP: two
  pivots, a squeeze tumble onto the front face on the table, then pivots and regrasps along the
  table's right edge to the goal; it succeeds in physics. Without tumbling there is no plan. The pen
  holder does not decide the route: the goal lies on another face, which only a tumble reaches.
"""

from pathlib import Path

import numpy as np
import pytest

from stages import artifacts, graph, plan, sample, se3
from stages.objectmodel import load_object_model
from stages.scene import PlacementSpec, load_scene

# One xdist worker runs every test of the reference chains, built once per session (conftest).
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("reference")]

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "data" / "scenes"
EXPERIMENTS = ("exp1_reach", "exp2_rotate", "exp3_obstacle")
#: Issue 15's USP margin (``poses.Params.usp_margin``) refuses the paper's route for Exp. 3: the truth, kept.
EXP3_NO_USP_ROUTE = pytest.mark.xfail(strict=True, reason=(
    "issue 15: the paper's Exp. 3 route tumbles into a USP pose whose CoM lies 0.31 mm past the table's "
    "edge; with usp_margin = 2 cm that pose is neither SP nor USP and is refused; the plan found tumbles "
    "onto the goal's face on the table (SP) instead"))


class Builds:
    """Each scene's chain with the full planner from the session's ``reference_chain`` (the golden
    test's, run once), and each ablation's plan once, beside it."""

    def __init__(self, root: Path, reference):
        self.root = root
        self.reference = reference
        self.analysis = reference(EXPERIMENTS[0]).analysis
        self.model, _ = load_object_model(self.analysis)
        self._plans: dict = {}

    def scene(self, name: str) -> Path:
        return SCENES / f"{name}.json"

    def build(self, name: str) -> Path:
        return self.reference(name).build

    def plan(self, name: str, **ablation) -> dict:
        key = (name, tuple(sorted(ablation.items())))
        if key not in self._plans:
            b = self.build(name)
            tag = "_".join(k for k, v in sorted(ablation.items()) if v) or "full"
            if tag == "full":
                self._plans[key] = artifacts.read_json(b / "full" / "plan.json", "plan")
            else:
                self._plans[key] = plan.run(self.scene(name), self.analysis, b / "sample", b / "graph",
                                            self.root / name / f"plan_{tag}.json", plan.Params(**ablation))
        return self._plans[key]

    def goal(self, name: str) -> np.ndarray:
        X, _ = sample.placement_pose(load_scene(self.scene(name)).goal, self.model, "goal")
        return X


@pytest.fixture(scope="module")
def builds(tmp_path_factory, reference_chain) -> Builds:
    return Builds(tmp_path_factory.mktemp("experiments"), reference_chain)


def _pose(cols: dict) -> np.ndarray:
    return se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in cols.items()})[0]


def _assert_reaches_goal(builds: Builds, name: str, p: dict) -> None:
    assert p["status"] == "ok", (p["status"], p.get("reason"), p["log"][-3:])
    np.testing.assert_allclose(_pose(p["steps"][-1]["X_WO_to"]), builds.goal(name), atol=1e-6)
    for prim in ("pivot", "tumble"):
        assert p["counts"][prim] == sum(s["primitive"] == prim for s in p["steps"])


def _com(builds: Builds, X: np.ndarray) -> np.ndarray:
    return se3.transform_points(X, builds.model.com)


@pytest.mark.parametrize(("name", "dx", "dyaw"), [("exp1_reach", 0.02, 0), ("exp1_reach", 0, -10),
                                                   ("exp2_rotate", -0.02, 0), ("exp2_rotate", 0, 10)])
def test_an_experiment_still_plans_with_its_goal_moved_2_cm_or_10_deg(builds, tmp_path, name, dx, dyaw):
    """Reaching the goal is the planner's property, not the lattice's luck (issue 14): Exp. 1 and 2
    plan to their goal moved 2 cm along the table's x, one way for each, or turned 10 deg, the other
    way for each (the benchmark's cases measure the property broadly)."""
    from tests.conftest import write_scene

    g = load_scene(SCENES / f"{name}.json").goal
    path = write_scene(tmp_path, f"{name}-moved", base=name,
                       **{"goal.xy": [g.xy[0] + dx, g.xy[1]], "goal.yaw_deg": g.yaw_deg + dyaw})
    sample.run(path, builds.analysis, tmp_path / "sample", sample.Params())
    graph.run(path, builds.analysis, tmp_path / "sample", tmp_path / "graph", graph.Params())
    p = plan.run(path, builds.analysis, tmp_path / "sample", tmp_path / "graph", tmp_path / "plan.json",
                 plan.Params())
    assert p["status"] == "ok", (p["status"], p.get("reason"))
    X, _ = sample.placement_pose(load_scene(path).goal, builds.model, "goal")
    np.testing.assert_allclose(_pose(p["steps"][-1]["X_WO_to"]), X, atol=1e-6)


def test_scenes_load_and_keep_the_lattice_small():
    for name in EXPERIMENTS:
        scene = load_scene(SCENES / f"{name}.json")
        assert scene.name == name
        assert scene.planner.max_poses <= 400


# --- Exp. 1: reach (§6.3, Table 2) ---------------------------------------------------------------

def test_exp1_regrasp_reaches_the_goal(builds):
    p = builds.plan("exp1_reach")
    _assert_reaches_goal(builds, "exp1_reach", p)
    assert p["counts"]["regrasp"] >= 1


def test_exp1_without_regrasp_ends_short_of_the_goal(builds):
    p = builds.plan("exp1_reach", no_regrasp=True)
    assert p["status"] == "partial", (p["status"], p.get("reason"))
    err = p["remaining_error"]
    # Short of the goal by several times execution's success tolerance (1 cm), and by no more than Table 2's
    # 12.5 cm for the graph MPC gait [3]; where in between depends on which grasps pass their borderline
    # IK checks, which moves with the last bits of the machine's floating point (5-10 cm seen).
    assert 0.03 < err["distance"] <= 0.15
    assert p["counts"]["regrasp"] == 0
    # The reported error is the plan's last pose against the goal (CoM, W).
    reached = _com(builds, _pose(p["steps"][-1]["X_WO_to"]))
    goal = _com(builds, builds.goal("exp1_reach"))
    np.testing.assert_allclose(reached[:2] - goal[:2], [err["x"], err["y"]], atol=1e-9)


def test_exp1_plan_file_is_the_same_with_and_without_the_mpc_helper(builds, tmp_path, monkeypatch):
    """The helper process only changes where the pivots' MPC checks run: exp1, whose search removes
    a pivot the MPC refuses, writes the same plan.json, byte for byte, either way."""
    b = builds.build("exp1_reach")
    monkeypatch.setattr(plan, "_spare_core", lambda: True)  # whatever the machine's load
    files = []
    for helper in (True, False):
        files.append(tmp_path / f"plan_{helper}.json")
        plan.run(builds.scene("exp1_reach"), builds.analysis, b / "sample", b / "graph", files[-1],
                 plan.Params(mpc_helper=helper))
    assert files[0].read_bytes() == files[1].read_bytes()


# --- Exp. 2: rotate (§6.4) ------------------------------------------------------------------------

def test_exp2_turn_needs_regrasps(builds):
    p = builds.plan("exp2_rotate")
    _assert_reaches_goal(builds, "exp2_rotate", p)
    assert p["counts"]["regrasp"] >= 1
    yaw = sum(s.get("angle", 0.0) for s in p["steps"] if s["primitive"] == "pivot")
    assert np.isclose(yaw, -np.pi / 2, atol=1e-6)  # the pivots add up to the -90° turn


def test_exp2_regrasps_twice_as_in_the_paper(builds):
    assert builds.plan("exp2_rotate")["counts"]["regrasp"] >= 2


def test_exp2_without_regrasp_cannot_turn(builds):
    p = builds.plan("exp2_rotate", no_regrasp=True)
    assert p["status"] != "ok"
    if p["status"] == "partial":
        err = p["remaining_error"]
        assert abs(err["yaw"]) > np.radians(20) or err["distance"] > 0.02


# --- Exp. 3: obstacle, tumble, USP (§6.5, Fig. 18) ------------------------------------------------

def test_experiment_starts_stand_on_the_table(builds):
    """The piano stands on feet: the pose sampler's SP test clips its support face by the table's edge,
    so a start with a foot off the table passes it, and in physics the piano tips over at once."""
    for name in EXPERIMENTS:
        scene = load_scene(SCENES / f"{name}.json")
        X, g = sample.placement_pose(scene.start, builds.model, name)
        feet = se3.transform_points(X, builds.model.vertices[np.asarray(builds.model.support[g])])
        half = np.asarray(scene.table.size) / 2
        assert np.all(np.abs(feet[:, :2]) <= half), name


@EXP3_NO_USP_ROUTE
def test_exp3_tumbles_into_usp_onto_a_catch_and_regrasps_there(builds):
    """Fig. 18 b-i: the piano is tumbled over the table's edge into USP, onto the catcher's ball waiting
    under the overhang; the pusher then presses it onto the table from above (the hold) while the
    catcher moves to its grasp contact, and the pusher to its own while the catcher's ball holds it
    alone (each move made while the other ball alone holds it by its normal force): a regrasp in USP.
    That grasp pivots it back into SP, at the goal."""
    b = builds.build("exp3_obstacle")
    smp = artifacts.read_json(b / "sample" / "sample.json", "sample")
    assert smp["goal"]["status"] == "ok" and smp["goal"]["placement_id"] != smp["start"]["placement_id"]
    p = builds.plan("exp3_obstacle")
    _assert_reaches_goal(builds, "exp3_obstacle", p)
    steps = p["steps"]
    tumbles = [i for i, s in enumerate(steps) if s["primitive"] == "tumble"]
    assert len(tumbles) == 1
    t = steps[tumbles[0]]
    pusher, catcher = t["pusher"], t["catcher"]
    assert t["support"] == "USP" and catcher != pusher
    scene = load_scene(builds.scene("exp3_obstacle"))
    ctx = plan._Context(scene, builds.analysis, b / "sample", b / "graph")
    r, half = scene.robot.ball_radius, np.asarray(scene.table.size) / 2
    X = _pose(t["X_WO_to"])

    def ball(c):
        return se3.transform_points(X, ctx.p_O[c] + r * ctx.n_O[c])

    c = t["catch_contact"]
    assert np.max(np.abs(ball(c)[:2]) - half) > r and se3.rotate_vectors(X, ctx.n_O[c])[2] < -0.9  # under it
    hold, regrasp, after = steps[tumbles[0] + 1: tumbles[0] + 4]
    assert hold["primitive"] == "regrasp" and hold["support"] == "USP" and hold["arms"] == [pusher]
    h = hold["contacts"][pusher]
    assert hold["contacts"][catcher] == c
    assert se3.rotate_vectors(X, ctx.n_O[h])[2] > 0.9 and np.all(np.abs(ball(h)[:2]) < half)  # on top, inboard
    assert regrasp["primitive"] == "regrasp" and regrasp["support"] == "USP"
    assert regrasp["arms"] == [catcher, pusher]
    g = regrasp["grasp_to"]
    assert ctx.grasps[f"hold_{catcher}"][g]  # the catcher's ball holds it alone while the pusher moves
    assert p["counts"]["usp_regrasp"] == 2
    assert after["primitive"] == "pivot" and after["support"] == "SP" and after["contacts"] == regrasp["contacts"]


def test_exp3_reaches_its_goal_in_physics(builds):
    """Exp. 3 end to end in PyBullet: the plan's pivots, tumble and regrasps bring the piano onto its
    front face at the goal by the table's edge, with no fall and no collision."""
    m = artifacts.read_json(builds.build("exp3_obstacle") / "full" / "execution.json", "execution_metrics")
    assert m["success"] and m["failures"] == [], {k: m[k] for k in ("failures", "final_position_error",
                                                                    "final_yaw_error_deg", "max_ball_force")}
    assert not m["fell"] and not m["collision"] and m["released"] and m["at_rest"]


def test_a_ball_under_the_object_is_refused_unless_it_is_past_the_tables_edge(builds):
    """Fig. 5 refuses contacts under the object because the ball would hit the table; past the table's
    edge (a USP overhang) nothing is in its way, so such grasps exist there, and only there."""
    b = builds.build("exp3_obstacle")
    scene = load_scene(builds.scene("exp3_obstacle"))
    ctx = plan._Context(scene, builds.analysis, b / "sample", b / "graph")
    r, half = scene.robot.ball_radius, np.asarray(scene.table.size) / 2
    gr = ctx.grasps
    X = ctx.X_WO[gr["pose_id"]]
    under_past = 0
    for side in ("left", "right"):
        c = gr[f"contact_{side}"]
        down = se3.rotate_vectors(X, ctx.n_O[c])[:, 2] < sample.Params().under_nz
        ball = se3.transform_points(X, ctx.p_O[c] + r * ctx.n_O[c])
        past = np.max(np.abs(ball[:, :2]) - half, axis=1) >= r + sample.Params().table_clearance - 1e-9
        assert np.all(past[down])
        under_past += int(down.sum())
    assert under_past > 0


def test_exp3_needs_the_tumble(builds):
    assert builds.plan("exp3_obstacle", no_tumble=True)["status"] == "infeasible"


def test_exp3_plans_in_sp_with_the_usp_pose_refused(builds):
    """The paper's route needs USP; with its USP pose refused (``EXP3_NO_USP_ROUTE``) the plan found
    never leaves SP, so the ablation without USP finds the same one."""
    full = builds.plan("exp3_obstacle")
    assert full["status"] == "ok" and all(s["support"] == "SP" for s in full["steps"])
    assert [s["edge_id"] for s in builds.plan("exp3_obstacle", no_usp=True)["steps"]] == \
        [s["edge_id"] for s in full["steps"]]


@EXP3_NO_USP_ROUTE
def test_exp3_regrasps_in_usp(builds):
    assert builds.plan("exp3_obstacle")["counts"]["usp_regrasp"] >= 1


# --- The planner's check of a tumble into USP (stages.plan._usp_tumble_mpc) ---------------------------
# The old Exp. 3 geometry: the upright piano at (0.068, 0.019), yaw 60°, tumbled to the right over hull
# edge (7, 8) onto its end (placement 32) with the left ball on contact 136 (the graph's pusher).

def _old_exp3_tumble(builds):
    b = builds.build("exp3_obstacle")  # any build: the tumbling MPC does not look at the table
    ctx = plan._Context(load_scene(builds.scene("exp3_obstacle")), builds.analysis, b / "sample", b / "graph")
    X, g = sample.placement_pose(PlacementSpec(xy=(0.06751095, 0.01878284), yaw_deg=60.0, down=(0.0, 0.0, -1.0)),
                                 ctx.model, "old exp3")
    return ctx, X


def test_usp_tumble_refused_when_its_catcher_cannot_hold_the_fall(builds):
    """The old Exp. 3's catchers: contact 0 on the piano's top face (what the sampler's USP grasps of the
    lying piano hold it by) cannot even share the push; contact 176, on the landing face but 14 cm from
    its foot, takes the object at the release and cannot hold it through the fall."""
    ctx, X = _old_exp3_tumble(builds)
    assert np.allclose(ctx.n_O[0], [0.0, 0.0, 1.0]) and np.allclose(ctx.n_O[176], [-1.0, 0.0, 0.0])
    assert "before the release" in plan._usp_tumble_mpc(ctx, plan.Params(), X, 7, 8, 136, 0)
    assert "after the release" in plan._usp_tumble_mpc(ctx, plan.Params(), X, 7, 8, 136, 176)


def test_usp_tumble_accepted_with_a_catcher_at_the_far_end_of_the_landing_face(builds):
    """Contact 175, on the landing face (the piano's end) near its far end, the ball under the
    overhang beyond the table's edge after the landing, lowers the piano and holds it."""
    ctx, X = _old_exp3_tumble(builds)
    assert np.allclose(ctx.n_O[175], [-1.0, 0.0, 0.0]) and ctx.p_O[175][2] > 0.4
    assert plan._usp_tumble_mpc(ctx, plan.Params(), X, 7, 8, 136, 175) == ""


# --- Catches and holds (Fig. 14, 18 b-f) on Exp. 3 -----------------------------------------------------

def test_catches_wait_under_the_overhang_and_holds_press_from_above(builds):
    """Every ok catch node: its contact on the landing face (outward normal within the catch cone of
    straight down), its ball beyond the table's edge by the clearance; every ok hold node: its contact
    on a face within that cone of straight up, its ball over the table; both with joints putting the
    ball there. The tumbles into a catch carry the catch's reason when it is not ok. Exp. 3 and the
    default scene: some of their nodes of each kind are ok, some not (Exp. 3's holds are all refused)."""
    seen = {("catch", True): 0, ("catch", False): 0, ("hold", True): 0, ("hold", False): 0}
    for name in ("exp3_obstacle", "default"):
        for kind, ok in _check_catches_and_holds(builds, name).items():
            seen[kind, True] += ok[0]
            seen[kind, False] += ok[1]
    assert all(n > 0 for n in seen.values()), seen


def _check_catches_and_holds(builds, name: str) -> dict:
    """:func:`test_catches_wait_under_the_overhang_and_holds_press_from_above` on one scene; returns
    ``{kind: (ok nodes, refused nodes)}``."""
    b = builds.build(name)
    scene = load_scene(builds.scene(name))
    ctx = plan._Context(scene, builds.analysis, b / "sample", b / "graph")
    ca = artifacts.read_table(b / "graph" / "catches.parquet", "catches")
    gp, r = graph.Params(), scene.robot.ball_radius
    half = np.asarray(scene.table.size) / 2
    counts = {}
    for kind, side in (("catch", -1.0), ("hold", 1.0)):
        rows = np.flatnonzero(ca["kind"] == kind)
        ok = rows[ca["status"][rows] == "ok"]
        counts[kind] = (len(ok), len(rows) - len(ok))
        for i in ok:
            X = ctx.X_WO[ca["pose_id"][i]]
            c = ca["contact"][i]
            assert side * se3.rotate_vectors(X, ctx.n_O[c])[2] >= np.cos(gp.catch_cone) - 1e-9
            ball = se3.transform_points(X, ctx.p_O[c] + r * ctx.n_O[c])
            beyond = np.max(np.abs(ball[:2]) - half)
            assert beyond >= r + gp.catch_clearance - 1e-9 if kind == "catch" else beyond <= -gp.catch_clearance
            q = np.asarray(ca["q"][i])[None]
            assert np.linalg.norm(ctx.robot.eef_position(str(ca["arm"][i]), q)[0] - ball) <= gp.ik_tol + 1e-9
    edges = ctx.edges
    into = (edges["primitive"] == "tumble") & np.isin(edges["node_b"], ca["node_id"])
    assert into.any()
    st = dict(zip(ca["node_id"].tolist(), ca["status"].tolist(), strict=True))
    for n, s in zip(edges["node_b"][into].tolist(), edges["status"][into].tolist(), strict=True):
        if st[n] != "ok":
            assert s != "ok"  # the catch's reason, or the pusher's when that failed first
    return counts


def test_a_tumble_the_motion_stage_cannot_do_is_backtracked_in_the_search(builds, tmp_path, monkeypatch):
    """``pivot plan`` asks ``trajectory.check_tumble`` of every pushed tumble it walks: when it fails
    (here made to, as for a tumble with no catcher), the edge is removed with that reason and the search
    goes on: Exp. 3's goal is on another face, and the plan left rolls onto it by a squeeze tumble,
    which that check does not concern. As it is, Exp. 3's plan tumbles once."""
    from stages import trajectory

    assert builds.plan("exp3_obstacle")["counts"]["tumble"] == 1  # its tumble passed check_tumble
    b = builds.build("exp3_obstacle")
    asked = []

    def refuse(env, q, step, X_from, X_to):
        asked.append((tuple(step["edge"]), step["pusher"]))
        return "no_catcher", "step 0: no catcher works (made to fail)"

    monkeypatch.setattr(trajectory, "check_tumble", refuse)
    p = plan.run(builds.scene("exp3_obstacle"), builds.analysis, b / "sample", b / "graph", tmp_path / "plan.json",
                 plan.Params())
    assert asked and any(e["primitive"] == "tumble" and e["reason"] == "no_catcher" for e in p["log"])
    assert {arm for _, arm in asked} == {"left", "right"}  # each arm pushed before the edge went
    tumbles = [st for st in p["steps"] if st["primitive"] == "tumble"]
    assert p["status"] == "ok" and tumbles and all(st["mode"] == "squeeze" for st in tumbles)


def test_a_tumble_refused_with_the_graphs_pusher_is_tried_with_the_other_arm(builds, tmp_path, monkeypatch):
    """A pushed tumble into SP that ``trajectory.check_tumble`` refuses with the graph's pusher is
    checked with the other arm pushing (so the first arm catching) before its edge is removed. Made
    to: every tumble pushed by the arm the search asks first is refused, every other accepted; the
    next question is the same tumble with the other arm (its own first pusher, found by the graph's
    code), and the plan pushes that tumble with it. (Exp. 3's real check refuses both arms there.)"""
    from stages import trajectory

    b = builds.build("exp3_obstacle")
    asked = []

    def refuse_the_first_arm(env, q, step, X_from, X_to):
        asked.append((tuple(step["edge"]), step["pusher"]))
        if step["pusher"] == asked[0][1]:
            return "no_catcher", "step 0: no catcher works (made to fail)"
        return "ok", ""

    monkeypatch.setattr(trajectory, "check_tumble", refuse_the_first_arm)
    p = plan.run(builds.scene("exp3_obstacle"), builds.analysis, b / "sample", b / "graph", tmp_path / "plan.json",
                 plan.Params())
    first = asked[0][1]
    other = "right" if first == "left" else "left"
    assert asked[1] == (asked[0][0], other)
    pushed = [st for st in p["steps"] if st["primitive"] == "tumble" and st["pusher"] != "both"]
    assert p["status"] == "ok" and [(tuple(st["edge"]), st["pusher"]) for st in pushed] == [asked[1]]
    assert not any(e["primitive"] == "tumble" for e in p["log"])  # the refusal removed no edge


def test_a_pivot_whose_ball_has_rolled_to_its_faces_edge_is_refused(builds):
    """The plan's walk carries how far each ball has rolled on the object (``stages.rolling``) over the
    pivots of one grasp: Exp. 2's first pivot passes from a fresh grasp, and the same pivot from a
    state whose left ball has already rolled 20 cm along its face is ``ball_rolls_off``."""
    name = "exp2_rotate"
    b = builds.build(name)
    p = builds.plan(name)
    ctx = plan._Context(load_scene(builds.scene(name)), builds.analysis, b / "sample", b / "graph")
    step = next(s for s in p["steps"] if s["primitive"] == "pivot")
    u, v, g = step["node_from"], step["node_to"], step["grasp"]
    X = ctx.X_WO[step["pose_from"]]
    state = plan._State({a: ctx.q_grasp[a][g] for a in ("left", "right")},
                        {a: se3.rotate_vectors(X, ctx.n_O[ctx.contact(g, a)]) for a in ("left", "right")}, X)
    data = {"primitive": "pivot", "edge_id": step["edge_id"]}
    ok, why, _, new = plan._check_step(ctx, plan.Params(), state, u, v, data)
    assert ok and why == "ok" and np.linalg.norm(new.roll["left"]) > 0
    n = ctx.n_O[ctx.contact(g, "left")]
    along = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    state.roll["left"] = 0.2 * along / np.linalg.norm(along)
    ok, why, step_out, _ = plan._check_step(ctx, plan.Params(), state, u, v, data)
    assert not ok and why == "ball_rolls_off" and "left ball" in step_out["detail"]


def test_a_pivot_refused_for_where_the_walk_left_its_balls_passes_after_a_retake_of_its_grasp(builds):
    """The walk retakes a grasp in SP (release to the pose's free node, the same contacts again) when a
    pivot fails from the state the pivots before it left: Exp. 2's first pivot, its left ball rolled
    20 cm, passes after the retake, its balls back on the planned contacts; not with regrasps
    ablated, nor without the graph's regrasp edge."""
    name = "exp2_rotate"
    b = builds.build(name)
    step = next(s for s in builds.plan(name)["steps"] if s["primitive"] == "pivot")
    ctx = plan._Context(load_scene(builds.scene(name)), builds.analysis, b / "sample", b / "graph")
    G, _, _ = plan.build_search_graph(ctx, plan.Params())
    u, v, g = step["node_from"], step["node_to"], step["grasp"]
    X = ctx.X_WO[step["pose_from"]]
    state = plan._State({a: ctx.q_grasp[a][g] for a in ("left", "right")},
                        {a: se3.rotate_vectors(X, ctx.n_O[ctx.contact(g, a)]) for a in ("left", "right")}, X)
    n = ctx.n_O[ctx.contact(g, "left")]
    along = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    state.roll["left"] = 0.2 * along / np.linalg.norm(along)
    data = G.edges[u, v]
    ok, why, walked, new = plan._check_or_retake(ctx, plan.Params(), G, state, u, v, data)
    free = ctx.free_of_pose[step["pose_from"]]
    assert ok and [(s["primitive"], s["node_from"], s["node_to"]) for s in walked] == [
        ("regrasp", u, free), ("regrasp", free, u), ("pivot", u, v)]
    assert walked[1]["arms"] == ["left", "right"] and walked[1]["grasp_to"] == g and walked[1]["retake"]
    assert np.linalg.norm(new.roll["left"]) < 0.05  # one pivot's rolling, not 20 cm more
    ok, why, walked, _ = plan._check_or_retake(ctx, plan.Params(no_regrasp=True), G, state, u, v, data)
    assert not ok and why == "ball_rolls_off" and len(walked) == 1
    G.remove_edge(free, u)  # no retake without the graph's regrasp edge
    ok, why, walked, _ = plan._check_or_retake(ctx, plan.Params(), G, state, u, v, data)
    assert not ok and why == "ball_rolls_off"
