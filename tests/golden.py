"""Golden artifacts of the reference scenes: every stage's output, kept as a readable digest.

``tests/golden/<scene>.json`` holds, per stage, each artifact of the chain analyze -> sample -> graph
-> plan -> mpc -> execute on ``data/scenes/<scene>.json`` (the CLI's default parameters, execution
without rendered frames). A JSON artifact is kept whole (less the input hashes and the producer's
version, which change with any upstream byte); a Parquet artifact as its row count and, per column,
order-sensitive statistics (``n``, ``min``, ``max``, ``mean``, ``wsum`` = the values weighted by
cos(row), for floats; the exact sums for integers; the value counts for strings). A review of
``git diff tests/golden`` shows which stage, artifact and column moved, and by how much.

``make golden`` (``python -m tests.golden``) regenerates the digests; ``make test`` compares them
(``tests/test_golden.py``) with the tolerances of :func:`tolerance`: 1e-6 relative for the planning
stages, the physics metrics of the execution with physics tolerances (a millimetre, a tenth of a
degree). Tolerances cannot absorb a decision that a last bit flips (an IK that converges at its
tolerance or not), so the chains run on one pinned floating point (``PINNED_ENV``: no SIMD dispatch
in numpy, generic OpenBLAS kernels, piqp's AVX2 build), the same on every x86-64 machine.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

REPO = Path(__file__).resolve().parents[1]
GOLDEN = REPO / "tests" / "golden"
SCENES = ("default", "exp1_reach", "exp2_rotate", "exp3_obstacle")
# stage -> the artifacts it writes that the golden digest keeps (the frames and timings are not kept).
ARTIFACTS = {
    "analyze": ("analysis.json", "hull.parquet", "segments.parquet", "placements.parquet", "contacts.parquet",
                "pairs.parquet"),
    "sample": ("sample.json", "poses.parquet", "pose_links.parquet", "grasps.parquet", "grasp_rejects.parquet"),
    "graph": ("graph.json", "nodes.parquet", "edges.parquet", "catches.parquet"),
    "plan": ("plan.json",),
    "mpc": ("trajectories.json", "trajectories.parquet"),
    "execute": ("execution.json",),
}


@dataclass(frozen=True)
class Tolerance:
    """``|a - b| <= atol + rtol * |b|`` for floats; everything else compares exactly."""

    rtol: float
    atol: float


PLANNING = Tolerance(rtol=1e-6, atol=1e-9)
# Physics: positions (m) and slips to 1 mm, angles (deg) to 0.1 deg, forces (N) and the rest 2 %.
PHYSICS = {"": Tolerance(0.02, 1e-3), "deg": Tolerance(0.0, 0.1)}


def tolerance(stage: str, key: str) -> Tolerance:
    """The tolerance of ``key`` (a dotted path into the digest) of ``stage``'s artifact."""
    if stage != "execute":
        return PLANNING
    return PHYSICS["deg"] if "deg" in key else PHYSICS[""]


@dataclass(frozen=True)
class Chain:
    """Where one reference scene's chain wrote its artifacts (the analysis may be shared)."""

    scene: Path
    analysis: Path
    build: Path

    def folder(self, stage: str) -> Path:
        return {"analyze": self.analysis, "sample": self.build / "sample", "graph": self.build / "graph"}.get(
            stage, self.build / "full")


#: The reference chains run on the same floating point on every x86-64 machine: numpy's baseline
#: loops (no AVX2/AVX-512 dispatch), OpenBLAS's generic SSE3 kernels and piqp's AVX2 build (not its
#: AVX-512 one). Each SIMD path rounds differently in the last bits, which flips borderline IK and
#: collision decisions downstream and moves the physics by millimetres, so digests made on one kind of
#: machine would not match another's.
PINNED_ENV = {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4", "OPENBLAS_CORETYPE": "Prescott"}


def run_chain(scene: Path, root: Path) -> Chain:
    """The six stages on ``scene`` with the CLI's default parameters (no frames rendered), into
    ``root/<scene>/``, in a process on the pinned floating point (``PINNED_ENV``); scenes with the same
    object (mesh, mass, scale) share one analysis under ``root``."""
    import os
    import subprocess

    env = {**os.environ, **PINNED_ENV, "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, "-m", "tests.golden", "--chain", str(scene), str(root)], cwd=REPO, env=env,
                   check=True, stdout=subprocess.DEVNULL)
    return _chain(scene, root)


def _chain(scene: Path, root: Path) -> Chain:
    from stages.scene import load_scene

    spec = load_scene(scene).object
    analysis = root / f"analysis-{spec.mesh_path.stem}-{spec.mass:g}kg-x{spec.scale:g}"
    return Chain(scene, analysis, root / scene.stem)


def _run_chain_here(scene: Path, root: Path) -> None:
    """:func:`run_chain`'s process: piqp's AVX2 build is chosen before anything imports piqp (its
    ``__init__`` picks the build from ``piqp.instruction_set``, loaded here first and told no AVX-512)."""
    import importlib.util

    where = importlib.util.find_spec("piqp").submodule_search_locations[0]
    spec = importlib.util.spec_from_file_location(
        "piqp.instruction_set", next(Path(where).glob("instruction_set*.so")))
    isa = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(isa)
    isa.avx512f = False
    sys.modules["piqp.instruction_set"] = isa
    from stages import analyze, execute, graph, plan, sample, trajectory
    from stages.scene import load_scene

    spec = load_scene(scene).object
    ch = _chain(scene, root)
    analysis = ch.analysis
    if not (analysis / "analysis.json").is_file():
        analyze.run(spec.mesh_path, analysis, spec.mass, analyze.Params(), scale=spec.scale)
    sample.run(scene, analysis, ch.folder("sample"), sample.Params())
    graph.run(scene, analysis, ch.folder("sample"), ch.folder("graph"), graph.Params())
    full = ch.folder("plan")
    p = plan.run(scene, analysis, ch.folder("sample"), ch.folder("graph"), full / "plan.json", plan.Params())
    if p["status"] != "infeasible":
        stats = trajectory.run(scene, analysis, full / "plan.json", full / "trajectories.parquet", trajectory.Params())
        if stats["status"] == "ok":
            execute.run(scene, analysis, full / "trajectories.parquet", full, execute.Params())


def digest_json(path: Path) -> dict:
    data = json.loads(path.read_text())
    meta = data.get("meta", {})
    data["meta"] = {k: v for k, v in meta.items() if k not in ("inputs", "producer")}
    return data


def digest_column(values) -> dict:
    """Order-sensitive statistics of one column (list columns flattened row after row)."""
    if values.dtype == object:
        rows = [np.asarray(v).ravel() for v in values]
        flat = np.concatenate(rows) if rows else np.zeros(0)
        if flat.dtype.kind in "fiub":
            return {"list_lengths": int(sum(len(r) for r in rows)), **digest_column(flat)}
        values = np.asarray([str(v) for v in values])
    kind = values.dtype.kind
    if kind in "US":
        uniq, n = np.unique(values, return_counts=True)
        return {"n": len(values), "counts": {str(u): int(k) for u, k in zip(uniq, n, strict=True)}}
    if kind in "iub":
        v = values.astype(np.int64)
        w = np.arange(len(v)) % 7 + 1
        return {"n": len(v), "sum": int(v.sum()), "wsum": int((v * w).sum())}
    v = values.astype(np.float64)
    finite = np.isfinite(v)
    f = v[finite]
    w = np.cos(np.arange(len(v)))[finite]
    out = {"n": len(v), "nonfinite": int((~finite).sum())}
    if len(f):
        out.update(min=float(f.min()), max=float(f.max()), mean=float(f.mean()), wsum=float((f * w).sum()))
    return out


def digest_parquet(path: Path) -> dict:
    table = pq.read_table(path)
    meta = {k.decode(): json.loads(v) for k, v in (table.schema.metadata or {}).items()
            if k.decode() not in ("ARROW:schema", "inputs", "producer")}
    cols = {}
    for name in table.column_names:
        col = table.column(name)
        arr = (np.array([np.asarray(x) for x in col.to_pylist()] + [None], dtype=object)[:-1]
               if str(col.type).startswith(("list", "large_list")) else col.to_numpy(zero_copy_only=False))
        cols[name] = digest_column(arr)
    return {"meta": meta, "rows": table.num_rows, "columns": cols}


def digest_chain(ch: Chain) -> dict:
    """``{stage: {artifact: digest}}`` of every kept artifact the chain wrote (a missing one: None)."""
    out = {}
    for stage, names in ARTIFACTS.items():
        out[stage] = {}
        for name in names:
            p = ch.folder(stage) / name
            out[stage][name] = None if not p.is_file() else (
                digest_json(p) if name.endswith(".json") else digest_parquet(p))
    return out


def compare(golden: dict, new: dict) -> list[str]:
    """One line per difference beyond the tolerances: ``stage/artifact key: golden -> new``."""
    lines = []
    for stage in sorted(set(golden) | set(new)):
        arts_a, arts_b = golden.get(stage, {}), new.get(stage, {})
        for name in sorted(set(arts_a) | set(arts_b)):
            for key, a, b in _walk(arts_a.get(name, "<absent>"), arts_b.get(name, "<absent>"), ""):
                tol = tolerance(stage, key)
                numbers = all(isinstance(v, float | int) and not isinstance(v, bool) for v in (a, b))
                if numbers and isinstance(a, float) | isinstance(b, float):
                    if abs(b - a) <= tol.atol + tol.rtol * abs(a):
                        continue
                elif a == b:
                    continue
                lines.append(f"{stage}/{name}{' ' + key if key else ''}: {_short(a)} -> {_short(b)}")
    return lines


def _walk(a, b, key: str) -> Iterator[tuple[str, object, object]]:
    """Leaves of two nested dicts/lists side by side: (key path, golden, new)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            yield from _walk(a.get(k, "<absent>"), b.get(k, "<absent>"), f"{key}.{k}" if key else str(k))
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            yield from _walk(x, y, f"{key}[{i}]")
    else:
        yield key, a, b


def _short(v) -> str:
    s = json.dumps(v, sort_keys=True) if not isinstance(v, str) else v
    return s if len(s) <= 80 else s[:77] + "..."


def write_golden(scene: str, digest: dict) -> Path:
    path = GOLDEN / f"{scene}.json"
    path.write_text(json.dumps(digest, indent=1, sort_keys=True) + "\n")
    return path


def main(argv: list[str]) -> int:
    """``make golden``: run each reference scene's chain in a temporary folder and rewrite its digest."""
    import tempfile

    scenes = argv or list(SCENES)
    with tempfile.TemporaryDirectory(prefix="pivot-golden-") as tmp:
        for name in scenes:
            ch = run_chain(REPO / "data" / "scenes" / f"{name}.json", Path(tmp))
            print(f"wrote {write_golden(name, digest_chain(ch)).relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["--chain"]:
        _run_chain_here(Path(sys.argv[2]), Path(sys.argv[3]))
        sys.exit(0)
    sys.exit(main(sys.argv[1:]))
