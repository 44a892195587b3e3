"""Scene descriptions for MeshCat's browser viewer: three.js JSON objects, keyframe tracks and the page.

MeshCat's viewer (``meshcat/viewer/dist/main.min.js`` of the ``meshcat`` package, three.js r132 inside)
is driven by commands: ``set_object`` takes an object in the JSON format of ``THREE.ObjectLoader``
(format 4.5), ``set_transform`` a column-major ``(16,)`` matrix, ``set_animation`` clips in the JSON
format of ``THREE.AnimationClip.parse`` (tracks with flat ``times``/``values`` arrays, seconds). This
module builds those dictionaries from numpy arrays (poses ``(4, 4)``, SI units, frame W) and writes
the static page that MeshCat's own ``static_html`` export writes: the viewer script inlined, then the
commands, so that the file needs no network and no server.

Identifiers (uuids) are derived from the node's path and a counter, and floats are rounded to a fixed
number of decimals, so the same scene gives byte-identical pages.
"""

from __future__ import annotations

import importlib.util
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.errors import InputError

#: Decimals kept in the page: 0.1 mm for positions in m, 1e-4 for unit quaternions and directions.
DECIMALS = 4


@dataclass(frozen=True)
class Node:
    """One three.js object: ``kind`` ``Mesh``, ``LineSegments``, ``Line`` or ``Group``; ``geometry`` and
    ``material`` dictionaries (see :func:`box`, :func:`material`); ``X (4, 4)`` its pose in its parent."""

    kind: str
    geometry: dict | None = None
    material: dict | None = None
    X: np.ndarray | None = None
    children: tuple[Node, ...] = ()
    name: str = ""


@dataclass
class Track:
    """A keyframe track of one node: ``prop`` ``position`` (vector), ``quaternion`` (x, y, z, w),
    ``scale`` (vector) or ``visible`` (bool); ``times (T,)`` s, ``values (T, k)``."""

    prop: str
    times: np.ndarray
    values: np.ndarray


@dataclass
class Page:
    """The commands of one page, in order, and the page's own data (``extra``, JSON) for its script."""

    commands: list[dict] = field(default_factory=list)
    animations: list[dict] = field(default_factory=list)
    duration: float = 0.0

    def set_object(self, path: str, node: Node) -> None:
        self.commands.append({"type": "set_object", "path": path, "object": object_json(node, path)})

    def set_transform(self, path: str, X: np.ndarray) -> None:
        self.commands.append({"type": "set_transform", "path": path, "matrix": _matrix(X)})

    def set_property(self, path: str, prop: str, value) -> None:
        self.commands.append({"type": "set_property", "path": path, "property": prop, "value": value})

    def animate(self, path: str, tracks: list[Track]) -> None:
        """Animate the node at ``path`` (its group, so the user's visibility box stays the user's)."""
        out = []
        for tr in tracks:
            kind = {"position": "vector", "scale": "vector", "quaternion": "quaternion", "visible": "bool"}[tr.prop]
            values = np.asarray(tr.values)
            flat = values.astype(bool).ravel().tolist() if kind == "bool" else _floats(values.ravel())
            out.append({"name": f".{tr.prop}", "type": kind, "times": _floats(tr.times, 3), "values": flat})
            self.duration = max(self.duration, float(tr.times[-1]))
        self.animations.append({"path": path, "clip": {"name": "default", "tracks": out}})


def _floats(a: np.ndarray, decimals: int = DECIMALS) -> list[float]:
    r = np.round(np.asarray(a, dtype=float), decimals)
    return (r + 0.0).tolist()  # + 0.0 turns -0.0 into 0.0


def _matrix(X: np.ndarray) -> list[float]:
    X = np.asarray(X, dtype=float)
    if X.shape != (4, 4) or not np.all(np.isfinite(X)):
        raise ValueError(f"a pose must be a finite (4, 4) matrix, got shape {X.shape}")
    return _floats(X.T.ravel(), 6)  # three.js matrices are column-major


def object_json(root: Node, path: str) -> dict:
    """``THREE.ObjectLoader`` JSON (format 4.5) of the tree under ``root``; uuids from ``path``."""
    geometries, materials = [], []

    def lower(node: Node) -> dict:
        i = len(geometries) + len(materials)
        obj = {"uuid": f"{path}#o{i}", "type": node.kind, "name": node.name}
        if node.X is not None:
            obj["matrix"] = _matrix(node.X)
        if node.geometry is not None:
            geometries.append({**node.geometry, "uuid": f"{path}#g{len(geometries)}"})
            obj["geometry"] = geometries[-1]["uuid"]
        if node.material is not None:
            materials.append({**node.material, "uuid": f"{path}#m{len(materials)}"})
            obj["material"] = materials[-1]["uuid"]
        if node.children:
            obj["children"] = [lower(c) for c in node.children]
        return obj

    obj = lower(root)
    return {"metadata": {"version": 4.5, "type": "Object"}, "geometries": geometries, "materials": materials,
            "object": obj}


# -------------------------------------------------------------------------------------------- shapes


def material(rgb, opacity: float = 1.0, kind: str = "MeshLambertMaterial", on_top: bool = False) -> dict:
    """A material of colour ``rgb`` (3 floats in [0, 1]); ``opacity`` below 1 makes it transparent;
    ``on_top`` draws it through whatever stands in front (overlays: forces, supports, paths)."""
    r, g, b = (int(round(255 * float(c))) for c in rgb[:3])
    out = {"type": kind, "color": (r << 16) + (g << 8) + b, "side": 2}
    if opacity < 1.0:
        out.update(transparent=True, opacity=float(opacity), depthWrite=False)
    if on_top:
        out.update(depthTest=False, depthWrite=False, transparent=True)
    return out


def box(size) -> dict:
    """Box geometry of full extents ``size (3,)`` m, centred on its frame."""
    sx, sy, sz = (float(s) for s in size)
    return {"type": "BoxGeometry", "width": sx, "height": sy, "depth": sz}


def sphere(radius: float) -> dict:
    return {"type": "SphereGeometry", "radius": float(radius), "widthSegments": 20, "heightSegments": 12}


def _cylinder_y(radius_top: float, radius_bottom: float, height: float) -> dict:
    return {"type": "CylinderGeometry", "radiusTop": float(radius_top), "radiusBottom": float(radius_bottom),
            "height": float(height), "radialSegments": 20}


#: three.js cylinders and cones run along their y axis; this turns y onto z (URDF, scenes).
Y_TO_Z = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def cylinder(radius: float, length: float, mat: dict, X: np.ndarray | None = None) -> Node:
    """A cylinder along z of its frame (URDF convention), centred on it."""
    X = np.eye(4) if X is None else X
    return Node("Mesh", _cylinder_y(radius, radius, length), mat, X @ Y_TO_Z)


def capsule(a: np.ndarray, b: np.ndarray, radius: float, mat: dict, X: np.ndarray | None = None) -> Node:
    """A capsule: segment ``a -> b`` (m, in the parent frame) swept by a sphere of ``radius`` m."""
    X = np.eye(4) if X is None else X
    a, b = np.asarray(a, float), np.asarray(b, float)
    ends = [Node("Mesh", sphere(radius), mat, X @ translation(p)) for p in (a, b)]
    length = float(np.linalg.norm(b - a))
    if length < 1e-9:
        return Node("Group", children=(ends[0],))
    shaft = Node("Mesh", _cylinder_y(radius, radius, length), mat, X @ _segment_frame(a, b))
    return Node("Group", children=(shaft, *ends))


def arrow(mat: dict, radius: float = 0.004) -> Node:
    """A unit arrow along +y whose tip is at the origin and tail at ``y = -1``: scale it by ``(1, L, 1)``
    for length ``L`` and turn y onto the direction it points."""
    head = 0.25
    shaft = Node("Mesh", _cylinder_y(radius, radius, 1 - head), mat, translation([0, -1 + (1 - head) / 2, 0]))
    cone = Node("Mesh", _cylinder_y(0.0, 2.5 * radius, head), mat, translation([0, -head / 2, 0]))
    return Node("Group", children=(shaft, cone))


def triangle_mesh(vertices: np.ndarray, faces: np.ndarray, mat: dict, X: np.ndarray | None = None) -> Node:
    """A triangle mesh ``vertices (n, 3)`` m, ``faces (m, 3)`` int (flat-shaded by three.js normals)."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    geom = {"type": "BufferGeometry", "data": {
        "attributes": {"position": {"itemSize": 3, "type": "Float32Array", "array": _floats(v.ravel()),
                                    "normalized": False}},
        "index": {"type": "Uint32Array", "array": f.ravel().tolist()}}}
    return Node("Mesh", geom, mat, X)


def polyline(points: np.ndarray, rgb, segments: bool = False) -> Node:
    """A line through ``points (n, 3)`` m (``segments``: pairs of points, one segment each), drawn on top."""
    p = np.asarray(points, dtype=float)
    geom = {"type": "BufferGeometry", "data": {"attributes": {"position": {
        "itemSize": 3, "type": "Float32Array", "array": _floats(p.ravel()), "normalized": False}}}}
    return Node("LineSegments" if segments else "Line", geom, material(rgb, kind="LineBasicMaterial", on_top=True))


def translation(p) -> np.ndarray:
    X = np.eye(4)
    X[:3, 3] = p
    return X


def _segment_frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose whose y axis runs along ``a -> b``, centred on the segment's midpoint."""
    return pose_along_y(b - a, (a + b) / 2)


def pose_along_y(d: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """A pose ``(4, 4)`` at ``origin`` whose y axis is the direction of ``d (3,)`` (any length > 0)."""
    y = np.asarray(d, float) / np.linalg.norm(d)
    helper = np.array([1.0, 0, 0]) if abs(y[0]) < 0.9 else np.array([0, 0, 1.0])
    x = np.cross(y, helper)
    x /= np.linalg.norm(x)
    X = np.eye(4)
    X[:3, 0], X[:3, 1], X[:3, 2], X[:3, 3] = x, y, np.cross(x, y), origin
    return X


# ---------------------------------------------------------------------------------------------- page


def _viewer_dir() -> Path:
    """``meshcat/viewer`` of the installed ``meshcat`` package, found without importing the package
    (which would start its server machinery)."""
    spec = importlib.util.find_spec("meshcat")
    if spec is None or not spec.submodule_search_locations:
        raise InputError("meshcat: the package is not installed (pip install meshcat); it holds the viewer")
    return Path(next(iter(spec.submodule_search_locations))) / "viewer"


def viewer_script() -> str:
    """The MeshCat viewer's script (``viewer/dist/main.min.js``, three.js r132 inside)."""
    path = _viewer_dir() / "dist" / "main.min.js"
    if not path.is_file():
        raise InputError(f"{path}: MeshCat's viewer script is missing from the meshcat package")
    return path.read_text(encoding="utf-8")


def viewer_licence() -> str:
    """The MeshCat viewer's MIT licence, which a copy of its script carries (as an HTML comment)."""
    path = _viewer_dir() / "LICENSE"
    text = path.read_text(encoding="utf-8") if path.is_file() else "MIT License, Copyright (c) 2018 Robin Deits"
    return "<!-- The script below is MeshCat's viewer (the meshcat package), under this licence:\n" + \
        text.replace("--", "- -").strip() + "\n-->"


def _script_json(data) -> str:
    """JSON for inlining in a ``<script>`` element (no ``</`` that would end it early)."""
    return json.dumps(data, separators=(",", ":"), sort_keys=True, allow_nan=False).replace("</", "<\\/")


def page_html(page: Page, title: str, extra: dict, head: str, body: str, script: str) -> str:
    """The whole self-contained page: MeshCat's script, the scene's commands and animation, then the
    caller's ``head`` (CSS), ``body`` (HTML) and ``script`` (JavaScript run after the scene is loaded,
    with ``viewer`` and ``PIVOT`` (``extra``) in scope)."""
    scene = {"commands": page.commands, "animations": page.animations, "duration": page.duration}
    return "\n".join([
        "<!DOCTYPE html>", "<html>", "<head>", '<meta charset="utf-8">', f"<title>{_escape(title)}</title>",
        "<style>body { margin: 0; overflow: hidden; font-family: sans-serif; }",
        "#meshcat-pane { width: 100vw; height: 100vh; overflow: hidden; }", head, "</style>", "</head>", "<body>",
        '<div id="meshcat-pane"></div>', body,
        viewer_licence(), f"<script>\n{viewer_script()}\n</script>",
        f'<script type="application/json" id="pivot-scene">{_script_json(scene)}</script>',
        f'<script type="application/json" id="pivot-data">{_script_json(extra)}</script>',
        "<script>",
        "var viewer = new MeshCat.Viewer(document.getElementById('meshcat-pane'));",
        "var SCENE = JSON.parse(document.getElementById('pivot-scene').textContent);",
        "var PIVOT = JSON.parse(document.getElementById('pivot-data').textContent);",
        "SCENE.commands.forEach(function (c) { viewer.handle_command(c); });",
        "if (SCENE.animations.length) {",
        "  viewer.handle_command({type: 'set_animation', animations: SCENE.animations,",
        "                         options: {play: true, repetitions: 1, clampWhenFinished: true}});",
        "  viewer.animator.pause();  // loaded and seekable, but still until the user presses play",
        "}",
        script, "</script>", "</body>", "</html>", ""])


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
