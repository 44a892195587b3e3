"""The reproduction report (stages.report) reads the execution's criteria and says what was calibrated."""

from stages import artifacts, report


def _write(path, data, artifact):
    path.parent.mkdir(parents=True, exist_ok=True)
    artifacts.write_json(path, data, artifacts.make_meta(artifact, {}, {}, "test"))


def test_table_2_says_what_was_calibrated_with_the_stop_at_the_first_geometry(tmp_path):
    _write(tmp_path / "exp1_reach" / "full" / "plan.json", {"status": "ok", "steps": [], "log": []}, "plan")
    _write(tmp_path / "exp1_reach_first" / "no-regrasp" / "plan.json",
           {"status": "partial", "steps": [], "log": [],
            "remaining_error": {"x": -0.060, "y": 0.112, "distance": 0.128}}, "plan")
    text = report.write_report(tmp_path, tmp_path / "report" / "README.md", ["exp1_reach"])
    line = next(x for x in text.splitlines() if x.startswith("Calibrated:"))
    assert "base moved 4 cm back (x -0.70 -> -0.74 m)" in line and "(0.38, 0.00) to (0.27, -0.025)" in line
    assert "-6.0 cm along x, +11.2 cm along y (12.8 cm from its goal; plan partial)" in line


def test_the_calibration_line_says_when_the_first_geometry_was_not_built(tmp_path):
    _write(tmp_path / "exp1_reach" / "full" / "plan.json", {"status": "ok", "steps": [], "log": []}, "plan")
    text = report.write_report(tmp_path, tmp_path / "README.md", ["exp1_reach"])
    assert "not built here (`make SCENE=exp1_reach_first VARIANT=no-regrasp plan`)" in text


def test_physics_lines_name_the_failed_criteria_the_force_and_the_seeds():
    e = {"success": False, "failures": ["not_released", "not_at_rest"], "final_position_error": 0.002,
         "final_yaw_error_deg": 0.3, "final_tilt_error_deg": 0.1, "rest_duration": 0.0, "released": False,
         "retreated": False, "at_rest": False, "max_com_deviation": 0.003, "fell": False, "max_ball_force": 47.5,
         "max_ball_force_step": 51.0, "force_bound": 50.0, "time_over_force_bound": 0.0, "time_at_force_bound": 3.2,
         "max_planned_ball_force": 42.0, "max_support_slip": 0.0084, "worst_slip_primitive": 4,
         "max_support_rotation_slip_deg": 3.7, "worst_rotation_slip_primitive": 4,
         "slip": [{"primitive": 4, "kind": "regrasp", "translation": 0.0084, "rotation_deg": 3.7}]}
    rb = {"seeds": 10, "succeeded": 8, "required": 9, "failures": {"over_force_bound": 1, "missed_position": 1},
          "meta": {"params": {"friction_jitter": 0.2, "mass_jitter": 0.15, "com_jitter": 0.01, "pose_jitter": 0.003}}}
    text = "\n".join(report._physics_lines(e, rb))
    assert "success False (failed: not_released, not_at_rest)" in text
    assert "peak 47.5 N" in text and "bound 50 N" in text and "3.70° of rotation (primitive 4)" in text
    assert "8 of 10 (missed_position 1, over_force_bound 1) perturbed seeds succeed" in text
