"""Provenance: a stage refuses upstream artifacts made from other inputs than the ones it is given.

Every artifact records the sha256 of its input files (``meta["inputs"]``, see ``stages.artifacts``).
Before a stage computes, it checks the chain it reads back to the scene it is given now: the
analysis was made from the scene's mesh, scale and mass; the samples from this scene and this
analysis; the graph from these samples; the plan and the trajectories from this scene and this
analysis. A stale or foreign upstream is bad input (``ArtifactError``: one line naming both files).
A plan's steps are also checked for what the MPC needs (:func:`check_plan_steps`).
"""

from __future__ import annotations

import math
from pathlib import Path

from stages import artifacts
from stages.errors import ArtifactError
from stages.scene import Scene

ANALYSIS_TABLES = ("hull", "placements", "contacts", "pairs")
SAMPLE_TABLES = ("poses", "pose_links", "grasps", "grasp_rejects")
GRAPH_TABLES = ("nodes", "edges", "catches")


def analysis_inputs(analysis_dir: str | Path) -> dict[str, Path]:
    """The analysis tables a downstream artifact records as its inputs (name -> file)."""
    return {n: Path(analysis_dir) / f"{n}.parquet" for n in ANALYSIS_TABLES}


def check_analysis(analysis_dir: str | Path, scene: Scene) -> None:
    """The analysis in ``analysis_dir`` was made from ``scene``'s mesh with its scale and mass."""
    d = Path(analysis_dir)
    summary = d / "analysis.json"
    meta = artifacts.read_meta(summary, "analysis")
    artifacts.check_inputs(summary, meta, {"mesh": scene.object.mesh_path})
    for key, value in (("scale", scene.object.scale), ("mass", scene.object.mass)):
        made = meta.get("params", {}).get(key)
        if made != value:
            raise ArtifactError(f"{summary} was made with {key} {made}, not the {key} {value} of {scene.path}; "
                                f"rerun pivot analyze")
    for name in ANALYSIS_TABLES:  # one run's files, not a mix of two
        artifacts.check_inputs(d / f"{name}.parquet", artifacts.read_meta(d / f"{name}.parquet", name),
                               {"mesh": scene.object.mesh_path})


def check_sample(sample_dir: str | Path, scene: Scene, analysis_dir: str | Path) -> None:
    """The samples in ``sample_dir`` were made from ``scene`` and the analysis in ``analysis_dir``."""
    check_analysis(analysis_dir, scene)
    given = {"scene": scene.path, **analysis_inputs(analysis_dir)}
    d = Path(sample_dir)
    for name in SAMPLE_TABLES:
        artifacts.check_inputs(d / f"{name}.parquet", artifacts.read_meta(d / f"{name}.parquet", name), given)
    artifacts.check_inputs(d / "sample.json", artifacts.read_meta(d / "sample.json", "sample"), given)


def check_graph(graph_dir: str | Path, scene: Scene, analysis_dir: str | Path, sample_dir: str | Path) -> None:
    """The graph in ``graph_dir`` was made from ``scene`` and the samples in ``sample_dir``."""
    check_sample(sample_dir, scene, analysis_dir)
    sd, d = Path(sample_dir), Path(graph_dir)
    given = {"scene": scene.path, **{n: sd / f"{n}.parquet" for n in ("poses", "grasps", "pose_links")}}
    for name in GRAPH_TABLES:
        artifacts.check_inputs(d / f"{name}.parquet", artifacts.read_meta(d / f"{name}.parquet", name), given)
    artifacts.check_inputs(d / "graph.json", artifacts.read_meta(d / "graph.json", "graph"), given)


def check_made_from(path: str | Path, meta: dict, scene: Scene, analysis_dir: str | Path) -> None:
    """The plan or trajectories ``path`` (metadata ``meta``) were made from ``scene`` and this analysis."""
    check_analysis(analysis_dir, scene)
    artifacts.check_inputs(path, meta, {"scene": scene.path, **analysis_inputs(analysis_dir)})


_POSE_KEYS = ("x", "y", "z", "qx", "qy", "qz", "qw")
_STEP_KEYS = {"pivot": ("vertex", "contacts"), "regrasp": ("support",), "tumble": ("pusher", "pusher_contact", "edge")}
#: A squeeze tumble (``stages.squeeze``): both balls on their grasp's contacts roll the object over its edge,
#: with the squeeze parameters the graph checked it with.
_SQUEEZE_KEYS = ("contacts", "edge", "squeeze")


def check_plan_steps(plan_path: str | Path, plan: dict, n_vertices: int, n_contacts: int) -> None:
    """Each step of ``plan`` is one the planner writes: a known primitive with its keys, poses of
    finite numbers, hull vertices in ``[0, n_vertices)`` and contacts in ``[0, n_contacts)``.

    A plan whose hash was forged after an edit still cannot send the MPC a ``fly`` or a pivot about
    vertex 999; raises ``ArtifactError`` naming the file and the step.
    """
    def bad(k: int, what: str) -> ArtifactError:
        return ArtifactError(f"{plan_path}: step {k}: {what}")

    def index(k: int, name: str, v, n: int, lowest: int = 0) -> None:
        if isinstance(v, bool) or not isinstance(v, int) or not lowest <= v < n:
            raise bad(k, f"{name} {v!r} is not one of {lowest}..{n - 1}")

    if not isinstance(plan.get("steps"), list):
        raise ArtifactError(f"{plan_path}: no list of steps")
    for k, step in enumerate(plan["steps"]):
        prim = step.get("primitive") if isinstance(step, dict) else None
        if prim not in _STEP_KEYS:
            raise bad(k, f"primitive {prim!r} is not one of {', '.join(_STEP_KEYS)}")
        keys = _SQUEEZE_KEYS if prim == "tumble" and step.get("mode") == "squeeze" else _STEP_KEYS[prim]
        missing = [key for key in ("X_WO_from", "X_WO_to", *keys) if key not in step]
        if missing:
            raise bad(k, f"the {prim} has no {', '.join(missing)}")
        for key in ("X_WO_from", "X_WO_to"):
            X = step[key]
            if not isinstance(X, dict) or not all(_finite_numbers(X.get(c)) for c in _POSE_KEYS):
                raise bad(k, f"{key} is not a pose of finite x, y, z, qx, qy, qz, qw")
        if prim == "pivot":
            index(k, "vertex", step["vertex"], n_vertices)
        if prim == "tumble" and "pusher_contact" in step:
            index(k, "pusher_contact", step["pusher_contact"], n_contacts)
        if prim == "tumble":
            for v in step["edge"] if isinstance(step["edge"], list) and len(step["edge"]) == 2 else [None]:
                index(k, "edge vertex", v, n_vertices)
        contacts = step.get("contacts", {})
        for arm, c in (contacts.items() if isinstance(contacts, dict) else [("contacts", contacts)]):
            index(k, f"{arm} contact", c, n_contacts, lowest=-1)  # -1: that ball touches nothing


def _finite_numbers(v) -> bool:
    values = v if isinstance(v, list) else [v]
    return bool(values) and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                                for x in values)
