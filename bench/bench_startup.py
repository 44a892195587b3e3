"""Start-up of the CLI (issue 16, point 8): ``pivot --help``, the whole default chain from scratch with
``pivot run``, and a second ``pivot run`` with nothing changed, each in its own process as a user
runs them (median of ``RUNS``)."""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RUNS = 5
TARGETS = {"help": 0.3, "chain": 12.0, "noop": 1.0}


def _time(args: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "pivotcli", *args], cwd=cwd, check=False, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(REPO)})
    return time.perf_counter() - t0


def _row(what: str, seconds: float, target: float) -> tuple[str, str, str, str]:
    return what, f"{seconds:.2f} s", f"<= {target:g} s {'ok' if seconds <= target else 'MISSED'}", ""


def rows() -> list[tuple[str, str, str, str]]:
    scene = str(REPO / "data" / "scenes" / "default.json")
    with tempfile.TemporaryDirectory(prefix="pivot-startup-") as tmp:
        work = Path(tmp)
        help_s = statistics.median(_time(["--help"], work) for _ in range(RUNS))
        chain = _time(["run", scene, "--no-figures"], work)  # from scratch: once (about 20 s)
        noop = statistics.median(_time(["run", scene, "--no-figures"], work) for _ in range(RUNS))
    return [_row("start-up: pivot --help", help_s, TARGETS["help"]),
            _row("start-up: pivot run default, from scratch (1 run)", chain, TARGETS["chain"]),
            _row("start-up: pivot run default, nothing changed", noop, TARGETS["noop"])]
