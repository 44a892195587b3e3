"""Figures (matplotlib, Agg backend): every ``pivot show`` picture is drawn here and nowhere else."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
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
