"""The on-disk format of a Monte Carlo results directory (this module alone owns it).

Layout::

    DIR/run.json                 what was run (`run_folder.run_identity`): experiment, base
                                 seed, object library and its content hash, every
                                 condition's resolved scenario without the seed and its
                                 CNN weights' sha256, code version; plus the most trials
                                 asked for and the created time. Written by the runner
                                 before any trial; a resume with another identity is
                                 refused.
    DIR/trials.parquet           the packed records: one row per trial, one column per
                                 `TrialRecord` field (`records_table` has the columns).
                                 Written when an `evaluate` call finishes, and by
                                 `drake-grasp results pack` (`pack_records`).
    DIR/trials/<stem>.json       one finished trial (a `TrialRecord`) not packed yet; <stem>
                                 is the trial id with "/" replaced by "__"
                                 ("isolation/ctr/0007" -> "isolation__ctr__0007.json").
    DIR/replays/<stem>.html      optional Meshcat replay of a trial (written by the runner;
                                 the report links those of failed trials). Kept as files:
                                 a page to open in a browser, and few of them.

The per-trial JSON files are the crash-safe write path while a run goes on: each is
written under a temporary name in the same folder and renamed into place when complete,
so a killed run leaves no half-written record; the driver of a run writes them all
(`montecarlo`: workers return their records), so no two processes contend for a file. A trial counts as done iff it is a
row of the table or its file exists and parses; one in both (a pack killed between the
table's rename and the files' removal) counts once, as its file says (`pack_records`).
Both forms are plain data (no pickle): a results directory from someone else can be read
without running their code.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import asdict, dataclass, field, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from drake_grasp.core.files import atomic_write_text
# Re-exported: reports and analysis scripts import the statistics from here.
from drake_grasp.evaluation.proportions import mcnemar_exact_p, wilson_interval  # noqa: F401
from drake_grasp.evaluation.records_table import (TABLE_FILE, TRIALS_DIR, folder_lock, read_table,
                                                  write_table)

RUN_INFO_FILE = "run.json"
REPLAYS_DIR = "replays"
# Bumped when a field changes meaning or is removed; files carry it as "format_version".
RECORD_FORMAT_VERSION = 1

# Why a grasp episode failed: the classes `drake_grasp.systems.judge.GraspJudge` decides from
# the contact history (see its docstring), plus "timeout" (the policy had not finished when
# the episode's time was up) and "simulation-error" (the simulation raised). The one list
# the judge, the trial records and the report share.
GRASP_FAILURES = ("missed", "pushed-away", "collision", "slipped-during-lift",
                  "slipped-during-hold", "timeout", "simulation-error")
FAILURE_CLASSES = ("none",) + GRASP_FAILURES
# Classes of records written before the contact judge (geometric judge): still readable,
# shown in reports only when a results folder holds them.
LEGACY_FAILURE_CLASSES = ("slipped", "shifted-away")

# Characters allowed in a trial id: file-name safe on every common filesystem once "/" is
# mapped to "__", and unambiguous in Markdown links.
_TRIAL_ID_RE = re.compile(r"^[A-Za-z0-9._=+\-/]+$")


def _json_safe(value: Any, where: str) -> Any:
    """Plain JSON types from numpy scalars/arrays, tuples, paths; non-finite floats -> None.

    Non-finite floats become None because JSON has no NaN/inf (Python writes a non-standard
    token other readers reject), and None already means "not measured" in a record.
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ValueError(f"{where}: dict key {k!r} is not a string (JSON needs string keys)")
            out[k] = _json_safe(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [_json_safe(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    # numpy without importing it: scalars have .item(), arrays .tolist().
    if hasattr(value, "tolist"):
        return _json_safe(value.tolist(), where)
    if hasattr(value, "item"):
        return _json_safe(value.item(), where)
    raise ValueError(f"{where}: value {value!r} of type {type(value).__name__} is not JSON-serializable")


# --------------------------------------------------------------------------- trial ids

def trial_file_stem(trial_id: str) -> str:
    """File-name stem of a trial: "isolation/ctr/0007" -> "isolation__ctr__0007".

    Raises:
        ValueError: The id is empty, has characters outside [A-Za-z0-9._=+-/], or would not
            map back to itself (e.g. it contains "__", or a component starts/ends with "_").
    """
    if not isinstance(trial_id, str) or not trial_id or not _TRIAL_ID_RE.match(trial_id):
        raise ValueError(f"trial_id {trial_id!r}: expected a non-empty string of "
                         "[A-Za-z0-9._=+-/] characters")
    parts = trial_id.split("/")
    if any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"trial_id {trial_id!r}: empty, '.' or '..' path component")
    stem = trial_id.replace("/", "__")
    # The mapping must be reversible so a file name always names one trial.
    if trial_id_from_stem(stem) != trial_id:
        raise ValueError(f"trial_id {trial_id!r}: '__' or components starting/ending with '_' "
                         "make the file name ambiguous")
    return stem


def trial_id_from_stem(stem: str) -> str:
    """Inverse of `trial_file_stem`."""
    return stem.replace("__", "/")


def trial_path(results_dir: str | os.PathLike, trial_id: str) -> Path:
    """`DIR/trials/<stem>.json` of a trial."""
    return Path(results_dir) / TRIALS_DIR / f"{trial_file_stem(trial_id)}.json"


def replay_path(results_dir: str | os.PathLike, trial_id: str) -> Path:
    """`DIR/replays/<stem>.html`: where a trial's replay page belongs (it may not exist)."""
    return Path(results_dir) / REPLAYS_DIR / f"{trial_file_stem(trial_id)}.html"


# --------------------------------------------------------------------------- the record

# Field kinds for validation: (kind, may be None).
_KINDS: dict[str, tuple[str, bool]] = {
    "trial_id": ("str", False), "experiment": ("str", False), "condition": ("str", False),
    "policy": ("str", False), "noise": ("str", False), "noise_scale": ("float", True),
    "depth_noise": ("bool", False), "offset_m": ("float", True),
    "disturbance": ("dict", False), "scenario_name": ("str", False),
    "scenario_yaml": ("str", False), "seed": ("int", False), "config_hash": ("str", False),
    "code_version": ("str", False), "success": ("bool", False),
    "failure_class": ("str", False), "failure_reason": ("str", True),
    "final_distance_m": ("float", True), "sim_time_s": ("float", False),
    "wall_time_s": ("float", False), "control_steps": ("int", False),
    "object_ids": ("list_str", False), "grasped_object_id": ("str", True),
    "run_index": ("int", True), "attempt_index": ("int", True), "extra": ("dict", False),
}


def _check_value(name: str, value: Any, where: str) -> Any:
    """Returns `value` coerced to the field's plain type, or raises a ValueError naming it."""
    kind, optional = _KINDS[name]
    if value is None:
        if optional:
            return None
        raise ValueError(f"{where}: key {name!r} is null; expected {kind}")
    # numpy scalars -> Python (np.float64 passes isinstance float, np.int64/np.bool_ do not).
    if not isinstance(value, (str, dict, list, tuple)) and hasattr(value, "item"):
        value = value.item()
    bad = ValueError(f"{where}: key {name!r} has value {value!r} "
                     f"({type(value).__name__}); expected {kind}{' or null' if optional else ''}")
    if kind == "str":
        if not isinstance(value, str):
            raise bad
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise bad
        return value
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return int(value)
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        value = float(value)
        if not math.isfinite(value):
            if optional:
                return None  # "not measured"; JSON cannot carry NaN
            raise bad
        return value
    if kind == "dict":
        if not isinstance(value, dict):
            raise bad
        return _json_safe(value, f"{where}: key {name!r}")
    if kind == "list_str":
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise bad
        return list(value)
    raise AssertionError(kind)


@dataclass
class TrialRecord:
    """One finished Monte Carlo trial (`DIR/trials/<stem>.json`, or a row of `trials.parquet`).

    Attributes:
        trial_id: Unique within the results dir, e.g. "isolation/ctr/0007".
        experiment: Experiment name, e.g. "isolation", "clutter", "clutter-shift",
            "sim-distance".
        condition: The arm of the experiment: "ctr", "gpd", "ctr_noise", "gpd_noise",
            "init", "cnn-only", "cnn-ctr", or "name=value" for sweeps ("noise_scale=0.4").
        policy: Policy that ran ("ctr", "gpd", "cnn-only", "init", "scripted", ...).
        noise: Kinematic noise model ("none", "gaussian", ...).
        noise_scale: Scale of the kinematic noise (the paper's 0.4); None without noise.
        depth_noise: Whether depth-image noise was on.
        offset_m: Constant kinematic offset [m], None when not used.
        disturbance: What was done to the scene mid-trial, e.g. {"kind": "shift",
            "time_s": 1.2, "dx_m": 0.03}; {} for none.
        scenario_name: Named scenario the trial was built from.
        scenario_yaml: The fully resolved scenario (seed included): replays the trial exactly.
            "" when building the scenario raised (a simulation error).
        seed: The trial's seed.
        config_hash: Hash of the condition's resolved settings without the per-trial parts
            (`run_folder.config_hash`: the seed, and the object and pose chosen per trial),
            so all trials of a condition share it; "unresolved" when the trial's scenario
            could not be built.
        code_version: `drake_grasp.core.provenance.code_version()`: package version plus the
            git commit when run from a checkout ("0.1.0+git.<sha>[+dirty]"), else
            "0.1.0+unknown".
        success: Grasp held through lift and hold (False for INIT trials: no grasp).
        failure_class: One of `FAILURE_CLASSES` (see `classify_failure`).
        failure_reason: Free text from the supervisor / runner; None on success.
        final_distance_m: The paper's Figure 5 metric: (x, y, theta) distance of the gripper
            to the closest true grasp when the fingers start closing [m]; None if unknown.
        sim_time_s: Simulated time [s].
        wall_time_s: Wall-clock time of the trial [s].
        control_steps: Controller iterations taken.
        object_ids: Objects in the scene.
        grasped_object_id: Object lifted, None when none was.
        run_index: Clutter experiments: which run (pile) this attempt belongs to.
        attempt_index: Clutter experiments: attempt number within the run.
        extra: Free-form JSON data (diagnostics); numpy values become lists/numbers.
    """

    trial_id: str
    experiment: str
    condition: str
    policy: str
    noise: str
    noise_scale: float | None
    depth_noise: bool
    offset_m: float | None
    disturbance: dict
    scenario_name: str
    scenario_yaml: str
    seed: int
    config_hash: str
    code_version: str
    success: bool
    failure_class: str
    failure_reason: str | None
    final_distance_m: float | None
    sim_time_s: float
    wall_time_s: float
    control_steps: int
    object_ids: list[str] = field(default_factory=list)
    grasped_object_id: str | None = None
    run_index: int | None = None
    attempt_index: int | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Fail where a bad record is made, not later when a report trips over it.
        where = f"TrialRecord(trial_id={self.trial_id!r})"
        for f in fields(self):
            setattr(self, f.name, _check_value(f.name, getattr(self, f.name), where))
        _check_consistency(self, where)

    def to_dict(self) -> dict:
        """Plain JSON-ready dict with exactly the dataclass fields."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict, *, source: str | os.PathLike | None = None) -> "TrialRecord":
        """Builds a record from `to_dict()` output (or a parsed trial file).

        Args:
            data: The dict. A "format_version" key (as written in files) is accepted.
            source: Where `data` came from (a file), named in errors.

        Raises:
            ValueError: A key is unknown or missing, a value has the wrong type, or the
                file was written by a newer format; the message names `source` and the key.
        """
        where = os.fspath(source) if source is not None else "<dict>"
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected a JSON object, got {type(data).__name__}")
        data = dict(data)
        version = data.pop("format_version", RECORD_FORMAT_VERSION)
        if not isinstance(version, int) or version > RECORD_FORMAT_VERSION:
            raise ValueError(f"{where}: key 'format_version' has value {version!r}; this code "
                             f"reads versions <= {RECORD_FORMAT_VERSION}")
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"{where}: unknown key {unknown[0]!r} in trial record "
                             f"(unknown: {unknown}; expected keys: {names})")
        missing = [n for n in names if n not in data]
        if missing:
            raise ValueError(f"{where}: missing key {missing[0]!r} in trial record (missing: {missing})")
        values = {n: _check_value(n, data[n], where) for n in names}
        record = cls.__new__(cls)
        for n, v in values.items():
            object.__setattr__(record, n, v)
        _check_consistency(record, where)
        return record


def _check_consistency(record: TrialRecord, where: str) -> None:
    trial_file_stem(record.trial_id)  # raises on an id that cannot be a file name
    if record.failure_class not in FAILURE_CLASSES + LEGACY_FAILURE_CLASSES:
        raise ValueError(f"{where}: key 'failure_class' has value {record.failure_class!r}; "
                         f"expected one of {FAILURE_CLASSES}")
    if record.success and record.failure_class != "none":
        raise ValueError(f"{where}: success is true but failure_class is "
                         f"{record.failure_class!r}; expected 'none'")


def classify_failure(success: bool, failure_reason: str | None, *,
                     disturbance: dict | None = None,
                     exception: BaseException | None = None) -> str:
    """The failure class of a trial, one of `FAILURE_CLASSES`.

    The grasp judge (`drake_grasp.systems.judge`) starts every reason with its class
    ("slipped-during-lift: ..."); policies that give up say why in their own words.
    Rules, first match wins (reasons are matched case-insensitively):

    1. success -> "none".
    2. an exception was raised, or the reason starts with "simulation-error",
       "simulation error" or "exception" -> "simulation-error".
    3. reason starts with "init" -> "none". INIT trials ("init: no grasp attempted") only
       measure the starting distance; they attempted no grasp, so no grasp failed. Calling
       them "missed" would pollute failure counts; the report leaves INIT out of success
       tables altogether (their `success` is False).
    4. reason starts with one of `GRASP_FAILURES` (followed by ":", a space or nothing)
       -> that class ("timeout in phase approach" -> "timeout").
    5. reason starts with "slipped" (the geometric judge's words) -> "slipped-during-hold".
    6. reason mentions "collision" -> "collision".
    7. anything else (no reason, "no top-down grasp: ...", "missed: no grasp detected")
       -> "missed".

    Args:
        success: Whether the grasp held.
        failure_reason: The judge's or the policy's reason, None if none was given.
        disturbance: The trial's disturbance dict; kept for callers, no longer used (a
            sheet shift no longer makes its own class: the judge's "pushed-away" says
            when the object moved before the pads closed on it).
        exception: The exception that ended the trial, if any.

    Returns:
        The failure class.
    """
    del disturbance
    if success:
        return "none"
    reason = (failure_reason or "").strip().lower()
    if exception is not None or reason.startswith(("simulation-error", "simulation error",
                                                   "exception")):
        return "simulation-error"
    if reason.startswith("init"):
        return "none"
    for name in sorted(GRASP_FAILURES, key=len, reverse=True):
        if reason == name or reason.startswith((name + ":", name + " ")):
            return name
    if reason.startswith("slipped"):
        return "slipped-during-hold"
    if "collision" in reason:
        return "collision"
    return "missed"


# --------------------------------------------------------------------------- directory I/O

def write_record(results_dir: str | os.PathLike, record: TrialRecord) -> Path:
    """Writes `DIR/trials/<stem>.json` atomically (replacing an earlier file of that trial).

    Returns:
        The file written.
    """
    if not isinstance(record, TrialRecord):
        raise TypeError(f"write_record: expected a TrialRecord, got {type(record).__name__}")
    path = trial_path(results_dir, record.trial_id)
    data = {"format_version": RECORD_FORMAT_VERSION, **record.to_dict()}
    # allow_nan=False: validation already mapped NaN to None; anything left is a bug.
    text = json.dumps(data, indent=1, sort_keys=False, allow_nan=False) + "\n"
    return atomic_write_text(path, text)


def _trial_files(results_dir: Path) -> list[Path]:
    folder = results_dir / TRIALS_DIR
    if not folder.is_dir():
        return []
    # Hidden names are temporary files of writes in progress (or of killed writers).
    return sorted(p for p in folder.iterdir()
                  if p.suffix == ".json" and not p.name.startswith(".") and p.is_file())


def read_record(path: str | os.PathLike) -> TrialRecord:
    """Reads one trial file.

    Raises:
        ValueError: The file is not valid JSON, not a valid record, or its name does not
            match its trial_id; the message names the file.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: corrupt trial record (not valid JSON: {e})") from e
    record = TrialRecord.from_dict(data, source=path)
    if trial_file_stem(record.trial_id) != path.stem:
        raise ValueError(f"{path}: file name does not match its trial_id {record.trial_id!r} "
                         f"(expected {trial_file_stem(record.trial_id)}.json)")
    return record


def table_path(results_dir: str | os.PathLike) -> Path:
    """`DIR/trials.parquet`: the folder's packed records (it may not exist)."""
    return Path(results_dir) / TABLE_FILE


def read_table_records(results_dir: str | os.PathLike) -> list[TrialRecord]:
    """The records packed in `DIR/trials.parquet`, in table order ([] without a table).

    Raises:
        ValueError: The table is corrupt, from a newer format, holds an invalid record or
            one trial twice; the message names the file (and the row).
    """
    path = table_path(results_dir)
    if not path.is_file():
        return []
    records, seen = [], set()
    for i, row in enumerate(read_table(path, _KINDS)):
        record = TrialRecord.from_dict(row, source=f"{path} row {i}")
        if record.trial_id in seen:
            raise ValueError(f"{path} row {i}: trial {record.trial_id!r} is in the table twice")
        seen.add(record.trial_id)
        records.append(record)
    return records


def _loose_records(results_dir: Path) -> dict[str, tuple[Path, TrialRecord]]:  # id: (file, record)
    return {(r := read_record(p)).trial_id: (p, r) for p in _trial_files(results_dir)}


def load_records(results_dir: str | os.PathLike) -> list[TrialRecord]:
    """All finished trials of a results dir, packed (`trials.parquet`) or not
    (`trials/*.json`), sorted by trial_id ([] when there are none). A trial in both forms
    counts once, as its file says.

    Raises:
        ValueError: The table or a trial file is corrupt (named in the message).
    """
    results_dir = Path(results_dir)
    records = {r.trial_id: r for r in read_table_records(results_dir)}
    records.update({k: r for k, (_, r) in _loose_records(results_dir).items()})
    return [records[k] for k in sorted(records)]


def trial_paths(results_dir: str | os.PathLike, *, condition: str | None = None) -> list[Path]:
    """`trial_path` of every finished trial (of `condition`), packed or not, sorted: names
    to hand to workers, each read back with `record_at`."""
    return sorted(trial_path(results_dir, r.trial_id) for r in load_records(results_dir)
                  if condition is None or r.condition == condition)


def find_record(results_dir: str | os.PathLike, trial_id: str) -> TrialRecord:
    """The record of one trial, from its file or the folder's table.

    Raises:
        ValueError: The folder has no such trial, or what holds it is corrupt (named).
    """
    path = trial_path(results_dir, trial_id)
    if path.is_file():
        return read_record(path)
    for record in read_table_records(results_dir):
        if record.trial_id == trial_id:
            return record
    raise ValueError(f"{results_dir}: no trial {trial_id!r} (neither {path} nor a row of "
                     f"{table_path(results_dir)})")


def record_at(path: str | os.PathLike) -> TrialRecord:
    """The record a trial file's path names (`DIR/trials/<stem>.json`): the file, or once
    the folder is packed, the table's row of that trial (`find_record`)."""
    path = Path(path)
    if path.is_file() or path.parent.name != TRIALS_DIR:
        return read_record(path)
    return find_record(path.parent.parent, trial_id_from_stem(path.stem))


def done_trial_ids(results_dir: str | os.PathLike) -> set[str]:
    """Ids of the trials in the table or whose file parses: what a resumed run may skip.

    A corrupt trial file does not count (the trial is run again and its file replaced), so
    this never raises on one; `load_records` does.

    Raises:
        ValueError: The table is corrupt (named in the message): re-running its trials
            would replace a whole run's records, so that is left to a person.
    """
    done = {r.trial_id for r in read_table_records(results_dir)}
    for p in _trial_files(Path(results_dir)):
        try:
            done.add(read_record(p).trial_id)
        except (ValueError, OSError):
            continue
    return done


def _same(a: TrialRecord, b: TrialRecord) -> bool:
    """Equal field by field, types and float bits included (1 != 1.0 here)."""
    return json.dumps(a.to_dict(), allow_nan=False) == json.dumps(b.to_dict(), allow_nan=False)


def pack_records(results_dir: str | os.PathLike) -> dict:
    """Packs the folder's trial files into `DIR/trials.parquet` and removes them.

    The new table (old rows + every file's record, a file replacing its trial's row,
    sorted by trial_id) is written to a temporary name and renamed into place. A file is
    removed only once the table on disk reads back its record equal (types and float bits
    included); then the empty `trials/`. A kill at any point leaves the old table and the
    files, or the new table and files repeating its rows: `load_records` counts each once.

    Returns:
        {"folder", "rows" (in the table now), "packed" (files removed; 0: nothing written)}.

    Raises:
        FileNotFoundError: The folder does not exist.
        ValueError: A file or the table is corrupt, or a file's record does not come back
            equal from the table (named in the message; that file is kept).
    """
    results_dir = Path(results_dir)
    with folder_lock(results_dir):  # one pack of a folder at a time
        loose, old = _loose_records(results_dir), read_table_records(results_dir)
        if not loose:
            return {"folder": str(results_dir), "rows": len(old), "packed": 0}
        merged = {r.trial_id: r for r in old}
        merged.update({k: r for k, (_, r) in loose.items()})
        rows = [merged[k].to_dict() for k in sorted(merged)]
        write_table(table_path(results_dir), rows, _KINDS)
        packed = {r.trial_id: r for r in read_table_records(results_dir)}
        for trial_id, (path, record) in loose.items():
            if trial_id not in packed or not _same(packed[trial_id], record):
                raise ValueError(f"{path}: its record does not read back equal from "
                                 f"{table_path(results_dir)}; the file is kept")
        for path, _ in loose.values():
            path.unlink()
        folder = results_dir / TRIALS_DIR
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
        return {"folder": str(results_dir), "rows": len(packed), "packed": len(loose)}


def write_run_info(results_dir: str | os.PathLike, info: dict) -> Path:
    """Writes `DIR/run.json` atomically.

    Args:
        results_dir: The results dir (created when missing).
        info: Experiment name ("experiment"), resolved settings, code version, ...; JSON
            data. A "created_utc" ISO time is added when absent.

    Returns:
        The file written.
    """
    if not isinstance(info, dict):
        raise TypeError(f"write_run_info: expected a dict, got {type(info).__name__}")
    data = _json_safe(dict(info), f"{Path(results_dir) / RUN_INFO_FILE}")
    data.setdefault("created_utc", datetime.now(timezone.utc).isoformat(timespec="seconds"))
    return atomic_write_text(Path(results_dir) / RUN_INFO_FILE,
                             json.dumps(data, indent=1, allow_nan=False) + "\n")


def read_run_info(results_dir: str | os.PathLike) -> dict:
    """Reads `DIR/run.json`.

    Raises:
        FileNotFoundError: There is no run.json (named in the message).
        ValueError: It is not a JSON object (named in the message).
    """
    path = Path(results_dir) / RUN_INFO_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no run info (written by the runner at start)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: corrupt run info (not valid JSON: {e})") from e
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data
