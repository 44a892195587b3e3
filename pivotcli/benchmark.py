"""``pivot benchmark make|run|report``: measure the chain on general objects and goals (issue 13)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from pivotcli.common import cli_errors, console, info, state
from stages.errors import InputError

app = typer.Typer(help="A benchmark of general objects and goals: make the suite, sweep it on Dask, report.",
                  no_args_is_help=True)


@app.command("make")
def make(
    out: Annotated[Path, typer.Argument(help="Suite folder to write.")],
    objects: Annotated[str, typer.Option(help="Comma-separated object families (default: all).")] = "",
    goals: Annotated[int, typer.Option(min=1, help="Goals per object (kinds cycle translate, rotate, face).")] = 6,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the goal generator.")] = 0,
) -> None:
    """Write one scene per (object, goal) and label each goal reachable or not (a necessary test)."""
    from stages import objects as families
    from stages.benchmark import suite

    names = tuple(n for n in objects.split(",") if n) or tuple(families.FAMILIES)
    with cli_errors():
        data = suite.make_suite(out, suite.SuiteParams(objects=names, goals=goals, seed=seed))
    cases = data["cases"]
    reachable = sum(c["reachable"] for c in cases)
    info(f"{len(cases)} cases over {len(names)} objects, {reachable} labelled reachable -> {out}/suite.json")


@app.command("run")
def run(
    out: Annotated[Path, typer.Argument(help="Suite folder written by pivot benchmark make.")],
    scheduler: Annotated[str, typer.Option(help="Address of an existing Dask scheduler (tcp://host:8786); "
                                                "default: a LocalCluster on this machine.")] = "",
    workers: Annotated[int, typer.Option(min=1, help="LocalCluster worker processes.")] = 2,
    seeds: Annotated[int, typer.Option(min=1, help="Physics runs per case: seed 0 nominal, k > 0 randomized.")] = 2,
    timeout: Annotated[float, typer.Option(min=1.0, help="Time limit of one case's chain and runs (s).")] = 600.0,
) -> None:
    """Run every case's whole chain and its physics seeds on Dask -> results.parquet (resumable)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from stages.benchmark import sweep

    with cli_errors():
        if not (out / "suite.json").is_file():
            raise InputError(f"{out / 'suite.json'}: missing (run pivot benchmark make {out} first)")
        n = len(json.loads((out / "suite.json").read_text())["cases"])
        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      console=console, disable=state["quiet"]) as progress:
            task = progress.add_task("benchmark", total=n)

            def done(case: str, skipped: bool) -> None:
                progress.update(task, advance=1, description=f"{case}{' (current, skipped)' if skipped else ''}")

            s = sweep.sweep(out, sweep.SweepParams(seeds=seeds, timeout=timeout, workers=workers,
                                                   scheduler=scheduler), on_case=done)
    info(f"{s.cases} cases: {s.ran} ran, {s.skipped} current (skipped), {s.crashed} lost workers; "
         f"{s.rows} rows -> {out}/results.parquet")


@app.command("report")
def report(
    out: Annotated[Path, typer.Argument(help="Suite folder with results.parquet.")],
) -> None:
    """Success rates per object and goal kind, failure reasons, time per stage -> report.md + figures."""
    from stages.benchmark import report as stage

    with cli_errors():
        path = stage.write_report(out)
    info(f"wrote {path}")
