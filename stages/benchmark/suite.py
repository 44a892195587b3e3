"""``pivot benchmark make``: a seeded suite of scenes over general objects and goals (issue 13).

For each object family of :mod:`stages.objects`, ``goals`` cases cycle through three goal kinds:

- ``translate``: the same face down and the same heading, moved 0.10–0.45 m in any direction;
- ``rotate``: the same face down, turned 30–180° about the vertical, moved up to 0.45 m;
- ``face``: another stable placement down (a tumble is needed), any heading, moved up to 0.45 m;
  an object with no other placement stable by ``face_margin`` gets a ``rotate`` goal instead.

The start rests on the object's upright placement (the face whose normal is nearest O's -z) at a
random heading. Start and goal lie on the default scene's table (``data/scenes/default.json``: its
table, robot and planner settings) with their whole footprint (the hull's plan view) at least
``edge_margin`` inside its edges and ``reach_margin`` in front of the robot's trunk, so that every
case is a task a person would set this robot. Positions are drawn uniformly from the placements'
admissible boxes (closed form for a given heading), by rejection for the translation's length.

The reachability label is a cheap necessary condition: both the start and the goal pose have at
least one grasp that passes the sample stage's whole grasp refinement (§4.2–4.3: IK for both arms,
collision-free, stable; :func:`stages.sample.refine_grasps`). A case that fails it is labelled
``unreachable`` with the reason and stays in the suite; the report counts it apart.
"""

from __future__ import annotations

import json
import logging
import shutil
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from stages import artifacts, objects, se3
from stages import sample as sample_stage
from stages.analyze import Params as AnalyzeParams
from stages.analyze import run as analyze_run
from stages.errors import InputError
from stages.objectmodel import load_object_model
from stages.poses import PoseSet
from stages.robot import IKParams, load_robot
from stages.scene import load_scene

log = logging.getLogger("pivot.benchmark")

DATA = Path(__file__).resolve().parents[2] / "data"
KINDS = ("translate", "rotate", "face")


@dataclass(frozen=True)
class SuiteParams:
    """How the suite is drawn (m, deg)."""

    objects: tuple[str, ...] = field(default_factory=lambda: tuple(objects.FAMILIES))
    goals: int = 6
    seed: int = 0
    #: Translation length of translate goals, and the most of the other kinds (m).
    translation: tuple[float, float] = (0.10, 0.45)
    #: Heading change of rotate goals (deg, either sign).
    rotation_deg: tuple[float, float] = (30.0, 180.0)
    #: The whole footprint at least this far inside the table's edges (m) ...
    edge_margin: float = 0.02
    #: ... and this far in front of the robot's trunk boxes (m).
    reach_margin: float = 0.03
    #: A face goal rests on a stable placement whose CoM lies this far inside its support (m).
    face_margin: float = 0.02
    #: Draws of a heading (and of a position for the translation) before a case gives up.
    tries: int = 400
    template: str = str(DATA / "scenes" / "default.json")


@dataclass(frozen=True)
class Placement:
    """A drawn placement: placement id, CoM projection ``xy`` (m, W) and heading (deg)."""

    g: int
    xy: tuple[float, float]
    yaw_deg: float


def footprint_bounds(model, g: int, yaw: float) -> np.ndarray:
    """``(4,)`` min x, max x, min y, max y (m) of placement ``g``'s hull in plan view, turned by ``yaw``
    (rad) about the vertical through the CoM projection (the scene's ``xy``), relative to that point."""
    p = se3.transform_points(model.X_TO[g], model.vertices)[:, :2]
    c, s = np.cos(yaw), np.sin(yaw)
    q = p @ np.array([[c, s], [-s, c]])
    return np.array([q[:, 0].min(), q[:, 0].max(), q[:, 1].min(), q[:, 1].max()])


def admissible_box(bounds: np.ndarray, area: np.ndarray) -> np.ndarray | None:
    """``(4,)`` x lo, x hi, y lo, y hi of the CoM projections whose footprint (``footprint_bounds``)
    lies in ``area`` (x lo, x hi, y lo, y hi, m); None when the footprint does not fit."""
    box = np.array([area[0] - bounds[0], area[1] - bounds[1], area[2] - bounds[2], area[3] - bounds[3]])
    return None if box[0] > box[1] or box[2] > box[3] else box


def draw_case(rng: np.random.Generator, model, kind: str, g0: int, faces: list[int], area: np.ndarray,
              prm: SuiteParams) -> tuple[Placement, Placement] | None:
    """Draw a (start, goal) pair of ``kind`` by rejection (module docstring); None after ``prm.tries``."""
    lo, hi = prm.translation
    for _ in range(prm.tries):
        yaw0 = rng.uniform(-180.0, 180.0)
        box0 = admissible_box(footprint_bounds(model, g0, np.radians(yaw0)), area)
        if box0 is None:
            continue
        xy0 = rng.uniform(box0[[0, 2]], box0[[1, 3]])
        g1, yaw1, dmin = g0, yaw0, 0.0
        if kind == "translate":
            dmin = lo
        elif kind == "rotate":
            yaw1 = yaw0 + rng.choice([-1.0, 1.0]) * rng.uniform(*prm.rotation_deg)
        else:
            g1, yaw1 = int(rng.choice(faces)), rng.uniform(-180.0, 180.0)
        box1 = admissible_box(footprint_bounds(model, g1, np.radians(yaw1)), area)
        if box1 is None:
            continue
        for _ in range(prm.tries // 10):
            xy1 = rng.uniform(box1[[0, 2]], box1[[1, 3]])
            if dmin <= np.linalg.norm(xy1 - xy0) <= hi:
                wrap = (yaw1 + 180.0) % 360.0 - 180.0
                return (Placement(g0, (round(xy0[0], 4), round(xy0[1], 4)), round(yaw0, 2)),
                        Placement(g1, (round(xy1[0], 4), round(xy1[1], 4)), round(wrap, 2)))
    return None


def reach_area(template: dict, robot, prm: SuiteParams) -> np.ndarray:
    """``(4,)`` x lo, x hi, y lo, y hi (m, W) where a footprint may lie: the table less ``edge_margin``,
    in front of the trunk boxes (their largest x over the table) by ``reach_margin``."""
    sx, sy = template["table"]["size"]
    st = robot.static
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=float)
    trunk_x = max((se3.transform_points(X, corners * h)[:, 0].max() for X, h in zip(st.box_X_W, st.box_half,
                                                                                      strict=True)),
                  default=-np.inf)
    x_lo = max(-sx / 2 + prm.edge_margin, trunk_x + prm.reach_margin)
    return np.array([x_lo, sx / 2 - prm.edge_margin, -sy / 2 + prm.edge_margin, sy / 2 - prm.edge_margin])


def upright_placement(model) -> int:
    """The placement whose outward normal is nearest O's -z (the family's natural upright)."""
    return int(np.argmax(model.normals @ np.array([0.0, 0.0, -1.0])))


def other_faces(model, tables: dict, g0: int, margin: float) -> list[int]:
    """Stable placements other than ``g0`` whose CoM lies at least ``margin`` (m) inside their support."""
    pl = tables["placements"]
    ok = np.asarray(pl["stable"], bool) & (np.asarray(pl["margin"], float) >= margin)
    return [int(g) for g in np.flatnonzero(ok) if g != g0]


def scene_dict(template: dict, name: str, family, start: Placement, goal: Placement, model) -> dict:
    """A scene (``stages.scene`` schema) from the template with this object, start and goal."""
    def placement(p: Placement) -> dict:
        down = [round(float(v), 6) for v in model.normals[p.g]]
        return {"down": down, "xy": list(p.xy), "yaw_deg": p.yaw_deg}

    return {**template, "name": name,
            "object": {"mesh": f"../objects/{family.name}.obj", "mass": family.mass,
                       "friction": family.friction, "scale": 1.0},
            "robot": {**template["robot"], "urdf": "../robots/" + Path(template["robot"]["urdf"]).name},
            "start": placement(start), "goal": placement(goal)}


def grasp_counts(scene_path: Path, analysis_dir: Path, robot, collide, model, tables: dict) -> tuple[int, int]:
    """Grasps that pass the sample stage's refinement at the scene's start and goal poses (the label)."""
    scene = load_scene(scene_path)
    X0, g0 = sample_stage.placement_pose(scene.start, model, "start")
    X1, g1 = sample_stage.placement_pose(scene.goal, model, "goal")
    n = 2
    ps = PoseSet(X_WO=np.stack([X0, X1]), placement=np.array([g0, g1]), support=np.array(["SP", "SP"]),
                 status=np.array(["ok", "ok"]), parent=np.full(n, -1), primitive=np.array(["start", "goal"]),
                 vertex=np.full(n, -1), edge=np.full((n, 2), -1), angle=np.zeros(n),
                 margin=np.asarray(tables["placements"]["margin"], float)[[g0, g1]],
                 links=np.zeros((0, 2), np.int64), link_primitive=np.zeros(0, str), link_vertex=np.zeros(0, np.int64),
                 link_edge=np.zeros((0, 2), np.int64), link_angle=np.zeros(0))
    rng = np.random.default_rng(scene.planner.seed)
    grasps, _, _ = sample_stage.refine_grasps(scene, model, tables, ps, robot, collide, sample_stage.Params(), rng)
    pose = np.asarray(grasps["pose_id"])
    return int((pose == 0).sum()), int((pose == 1).sum())


def label(n_start: int, n_goal: int) -> tuple[bool, str]:
    """``(reachable, reason)`` from the grasp counts at the start and the goal."""
    if n_start == 0:
        return False, "no_grasp_at_start"
    if n_goal == 0:
        return False, "no_grasp_at_goal"
    return True, ""


def prepare_object(out: Path, family) -> tuple[Path, Path]:
    """Write the family's mesh to ``out/objects`` and analyse it into ``out/analysis/<name>``."""
    mesh = objects.write_mesh(family.name, out / "objects" / f"{family.name}.obj")
    adir = out / "analysis" / family.name
    analyze_run(mesh, adir, family.mass, AnalyzeParams(), producer=f"benchmark make {family.name}")
    return mesh, adir


def object_cases(out: Path, template: dict, family, prm: SuiteParams) -> list[dict]:
    """Draw, write and label the ``prm.goals`` cases of one object family (its own random stream, so a
    family's cases do not depend on the other objects asked for)."""
    _, adir = prepare_object(out, family)
    model, tables = load_object_model(adir)
    scene0 = load_scene(prm.template)
    robot = load_robot(scene0.robot.urdf_path, scene0.base_transform(), tuple(scene0.robot.eef_links),
                       ik_params=IKParams(min_chunk=1024))
    collide = sample_stage.make_scene_collision_fn(scene0, robot, tables["mesh"],
                                                   clearance=(sample_stage.Params().arm_clearance,
                                                              sample_stage.Params().stick_clearance))
    robot.prepare_ik()
    area = reach_area(template, robot, prm)
    g0 = upright_placement(model)
    faces = other_faces(model, tables, g0, prm.face_margin)
    rng = np.random.default_rng([prm.seed, zlib.crc32(family.name.encode())])
    cases = []
    for k in range(prm.goals):
        # An object with no other face stable by face_margin (the duck) gets a rotate goal instead.
        kind = KINDS[k % len(KINDS)] if faces or KINDS[k % len(KINDS)] != "face" else "rotate"
        drawn = draw_case(rng, model, kind, g0, faces, area, prm)
        case = {"case": f"{family.name}-{k:02d}-{kind}", "object": family.name, "kind": kind, "goal_index": k,
                "scene": f"scenes/{family.name}-{k:02d}-{kind}.json", "reachable": False, "reason": "",
                "grasps_start": 0, "grasps_goal": 0, "translation": float("nan"), "rotation_deg": float("nan")}
        if drawn is None:
            case["reason"] = "no_admissible_placement"
            cases.append(case)
            continue
        start, goal = drawn
        path = out / case["scene"]
        write_plain_json(path, scene_dict(template, case["case"], family, start, goal, model))
        n0, n1 = grasp_counts(path, adir, robot, collide, model, tables)
        reachable, why = label(n0, n1)
        dyaw = (goal.yaw_deg - start.yaw_deg + 180.0) % 360.0 - 180.0
        case.update(reachable=reachable, reason=why, grasps_start=n0,
                    grasps_goal=n1, translation=round(float(np.hypot(*np.subtract(goal.xy, start.xy))), 4),
                    rotation_deg=round(float(dyaw), 2), start_placement=start.g, goal_placement=goal.g)
        cases.append(case)
    return cases


def write_plain_json(path: Path, data: dict) -> None:
    """Write ``data`` as indented JSON, atomically (a scene file: no artifact metadata)."""
    with artifacts.atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1) + "\n")


def make_suite(out: str | Path, prm: SuiteParams = SuiteParams()) -> dict:
    """Write the suite into ``out`` (layout in :mod:`stages.benchmark`); returns ``suite.json``'s data.

    Raises ``InputError`` (via :func:`stages.objects.make_mesh`) for an unknown object name.
    """
    out = Path(out)
    unknown = [n for n in prm.objects if n not in objects.FAMILIES]
    if unknown:  # before anything is written
        raise InputError(f"--objects: no object family {unknown[0]!r} (known: {', '.join(objects.FAMILIES)})")
    template = json.loads(Path(prm.template).read_text())
    urdf = (Path(prm.template).parent / template["robot"]["urdf"]).resolve()
    (out / "robots").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(urdf, out / "robots" / urdf.name)
    families = [objects.FAMILIES[name] for name in prm.objects]
    cases = []
    for family in families:
        log.info("benchmark make: %s (%d goals)", family.name, prm.goals)
        cases.extend(object_cases(out, template, family, prm))
    data = {"cases": cases,
            "objects": {f.name: {"mass": f.mass, "size": list(f.size), "why": f.why, "source": f.source}
                        for f in families}}
    params = {**asdict(prm), "template": Path(prm.template).name}
    artifacts.write_json(out / "suite.json", data, artifacts.make_meta("benchmark_suite", params, {}, "benchmark make"))
    return data
