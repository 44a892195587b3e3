"""``pivot benchmark run``: every case's whole chain as Dask tasks, resumable (issue 13).

A case is one Dask task (:func:`run_case`) that runs the chain exactly as a user would, each stage
its own ``python -m pivotcli`` process in the case's build folder ``runs/<case>/`` (the commands of
the Makefile's stage targets): analyze, sample, graph, plan, mpc, then execute once per seed (seed 0
nominal, seed k > 0 ``--seed k``: friction, CoM, inertia, mass and initial position perturbed). A stage's
output goes to ``runs/<case>/logs/<stage>.log``; its wall time and peak resident memory
(``os.wait4``'s ``ru_maxrss`` of that process) are measured.

Failures are data: a stage that exits 1 (no plan, MPC failure, missed goal) or 2 (bad input), a
process that crashes or is killed after the case's time limit, a task whose worker dies: each gives
result rows with the stage reached, the exit code, a reason code and the error's last line; the
sweep goes on. A case is done when ``runs/<case>/case.json`` exists (written last, atomically) and
its key (the scene's, mesh's and robot's sha256, the code's fingerprint, seeds and limit) is the
current one; a rerun skips it.

The cluster is Dask distributed: a ``LocalCluster`` of ``workers`` single-threaded processes, or an
existing scheduler (``tcp://host:8786``) whose workers have pivot installed and see ``OUT`` at the
same path (a shared file system).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from stages import __version__, artifacts, stagelog
from stages.artifacts import Field

log = logging.getLogger("pivot.benchmark")

CHAIN = ("analyze", "sample", "graph", "plan", "mpc")
STAGES = (*CHAIN, "execute")
CODE = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class StageRun:
    """One stage process: exit code (-1 for a timeout), wall time (s), peak memory (MB), last error line."""

    stage: str
    exit_code: int
    seconds: float
    peak_mb: float
    error: str = ""

    @property
    def timed_out(self) -> bool:
        return self.exit_code == TIMEOUT


TIMEOUT = -1


def run_stage(stage: str, argv: list[str], log_path: Path, timeout: float) -> StageRun:
    """Run ``argv`` in its own session, output to ``log_path``; kill its process group after ``timeout``
    s. Peak memory is the process's ``ru_maxrss`` (its own, not its helpers')."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    killed = threading.Event()
    with open(log_path, "w") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)

        def kill() -> None:
            killed.set()
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

        timer = threading.Timer(max(timeout, 0.0), kill)
        timer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            timer.cancel()
        proc.returncode = code = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - t0
    if killed.is_set():
        return StageRun(stage, TIMEOUT, seconds, usage.ru_maxrss / 1024, f"timed out after {timeout:.0f} s")
    return StageRun(stage, code, seconds, usage.ru_maxrss / 1024, "" if code == 0 else last_line(log_path))


def last_line(path: Path) -> str:
    """The last non-empty line of a log (a traceback's exception or pivot's one-line error)."""
    lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    return lines[-1][:300] if lines else ""


def stage_argv(stage: str, scene: Path, b: Path, seed: int = 0) -> list[str]:
    """The ``pivot`` command of a stage for the case's scene and build folder (the Makefile's)."""
    pivot = [sys.executable, "-m", "pivotcli", "-q"]
    full = b / "full"
    return {
        "analyze": [*pivot, "analyze", "--scene", str(scene), "--out", str(b / "analysis")],
        "sample": [*pivot, "sample", str(scene), "--analysis", str(b / "analysis"), "--out", str(b / "sample")],
        "graph": [*pivot, "graph", str(scene), "--build", str(b)],
        "plan": [*pivot, "plan", str(scene), "--build", str(b), "--out", str(full / "plan.json")],
        "mpc": [*pivot, "mpc", str(scene), "--build", str(b), "--plan", str(full / "plan.json"),
                "--out", str(full / "trajectories.parquet")],
        "execute": [*pivot, "execute", str(scene), "--build", str(b), "--trajectories",
                    str(full / "trajectories.parquet"), "--out", str(full / f"seed{seed}"), "--seed", str(seed),
                    "--frames", "0"],
    }[stage]


RESULT_FIELDS = [
    Field("case", "id"), Field("object"), Field("kind"), Field("reachable"), Field("reach_reason"),
    Field("seed", "id"), Field("stage_reached"), Field("exit_code"), Field("reason"), Field("error"),
    Field("plan_found"), Field("pivots"), Field("tumbles"), Field("regrasps"), Field("usp_regrasps"),
    Field("backtracks"), Field("success"), Field("final_position_error", "m"), Field("final_yaw_error_deg", "deg"),
    Field("fell"), Field("collision"),
    *[Field(f"t_{s}", "s") for s in STAGES], *[Field(f"mem_{s}", "MB") for s in STAGES],
]


def slug(text: str) -> str:
    """A reason code from a sentence: lower case, numbers as ``n``, words joined by ``_``."""
    return re.sub(r"[^a-z0-9]+", "_", re.sub(r"\d+(\.\d+)?", "n", text.lower())).strip("_")


def read_json(path: Path) -> dict:
    """A JSON file's content, or {} when it is missing or unreadable (a crashed stage's)."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def blank_row(case: dict, seed: int) -> dict:
    """A result row before any stage ran."""
    return {"case": case["case"], "object": case["object"], "kind": case["kind"],
            "reachable": bool(case["reachable"]), "reach_reason": case["reason"], "seed": seed,
            "stage_reached": "", "exit_code": 0, "reason": "", "error": "", "plan_found": False, "pivots": 0,
            "tumbles": 0, "regrasps": 0, "usp_regrasps": 0, "backtracks": 0, "success": False,
            "final_position_error": float("nan"), "final_yaw_error_deg": float("nan"), "fell": False,
            "collision": False, **{f"{m}_{s}": float("nan") for m in ("t", "mem") for s in STAGES}}


def stage_outcome(run: StageRun, b: Path, seed: int) -> tuple[str, str]:
    """``(reason code, error)`` of a stage that did not exit 0 (``run.exit_code != 0``)."""
    if run.timed_out:
        return f"{run.stage}:timeout", run.error
    if run.exit_code == 2:
        return f"{run.stage}:bad_input", run.error
    full = b / "full"
    if run.exit_code == 1 and run.stage == "plan":
        plan = read_json(full / "plan.json")
        if plan.get("status") == "infeasible":
            return "plan:" + slug(plan.get("reason", "")), plan.get("reason", "")
    if run.exit_code == 1 and run.stage == "mpc":
        stats = read_json(full / "trajectories.json")
        if stats.get("status", "ok") != "ok":
            return "mpc:" + stats["status"], stats.get("reason", f"primitive {stats.get('failed_primitive')}")
    if run.exit_code == 1 and run.stage == "execute":
        ex = read_json(full / f"seed{seed}" / "execution.json")
        if "success" in ex:
            return physics_reason(ex)
    return f"{run.stage}:crash", run.error


def physics_reason(ex: dict) -> tuple[str, str]:
    """``(reason code, detail)`` of an execution (``execution.json``): ``physics:<code>`` with the first of
    its ``failures`` (``stages.execute.FAILURES``: fell, collision, over_force_bound, not_released,
    not_retreated, tilted, not_at_rest, missed_position, missed_yaw), the detail naming the others."""
    if ex.get("success"):
        return "ok", ""
    failures = list(ex.get("failures", []))
    if failures and failures[0] not in ("fell", "collision"):
        first = failures[0]
        detail = {"over_force_bound": f"{ex.get('max_ball_force', float('nan')):.1f} N over "
                                      f"{ex.get('force_bound', float('nan')):.0f} N",
                  "tilted": f"{ex.get('final_tilt_error_deg', float('nan')):.1f} deg"}.get(first, "")
        return f"physics:{first}", "; ".join(x for x in (detail, ", ".join(failures[1:])) if x)
    if ex.get("fell"):
        return "physics:fell", str(ex.get("fell_reason", ""))
    if ex.get("collision"):
        names = [*ex.get("robot_object_contacts", []), *ex.get("robot_obstacle_contacts", []),
                 *ex.get("robot_table_contacts", []), *ex.get("object_obstacle_contacts", [])]
        return "physics:collision", ", ".join(map(str, names))[:300]
    return "physics:missed_goal", (f"{100 * ex.get('final_position_error', float('nan')):.1f} cm, "
                                   f"{ex.get('final_yaw_error_deg', float('nan')):.1f} deg")


def plan_counts(b: Path) -> dict:
    """Plan found and its primitive counts from ``full/plan.json``."""
    plan = read_json(b / "full" / "plan.json")
    c = plan.get("counts", {})
    return {"plan_found": plan.get("status") == "ok", "pivots": int(c.get("pivot", 0)),
            "tumbles": int(c.get("tumble", 0)), "regrasps": int(c.get("regrasp", 0)),
            "usp_regrasps": int(c.get("usp_regrasp", 0)),
            "backtracks": stagelog.backtracks(plan)}


def run_chain(case: dict, out: Path, seeds: int, timeout: float) -> list[dict]:
    """The case's chain and its executions (module docstring); one row per seed."""
    b = out / "runs" / case["case"]
    scene = out / case["scene"]
    deadline = time.monotonic() + timeout
    common = blank_row(case, 0)
    for stale in ("analysis", "sample", "graph", "full"):  # a rerun reads only what it wrote itself
        shutil.rmtree(b / stale, ignore_errors=True)

    def stage(name: str, seed: int = 0) -> StageRun:
        log_name = f"execute{seed}.log" if name == "execute" else f"{name}.log"
        return run_stage(name, stage_argv(name, scene, b, seed), b / "logs" / log_name, deadline - time.monotonic())

    for name in CHAIN:
        run = stage(name)
        common.update({f"t_{name}": run.seconds, f"mem_{name}": run.peak_mb, "stage_reached": name,
                       "exit_code": run.exit_code})
        if name in ("plan", "mpc"):
            common.update(plan_counts(b))
        if run.exit_code != 0:
            reason, error = stage_outcome(run, b, 0)
            common.update(reason=reason, error=error)
            return [{**common, "seed": k} for k in range(seeds)]
    rows = []
    for k in range(seeds):
        run = stage("execute", k)
        row = {**common, "seed": k, "stage_reached": "execute", "exit_code": run.exit_code,
               "t_execute": run.seconds, "mem_execute": run.peak_mb}
        ex = read_json(b / "full" / f"seed{k}" / "execution.json")
        reason, error = physics_reason(ex) if run.exit_code in (0, 1) and "success" in ex else \
            stage_outcome(run, b, k)
        row.update(reason=reason, error=error, success=bool(ex.get("success", False)) and reason == "ok",
                   final_position_error=float(ex.get("final_position_error", float("nan"))),
                   final_yaw_error_deg=float(ex.get("final_yaw_error_deg", float("nan"))),
                   fell=bool(ex.get("fell", False)), collision=bool(ex.get("collision", False)))
        rows.append(row)
    return rows


def code_fingerprint() -> str:
    """sha256 over pivot's version and the source of ``stages/`` and ``pivotcli/`` (what the chain runs)."""
    h = hashlib.sha256(__version__.encode())
    for path in sorted([*(CODE / "stages").rglob("*.py"), *(CODE / "pivotcli").rglob("*.py")]):
        h.update(str(path.relative_to(CODE)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def case_key(case: dict, out: Path, seeds: int, timeout: float, code: str) -> str:
    """What makes a case's results current: its scene, mesh and robot files, the code, seeds and limit."""
    scene = out / case["scene"]
    if not scene.is_file():
        return f"no-scene:{code}:{seeds}:{timeout}"
    data = json.loads(scene.read_text())
    files = [scene, scene.parent / data["object"]["mesh"], scene.parent / data["robot"]["urdf"]]
    digests = [artifacts.sha256_file(f) if f.is_file() else "missing" for f in files]
    return hashlib.sha256(json.dumps([*digests, code, seeds, timeout]).encode()).hexdigest()


def run_case(out: str, case: dict, seeds: int, timeout: float, key: str) -> list[dict]:
    """The Dask task of one case: its rows (one per seed), also written to ``runs/<case>/case.json``.

    Any exception becomes ``harness:crash`` rows, not stored (a rerun tries the case again); a case
    without a scene (the suite could not draw one) gives rows with the suite's reason.
    """
    o = Path(out)
    try:
        if (o / case["scene"]).is_file():
            rows = run_chain(case, o, seeds, timeout)
        else:
            rows = [{**blank_row(case, k), "reason": f"make:{case['reason']}"} for k in range(seeds)]
    except Exception as e:  # a bug of the harness or the file system: recorded, the sweep goes on
        return crash_rows(case, seeds, f"{type(e).__name__}: {e}")
    meta = artifacts.make_meta("benchmark_case", {"seeds": seeds, "timeout": timeout}, {}, "benchmark run")
    artifacts.write_json(o / "runs" / case["case"] / "case.json", {"key": key, "rows": rows}, meta)
    return rows


def crash_rows(case: dict, seeds: int, error: str) -> list[dict]:
    """Rows of a case whose task raised or whose worker died."""
    return [{**blank_row(case, k), "reason": "harness:crash", "error": error[:300]} for k in range(seeds)]


def finished_rows(out: Path, case: dict, key: str) -> list[dict] | None:
    """The stored rows of a case whose ``case.json`` carries ``key``; None when it must run."""
    data = read_json(out / "runs" / case["case"] / "case.json")
    return data.get("rows") if data.get("key") == key else None


@dataclass(frozen=True)
class SweepParams:
    """The sweep: seeds per case, the per-case limit (s), the cluster."""

    seeds: int = 2
    timeout: float = 600.0
    workers: int = 2
    scheduler: str = ""


@dataclass(frozen=True)
class SweepSummary:
    cases: int
    ran: int
    skipped: int
    crashed: int
    rows: int


def sweep(out: str | Path, prm: SweepParams = SweepParams(),
          on_case: Callable[[str, bool], None] | None = None) -> SweepSummary:
    """Run every case of ``out/suite.json`` not yet current on Dask; write ``out/results.parquet``.

    ``on_case(case, skipped)`` is called as each case finishes (the CLI's progress bar).
    """
    out = Path(out).resolve()
    suite = artifacts.read_json(out / "suite.json", "benchmark_suite")
    code = code_fingerprint()
    rows: dict[str, list[dict]] = {}
    todo = []
    for case in suite["cases"]:
        key = case_key(case, out, prm.seeds, prm.timeout, code)
        done = finished_rows(out, case, key)
        if done is None:
            todo.append((case, key))
        else:
            rows[case["case"]] = done
            if on_case:
                on_case(case["case"], True)
    crashed = 0
    if todo:
        crashed = _submit(out, todo, prm, rows, on_case)
    ordered = [r for case in suite["cases"] for r in rows[case["case"]]]
    write_results(out / "results.parquet", ordered, prm)
    return SweepSummary(len(suite["cases"]), len(todo), len(suite["cases"]) - len(todo), crashed, len(ordered))


def _submit(out: Path, todo: list, prm: SweepParams, rows: dict, on_case) -> int:
    """Run ``todo`` on the cluster; fill ``rows``; returns how many tasks raised (worker lost)."""
    from distributed import Client, LocalCluster, as_completed

    logging.getLogger("distributed").setLevel(logging.ERROR)  # the scheduler's own chatter, not ours
    cluster = None
    if not prm.scheduler:
        cluster = LocalCluster(n_workers=prm.workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR)
    crashed = 0
    try:
        with Client(prm.scheduler or cluster) as client:
            futures = {client.submit(run_case, str(out), case, prm.seeds, prm.timeout, key, pure=False,
                                     key=f"pivot-case-{case['case']}"): case for case, key in todo}
            for fut in as_completed(futures):
                case = futures[fut]
                try:
                    rows[case["case"]] = fut.result()
                except Exception as e:  # the worker died (KilledWorker) or the task could not run
                    crashed += 1
                    rows[case["case"]] = crash_rows(case, prm.seeds, f"{type(e).__name__}: {e}")
                if on_case:
                    on_case(case["case"], False)
    finally:
        if cluster is not None:
            cluster.close()
    return crashed


def write_results(path: Path, rows: list[dict], prm: SweepParams) -> None:
    """``results.parquet``: one row per (case, seed), columns :data:`RESULT_FIELDS`."""
    # Each column takes the type of its value in a blank row; a NaN stored in case.json reads back None.
    blank = blank_row({"case": "", "object": "", "kind": "", "reachable": False, "reason": ""}, 0)
    types = {str: object, bool: bool, int: np.int64, float: np.float64}
    cols = {f.name: np.array([float("nan") if r[f.name] is None else r[f.name] for r in rows],
                             dtype=types[type(blank[f.name])]) for f in RESULT_FIELDS}
    meta = artifacts.make_meta("benchmark_results", {**asdict(prm)}, {"suite": path.parent / "suite.json"},
                               "benchmark run")
    artifacts.write_table(path, cols, RESULT_FIELDS, meta)
