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
- ``exp3_obstacle`` (§6.5, Fig. 18): a pen holder in front (+x) of the upright piano, which stands
  turned 90° (its width along y) left of the middle of a narrow table (0.6 m deep, 0.7 m wide: about
  the narrowest on which the piano both stands on its two feet and, tumbled to the right, lands on
  its end with its CoM inside the right edge); the goal lies on its end at the table's right edge,
  turned 30°. The plan tumbles the piano onto its end (into SP), grasps it with a squeeze pair (its
  top and bottom, which face left and right as it lies) and turns it 60° about one corner by the
  edge, the CoM swinging out over the edge on the way (a USP pose, both balls holding it), back into
  SP at the goal: without tumbling or without USP, no plan. It does not regrasp in USP as Fig. 18
  e–f does. The planner can (``stages.graph``: a tumble into USP lands on a catch node, the catcher
  under the overhang; a hand-over, and regrasps in USP between any two grasps, move one ball at a
  time while the other holds the piano alone), but on the ~100 layouts searched the hand-overs the
  graph offers after a tumble need the pusher's ball, which comes from the side the piano falls away
  from, to hold it alone from that inboard side (the left ball takes a pair's contact with the larger
  y), and it does so only with its friction at the limit (tangential / normal force = mu); checked
  with 0.8 of the friction, as the MPC plans (``stages.sample.Params.hold_friction_safety``), the
  one layout found has no path (``test_exp3_regrasps_in_usp``, xfail). With the full friction that
  layout (start (0, -0.1) at yaw 130°, the goal on the piano's front face at
  (-0.016, -0.213), yaw 130°, the pen holder at (0.22, 0.22)): pivot, tumble into USP onto the
  catch, hand-over, a regrasp in USP, pivot into SP; in PyBullet the nominal run and seeds 0, 2, 3, 4
  succeed, seed 1 (its CoM 5 mm further out) tips 4° onto the right stick in the hand-over. The pen
  holder does not decide the route (the plan and the ablations come out the same without it).
"""

from pathlib import Path

import numpy as np
import pytest

from stages import analyze, artifacts, graph, plan, sample, se3
from stages.objectmodel import load_object_model
from stages.scene import PlacementSpec, load_scene

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "data" / "scenes"
EXPERIMENTS = ("exp1_reach", "exp2_rotate", "exp3_obstacle")


class Builds:
    """Analysis once, sample + graph once per scene, each plan (scene, ablation) once."""

    def __init__(self, root: Path):
        self.root = root
        self.analysis = root / "analysis"
        scene = load_scene(SCENES / f"{EXPERIMENTS[0]}.json")
        analyze.run(scene.object.mesh_path, self.analysis, scene.object.mass, analyze.Params())
        self.model, _ = load_object_model(self.analysis)
        self._built: set = set()
        self._plans: dict = {}

    def scene(self, name: str) -> Path:
        return SCENES / f"{name}.json"

    def build(self, name: str) -> Path:
        b = self.root / name
        if name not in self._built:
            sample.run(self.scene(name), self.analysis, b / "sample", sample.Params())
            graph.run(self.scene(name), self.analysis, b / "sample", b / "graph", graph.Params())
            self._built.add(name)
        return b

    def plan(self, name: str, **ablation) -> dict:
        key = (name, tuple(sorted(ablation.items())))
        if key not in self._plans:
            b = self.build(name)
            tag = "_".join(k for k, v in sorted(ablation.items()) if v) or "full"
            self._plans[key] = plan.run(self.scene(name), self.analysis, b / "sample", b / "graph",
                                        b / f"plan_{tag}.json", plan.Params(**ablation))
        return self._plans[key]

    def goal(self, name: str) -> np.ndarray:
        X, _ = sample.placement_pose(load_scene(self.scene(name)).goal, self.model, "goal")
        return X


@pytest.fixture(scope="module")
def builds(tmp_path_factory) -> Builds:
    return Builds(tmp_path_factory.mktemp("experiments"))


def _pose(cols: dict) -> np.ndarray:
    return se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in cols.items()})[0]


def _assert_reaches_goal(builds: Builds, name: str, p: dict) -> None:
    assert p["status"] == "ok", (p["status"], p.get("reason"), p["log"][-3:])
    np.testing.assert_allclose(_pose(p["steps"][-1]["X_WO_to"]), builds.goal(name), atol=1e-6)
    for prim in ("pivot", "tumble"):
        assert p["counts"][prim] == sum(s["primitive"] == prim for s in p["steps"])


def _com(builds: Builds, X: np.ndarray) -> np.ndarray:
    return se3.transform_points(X, builds.model.com)


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
    assert err["x"] < -0.03 and err["distance"] > 0.05  # short of the goal (err = reached - goal)
    assert p["counts"]["regrasp"] == 0
    # The reported error is the plan's last pose against the goal (CoM, W).
    reached = _com(builds, _pose(p["steps"][-1]["X_WO_to"]))
    goal = _com(builds, builds.goal("exp1_reach"))
    np.testing.assert_allclose(reached[:2] - goal[:2], [err["x"], err["y"]], atol=1e-9)


def test_exp1_error_as_in_table_2(builds):
    err = builds.plan("exp1_reach", no_regrasp=True).get("remaining_error", {"x": 0.0})
    assert -0.15 <= err["x"] <= -0.10
    assert abs(err["y"]) <= 0.02  # short along x, as Table 2's: the one-grasp gait stops in the forward direction


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


def test_exp3_tumbles_into_sp_and_pivots_through_usp_to_the_goal(builds):
    """The piano gets onto its end (the goal's face) by a tumble that lands in SP; a pivot by the
    table's edge then swings it through USP (both balls holding) and back into SP at the goal."""
    b = builds.build("exp3_obstacle")
    smp = artifacts.read_json(b / "sample" / "sample.json", "sample")
    assert smp["goal"]["status"] == "ok" and smp["goal"]["placement_id"] != smp["start"]["placement_id"]
    p = builds.plan("exp3_obstacle")
    _assert_reaches_goal(builds, "exp3_obstacle", p)
    steps = p["steps"]
    tumbles = [i for i, s in enumerate(steps) if s["primitive"] == "tumble"]
    assert tumbles and all(steps[i]["support"] == "SP" and "grasp_to" not in steps[i] for i in tumbles)
    usp = [i for i, s in enumerate(steps) if s["support"] == "USP"]
    assert usp and min(usp) > tumbles[0]
    assert all(steps[i]["primitive"] == "pivot" for i in usp)  # entered and left by pivots, one grasp
    after = steps[max(usp) + 1]
    assert after["primitive"] == "pivot" and after["support"] == "SP"
    assert after["contacts"] == steps[max(usp)]["contacts"]  # the same squeeze pair in and out


def test_exp3_needs_the_tumble(builds):
    assert builds.plan("exp3_obstacle", no_tumble=True)["status"] == "infeasible"


def test_exp3_needs_usp(builds):
    assert builds.plan("exp3_obstacle", no_usp=True)["status"] == "infeasible"


@pytest.mark.xfail(strict=True, reason="no regrasp in USP: every hand-over out of a USP catch (and USP regrasp) the "
                                       "graph offers on the layouts searched needs one ball to hold it alone at its "
                                       "friction limit, refused with 0.8 of the friction (hold_friction_safety); "
                                       "see the module docstring")
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


# --- The catch and hand-over (Fig. 14, 18 b-f) on the hand-over layout, holds at the full friction ----------

HANDOVER_LAYOUT = {  # the layout of the module docstring (found with holds at the full friction)
    "obstacles": [{"type": "cylinder", "radius": 0.06, "height": 0.12, "xyz": [0.22, 0.22, 0.06]}],
    "start": {"down": [0, 0, -1], "xy": [0.0, -0.1], "yaw_deg": 130},
    "goal": {"down": [0, 1, 0], "xy": [-0.016048178922203143, -0.21267890957577745], "yaw_deg": 130},
}


@pytest.fixture(scope="module")
def handover(builds, tmp_path_factory):
    """The hand-over layout planned twice: USP holds at the full friction, and at 0.8 of it (the default)."""
    import json

    d = tmp_path_factory.mktemp("handover")
    data = json.loads((SCENES / "exp3_obstacle.json").read_text())
    data.update(HANDOVER_LAYOUT, name="exp3_handover")
    data["object"]["mesh"] = str(REPO / "data" / "objects" / "toy_piano.obj")
    data["robot"]["urdf"] = str(REPO / "data" / "robots" / "sda5f.urdf")
    scene = d / "exp3_handover.json"
    scene.write_text(json.dumps(data))
    out = {}
    for safety in (1.0, 0.8):
        b = d / f"safety{safety}"
        sample.run(scene, builds.analysis, b / "sample", sample.Params(hold_friction_safety=safety))
        graph.run(scene, builds.analysis, b / "sample", b / "graph", graph.Params(hold_friction_safety=safety))
        out[safety] = (b, plan.run(scene, builds.analysis, b / "sample", b / "graph", b / "plan.json", plan.Params()))
    return scene, out


def test_tumble_into_usp_lands_on_a_catch_and_hands_over_one_ball_at_a_time(builds, handover):
    """Holds at the full friction: the piano is tumbled over the table's edge into USP, the catcher's ball
    waiting under the overhang beyond the edge; the hand-over (the pusher onto its grasp contact, then
    the catcher onto its own, each while the other ball holds alone) and a second regrasp in USP (one
    ball at a time) take the grasp that pivots it back into SP, where it is released at the goal."""
    scene_path, out = handover
    b, p = out[1.0]
    assert p["status"] == "ok", (p.get("reason"), p["log"][-3:])
    steps = p["steps"]
    tumbles = [i for i, s in enumerate(steps) if s["primitive"] == "tumble"]
    assert len(tumbles) == 1
    t = steps[tumbles[0]]
    assert t["support"] == "USP" and t["catcher"] != t["pusher"]
    scene = load_scene(scene_path)
    ctx = plan._Context(scene, builds.analysis, b / "sample", b / "graph")
    r = scene.robot.ball_radius
    ball = se3.transform_points(_pose(t["X_WO_to"]), ctx.p_O[t["catch_contact"]] + r * ctx.n_O[t["catch_contact"]])
    assert np.max(np.abs(ball[:2]) - np.asarray(scene.table.size) / 2) > r  # under the overhang, past the edge
    hand, regrasp, after = steps[tumbles[0] + 1: tumbles[0] + 4]
    assert hand["primitive"] == "regrasp" and hand["support"] == "USP"
    assert hand["arms"] == [t["pusher"], t["catcher"]]  # the pusher first, the catcher after it
    assert regrasp["primitive"] == "regrasp" and regrasp["support"] == "USP"
    assert sorted(regrasp["arms"]) == ["left", "right"] and regrasp["contacts"] != hand["contacts"]
    assert p["counts"]["usp_regrasp"] == 2
    assert after["primitive"] == "pivot" and after["support"] == "SP" and after["contacts"] == regrasp["contacts"]
    np.testing.assert_allclose(_pose(steps[-1]["X_WO_to"]), sample.placement_pose(scene.goal, ctx.model, "g")[0],
                               atol=1e-6)


def test_catches_wait_under_the_overhang_and_hold_the_object_alone(builds, handover):
    """Every ok catch node: its contact on the landing face (outward normal within the catch cone of
    straight down), its ball beyond the table's edge by the clearance, its joints putting the ball
    there; the tumbles into it carry the catch's reason when it is not ok."""
    scene_path, out = handover
    b, _ = out[1.0]
    scene = load_scene(scene_path)
    ctx = plan._Context(scene, builds.analysis, b / "sample", b / "graph")
    ca = artifacts.read_table(b / "graph" / "catches.parquet", "catches")
    gp, r = graph.Params(), scene.robot.ball_radius
    ok = np.flatnonzero(ca["status"] == "ok")
    assert len(ok) > 0 and len(ok) < len(ca["status"])
    for i in ok:
        X = ctx.X_WO[ca["pose_id"][i]]
        c = ca["contact"][i]
        assert se3.rotate_vectors(X, ctx.n_O[c])[2] <= -np.cos(gp.catch_cone) + 1e-9
        ball = se3.transform_points(X, ctx.p_O[c] + r * ctx.n_O[c])
        assert np.max(np.abs(ball[:2]) - np.asarray(scene.table.size) / 2) >= r + gp.catch_clearance - 1e-9
        q = np.asarray(ca["q"][i])[None]
        assert np.linalg.norm(ctx.robot.eef_position(str(ca["arm"][i]), q)[0] - ball) <= gp.ik_tol + 1e-9
    edges = ctx.edges
    into = (edges["primitive"] == "tumble") & np.isin(edges["node_b"], ca["node_id"])
    st = dict(zip(ca["node_id"].tolist(), ca["status"].tolist(), strict=True))
    for n, s in zip(edges["node_b"][into].tolist(), edges["status"][into].tolist(), strict=True):
        if st[n] != "ok":
            assert s != "ok"  # the catch's reason, or the pusher's when that failed first


def test_hand_over_needs_a_hold_at_the_friction_limit_there(handover):
    """With the one-ball holds checked at 0.8 of the friction (the default, as the MPC plans) the same
    layout has no plan: its hand-overs held the piano at the friction limit (in physics seed 1 tipped)."""
    _, out = handover
    assert out[0.8][1]["status"] == "infeasible"
