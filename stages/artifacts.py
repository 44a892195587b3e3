"""Parquet and JSON artifacts with the metadata of DESIGN.md, written atomically.

A Parquet artifact is a table of columns (struct-of-arrays). Its schema metadata holds ``artifact``
(name), ``schema_version``, ``params`` (JSON), ``inputs`` (name -> sha256 of each input file),
``producer``, and ``units``/``frames`` (column -> unit, column -> frame: the same as the fields' own
metadata, which pandas, polars and DuckDB do not show); each field holds ``unit`` and, for geometric
columns, ``frame``. A JSON artifact holds the same under its ``meta`` key. Timings never go into an
artifact: they go to ``<artifact>.timings.json`` beside it, so that reruns with the same inputs are
byte-identical.

Every write goes to a temporary file in the target folder and is renamed into place, so an
interrupted run never leaves a half-written artifact behind.
"""

from __future__ import annotations

import contextlib
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

SCHEMA_VERSION = 1


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
        "producer": f"pivot {__version__}: {producer}",
    }


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success rename it onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


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
    # The units and frames again as schema-level maps: pandas, polars and DuckDB show the schema's metadata
    # but drop the fields'.
    units = {"units": {f.name: f.unit for f in fields}, "frames": {f.name: f.frame for f in fields if f.frame}}
    schema = pa.schema(schema_fields, metadata={k: json.dumps(v, sort_keys=True) for k, v in {**meta, **units}.items()})
    table = pa.Table.from_arrays(arrays, schema=schema)
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
        raise ArtifactError(f"{path}: not a readable Parquet artifact (truncated or corrupt): {e}") from e
    raw = table.schema.metadata or {}
    try:
        meta = {k.decode(): json.loads(v) for k, v in raw.items() if k.decode() != "ARROW:schema"}
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ArtifactError(f"{path}: artifact metadata is not valid JSON") from e
    _check_meta(path, meta, artifact)
    missing = [c for c in (required or []) if c not in table.column_names]
    if missing:
        raise ArtifactError(f"{path}: wrong schema for '{meta['artifact']}': missing columns {missing}")
    cols = {}
    for name in table.column_names:
        col = table.column(name)
        if pa.types.is_list(col.type) or pa.types.is_large_list(col.type):
            cols[name] = np.array([np.asarray(v) for v in col.to_pylist()] + [None], dtype=object)[:-1]
        else:
            cols[name] = col.to_numpy(zero_copy_only=False)
    return Table(cols, meta)


def write_json(path: str | Path, data: Mapping, meta: dict) -> None:
    """Write a JSON artifact ``{"meta": meta, **data}`` (sorted keys, stable float text)."""
    text = json.dumps({"meta": meta, **_jsonable(dict(data))}, indent=1, sort_keys=True) + "\n"
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
    return data


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
IGNORED_META = ("producer",)  # informational: names the command line, not the content


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
