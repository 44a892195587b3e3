"""Figures (matplotlib, Agg backend): every ``pivot show`` picture is drawn here and nowhere else."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection  # noqa: E402

from stages import artifacts  # noqa: E402
from stages.errors import ArtifactError  # noqa: E402


def _save(fig, png: str | Path) -> None:
    with artifacts.atomic_path(png) as tmp:
        fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)


def _equal_axes(ax, pts: np.ndarray) -> None:
    lo, hi = pts.min(0), pts.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2 * 1.05
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")


def show_analysis(analysis_dir: str | Path, png: str | Path, n_pairs: int = 12) -> None:
    """Fig. 4: (a) the object with its pivot vertices, (b) facets in colours, contacts and pairs."""
    d = Path(analysis_dir)
    if not (d / "object.ply").is_file():
        raise ArtifactError(f"{d / 'object.ply'}: missing (run pivot analyze first)")
    mesh = trimesh.load(d / "object.ply", force="mesh", process=False)
    seg = artifacts.read_table(d / "segments.parquet", "segments")
    hull = artifacts.read_table(d / "hull.parquet", "hull")
    con = artifacts.read_table(d / "contacts.parquet", "contacts")
    pairs = artifacts.read_table(d / "pairs.parquet", "pairs")
    tris = np.asarray(mesh.triangles)
    # A triangle may lie in several facets (superimposed): colour it by the largest one.
    owner = np.full(len(tris), -1)
    for f in np.argsort(seg["area"])[::1]:  # small first, so larger facets overwrite
        owner[seg["triangles"][f]] = f
    cmap = plt.get_cmap("tab20")
    colours = cmap((owner % 20) / 19.0)
    shade = 0.55 + 0.45 * np.abs(mesh.face_normals @ np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
    colours[:, :3] *= shade[:, None]

    fig = plt.figure(figsize=(12, 6))
    ax1 = fig.add_subplot(1, 2, 1, projection="3d")
    ax1.add_collection3d(Poly3DCollection(tris, facecolors=(0.8, 0.8, 0.85, 0.35), edgecolors=(0.5, 0.5, 0.5, 0.15),
                                          linewidths=0.2))
    is_v = hull["kind"] == "vertex"
    pv = np.stack([hull["x0"][is_v], hull["y0"][is_v], hull["z0"][is_v]], 1)
    ea = np.stack([hull["x0"][~is_v], hull["y0"][~is_v], hull["z0"][~is_v]], 1)
    eb = np.stack([hull["x1"][~is_v], hull["y1"][~is_v], hull["z1"][~is_v]], 1)
    ax1.add_collection3d(Line3DCollection(np.stack([ea, eb], 1), colors="tab:blue", linewidths=0.6, alpha=0.6))
    ax1.scatter(*pv.T, color="red", s=14, depthshade=False)
    ax1.set_title(f"(a) {len(pv)} pivot vertices (red), {len(ea)} tumble edges (blue)")
    _equal_axes(ax1, mesh.vertices)

    ax2 = fig.add_subplot(1, 2, 2, projection="3d", computed_zorder=False)  # points and pairs on top
    colours[:, 3] = 0.8
    ax2.add_collection3d(Poly3DCollection(tris, facecolors=colours, edgecolors=(0, 0, 0, 0.08), linewidths=0.2))
    P = np.stack([con["px"], con["py"], con["pz"]], 1)
    Nn = np.stack([con["nx"], con["ny"], con["nz"]], 1)
    lift = P + 0.004 * Nn  # keep the dots in front of their own facet
    ax2.scatter(*lift.T, color="black", s=4, depthshade=False, zorder=3)
    if len(pairs):
        pick = np.linspace(0, len(pairs) - 1, min(n_pairs, len(pairs))).round().astype(int)
        a, b = P[pairs["contact_a"][pick]], P[pairs["contact_b"][pick]]
        ax2.add_collection3d(Line3DCollection(np.stack([a, b], 1), colors="crimson", linewidths=1.4, zorder=4))
    ax2.set_title(f"(b) {len(seg)} facets, {len(P)} contacts, {len(pairs)} pairs ({min(n_pairs, len(pairs))} drawn)")
    _equal_axes(ax2, mesh.vertices)
    for ax in (ax1, ax2):
        ax.view_init(elev=22, azim=-60)
    fig.tight_layout()
    _save(fig, png)


def show_poses(scene, sample_dir: str | Path, png: str | Path, com_O=None, reach: list | None = None) -> None:
    """Fig. 10a: sampled object poses over the table (CoM; SP red, USP blue), pivot links red,
    tumble links blue, grasps per pose as dot size, obstacles grey, the arms' reach dashed.

    ``com_O``: the CoM in the object frame (dots at the CoM, else at the object frame's origin);
    ``reach``: optional ``[(name, centre_W (3,), radius)]`` spheres, drawn where they cut the plane
    of the CoM's median height.
    """
    from stages import se3

    d = Path(sample_dir)
    ps = artifacts.read_table(d / "poses.parquet", "poses")
    links = artifacts.read_table(d / "pose_links.parquet", "pose_links")
    grasps = artifacts.read_table(d / "grasps.parquet", "grasps")
    X = se3.matrix_from_columns(ps.columns)
    p = X[:, :3, 3] if com_O is None else se3.transform_points(X, np.asarray(com_O, dtype=float))
    ok = ps["status"] == "ok"
    n_grasps = np.bincount(grasps["pose_id"], minlength=len(ps)) if len(grasps) else np.zeros(len(ps), int)
    fig, ax = plt.subplots(figsize=(9, 7))
    sx, sy = scene.table.size
    ax.add_patch(plt.Rectangle((-sx / 2, -sy / 2), sx, sy, fc=(0.93, 0.9, 0.85), ec="k", lw=1))
    for ob in scene.obstacle_geometries():
        if ob.kind == "box":
            corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * np.asarray(ob.size[:2]) / 2
            c = (ob.X_WOb[:2, :2] @ corners.T).T + ob.X_WOb[:2, 3]
            ax.add_patch(plt.Polygon(c, fc="0.55", ec="k"))
        elif ob.kind == "cylinder":
            ax.add_patch(plt.Circle(ob.X_WOb[:2, 3], ob.radius, fc="0.55", ec="k"))
        else:
            v = se3.transform_points(ob.X_WOb, ob.vertices)[:, :2]
            ax.scatter(v[:, 0], v[:, 1], s=1, c="0.55")
    a, b = links["pose_a"], links["pose_b"]
    for prim, colour in (("pivot", "tab:red"), ("tumble", "tab:blue")):
        m = links["primitive"] == prim
        segs = np.stack([p[a[m], :2], p[b[m], :2]], axis=1)
        ax.add_collection(LineCollection(segs, colors=colour, lw=0.6, alpha=0.5, label=f"{prim} ({m.sum()})"))
    for kind, colour in (("SP", "tab:red"), ("USP", "tab:blue")):
        m = ok & (ps["support"] == kind)
        ax.scatter(p[m, 0], p[m, 1], s=6 + 1.5 * np.sqrt(n_grasps[m]), c=colour, alpha=0.8, zorder=3,
                   label=f"{kind} poses ({m.sum()})")
    bad = ~ok
    ax.scatter(p[bad, 0], p[bad, 1], s=8, marker="x", c="0.4", zorder=3, label=f"rejected ({bad.sum()})")
    ax.scatter(*p[0, :2], s=120, marker="*", c="gold", ec="k", zorder=4, label="start")
    z = float(np.median(p[ok, 2])) if ok.any() else 0.2
    for name, centre, radius in reach or []:
        h = radius**2 - (z - centre[2]) ** 2
        if h > 0:
            ax.add_patch(plt.Circle(centre[:2], np.sqrt(h), fill=False, ls="--", ec="tab:green", lw=1))
            ax.annotate(f"{name} reach", centre[:2] + np.array([np.sqrt(h) * 0.7, 0.0]), color="tab:green")
    ax.set_aspect("equal")
    ax.set_xlim(-sx / 2 - 0.45, sx / 2 + 0.1)
    ax.set_ylim(-sy / 2 - 0.15, sy / 2 + 0.15)
    ax.set_xlabel("x (m, away from the robot)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{scene.name}: {ok.sum()} poses, {len(grasps)} grasps (dot size), Fig. 10a")
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    _save(fig, png)


def show_trajectories(traj_dir_or_file: str | Path, png: str | Path, f_max: float, mu_table: float,
                      limits: dict | None = None) -> None:
    """Fig. 12-style plots over time: object tilt and yaw against the reference, ball forces with their
    bound, the table reaction against its friction cone, joint angles within their limits.

    ``limits``: ``{"left": (lower (n,), upper (n,)), "right": ...}`` to normalise the joint angles.
    """
    path = Path(traj_dir_or_file)
    if path.is_dir():
        path = path / "trajectories.parquet"
    tr = artifacts.read_table(path, "trajectories")
    t = tr["t"]
    kinds = tr["kind"]
    fig, axes = plt.subplots(4, 1, figsize=(11, 11), sharex=True)
    # Background bands per primitive kind.
    colours = {"pivot": (1, 0.85, 0.85), "tumble": (0.85, 0.88, 1), "transit": (0.9, 0.97, 0.9), "hold": (1, 1, 1)}
    change = np.flatnonzero(np.r_[True, kinds[1:] != kinds[:-1], True])
    for ax in axes:
        for a, b in zip(change[:-1], change[1:], strict=True):
            ax.axvspan(t[a], t[min(b, len(t) - 1)], color=colours.get(kinds[a], (1, 1, 1)), lw=0)
    ax = axes[0]
    ax.plot(t, np.degrees(tr["tilt"]), c="tab:red", lw=1.2, label="tilt")
    ax.plot(t, np.degrees(tr["tilt_ref"]), c="tab:red", ls="--", lw=0.8, label="tilt reference")
    ax.plot(t, np.degrees(tr["yaw"]), c="tab:blue", lw=1.2, label="yaw")
    ax.plot(t, np.degrees(tr["yaw_ref"]), c="tab:blue", ls="--", lw=0.8, label="yaw reference")
    ax.set_ylabel("angle from the\nprimitive's start (deg)")
    ax.legend(loc="upper right", fontsize=8, ncol=2)
    ax.set_title("pivot (red bands), tumble (blue), transit (green): object, forces, table, joints")
    ax = axes[1]
    for side, colour in (("l", "tab:orange"), ("r", "tab:purple")):
        f = np.stack([tr[f"f{side}x"], tr[f"f{side}y"], tr[f"f{side}z"]], 1)
        ax.plot(t, np.linalg.norm(f, axis=1), c=colour, lw=1, label=f"|f| {'left' if side == 'l' else 'right'} ball")
    ax.axhline(f_max, c="k", ls=":", lw=1, label=f"bound {f_max:g} N")
    ax.set_ylabel("ball force (N)")
    ax.legend(loc="upper right", fontsize=8)
    ax = axes[2]
    f0 = np.stack([tr["f0x"], tr["f0y"], tr["f0z"]], 1)
    ratio = np.linalg.norm(f0[:, :2], axis=1) / np.maximum(f0[:, 2], 1e-9)
    ax.plot(t, ratio, c="tab:green", lw=1, label="|f_t| / f_n at the table")
    ax.axhline(mu_table, c="k", ls=":", lw=1, label=f"μ table {mu_table:g}")
    ax2 = ax.twinx()
    ax2.plot(t, f0[:, 2], c="0.4", lw=0.8)
    ax2.set_ylabel("f_n (N)", color="0.4")
    ax.set_ylabel("friction ratio")
    ax.set_ylim(0, max(1.1 * mu_table, float(np.nanmax(ratio)) * 1.1 if len(ratio) else 1))
    ax.legend(loc="upper right", fontsize=8)
    ax = axes[3]
    for arm, colour in (("left", "tab:orange"), ("right", "tab:purple")):
        q = np.stack(list(tr[f"q_{arm}"]))
        if limits:
            lo, hi = limits[arm]
            q = (q - lo) / (hi - lo)
        ax.plot(t, q, c=colour, lw=0.7, alpha=0.8)
    if limits:
        ax.axhline(0, c="k", ls=":", lw=1)
        ax.axhline(1, c="k", ls=":", lw=1)
        ax.set_ylabel("joints, 0 = lower\n1 = upper limit")
    else:
        ax.set_ylabel("joints (rad)")
    ax.set_xlabel("t (s)")
    fig.tight_layout()
    _save(fig, png)


def show_plan(scene, build_dir: str | Path, png: str | Path, plan_path: str | Path | None = None) -> None:
    """Fig. 10b with the chosen path, and a storyboard of the plan's object poses over the table.

    Left: the explored lattice, faint (each pose with a grasp at its CoM, a line per pair of poses a
    feasible pivot or tumble joins), the plan's path over it in bold (each step coloured by its
    primitive: pivot red, tumble blue, a regrasp a yellow diamond), the start and the goal.
    Right: the object's footprint at each pose of the plan (light to dark in plan order), the pivot
    vertices used, obstacles, the start, the plan's end and the goal's footprint (dashed).
    """
    from stages import se3

    b = Path(build_dir)
    plan = artifacts.read_json(plan_path or b / "plan.json", "plan")
    nodes = artifacts.read_table(b / "graph" / "nodes.parquet", "nodes")
    edges = artifacts.read_table(b / "graph" / "edges.parquet", "edges")
    ps = artifacts.read_table(b / "sample" / "poses.parquet", "poses")
    summary = artifacts.read_json(b / "analysis" / "analysis.json", "analysis")
    mesh = trimesh.load(b / "analysis" / "object.ply", force="mesh", process=False)
    com = np.asarray(summary["com"])
    X = se3.matrix_from_columns(ps.columns)
    p = se3.transform_points(X, com)[:, :2]
    pose = nodes["pose_id"]

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(16, 7.5))
    sx, sy = scene.table.size
    for a_ in (ax, ax2):
        _draw_table(a_, scene)
    ok = edges["status"] == "ok"
    _draw_lattice(ax, p, pose, edges, ok)
    path = plan.get("nodes", [])
    goal_pose = _goal_pose(b)
    _draw_plan_path(ax, p, pose[np.asarray(path, dtype=int)], plan.get("steps", []))
    if goal_pose is not None:
        ax.scatter(*p[goal_pose], s=260, marker="*", c="gold", ec="k", lw=1.2, zorder=6, label="goal")
    ax.set_title(f"graph: {len(nodes)} nodes, {ok.sum()} edges (faint); plan {plan['status']} (bold)")
    ax.legend(loc="upper left", fontsize=8)

    goal = (X[goal_pose], p[goal_pose]) if goal_pose is not None else None
    _draw_storyboard(ax2, b, plan.get("steps", []), mesh.convex_hull.vertices, com, goal)
    c = plan.get("counts", {})
    ax2.set_title(f"plan: {c.get('pivot', 0)} pivots, {c.get('tumble', 0)} tumbles, {c.get('regrasp', 0)} regrasps "
                  "(black dots: pivot vertices)")
    ax2.legend(loc="upper left", fontsize=8)
    for a_ in (ax, ax2):
        a_.set_aspect("equal")
        a_.set_xlim(-sx / 2 - 0.05, sx / 2 + 0.05)
        a_.set_ylim(-sy / 2 - 0.1, sy / 2 + 0.1)
        a_.set_xlabel("x (m)")
        a_.set_ylabel("y (m)")
    fig.tight_layout()
    _save(fig, png)


def _draw_table(ax, scene) -> None:
    """The table's top and the obstacles' footprints (m, W) in plan view."""
    sx, sy = scene.table.size
    ax.add_patch(plt.Rectangle((-sx / 2, -sy / 2), sx, sy, fc=(0.95, 0.93, 0.9), ec="k", lw=1))
    for ob in scene.obstacle_geometries():
        if ob.kind == "box":
            c = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * np.asarray(ob.size[:2]) / 2
            ax.add_patch(plt.Polygon((ob.X_WOb[:2, :2] @ c.T).T + ob.X_WOb[:2, 3], fc="0.5", ec="k"))
        elif ob.kind == "cylinder":
            ax.add_patch(plt.Circle(ob.X_WOb[:2, 3], ob.radius, fc="0.5", ec="k"))


def _draw_storyboard(ax2, b: Path, steps: list, hull2: np.ndarray, com: np.ndarray, goal) -> None:
    """:func:`show_plan`'s right panel: the object's hull footprint ``hull2`` (O) at each pose of the
    plan's ``steps`` (light to dark in plan order) with its CoM, the pivot vertices used, the start,
    the plan's end and, with ``goal`` (its pose (4, 4) and CoM xy (2,)), the goal's footprint (dashed)."""
    from scipy.spatial import ConvexHull

    from stages import se3

    Xs = []
    for s in steps:
        for key in ("X_WO_from", "X_WO_to"):
            Xs.append(se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in s[key].items()})[0])
    uniq = []
    for Xi in Xs:
        if not uniq or np.abs(uniq[-1] - Xi).max() > 1e-9:
            uniq.append(Xi)
    cmap = plt.get_cmap("viridis")
    for i, Xi in enumerate(uniq):
        v = se3.transform_points(Xi, hull2)[:, :2]
        h = ConvexHull(v)
        ax2.add_patch(plt.Polygon(v[h.vertices], fill=False, ec=cmap(i / max(len(uniq) - 1, 1)), lw=1.2))
        c = se3.transform_points(Xi, com)
        ax2.scatter(*c[:2], s=8, color=cmap(i / max(len(uniq) - 1, 1)), zorder=3)
    for s in steps:
        if s["primitive"] == "pivot":
            Xa = se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in s["X_WO_from"].items()})[0]
            vpos = se3.transform_points(Xa, np.asarray([hull_vertex(b, s["vertex"])]))[0]
            ax2.scatter(*vpos[:2], marker="o", s=18, c="k", zorder=4)
    if uniq:
        for Xi, label, m in ((uniq[0], "start", "o"), (uniq[-1], "end", "X")):
            ax2.scatter(*se3.transform_points(Xi, com)[:2], s=120, marker=m, c="w", ec="k", zorder=5, label=label)
    if goal is not None:
        v = se3.transform_points(goal[0], hull2)[:, :2]
        ax2.add_patch(plt.Polygon(v[ConvexHull(v).vertices], fill=False, ec="goldenrod", lw=2, ls="--", zorder=5))
        ax2.scatter(*goal[1], s=260, marker="*", c="gold", ec="k", lw=1.2, zorder=6, label="goal")


def _draw_lattice(ax, p: np.ndarray, pose: np.ndarray, edges, ok: np.ndarray) -> None:
    """The explored lattice, faint: one line per pair of poses that a feasible pivot or tumble joins
    (whatever the grasp) and a dot per pose with a grasp, so that the plan drawn over it stays readable.

    p : (P, 2) float m, each pose's CoM in W; pose : (N,) int, each node's pose.
    """
    for prim, colour in (("pivot", (0.93, 0.72, 0.72)), ("tumble", (0.72, 0.78, 0.95))):
        m = ok & (edges["primitive"] == prim)
        pairs = np.unique(np.sort(np.stack([pose[edges["node_a"][m]], pose[edges["node_b"][m]]], 1), axis=1), axis=0)
        segs = np.stack([p[pairs[:, 0]], p[pairs[:, 1]]], 1) if len(pairs) else np.zeros((0, 2, 2))
        ax.add_collection(LineCollection(segs, colors=[colour], lw=0.6, zorder=1,
                                         label=f"{prim}: {m.sum()} edges, {len(pairs)} pose pairs"))
    used = np.unique(pose)
    ax.scatter(p[used, 0], p[used, 1], s=4, c="0.6", zorder=2, lw=0, label=f"{len(used)} poses")


def _draw_plan_path(ax, p: np.ndarray, pose_path: np.ndarray, steps: list) -> None:
    """The plan's poses joined in order, bold, each step coloured by its primitive; a regrasp (same pose)
    as a diamond."""
    colours = {"pivot": "tab:red", "tumble": "tab:blue", "regrasp": "goldenrod"}
    if not len(pose_path):
        return
    for i, s in enumerate(steps[: len(pose_path) - 1]):
        a, b = p[pose_path[i]], p[pose_path[i + 1]]
        c = colours.get(s.get("primitive"), "k")
        if s.get("primitive") == "regrasp":
            ax.scatter(*a, s=70, marker="D", c=c, ec="k", zorder=6)
        else:
            ax.plot([a[0], b[0]], [a[1], b[1]], c=c, lw=3.5, zorder=4, solid_capstyle="round")
    ax.plot(p[pose_path, 0], p[pose_path, 1], c="k", lw=0.8, zorder=5, marker="o", ms=3,
            label="plan (red pivot, blue tumble, diamond regrasp)")
    ax.scatter(*p[pose_path[0]], s=120, marker="o", c="w", ec="k", zorder=6, label="start")


def _goal_pose(build_dir: Path) -> int | None:
    """The goal's pose id in the sample (``sample.json``), or None when the goal has no pose."""
    goal = artifacts.read_json(Path(build_dir) / "sample" / "sample.json", "sample").get("goal", {})
    return int(goal["pose_id"]) if goal.get("status") == "ok" and goal.get("pose_id", -1) >= 0 else None


def hull_vertex(build_dir: Path, vertex_id: int) -> np.ndarray:
    """Position ``(3,)`` in O of hull corner ``vertex_id`` of an analysis."""
    hull = artifacts.read_table(Path(build_dir) / "analysis" / "hull.parquet", "hull")
    i = np.flatnonzero((hull["kind"] == "vertex") & (hull["v0"] == vertex_id))[0]
    return np.array([hull["x0"][i], hull["y0"][i], hull["z0"][i]])


def show_execution(run_dir: str | Path, png: str | Path, gif: str | Path | None = None) -> None:
    """Fig. 15-18: a storyboard of the frames PyBullet rendered during ``pivot execute`` (PNG; the goal's
    footprint is the gold plate on the table, the camera chosen from the scene: ``stages.execute.scene_camera``)
    and an animated GIF of them at ``GIF_SPEEDUP`` x real time; plus the object's tracking error and pivot
    slip over time under the frames."""
    from PIL import Image

    d = Path(run_dir)
    if not (d / "frames.npz").is_file():
        raise ArtifactError(f"{d / 'frames.npz'}: missing (run pivot execute with --frames > 0 first)")
    frames = np.load(d / "frames.npz")["frames"]
    log = artifacts.read_table(d / "execution.parquet", "execution")
    metrics = artifacts.read_json(d / "execution.json", "execution_metrics")
    k = len(frames)
    cols = min(4, k)
    show = np.linspace(0, k - 1, min(k, 8)).round().astype(int)
    rows = int(np.ceil(len(show) / cols))
    fig = plt.figure(figsize=(3.2 * cols, 2.6 * rows + 2.6))
    t = log["t"]
    for i, f in enumerate(show):
        ax = fig.add_subplot(rows + 1, cols, i + 1)
        ax.imshow(frames[f])
        ax.set_title(f"({chr(97 + i)}) t = {t[int(round(f * (len(t) - 1) / max(k - 1, 1)))]:.1f} s", fontsize=9)
        ax.axis("off")
    ax = fig.add_subplot(rows + 1, 1, rows + 1)
    ax.plot(t, 1000 * log["com_error"], lw=1, label="CoM deviation from the plan (mm)")
    ax.plot(t, 1000 * log["pivot_slip"], lw=1, label="pivot slip (mm)")
    ax.set_xlabel("t (s)")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(f"success {metrics['success']}: final error {100 * metrics['final_position_error']:.2f} cm, "
                 f"{metrics['final_yaw_error_deg']:.2f}°; fell {metrics['fell']}, collision {metrics['collision']}",
                 fontsize=10)
    fig.tight_layout()
    _save(fig, png)
    if gif is not None:
        images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
        with artifacts.atomic_path(gif) as tmp:
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                           duration=gif_frame_ms(float(t[-1] - t[0]), k), loop=0)


#: The execution GIF plays the motion this many times faster than real time.
GIF_SPEEDUP = 8.0


def gif_frame_ms(duration: float, frames: int) -> int:
    """Milliseconds per GIF frame so that ``frames`` spread over ``duration`` s of motion play at
    ``GIF_SPEEDUP`` x real time (between 40 ms, what viewers honour, and 1 s)."""
    return int(np.clip(round(1000.0 * duration / max(frames - 1, 1) / GIF_SPEEDUP), 40, 1000))


def show_benchmark_rates(groups: list[tuple[str, dict]], png: str | Path) -> None:
    """Benchmark: per group (object or goal kind) the plan-found rate over reachable cases and the
    physics success rate over planned runs (counts of :func:`stages.benchmark.report.rates`)."""
    names = [g for g, _ in groups]
    found = [r["found"] / r["reachable"] if r["reachable"] else 0.0 for _, r in groups]
    phys = [r["success_planned"] / r["runs_planned"] if r["runs_planned"] else 0.0 for _, r in groups]
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.8 * len(names) + 2), 3.6))
    ax.bar(x - 0.2, found, 0.4, label="plan found (of reachable cases)")
    ax.bar(x + 0.2, phys, 0.4, label="physics success (of planned runs)")
    for i, (_, r) in enumerate(groups):
        ax.text(i, 1.02, f"{r['reachable']}/{r['cases']}", ha="center", fontsize=7)
    ax.set_xticks(x, names, rotation=30, ha="right")
    ax.set_ylim(0, 1.12)
    ax.set_ylabel("rate")
    ax.set_title("benchmark (numbers: reachable / cases)", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.3), ncol=2)
    fig.tight_layout()
    _save(fig, png)


def show_benchmark_times(times: dict[str, np.ndarray], png: str | Path) -> None:
    """Benchmark: the distribution of wall time (s) per stage process, as box plots (log scale)."""
    names = [k for k, v in times.items() if len(v)]
    fig, ax = plt.subplots(figsize=(6.4, 3.4))
    ax.boxplot([times[k] for k in names], showfliers=True)
    ax.set_xticks(np.arange(1, len(names) + 1), names)
    ax.set_yscale("log")
    ax.set_ylabel("wall time (s)")
    ax.set_title("time per stage process", fontsize=10)
    fig.tight_layout()
    _save(fig, png)
