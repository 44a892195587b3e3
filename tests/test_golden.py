"""Every stage's artifacts of the reference scenes match their golden digests (tests/golden.py).

A behaviour change shows here first: review ``git diff tests/golden`` after ``make golden`` and commit
the digests with the change that explains them.
"""

import json

import pytest

from tests.golden import GOLDEN, SCENES, compare, digest_chain

# One xdist worker runs every test of the reference chains, built once per session (conftest).
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("reference")]


@pytest.mark.parametrize("scene", SCENES)
def test_reference_scene_matches_its_golden_artifacts(reference_chain, scene):
    path = GOLDEN / f"{scene}.json"
    assert path.is_file(), f"{path} missing: make golden"
    lines = compare(json.loads(path.read_text()), digest_chain(reference_chain(scene)))
    shown = "\n".join(lines[:40]) + (f"\n... and {len(lines) - 40} more" if len(lines) > 40 else "")
    assert not lines, f"{scene}: artifacts differ from tests/golden (make golden, then review the diff):\n{shown}"


def test_compare_names_the_stage_artifact_and_column_beyond_tolerance():
    golden = {"plan": {"plan.json": {"cost": 1.1, "status": "ok"}},
              "execute": {"execution.json": {"final_position_error": 0.0007, "final_yaw_error_deg": 0.1}}}
    same = {"plan": {"plan.json": {"cost": 1.1 + 1e-12, "status": "ok"}},
            "execute": {"execution.json": {"final_position_error": 0.0012, "final_yaw_error_deg": 0.15}}}
    assert compare(golden, same) == []  # 0.5 mm and 0.05 deg are within the physics tolerances
    moved = {"plan": {"plan.json": {"cost": 1.2, "status": "ok"}},
             "execute": {"execution.json": {"final_position_error": 0.0027, "final_yaw_error_deg": 0.1}}}
    assert compare(golden, moved) == ["execute/execution.json final_position_error: 0.0007 -> 0.0027",
                                      "plan/plan.json cost: 1.1 -> 1.2"]
