"""What every command shares: error reporting, verbosity, progress."""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

import typer
from rich.console import Console
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from stages.errors import PivotError

log = logging.getLogger("pivot")
console = Console(stderr=True)
state = {"quiet": False, "verbose": 0}


@contextlib.contextmanager
def cli_errors() -> Iterator[None]:
    """Turn a ``PivotError`` into one line on stderr and exit code 2 (DESIGN.md, Errors)."""
    try:
        yield
    except PivotError as e:
        message = " ".join(str(e).split("\n"))
        typer.echo(f"pivot: error: {message}", err=True)
        raise typer.Exit(code=2) from None


@contextlib.contextmanager
def step(description: str) -> Iterator[None]:
    """A spinner with elapsed time on stderr while a step runs (nothing when quiet or not a tty)."""
    if state["quiet"] or not sys.stderr.isatty():
        yield
        return
    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                  console=console, transient=True) as progress:
        progress.add_task(description, total=None)
        yield


def info(message: str) -> None:
    """A line for the user on stderr unless ``--quiet``."""
    if not state["quiet"]:
        console.print(message, highlight=False, soft_wrap=True)


def configure(verbose: int, quiet: bool) -> None:
    """Show the stages' logs on stderr: warnings by default, INFO with ``-v``, DEBUG with ``-vv``.

    One handler on the ``pivot`` and ``stages`` loggers, bound to the current ``sys.stderr`` and replaced
    on each call (so that repeated invocations in one process, as in tests, do not print twice).
    """
    state["quiet"], state["verbose"] = quiet, verbose
    level = logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING
    if quiet:
        level = logging.ERROR
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s", stream=sys.stderr)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    for name in ("pivot", "stages"):
        logger = logging.getLogger(name)
        for old in [h for h in logger.handlers if getattr(h, "_pivot", False)]:
            logger.removeHandler(old)
        handler._pivot = True
        logger.addHandler(handler)
        logger.setLevel(level)
        logger.propagate = False
