"""analysis/fcn_default_decision.py: the pre-registered rule on fabricated summaries."""

import json

import pytest


def write_runs(root, counts):
    """counts: run folder name -> (successes, attempts)."""
    for name, (k, n) in counts.items():
        (root / name).mkdir(parents=True, exist_ok=True)
        (root / name / "summary.json").write_text(json.dumps({"policies": {"ctr": {
            "successes": k, "n": n,
            "failure_classes": {"none": k, "collision": n - k, "missed": 0}}}}))


def runs(fcn, cnn, iso_fcn=118, iso_cnn=119, *, shift=(11, 12), clutter=(17, 18), iso=13,
         candidate="fcn"):
    """Four clutter runs per net with `fcn` (the candidate's) / `cnn` grasped of 50
    attempts each, and the isolation run of each (of 120)."""
    out = {}
    for run in ([f"clutter-shift-seed{s}" for s in shift] + [f"clutter-seed{s}" for s in clutter]):
        out[f"{candidate}-{run}"], out[f"cnn-{run}"] = (fcn, 50), (cnn, 50)
    out[f"{candidate}-isolation-seed{iso}"] = (iso_fcn, 120)
    out[f"cnn-isolation-seed{iso}"] = (iso_cnn, 120)
    return out


@pytest.mark.parametrize("fcn,cnn,iso_fcn,decision", [
    (45, 44, 117, "fcn becomes the default"),   # higher; isolation 2 fewer: within the margin
    (45, 45, 119, "cnn stays the default"),     # a tie stays with the incumbent
    (46, 44, 116, "cnn stays the default"),     # isolation 3 fewer: outside the margin
    (40, 44, 120, "cnn stays the default"),
])
def test_the_rule(analysis_script, tmp_path, fcn, cnn, iso_fcn, decision):
    D = analysis_script("fcn_default_decision")
    write_runs(tmp_path, runs(fcn, cnn, iso_fcn=iso_fcn))
    out = D.decide(tmp_path)
    assert out["decision"] == decision
    assert out["pooled"]["fcn"]["successes"] == 4 * fcn
    assert out["pooled"]["fcn"]["attempts"] == 200
    assert out["runs"]["cnn-clutter-seed17"]["failure_classes"] == {"collision": 50 - cnn}


def test_part_of_the_runs_decides_nothing(analysis_script, tmp_path):
    D = analysis_script("fcn_default_decision")
    counts = runs(45, 40)
    del counts["cnn-clutter-seed18"]
    write_runs(tmp_path, counts)
    with pytest.raises(SystemExit, match="cnn-clutter-seed18/summary.json: no such file"):
        D.main([str(tmp_path)])
    assert not (tmp_path / "decision.json").exists()


def test_other_seeds(analysis_script, tmp_path):
    """The second decision (fcn-all-decision) reads its own seeds' folders."""
    D = analysis_script("fcn_default_decision")
    write_runs(tmp_path, runs(46, 44, 117, 120, shift=(13, 14), clutter=(19, 20), iso=14))
    D.main([str(tmp_path), "--clutter-shift-seeds", "13,14", "--clutter-seeds", "19,20",
            "--isolation-seed", "14", "--out", str(tmp_path / "decision.json")])
    out = json.loads((tmp_path / "decision.json").read_text())
    assert out["pooled"]["fcn"] == {"successes": 184, "attempts": 200, "rate": 0.92,
                                    "ci95": out["pooled"]["fcn"]["ci95"]}
    assert out["rule"]["fcn_pooled_rate_higher"] and not out["rule"]["fcn_isolation_within_margin"]
    assert out["decision"] == "cnn stays the default"   # 3 fewer in isolation
    with pytest.raises(SystemExit, match="comma-separated integers"):
        D.main([str(tmp_path), "--clutter-seeds", "19;20"])


def test_another_candidate(analysis_script, tmp_path):
    """cnn-more-epochs: the candidate's folders are `new-...`, the default's `cnn-...`."""
    D = analysis_script("fcn_default_decision")
    write_runs(tmp_path, runs(45, 44, 118, 120, shift=(15, 16), clutter=(21, 22), iso=15,
                              candidate="new"))
    out = D.decide(tmp_path, clutter_shift_seeds=(15, 16), clutter_seeds=(21, 22),
                   isolation_seed=15, candidate="new")
    assert out["pooled"]["new"]["successes"] == 180 and out["pooled"]["cnn"]["successes"] == 176
    assert out["rule"] == {"new_pooled_rate_higher": True, "new_isolation_within_margin": True,
                           "isolation_margin": 2}
    assert out["decision"] == "new becomes the default"
    with pytest.raises(FileNotFoundError, match="fcn-clutter-shift-seed15"):
        D.decide(tmp_path, clutter_shift_seeds=(15, 16), clutter_seeds=(21, 22),
                 isolation_seed=15)   # the default candidate prefix finds no runs here
    with pytest.raises(SystemExit, match="candidate 'cnn'"):
        D.main([str(tmp_path), "--candidate", "cnn"])
