"""Errors for bad input. Expected failures (IK misses, infeasible QPs) are data, not exceptions."""

import contextlib
import os
from collections.abc import Iterator


class PivotError(Exception):
    """Bad input: the message names the file and the problem. The CLI prints it and exits 2."""


class InputError(PivotError):
    """An input file is missing, unreadable, or its content is invalid."""


class ArtifactError(PivotError):
    """An artifact is missing, truncated, or has the wrong schema."""


@contextlib.contextmanager
def about(path) -> Iterator[None]:
    """Name ``path`` in a ``PivotError`` raised inside that names no file (a library's check of the
    data read from ``path``), so that the user learns which file to fix."""
    try:
        yield
    except PivotError as e:
        first = str(e).split(": ", 1)[0]
        if os.path.exists(first) or first.rsplit(".", 1)[-1] in ("json", "parquet", "ply", "npz", "obj", "stl"):
            raise
        raise type(e)(f"{path}: {e}") from e
