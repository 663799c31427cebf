"""The Parquet table of a results folder's trial records (`DIR/trials.parquet`).

A finished run's records are packed into one plain Parquet file, one row per trial, instead
of one JSON file per trial (`records.pack_records` decides what goes in; this module only
encodes and decodes rows). Any Parquet reader opens it (pyarrow, pandas, polars, DuckDB):
no extension types, one column per `TrialRecord` field, named as the field:

==========  ==========================================================================
kind        column
==========  ==========================================================================
str         string (required, or optional where the field may be None)
bool        boolean
int         int64
float       float64 (null where the record has None): the JSON files' doubles bit for bit
list_str    list<string>
dict        string holding the field as compact JSON (`disturbance`, `extra`): free-form
            data with no fixed schema; read it with `json.loads` (or DuckDB's `->>`)
==========  ==========================================================================

The file's key-value metadata has `drake_grasp.trial_table` = {"format_version": N,
"json_columns": [...]}, so a table from a newer writer is refused rather than misread.
Files are written under a hidden temporary name in the same folder, flushed to disk and
renamed into place: a reader sees the old table or the new one, never half of one.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

TABLE_FILE = "trials.parquet"
TRIALS_DIR = "trials"  # the folder of the per-trial JSON files not packed yet
# Bumped when a column changes meaning or type; the file's metadata carries it.
TABLE_FORMAT_VERSION = 1
_META_KEY = b"drake_grasp.trial_table"


def _arrow_type(kind: str):
    import pyarrow as pa

    return {"str": pa.string(), "bool": pa.bool_(), "int": pa.int64(), "float": pa.float64(),
            "list_str": pa.list_(pa.string()), "dict": pa.string()}[kind]


def table_schema(kinds: dict[str, tuple[str, bool]]):
    """The Arrow schema of a table whose fields have `kinds` ({name: (kind, may be None)},
    kinds as in the module docstring), with the format metadata."""
    import pyarrow as pa

    meta = {"format_version": TABLE_FORMAT_VERSION,
            "json_columns": [n for n, (k, _) in kinds.items() if k == "dict"]}
    return pa.schema([pa.field(n, _arrow_type(k), nullable=opt) for n, (k, opt) in kinds.items()],
                     metadata={_META_KEY: json.dumps(meta).encode()})


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # a filesystem that cannot open folders: the rename is all there is
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike):
    """Holds an exclusive advisory lock (flock) on the folder itself while the block runs,
    so that two packs of one folder (a finishing `evaluate` and `drake-grasp results pack`)
    take turns instead of one table replacing rows the other had just packed. No lock file
    is left behind; where flock does not exist (not POSIX) the block runs unlocked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def write_table(path: str | os.PathLike, rows: list[dict[str, Any]],
                kinds: dict[str, tuple[str, bool]]) -> Path:
    """Writes `rows` (plain dicts with exactly the keys of `kinds`) as a Parquet table,
    atomically: a hidden temporary file beside `path`, fsync, rename, fsync of the folder.

    Raises:
        ValueError: A row's value does not fit its column (the message names the file, the
            row's trial_id and the column).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    schema = table_schema(kinds)
    columns = {n: [] for n in kinds}
    for row in rows:
        for name, (kind, _) in kinds.items():
            value = row[name]
            if kind == "dict":
                value = json.dumps(value, separators=(",", ":"), allow_nan=False)
            columns[name].append(value)
    arrays = []
    for f in schema:
        try:
            arrays.append(pa.array(columns[f.name], type=f.type))
        except (pa.ArrowException, OverflowError, TypeError) as e:
            raise ValueError(f"{path}: column {f.name!r} cannot hold the records' values "
                             f"({e})") from e
    table = pa.Table.from_arrays(arrays, schema=schema)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        pq.write_table(table, tmp, compression="zstd")
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(path.parent)
    return path


def _format_meta(path: Path, schema) -> dict:
    raw = (schema.metadata or {}).get(_META_KEY)
    if raw is None:
        raise ValueError(f"{path}: not a trial table (no {_META_KEY.decode()!r} metadata; "
                         "written by `drake-grasp results pack` or `evaluate`)")
    try:
        meta = json.loads(raw)
        version = meta["format_version"]
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: corrupt trial table metadata {raw[:80]!r}") from e
    if not isinstance(version, int) or version > TABLE_FORMAT_VERSION:
        raise ValueError(f"{path}: table format_version {version!r}; this code reads "
                         f"versions <= {TABLE_FORMAT_VERSION}")
    return meta


def read_table(path: str | os.PathLike, kinds: dict[str, tuple[str, bool]]) -> list[dict]:
    """Reads a table written by `write_table` back into plain dicts (JSON columns parsed).

    Raises:
        ValueError: The file is not a readable Parquet file, not a trial table, from a newer
            format, or lacks/adds a column; the message names the file.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as e:
        if isinstance(e, FileNotFoundError):
            raise
        raise ValueError(f"{path}: corrupt trial table (not a readable Parquet file: {e})") from e
    _format_meta(path, table.schema)
    names = list(table.column_names)
    missing = [n for n in kinds if n not in names]
    unknown = [n for n in names if n not in kinds]
    if missing or unknown:
        raise ValueError(f"{path}: trial table columns differ from the record's fields "
                         f"(missing: {missing}; unknown: {unknown})")
    rows = table.select(list(kinds)).to_pylist()
    for i, row in enumerate(rows):
        for name, (kind, _) in kinds.items():
            if kind == "dict":
                try:
                    row[name] = json.loads(row[name])
                except (TypeError, ValueError) as e:
                    raise ValueError(f"{path}: row {i} ({row.get('trial_id')!r}): column "
                                     f"{name!r} is not JSON text ({e})") from e
    return rows


def folders_with_files(paths: list[str | os.PathLike], subdir: str, pattern: str, *,
                       beside: str = "") -> list[tuple[Path, int]]:
    """Folders under `paths` (each searched recursively) whose `subdir/` holds files
    matching `pattern` (hidden names left out: writes in progress), with `beside` next to
    `subdir` when given: (folder, number of files), sorted by folder.

    Raises:
        FileNotFoundError: A path is not a folder (named in the message).
    """
    found = {}
    for root in map(Path, paths):
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: not a folder")
        for here, dirs, _ in os.walk(root):
            here = Path(here)
            if here.name == subdir:
                n = sum(1 for f in here.glob(pattern) if not f.name.startswith(".")
                        and f.is_file())
                if n and (not beside or (here.parent / beside).is_file()):
                    found[here.parent] = n
                dirs.clear()  # record files only below
            else:
                dirs.sort()
    return sorted(found.items())


def unpacked_folders(paths: list[str | os.PathLike]) -> list[tuple[Path, int]]:
    """Results folders under `paths` (each a folder, searched recursively) that hold trial
    files not packed yet: (folder, number of `trials/*.json`), sorted by folder.

    Raises:
        FileNotFoundError: A path is not a folder (named in the message).
    """
    return folders_with_files(paths, TRIALS_DIR, "*.json")
