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
    """Turn a ``PivotError`` or an ``OSError`` (an output that cannot be written, a file that cannot
    be read) into one line on stderr and exit code 2, and Ctrl-C into one line and exit code 130
    (DESIGN.md, Errors). Writes are atomic, so neither leaves a partial artifact."""
    try:
        yield
    except PivotError as e:
        message = " ".join(str(e).split("\n"))
        typer.echo(f"pivot: error: {message}", err=True)
        raise typer.Exit(code=2) from None
    except OSError as e:
        where = f"{e.filename}: " if e.filename else ""
        typer.echo(f"pivot: error: {where}{e.strerror or e}", err=True)
        raise typer.Exit(code=2) from None
    except KeyboardInterrupt:
        typer.echo("pivot: interrupted (no artifact was written in part)", err=True)
        raise typer.Exit(code=130) from None


def quiet_import(name: str):
    """Import module ``name`` with the process' stdout and stderr silenced: PyBullet prints a banner
    from C on import (to stderr), which would add a line to every message of a command that uses it."""
    import ctypes
    import importlib
    import os

    sys.stdout.flush()
    sys.stderr.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    try:
        with open(os.devnull, "w") as null:
            for fd in saved:
                os.dup2(null.fileno(), fd)
            try:
                return importlib.import_module(name)
            finally:
                ctypes.CDLL(None).fflush(None)  # C's buffered output goes to /dev/null, not after
                for fd, copy in saved.items():
                    os.dup2(copy, fd)
    finally:
        for copy in saved.values():
            os.close(copy)


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
