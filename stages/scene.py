"""Scene files: load and validate a scene JSON file into frozen dataclasses.

A scene names the object, the table, the robot, the obstacles, the start and goal placements of the
object and the planner parameters (DESIGN.md, Scenes). Units are SI (m, kg, N); angles are in degrees
only where the key ends in ``_deg`` (the dataclasses keep the degrees as written so that a scene
round-trips, and offer the radians as properties). Relative file paths are relative to the folder of
the scene file.

Frames (DESIGN.md, Conventions): world W has its origin at the centre of the table top, z up, x away
from the robot, y to the robot's left. The table top is the rectangle ``|x| <= sx/2, |y| <= sy/2`` at
z = 0.

Schema (keys marked * are required; the others take the default shown)::

    name            str, default the scene file's stem; letters, digits, "_", "-", "." (it names the
                    build folder)
    object*         the object to move
      mesh*         str, path of the object mesh (OBJ/STL/PLY/OFF/GLB) in its own frame O, metres
      mass*         number > 0, kg
      friction      number >= 0, Coulomb coefficient object/table and object/ball, default 0.5
      scale         number > 0, factor applied to the mesh coordinates, default 1.0
    table*
      size*         [sx, sy], numbers > 0, m: extent of the top along W x and W y
      height*       number > 0, m: the top above the floor (it places the table, nothing else)
      friction      number >= 0, default 0.5
    robot*
      urdf*         str, path of the robot URDF
      base_xyz*     [x, y, z], m: origin of the robot base frame B in W. The base sits on the floor,
                    so z is normally -table.height.
      base_yaw_deg  number, deg: rotation of B about W z, default 0 (B x along W x)
      eef_links     [left, right], two distinct link names: the centres of the ball end-effectors
                    E1 (left arm, as seen from the robot) and E2, default ["left_ball", "right_ball"]
      ball_radius   number > 0, m, default 0.02
      max_eef_force number > 0, N: bound on each end-effector force, default 50.0
    obstacles       list, default []. Each item is one of
      {"type": "box", "size"*: [sx, sy, sz] > 0, "xyz"*: [x, y, z], "yaw_deg": 0}
      {"type": "cylinder", "radius"*: > 0, "height"*: > 0, "xyz"*: [x, y, z]}   (axis along W z)
      {"type": "mesh", "mesh"*: path, "scale": 1 (> 0), "xyz"*: [x, y, z], "yaw_deg": 0}
                    xyz is the centre of a box or cylinder (as in fcl and URDF: a box standing on the
                    table has z = sz/2) and the origin of a mesh's own frame; yaw turns the obstacle
                    about W z. An obstacle's frame is called Ob.
    start*, goal*   a placement of the object on the table
      down          [dx, dy, dz], nonzero: the direction in frame O that points down onto the table;
                    the placement is the hull face whose outward normal is nearest to it (resolved by
                    the analysis stage, not here)
      placement     int >= 0: a placement id of the analysis, instead of down (give exactly one)
      xy*           [x, y], m: the reference point of the placement (the vertical projection of the
                    centre of mass) in W; it must lie on the table and outside every obstacle's
                    footprint (its vertical projection)
      yaw_deg       number, deg: rotation about W z, default 0
    planner         default: every key at its default
      theta_t_deg   number in (0, 180], deg: pivoting step about a vertex (§5.1), default 15
      tilt_deg      number in (0, 90), deg: how far the object is tilted onto its pivot, default 8
      usp           bool: also plan through unstable placements (§5.1), default true
      weights       {"pivot": 0.1, "regrasp": 0.5, "tumble": 1.0}, numbers >= 0: edge weights of the
                    graph (§5.1); missing keys take these defaults
      seed          int >= 0, default 0
      max_poses     int >= 1: object poses sampled breadth first from the start, default 400; the
                    lattice grown from the goal adds a quarter as many, goal_reach its share, and
                    the joins a few more
      goal_reach    number in [0, 10]: then grow the lattice on toward the goal by weighted A*, this
                    fraction of max_poses more (``stages.poses``), default 0.5: it reaches goals the
                    breadth-first lattice does not; 0 keeps §5.1's breadth-first lattice alone

Any problem raises :class:`~stages.errors.InputError` with one line naming the file and the key path,
e.g. ``scenes/x.json: object.mass: must be > 0 (got -1)``; invalid JSON names the line and column.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from stages import se3
from stages.errors import InputError

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: A ``down`` direction shorter than this is no direction.
_MIN_DOWN_NORM = 1e-9


@dataclass(frozen=True)
class ObjectSpec:
    """The manipulated object. ``mesh`` is the path as written; ``mesh_path`` the resolved file."""

    mesh: str
    mass: float
    friction: float = 0.5
    scale: float = 1.0
    mesh_path: Path = field(default=Path(), compare=False, repr=False)


@dataclass(frozen=True)
class TableSpec:
    """The table: top of ``size`` (sx, sy) m centred on W's origin at z = 0, ``height`` m above the floor."""

    size: tuple[float, float]
    height: float
    friction: float = 0.5


@dataclass(frozen=True)
class RobotSpec:
    """The dual-arm robot: URDF, base pose in W, the two ball links (left, right) and force bound."""

    urdf: str
    base_xyz: tuple[float, float, float]
    base_yaw_deg: float = 0.0
    eef_links: tuple[str, str] = ("left_ball", "right_ball")
    ball_radius: float = 0.02
    max_eef_force: float = 50.0
    urdf_path: Path = field(default=Path(), compare=False, repr=False)

    @property
    def base_yaw(self) -> float:
        """Base yaw about W z, rad."""
        return math.radians(self.base_yaw_deg)


@dataclass(frozen=True)
class Obstacle:
    """One obstacle as written in the scene; the fields of the other types are None.

    ``vertices``/``faces`` hold a mesh obstacle's triangles in its frame Ob, scaled (m), read once at
    load time so that later stages need no file access.
    """

    type: str
    xyz: tuple[float, float, float]
    yaw_deg: float = 0.0
    size: tuple[float, float, float] | None = None
    radius: float | None = None
    height: float | None = None
    mesh: str | None = None
    scale: float | None = None
    mesh_path: Path | None = field(default=None, compare=False, repr=False)
    vertices: np.ndarray | None = field(default=None, compare=False, repr=False)
    faces: np.ndarray | None = field(default=None, compare=False, repr=False)

    @property
    def X_WOb(self) -> np.ndarray:
        """Pose ``(4, 4)`` of the obstacle frame Ob in W."""
        return se3.make_transform(se3.rot_z(math.radians(self.yaw_deg)), np.asarray(self.xyz))


@dataclass(frozen=True)
class PlacementSpec:
    """A start or goal placement: ``down`` (direction in O) or ``placement`` (id), and its xy and yaw."""

    xy: tuple[float, float]
    yaw_deg: float = 0.0
    down: tuple[float, float, float] | None = None
    placement: int | None = None

    @property
    def yaw(self) -> float:
        """Yaw about W z, rad."""
        return math.radians(self.yaw_deg)

    @property
    def down_unit(self) -> np.ndarray | None:
        """``down`` normalised, ``(3,)``, or None when the placement is given by id."""
        if self.down is None:
            return None
        d = np.asarray(self.down, dtype=float)
        return d / np.linalg.norm(d)


@dataclass(frozen=True)
class EdgeWeights:
    """Graph edge weights per primitive (§5.1)."""

    pivot: float = 0.1
    regrasp: float = 0.5
    tumble: float = 1.0


@dataclass(frozen=True)
class PlannerSpec:
    """Planner parameters of the scene (see the module docstring for their meaning)."""

    theta_t_deg: float = 15.0
    tilt_deg: float = 8.0
    usp: bool = True
    weights: EdgeWeights = EdgeWeights()
    seed: int = 0
    max_poses: int = 400
    goal_reach: float = 0.5

    @property
    def theta_t(self) -> float:
        """Pivoting step, rad."""
        return math.radians(self.theta_t_deg)

    @property
    def tilt(self) -> float:
        """Tilt angle, rad."""
        return math.radians(self.tilt_deg)


@dataclass(frozen=True, eq=False)
class ObstacleGeometry:
    """One collision body in W as plain data, from which fcl (or PyBullet) shapes are built.

    The shape is centred on its own frame Ob, whose pose in W is ``X_WOb (4, 4)``:

    - ``kind == "box"``: ``size`` full extents (m) along Ob x, y, z, as ``fcl.Box(*size)``;
    - ``kind == "cylinder"``: ``radius``, ``height`` (m), axis Ob z, as ``fcl.Cylinder(radius, height)``;
    - ``kind == "mesh"``: ``vertices (n, 3)`` float m in Ob and ``faces (m, 3)`` int, as a
      ``fcl.BVHModel``.

    ``name`` is the key path in the scene (``"obstacles[2]"``) or ``"table"``, for reason codes.
    """

    name: str
    kind: str
    X_WOb: np.ndarray
    size: tuple[float, float, float] | None = None
    radius: float | None = None
    height: float | None = None
    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None


@dataclass(frozen=True)
class Scene:
    """A validated scene. Equality compares the content as written (``to_dict``), not resolved paths."""

    name: str
    object: ObjectSpec
    table: TableSpec
    robot: RobotSpec
    start: PlacementSpec
    goal: PlacementSpec
    obstacles: tuple[Obstacle, ...] = ()
    planner: PlannerSpec = PlannerSpec()
    path: Path = field(default=Path(), compare=False, repr=False)

    def base_transform(self) -> np.ndarray:
        """Pose ``X_WB (4, 4)`` of the robot base frame B in W."""
        R = se3.rot_z(self.robot.base_yaw)
        return se3.make_transform(R, np.asarray(self.robot.base_xyz, dtype=float))

    def obstacle_poses(self) -> np.ndarray:
        """Poses ``X_WOb (n_obstacles, 4, 4)`` of the obstacles, in scene order."""
        if not self.obstacles:
            return np.zeros((0, 4, 4))
        return np.stack([ob.X_WOb for ob in self.obstacles])

    def obstacle_geometries(self) -> tuple[ObstacleGeometry, ...]:
        """The obstacles as collision bodies, in scene order (the table is :meth:`table_geometry`)."""
        out = []
        for i, ob in enumerate(self.obstacles):
            out.append(ObstacleGeometry(
                name=f"obstacles[{i}]", kind=ob.type, X_WOb=ob.X_WOb, size=ob.size, radius=ob.radius,
                height=ob.height, vertices=ob.vertices, faces=ob.faces,
            ))
        return tuple(out)

    def table_geometry(self) -> ObstacleGeometry:
        """The table as a box from the floor to the top (z = 0), so that arms cannot pass under it."""
        sx, sy = self.table.size
        h = self.table.height
        X_WT = se3.make_transform(np.eye(3), np.array([0.0, 0.0, -h / 2]))
        return ObstacleGeometry(name="table", kind="box", X_WOb=X_WT, size=(sx, sy, h))

    def on_table(self, p_W: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether points ``p_W (..., 2 or 3)`` (m, only x and y used) lie on the top, ``margin`` inside.

        Returns ``(...)`` bool.
        """
        p_W = np.asarray(p_W, dtype=float)
        half = np.asarray(self.table.size) / 2 - margin
        return np.all(np.abs(p_W[..., :2]) <= half, axis=-1)

    def to_dict(self) -> dict[str, Any]:
        """The canonical JSON-able form: every key present, defaults filled, paths as written."""
        ob, ta, ro, pl = self.object, self.table, self.robot, self.planner
        return {
            "name": self.name,
            "object": {"mesh": ob.mesh, "mass": ob.mass, "friction": ob.friction, "scale": ob.scale},
            "table": {"size": list(ta.size), "height": ta.height, "friction": ta.friction},
            "robot": {
                "urdf": ro.urdf, "base_xyz": list(ro.base_xyz), "base_yaw_deg": ro.base_yaw_deg,
                "eef_links": list(ro.eef_links), "ball_radius": ro.ball_radius,
                "max_eef_force": ro.max_eef_force,
            },
            "obstacles": [_obstacle_to_dict(o) for o in self.obstacles],
            "start": _placement_to_dict(self.start),
            "goal": _placement_to_dict(self.goal),
            "planner": {
                "theta_t_deg": pl.theta_t_deg, "tilt_deg": pl.tilt_deg, "usp": pl.usp,
                "weights": {"pivot": pl.weights.pivot, "regrasp": pl.weights.regrasp,
                            "tumble": pl.weights.tumble},
                "seed": pl.seed, "max_poses": pl.max_poses, "goal_reach": pl.goal_reach,
            },
        }


def _obstacle_to_dict(ob: Obstacle) -> dict[str, Any]:
    if ob.type == "box":
        return {"type": "box", "size": list(ob.size), "xyz": list(ob.xyz), "yaw_deg": ob.yaw_deg}
    if ob.type == "cylinder":
        return {"type": "cylinder", "radius": ob.radius, "height": ob.height, "xyz": list(ob.xyz)}
    return {"type": "mesh", "mesh": ob.mesh, "scale": ob.scale, "xyz": list(ob.xyz), "yaw_deg": ob.yaw_deg}


def _placement_to_dict(p: PlacementSpec) -> dict[str, Any]:
    d: dict[str, Any] = {"down": list(p.down)} if p.down is not None else {"placement": p.placement}
    d.update({"xy": list(p.xy), "yaw_deg": p.yaw_deg})
    return d


def load_scene(path: str | Path) -> Scene:
    """Read and validate the scene file at ``path``; raise InputError (one line) on any problem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise InputError(f"{path}: cannot read scene file: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: scene file is not UTF-8 text") from None
    try:
        data = json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as e:
        raise InputError(f"{path}:{e.lineno}:{e.colno}: invalid JSON: {e.msg}") from None
    except _DuplicateKey as e:
        raise InputError(f"{path}: duplicate key {json.dumps(e.args[0])}") from None
    return scene_from_dict(data, path)


class _DuplicateKey(Exception):
    pass


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise _DuplicateKey(k)
        out[k] = v
    return out


def scene_from_dict(data: Any, path: str | Path) -> Scene:
    """Validate parsed scene ``data``; ``path`` is the scene file (names it in errors, anchors paths)."""
    return _Reader(Path(path)).scene(data)


def _show(value: Any) -> str:
    """A value for an error message: JSON spelling, one line, at most 60 characters."""
    try:
        s = json.dumps(value)
    except (TypeError, ValueError):
        s = repr(value)
    return s if len(s) <= 60 else s[:57] + "..."


def _join(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


class _Reader:
    """Validation of one scene file; every failure names the file and the key path."""

    def __init__(self, file: Path):
        self.file = file
        self.root = file.parent

    def fail(self, path: str, message: str) -> NoReturn:
        raise InputError(f"{self.file}: {path or '(top level)'}: {message}")

    # ---- primitive checks -------------------------------------------------------------------------

    def keys(self, d: Any, path: str, required: tuple[str, ...], optional: tuple[str, ...]) -> dict:
        if not isinstance(d, dict):
            self.fail(path, f"must be a JSON object (got {_show(d)})")
        allowed = required + optional
        for k in d:
            if k not in allowed:
                self.fail(_join(path, k), f"unknown key (expected one of {', '.join(allowed)})")
        for k in required:
            if k not in d:
                self.fail(_join(path, k), "missing required key")
        return d

    def number(self, v: Any, path: str, *, gt: float | None = None, ge: float | None = None,
               lt: float | None = None, le: float | None = None) -> float:
        if isinstance(v, bool) or not isinstance(v, int | float):
            self.fail(path, f"must be a number (got {_show(v)})")
        x = float(v)
        if not math.isfinite(x):
            self.fail(path, f"must be finite (got {_show(v)})")
        for bound, ok, word in ((gt, lambda b: x > b, ">"), (ge, lambda b: x >= b, ">="),
                                (lt, lambda b: x < b, "<"), (le, lambda b: x <= b, "<=")):
            if bound is not None and not ok(bound):
                self.fail(path, f"must be {word} {bound:g} (got {_show(v)})")
        return x

    def integer(self, v: Any, path: str, *, ge: int) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(path, f"must be an integer (got {_show(v)})")
        if v < ge:
            self.fail(path, f"must be >= {ge} (got {_show(v)})")
        return int(v)

    def boolean(self, v: Any, path: str) -> bool:
        if not isinstance(v, bool):
            self.fail(path, f"must be true or false (got {_show(v)})")
        return v

    def string(self, v: Any, path: str) -> str:
        if not isinstance(v, str) or not v:
            self.fail(path, f"must be a non-empty string (got {_show(v)})")
        return v

    def vector(self, v: Any, path: str, n: int, **bounds: float) -> tuple[float, ...]:
        if not isinstance(v, list) or len(v) != n:
            self.fail(path, f"must be a list of {n} numbers (got {_show(v)})")
        return tuple(self.number(x, _join(path, i), **bounds) for i, x in enumerate(v))

    def file_path(self, v: Any, path: str) -> tuple[str, Path]:
        s = self.string(v, path)
        resolved = (self.root / s).resolve()
        if not resolved.is_file():
            self.fail(path, f"file not found: {resolved}")
        return s, resolved

    # ---- sections ---------------------------------------------------------------------------------

    def scene(self, data: Any) -> Scene:
        d = self.keys(data, "", ("object", "table", "robot", "start", "goal"),
                      ("name", "obstacles", "planner"))
        name = self.file.stem
        if "name" in d:
            name = self.string(d["name"], "name")
            if not _NAME.match(name):
                self.fail("name", f"must be letters, digits, '_', '-' or '.' (got {_show(name)})")
        # Checked in the order of the schema, so the first problem reported is the first in the file.
        obj = self.object(d["object"])
        table = self.table(d["table"])
        robot = self.robot(d["robot"])
        obstacles = self.obstacles(d.get("obstacles", []))
        start = self.placement(d["start"], "start", table, obstacles)
        goal = self.placement(d["goal"], "goal", table, obstacles)
        return Scene(
            name=name, object=obj, table=table, robot=robot, start=start, goal=goal, obstacles=obstacles,
            planner=self.planner(d.get("planner", {})), path=self.file.resolve(),
        )

    def object(self, v: Any) -> ObjectSpec:
        p = "object"
        d = self.keys(v, p, ("mesh", "mass"), ("friction", "scale"))
        mesh, mesh_path = self.file_path(d["mesh"], _join(p, "mesh"))
        return ObjectSpec(
            mesh=mesh, mesh_path=mesh_path, mass=self.number(d["mass"], _join(p, "mass"), gt=0),
            friction=self.number(d.get("friction", 0.5), _join(p, "friction"), ge=0),
            scale=self.number(d.get("scale", 1.0), _join(p, "scale"), gt=0),
        )

    def table(self, v: Any) -> TableSpec:
        p = "table"
        d = self.keys(v, p, ("size", "height"), ("friction",))
        return TableSpec(
            size=self.vector(d["size"], _join(p, "size"), 2, gt=0),
            height=self.number(d["height"], _join(p, "height"), gt=0),
            friction=self.number(d.get("friction", 0.5), _join(p, "friction"), ge=0),
        )

    def robot(self, v: Any) -> RobotSpec:
        p = "robot"
        d = self.keys(v, p, ("urdf", "base_xyz"),
                      ("base_yaw_deg", "eef_links", "ball_radius", "max_eef_force"))
        urdf, urdf_path = self.file_path(d["urdf"], _join(p, "urdf"))
        links = d.get("eef_links", ["left_ball", "right_ball"])
        lp = _join(p, "eef_links")
        if not isinstance(links, list) or len(links) != 2:
            self.fail(lp, f"must be a list of 2 link names [left, right] (got {_show(links)})")
        links = tuple(self.string(x, _join(lp, i)) for i, x in enumerate(links))
        if links[0] == links[1]:
            self.fail(lp, f"the two links must differ (got {_show(list(links))})")
        return RobotSpec(
            urdf=urdf, urdf_path=urdf_path, base_xyz=self.vector(d["base_xyz"], _join(p, "base_xyz"), 3),
            base_yaw_deg=self.number(d.get("base_yaw_deg", 0.0), _join(p, "base_yaw_deg")),
            eef_links=links,
            ball_radius=self.number(d.get("ball_radius", 0.02), _join(p, "ball_radius"), gt=0),
            max_eef_force=self.number(d.get("max_eef_force", 50.0), _join(p, "max_eef_force"), gt=0),
        )

    def obstacles(self, v: Any) -> tuple[Obstacle, ...]:
        if not isinstance(v, list):
            self.fail("obstacles", f"must be a list (got {_show(v)})")
        return tuple(self.obstacle(item, f"obstacles[{i}]") for i, item in enumerate(v))

    def obstacle(self, v: Any, p: str) -> Obstacle:
        if not isinstance(v, dict):
            self.fail(p, f"must be a JSON object (got {_show(v)})")
        kind = v.get("type")
        if kind not in ("box", "cylinder", "mesh"):
            self.fail(_join(p, "type"), f"must be \"box\", \"cylinder\" or \"mesh\" (got {_show(kind)})")
        if kind == "box":
            d = self.keys(v, p, ("type", "size", "xyz"), ("yaw_deg",))
            return Obstacle(
                type=kind, xyz=self.vector(d["xyz"], _join(p, "xyz"), 3),
                yaw_deg=self.number(d.get("yaw_deg", 0.0), _join(p, "yaw_deg")),
                size=self.vector(d["size"], _join(p, "size"), 3, gt=0),
            )
        if kind == "cylinder":
            d = self.keys(v, p, ("type", "radius", "height", "xyz"), ())
            return Obstacle(
                type=kind, xyz=self.vector(d["xyz"], _join(p, "xyz"), 3),
                radius=self.number(d["radius"], _join(p, "radius"), gt=0),
                height=self.number(d["height"], _join(p, "height"), gt=0),
            )
        d = self.keys(v, p, ("type", "mesh", "xyz"), ("scale", "yaw_deg"))
        mesh, mesh_path = self.file_path(d["mesh"], _join(p, "mesh"))
        scale = self.number(d.get("scale", 1.0), _join(p, "scale"), gt=0)
        vertices, faces = self.read_mesh(mesh_path, _join(p, "mesh"))
        return Obstacle(
            type=kind, xyz=self.vector(d["xyz"], _join(p, "xyz"), 3),
            yaw_deg=self.number(d.get("yaw_deg", 0.0), _join(p, "yaw_deg")),
            mesh=mesh, scale=scale, mesh_path=mesh_path, vertices=_frozen(vertices * scale),
            faces=_frozen(faces),
        )

    def read_mesh(self, path: Path, key: str) -> tuple[np.ndarray, np.ndarray]:
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as e:  # trimesh raises many different types for unreadable files
            self.fail(key, f"cannot read mesh {path}: {type(e).__name__}: {e}".replace("\n", " "))
        if len(mesh.faces) == 0:
            self.fail(key, f"mesh {path} has no triangles")
        v = np.asarray(mesh.vertices, dtype=float)
        if not np.all(np.isfinite(v)):
            self.fail(key, f"mesh {path} has non-finite vertices")
        return v, np.asarray(mesh.faces, dtype=np.int64)

    def placement(self, v: Any, p: str, table: TableSpec, obstacles: tuple[Obstacle, ...]) -> PlacementSpec:
        d = self.keys(v, p, ("xy",), ("down", "placement", "yaw_deg"))
        if ("down" in d) == ("placement" in d):
            self.fail(p, "give exactly one of \"down\" and \"placement\"")
        down = placement = None
        if "down" in d:
            down = self.vector(d["down"], _join(p, "down"), 3)
            if math.hypot(*down) < _MIN_DOWN_NORM:
                self.fail(_join(p, "down"), f"must be a nonzero direction (got {_show(d['down'])})")
        else:
            placement = self.integer(d["placement"], _join(p, "placement"), ge=0)
        xp = _join(p, "xy")
        xy = self.vector(d["xy"], xp, 2)
        sx, sy = table.size
        if abs(xy[0]) > sx / 2 or abs(xy[1]) > sy / 2:
            self.fail(xp, f"off the table |x| <= {sx / 2:g}, |y| <= {sy / 2:g} (got {_show(d['xy'])})")
        for i, ob in enumerate(obstacles):
            if _footprint_contains(ob, np.asarray(xy)):
                self.fail(xp, f"inside the footprint of obstacles[{i}] ({ob.type}) (got {_show(d['xy'])})")
        return PlacementSpec(
            xy=xy, yaw_deg=self.number(d.get("yaw_deg", 0.0), _join(p, "yaw_deg")), down=down,
            placement=placement,
        )

    def planner(self, v: Any) -> PlannerSpec:
        p = "planner"
        d = self.keys(v, p, (), ("theta_t_deg", "tilt_deg", "usp", "weights", "seed", "max_poses", "goal_reach"))
        wp = _join(p, "weights")
        w = self.keys(d.get("weights", {}), wp, (), ("pivot", "regrasp", "tumble"))
        default = EdgeWeights()
        weights = EdgeWeights(**{
            k: self.number(w.get(k, getattr(default, k)), _join(wp, k), ge=0)
            for k in ("pivot", "regrasp", "tumble")
        })
        return PlannerSpec(
            theta_t_deg=self.number(d.get("theta_t_deg", 15.0), _join(p, "theta_t_deg"), gt=0, le=180),
            tilt_deg=self.number(d.get("tilt_deg", 8.0), _join(p, "tilt_deg"), gt=0, lt=90),
            usp=self.boolean(d.get("usp", True), _join(p, "usp")),
            weights=weights,
            seed=self.integer(d.get("seed", 0), _join(p, "seed"), ge=0),
            max_poses=self.integer(d.get("max_poses", 400), _join(p, "max_poses"), ge=1),
            goal_reach=self.number(d.get("goal_reach", PlannerSpec.goal_reach), _join(p, "goal_reach"), ge=0, le=10),
        )


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def _footprint_contains(ob: Obstacle, xy_W: np.ndarray) -> np.ndarray:
    """Whether points ``xy_W (..., 2)`` (m) lie in the obstacle's vertical projection (closed), ``(...)``.

    Mesh obstacles use the convex hull of their projected vertices (a superset of the true footprint).
    """
    X_ObW = se3.invert(ob.X_WOb)
    p = np.concatenate([xy_W, np.zeros(xy_W.shape[:-1] + (1,))], axis=-1)
    q = se3.transform_points(X_ObW, p)[..., :2]  # points in Ob (the yaw is about z, so z is irrelevant)
    if ob.type == "box":
        return np.all(np.abs(q) <= np.asarray(ob.size[:2]) / 2, axis=-1)
    if ob.type == "cylinder":
        return np.linalg.norm(q, axis=-1) <= ob.radius
    try:
        hull = ConvexHull(ob.vertices[:, :2])
    except QhullError:
        return np.zeros(q.shape[:-1], dtype=bool)  # a flat projection has no area to stand in
    return np.all(q @ hull.equations[:, :2].T + hull.equations[:, 2] <= 0, axis=-1)
