"""``pivot view``: a plan and its execution in 3D, in one self-contained HTML page (MeshCat's viewer).

Reads a build folder (``analysis/``, ``sample/``, ``<variant>/plan.json``, ``trajectories.parquet``,
``execution.parquet`` when the run was executed) and the scene, and writes ``<variant>/view.html``:
MeshCat's viewer inlined with the scene as commands (``stages.threejs``), so the file opens from disk
with no network and no server, and the camera turns and zooms (MeshCat's orbit controls).

What it shows, in frame W (z up, table top at z = 0):

- the table, the obstacles, the robot from its URDF (the ``<visual>`` boxes, cylinders, spheres and
  capsules of every link, with their URDF colours), the object (its analysed mesh, decimated by
  vertex clustering above ``Params.max_faces`` triangles);
- ``plan``: the object and both arms animated along ``trajectories.parquet`` (object pose, joints
  through the robot model's forward kinematics), each ball's force on the object as an arrow ending at
  the contact point (the point of the object's surface nearest the ball centre), drawn while the ball
  is in contact; the planned CoM path (yellow, as in the paper's Fig. 3);
- ``execution``: the same from ``execution.parquet``, the physics log: the object (orange, see-through),
  the arms (hidden at first: they overlay the plan's), the CoM path (orange), and each ball's measured
  normal force (the log's summed normal force, along the line from the ball centre to the contact
  point, as a sphere's contact normal runs: the log holds no tangential force);
- the goal placement as a green ghost, the pivot vertices (red) and tumble edges (blue) the plan uses,
  the one in use enlarged while its primitive runs;
- a panel with play/pause, speed, a time slider with tick marks at the regrasp and catch moments
  (buttons that jump there), the primitive's index, name, support and phase at the current time.

Keyframes are trajectory rows ``Params.rate`` times a second, plus every row where the primitive,
its phase or a contact flag changes (so contacts switch on the right row); three.js interpolates
between them (linear positions, slerp rotations). Rows are the MPC's time steps (t in s).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from stages import artifacts, se3, threejs
from stages.errors import ArtifactError, InputError
from stages.threejs import Node, Page, Track

ARMS = ("left", "right")
#: Colours: the planned CoM path yellow as in the paper's Fig. 3, planned forces magenta, the execution
#: (object, CoM path, forces) orange.
PLAN_PATH_RGB, PLAN_FORCE_RGB, EXEC_RGB = (0.95, 0.85, 0.1), (0.85, 0.1, 0.75), (1.0, 0.55, 0.1)


@dataclass(frozen=True)
class Params:
    """Settings of the view (documented defaults)."""

    #: Keyframes per second of trajectory (Hz). The MPC's rows come at 24 Hz; 12 keeps joint motion
    #: smooth under interpolation and halves the page.
    rate: float = 12.0
    #: Largest triangle count of the object's mesh in the page; larger meshes are decimated.
    max_faces: int = 5000
    #: Arrow length per newton of ball force (m/N): the 50 N bound draws as 0.2 m.
    force_scale: float = 0.004
    #: Forces below this (N) draw no arrow.
    min_force: float = 0.5


@dataclass(frozen=True)
class Visual:
    """One URDF ``<visual>``: ``kind`` box | cylinder | sphere | capsule in link ``link``, at ``X_LG
    (4, 4)``; ``dims`` box full size (3,), cylinder/capsule (radius, length), sphere (radius,); ``rgba``."""

    link: str
    kind: str
    X_LG: np.ndarray
    dims: np.ndarray
    rgba: tuple[float, float, float, float]


@dataclass(frozen=True)
class Joint:
    """A URDF joint as the view needs it: its parent link, origin ``X_PC (4, 4)``, kind and axis (3,)."""

    parent: str
    X_PC: np.ndarray
    kind: str
    axis: np.ndarray


# ----------------------------------------------------------------------------------------------- URDF


def _origin(el: ET.Element | None) -> np.ndarray:
    """URDF ``<origin xyz rpy>``: rpy about fixed x, y then z axes (scipy's extrinsic ``"xyz"``)."""
    o = None if el is None else el.find("origin")
    xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
    rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
    return se3.make_transform(Rotation.from_euler("xyz", rpy).as_matrix(), np.array(xyz))


def read_urdf(path: str | Path) -> tuple[list[Visual], dict[str, Joint]]:
    """The ``<visual>`` shapes of every link and the joints (keyed by child link) of a URDF file."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
        colours = {m.get("name"): m.find("color").get("rgba") for m in root.iter("material")
                   if m.get("name") and m.find("color") is not None}
        visuals = [_visual(path, link.get("name"), v, colours) for link in root.findall("link")
                   for v in link.findall("visual")]
        joints = {}
        for j in root.findall("joint"):
            axis = j.find("axis")
            joints[j.find("child").get("link")] = Joint(
                j.find("parent").get("link"), _origin(j), j.get("type"),
                np.array([float(v) for v in (axis.get("xyz") if axis is not None else "1 0 0").split()]))
    except (OSError, ET.ParseError, AttributeError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the URDF's visuals and joints ({exc})") from exc
    return visuals, joints


def _visual(path: Path, link: str, el: ET.Element, colours: dict) -> Visual:
    shape = next(iter(el.find("geometry")))
    mat = el.find("material")
    rgba_text = None
    if mat is not None:
        rgba_text = mat.find("color").get("rgba") if mat.find("color") is not None else colours.get(mat.get("name"))
    rgba = tuple(float(v) for v in (rgba_text or "0.7 0.7 0.7 1").split())
    if shape.tag == "box":
        dims = [float(v) for v in shape.get("size").split()]
    elif shape.tag in ("cylinder", "capsule"):
        dims = [float(shape.get("radius")), float(shape.get("length"))]
    elif shape.tag == "sphere":
        dims = [float(shape.get("radius"))]
    else:
        raise InputError(f"{path}: link {link}: visual <{shape.tag}> is not drawn by pivot view "
                         "(box, cylinder, capsule or sphere)")
    return Visual(link, shape.tag, _origin(el), np.array(dims), rgba)


def static_link_poses(joints: dict[str, Joint], X_WB: np.ndarray, moving: set[str],
                      torso_angle: float = 0.0) -> dict[str, np.ndarray]:
    """World poses ``(4, 4)`` of the links that do not move with the arms (``moving``): the root at
    ``X_WB`` and every link reached from it through fixed joints or, at ``torso_angle`` rad, movable
    joints outside the arms (the torso, which planning holds still; see ``stages.robot``)."""
    links = set(joints) | {j.parent for j in joints.values()}
    root = next(iter(sorted(links - set(joints))))
    X_W = {root: np.asarray(X_WB, float)}
    pending = [root]
    while pending:
        parent = pending.pop()
        for child, j in sorted(joints.items()):
            if j.parent != parent or child in moving:
                continue
            X = X_W[parent] @ j.X_PC
            if j.kind != "fixed":
                X = X @ se3.make_transform(se3.rotation_about_axis(j.axis / np.linalg.norm(j.axis), torso_angle),
                                           np.zeros(3))
            X_W[child] = X
            pending.append(child)
    return X_W


def visual_node(v: Visual) -> Node:
    """The three.js object of one URDF visual, in its link's frame."""
    mat = threejs.material(v.rgba[:3], v.rgba[3] if len(v.rgba) > 3 else 1.0)
    if v.kind == "box":
        return Node("Mesh", threejs.box(v.dims), mat, v.X_LG)
    if v.kind == "sphere":
        return Node("Mesh", threejs.sphere(v.dims[0]), mat, v.X_LG)
    if v.kind == "cylinder":
        return threejs.cylinder(v.dims[0], v.dims[1], mat, v.X_LG)
    half = np.array([0.0, 0.0, v.dims[1] / 2])
    return threejs.capsule(-half, half, v.dims[0], mat, v.X_LG)


# ---------------------------------------------------------------------------------------- the object


def decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering (Rossignac-Borrel): snap vertices to a grid, merge each cell's vertices into
    their mean, drop the triangles that collapse; the cell grows by 1.5x until at most ``max_faces``
    remain. ``vertices (n, 3)`` m, ``faces (m, 3)``; a mesh already small enough is returned as is."""
    v, f = np.asarray(vertices, float), np.asarray(faces, np.int64)
    if len(f) <= max_faces:
        return v, f
    cell = float(np.ptp(v, axis=0).max()) / 200.0
    while True:
        keys = np.floor((v - v.min(0)) / cell).astype(np.int64)
        _, cluster, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        cluster = cluster.ravel()
        centre = np.zeros((len(counts), 3))
        np.add.at(centre, cluster, v)
        centre /= counts[:, None]
        g = cluster[f]
        keep = (g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])
        g = np.unique(np.sort(g[keep], axis=1), axis=0, return_index=True)[1]
        g = cluster[f][keep][np.sort(g)]
        if len(g) <= max_faces:
            used, inverse = np.unique(g, return_inverse=True)
            return centre[used], inverse.reshape(-1, 3)
        cell *= 1.5



def contact_points(mesh: trimesh.Trimesh, X_WO: np.ndarray, p_W: np.ndarray, touch: np.ndarray) -> np.ndarray:
    """Where each ball touches the object: the point of the mesh (frame O) nearest the ball centre
    ``p_W (K, 3)`` at object pose ``X_WO (K, 4, 4)``, in W; rows not touching keep the ball centre."""
    out = np.array(p_W, dtype=float)
    rows = np.flatnonzero(touch)
    if len(rows):
        p_O = se3.transform_points(se3.invert(X_WO[rows]), p_W[rows])
        out[rows] = se3.transform_points(X_WO[rows], trimesh.proximity.closest_point(mesh, p_O)[0])
    return out


# ------------------------------------------------------------------------------------------ motions


@dataclass(frozen=True)
class Motion:
    """One motion to draw, the plan's or the execution's, at keyframes: ``t (K,)`` s, object poses
    ``X_WO (K, 4, 4)``, joints ``q[arm] (K, n)`` rad, ball force on the object ``f[arm] (K, 3)`` N in W
    acting at ``c[arm] (K, 3)`` m (W), ``touch[arm] (K,)``; ``com_W (T, 3)`` the CoM at every row."""

    t: np.ndarray
    X_WO: np.ndarray
    q: dict
    f: dict
    c: dict
    touch: dict
    com_W: np.ndarray


def keyframe_rows(t: np.ndarray, changes: list[np.ndarray], rate: float) -> np.ndarray:
    """Rows ``(K,)`` kept as keyframes: about ``rate`` per second of ``t (T,)`` s, the first and last
    rows, and every row where one of ``changes`` (arrays ``(T,)``) takes a new value."""
    T = len(t)
    dt = float(np.median(np.diff(t))) if T > 1 else 1.0
    keep = np.zeros(T, bool)
    keep[::max(1, int(round(1.0 / (rate * dt))))] = True
    keep[[0, -1]] = True
    for a in changes:
        keep[1:] |= a[1:] != a[:-1]
    return np.flatnonzero(keep)


def plan_motion(tr, rows: np.ndarray, mesh: trimesh.Trimesh, com_O: np.ndarray) -> Motion:
    """The plan's motion from ``trajectories.parquet`` (table ``tr``) at keyframe ``rows``."""
    X_all = se3.matrix_from_columns(tr.columns)
    X = X_all[rows]
    q, f, c, touch = {}, {}, {}, {}
    for arm, s in zip(ARMS, "lr", strict=True):
        q[arm] = np.stack(list(tr[f"q_{arm}"]))[rows]
        touch[arm] = np.asarray(tr[f"{arm}_contact"], bool)[rows]
        f[arm] = np.stack([tr[f"f{s}x"], tr[f"f{s}y"], tr[f"f{s}z"]], 1)[rows]
        c[arm] = contact_points(mesh, X, np.stack([tr[f"{s}x"], tr[f"{s}y"], tr[f"{s}z"]], 1)[rows], touch[arm])
    return Motion(tr["t"][rows], X, q, f, c, touch, se3.transform_points(X_all, com_O))


def executed_motion(log, rows: np.ndarray, robot, mesh: trimesh.Trimesh, com_O: np.ndarray) -> Motion:
    """The physics log's motion (``execution.parquet``, one row per trajectory row while it ran) at
    ``rows``: the measured joints and object pose, each ball's summed normal force along its radius to
    the contact."""
    X_all = se3.matrix_from_columns(log.columns)
    X = X_all[rows]
    q, f, c, touch = {}, {}, {}, {}
    for arm in ARMS:
        q[arm] = np.stack(list(log[f"q_{arm}"]))[rows]
        touch[arm] = np.asarray(log[f"{arm}_touch"], bool)[rows]
        p = robot.eef_position(arm, q[arm])
        c[arm] = contact_points(mesh, X, p, touch[arm])
        d = c[arm] - p
        n = np.linalg.norm(d, axis=1, keepdims=True)
        f[arm] = d / np.maximum(n, 1e-9) * np.asarray(log[f"{arm}_force"], float)[rows, None] * (n > 1e-9)
    return Motion(log["t"][rows], X, q, f, c, touch, se3.transform_points(X_all, com_O))


def _pose_tracks(t: np.ndarray, X: np.ndarray) -> list[Track]:
    return [Track("position", t, X[:, :3, 3]), Track("quaternion", t, se3.quat_from_matrix(X[:, :3, :3]))]


def arm_link_visuals(robot, arm: str, visuals: list[Visual], X_links: np.ndarray) -> dict[int, list[Visual]]:
    """The visuals of an arm's frames grouped by the frame that moves them: a frame fixed to the one
    before it (tool flange, stick, ball) rides with the last movable frame, its visuals moved into that
    frame, so the page animates one pose per joint. ``X_links (L, 4, 4)`` the frames' poses at any
    one configuration; returns frame index -> visuals in that frame."""
    a = robot.arm(arm)
    out: dict[int, list[Visual]] = {}
    owner = 0
    for k, link in enumerate(a.link_names):
        if a.joint[k] >= 0 or k == 0:
            owner = k
        X_ok = se3.invert(X_links[owner]) @ X_links[k]
        for v in visuals:
            if v.link == link:
                out.setdefault(owner, []).append(replace(v, X_LG=X_ok @ v.X_LG))
    return out


def add_motion(page: Page, group: str, m: Motion, robot, visuals: list[Visual], object_node: Node,
               params: Params, rgb, force_rgb) -> None:
    """The object, the arms' links and the ball-force arrows (colour ``force_rgb``, drawn through the
    arm that hides them) of motion ``m`` under ``/meshcat/<group>``, animated; its CoM path (``rgb``)."""
    page.set_object(f"/meshcat/{group}/object", object_node)
    page.animate(f"/meshcat/{group}/object", _pose_tracks(m.t, m.X_WO))
    page.set_object(f"/meshcat/{group}/com_path", threejs.polyline(m.com_W, rgb))
    for arm in ARMS:
        X_links = robot.fk(arm, m.q[arm])
        for k, shapes in arm_link_visuals(robot, arm, visuals, X_links[0]).items():
            path = f"/meshcat/{group}/robot/{robot.arm(arm).link_names[k]}"
            page.set_object(path, Node("Group", children=tuple(visual_node(v) for v in shapes)))
            page.animate(path, _pose_tracks(m.t, X_links[:, k]))
        size = np.linalg.norm(m.f[arm], axis=1)
        d = np.where(size[:, None] > 1e-9, m.f[arm], [0.0, 0.0, 1.0])
        R = se3.rotation_between(np.array([0.0, 1.0, 0.0]), d)
        length = np.maximum(size * params.force_scale, 1e-3)
        path = f"/meshcat/{group}/forces/{arm}"
        page.set_object(path, threejs.arrow(threejs.material(force_rgb, on_top=True)))
        page.animate(path, [Track("position", m.t, m.c[arm]), Track("quaternion", m.t, se3.quat_from_matrix(R)),
                            Track("scale", m.t, np.stack([np.ones_like(length), length, np.ones_like(length)], 1)),
                            Track("visible", m.t, m.touch[arm] & (size >= params.min_force))])


# ------------------------------------------------------------------------------------------ the scene


def add_scene(page: Page, scene, robot, visuals: list[Visual], joints: dict[str, Joint]) -> None:
    """Table (top at z = 0), obstacles, the robot's trunk (its static links) and the camera."""
    sx, sy = scene.table.size
    page.set_object("/meshcat/table", Node("Mesh", threejs.box((sx, sy, 0.03)), threejs.material((0.8, 0.68, 0.5)),
                                           threejs.translation([0, 0, -0.015])))
    red = threejs.material((0.8, 0.2, 0.15))
    for i, ob in enumerate(scene.obstacle_geometries()):
        if ob.kind == "box":
            node = Node("Mesh", threejs.box(ob.size), red, ob.X_WOb)
        elif ob.kind == "cylinder":
            node = threejs.cylinder(ob.radius, ob.height, red, ob.X_WOb)
        else:
            node = threejs.triangle_mesh(ob.vertices, ob.faces, red, ob.X_WOb)
        page.set_object(f"/meshcat/obstacles/{i}", node)
    moving = {link for arm in ARMS for link in robot.arm(arm).link_names}
    X_W = static_link_poses(joints, scene.base_transform(), moving, robot.torso_angle)
    for link, X in sorted(X_W.items()):
        nodes = tuple(visual_node(v) for v in visuals if v.link == link)
        if nodes:
            page.set_object(f"/meshcat/robot_trunk/{link}", Node("Group", children=nodes, X=X))
    page.set_transform("/Grid", threejs.translation([0, 0, -scene.table.height]))
    page.set_property("/Axes", "visible", False)
    page.set_transform("/Cameras/default", threejs.translation([0.0, 0.0, 0.1]))
    # The camera's frame is turned so its y is W's z: (1.0, 0.6, 0.8) sits at W offset (1.0, -0.8, 0.6),
    # across the table from the robot and to its right, so the arms do not hide the object.
    page.set_property("/Cameras/default/rotated/<object>", "position", [1.0, 0.6, 0.8])


def hull_points(hull, ids) -> np.ndarray:
    """Positions ``(k, 3)`` in O of hull corners ``ids`` (the analysis' vertex ids)."""
    is_v = hull["kind"] == "vertex"
    where = {int(v): i for i, v in zip(np.flatnonzero(is_v), hull["v0"][is_v], strict=True)}
    rows = [where[int(i)] for i in ids]
    return np.stack([hull["x0"][rows], hull["y0"][rows], hull["z0"][rows]], 1)


def add_supports(page: Page, steps: list[dict], hull, t: np.ndarray, primitive: np.ndarray) -> None:
    """Each pivot's vertex (red) and tumble's edge (blue) in W at the step's start, and a larger copy
    shown while that step runs (``t (K,)`` s, ``primitive (K,)`` the step index at each keyframe)."""
    for k, s in enumerate(steps):
        if s["primitive"] not in ("pivot", "tumble"):
            continue
        X = se3.matrix_from_columns({c: np.atleast_1d(v) for c, v in s["X_WO_from"].items()})[0]
        ids = [s["vertex"]] if s["primitive"] == "pivot" else list(s["edge"])
        p = se3.transform_points(X, hull_points(hull, ids))
        rgb = (0.9, 0.1, 0.1) if s["primitive"] == "pivot" else (0.1, 0.3, 0.95)
        mat = threejs.material(rgb, on_top=True)
        for name, r in (("used", 0.006), ("active", 0.014)):
            node = threejs.capsule(p[0], p[-1], r, mat)
            page.set_object(f"/meshcat/supports/{name}/step{k}", node)
        page.animate(f"/meshcat/supports/active/step{k}", [Track("visible", t, primitive == k)])


def timeline(tr, steps: list[dict]) -> dict:
    """What the panel shows over time: ``segments`` ``[t, step, kind, phase]`` at every change of
    step or phase, ``events`` ``[t, label]`` at the regrasp and catch moments."""
    t, prim, kind, phase = tr["t"], tr["primitive"], tr["kind"], tr["phase"]
    change = np.flatnonzero(np.r_[True, (prim[1:] != prim[:-1]) | (phase[1:] != phase[:-1])])
    segments = [[round(float(t[i]), 3), int(prim[i]), str(kind[i]), str(phase[i])] for i in change]
    events = []
    for i in change:
        s = steps[int(prim[i])]
        if s["primitive"] == "regrasp" and kind[i] == "transit" and phase[i] in ARMS:
            held = " (the other ball holds the object: USP)" if s.get("support") == "USP" else ""
            events.append([round(float(t[i]), 3), f"regrasp: the {phase[i]} ball moves{held}"])
        elif s["primitive"] == "tumble" and phase[i] == "release":
            events.append([round(float(t[i]), 3), f"tumble: the {s.get('pusher', '?')} ball releases"])
        elif s["primitive"] == "tumble" and phase[i] == "catch":
            events.append([round(float(t[i]), 3), f"catch: the {s.get('catcher', '?')} ball lowers the object"])
    return {"segments": segments, "events": events,
            "steps": [{"primitive": s["primitive"], "support": s.get("support", "")} for s in steps]}


# ------------------------------------------------------------------------------------------- the page

PANEL_CSS = """
#pv-panel { position: absolute; left: 8px; top: 8px; width: 340px; max-height: 95vh; overflow-y: auto;
  background: rgba(255, 255, 255, 0.88); border-radius: 6px; padding: 8px 10px; font-size: 12px; }
#pv-panel h1 { font-size: 15px; margin: 0 0 4px 0; }
#pv-slider { width: 100%; }
#pv-step { font-weight: bold; margin: 4px 0; }
#pv-events button { display: block; margin: 2px 0; text-align: left; font-size: 12px; }
.pv-key { display: inline-block; width: 10px; height: 10px; margin: 0 3px 0 8px; }
"""

PANEL_JS = """
(function () {
  var A = viewer.animator, T = SCENE.duration, D = PIVOT;
  var $ = function (id) { return document.getElementById(id); };
  var slider = $('pv-slider'), play = $('pv-play');
  slider.max = T;
  function seek(t) { t = Math.max(0, Math.min(T, t)); A.seek(t); A.display_progress(t); slider.value = t; }
  window.pivotSeek = seek;
  slider.addEventListener('input', function () { seek(parseFloat(slider.value)); });
  play.addEventListener('click', function () {
    if (A.playing) { A.pause(); } else { if (A.time >= T - 1e-6) { seek(0); } A.play(); }
  });
  $('pv-speed').addEventListener('change', function () { A.mixer.timeScale = parseFloat(this.value); });
  document.querySelectorAll('#pv-events button').forEach(function (b) {
    b.addEventListener('click', function () { seek(parseFloat(b.dataset.t)); });
  });
  document.querySelectorAll('.pv-layer').forEach(function (box) {
    box.addEventListener('change', function () {
      viewer.scene_tree.find(['meshcat', box.dataset.layer]).vis_controller.setValue(box.checked);
    });
  });
  function segmentAt(t) {
    var s = D.timeline.segments, lo = 0, hi = s.length - 1;
    if (!s.length) { return null; }
    while (lo < hi) { var mid = (lo + hi + 1) >> 1; if (s[mid][0] <= t + 1e-9) { lo = mid; } else { hi = mid - 1; } }
    return s[lo];
  }
  function update() {
    var t = A.time, s = segmentAt(t);
    if (A.playing) { slider.value = t; }
    $('pv-time').textContent = t.toFixed(2) + ' / ' + T.toFixed(2) + ' s';
    if (s) {
      var st = D.timeline.steps[s[1]];
      $('pv-step').textContent = 'step ' + (s[1] + 1) + ' of ' + D.timeline.steps.length + ': ' + st.primitive +
        ' (' + st.support + '), ' + s[2] + (s[3] && s[3] !== s[2] ? ': ' + s[3] : '');
    }
    play.textContent = A.playing ? 'pause' : 'play';
    document.querySelectorAll('.pv-layer').forEach(function (box) {  // also hidden from the scene tree
      box.checked = viewer.scene_tree.find(['meshcat', box.dataset.layer]).object.visible;
    });
    requestAnimationFrame(update);
  }
  var m = /t=([0-9.]+)/.exec(window.location.hash);
  seek(m ? parseFloat(m[1]) : 0);
  update();
})();
"""


def panel_html(info: dict) -> str:
    """The control panel: title, status lines, play/pause, speed, slider with event ticks, layers."""
    esc = threejs._escape
    events = info["timeline"]["events"]
    ticks = "".join(f'<option value="{t}"></option>' for t, _ in events)
    buttons = "".join(f'<button data-t="{t}">{t:.1f} s: {esc(label)}</button>' for t, label in events)
    lines = "".join(f"<div>{esc(line)}</div>" for line in info["lines"])
    keys = [("plan", (0.3, 0.45, 0.85), "planned object"), ("execution", EXEC_RGB, "executed: object, CoM, force"),
            ("goal", (0.2, 0.8, 0.3), "goal"), ("com", PLAN_PATH_RGB, "planned CoM path"),
            ("force", PLAN_FORCE_RGB, "planned ball force"),
            ("pivot", (0.9, 0.1, 0.1), "pivot vertex"), ("tumble", (0.1, 0.3, 0.95), "tumble edge")]
    legend = "".join(f'<span class="pv-key" style="background: rgb({", ".join(str(int(255 * c)) for c in rgb)})">'
                     f"</span>{esc(text)}" for _, rgb, text in keys)
    layers = "".join(f'<label><input type="checkbox" class="pv-layer" data-layer="{name}" checked> {name}</label> '
                     for name in info["layers"])
    return f"""<div id="pv-panel">
<h1>{esc(info["title"])}</h1>{lines}
<div id="pv-step">{esc(info["status"])}</div>
<div><button id="pv-play">play</button> speed <select id="pv-speed"><option value="0.25">0.25x</option>
<option value="0.5">0.5x</option><option value="1" selected>1x</option><option value="2">2x</option>
<option value="4">4x</option></select> <span id="pv-time"></span></div>
<input type="range" id="pv-slider" min="0" max="0" step="0.01" value="0" list="pv-ticks">
<datalist id="pv-ticks">{ticks}</datalist>
<div>show: {layers}</div>
<div id="pv-events">{"regrasp and catch moments:" if events else ""}{buttons}</div>
<div>{legend}</div>
<div style="color: #555">drag to turn, scroll to zoom, right-drag to pan; the scene tree (Open Controls) hides any
part</div>
</div>"""


# ---------------------------------------------------------------------------------------------- run


@dataclass(frozen=True)
class ViewResult:
    """What ``run`` wrote: the page, whether it shows a motion (``status`` ``ok``) or only the scene
    (``no_plan``, ``no_trajectories``, with ``reason``), its size (bytes) and keyframe count."""

    path: Path
    status: str
    reason: str
    size: int
    keyframes: int


def _step_motion(X: np.ndarray, robot) -> Motion:
    """A motion of one keyframe: the object at ``X (4, 4)``, the arms at rest, no contact."""
    z = {arm: np.zeros((1, 3)) for arm in ARMS}
    return Motion(np.zeros(1), X[None], {arm: robot.arm(arm).q_rest[None] for arm in ARMS}, z, z,
                  {arm: np.zeros(1, bool) for arm in ARMS}, np.zeros((0, 3)))


def _check_scene(scene_path: Path, plan: dict, plan_path: Path) -> None:
    want = plan.get("meta", {}).get("inputs", {}).get("scene")
    if want and artifacts.sha256_file(scene_path) != want:
        raise InputError(f"{scene_path}: not the scene {plan_path} was planned for (its sha256 differs); "
                         "pass the build's scene with --scene")


def _object_nodes(mesh: trimesh.Trimesh, params: Params) -> dict[str, Node]:
    v, f = decimate(mesh.vertices, mesh.faces, params.max_faces)
    return {"plan": threejs.triangle_mesh(v, f, threejs.material((0.3, 0.45, 0.85), kind="MeshPhongMaterial")),
            "execution": threejs.triangle_mesh(v, f, threejs.material((1.0, 0.55, 0.1), 0.45)),
            "goal": threejs.triangle_mesh(v, f, threejs.material((0.2, 0.8, 0.3), 0.3))}


def run(build_dir: str | Path, scene_path: str | Path, out: str | Path, variant: str = "full",
        params: Params = Params(), execution_dir: str | Path | None = None) -> ViewResult:
    """Write the view of ``<build_dir>/<variant>`` to ``out`` (HTML), with the execution in
    ``execution_dir`` (default beside the plan) when it holds one. A build without a plan or without
    trajectories gives the scene with the start and goal and the reason, status not ``ok``."""
    from stages.sample import placement_pose

    b, scene_path = Path(build_dir), Path(scene_path)
    inp = _read_inputs(b, scene_path, variant, params)
    page = Page()
    add_scene(page, inp.scene, inp.robot, inp.visuals, inp.joints)
    page.set_object("/meshcat/goal", inp.nodes["goal"])  # a mesh at the top: MeshCat computes its normals
    page.set_transform("/meshcat/goal", placement_pose(inp.scene.goal, inp.model, f"{scene_path}: goal")[0])
    counts = [f"{n} {k}s" for k, n in inp.plan.get("counts", {}).items() if k != "usp_regrasp"]
    lines = [", ".join([f"plan: {inp.plan['status']}", *counts])]
    traj = b / variant / "trajectories.parquet"
    if inp.plan["status"] != "ok" or not traj.is_file():
        status = "no_plan" if inp.plan["status"] != "ok" else "no_trajectories"
        reason = inp.plan.get("reason", "") if status == "no_plan" else _mpc_reason(b / variant)
        start = placement_pose(inp.scene.start, inp.model, f"{scene_path}: start")[0]
        add_motion(page, "plan", _step_motion(start, inp.robot), inp.robot, inp.visuals, inp.nodes["plan"], params,
                   PLAN_PATH_RGB, PLAN_FORCE_RGB)
        keyframes, info_t, layers = 0, {"segments": [], "events": [], "steps": []}, ["plan"]
    else:
        status, reason = "ok", ""
        keyframes, info_t, layers = _motion_layers(page, inp, artifacts.read_table(traj, "trajectories"),
                                                   Path(execution_dir or b / variant), params, lines)
    info = {"title": f"pivot view: {inp.scene.name} ({variant})", "lines": lines, "timeline": info_t,
            "status": f"{status.replace('_', ' ')}: {reason}" if status != "ok" else "", "layers": layers}
    html = threejs.page_html(page, info["title"], info, PANEL_CSS, panel_html(info), PANEL_JS)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with artifacts.atomic_path(out) as tmp:
        tmp.write_text(html, encoding="utf-8")
    return ViewResult(out, status, reason, len(html.encode("utf-8")), keyframes)


@dataclass(frozen=True)
class _Inputs:
    """What a view reads: the scene, the analysed object (model and tables), the robot and its URDF
    visuals and joints, the plan, and the object's three.js meshes (plan, execution, goal)."""

    scene: object
    model: object
    tables: dict
    robot: object
    visuals: list
    joints: dict
    plan: dict
    nodes: dict


def _read_inputs(b: Path, scene_path: Path, variant: str, params: Params) -> _Inputs:
    from stages.objectmodel import load_object_model
    from stages.robot import load_robot
    from stages.scene import load_scene

    scene = load_scene(scene_path)
    plan_path = b / variant / "plan.json"
    plan = artifacts.read_json(plan_path, "plan")
    _check_scene(scene_path, plan, plan_path)
    model, tables = load_object_model(b / "analysis")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    visuals, joints = read_urdf(scene.robot.urdf_path)
    return _Inputs(scene, model, tables, robot, visuals, joints, plan, _object_nodes(tables["mesh"], params))


def _motion_layers(page: Page, inp: _Inputs, tr, execution_dir: Path, params: Params,
                   lines: list[str]) -> tuple[int, dict, list[str]]:
    """The plan's layer from trajectories ``tr``, the supports, the execution's layer when there is one;
    returns the keyframe count, the panel's timeline and the layers' names."""
    rows = keyframe_rows(tr["t"], [tr["primitive"], tr["phase"], tr["left_contact"], tr["right_contact"]],
                         params.rate)
    mesh = inp.tables["mesh"]
    m = plan_motion(tr, rows, mesh, inp.model.com)
    add_motion(page, "plan", m, inp.robot, inp.visuals, inp.nodes["plan"], params, PLAN_PATH_RGB, PLAN_FORCE_RGB)
    add_supports(page, inp.plan["steps"], inp.tables["hull"], m.t, tr["primitive"][rows])
    layers = ["plan", *_add_execution(page, execution_dir, tr, rows, inp.robot, inp.visuals, mesh, inp.model.com,
                                      inp.nodes, params, lines)]
    return len(rows), timeline(tr, inp.plan["steps"]), layers


def _mpc_reason(run_dir: Path) -> str:
    p = run_dir / "trajectories.json"
    if not p.is_file():
        return "no trajectories (run pivot mpc first)"
    stats = artifacts.read_json(p, "mpc")
    return f"the MPC stage stopped: {stats.get('status')} {stats.get('reason', '')}".strip()


def _add_execution(page: Page, run_dir: Path, tr, rows, robot, visuals, mesh, com_O, nodes, params,
                   lines: list[str]) -> list[str]:
    """The execution's layer when ``execution.parquet`` exists; its summary goes to ``lines``."""
    path = run_dir / "execution.parquet"
    if not path.is_file():
        lines.append("execution: none (run pivot execute to compare with physics)")
        return []
    log = artifacts.read_table(path, "execution")
    # A log that stops early is drawn as far as it goes; the release after the plan's last step (the
    # balls let go and back off, ``stages.execute.with_release``) is not drawn.
    n = min(len(log["t"]), len(tr["t"]))
    if n == 0 or not np.allclose(log["t"][:n], tr["t"][:n], atol=1e-6):
        raise ArtifactError(f"{path}: its rows are not the trajectories' time steps (an execution of other "
                            "trajectories?)")
    m = executed_motion(log, np.append(rows[rows < n - 1], n - 1), robot, mesh, com_O)
    add_motion(page, "execution", m, robot, visuals, nodes["execution"], params, EXEC_RGB, EXEC_RGB)
    page.set_property("/meshcat/execution/robot", "visible", False)
    metrics = run_dir / "execution.json"
    if metrics.is_file():
        x = artifacts.read_json(metrics, "execution_metrics")
        lines.append(f"execution: success {x['success']}, final error {100 * x['final_position_error']:.2f} cm / "
                     f"{x['final_yaw_error_deg']:.2f} deg, fell {x['fell']}, collision {x['collision']}")
    return ["execution"]


def write_case_views(out: str | Path, cases: list[dict]) -> dict[str, str]:
    """The benchmark's views: ``runs/<case>/full/view.html`` of every case with a plan, with its seed-0
    execution, written when missing or older than the plan, trajectories or execution. Returns each
    case's view as a path relative to ``out``; a case whose view cannot be written is left out."""
    import logging

    from stages.errors import PivotError

    out, links = Path(out), {}
    for c in cases:
        b = out / "runs" / c["case"]
        page = b / "full" / "view.html"
        inputs = [b / "full" / n for n in ("plan.json", "trajectories.parquet")] + [b / "full" / "seed0" /
                                                                                   "execution.parquet"]
        if not inputs[0].is_file():
            continue
        newest = max(p.stat().st_mtime for p in inputs if p.is_file())
        try:
            if not page.is_file() or page.stat().st_mtime < newest:
                run(b, out / c["scene"], page, execution_dir=b / "full" / "seed0")
            links[c["case"]] = page.relative_to(out).as_posix()
        except PivotError as e:
            logging.getLogger("pivot.view").warning("%s: no view: %s", c["case"], e)
    return links
