"""On-disk caches of what is slow to derive and depends only on its inputs (issue 20).

A cache entry is a ``.npz`` of plain arrays named by the sha256 of everything it is derived from
(the input file's bytes, the generation parameters and the source of the code that derives it), so
an entry is never stale: any change makes a new name. Entries are written atomically; one that
cannot be read is derived again. The folder is ``$PIVOT_CACHE_DIR`` when set ("" turns the cache
off), else ``$XDG_CACHE_HOME/pivot``, else ``~/.cache/pivot`` (the XDG base-directory convention
that ``platformdirs`` follows on Linux).
"""

from __future__ import annotations

import hashlib
import os
import zipfile
from pathlib import Path

import numpy as np

from stages.artifacts import atomic_path


def cache_dir() -> Path | None:
    """The cache folder (module docstring), or None when ``PIVOT_CACHE_DIR`` is set empty."""
    own = os.environ.get("PIVOT_CACHE_DIR")
    if own is not None:
        return Path(own) if own else None
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "pivot"


def entry_name(kind: str, *parts: object) -> str:
    """``<kind>-<sha256 of the parts' reprs>.npz``: the name of an entry derived from ``parts``."""
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else repr(p).encode())
        h.update(b"\0")
    return f"{kind}-{h.hexdigest()}.npz"


def load(name: str) -> dict[str, np.ndarray] | None:
    """The arrays of entry ``name``, or None when there is none (or it cannot be read)."""
    folder = cache_dir()
    if folder is None or not (folder / name).is_file():
        return None
    try:
        with np.load(folder / name, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile):
        return None


def save(name: str, arrays: dict[str, np.ndarray]) -> None:
    """Store ``arrays`` as entry ``name`` (atomically; silently not when the folder is not writable)."""
    folder = cache_dir()
    if folder is None:
        return
    try:
        with atomic_path(folder / name) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
    except OSError:
        pass
