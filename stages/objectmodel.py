"""The analysed object as later stages need it, read back from the analysis artifacts (frame O)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from stages import artifacts, se3
from stages.errors import ArtifactError
from stages.poses import ObjectModel


def load_object_model(analysis_dir: str | Path) -> tuple[ObjectModel, dict]:
    """``(ObjectModel, tables)``: hull, placements and the mesh; ``tables`` holds the raw artifacts
    (``contacts``, ``pairs``, ``placements``, ``hull``, ``summary``) for stages that need more."""
    d = Path(analysis_dir)
    summary = artifacts.read_json(d / "analysis.json", "analysis")
    hull = artifacts.read_table(d / "hull.parquet", "hull")
    pl = artifacts.read_table(d / "placements.parquet", "placements")
    contacts = artifacts.read_table(d / "contacts.parquet", "contacts")
    pairs = artifacts.read_table(d / "pairs.parquet", "pairs")
    if not (d / "object.ply").is_file():
        raise ArtifactError(f"{d / 'object.ply'}: missing (run pivot analyze first)")
    mesh = trimesh.load(d / "object.ply", force="mesh", process=False)
    is_v = hull["kind"] == "vertex"
    V = np.stack([hull["x0"][is_v], hull["y0"][is_v], hull["z0"][is_v]], axis=1)
    model = ObjectModel(
        vertices=V,
        edges=np.stack([hull["v0"][~is_v], hull["v1"][~is_v]], axis=1),
        edge_faces=np.stack([hull["face_a"][~is_v], hull["face_b"][~is_v]], axis=1),
        edge_angle=hull["angle"][~is_v],
        normals=np.stack([pl["nx"], pl["ny"], pl["nz"]], axis=1),
        X_TO=se3.matrix_from_columns(pl.columns),
        support=list(pl["support_vertices"]),
        stable=np.asarray(pl["stable"], dtype=bool),
        com=np.asarray(summary["com"], dtype=float),
        mesh_vertices=np.asarray(mesh.vertices),
        mesh_faces=np.asarray(mesh.faces),
    )
    tables = {"hull": hull, "placements": pl, "contacts": contacts, "pairs": pairs, "summary": summary,
              "mesh": mesh}
    return model, tables
