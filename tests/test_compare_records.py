"""analysis/compare_records.py: two evaluate folders compared trial by trial."""

import json
import shutil
from pathlib import Path

import pytest

FOLDER = Path(__file__).resolve().parents[1] / "analysis" / "results" / "paper-bn12500-ep3" / "clutter"


def test_a_folder_against_an_edited_copy_of_itself(analysis_script, tmp_path):
    R = analysis_script("compare_records")
    from drake_grasp.evaluation.records import load_records, write_record

    # The committed folder may be packed (trials.parquet); its copy holds the same records as
    # one file each, the form a run writes, so both forms are read and compared.
    copy = tmp_path / "copy"
    shutil.copytree(FOLDER, copy, ignore=shutil.ignore_patterns("trials", "trials.parquet"))
    for record in load_records(FOLDER):
        write_record(copy, record)
    same = R.compare(str(FOLDER), str(copy), "ctr")
    n = same["compared"]
    assert n == 71 and same["only_a"] == same["only_b"] == 0
    assert same["same"] == {k: n for k in same["same"]} and same["outcome_differs"] == []
    assert same["a_rate"]["successes"] == same["b_rate"]["successes"] == 64
    files = sorted((copy / "trials").glob("*.json"))
    edited = json.loads(files[0].read_text())
    edited["final_distance_m"] = edited["final_distance_m"] + 0.0005
    files[0].write_text(json.dumps(edited))
    other = json.loads(files[1].read_text())
    other["control_steps"] += 1
    files[1].write_text(json.dumps(other))
    files[2].unlink()
    out = R.compare(str(FOLDER), str(copy), "ctr")
    assert out["compared"] == n - 1 and out["only_a"] == 1
    assert out["same"]["final_distance_exact"] == n - 2
    assert out["same"]["final_distance_within_1mm"] == n - 1
    assert out["same"]["control_steps"] == n - 2 and out["same"]["all_exact"] == n - 3
    with pytest.raises(SystemExit, match="no trial of condition 'gpd' in both"):
        R.compare(str(FOLDER), str(copy), "gpd")
