"""analysis/results/cnn-view-average/decide.py: the pre-registered rules on fabricated
summaries."""

import json

import pytest

SCRIPT = "results/cnn-view-average/decide"


def write_runs(root, counts):
    """counts: run folder name -> (successes, attempts)."""
    for name, (k, n) in counts.items():
        (root / name).mkdir(parents=True, exist_ok=True)
        (root / name / "summary.json").write_text(json.dumps({"policies": {"ctr": {
            "successes": k, "n": n, "trial_wall_time_s": {"sum": 1.0},
            "failure_classes": {"none": k, "collision": n - k, "missed": 0}}}}))


def stage1(d4, plain, n=100):
    return {**{f"d4-clutter-seed{s}": (d4, n) for s in range(29, 34)},
            **{f"plain-clutter-seed{s}": (plain, n) for s in range(29, 34)}}


def stage2(d4_shift, plain_shift, d4_iso, plain_iso):
    return {**{f"d4-clutter-shift-seed{s}": (d4_shift, 100) for s in range(23, 28)},
            **{f"plain-clutter-shift-seed{s}": (plain_shift, 100) for s in range(23, 28)},
            "d4-isolation-seed19": (d4_iso, 120), "plain-isolation-seed19": (plain_iso, 120)}


@pytest.mark.parametrize("d4,plain,passed", [
    (95, 90, True),    # +5 points of 500 attempts each: Fisher p = 0.004
    (93, 90, False),   # +3 points: p = 0.11, not below 0.05
    (90, 85, True),
    (85, 90, False),   # lower, however significant
])
def test_rule_1(analysis_script, tmp_path, d4, plain, passed):
    D = analysis_script(SCRIPT)
    write_runs(tmp_path, stage1(d4, plain))
    out = D.decide(tmp_path)
    assert out["rule1"]["passed"] is passed
    s1 = out["stage1_clutter"]
    assert (s1["d4"]["successes"], s1["d4"]["attempts"]) == (5 * d4, 500)
    assert s1["gain"] == pytest.approx((d4 - plain) / 100)
    assert s1["plain"]["runs"]["clutter-seed29"]["failure_classes"] == {"collision": 100 - plain}
    if not passed:
        assert out["decision"].startswith("stage 1 failed")


@pytest.mark.parametrize("d4_shift,plain_shift,d4_iso,plain_iso,decision", [
    (88, 88, 117, 119, "view_average d4 becomes CTR's default"),  # a tie; 2 fewer
    (87, 88, 119, 119, "stage 2 failed: the image as shown stays the default"),
    (90, 88, 116, 119, "stage 2 failed: the image as shown stays the default"),
])
def test_rule_2(analysis_script, tmp_path, d4_shift, plain_shift, d4_iso, plain_iso, decision):
    D = analysis_script(SCRIPT)
    write_runs(tmp_path, {**stage1(95, 90), **stage2(d4_shift, plain_shift, d4_iso, plain_iso)})
    out = D.decide(tmp_path)
    assert out["decision"] == decision
    assert out["stage2_isolation"]["d4"]["successes"] == d4_iso


def test_part_of_the_runs_decides_nothing(analysis_script, tmp_path):
    D = analysis_script(SCRIPT)
    counts = stage1(95, 90)
    del counts["plain-clutter-seed33"]
    write_runs(tmp_path, counts)
    with pytest.raises(SystemExit, match="plain-clutter-seed33/summary.json: no such file"):
        D.main([str(tmp_path), "--out", str(tmp_path / "decision.json")])
    assert not (tmp_path / "decision.json").exists()
    write_runs(tmp_path, {**stage1(95, 90), "d4-isolation-seed19": (119, 120)})
    assert "stage 2 not complete" in D.decide(tmp_path)["decision"]


def test_another_candidate_and_other_seeds(analysis_script, tmp_path):
    """The same rules for `../cnn-onpolicy-finetune/`: the candidate's folder prefix and
    the seeds from the command line; the d4 folders are not read."""
    D = analysis_script(SCRIPT)
    write_runs(tmp_path, {**{f"onpolicy-clutter-seed{s}": (95, 100) for s in range(34, 39)},
                          **{f"plain-clutter-seed{s}": (90, 100) for s in range(34, 39)}})
    out_file = tmp_path / "decision.json"
    assert D.main([str(tmp_path), "--candidate", "onpolicy", "--clutter-seeds",
                   "34,35,36,37,38", "--out", str(out_file)]) == 0
    out = json.loads(out_file.read_text())
    assert out["rule1"]["passed"] and out["stage1_clutter"]["onpolicy"]["successes"] == 475
    assert "stage 2 not complete" in out["decision"] and "onpolicy-isolation-seed19" in out["decision"]
    write_runs(tmp_path, {**{f"onpolicy-clutter-seed{s}": (88, 100) for s in range(34, 39)}})
    out = D.decide(tmp_path, "onpolicy", (34, 35, 36, 37, 38))
    assert out["decision"] == "stage 1 failed: the shipped net stays the default"
    with pytest.raises(FileNotFoundError, match="plain-clutter-seed29/summary.json: no such file"):
        D.decide(tmp_path, "onpolicy")
