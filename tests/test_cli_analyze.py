"""The CLI end to end: analyze, show, diff, errors; artifacts byte-identical across runs."""


import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from pivotcli.app import app
from stages import artifacts
from tests.conftest import REPO

runner = CliRunner()
GOLDEN = REPO / "tests" / "golden" / "toy_piano"


def invoke(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def test_version_and_help():
    r = invoke("--version")
    assert r.exit_code == 0 and r.output.startswith("pivot ")
    r = invoke("--help")
    assert r.exit_code == 0 and "analyze" in r.output and "diff" in r.output


def test_analyze_box_end_to_end_then_show_and_diff(box_path, tmp_path):
    out = tmp_path / "an"
    r = invoke("analyze", box_path, "--mass", "2", "--out", out)
    assert r.exit_code == 0, r.output
    for name in ("hull", "placements", "segments", "contacts", "pairs"):
        t = artifacts.read_table(out / f"{name}.parquet", name)
        assert t.meta["params"]["mass"] == 2.0
        assert t.meta["inputs"]["mesh"] == artifacts.sha256_file(box_path)
    assert artifacts.read_json(out / "analysis.json", "analysis")["counts"]["pivot_vertices"] == 8
    png = tmp_path / "fig.png"
    assert invoke("show", "analysis", out, "--png", png).exit_code == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A rerun is byte-identical; diff says equal.
    out2 = tmp_path / "an2"
    assert invoke("analyze", box_path, "--mass", "2", "--out", out2).exit_code == 0
    for p in out.glob("*.parquet"):
        assert p.read_bytes() == (out2 / p.name).read_bytes(), p.name
    r = invoke("diff", out, out2)
    assert r.exit_code == 0 and "equal" in r.output
    # Another parameter: diff exits 1 and says what differs.
    out3 = tmp_path / "an3"
    assert invoke("analyze", box_path, "--mass", "2", "--spacing", "0.05", "--out", out3).exit_code == 0
    r = invoke("diff", out / "contacts.parquet", out3 / "contacts.parquet")
    assert r.exit_code == 1 and "rows" in r.output


def test_analyze_curved_object_is_byte_identical_across_runs_and_takes_the_pair_options(tmp_path):
    mesh = tmp_path / "capsule.stl"
    trimesh.creation.capsule(height=0.25, radius=0.1).export(mesh)
    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:
        r = invoke("analyze", mesh, "--mass", "2", "--out", out)
        assert r.exit_code == 0, r.output
    for p in outs[0].glob("*.parquet"):
        assert p.read_bytes() == (outs[1] / p.name).read_bytes(), p.name
    pairs = artifacts.read_table(outs[0] / "pairs.parquet", "pairs")
    assert len(pairs) == 150 and (pairs["facet_a"] == -1).all()  # the default max_pairs, all cone pairs
    out = tmp_path / "c"
    r = invoke("analyze", mesh, "--mass", "2", "--max-pairs", "20", "--cone-angle", "10", "--out", out)
    assert r.exit_code == 0, r.output
    pairs = artifacts.read_table(out / "pairs.parquet", "pairs")
    assert len(pairs) == 20 and (pairs["angle"] <= np.radians(10)).all()
    assert pairs.meta["params"]["max_pairs"] == 20 and pairs.meta["params"]["cone_angle_deg"] == 10


@pytest.mark.parametrize(
    "name, text, args",
    [
        ("missing.obj", None, []),
        ("empty.obj", "", []),
        ("nan.obj", "v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", []),
        ("huge.obj", "v 0 0 0\nv 100 0 0\nv 0 100 0\nv 0 0 100\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n", []),
        ("ok.obj", "v 0 0 0\nv .1 0 0\nv 0 .1 0\nv 0 0 .1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n", ["--mass", "-1"]),
    ],
)
def test_bad_input_gives_one_line_exit_2_and_no_artifact(tmp_path, name, text, args):
    p = tmp_path / name
    if text is not None:
        p.write_text(text)
    out = tmp_path / "out"
    r = invoke("analyze", p, "--out", out, *args)
    assert r.exit_code == 2
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("pivot: error:") and name in lines[0]
    assert not out.exists() or not any(out.iterdir())


def test_truncated_artifact_is_refused_in_one_line(box_path, tmp_path):
    out = tmp_path / "an"
    assert invoke("analyze", box_path, "--mass", "2", "--out", out).exit_code == 0
    blob = (out / "pairs.parquet").read_bytes()
    (out / "pairs.parquet").write_bytes(blob[: len(blob) // 2])
    r = invoke("show", "analysis", out, "--png", tmp_path / "x.png")
    assert r.exit_code == 2 and "pairs.parquet" in r.output and "truncated" in r.output
    assert not (tmp_path / "x.png").exists()


def test_toy_piano_analysis_matches_golden(tmp_path):
    out = tmp_path / "piano"
    r = invoke("analyze", "--scene", REPO / "data" / "scenes" / "default.json", "--out", out)
    assert r.exit_code == 0, r.output
    assert GOLDEN.is_dir(), "golden artifacts missing: make golden"
    r = invoke("diff", GOLDEN, out, "--rtol", "1e-7", "--atol", "1e-9")
    assert r.exit_code == 0, r.output


def test_diff_only_one_key_of_two_json_artifacts(tmp_path):
    meta = artifacts.make_meta("plan", {"no_usp": False}, {}, "test")
    a, b, c = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "c.json"
    artifacts.write_json(a, {"status": "ok", "steps": [{"primitive": "pivot", "angle": 0.5}]}, meta)
    artifacts.write_json(b, {"status": "ok", "steps": [{"primitive": "pivot", "angle": 0.5}]},
                         artifacts.make_meta("plan", {"no_usp": True}, {}, "test"))
    artifacts.write_json(c, {"status": "ok", "steps": [{"primitive": "pivot", "angle": -0.5}]}, meta)
    assert invoke("diff", a, b).exit_code == 1  # the flags differ
    assert invoke("diff", a, b, "--only", "steps").exit_code == 0
    r = invoke("diff", a, c, "--only", "steps")
    assert r.exit_code == 1 and "steps[0].angle" in r.output
    r = invoke("diff", a, c, "--only", "cost")
    assert r.exit_code == 2 and "no key 'cost'" in r.output
