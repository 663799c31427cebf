"""Packed trial records (`DIR/trials.parquet`): round trip, resume, kills, other readers,
reports, corrupt tables and `drake-grasp results pack`. Fast: no Drake simulation."""

import json
import shutil
import struct
from pathlib import Path

import pytest

from drake_grasp.evaluation import records as records_module
from drake_grasp.evaluation import records_table
from drake_grasp.evaluation.records import (TrialRecord, done_trial_ids, find_record,
                                            load_records, pack_records, read_record, record_at,
                                            table_path, trial_path, trial_paths, write_record)
from test_results import make_record

ROOT = Path(__file__).resolve().parents[1]
# A small committed results folder: 62 clutter-shift attempts of Table 1's seed.
COMMITTED = ROOT / "analysis" / "results" / "paper-bn12500-ep3" / "clutter-shift"


def fabricated() -> list[TrialRecord]:
    """Records that stress the columns: None in every optional field, awkward floats,
    nested free-form data, ints that a float column would change, non-ASCII text."""
    return [
        make_record(),
        make_record("isolation/gpd/0001", condition="gpd", policy="gpd", success=False,
                    failure_class="missed", failure_reason="missed: no grasp — ünïcode",
                    final_distance_m=None, grasped_object_id=None, object_ids=[],
                    sim_time_s=0.1 + 0.2, wall_time_s=5e-324, control_steps=0,
                    extra={"scores": [1, 2.0, -0.0, 1e308], "nested": {"a": [None, True]},
                           "big": 2 ** 60}),
        make_record("clutter/ctr/0003/attempt02", experiment="clutter", run_index=3,
                    attempt_index=2, noise="gaussian", noise_scale=0.4, offset_m=-0.0,
                    depth_noise=True, seed=2 ** 62, final_distance_m=1 / 3,
                    disturbance={"kind": "shift", "time_s": 1.2, "dxy_m": [0.03, -0.01]},
                    extra={}, object_ids=["a_000", "b_001", "c_002"]),
    ]


def exact(record: TrialRecord) -> str:
    """A record as text that tells 1 from 1.0 and every float bit apart."""
    return json.dumps(record.to_dict())


def float_bits(record: TrialRecord) -> list:
    return [struct.pack("<d", v) if isinstance(v, float) else v
            for v in record.to_dict().values()]


def test_fabricated_records_round_trip_exactly(tmp_path):
    recs = fabricated()
    for r in recs:
        write_record(tmp_path, r)
    from_files = load_records(tmp_path)
    assert pack_records(tmp_path) == {"folder": str(tmp_path), "rows": 3, "packed": 3}
    assert not (tmp_path / "trials").exists()
    from_table = load_records(tmp_path)
    assert from_table == from_files == sorted(recs, key=lambda r: r.trial_id)
    assert [exact(r) for r in from_table] == [exact(r) for r in from_files]
    assert [float_bits(r) for r in from_table] == [float_bits(r) for r in from_files]
    big = next(r for r in from_table if r.trial_id == "isolation/gpd/0001")
    assert type(big.extra["big"]) is int and str(big.extra["scores"][2]) == "-0.0"


def test_a_committed_folder_round_trips_exactly(tmp_path):
    """A committed run (packed) written back out as one file per trial, the form a run
    writes, and packed again comes back field for field and bit for bit."""
    committed = load_records(COMMITTED)
    folder = tmp_path / "run"
    for r in committed:
        write_record(folder, r)
    files = sorted((folder / "trials").glob("*.json"))
    before = {read_record(f).trial_id: exact(read_record(f)) for f in files}
    assert before == {r.trial_id: exact(r) for r in committed}
    pack_records(folder)
    after = {r.trial_id: exact(r) for r in load_records(folder)}
    assert after == before and len(after) == len(files) > 50
    # A path naming a packed trial still finds it (what the analysis scripts hand around).
    name = files[0]
    assert not name.exists()
    assert exact(record_at(name)) == before[records_module.trial_id_from_stem(name.stem)]
    assert [p.name for p in trial_paths(folder, condition="ctr")] == \
        sorted(f.name for f in files if "__ctr__" in f.name)


def test_resume_reads_table_and_files_and_packs_both(tmp_path):
    recs = [make_record(f"isolation/ctr/{i:04d}", seed=i) for i in range(6)]
    for r in recs[:3]:
        write_record(tmp_path, r)
    pack_records(tmp_path)
    for r in recs[3:]:  # a resumed run adds files beside the table
        write_record(tmp_path, r)
    assert done_trial_ids(tmp_path) == {r.trial_id for r in recs}
    assert load_records(tmp_path) == recs
    assert find_record(tmp_path, recs[1].trial_id) == recs[1]  # from the table
    assert find_record(tmp_path, recs[4].trial_id) == recs[4]  # from its file
    with pytest.raises(ValueError, match="no trial 'isolation/ctr/0099'"):
        find_record(tmp_path, "isolation/ctr/0099")
    assert pack_records(tmp_path)["rows"] == 6
    assert load_records(tmp_path) == recs and not (tmp_path / "trials").exists()
    # A file rewritten for a packed trial wins over its row, and replaces it when packed.
    changed = make_record("isolation/ctr/0001", seed=1, success=False, failure_class="missed")
    write_record(tmp_path, changed)
    assert load_records(tmp_path)[1] == changed and len(load_records(tmp_path)) == 6
    pack_records(tmp_path)
    assert load_records(tmp_path)[1] == changed and len(load_records(tmp_path)) == 6
    assert pack_records(tmp_path) == {"folder": str(tmp_path), "rows": 6, "packed": 0}


def test_a_kill_between_table_and_file_removal_counts_nothing_twice(tmp_path, monkeypatch):
    old = [make_record(f"isolation/ctr/{i:04d}", seed=i) for i in range(2)]
    for r in old:
        write_record(tmp_path, r)
    pack_records(tmp_path)
    new = [make_record(f"isolation/gpd/{i:04d}", condition="gpd", seed=i) for i in range(3)]
    for r in new:
        write_record(tmp_path, r)

    class Killed(BaseException):
        pass

    def die(self, *a, **k):
        raise Killed

    # Killed after the new table's rename, before any file's removal.
    monkeypatch.setattr(Path, "unlink", die)
    with pytest.raises(Killed):
        pack_records(tmp_path)
    monkeypatch.undo()
    assert len(list((tmp_path / "trials").glob("*.json"))) == 3
    assert len(records_table.read_table(table_path(tmp_path), records_module._KINDS)) == 5
    assert load_records(tmp_path) == sorted(old + new, key=lambda r: r.trial_id)
    assert done_trial_ids(tmp_path) == {r.trial_id for r in old + new}
    # Killed before the rename: the old table stands, no temporary file is left.
    monkeypatch.setattr(records_table.os, "replace", die)
    with pytest.raises(Killed):
        pack_records(tmp_path)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["trials", "trials.parquet"]
    assert len(load_records(tmp_path)) == 5
    # Run again, it finishes.
    assert pack_records(tmp_path) == {"folder": str(tmp_path), "rows": 5, "packed": 3}
    assert load_records(tmp_path) == sorted(old + new, key=lambda r: r.trial_id)


def test_plain_parquet_that_other_readers_open(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    for r in fabricated():
        write_record(tmp_path, r)
    pack_records(tmp_path)
    table = pq.read_table(table_path(tmp_path))
    assert table.column_names == list(make_record().to_dict())
    assert not any(isinstance(f.type, pa.ExtensionType) for f in table.schema)
    types = {f.name: f.type for f in table.schema}
    assert types["seed"] == pa.int64() and types["final_distance_m"] == pa.float64()
    assert types["object_ids"] == pa.list_(pa.string()) and types["extra"] == pa.string()
    rows = {row["trial_id"]: row for row in table.to_pylist()}
    assert json.loads(rows["isolation/gpd/0001"]["extra"])["nested"] == {"a": [None, True]}
    assert rows["isolation/gpd/0001"]["final_distance_m"] is None
    try:
        import pandas
    except ImportError:
        return  # pandas is optional; pyarrow's own reading above is the check
    df = pandas.read_parquet(table_path(tmp_path))
    assert list(df["trial_id"]) == sorted(r.trial_id for r in fabricated())
    assert df["success"].tolist() == [True, True, False]


def test_report_is_the_same_before_and_after_packing(tmp_path):
    from drake_grasp.evaluation.report import make_report

    folder = tmp_path / "run"
    shutil.copytree(COMMITTED, folder)
    before = make_report(folder)
    text = (folder / "report.md").read_text()
    pack_records(folder)
    assert not (folder / "trials").exists()
    assert make_report(folder) == before
    assert (folder / "report.md").read_text() == text


def test_a_corrupt_table_is_named(tmp_path):
    write_record(tmp_path, make_record())
    pack_records(tmp_path)
    path = table_path(tmp_path)
    path.write_bytes(path.read_bytes()[:100])
    for read in (load_records, done_trial_ids, pack_records):
        with pytest.raises(ValueError, match=f"{path}: corrupt trial table"):
            read(tmp_path)
    # A Parquet file some other program wrote is not taken for one.
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.table({"trial_id": ["x"]}), path)
    with pytest.raises(ValueError, match=f"{path}: not a trial table"):
        load_records(tmp_path)


def test_a_table_missing_a_column_or_holding_a_trial_twice_is_named(tmp_path):
    kinds = records_module._KINDS
    row = make_record().to_dict()
    records_table.write_table(table_path(tmp_path), [row, row], kinds)
    with pytest.raises(ValueError, match=r"trials\.parquet row 1: trial 'isolation/ctr/0007' "
                                         "is in the table twice"):
        load_records(tmp_path)
    short = {k: v for k, v in kinds.items() if k != "seed"}
    records_table.write_table(table_path(tmp_path), [row], short)
    with pytest.raises(ValueError, match=r"trials\.parquet: trial table columns differ.*"
                                         r"missing: \['seed'\]"):
        load_records(tmp_path)


def test_results_pack_command_finds_nested_folders(tmp_path, capsys):
    from drake_grasp.cli.main import build_parser, main

    for name in ("a/run1", "a/b/run2"):
        for r in fabricated()[:2]:
            write_record(tmp_path / name, r)
    # a label check's folder: run.json and scenes/*.json
    scenes = tmp_path / "a" / "lc" / "scenes"
    scenes.mkdir(parents=True)
    (scenes.parent / "run.json").write_text("{}")
    (scenes / "scene-00000.json").write_text(json.dumps({"format": "f", "scene_index": 0}))
    assert main(["results", "pack", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"{tmp_path / 'a' / 'b' / 'run2'}: 2 trial files" in out
    assert f"{tmp_path / 'a' / 'lc'}: 1 scene files" in out
    assert all((tmp_path / n / "trials").is_dir() for n in ("a/run1", "a/b/run2"))
    assert main(["results", "pack", str(tmp_path / "a"), "--no-progress"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["folders"] == 3 and summary["trial_files_packed"] == 4
    assert summary["scene_files_packed"] == 1 and not scenes.exists()
    assert (scenes.parent / "scenes.parquet").is_file()
    for n in ("a/run1", "a/b/run2"):
        assert not (tmp_path / n / "trials").exists()
        assert load_records(tmp_path / n) == sorted(fabricated()[:2], key=lambda r: r.trial_id)
    assert main(["results", "pack", str(tmp_path / "nowhere")]) == 2
    assert "nowhere: not a folder" in capsys.readouterr().err
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices["results"]
    pack = next(a for a in sub._actions if a.dest == "results_command").choices["pack"]
    assert "trials.parquet" in pack.format_help() and "--dry-run" in pack.format_help()


def test_a_folder_with_only_a_table_holds_a_run(tmp_path):
    from drake_grasp.evaluation.run_folder import folder_conflict

    write_record(tmp_path, make_record())
    pack_records(tmp_path)
    assert "holds trial records but no run.json" in folder_conflict(tmp_path, {"x": 1})
    assert trial_path(tmp_path, "isolation/ctr/0007").parent.name == "trials"


def test_two_packs_of_one_folder_take_turns(tmp_path):
    import threading

    for r in fabricated():
        write_record(tmp_path, r)
    result = {}
    with records_table.folder_lock(tmp_path):
        worker = threading.Thread(target=lambda: result.update(pack_records(tmp_path)))
        worker.start()
        worker.join(0.5)
        assert worker.is_alive() and not table_path(tmp_path).exists()  # waiting its turn
    worker.join(30)
    assert result == {"folder": str(tmp_path), "rows": 3, "packed": 3}
    assert len(load_records(tmp_path)) == 3


def test_a_packed_clutter_attempt_still_replays_from_its_path(tmp_path):
    """`replay.recorded_pile` (what the analysis scripts replay attempts from) takes the
    path of an attempt's file; once its folder is packed, the same path reads the row."""
    from drake_grasp.evaluation.replay import recorded_pile

    folder = tmp_path / "run"
    shutil.copytree(COMMITTED, folder)
    path = folder / "trials" / "clutter-shift__ctr__0000__attempt01.json"
    rec, scenario, scene = recorded_pile(path)
    pack_records(folder)
    assert not path.exists()
    packed, packed_scenario, packed_scene = recorded_pile(path)
    assert json.dumps(packed) == json.dumps({k: v for k, v in rec.items()
                                             if k != "format_version"})
    from pydrake.common.yaml import yaml_dump_typed

    assert yaml_dump_typed(packed_scenario) == yaml_dump_typed(scenario)
    assert packed_scene.to_dict() == scene.to_dict() and scene.objects
