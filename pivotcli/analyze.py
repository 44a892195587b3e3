"""``pivot analyze MESH``: hull, segments, placements, contacts and pairs (§4.1)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info, step
from pivotcli.layout import Layout
from stages import analyze as stage
from stages.artifacts import output_lock
from stages.errors import InputError
from stages.scene import load_scene

_D = stage.Params()


def analyze(
    mesh: Annotated[Path | None, typer.Argument(help="Object mesh (OBJ, STL, PLY, OFF, GLB), in metres.")] = None,
    scene: Annotated[Path | None, typer.Option(help="Take the mesh, mass and scale from this scene file.")] = None,
    mass: Annotated[float, typer.Option(help="Object mass (kg).")] = 3.1,
    build: Annotated[Path | None, typer.Option(help="Build folder (default build/<scene or mesh name>).")] = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output folder (default <build>/analysis).")] = None,
    scale: Annotated[float, typer.Option(help="Multiply the mesh coordinates by this (e.g. 0.001 for mm).")] = 1.0,
    segment_angle: Annotated[float, typer.Option(help="Region-growing normal threshold (deg).")] = _D.segment_angle_deg,
    min_facet_area: Annotated[float, typer.Option(help="Smallest facet with contacts (m^2).")] = _D.min_facet_area,
    spacing: Annotated[float, typer.Option(help="Minimum spacing of contact points (m).")] = _D.sample_spacing,
    boundary_margin: Annotated[
        float, typer.Option(help="Minimum distance of a contact to its facet boundary (m).")
    ] = _D.boundary_margin,
    ball_radius: Annotated[float, typer.Option(help="Ball end-effector radius (m).")] = _D.ball_radius,
    pair_angle: Annotated[
        float, typer.Option(help="Flat-facet pairs: opposite-normal tolerance and squeeze cone (deg).")
    ] = _D.pair_angle_deg,
    cone_angle: Annotated[
        float, typer.Option(help="Pairs with a curved contact: friction-cone half-angle of the squeeze (deg).")
    ] = _D.cone_angle_deg,
    max_pairs: Annotated[
        int, typer.Option(help="At most this many pairs (flat-facet pairs are always kept).")
    ] = _D.max_pairs,
    sp_margin: Annotated[float, typer.Option(help="CoM margin inside the support polygon (m).")] = _D.sp_margin,
    seed: Annotated[int, typer.Option(help="Seed of the surface sampling.")] = _D.seed,
) -> None:
    """Analyse an object mesh: pivot vertices, tumble edges, placements, contact points and pairs."""
    params = stage.Params(
        segment_angle_deg=segment_angle, min_facet_area=min_facet_area, sample_spacing=spacing,
        boundary_margin=boundary_margin, ball_radius=ball_radius, pair_angle_deg=pair_angle,
        cone_angle_deg=cone_angle, max_pairs=max_pairs, sp_margin=sp_margin, seed=seed,
        sample_density=_D.sample_density, hull_coplanar_deg=_D.hull_coplanar_deg, flat_facet_deg=_D.flat_facet_deg,
    )
    with cli_errors():
        if scene is not None:
            spec = load_scene(scene).object
            mesh, mass, scale = spec.mesh_path, spec.mass, spec.scale
        elif mesh is None:
            raise InputError("pivot analyze: give a MESH file or --scene SCENE")
        out = out or Layout.of(scene or mesh, build).analysis
        with output_lock(out), step(f"analysing {mesh.name}"):
            result = stage.run(mesh, out, mass, params, scale=scale, producer=f"analyze {mesh}")
    c = result.summary["counts"]
    info(
        f"{mesh.name}: {c['facets']} facets, {c['pivot_vertices']} pivot vertices, {c['tumble_edges']} tumble "
        f"edges, {c['placements']} placements ({c['stable_placements']} SP), {c['contacts']} contacts, "
        f"{c['pairs']} pairs in {result.timings['total']:.3f} s -> {out}/"
    )
