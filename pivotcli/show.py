"""``pivot show <artifact>``: draw the figure a person wants to see (PNG)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, info

app = typer.Typer(help="Draw figures of artifacts (PNG).", no_args_is_help=True)


@app.command("analysis")
def analysis(
    analysis_dir: Annotated[Path, typer.Argument(help="Folder written by pivot analyze.")],
    png: Annotated[Path, typer.Option(help="Output PNG.")] = Path("analysis.png"),
) -> None:
    """Fig. 4: pivot vertices and tumble edges; facets, contact points and some contact pairs."""
    from stages import plots

    with cli_errors():
        plots.show_analysis(analysis_dir, png)
    info(f"wrote {png}")


@app.command("poses")
def poses(
    sample_dir: Annotated[Path, typer.Argument(help="Folder written by pivot sample.")],
    scene: Annotated[Path, typer.Option(help="The scene file the poses were sampled for.")],
    analysis: Annotated[Path | None, typer.Option(help="Analysis folder (default: beside the sample).")] = None,
    png: Annotated[Path, typer.Option(help="Output PNG.")] = Path("poses.png"),
) -> None:
    """Fig. 10a: sampled poses over the table, pivot and tumble links, the arms' reach."""
    from stages import artifacts, plots
    from stages.robot import load_robot
    from stages.scene import load_scene

    with cli_errors():
        sc = load_scene(scene)
        summary = artifacts.read_json((analysis or sample_dir.parent / "analysis") / "analysis.json", "analysis")
        robot = load_robot(sc.robot.urdf_path, sc.base_transform(), tuple(sc.robot.eef_links))
        reach = [(arm, robot.arm(arm).reach_centre, robot.arm(arm).reach_radius) for arm in ("left", "right")]
        plots.show_poses(sc, sample_dir, png, com_O=summary["com"], reach=reach)
    info(f"wrote {png}")


@app.command("trajectories")
def trajectories(
    build_dir: Annotated[Path, typer.Argument(help="Folder with trajectories.parquet (or the file).")],
    scene: Annotated[Path, typer.Option(help="The scene file (force bound, friction, robot limits).")],
    png: Annotated[Path, typer.Option(help="Output PNG.")] = Path("trajectories.png"),
) -> None:
    """Fig. 12: tilt and yaw vs reference, ball forces vs bound, table friction, joint angles vs limits."""
    from stages import plots
    from stages.robot import load_robot
    from stages.scene import load_scene

    with cli_errors():
        sc = load_scene(scene)
        robot = load_robot(sc.robot.urdf_path, sc.base_transform(), tuple(sc.robot.eef_links))
        limits = {a: (robot.arm(a).lower, robot.arm(a).upper) for a in ("left", "right")}
        plots.show_trajectories(build_dir, png, sc.robot.max_eef_force, sc.table.friction, limits)
    info(f"wrote {png}")


@app.command("plan")
def plan(
    build_dir: Annotated[Path, typer.Argument(help="Build folder of the scene (with graph/ and plan.json).")],
    scene: Annotated[Path, typer.Option(help="The scene file.")],
    plan_file: Annotated[Path | None, typer.Option("--plan", help="Plan file (default <build>/plan.json).")] = None,
    png: Annotated[Path, typer.Option(help="Output PNG.")] = Path("plan.png"),
) -> None:
    """Fig. 10b with the plan's path highlighted, and a storyboard of the object poses over the table."""
    from stages import plots
    from stages.scene import load_scene

    with cli_errors():
        plots.show_plan(load_scene(scene), build_dir, png, plan_file)
    info(f"wrote {png}")


@app.command("execution")
def execution(
    run_dir: Annotated[Path, typer.Argument(help="Folder written by pivot execute.")],
    png: Annotated[Path | None, typer.Option(help="Storyboard PNG (default <dir>/execution.png).")] = None,
    gif: Annotated[Path | None, typer.Option(help="Animated GIF (default <dir>/execution.gif).")] = None,
    scene: Annotated[Path | None, typer.Option(help="Unused; accepted for symmetry with the others.")] = None,
) -> None:
    """Fig. 15-18: PyBullet frames of the execution as a storyboard PNG and an animated GIF."""
    from stages import plots

    png = png or run_dir / "execution.png"
    gif = gif or png.with_suffix(".gif")
    with cli_errors():
        plots.show_execution(run_dir, png, gif)
    info(f"wrote {png} and {gif}")
