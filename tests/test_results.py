"""Trial-record format of a results directory (drake_grasp.evaluation.records). Fast, no Drake."""

import json
import math

import numpy as np
import pytest

from drake_grasp.evaluation.records import (FAILURE_CLASSES, TrialRecord, classify_failure, done_trial_ids,
                                 load_records, read_run_info, trial_file_stem, trial_id_from_stem,
                                 wilson_interval, write_record, write_run_info)


def make_record(trial_id="isolation/ctr/0007", **overrides) -> TrialRecord:
    values = dict(
        trial_id=trial_id, experiment="isolation", condition="ctr", policy="ctr", noise="none",
        noise_scale=None, depth_noise=False, offset_m=None, disturbance={},
        scenario_name="isolation", scenario_yaml="seed: 7\npolicy: ctr\n", seed=7,
        config_hash="abc123", code_version="0.1.0", success=True, failure_class="none",
        failure_reason=None, final_distance_m=0.012, sim_time_s=6.5, wall_time_s=3.25,
        control_steps=75, object_ids=["mug_03"], grasped_object_id="mug_03", run_index=None,
        attempt_index=None, extra={"note": "x"})
    values.update(overrides)
    return TrialRecord(**values)


def test_round_trip_through_dict_and_file(tmp_path):
    rec = make_record(disturbance={"kind": "shift", "time_s": 1.5, "dxy_m": np.array([0.01, 0.02])},
                      extra={"scores": np.arange(3, dtype=np.float32), "bad": float("nan")},
                      final_distance_m=np.float64(0.02), seed=np.int64(3), run_index=2, attempt_index=4)
    # numpy values became plain JSON types, NaN in free-form data became None
    assert rec.disturbance["dxy_m"] == [0.01, 0.02]
    assert rec.extra == {"scores": [0.0, 1.0, 2.0], "bad": None}
    assert type(rec.seed) is int and type(rec.final_distance_m) is float
    assert TrialRecord.from_dict(rec.to_dict()) == rec
    path = write_record(tmp_path, rec)
    assert path == tmp_path / "trials" / "isolation__ctr__0007.json"
    assert json.loads(path.read_text())["format_version"] == 1
    assert load_records(tmp_path) == [rec]


def test_schema_field_names():
    assert list(make_record().to_dict()) == [
        "trial_id", "experiment", "condition", "policy", "noise", "noise_scale", "depth_noise",
        "offset_m", "disturbance", "scenario_name", "scenario_yaml", "seed", "config_hash",
        "code_version", "success", "failure_class", "failure_reason", "final_distance_m",
        "sim_time_s", "wall_time_s", "control_steps", "object_ids", "grasped_object_id",
        "run_index", "attempt_index", "extra"]


def test_unknown_missing_and_bad_keys_are_named():
    d = make_record().to_dict()
    with pytest.raises(ValueError, match=r"f\.json.*unknown key 'colour'"):
        TrialRecord.from_dict({**d, "colour": 1}, source="f.json")
    del d["seed"]
    with pytest.raises(ValueError, match=r"f\.json.*missing key 'seed'"):
        TrialRecord.from_dict(d, source="f.json")
    d = make_record().to_dict()
    with pytest.raises(ValueError, match=r"key 'success' has value 'yes'"):
        TrialRecord.from_dict({**d, "success": "yes"}, source="f.json")
    with pytest.raises(ValueError, match="failure_class.*'exploded'"):
        make_record(success=False, failure_class="exploded")
    with pytest.raises(ValueError, match="success is true"):
        make_record(success=True, failure_class="missed")
    with pytest.raises(ValueError, match="format_version"):
        TrialRecord.from_dict({**d, "format_version": 99}, source="f.json")


def test_trial_ids_map_to_safe_reversible_file_names():
    assert trial_file_stem("isolation/ctr/0007") == "isolation__ctr__0007"
    assert trial_id_from_stem("sweep__noise_scale=0.4__0001") == "sweep/noise_scale=0.4/0001"
    for bad in ("", "a//b", "a/../b", "a b", "a__b", "a_/b", "x\\y"):
        with pytest.raises(ValueError, match="trial_id"):
            trial_file_stem(bad)


def test_atomic_write_leaves_no_temp_files(tmp_path):
    for i in range(5):
        write_record(tmp_path, make_record(f"isolation/ctr/{i:04d}", seed=i))
    write_record(tmp_path, make_record("isolation/ctr/0003", seed=33))  # rewrite replaces
    write_run_info(tmp_path, {"experiment": "isolation", "settings": {"trials": 5}})
    names = sorted(p.name for p in (tmp_path / "trials").iterdir())
    assert names == [f"isolation__ctr__{i:04d}.json" for i in range(5)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json", "trials"]
    assert [r.seed for r in load_records(tmp_path)] == [0, 1, 2, 33, 4]


def test_corrupt_record_is_named_and_not_done(tmp_path):
    write_record(tmp_path, make_record("isolation/ctr/0000"))
    write_record(tmp_path, make_record("isolation/ctr/0001"))
    bad = tmp_path / "trials" / "isolation__ctr__0001.json"
    bad.write_text('{"trial_id": "isolation/ctr/00')  # a torn write by something else
    # a temporary file of a write in progress is not a trial
    (tmp_path / "trials" / ".isolation__ctr__0002.json.123.tmp").write_text("{")
    with pytest.raises(ValueError, match="isolation__ctr__0001.json"):
        load_records(tmp_path)
    assert done_trial_ids(tmp_path) == {"isolation/ctr/0000"}


def test_done_trial_ids(tmp_path):
    assert done_trial_ids(tmp_path) == set()
    assert load_records(tmp_path) == []
    for tid in ("clutter/ctr/run03/a01", "clutter/gpd/run00/a02"):
        write_record(tmp_path, make_record(tid, experiment="clutter", run_index=3, attempt_index=1))
    assert done_trial_ids(tmp_path) == {"clutter/ctr/run03/a01", "clutter/gpd/run00/a02"}


def test_file_name_must_match_trial_id(tmp_path):
    path = write_record(tmp_path, make_record("isolation/ctr/0000"))
    path.rename(path.with_name("isolation__ctr__0009.json"))
    with pytest.raises(ValueError, match="isolation__ctr__0009.json.*does not match"):
        load_records(tmp_path)


def test_run_info_round_trip(tmp_path):
    with pytest.raises(FileNotFoundError, match="run.json"):
        read_run_info(tmp_path)
    write_run_info(tmp_path, {"experiment": "clutter", "settings": {"noise_scale": np.float64(0.4)}})
    info = read_run_info(tmp_path)
    assert info["experiment"] == "clutter" and info["settings"] == {"noise_scale": 0.4}
    assert "created_utc" in info


@pytest.mark.parametrize("success, reason, kw, expected", [
    (True, None, {}, "none"),
    (False, "init: no grasp attempted", {}, "none"),
    (False, "missed: no object touched both pads when the closing ended", {}, "missed"),
    (False, "missed: no object touched both pads when the closing ended",
     {"disturbance": {"kind": "shift", "time_s": 1.0}}, "missed"),
    (False, "missed: no grasp detected", {"disturbance": {"kind": "shift", "time_s": None}}, "missed"),
    (False, "pushed-away: can_000 moved 3.1 cm before the closing pads touched it", {},
     "pushed-away"),
    (False, "collision: the gripper's palm touched can_000 during the descent", {}, "collision"),
    (False, "slipped-during-lift: can_000 was held ...", {}, "slipped-during-lift"),
    (False, "slipped-during-hold: can_000 was held ...", {}, "slipped-during-hold"),
    # The geometric judge's words (records written before the contact judge).
    (False, "slipped: the object left the pads during lift/hold", {}, "slipped-during-hold"),
    (False, "timeout in mode approach", {}, "timeout"),
    (False, "timeout: the grasp motion was in its 'lift' phase", {}, "timeout"),
    (False, "finger collision pushed the object away", {}, "collision"),
    (False, "anything", {"exception": RuntimeError("boom")}, "simulation-error"),
    (False, "simulation error: RuntimeError", {}, "simulation-error"),
    (False, None, {}, "missed"),
    (False, "no top-down grasp: too wide", {}, "missed"),
])
def test_classify_failure(success, reason, kw, expected):
    assert classify_failure(success, reason, **kw) == expected
    assert expected in FAILURE_CLASSES


@pytest.mark.parametrize("k, n, lo, hi", [
    (0, 10, 0.0, 0.2775), (10, 10, 0.7225, 1.0), (5, 10, 0.2366, 0.7634), (39, 40, 0.8712, 0.9956),
])
def test_wilson_interval_hand_checked(k, n, lo, hi):
    # Hand check of 5/10: p=0.5, z^2=3.8415; centre (0.5+0.19207)/1.38415 = 0.5;
    # half = 1.96*sqrt(0.025+0.009604)/1.38415 = 0.2634 -> (0.2366, 0.7634).
    got = wilson_interval(k, n)
    assert got == pytest.approx((lo, hi), abs=5e-5)
    assert 0.0 <= got[0] <= k / n <= got[1] <= 1.0


def test_wilson_interval_edges():
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(5, 4)
    lo, hi = wilson_interval(50, 100)
    assert math.isclose(lo + hi, 1.0)
