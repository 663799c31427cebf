"""Per-scene records of the label check and the grasp-tolerance study, as files or a table.

A run (`drake-grasp label-check`, `grasp-tolerance`) writes one JSON record per scene under
`OUT/scenes/` while it runs, each atomically: the crash-safe path that lets a killed run
resume. When the run ends, `pack_scene_records` moves them into `OUT/scenes.parquet`,
one row per scene, readable by any Parquet reader:

============  ===============================================================
column        what
============  ===============================================================
scene_index   int64: the scene's index in the run
format        string: the record's format (`drake_grasp.label_check/1`, ...)
record        string: the whole record as compact JSON text (its checks are nested
              lists; read with `json.loads` or DuckDB's `->` / `->>`)
============  ===============================================================

`read_records` and `done_scene_indices` read both forms; a scene in both counts once, as
its file says. The record column is Python's JSON text, as the files are: a NaN in a
record stays `NaN` (which strict JSON readers refuse). The table is written with `records_table.write_table` (hidden temporary
name, fsync, rename), and a file is removed only once the table reads its record back
equal: a kill at any point leaves every scene readable exactly once.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from drake_grasp.evaluation.records_table import (folder_lock, folders_with_files,
                                                  read_table, write_table)

RECORDS = "scenes"
SCENES_TABLE = "scenes.parquet"
# The record column is JSON text written here (Python's JSON: a NaN in a record stays NaN).
_KINDS = {"scene_index": ("int", False), "format": ("str", False), "record": ("str", False)}


def record_path(out: Path, scene_index: int) -> Path:
    """Where scene `scene_index`'s record file lives in a run folder (while it runs)."""
    return Path(out) / RECORDS / f"scene-{scene_index:05d}.json"


def _table_records(out: Path) -> dict[int, dict]:
    path = out / SCENES_TABLE
    if not path.is_file():
        return {}
    found = {}
    for i, row in enumerate(read_table(path, _KINDS)):
        try:
            record = json.loads(row["record"])
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path} row {i}: the record is not JSON text ({e})") from None
        if not isinstance(record, dict) or record.get("scene_index") != row["scene_index"]:
            raise ValueError(f"{path} row {i}: the record does not hold scene "
                             f"{row['scene_index']}")
        if row["scene_index"] in found:
            raise ValueError(f"{path} row {i}: scene {row['scene_index']} is in the table twice")
        found[row["scene_index"]] = record
    return found


def _file_records(out: Path) -> dict[int, tuple[Path, dict]]:
    folder = out / RECORDS
    if not folder.is_dir():
        return {}
    found = {}
    for path in sorted(folder.glob("scene-*.json")):
        try:
            record = json.loads(path.read_text())
        except ValueError as e:
            raise ValueError(f"{path}: not a valid record ({e})") from None
        index = record.get("scene_index") if isinstance(record, dict) else None
        if not isinstance(index, int) or path != record_path(out, index):
            raise ValueError(f"{path}: expected a scene record named by its scene_index, "
                             f"got scene_index {index!r}")
        found[index] = (path, record)
    return found


def read_records(out, num_scenes: int | None = None, *, format: str) -> list[dict]:
    """The scene records of a run folder (the first `num_scenes`, or all), packed or not,
    sorted by scene index, each checked to be of `format`.

    Raises:
        ValueError: A file or the table is corrupt, or a record has another format (named).
    """
    out = Path(out)
    merged = _table_records(out)
    merged.update({i: r for i, (_, r) in _file_records(out).items()})
    records = []
    for i in sorted(merged):
        record = merged[i]
        if record.get("format") != format:
            raise ValueError(f"{out}: scene {i} has format {record.get('format')!r}, "
                             f"expected {format!r}")
        if num_scenes is None or i < num_scenes:
            records.append(record)
    return records


def done_scene_indices(out) -> set[int]:
    """Scenes with a record (table row or file): what a resumed run skips."""
    out = Path(out)
    return set(_table_records(out)) | set(_file_records(out))


def pack_scene_records(out) -> dict:
    """Moves the folder's scene files into `OUT/scenes.parquet` (old rows kept, a file
    replacing its scene's row), then removes each file once the table reads it back
    equal, and the empty `scenes/`.

    Returns:
        {"folder", "rows" (in the table now), "packed" (files removed)}.
    """
    out = Path(out)
    with folder_lock(out):
        files, merged = _file_records(out), _table_records(out)
        if files:
            merged.update({i: r for i, (_, r) in files.items()})
            rows = [{"scene_index": i, "format": str(merged[i].get("format")),
                     "record": json.dumps(merged[i], separators=(",", ":"))}
                    for i in sorted(merged)]
            write_table(out / SCENES_TABLE, rows, _KINDS)
        back = _table_records(out)
        for i, (path, record) in files.items():
            if json.dumps(back.get(i)) != json.dumps(record):
                raise ValueError(f"{path}: its record does not read back equal from "
                                 f"{out / SCENES_TABLE}; the file is kept")
        for path, _ in files.values():
            path.unlink()
        folder = out / RECORDS
        if folder.is_dir() and not any(folder.iterdir()):
            os.rmdir(folder)
        return {"folder": str(out), "rows": len(back), "packed": len(files)}


def unpacked_scene_folders(paths) -> list[tuple[Path, int]]:
    """Run folders under `paths` (searched recursively) whose `scenes/` holds record files
    beside their run.json: (folder, number of files), sorted."""
    return folders_with_files(paths, RECORDS, "scene-*.json", beside="run.json")
