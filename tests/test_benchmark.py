"""The benchmark: goal drawing against closed-form footprints, the stage runner's limits, and a smoke
sweep on a Dask LocalCluster (schema and values against the per-case artifacts, a crashing case
recorded while the others finish, a rerun that skips the finished cases)."""

import json
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from pivotcli.app import app
from stages import artifacts
from stages.benchmark import suite, sweep

runner = CliRunner()


class _Model:
    """A box of 0.4 x 0.2 (plan) resting with its CoM projection at the origin (one placement)."""

    vertices = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (-0.1, 0.1) for z in (0.0, 0.3)])
    X_TO = np.eye(4)[None]


def test_footprint_of_a_box_turned_90_deg_swaps_its_extents():
    b = suite.footprint_bounds(_Model, 0, np.pi / 2)
    np.testing.assert_allclose(b, [-0.1, 0.1, -0.2, 0.2], atol=1e-12)


def test_admissible_box_keeps_the_whole_footprint_inside_the_area():
    area = np.array([-0.3, 0.4, -0.25, 0.25])
    box = suite.admissible_box(suite.footprint_bounds(_Model, 0, 0.0), area)
    np.testing.assert_allclose(box, [-0.1, 0.2, -0.15, 0.15])
    assert suite.admissible_box(suite.footprint_bounds(_Model, 0, 0.0), np.array([0, 0.3, -1, 1])) is None


@pytest.mark.parametrize("kind", ["translate", "rotate"])
def test_drawn_goals_fit_the_area_and_their_kind(kind):
    prm = suite.SuiteParams(objects=())
    area = np.array([-0.33, 0.43, -0.28, 0.28])
    rng = np.random.default_rng(1)
    for _ in range(20):
        start, goal = suite.draw_case(rng, _Model, kind, 0, [], area, prm)
        for p in (start, goal):  # the footprint lies in the area (rounding of xy to 0.1 mm)
            b = suite.footprint_bounds(_Model, 0, np.radians(p.yaw_deg)) + np.repeat(p.xy, 2)
            assert b[0] >= area[0] - 1e-4 and b[1] <= area[1] + 1e-4 and b[2] >= area[2] - 1e-4
            assert b[3] <= area[3] + 1e-4
        d = np.hypot(*np.subtract(goal.xy, start.xy))
        dyaw = abs((goal.yaw_deg - start.yaw_deg + 180) % 360 - 180)
        if kind == "translate":
            assert 0.1 - 1e-3 <= d <= 0.45 + 1e-3 and dyaw < 1e-6
        else:
            assert d <= 0.45 + 1e-3 and 30 - 0.01 <= dyaw <= 180 + 0.01


def test_a_stage_past_its_time_limit_is_killed_and_recorded(tmp_path):
    run = sweep.run_stage("plan", [sys.executable, "-c", "import time; time.sleep(30)"], tmp_path / "x.log", 0.5)
    assert run.timed_out and run.seconds < 10 and "timed out" in run.error


def test_a_failing_stage_reports_its_last_line_and_exit_code(tmp_path):
    code = "import sys; print('working'); sys.exit('pivot: error: x.json: object.mass: must be > 0')"
    run = sweep.run_stage("sample", [sys.executable, "-c", code], tmp_path / "x.log", 30)
    assert run.exit_code == 1 and run.error.endswith("must be > 0") and run.peak_mb > 1
    assert sweep.stage_outcome(run, tmp_path, 0) == ("sample:crash", run.error)


def test_reason_codes_fold_numbers():
    assert sweep.slug("gave up after 12 removed edges") == "gave_up_after_n_removed_edges"


@pytest.mark.slow
def test_smoke_sweep_on_a_local_cluster(tmp_path):
    out = tmp_path / "bench"
    r = runner.invoke(app, ["benchmark", "make", str(out), "--objects", "box", "--goals", "2"])
    assert r.exit_code == 0, r.output
    cases = artifacts.read_json(out / "suite.json", "benchmark_suite")["cases"]
    assert [c["kind"] for c in cases] == ["translate", "rotate"]
    for c in cases:  # every case is an ordinary scene file
        assert json.loads((out / c["scene"]).read_text())["name"] == c["case"]
    broken = cases[-1]["case"]
    (out / "runs" / broken).mkdir(parents=True)
    (out / "runs" / broken / "logs").write_text("a file where the case's log folder goes: its task raises")

    r = runner.invoke(app, ["-q", "benchmark", "run", str(out), "--workers", "2", "--seeds", "1",
                            "--timeout", "400"])
    assert r.exit_code == 0, r.output
    res = artifacts.read_table(out / "results.parquet", "benchmark_results")
    assert list(res.columns) == [f.name for f in sweep.RESULT_FIELDS] and len(res) == len(cases)
    rows = {c: i for i, c in enumerate(res["case"])}
    i = rows[broken]
    assert res["reason"][i] == "harness:crash" and "FileExistsError" in res["error"][i]
    for c in cases[:-1]:  # the others finished, and their rows say what their artifacts say
        i, b = rows[c["case"]], out / "runs" / c["case"]
        assert res["stage_reached"][i] in sweep.STAGES and np.isfinite(res["t_analyze"][i])
        assert res["reachable"][i] == c["reachable"]
        plan = json.loads((b / "full" / "plan.json").read_text())
        assert res["plan_found"][i] == (plan["status"] == "ok")
        assert res["pivots"][i] == plan.get("counts", {}).get("pivot", 0)
        if res["stage_reached"][i] == "execute":
            ex = json.loads((b / "full" / "seed0" / "execution.json").read_text())
            assert res["success"][i] == ex["success"]
            assert res["final_position_error"][i] == pytest.approx(ex["final_position_error"])
    stamps = {c["case"]: (out / "runs" / c["case"] / "case.json").stat().st_mtime_ns for c in cases[:-1]}

    r = runner.invoke(app, ["benchmark", "run", str(out), "--workers", "2", "--seeds", "1", "--timeout", "400"])
    assert r.exit_code == 0 and "1 ran, 1 current (skipped)" in r.output, r.output
    assert stamps == {c: (out / "runs" / c / "case.json").stat().st_mtime_ns for c in stamps}

    r = runner.invoke(app, ["benchmark", "report", str(out)])
    assert r.exit_code == 0, r.output
    text = (out / "report.md").read_text()
    assert "harness:crash" in text and (out / "figures" / "rates_by_object.png").stat().st_size > 1000
    planned = [c["case"] for c in cases if (out / "runs" / c["case"] / "full" / "plan.json").is_file()]
    assert planned and text.count("[3D](") == len(planned)  # every case with a plan links its 3D view
    for c in planned:
        assert f"[3D](runs/{c}/full/view.html)" in text and (out / "runs" / c / "full" / "view.html").is_file()


def test_an_unknown_object_is_one_line_exit_2_and_writes_nothing(tmp_path):
    r = runner.invoke(app, ["benchmark", "make", str(tmp_path / "out"), "--objects", "box,sofa"])
    assert r.exit_code == 2 and "no object family 'sofa'" in r.output and not (tmp_path / "out").exists()


def test_physics_reason_names_the_first_failed_criterion():
    """The sweep's reason code of a failed run is its first failed criterion (``execution.json``'s
    ``failures``), so the report ranks over_force_bound, not_released, tilted, ... apart."""
    from stages.benchmark import sweep

    assert sweep.physics_reason({"success": True, "failures": []}) == ("ok", "")
    ex = {"success": False, "failures": ["over_force_bound", "not_released"], "max_ball_force": 55.2,
          "force_bound": 50.0}
    assert sweep.physics_reason(ex) == ("physics:over_force_bound", "55.2 N over 50 N; not_released")
    ex = {"success": False, "failures": ["tilted"], "final_tilt_error_deg": 3.14}
    assert sweep.physics_reason(ex) == ("physics:tilted", "3.1 deg")
    assert sweep.physics_reason({"success": False, "failures": ["not_released", "not_retreated"]}) == \
        ("physics:not_released", "not_retreated")
    ex = {"success": False, "failures": ["fell", "missed_position"], "fell": True, "fell_reason": "tilted 40 deg"}
    assert sweep.physics_reason(ex) == ("physics:fell", "tilted 40 deg")
    old = {"success": False, "final_position_error": 0.02, "final_yaw_error_deg": 1.0}  # before issue 15
    assert sweep.physics_reason(old)[0] == "physics:missed_goal"



def test_a_candidates_grasp_does_not_depend_on_the_rest_of_its_batch(small_build):
    """Grasp refinement of a few poses alone finds, at each, the grasps (pair and joints) that the
    refinement of every pose at once finds there: a collision retry's IK jitter is the candidate's
    own, as the first IK's is. The benchmark's reachability label (the start and goal refined alone)
    then counts the grasps the sample stage has there."""
    from stages import artifacts, se3
    from stages import sample as sample_stage
    from stages.objectmodel import load_object_model
    from stages.poses import PoseSet
    from stages.robot import IKParams, load_robot
    from stages.scene import load_scene

    scene_path, b = small_build
    scene = load_scene(scene_path)
    model, tables = load_object_model(b / "analysis")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links),
                       ik_params=IKParams(min_chunk=1024))
    p = sample_stage.Params()
    collide = sample_stage.make_scene_collision_fn(scene, robot, tables["mesh"],
                                                   clearance=(p.arm_clearance, p.stick_clearance))
    robot.prepare_ik()
    t = artifacts.read_table(b / "sample" / "poses.parquet", "poses")
    keep = np.flatnonzero(np.asarray(t["status"]) == "ok")[:24]
    n = len(keep)
    ps = PoseSet(X_WO=se3.matrix_from_columns(t.columns)[keep], placement=np.asarray(t["placement_id"])[keep],
                 support=np.asarray(t["support"])[keep], status=np.full(n, "ok"), parent=np.full(n, -1),
                 primitive=np.full(n, "pivot"), vertex=np.full(n, -1), edge=np.full((n, 2), -1), angle=np.zeros(n),
                 margin=np.asarray(t["margin"])[keep], links=np.zeros((0, 2), np.int64),
                 link_primitive=np.zeros(0, str), link_vertex=np.zeros(0, np.int64),
                 link_edge=np.zeros((0, 2), np.int64), link_angle=np.zeros(0))

    def refine(ids):
        g, rej, _ = sample_stage.refine_grasps(scene, model, tables, ps, robot, collide, p, np.random.default_rng(0),
                                                ids)
        rows = sorted(zip(g["pose_id"].tolist(), g["pair_id"].tolist(), map(tuple, np.round(g["q_left"], 9)),
                          map(tuple, np.round(g["q_right"], 9)), strict=True))
        return rows, rej

    every, rejects = refine(None)
    few, _ = refine(np.arange(0, n, 3))
    assert (np.char.find(rejects["reason"].astype(str), "collision") >= 0).sum() > 50  # retries were made
    assert few == [r for r in every if r[0] % 3 == 0] and len(few) > 20

