"""Provenance: a stage refuses upstream artifacts made from other inputs than the ones it is given.

Every artifact records the sha256 of its input files (``meta["inputs"]``, see ``stages.artifacts``).
Before a stage computes, it checks the chain it reads back to the scene it is given now: the
analysis was made from the scene's mesh, scale and mass; the samples from this scene and this
analysis; the graph from these samples; the plan and the trajectories from this scene and this
analysis. A stale or foreign upstream is bad input (``ArtifactError``: one line naming both files).
"""

from __future__ import annotations

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
