"""The pipeline as a contract: default paths chain, Make and ``pivot run`` rerun the same stages (the
import graph's), ``pivot run`` works from an installed package, the CLI starts without the stages."""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pivotcli.app import app
from pivotcli.layout import FIGURES, PACKAGE_ROOT, STAGES, Layout, code_files, variant_of
from tests.conftest import write_scene

REPO = Path(__file__).resolve().parents[1]
runner = CliRunner()
TINY = {"planner.max_poses": 30, "goal.xy": [-0.14, 0.0]}


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def _install_copy(dst: Path) -> Path:
    """What ``pip install`` puts in site-packages (the ``pivotcli`` and ``stages`` packages' modules, no
    Makefile, no data), with sources an hour old so that artifacts made now are newer."""
    site = dst / "site"
    for pkg in ("pivotcli", "stages"):
        for src in (REPO / pkg).rglob("*.py"):
            target = site / src.relative_to(REPO)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, target)
    old = time.time() - 3600
    for p in site.rglob("*"):
        os.utime(p, (old, old))
    return site


def test_every_command_on_its_defaults_chains_in_order_from_an_empty_folder(tmp_path, monkeypatch):
    site = _install_copy(tmp_path)
    scene = write_scene(tmp_path, "tiny", **TINY)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    for args in (("analyze", "--scene", scene), ("sample", scene), ("graph", scene), ("plan", scene),
                 ("mpc", scene), ("execute", scene, "--frames", "4")):
        r = invoke(*args)
        assert r.exit_code == 0, (args, r.output)
    lay = Layout.of(scene)
    for s in STAGES:
        assert all(p.is_file() for p in lay.outputs(s.name)), s.name
    assert sorted(p.name for p in work.iterdir()) == ["build"]
    assert lay.stale("execute") == [] and lay.plan == Path("build/tiny/full/plan.json")

    # pivot run from the installed copy (no Makefile anywhere) finds every stage up to date, draws the
    # figures and prints its summary on stdout; after an output is deleted it reruns that stage alone.
    def pivot_run(*args):
        return subprocess.run([sys.executable, "-m", "pivotcli", "run", str(scene), *args], cwd=work,
                              capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(site)})

    proc = pivot_run("--json")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["ran"] == {} and summary["plan"]["status"] == "ok" and summary["physics"]["success"]
    assert sorted(Path(f).name for f in summary["figures"]) == sorted(Path(f.path).name for f in FIGURES)
    (lay.run_dir / "execution.parquet").unlink()
    proc = pivot_run("--json")
    assert proc.returncode == 0, proc.stderr
    assert list(json.loads(proc.stdout)["ran"]) == ["execute"]
    proc = pivot_run()
    assert proc.returncode == 0 and "ran: nothing (every stage up to date)" in proc.stdout, proc.stderr


def test_an_ablation_plans_into_its_own_folder_and_mpc_finds_it_by_variant():
    assert variant_of(no_tumble=True) == "no-tumble" and variant_of() == "full"
    lay = Layout.of(Path("x/s.json"), variant="no-usp")
    assert lay.plan == Path("build/s/no-usp/plan.json") and lay.analysis == Path("build/s/analysis")


def test_execute_depends_on_every_module_it_imports_and_graph_not_on_the_planner():
    rel = {s.name: {str(p.relative_to(PACKAGE_ROOT)) for p in code_files(s.command)} for s in STAGES}
    # The hand-kept Makefile list missed these three, which stages/execute.py imports.
    assert {"stages/robot.py", "stages/scene.py", "stages/analyze.py", "stages/execute.py",
            "pivotcli/execute.py"} <= rel["execute"]
    assert "stages/plan.py" not in rel["graph"] and "stages/execute.py" not in rel["plan"]
    assert "pivotcli/sample.py" in rel["sample"]  # the CLI module holding a stage's parameters counts
    assert "stages/plots.py" not in rel["execute"]


# ------------------------------------------------------------------------------ Make and pivot run
def _copy_tree(dst: Path) -> Path:
    """A copy of the checkout's code, data and Makefile whose sources are an hour old."""
    repo = dst / "repo"
    for d in ("pivotcli", "stages", "data"):
        shutil.copytree(REPO / d, repo / d, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "Makefile", repo / "Makefile")
    old = time.time() - 3600
    for p in repo.rglob("*"):
        os.utime(p, (old, old))
    return repo


def _fake_build(repo: Path) -> Layout:
    """Every output and figure of the default scene, each stage's newer than its upstream's."""
    lay = Layout.of(repo / "data/scenes/default.json", repo / "build/default")
    t = time.time() - 600
    for s in STAGES:
        t += 10
        for p in [*lay.outputs(s.name), *[lay.figure(f.name) for f in FIGURES if f.stage == s.name]]:
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text("{}")
            os.utime(p, (t + 5 * p.suffix.endswith("png"),) * 2)
    return lay


def _make_reruns(repo: Path) -> list[str]:
    """The stages and figures ``make analysis sample plan mpc execute`` would rerun, from ``make -t``
    (which touches the targets it would remake instead of running their recipes)."""
    env = {**os.environ, "PYTHONPATH": str(repo)}
    proc = subprocess.run(["make", "-t", "--no-print-directory", "-C", str(repo), "INSTALLED=",
                           f"PIVOT={sys.executable} -m pivotcli", "analysis", "sample", "plan", "mpc", "execute"],
                          capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    touched = {line.split()[1] for line in proc.stdout.splitlines() if line.startswith("touch ")}
    lay = Layout.of(Path("data/scenes/default.json"), Path("build/default"))
    ran = [s.name for s in STAGES if touched & {str(p) for p in lay.outputs(s.name)}]
    return ran + [f"{f.name}.png" for f in FIGURES if str(lay.figure(f.name)) in touched]


def _run_reruns(repo: Path) -> list[str]:
    """The stages ``pivot run`` would rerun: ``Layout.stale`` of the copied package, in its own process."""
    code = ("from pathlib import Path; from pivotcli.layout import Layout, STAGES\n"
            "lay = Layout.of(Path('data/scenes/default.json'))\n"
            "stale = set()\n"
            "for s in STAGES:\n"
            "    if lay.stale(s.name) or (s.upstream in stale): stale.add(s.name); print(s.name)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(repo)})
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.split()


@pytest.mark.parametrize("change, stages", [
    ("", []),
    ("touch stages/execute.py", ["execute"]),
    ("touch stages/robot.py", ["sample", "graph", "plan", "mpc", "execute"]),
    ("touch pivotcli/sample.py", ["sample", "graph", "plan", "mpc", "execute"]),
    ("touch stages/trajectory.py", ["plan", "mpc", "execute"]),
    ("rm build/default/sample/poses.parquet", ["sample", "graph", "plan", "mpc", "execute"]),
    ("touch data/scenes/default.json", ["analyze", "sample", "graph", "plan", "mpc", "execute"]),
])
def test_make_and_pivot_run_rerun_the_stages_a_change_reaches_and_only_those(tmp_path, change, stages):
    repo = _copy_tree(tmp_path)
    _fake_build(repo)
    if change:
        subprocess.run(change.split(), cwd=repo, check=True)
    assert _run_reruns(repo) == stages
    figures = {"analyze": "analysis", "sample": "poses", "plan": "plan", "mpc": "trajectories",
               "execute": "execution"}
    assert _make_reruns(repo) == stages + [f"{figures[s]}.png" for s in stages if s in figures]


def test_a_figure_reruns_when_only_its_drawing_code_changes(tmp_path):
    repo = _copy_tree(tmp_path)
    _fake_build(repo)
    (repo / "stages/plots.py").touch()  # the PNG figures' drawing code (the 3D view has its own, stages/view.py)
    assert _make_reruns(repo) == [f"{f.name}.png" for f in FIGURES if f.module == "pivotcli.show"]
    assert _run_reruns(repo) == []


# ---------------------------------------------------------------------------------------- start-up
def test_pivot_help_imports_no_stage_and_no_numpy():
    code = ("import sys\nfrom pivotcli.app import main\nsys.argv = ['pivot', '--help']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'stages', 'trimesh')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr
    assert "analyze" in proc.stdout and "benchmark" in proc.stdout
    assert proc.stdout.strip().splitlines()[-1] == "['stages', 'stages.errors']"


# ----------------------------------------------------------------------------------------- logging
def test_v_logs_each_stage_counts_and_vv_its_reasons(box_path, tmp_path):
    r = invoke("analyze", box_path, "--out", tmp_path / "a")
    assert r.exit_code == 0 and "stages.analyze" not in r.output
    r = invoke("-v", "analyze", box_path, "--out", tmp_path / "a")
    assert "stages.analyze: analysis: cone_pairs 0, " in r.output and "filtered" not in r.output, r.output
    r = invoke("-vv", "analyze", box_path, "--out", tmp_path / "a")
    assert "stages.analyze: analysis: contact candidates filtered: " in r.output, r.output


def test_vv_plan_logs_every_step_and_every_edge_backtracking_removed(small_build, tmp_path):
    scene, b = small_build
    r = invoke("-vv", "plan", scene, "--build", b, "--out", tmp_path / "plan.json")
    assert r.exit_code == 0, r.output
    plan = json.loads((tmp_path / "plan.json").read_text())
    lines = r.output.splitlines()
    assert sum(line.startswith("stages.plan: plan: step ") for line in lines) == len(plan["steps"])
    assert sum(line.startswith("stages.plan: plan: removed ") for line in lines) == len(plan["log"])
    assert any(line.startswith(f"stages.plan: plan: {plan['status']}, cost ") for line in lines)


# ------------------------------------------------------------------------------ units outside pyarrow
def test_parquet_artifacts_carry_units_and_frames_as_schema_level_maps(tmp_path):
    import numpy as np
    import pyarrow.parquet as pq

    from stages import artifacts

    fields = [artifacts.Field("pose_id", "id"), artifacts.Field("x", "m", "W"), artifacts.Field("angle", "rad")]
    cols = {"pose_id": np.arange(3), "x": np.zeros(3), "angle": np.ones(3)}
    artifacts.write_table(tmp_path / "t.parquet", cols, fields, artifacts.make_meta("t", {}, {}, "test"))
    schema = pq.read_schema(tmp_path / "t.parquet")
    units, frames = json.loads(schema.metadata[b"units"]), json.loads(schema.metadata[b"frames"])
    assert units == {f.name: schema.field(f.name).metadata[b"unit"].decode() for f in fields}
    assert units == {"pose_id": "id", "x": "m", "angle": "rad"} and frames == {"x": "W"}
