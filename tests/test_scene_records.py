"""evaluation/scene_records: a label check's (or grasp tolerance's) per-scene records as
files while it runs and as one Parquet table once packed, read the same either way."""

import json

import pyarrow.parquet as pq
import pytest

from drake_grasp.evaluation.scene_records import (SCENES_TABLE, done_scene_indices,
                                                  pack_scene_records, read_records, record_path,
                                                  unpacked_scene_folders)

FORMAT = "drake_grasp.label_check/1"


def _write(out, index, held=True, fmt=FORMAT):
    path = record_path(out, index)
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"format": fmt, "scene_index": index, "seed": 7,
              "checks": [{"kind": "accepted", "held": held, "X_WG": [[0.1, -0.0, 1e-17]]}],
              "wall_s": 0.1 + index}
    path.write_text(json.dumps(record))
    return record


def test_pack_moves_the_files_into_one_table_read_back_equal(tmp_path):
    out = tmp_path / "run"
    (out).mkdir()
    (out / "run.json").write_text("{}")
    records = [_write(out, i, held=i % 2 == 0) for i in (2, 0, 1)]
    before = read_records(out, format=FORMAT)
    assert [r["scene_index"] for r in before] == [0, 1, 2]
    assert unpacked_scene_folders([tmp_path]) == [(out, 3)]
    assert pack_scene_records(out) == {"folder": str(out), "rows": 3, "packed": 3}
    assert not (out / "scenes").exists() and unpacked_scene_folders([tmp_path]) == []
    after = read_records(out, format=FORMAT)
    assert json.dumps(after) == json.dumps(sorted(records, key=lambda r: r["scene_index"]))
    assert str(after[0]["checks"][0]["X_WG"][0][1]) == "-0.0"  # float bits kept
    assert read_records(out, 2, format=FORMAT) == after[:2]
    # Any Parquet reader sees one row per scene.
    table = pq.read_table(out / SCENES_TABLE)
    assert table.column("scene_index").to_pylist() == [0, 1, 2]
    assert json.loads(table.column("record")[1].as_py())["checks"][0]["held"] is False


def test_a_resumed_run_sees_both_forms_and_a_file_replaces_its_row(tmp_path):
    out = tmp_path / "run"
    _write(out, 0)
    pack_scene_records(out)
    _write(out, 1)
    _write(out, 0, held=False)  # written again after the pack: the file counts
    assert done_scene_indices(out) == {0, 1}
    got = read_records(out, format=FORMAT)
    assert [r["checks"][0]["held"] for r in got] == [False, True]
    assert pack_scene_records(out)["rows"] == 2
    assert [r["checks"][0]["held"] for r in read_records(out, format=FORMAT)] == [False, True]
    assert pack_scene_records(out) == {"folder": str(out), "rows": 2, "packed": 0}


def test_bad_records_are_named(tmp_path):
    out = tmp_path / "run"
    _write(out, 0, fmt="drake_grasp.grasp_tolerance/1")
    with pytest.raises(ValueError, match="scene 0 has format 'drake_grasp.grasp_tolerance/1'"):
        read_records(out, format=FORMAT)
    record_path(out, 1).write_text("{not json")
    with pytest.raises(ValueError, match="scene-00001.json: not a valid record"):
        read_records(out, format=FORMAT)
    record_path(out, 1).write_text(json.dumps({"format": FORMAT, "scene_index": 5}))
    with pytest.raises(ValueError, match="scene-00001.json: expected a scene record named by "
                                         "its scene_index, got scene_index 5"):
        done_scene_indices(out)
