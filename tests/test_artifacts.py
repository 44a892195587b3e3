"""Artifacts cannot lie (issue 17): a corrupt, stale or foreign artifact is refused by the command that
reads it with one line and exit 2, writing nothing; writes are atomic, locked and follow the umask."""

import hashlib
import json
import os
import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from pivotcli.app import app
from stages import artifacts
from stages.errors import ArtifactError
from tests.conftest import write_scene

runner = CliRunner()


@pytest.fixture(scope="session")
def chain(tmp_path_factory):
    """The whole chain of a tiny scene through the CLI, once per session: (folder, scene file name)."""
    root = tmp_path_factory.mktemp("chain")
    scene = write_scene(root, "tiny", **{"planner.max_poses": 30, "goal.xy": [-0.14, 0.0]})
    b = root / "build"
    for args in (["analyze", "--scene", scene, "--out", b / "analysis"],
                 ["sample", scene, "--analysis", b / "analysis", "--out", b / "sample"],
                 ["graph", scene, "--build", b],
                 ["plan", scene, "--build", b, "--out", b / "full" / "plan.json"],
                 ["mpc", scene, "--build", b, "--plan", b / "full" / "plan.json",
                  "--out", b / "full" / "trajectories.parquet"],
                 ["execute", scene, "--build", b, "--trajectories", b / "full" / "trajectories.parquet",
                  "--out", b / "full", "--frames", "2"]):
        r = runner.invoke(app, [str(a) for a in args])
        assert r.exit_code == 0, (args[0], r.output)
    return root


def _case(chain, tmp_path) -> tuple[Path, Path]:
    """A private copy of the chain's artifacts: (scene file, build folder)."""
    shutil.copytree(chain, tmp_path / "c")
    return tmp_path / "c" / "tiny.json", tmp_path / "c" / "build"


def _command(kind: str, scene: Path, b: Path) -> list:
    """The first command that reads artifact ``kind``: its schema is checked, not only its hash."""
    if kind in ("hull", "placements", "contacts", "pairs", "analysis"):
        return ["sample", scene, "--analysis", b / "analysis", "--out", b / "sample"]
    if kind in ("poses", "pose_links", "grasps"):
        return ["graph", scene, "--build", b]
    if kind == "segments":
        return ["show", "analysis", b / "analysis", "--png", b / "analysis.png"]
    if kind == "plan":
        return ["mpc", scene, "--build", b, "--plan", b / "full" / "plan.json",
                "--out", b / "full" / "trajectories.parquet"]
    if kind == "trajectories":
        return ["execute", scene, "--build", b, "--trajectories", b / "full" / "trajectories.parquet",
                "--out", b / "full", "--frames", "0"]
    if kind in ("execution", "execution_metrics"):
        return ["show", "execution", b / "full", "--png", b / "full" / "execution.png"]
    return ["plan", scene, "--build", b, "--out", b / "full" / "plan.json"]


FILES = {"hull": "analysis/hull.parquet", "placements": "analysis/placements.parquet",
         "contacts": "analysis/contacts.parquet", "pairs": "analysis/pairs.parquet",
         "segments": "analysis/segments.parquet", "analysis": "analysis/analysis.json",
         "poses": "sample/poses.parquet", "pose_links": "sample/pose_links.parquet", "grasps": "sample/grasps.parquet",
         "grasp_rejects": "sample/grasp_rejects.parquet", "sample": "sample/sample.json",
         "nodes": "graph/nodes.parquet", "edges": "graph/edges.parquet", "catches": "graph/catches.parquet",
         "graph": "graph/graph.json", "plan": "full/plan.json", "trajectories": "full/trajectories.parquet",
         "execution": "full/execution.parquet", "execution_metrics": "full/execution.json"}
WAYS = ("column_missing", "column_renamed", "wrong_type", "nan", "truncated", "wrong_inputs", "schema_version")
# Figures read these without a scene to check them against; every other kind is read by a stage.
NO_INPUTS_CHECK = {"segments", "execution", "execution_metrics"}
OTHER = hashlib.sha256(b"another scene").hexdigest()


def _corrupt_table(path: Path, way: str) -> None:
    t = pq.read_table(path)
    meta = {k.decode(): json.loads(v) for k, v in t.schema.metadata.items()}
    schema = artifacts.SCHEMAS[meta["artifact"]]
    floats = [c for c, k in schema.items() if k == "f"]
    col = floats[0] if floats else next(iter(schema))
    i = t.column_names.index(col)
    if way == "column_missing":
        t = t.drop_columns([col])
    elif way == "column_renamed":
        t = t.rename_columns([c + "_0" if c == col else c for c in t.column_names])
    elif way == "wrong_type":
        t = t.set_column(i, t.schema.field(i).with_type(pa.string()), t.column(i).cast(pa.string()))
    elif way == "nan":  # a NaN in a float column, a missing value in an integer one
        values = t.column(i).to_pylist()
        values[len(values) // 2] = float("nan") if floats else None
        t = t.set_column(i, t.schema.field(i), pa.array(values, type=t.column(i).type))
    elif way in ("wrong_inputs", "schema_version"):
        if way == "wrong_inputs":
            meta["inputs"] = {k: OTHER for k in meta["inputs"]}
        else:
            meta["schema_version"] = artifacts.SCHEMA_VERSION + 1
    t = t.replace_schema_metadata({k: json.dumps(v, sort_keys=True) for k, v in meta.items()})
    pq.write_table(t, path)


def _corrupt_json(path: Path, way: str) -> None:
    data = json.loads(path.read_text())
    key = sorted(k for k in data if k != "meta")[0]
    if way == "column_missing":
        del data[key]
    elif way == "column_renamed":
        data[key + "_0"] = data.pop(key)
    elif way == "wrong_type":
        data[key] = "a string"
    elif way == "nan":
        data[key] = float("nan")
    elif way == "wrong_inputs":
        data["meta"]["inputs"] = {k: OTHER for k in data["meta"]["inputs"]}
    elif way == "schema_version":
        data["meta"]["schema_version"] = artifacts.SCHEMA_VERSION + 1
    path.write_text(json.dumps(data, indent=1, sort_keys=True))


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _one_line_exit_2(r) -> str:
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert r.exit_code == 2, r.output
    assert len(lines) == 1 and "Traceback" not in r.output and lines[0].startswith("pivot: error: "), r.output
    return lines[0]


@pytest.mark.parametrize("way", WAYS)
@pytest.mark.parametrize("kind", sorted(FILES))
def test_a_corrupt_artifact_is_one_line_exit_2_and_nothing_is_written(chain, tmp_path, kind, way):
    if way == "wrong_inputs" and kind in NO_INPUTS_CHECK:
        pytest.skip("read only by a figure, which has no upstream to check it against")
    scene, b = _case(chain, tmp_path)
    path = b / FILES[kind]
    if way == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif path.suffix == ".json":
        _corrupt_json(path, way)
    else:
        _corrupt_table(path, way)
    before = _snapshot(tmp_path / "c")
    r = runner.invoke(app, [str(a) for a in _command(kind, scene, b)])
    line = _one_line_exit_2(r)
    assert path.name in line, line  # names the bad file
    assert _snapshot(tmp_path / "c") == before


def test_a_sample_of_another_mesh_is_refused_naming_both_files(chain, tmp_path):
    import trimesh

    scene, b = _case(chain, tmp_path)
    box = tmp_path / "box.stl"
    trimesh.creation.box((0.3, 0.2, 0.25)).export(box)
    other = write_scene(tmp_path, "other", **{"object.mesh": str(box), "planner.max_poses": 30})
    before = _snapshot(tmp_path / "c")
    r = runner.invoke(app, ["sample", str(other), "--analysis", str(b / "analysis"), "--out", str(b / "s2")])
    line = _one_line_exit_2(r)
    assert "analysis.json" in line and "box.stl" in line, line
    assert _snapshot(tmp_path / "c") == before


def test_a_graph_of_another_scene_and_an_mpc_of_another_plan_are_refused(chain, tmp_path):
    scene, b = _case(chain, tmp_path)
    other = write_scene(tmp_path / "c", "moved", **{"planner.max_poses": 30, "goal.xy": [-0.10, 0.0]})
    for args, names in ((["graph", other, "--build", b], ("poses.parquet", "moved.json")),
                        (["mpc", other, "--build", b, "--plan", b / "full" / "plan.json", "--out", b / "t.parquet"],
                         ("plan.json", "moved.json"))):
        before = _snapshot(tmp_path / "c")
        line = _one_line_exit_2(runner.invoke(app, [str(a) for a in args]))
        assert all(n in line for n in names), line
        assert _snapshot(tmp_path / "c") == before


def test_a_hand_edited_plan_step_is_refused(chain, tmp_path):
    scene, b = _case(chain, tmp_path)
    plan = b / "full" / "plan.json"
    for edit in ({"primitive": "fly"}, {"vertex": 999}):
        data = json.loads((chain / "build" / "full" / "plan.json").read_text())
        data["steps"][1].update(edit)
        plan.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
        line = _one_line_exit_2(runner.invoke(app, [str(a) for a in _command("plan", scene, b)]))
        assert "plan.json" in line and "edited" in line, line


@pytest.mark.parametrize("edit, says", [
    ({"primitive": "fly"}, "step 1: primitive 'fly' is not one of pivot, regrasp, tumble"),
    ({"vertex": 999}, "step 1: vertex 999 is not one of 0..41"),
    ({"vertex": None}, "step 1: vertex None is not one of 0..41"),
    ({"contacts": {"left": 5000, "right": 11}}, "step 1: left contact 5000 is not one of -1..202"),
    ({"X_WO_to": {"x": [float("nan")]}}, "step 1: X_WO_to is not a pose of finite"),
])
def test_a_plan_edited_with_its_hash_forged_is_refused_by_its_steps(chain, tmp_path, edit, says):
    """An editor who also rewrites meta.content still cannot send the MPC a fly or a missing vertex."""
    scene, b = _case(chain, tmp_path)
    path = b / "full" / "plan.json"
    data = json.loads(path.read_text())
    assert data["steps"][1]["primitive"] == "pivot"
    data["steps"][1].update(edit)
    data["meta"]["content"] = artifacts._digest({k: v for k, v in data.items() if k != "meta"})
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    before = _snapshot(tmp_path / "c")
    line = _one_line_exit_2(runner.invoke(app, [str(a) for a in _command("plan", scene, b)]))
    assert f"{path}: {says}" in line, line
    assert _snapshot(tmp_path / "c") == before


def test_a_hand_edited_table_is_refused(chain, tmp_path):
    """A valid id in place of another passes the schema; the content's sha256 catches it."""
    scene, b = _case(chain, tmp_path)
    path = b / "graph" / "edges.parquet"
    t = pq.read_table(path)
    i = t.column_names.index("node_b")
    values = t.column(i).to_pylist()
    values[0] += 1
    pq.write_table(t.set_column(i, t.schema.field(i), pa.array(values, type=pa.int64())), path)
    before = _snapshot(tmp_path / "c")
    line = _one_line_exit_2(runner.invoke(app, [str(a) for a in _command("edges", scene, b)]))
    assert "edges.parquet: its content does not match its sha256 (edited by hand?)" in line, line
    assert _snapshot(tmp_path / "c") == before


def test_a_stage_writes_its_target_after_its_side_files(chain):
    """Make takes a stage as done when its target is newer than its inputs: the side files it vouches
    for (trajectories.json, frames.npz) are renamed into place before it."""
    full = chain / "build" / "full"
    assert (full / "trajectories.json").stat().st_mtime_ns <= (full / "trajectories.parquet").stat().st_mtime_ns
    for side in ("frames.npz", "execution.parquet"):
        assert (full / side).stat().st_mtime_ns <= (full / "execution.json").stat().st_mtime_ns


def test_two_checkouts_at_different_paths_write_byte_identical_artifacts(tmp_path, monkeypatch):
    repo = Path(__file__).resolve().parents[1]
    built = []
    for name in ("one", "two/deeper"):
        root = tmp_path / name
        shutil.copytree(repo / "data", root / "data")
        scene = root / "data" / "scenes" / "default.json"
        data = json.loads(scene.read_text())
        data["planner"]["max_poses"] = 20
        scene.write_text(json.dumps(data))
        monkeypatch.chdir(root)
        for args in (["analyze", "--scene", scene, "--out", root / "build" / "analysis"],  # absolute paths
                     ["sample", "data/scenes/default.json", "--analysis", "build/analysis", "--out", "build/sample"]):
            r = runner.invoke(app, [str(a) for a in args])
            assert r.exit_code == 0, r.output
        built.append(_snapshot(root / "build"))
    one, two = ({k: v for k, v in s.items() if not k.endswith(".timings.json")} for s in built)
    assert sorted(one) == sorted(two)
    assert [k for k in one if one[k] != two[k]] == []


def test_a_second_writer_of_one_output_gets_one_line_and_exit_2(chain, tmp_path):
    scene, b = _case(chain, tmp_path)
    before = _snapshot(tmp_path / "c")
    with artifacts.output_lock(b / "analysis"):
        r = runner.invoke(app, ["analyze", "--scene", str(scene), "--out", str(b / "analysis"), "--seed", "7"])
        line = _one_line_exit_2(r)
        assert "another pivot is writing it" in line and str(b / "analysis") in line
        with pytest.raises(ArtifactError):
            with artifacts.output_lock(b / "analysis"):
                pass
    assert _snapshot(tmp_path / "c") == before  # and the lock file is gone
    with artifacts.output_lock(b / "analysis"):  # free again
        pass


def test_artifacts_are_written_with_the_mode_the_umask_allows(tmp_path):
    old = os.umask(0o022)
    try:
        artifacts.write_json(tmp_path / "a.json", {"x": 1}, artifacts.make_meta("a", {}, {}, "test"))
        assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o644
        os.umask(0o077)
        artifacts.write_json(tmp_path / "b.json", {"x": 1}, artifacts.make_meta("b", {}, {}, "test"))
        assert (tmp_path / "b.json").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)


@pytest.mark.parametrize("where", ["existing_file", "read_only"])
def test_an_output_that_cannot_be_written_is_one_line_exit_2(tmp_path, where):
    from tests.conftest import PIANO

    if where == "existing_file":
        out = tmp_path / "taken"
        out.write_text("")
    else:
        if os.geteuid() == 0:
            pytest.skip("root writes into read-only folders")
        (tmp_path / "ro").mkdir()
        os.chmod(tmp_path / "ro", 0o555)
        out = tmp_path / "ro" / "analysis"
    r = runner.invoke(app, ["analyze", str(PIANO), "--out", str(out)])
    assert str(out.name) in _one_line_exit_2(r)


@pytest.mark.parametrize("args, names", [
    (["analyze", "--mass", "abc"], "'--mass'"),
    (["mpc", "s.json", "--horizon", "abc"], "'--horizon'"),
    (["sample"], "'scene'"),
    (["analyze", "--bogus"], "--bogus"),
    (["show", "poses", "d"], "'--scene'"),
])
def test_a_usage_error_keeps_typers_box_and_its_last_line_names_the_option(args, names):
    r = runner.invoke(app, args)
    text = [x.strip("│ ") for x in r.output.splitlines() if x.strip("│╰╭╮╯─ ")]
    assert r.exit_code == 2 and "Usage:" in r.output, r.output
    assert names in text[-1], r.output


def test_ctrl_c_is_one_line_exit_130_and_leaves_no_partial_artifact(chain, tmp_path, monkeypatch):
    """Interrupted while writing the second table: the first is complete, no temporary file stays and
    the target (sample.json, what Make tracks) is not written, so Make reruns the stage."""
    scene, b = _case(chain, tmp_path)
    shutil.rmtree(b / "sample")
    written = []
    real = pq.write_table

    def write_then_interrupt(table, where, **kw):
        if written:
            raise KeyboardInterrupt
        written.append(where)
        real(table, where, **kw)

    monkeypatch.setattr(pq, "write_table", write_then_interrupt)
    r = runner.invoke(app, ["sample", str(scene), "--analysis", str(b / "analysis"), "--out", str(b / "sample")])
    lines = [x for x in r.output.splitlines() if x.strip()]
    assert r.exit_code == 130 and len(lines) == 1 and "interrupted" in lines[0], r.output
    assert sorted(p.name for p in (b / "sample").iterdir()) == ["poses.parquet"]
    assert not (b / ".sample.lock").exists()


def test_an_execute_error_is_one_line_without_pybullets_banner(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "pivotcli", "execute", str(tmp_path / "nope.json"), "--build",
                        str(tmp_path / "b")], capture_output=True, text=True, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    lines = [x for x in (r.stdout + r.stderr).splitlines() if x.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "nope.json" in lines[0], r.stdout + r.stderr


def test_a_plan_whose_start_is_its_goal_is_one_line_in_mpc(tmp_path):
    from stages import analyze, graph, plan, sample

    scene = write_scene(tmp_path, "same", **{"planner.max_poses": 20, "goal.xy": [-0.18, 0.0]})
    b = tmp_path / "build"
    analyze.run(scene.parent / json.loads(scene.read_text())["object"]["mesh"], b / "analysis", 3.1, analyze.Params())
    sample.run(scene, b / "analysis", b / "sample", sample.Params())
    graph.run(scene, b / "analysis", b / "sample", b / "graph", graph.Params())
    p = plan.run(scene, b / "analysis", b / "sample", b / "graph", b / "plan.json", plan.Params())
    assert p["status"] == "ok" and p["steps"] == []
    r = runner.invoke(app, ["mpc", str(scene), "--build", str(b), "--plan", str(b / "plan.json"),
                            "--out", str(b / "t.parquet")])
    assert "plan.json: the plan has no steps (the start is already the goal)" in _one_line_exit_2(r)
    assert not (b / "t.parquet").exists()


def test_a_library_error_about_a_file_is_prefixed_with_it(tmp_path):
    from stages.errors import InputError, about

    with pytest.raises(InputError, match=r"^/x/plan.json: mpc: X_WO_ref has non-finite entries$"):
        with about("/x/plan.json"):
            raise InputError("mpc: X_WO_ref has non-finite entries")
    named = f"{tmp_path}/a.json: bad"
    with pytest.raises(InputError, match=f"^{named}$"):
        with about("/x/plan.json"):
            raise InputError(named)


def test_an_output_file_with_a_folder_in_its_place_is_one_line_naming_it(chain, tmp_path):
    scene, b = _case(chain, tmp_path)
    (b / "taken").mkdir()
    r = runner.invoke(app, ["mpc", str(scene), "--build", str(b), "--plan", str(b / "full" / "plan.json"),
                            "--out", str(b / "taken")])
    assert f"{b / 'taken'}: cannot write it (Is a directory)" in _one_line_exit_2(r)
    assert not [p for p in b.rglob("*.tmp")]


def test_diff_ignores_the_content_hash_of_values_equal_within_tolerance(tmp_path):
    import numpy as np

    fields = [artifacts.Field("pair_id", "id"), artifacts.Field("width", "m")]
    meta = artifacts.make_meta("widths", {}, {}, "test")
    for name, w in (("a", 0.3), ("b", 0.3 + 1e-13)):
        artifacts.write_table(tmp_path / f"{name}.parquet", {"pair_id": np.arange(1), "width": np.array([w])},
                              fields, meta)
        artifacts.write_json(tmp_path / f"{name}.json", {"width": w}, meta)
    assert artifacts.read_table(tmp_path / "a.parquet").meta["content"] != \
        artifacts.read_table(tmp_path / "b.parquet").meta["content"]
    assert artifacts.diff_artifacts(tmp_path / "a.parquet", tmp_path / "b.parquet") == []
    assert artifacts.diff_artifacts(tmp_path / "a.json", tmp_path / "b.json") == []
