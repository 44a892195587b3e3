"""Parquet and JSON artifacts with the metadata of DESIGN.md, written atomically.

A Parquet artifact is a table of columns (struct-of-arrays). Its schema metadata holds ``artifact``
(name), ``schema_version``, ``params`` (JSON), ``inputs`` (name -> sha256 of each input file),
``producer``, and ``units``/``frames`` (column -> unit, column -> frame: the same as the fields' own
metadata, which pandas, polars and DuckDB do not show); each field holds ``unit`` and, for geometric
columns, ``frame``. A JSON artifact holds the same under its ``meta`` key. Timings never go into an
artifact: they go to ``<artifact>.timings.json`` beside it, so that reruns with the same inputs are
byte-identical.

Every write goes to a temporary file in the target folder and is renamed into place (with the mode
the umask gives a new file), so an interrupted run never leaves a half-written artifact behind; a
stage holds :func:`output_lock` on its output while it writes, so two runs never mix one folder.

Artifacts cannot lie (issue 17): a table is checked on read against :data:`SCHEMAS` (columns, types,
finite values, ids >= -1); a JSON artifact carries the sha256 of its content, so a hand edit is
refused; :func:`check_inputs` refuses an artifact made from other inputs than the ones given now.
Paths never enter an artifact (inputs are content hashes, the producer names files relative to the
working folder), so two checkouts at different paths write byte-identical artifacts.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import tempfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from stages import __version__
from stages.errors import ArtifactError

SCHEMA_VERSION = 2

# Column kinds of the pipeline's tables, checked on read: "f" finite float, "f~" float that may be
# infinite (never NaN), "i" integer, "id" integer id (>= -1, -1 meaning none), "b" bool, "s" string,
# "[f]" list of finite floats, "[id]" list of ids. A table may hold more columns than listed here.
_POSE = {k: "f" for k in ("x", "y", "z", "qx", "qy", "qz", "qw")}
SCHEMAS: dict[str, dict[str, str]] = {
    "hull": {"hull_id": "id", "kind": "s", "v0": "id", "v1": "id", "x0": "f", "y0": "f", "z0": "f", "x1": "f",
             "y1": "f", "z1": "f", "face_a": "id", "face_b": "id", "angle": "f"},
    "placements": {"placement_id": "id", "nx": "f", "ny": "f", "nz": "f", "area": "f", **_POSE, "stable": "b",
                   "margin": "f", "com_height": "f", "support_vertices": "[id]", "polygon": "[f]"},
    "segments": {"facet_id": "id", "seed": "id", "triangles": "[id]", "nx": "f", "ny": "f", "nz": "f", "area": "f",
                 "cx": "f", "cy": "f", "cz": "f", "contact_surface": "b", "boundary": "[id]"},
    "contacts": {"contact_id": "id", "facet_id": "id", "triangle": "id", "px": "f", "py": "f", "pz": "f",
                 "nx": "f", "ny": "f", "nz": "f"},
    "pairs": {"pair_id": "id", "contact_a": "id", "contact_b": "id", "facet_a": "id", "facet_b": "id",
              "width": "f", "angle": "f", "mx": "f", "my": "f", "mz": "f"},
    "poses": {"pose_id": "id", **_POSE, "placement_id": "id", "support": "s", "status": "s", "parent": "id",
              "primitive": "s", "vertex": "id", "edge_v0": "id", "edge_v1": "id", "angle": "f", "margin": "f~"},
    "pose_links": {"link_id": "id", "pose_a": "id", "pose_b": "id", "primitive": "s", "vertex": "id",
                   "edge_v0": "id", "edge_v1": "id", "angle": "f"},
    "grasps": {"grasp_id": "id", "pose_id": "id", "pair_id": "id", "contact_left": "id", "contact_right": "id",
               "margin": "f", "hold_left": "b", "hold_right": "b", "pivot_vertices": "[id]", "q_left": "[f]",
               "q_right": "[f]"},
    "grasp_rejects": {"pose_id": "id", "pair_id": "id", "reason": "s"},
    "nodes": {"node_id": "id", "kind": "s", "pose_id": "id", "grasp_id": "id", "support": "s"},
    "edges": {"edge_id": "id", "node_a": "id", "node_b": "id", "primitive": "s", "weight": "f", "status": "s",
              "directed": "b", "vertex": "id", "edge_v0": "id", "edge_v1": "id", "arm": "s"},
    "catches": {"node_id": "id", "kind": "s", "pose_id": "id", "arm": "s", "contact": "id", "status": "s",
                "q": "[f]"},
    "trajectories": {"step": "id", "t": "f", "primitive": "id", "kind": "s", "phase": "s", **_POSE,
                     **{f"{b}{ax}": "f" for b in ("l", "r", "fl", "fr", "f0") for ax in "xyz"},
                     "tilt": "f", "yaw": "f", "tilt_ref": "f", "yaw_ref": "f", "q_left": "[f]", "q_right": "[f]",
                     "left_contact": "b", "right_contact": "b"},
    "execution": {"t": "f", "primitive": "id", "kind": "s", **_POSE, **{f"plan_{k}": "f" for k in _POSE},
                  "q_left": "[f]", "q_right": "[f]"},
}


@dataclass(frozen=True)
class Field:
    """One column: name, unit (SI symbol, ``"1"`` for dimensionless, ``"id"`` for ids), frame."""

    name: str
    unit: str = "1"
    frame: str | None = None


@dataclass(frozen=True)
class Table:
    """A read artifact: columns as numpy arrays (list columns as object arrays) and its metadata."""

    columns: dict[str, np.ndarray]
    meta: dict

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def make_meta(artifact: str, params: Mapping, inputs: Mapping[str, str | Path], producer: str) -> dict:
    """Metadata dict for an artifact; ``inputs`` maps a name to a file path, stored as its sha256."""
    return {
        "artifact": artifact,
        "schema_version": SCHEMA_VERSION,
        "params": _jsonable(dict(params)),
        "inputs": {k: sha256_file(v) for k, v in sorted(inputs.items())},
        "producer": f"pivot {__version__}: {portable(producer)}",
    }


def portable(text: str) -> str:
    """``text`` with each absolute path in it written relative to the working folder (its file name
    when it lies outside), so that an artifact does not depend on where the checkout lies."""
    cwd = Path.cwd()
    words = []
    for w in text.split(" "):
        p = Path(w)
        if p.is_absolute():
            w = str(p.relative_to(cwd)) if p.is_relative_to(cwd) else p.name
        words.append(w)
    return " ".join(words)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success rename it onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a new file gets what the umask allows
        try:
            os.replace(tmp, path)
        except OSError as e:  # e.g. a folder in the way: name the target, not the temporary file
            raise ArtifactError(f"{path}: cannot write it ({e.strerror})") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def output_lock(path: str | Path) -> Iterator[None]:
    """Hold an exclusive lock on the output ``path`` (a folder or a file) while a stage writes it.

    The lock is the file ``.<name>.lock`` beside ``path`` (``flock``, released when the process dies);
    a second writer raises ``ArtifactError`` at once, so two runs never mix one output. The lock file
    is removed on release; a writer that locked a removed lock file tries again.
    """
    path = Path(path)
    lock = path.parent / f".{path.name}.lock"
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno in (errno.EAGAIN, errno.EACCES):
                raise ArtifactError(f"{path}: another pivot is writing it (lock {lock}); let it finish") from None
            raise
        try:
            if os.path.exists(lock) and os.stat(lock).st_ino == os.fstat(fd).st_ino:
                break
        except OSError:
            pass
        os.close(fd)  # the holder removed this lock file before we got it: take the new one
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


def write_table(path: str | Path, columns: Mapping[str, np.ndarray], fields: list[Field], meta: dict) -> None:
    """Write ``columns`` as a Parquet artifact with per-field ``unit``/``frame`` and schema metadata.

    ``fields`` fixes the column order and must name every column. List-valued columns are given as
    sequences of 1-D arrays (one per row).
    """
    names = [f.name for f in fields]
    if set(names) != set(columns):
        raise ValueError(f"fields {sorted(names)} do not match columns {sorted(columns)}")
    arrays, schema_fields = [], []
    for f in fields:
        arr = _to_arrow(columns[f.name])
        md = {"unit": f.unit}
        if f.frame:
            md["frame"] = f.frame
        schema_fields.append(pa.field(f.name, arr.type, metadata=md))
        arrays.append(arr)
    table = pa.Table.from_arrays(arrays, schema=pa.schema(schema_fields))
    # The units and frames again as schema-level maps: pandas, polars and DuckDB show the schema's metadata
    # but drop the fields'.
    units = {"units": {f.name: f.unit for f in fields}, "frames": {f.name: f.frame for f in fields if f.frame}}
    meta = {**meta, **units, "content": _table_digest(table)}
    table = table.replace_schema_metadata({k: json.dumps(v, sort_keys=True) for k, v in meta.items()})
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd", write_statistics=False)


def read_table(path: str | Path, artifact: str | None = None, required: list[str] | None = None) -> Table:
    """Read a Parquet artifact, checking it exists, parses, is ``artifact`` and has ``required`` columns."""
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: missing artifact (run the stage that writes it first)")
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as e:
        raise ArtifactError(f"{path}: not a readable Parquet artifact (truncated or corrupt)") from e
    raw = table.schema.metadata or {}
    try:
        meta = {k.decode(): json.loads(v) for k, v in raw.items() if k.decode() != "ARROW:schema"}
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ArtifactError(f"{path}: artifact metadata is not valid JSON") from e
    _check_meta(path, meta, artifact)
    missing = [c for c in (required or []) if c not in table.column_names]
    if missing:
        raise ArtifactError(f"{path}: wrong schema for '{meta['artifact']}': missing columns {missing}")
    _check_columns(path, table, SCHEMAS.get(meta["artifact"], {}))
    if meta.get("content") != _table_digest(table):
        raise ArtifactError(f"{path}: its content does not match its sha256 (edited by hand?); rerun its stage")
    cols = {}
    for name in table.column_names:
        col = table.column(name)
        try:
            if pa.types.is_list(col.type) or pa.types.is_large_list(col.type):
                cols[name] = np.array([np.asarray(v) for v in col.to_pylist()] + [None], dtype=object)[:-1]
            else:
                cols[name] = col.to_numpy(zero_copy_only=False)
        except (pa.ArrowException, ValueError, TypeError) as e:
            raise ArtifactError(f"{path}: column {name} cannot be read ({type(e).__name__})") from e
    return Table(cols, meta)


_KIND_NAMES = {"f": "floats", "f~": "floats", "i": "integers", "id": "integer ids", "b": "bools", "s": "strings",
               "[f]": "lists of floats", "[id]": "lists of integer ids"}


def _check_columns(path: Path, table: pa.Table, schema: Mapping[str, str]) -> None:
    """Refuse a table whose columns are missing, of another type, NaN, infinite or ids below -1."""
    missing = [c for c in schema if c not in table.column_names]
    if missing:
        raise ArtifactError(f"{path}: missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
                            f"(found {', '.join(table.column_names)})")
    for name, kind in schema.items():
        col = table.column(name)
        values = col
        if kind.startswith("["):
            if not (pa.types.is_list(col.type) or pa.types.is_large_list(col.type) or
                    (pa.types.is_null(col.type) and len(col) == 0)):
                raise ArtifactError(f"{path}: column {name} is {col.type}, not {_KIND_NAMES[kind]}")
            values = pa.chunked_array([c.flatten() for c in col.chunks], type=None) if len(col) else None
            if values is not None and col.null_count:
                raise ArtifactError(f"{path}: column {name} has {col.null_count} missing values")
            kind = kind[1:-1]
        if values is None or (pa.types.is_null(values.type) and len(values) == 0):
            continue
        _check_values(path, name, values, kind)


def _check_values(path: Path, name: str, values: pa.ChunkedArray, kind: str) -> None:
    t = values.type
    ok = {"f": pa.types.is_floating, "f~": pa.types.is_floating, "i": pa.types.is_integer, "id": pa.types.is_integer,
          "b": pa.types.is_boolean, "s": lambda t: pa.types.is_string(t) or pa.types.is_large_string(t)}[kind](t)
    if not ok:
        raise ArtifactError(f"{path}: column {name} is {t}, not {_KIND_NAMES[kind]}")
    if values.null_count:
        raise ArtifactError(f"{path}: column {name} has {values.null_count} missing values")
    if kind in ("f", "f~"):
        x = values.to_numpy()
        bad = np.isnan(x) if kind == "f~" else ~np.isfinite(x)
        if bad.any():
            raise ArtifactError(f"{path}: column {name} has {int(bad.sum())} non-finite values "
                                f"(first at row {int(np.argmax(bad))})")
    elif kind == "id":
        x = values.to_numpy()
        if len(x) and x.min() < -1:
            raise ArtifactError(f"{path}: column {name} has the id {int(x.min())} (ids are >= -1)")


def read_meta(path: str | Path, artifact: str | None = None) -> dict:
    """The metadata of a Parquet or JSON artifact (checked as by :func:`read_table`/:func:`read_json`,
    without reading a table's columns)."""
    path = Path(path)
    if path.suffix == ".json":
        return read_json(path, artifact)["meta"]
    if not path.is_file():
        raise ArtifactError(f"{path}: missing artifact (run the stage that writes it first)")
    try:
        raw = pq.read_schema(path).metadata or {}
        meta = {k.decode(): json.loads(v) for k, v in raw.items() if k.decode() != "ARROW:schema"}
    except (OSError, pa.ArrowException, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ArtifactError(f"{path}: not a readable Parquet artifact (truncated or corrupt)") from e
    _check_meta(path, meta, artifact)
    return meta


def write_json(path: str | Path, data: Mapping, meta: dict) -> None:
    """Write a JSON artifact ``{"meta": meta, **data}`` (sorted keys, stable float text)."""
    body = _jsonable(dict(data))
    text = json.dumps({"meta": {**meta, "content": _digest(body)}, **body}, indent=1, sort_keys=True) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def read_json(path: str | Path, artifact: str | None = None) -> dict:
    """Read a JSON artifact, checking it exists, parses and is ``artifact``."""
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: missing artifact (run the stage that writes it first)")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ArtifactError(f"{path}: not a valid JSON artifact (truncated or corrupt): {e}") from e
    if not isinstance(data, dict) or not isinstance(data.get("meta"), dict):
        raise ArtifactError(f"{path}: not a pivot artifact (no 'meta' block)")
    _check_meta(path, data["meta"], artifact)
    body = {k: v for k, v in data.items() if k != "meta"}
    if data["meta"].get("content") != _digest(body):
        raise ArtifactError(f"{path}: its content does not match its sha256 (edited by hand?); rerun its stage")
    return data


def _table_digest(table: pa.Table) -> str:
    """sha256 of a table's columns: names, types, null masks and values (not its metadata)."""
    h = hashlib.sha256()
    for name in table.column_names:
        col = table.column(name).combine_chunks()
        h.update(f"{name}:{len(col)}:{col.null_count};".encode())
        while pa.types.is_list(col.type) or pa.types.is_large_list(col.type):  # Parquet renames list items
            lengths = col.value_lengths().fill_null(-1).to_numpy(zero_copy_only=False).astype(np.int64)
            h.update(b"list;" + lengths.tobytes())
            col = col.flatten()
        h.update(f"{col.type};".encode())
        if col.null_count:  # the mask, then the values that are there
            h.update(col.is_null().to_numpy(zero_copy_only=False).tobytes())
            col = col.drop_null()
        if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
            h.update("\0".join(col.to_pylist()).encode())
        elif not pa.types.is_null(col.type):
            h.update(np.ascontiguousarray(col.to_numpy(zero_copy_only=False)).tobytes())
    return h.hexdigest()


def _digest(body: Mapping) -> str:
    """sha256 of a JSON artifact's content (everything but ``meta``) in a canonical text form."""
    text = json.dumps(body, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


_HASHES: dict[tuple, str] = {}


def check_inputs(path: str | Path, meta: Mapping, given: Mapping[str, str | Path]) -> None:
    """Refuse the artifact ``path`` unless it was made from the files ``given`` (name -> file) now.

    Compares the sha256 that ``meta["inputs"]`` recorded for each name with the file's; a stale or
    foreign upstream (another mesh, scene or analysis) raises ``ArtifactError`` naming both files.
    """
    recorded = meta.get("inputs", {})
    for name, file in given.items():
        if name not in recorded:
            raise ArtifactError(f"{path}: records no '{name}' input, so it cannot vouch for {file}; rerun its stage")
        if recorded[name] != _cached_sha256(Path(file)):
            raise ArtifactError(f"{path} was made from another {name} than {file}; rerun the stage that writes it")


def _cached_sha256(path: Path) -> str:
    try:
        st = path.stat()
    except OSError as e:
        raise ArtifactError(f"{path}: cannot read it ({e.strerror})") from None
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino)
    if key not in _HASHES:
        _HASHES[key] = sha256_file(path)
    return _HASHES[key]


def write_timings(artifact_path: str | Path, timings: Mapping[str, float]) -> None:
    """Write ``<artifact>.timings.json`` beside an artifact (seconds; never diffed)."""
    p = Path(artifact_path)
    text = json.dumps({k: round(float(v), 6) for k, v in timings.items()}, indent=1) + "\n"
    with atomic_path(p.with_name(p.name + ".timings.json")) as tmp:
        tmp.write_text(text)


def _check_meta(path: Path, meta: dict, artifact: str | None) -> None:
    if "artifact" not in meta or "schema_version" not in meta:
        raise ArtifactError(f"{path}: not a pivot artifact (no artifact/schema_version metadata)")
    if artifact is not None and meta["artifact"] != artifact:
        raise ArtifactError(f"{path}: expected a '{artifact}' artifact, found '{meta['artifact']}'")
    if meta["schema_version"] != SCHEMA_VERSION:
        raise ArtifactError(
            f"{path}: schema version {meta['schema_version']} is not {SCHEMA_VERSION}; rerun its stage"
        )


def _to_arrow(values) -> pa.Array:
    if isinstance(values, np.ndarray) and values.dtype != object:
        if values.ndim != 1:
            raise ValueError("columns must be 1-D; split vectors into x/y/z columns or use list columns")
        return pa.array(values)
    rows = [np.asarray(v) for v in values]
    if rows and rows[0].dtype.kind == "f":
        return pa.array([r.astype(np.float64).ravel() for r in rows], type=pa.list_(pa.float64()))
    if rows and rows[0].dtype.kind in "iub":
        return pa.array([r.astype(np.int64).ravel() for r in rows], type=pa.list_(pa.int64()))
    if rows and rows[0].dtype.kind in "US":
        return pa.array([str(r) for r in rows], type=pa.string())
    return pa.array([r.tolist() for r in rows])


def _jsonable(obj):
    """Plain-JSON copy of params: numpy scalars/arrays to Python, tuples to lists, paths to str."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


# --------------------------------------------------------------------------------------------- diff
IGNORED_META = ("producer", "content")  # the command line; the exact hash of what is compared with tolerances


def diff_artifacts(a: str | Path, b: str | Path, rtol: float = 1e-9, atol: float = 1e-9,
                   only: str | None = None) -> list[str]:
    """Differences between two artifacts (files) or two folders of artifacts, as short lines.

    Parquet columns are compared with ``numpy.isclose(rtol, atol)`` for floats and exactly otherwise;
    JSON values likewise, recursively. Timings files and the ``producer`` field are ignored. An
    empty list means equal. ``only``: compare just this top-level key of two JSON artifacts (e.g. the
    ``steps`` of two plans made with different flags).
    """
    a, b = Path(a), Path(b)
    if only is not None:
        if a.suffix != ".json" or b.suffix != ".json":
            raise ArtifactError(f"{a} / {b}: --only compares a key of two .json artifacts")
        da, db = read_json(a), read_json(b)
        missing = [str(p) for p, d in ((a, da), (b, db)) if only not in d]
        if missing:
            raise ArtifactError(f"{', '.join(missing)}: no key {only!r}")
        return _diff_values(da[only], db[only], only, rtol, atol)
    if a.is_dir() and b.is_dir():
        names = sorted({p.name for d in (a, b) for p in d.iterdir() if _is_artifact(p)})
        out = []
        for name in names:
            if not (a / name).exists() or not (b / name).exists():
                out.append(f"{name}: only in {a if (a / name).exists() else b}")
                continue
            out += [f"{name}: {line}" for line in diff_artifacts(a / name, b / name, rtol, atol)]
        return out
    if a.suffix != b.suffix or a.suffix not in (".parquet", ".json"):
        raise ArtifactError(f"{a} / {b}: can only compare two .parquet or two .json artifacts (or two folders)")
    if a.suffix == ".json":
        da, db = read_json(a), read_json(b)
        for d in (da, db):
            for k in IGNORED_META:
                d["meta"].pop(k, None)
        return _diff_values(da, db, "", rtol, atol)
    ta, tb = read_table(a), read_table(b)
    out = _diff_values({k: v for k, v in ta.meta.items() if k not in IGNORED_META},
                       {k: v for k, v in tb.meta.items() if k not in IGNORED_META}, "meta", rtol, atol)
    if len(ta) != len(tb):
        out.append(f"rows: {len(ta)} != {len(tb)}")
        return out
    for name in sorted(set(ta.columns) | set(tb.columns)):
        if name not in ta.columns or name not in tb.columns:
            out.append(f"column {name}: only in {a if name in ta.columns else b}")
            continue
        ca, cb = ta[name], tb[name]
        if ca.dtype == object:
            bad = [i for i in range(len(ca)) if not _close(ca[i], cb[i], rtol, atol)]
        else:
            bad = np.flatnonzero(~_close_elementwise(ca, cb, rtol, atol))
        if len(bad):
            out.append(f"column {name}: {len(bad)} of {len(ca)} rows differ (first at row {bad[0]})")
    return out


def _is_artifact(p: Path) -> bool:
    return p.suffix in (".parquet", ".json") and not p.name.endswith(".timings.json")


def _close_elementwise(x: np.ndarray, y: np.ndarray, rtol: float, atol: float) -> np.ndarray:
    if x.dtype.kind == "f" or y.dtype.kind == "f":
        return np.isclose(x.astype(float), y.astype(float), rtol=rtol, atol=atol, equal_nan=True)
    return np.asarray(x == y)


def _close(x, y, rtol: float, atol: float) -> bool:
    x, y = np.asarray(x), np.asarray(y)
    return x.shape == y.shape and bool(np.all(_close_elementwise(x, y, rtol, atol)))


def _diff_values(x, y, where: str, rtol: float, atol: float) -> list[str]:
    if isinstance(x, dict) and isinstance(y, dict):
        out = []
        for k in sorted(set(x) | set(y)):
            w = f"{where}.{k}" if where else str(k)
            if k not in x or k not in y:
                out.append(f"{w}: only in one")
            else:
                out += _diff_values(x[k], y[k], w, rtol, atol)
        return out
    if isinstance(x, list) and isinstance(y, list):
        if len(x) != len(y):
            return [f"{where}: length {len(x)} != {len(y)}"]
        return [line for i, (u, v) in enumerate(zip(x, y, strict=True))
                for line in _diff_values(u, v, f"{where}[{i}]", rtol, atol)]
    num = (int, float)
    if isinstance(x, num) and isinstance(y, num) and not isinstance(x, bool) and not isinstance(y, bool):
        return [] if np.isclose(x, y, rtol=rtol, atol=atol) else [f"{where}: {x} != {y}"]
    return [] if x == y else [f"{where}: {x!r} != {y!r}"]
