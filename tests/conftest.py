"""Shared fixtures: tiny meshes from trimesh.creation, written to temporary files."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

REPO = Path(__file__).resolve().parents[1]
PIANO = REPO / "data" / "objects" / "toy_piano.obj"


def l_prism(depth: float = 0.2) -> trimesh.Trimesh:
    """An L-shaped prism: profile (x, z) = a 0.3 x 0.1 foot with a 0.1 x 0.4 upright at x in [0, 0.1].

    Resting on the foot's far end face (x = 0.3, normal +x) the CoM (x ~ 0.12) is 0.18 m
    behind the face: that placement is not SP.
    """
    prof = np.array([(0, 0), (0.3, 0), (0.3, 0.1), (0.1, 0.1), (0.1, 0.4), (0, 0.4)], float)
    cap = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)]  # fan from (0, 0): the L is star-shaped from there
    n = len(prof)
    v = np.array([(x, y, z) for y in (-depth / 2, depth / 2) for x, z in prof])
    faces = [tuple(i for i in f) for f in cap] + [tuple(n + i for i in f[::-1]) for f in cap]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, n + j), (i, n + j, n + i)]
    m = trimesh.Trimesh(v, faces, process=True)
    trimesh.repair.fix_normals(m)
    return m


def uneven_box(size=(0.3, 0.2, 0.25), lift: float = 3e-4) -> trimesh.Trimesh:
    """A box whose faces are split once (each into four triangles) and whose bottom corner at (+x, +y)
    is lifted by ``lift`` m: its hull's bottom face merges triangles 0.1 deg apart (within the
    analysis' 0.5 deg), so its corners lie ~1e-4 m off the face's mean plane, as on organic meshes."""
    m = trimesh.creation.box(size)
    v, f = trimesh.remesh.subdivide(m.vertices, m.faces)
    corner = np.all(np.isclose(v, np.array(size) * [0.5, 0.5, -0.5]), axis=1)
    v[corner, 2] += lift
    return trimesh.Trimesh(v, f, process=True)


@pytest.fixture
def box_path(tmp_path) -> Path:
    p = tmp_path / "box.stl"
    trimesh.creation.box((0.3, 0.2, 0.4)).export(p)
    return p


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def write_scene(tmp_path: Path, name: str = "small", base: str = "default", **changes) -> Path:
    """A copy of the scene ``data/scenes/<base>.json`` with absolute paths and ``changes`` applied
    (dotted keys)."""
    import json

    data = json.loads((REPO / "data" / "scenes" / f"{base}.json").read_text())
    data["object"]["mesh"] = str(REPO / "data" / "objects" / "toy_piano.obj")
    data["robot"]["urdf"] = str(REPO / "data" / "robots" / "sda5f.urdf")
    data["name"] = name
    for key, value in changes.items():
        d = data
        parts = key.split(".")
        for k in parts[:-1]:
            d = d[k]
        d[parts[-1]] = value
    p = tmp_path / f"{name}.json"
    p.write_text(json.dumps(data))
    return p


@pytest.fixture(scope="session")
def small_build(tmp_path_factory):
    """analyze + sample + graph + plan of a small default-like scene (60 poses), built once."""
    from stages import analyze, graph, plan, sample

    tmp = tmp_path_factory.mktemp("small")
    scene = write_scene(tmp, **{"planner.max_poses": 60, "goal.xy": [-0.12, 0.0]})
    b = tmp / "build"
    analyze.run(PIANO, b / "analysis", 3.1, analyze.Params())
    sample.run(scene, b / "analysis", b / "sample", sample.Params())
    graph.run(scene, b / "analysis", b / "sample", b / "graph", graph.Params())
    plan.run(scene, b / "analysis", b / "sample", b / "graph", b / "plan.json", plan.Params())
    return scene, b


@pytest.fixture(scope="session")
def reference_chain(tmp_path_factory):
    """``reference_chain(name)``: the whole chain of ``data/scenes/<name>.json`` with the default
    parameters, run once per session (tests.golden.run_chain) and shared by every test that reads it."""
    from tests.golden import run_chain

    root = tmp_path_factory.mktemp("reference")
    chains = {}

    def get(name: str):
        if name not in chains:
            chains[name] = run_chain(REPO / "data" / "scenes" / f"{name}.json", root)
        return chains[name]

    return get
