"""Reports from results directories (drake_grasp.evaluation.report) and the analysis scripts. Fast."""

import json

import pytest

from drake_grasp.evaluation.report import make_combined_report, make_report
from drake_grasp.evaluation.records import (TrialRecord, classify_failure, replay_path, write_record,
                                 write_run_info)



def make_record(trial_id, **overrides) -> TrialRecord:
    values = dict(
        trial_id=trial_id, experiment="isolation", condition="ctr", policy="ctr", noise="none",
        noise_scale=None, depth_noise=False, offset_m=None, disturbance={},
        scenario_name="isolation", scenario_yaml="seed: 0\n", seed=0, config_hash="abc123",
        code_version="0.1.0", success=True, failure_class="none", failure_reason=None,
        final_distance_m=0.01, sim_time_s=6.5, wall_time_s=3.25, control_steps=75,
        object_ids=["mug_03"], grasped_object_id=None, run_index=None, attempt_index=None, extra={})
    values.update(overrides)
    return TrialRecord(**values)


def _trial(experiment, condition, i, *, success, distance, reason=None, policy=None, **kw):
    policy = policy or condition.split("_")[0]
    failure_class = classify_failure(success, reason, **({"exception": RuntimeError()}
                                                         if reason and reason.startswith("simulation") else {}))
    return make_record(f"{experiment}/{condition}/{i:04d}", experiment=experiment, condition=condition,
                       policy=policy, success=success, failure_reason=None if success else reason,
                       failure_class=failure_class, final_distance_m=distance, seed=i,
                       noise="gaussian" if condition.endswith("_noise") else "none", **kw)


def _fill(results_dir, experiment, spec):
    """spec: {condition: [(success, distance, reason), ...]}"""
    write_run_info(results_dir, {"experiment": experiment, "settings": {"trials": 8}})
    for condition, trials in spec.items():
        for i, (success, distance, reason) in enumerate(trials):
            write_record(results_dir, _trial(experiment, condition, i, success=success,
                                             distance=distance, reason=reason))


MISSED = "missed: nothing between the pads after closing"
SIM_SPEC = {
    "init": [(False, 0.10, "init: no grasp attempted")] * 8,
    "ctr": [(True, 0.01, None)] * 7 + [(False, 0.05, MISSED)],
    "ctr_noise": [(True, 0.02, None)] * 6 + [(False, 0.04, "slipped: left the pads"),
                                             (False, None, "simulation error: RuntimeError")],
    "gpd": [(True, 0.015, None)] * 8,
    "gpd_noise": [(True, 0.01, None)] * 2 + [(False, 0.08, MISSED)] * 6,
}


@pytest.fixture
def sim_dir(tmp_path):
    d = tmp_path / "sim-distance"
    _fill(d, "sim-distance", SIM_SPEC)
    # a replay page for one failed trial only
    page = replay_path(d, "sim-distance/gpd_noise/0003")
    page.parent.mkdir(parents=True)
    page.write_text("<html></html>")
    return d


def test_make_report_sim_distance(sim_dir):
    summary = make_report(sim_dir)
    on_disk = json.loads((sim_dir / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary))
    assert summary["experiment"] == "sim-distance"
    p = summary["policies"]
    assert list(p) == ["init", "ctr", "ctr_noise", "gpd", "gpd_noise"]
    assert (p["ctr"]["successes"], p["ctr"]["n"]) == (7, 8)
    assert p["ctr"]["success_rate"] == 7 / 8
    assert p["ctr"]["ci95"] == pytest.approx([0.5291, 0.9776], abs=5e-5)
    # the simulation error is not an attempt: 6 of 7 (hand check of Wilson 6/7: centre
    # (0.857143 + 0.274390) / 1.548780 = 0.730597, half 1.959964 * sqrt(0.017493 +
    # 0.019599) / 1.548780 = 0.243725)
    assert (p["ctr_noise"]["successes"], p["ctr_noise"]["n"]) == (6, 7)
    assert (p["ctr_noise"]["trials"], p["ctr_noise"]["simulation_errors"]) == (8, 1)
    assert p["ctr_noise"]["ci95"] == pytest.approx([0.4869, 0.9743], abs=5e-5)
    assert p["gpd"]["ci95"] == pytest.approx([0.6756, 1.0], abs=5e-5)
    assert p["gpd_noise"]["ci95"] == pytest.approx([0.0715, 0.5907], abs=5e-5)
    # INIT: distance statistics only
    assert p["init"]["distance_only"] and p["init"]["success_rate"] is None and p["init"]["ci95"] is None
    assert p["init"]["mean_final_distance_m"] == pytest.approx(0.10)
    assert p["init"]["fraction_within_3cm"] == 0.0
    assert p["init"]["failure_classes"]["none"] == 8
    # ... nor a trial of the within-3-cm fraction
    assert p["ctr_noise"]["fraction_within_3cm"] == 6 / 7
    assert p["ctr_noise"]["distance_n"] == 7
    assert p["ctr_noise"]["median_final_distance_m"] == pytest.approx(0.02)
    assert p["ctr_noise"]["failure_classes"] == {
        "none": 6, "missed": 0, "pushed-away": 0, "collision": 0, "slipped-during-lift": 0,
        "slipped-during-hold": 1, "timeout": 0, "simulation-error": 1}
    assert p["gpd_noise"]["histogram"]["counts"][:3] == [2, 0, 6]
    assert p["ctr"]["histogram"]["counts"][1] == 1  # 0.05 m falls in [3, 6) cm
    targets = {t["id"]: t for t in summary["targets"]}
    assert targets["sim-distance/ctr_noise-within-3cm"]["met"] is True
    assert targets["sim-distance/ctr_noise-within-3cm"]["margin"] == pytest.approx(600 / 7 - 70)
    assert targets["sim-distance/gpd_noise-within-3cm"]["met"] is True
    assert summary["figures"] == ["figure5_distance_histogram.png"]
    png = sim_dir / "figure5_distance_histogram.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = (sim_dir / "report.md").read_text()
    assert "![final distance histograms](figure5_distance_histogram.png)" in md
    assert "| ctr | 7 / 8 | 87.5% | [52.9%, 97.8%] | 0 |" in md
    assert "| ctr_noise | 6 / 7 | 85.7% | [48.7%, 97.4%] | 1 |" in md
    assert "init |" not in md.split("## Final distance")[0]  # INIT is not in the success table
    assert "**met** CTR with noise: >= 70% of trials within 3 cm: 85.7% (met by 15.7 points)" in md
    assert "(replays/sim-distance__gpd_noise__0003.html)" in md
    assert "replays/sim-distance__gpd_noise__0004.html" not in md
    assert "Figure 5" in md and "compare shapes, not values" in md
    leftovers = [f.name for f in sim_dir.rglob(".*")]
    assert leftovers == []


def test_make_report_table1_experiment_with_paper_numbers(tmp_path):
    d = tmp_path / "cs"
    _fill(d, "clutter-shift", {"ctr": [(True, 0.01, None)] * 19 + [(False, 0.2, MISSED)],
                               "gpd": [(True, 0.01, None)] * 5 + [(False, 0.2, MISSED)] * 15})
    out = tmp_path / "report"
    summary = make_report(d, out_dir=out)
    assert not (d / "report.md").exists() and (out / "report.md").exists()
    p = summary["policies"]
    assert p["ctr"]["ci95"] == pytest.approx([0.7639, 0.9911], abs=5e-5)
    assert p["gpd"]["ci95"] == pytest.approx([0.1119, 0.4687], abs=5e-5)
    assert summary["paper"]["table1"]["ctr"]["rate_percent"] == 77.3
    md = (out / "report.md").read_text()
    assert "| ctr | 19 / 20 | 95.0% | [76.4%, 99.1%] | 77.3% (58/75) | 0 |" in md
    assert "| gpd | 5 / 20 | 25.0% | [11.2%, 46.9%] | 22.5% (11/49) |" in md
    assert "**met** CTR grasp success >= 90% (clutter-shift): 95.0% (met by 5.0 points)" in md
    assert "**met** CTR success >= 40 points above GPD (clutter-shift): 70.0 points (met by 30.0 points)" in md
    assert "16 of 16 failed trials have no replay page in `replays/`." in md


def test_isolation_target_missed_by_how_much(tmp_path):
    d = tmp_path / "iso"
    _fill(d, "isolation", {"ctr": [(True, 0.01, None)] * 38 + [(False, 0.1, MISSED)] * 2})
    summary = make_report(d)
    (t,) = summary["targets"]
    assert t["met"] is False and t["margin"] == pytest.approx(-2.5)
    md = (d / "report.md").read_text()
    assert "**missed** CTR grasp success >= 97.5% (isolation): 95.0% (missed by 2.5 points)" in md
    assert "97.5% (39/40)" in md


def test_sweep_dir_produces_sweep_figure(tmp_path):
    d = tmp_path / "sweep"
    spec = {f"noise_scale={s}": [(True, 0.01, None)] * k + [(False, 0.1, MISSED)] * (8 - k)
            for s, k in (("0.0", 8), ("0.2", 6), ("0.4", 3))}
    _fill(d, "noise-sweep", spec)
    summary = make_report(d)
    assert "sweep_noise_scale.png" in summary["figures"]
    assert (d / "sweep_noise_scale.png").read_bytes()[:4] == b"\x89PNG"
    assert [summary["policies"][c]["successes"] for c in summary["policies"]] == [8, 6, 3]
    assert "![sweep over noise_scale](sweep_noise_scale.png)" in (d / "report.md").read_text()


def test_empty_dir_fails_clearly(tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path}.*no trial records"):
        make_report(tmp_path)
    with pytest.raises(ValueError, match="does not exist"):
        make_report(tmp_path / "nope")
    assert list(tmp_path.iterdir()) == []


def test_combined_report(tmp_path, sim_dir):
    iso, cs = tmp_path / "iso", tmp_path / "cs"
    _fill(iso, "isolation", {"ctr": [(True, 0.01, None)] * 40, "gpd": [(True, 0.01, None)] * 39
                             + [(False, 0.1, MISSED)]})
    _fill(cs, "clutter-shift", {"ctr": [(True, 0.01, None)] * 18 + [(False, 0.2, MISSED)] * 2,
                                "gpd": [(True, 0.01, None)] * 10 + [(False, 0.2, MISSED)] * 10})
    out = tmp_path / "published"
    summary = make_combined_report([iso, cs, sim_dir], out)
    assert list(summary["table1"]) == ["isolation", "clutter-shift"]
    assert summary["table1"]["isolation"]["gpd"]["sim"]["successes"] == 39
    assert "figure5.png" in summary["figures"] and (out / "figure5.png").exists()
    for f in summary["figures"]:
        assert (out / f).is_file()
    met = {t["id"]: t["met"] for t in summary["targets"]}
    assert met == {"isolation/ctr-success": True, "clutter-shift/ctr-success": True,
                   "clutter-shift/ctr-minus-gpd": True, "sim-distance/ctr_noise-within-3cm": True,
                   "sim-distance/gpd_noise-within-3cm": True}
    md = (out / "report.md").read_text()
    # 90% - 50% is exactly the 40-point target
    assert "above GPD (clutter-shift): 40.0 points (met exactly at the threshold)" in md
    assert "| Objects in isolation (`isolation`) | 100.0% (40/40) |" in md
    assert "97.5% (39/40)" in md and "77.3% (58/75)" in md
    # replay links are relative to the combined report's folder
    assert "(../sim-distance/replays/sim-distance__gpd_noise__0003.html)" in md
    with pytest.raises(ValueError, match="isolation.*both"):
        make_combined_report([iso, iso], tmp_path / "x")


def test_analysis_scripts(tmp_path, sim_dir, capsys, analysis_script):
    iso = tmp_path / "iso"
    _fill(iso, "isolation", {"ctr": [(True, 0.01, None)] * 39 + [(False, 0.1, MISSED)],
                             "gpd": [(True, 0.01, None)] * 40})
    figure5, table1 = analysis_script("figure5"), analysis_script("table1")
    for module in (figure5, table1):
        with pytest.raises(SystemExit) as e:
            module.main(["--help"])
        assert e.value.code == 0
    assert "--bin-cm" in capsys.readouterr().out
    assert figure5.main([str(sim_dir), "--out", str(tmp_path / "f5.png")]) == 0
    assert (tmp_path / "f5.png").read_bytes()[:4] == b"\x89PNG"
    assert table1.main([str(iso), "--out", str(tmp_path / "t1.md")]) == 0
    text = (tmp_path / "t1.md").read_text()
    assert "| Objects in isolation (`isolation`) | 97.5% (39/40) |" in text and "100.0% (40/40)" in text
    # Arms of one experiment run into separate folders share the figure; one arm in two
    # folders is refused, naming both.
    ctr_only, gpd_only = tmp_path / "sim-ctr", tmp_path / "sim-gpd"
    _fill(ctr_only, "sim-distance", {"ctr": SIM_SPEC["ctr"]})
    _fill(gpd_only, "sim-distance", {"gpd": SIM_SPEC["gpd"]})
    assert figure5.main([str(ctr_only), str(gpd_only), "--out", str(tmp_path / "f5b.png")]) == 0
    assert (tmp_path / "f5b.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(SystemExit) as e:
        figure5.main([str(ctr_only), str(sim_dir), "--out", str(tmp_path / "f5c.png")])
    assert e.value.code == 2
    assert f"'ctr' is in both {ctr_only} and {sim_dir}" in capsys.readouterr().err
    assert not (tmp_path / "f5c.png").exists()
    # DIR@conditions: only those arms of DIR; a condition DIR does not hold is named.
    assert figure5.main([f"{sim_dir}@init,gpd,gpd_noise", str(ctr_only),
                         "--out", str(tmp_path / "f5d.png")]) == 0
    assert (tmp_path / "f5d.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(SystemExit) as e:
        figure5.main([f"{ctr_only}@ctr,cnn-only", "--out", str(tmp_path / "f5e.png")])
    assert e.value.code == 2
    assert "no records of condition(s) ['cnn-only'] (it holds ['ctr'])" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # no Figure 5 arm there: a clear error, exit 2
        figure5.main([str(iso / "none")])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        table1.main([str(sim_dir), "--out", str(tmp_path / "t2.md")])
    assert e.value.code == 2
    assert "no Table 1 experiment" in capsys.readouterr().err


def test_table1_takes_each_policy_from_its_own_run(tmp_path, capsys, analysis_script):
    """table1.py DIR@ctr DIR@gpd: a row's CTR from one run and GPD from another (e.g. GPD
    re-run with another option on the same seed), the sources named; a condition given
    twice is refused, naming both dirs, and nothing is written."""
    a, b = tmp_path / "a", tmp_path / "b"
    ok, miss = (True, 0.01, None), (False, 0.1, MISSED)
    _fill(a, "clutter", {"ctr": [ok] * 3 + [miss], "gpd": [miss] * 4})
    _fill(b, "clutter", {"gpd": [ok] * 5})
    table1 = analysis_script("table1")
    assert table1.main([f"{a}@ctr", str(b), "--out", str(tmp_path / "t.md")]) == 0
    text = (tmp_path / "t.md").read_text()
    assert "| Clutter (`clutter`) | 75.0% (3/4) |" in text and "100.0% (5/5)" in text
    assert "0.0% (0/4)" not in text
    assert f"- clutter: ctr from `{a}`; gpd from `{b}`" in text
    with pytest.raises(SystemExit) as e:
        table1.main([str(a), str(b), "--out", str(tmp_path / "t2.md")])
    assert e.value.code == 2
    assert f"condition(s) ['gpd'] in both {a} and {b}" in capsys.readouterr().err
    assert not (tmp_path / "t2.md").exists()


def test_paired_outcomes_counts_the_trials_only_one_run_grasped(tmp_path, capsys, analysis_script):
    """analysis/paired_outcomes.py pairs two runs by trial id: 12 trials, 6 grasped by
    both, 3 only by A, 1 only by B, exact McNemar p = 2 * P(X <= 1 | n = 4, 1/2) = 0.625;
    the final distances and failure classes agree where the outcomes do;
    runs without a shared trial are an error naming them."""
    a, b = tmp_path / "a", tmp_path / "b"
    ok, miss = (True, 0.01, None), (False, 0.1, MISSED)
    _fill(a, "isolation", {"ctr": [ok] * 6 + [ok] * 3 + [miss] + [miss] * 2})
    _fill(b, "isolation", {"ctr": [ok] * 6 + [miss] * 3 + [ok] + [miss] * 2})
    module = analysis_script("paired_outcomes")
    assert module.main([str(a), str(b), "--names", "old,new", "--out",
                        str(tmp_path / "p.json")]) == 0
    result = json.loads((tmp_path / "p.json").read_text())
    assert (result["paired_trials"], result["both"], result["only_a"], result["only_b"],
            result["neither"]) == (12, 6, 3, 1, 2)
    assert (result["successes_a"], result["successes_b"]) == (9, 7)
    assert result["mcnemar_exact_p"] == 0.625
    assert result["only_b_trials"] == ["isolation/ctr/0009"]
    # The 8 trials with one outcome in both ended at the same distance, the same way.
    assert (result["final_distance_in_both"], result["same_final_distance"],
            result["same_failure_class"]) == (12, 8, 8)
    # Within 3 cm (Figure 5): the grasped trials ended at 1 cm, the missed at 10 cm.
    assert (result["within_3cm_a"], result["within_3cm_b"], result["within_3cm_only_a"],
            result["within_3cm_only_b"], result["within_3cm_mcnemar_exact_p"]) == (9, 7, 3, 1, 0.625)
    assert module.mcnemar_exact_p(13, 6) == pytest.approx(0.1671, abs=1e-4)
    assert module.mcnemar_exact_p(0, 0) == 1.0
    capsys.readouterr()
    other = tmp_path / "c"
    _fill(other, "clutter", {"gpd": [ok]})
    assert module.main([str(a), str(other)]) == 2
    assert "no trial id in both" in capsys.readouterr().err
    # --condition: one condition of runs of two; the other's trials are not counted.
    two_a, two_b = tmp_path / "two_a", tmp_path / "two_b"
    _fill(two_a, "perception", {"cnn-only": [ok, miss, miss], "cnn-ctr": [ok, ok]})
    _fill(two_b, "perception", {"cnn-only": [ok, ok, miss], "cnn-ctr": [miss, miss]})
    assert module.main([str(two_a), str(two_b), "--condition", "cnn-only", "--out",
                        str(tmp_path / "q.json")]) == 0
    q = json.loads((tmp_path / "q.json").read_text())
    assert (q["condition"], q["paired_trials"], q["only_a"], q["only_b"]) == ("cnn-only", 3, 0, 1)
    assert module.main([str(two_a), str(two_b), "--condition", "gpd"]) == 2
    assert "no trial id of condition 'gpd' in both" in capsys.readouterr().err


def test_simulation_errors_have_their_own_column_and_are_not_attempts(tmp_path):
    d = tmp_path / "iso"
    error = (False, None, "simulation error: RuntimeError: solver diverged")
    _fill(d, "isolation", {"ctr": [(True, 0.01, None)] * 3 + [(False, 0.1, MISSED)] + [error] * 2,
                           "gpd": [error] * 2})
    summary = make_report(d)
    ctr, gpd = summary["policies"]["ctr"], summary["policies"]["gpd"]
    assert (ctr["trials"], ctr["simulation_errors"], ctr["n"], ctr["successes"]) == (6, 2, 4, 3)
    assert ctr["success_rate"] == 0.75 and ctr["fraction_within_3cm"] == 0.75
    assert ctr["failure_classes"]["simulation-error"] == 2
    # a condition with only simulation errors has no rate (not 0%)
    assert (gpd["n"], gpd["success_rate"], gpd["ci95"], gpd["fraction_within_3cm"]) == (0, None, None, None)
    (t,) = summary["targets"]
    assert t["value"] == pytest.approx(75.0)
    md = (d / "report.md").read_text()
    assert ("| condition | successes / attempts | rate | Wilson 95% CI | paper (Table 1, Objects in "
            "isolation) | simulation errors (not attempts) |") in md
    assert "| ctr | 3 / 4 | 75.0% | [30.1%, 95.4%] | 97.5% (39/40) | 2 |" in md
    assert "| gpd | 0 / 0 | — | — | 97.5% | 2 |" in md
    assert ("excluded from success rates and from the fraction within 3 cm, i.e. rate = "
            "successes / (trials - simulation errors)") in md
    assert "- trials: 8 in 2 conditions (ctr, gpd), 4 of them simulation errors" in md


def test_report_of_selected_trials(tmp_path):
    d = tmp_path / "cl"
    write_run_info(d, {"experiment": "clutter"})
    for run in range(2):
        for a in range(2):
            write_record(d, make_record(f"clutter/ctr/{run:04d}/attempt{a:02d}", experiment="clutter",
                                        run_index=run, attempt_index=a))
    summary = make_report(d, trials=["clutter/ctr/0001"])
    assert summary["policies"]["ctr"]["trials"] == 2
    assert summary["selection"] == {"trials": 1, "records_in_folder": 4}
    assert make_report(d)["policies"]["ctr"]["trials"] == 4
    with pytest.raises(ValueError, match="none of its 4 trial records"):
        make_report(d, trials=["clutter/gpd/0000"])


def test_clutter_runs_attempts_per_run_and_how_they_ended(tmp_path):
    """Attempts per run (simulation errors excluded), grasped per run, the recorded run
    ends, a run without an ending record counted as unfinished, next to the paper's
    attempts per run; and the time table from the trials' wall times and run.json's
    `evaluate` calls."""
    d = tmp_path / "cl"
    write_run_info(d, {"experiment": "clutter", "sessions": [
        {"started_utc": "2026-01-01T00:00:00+00:00", "wall_s": 1800.0, "workers": 2,
         "records_added": 6, "completed": False},
        {"started_utc": "2026-01-01T01:00:00+00:00", "wall_s": 1800.0, "workers": 2,
         "records_added": 3, "completed": True}]})
    runs = {0: [(True, None), (False, None), (False, "simulation-error"), (False, None),
                (False, "3 consecutive failed grasps")],
            1: [(True, None), (True, "no objects left in view")],
            2: [(False, None), (True, None)]}  # interrupted: no ending record
    for run, attempts in runs.items():
        for a, (ok, end) in enumerate(attempts):
            error = end == "simulation-error"
            write_record(d, make_record(
                f"clutter/ctr/{run:04d}/attempt{a:02d}", experiment="clutter", run_index=run,
                attempt_index=a, success=ok, wall_time_s=10.0 * (a + 1),
                final_distance_m=None if error else 0.01,
                failure_class="simulation-error" if error else ("none" if ok else "missed"),
                failure_reason=None if ok else "missed: nothing between the pads",
                extra={} if end in (None, "simulation-error") else {"run_end": end}))
    st = make_report(d)["policies"]["ctr"]
    assert st["clutter_runs"] == {
        "runs": 3, "attempts": 8,
        "attempts_per_run": {"mean": 8 / 3, "min": 2, "max": 4},
        "grasped_per_run_mean": 4 / 3,
        "run_ends": {"3 consecutive failed grasps": 1, "no objects left in view": 1,
                     "unfinished": 1},
        # the clutter-removal figures: no attempt found no grasp; no record holds its scene
        "grasps_attempted": 8, "no_grasp_found": 0, "grasp_success_rate": 4 / 8,
        "objects": None, "cleared": 4, "percent_cleared": None}
    assert st["trial_wall_time_s"] == {"sum": 210.0, "median": 20.0, "n": 9}
    md = (d / "report.md").read_text()
    assert ("| ctr | 3 | 8 | 2.7 (2-4) | 7.4 (74 in 10 runs) | 1.3 | 3 consecutive failed "
            "grasps: 1; no objects left in view: 1; unfinished: 1 |") in md
    assert "| ctr | 9 | 0.06 h | 20.0 s |" in md
    assert "Elapsed: 1.00 h over 2 `evaluate` call(s) with 2 worker(s)" in md
    # Not clutter runs: no clutter section, and the elapsed time is said to be unknown.
    iso = tmp_path / "iso"
    write_run_info(iso, {"experiment": "isolation"})
    write_record(iso, make_record("isolation/ctr/0000"))
    summary = make_report(iso)
    assert "clutter_runs" not in summary["policies"]["ctr"]
    md = (iso / "report.md").read_text()
    assert "Clutter runs" not in md and "Elapsed: not recorded" in md


def test_records_of_the_geometric_judge_stay_readable(tmp_path):
    """Records written before the contact judge carry "slipped" / "shifted-away": they
    load, count, and get their own columns only where a folder holds them."""
    d = tmp_path / "old"
    write_run_info(d, {"experiment": "isolation"})
    write_record(d, make_record("isolation/ctr/0000"))
    write_record(d, make_record("isolation/ctr/0001", success=False, failure_class="slipped",
                                failure_reason="slipped: the object left the pads during lift/hold"))
    write_record(d, make_record("isolation/gpd/0000", condition="gpd", policy="gpd",
                                success=False, failure_class="shifted-away",
                                failure_reason="missed: nothing between the pads after closing"))
    summary = make_report(d)
    assert summary["policies"]["ctr"]["failure_classes"]["slipped"] == 1
    assert summary["policies"]["gpd"]["failure_classes"]["shifted-away"] == 1
    md = (d / "report.md").read_text()
    assert "| slipped-during-hold | timeout | simulation-error | slipped | shifted-away |" in md
    new = tmp_path / "new"
    write_run_info(new, {"experiment": "isolation"})
    write_record(new, make_record("isolation/ctr/0000"))
    make_report(new)
    assert "shifted-away" not in (new / "report.md").read_text()


def test_fairness_table_names_each_policys_sensor_and_decision_time():
    from drake_grasp.evaluation.report_tables import fairness_markdown

    records = [make_record("isolation/ctr/0000", extra={"decision_time_s": 1.0, "decisions": 40}),
               make_record("isolation/ctr/0001", extra={"decision_time_s": 3.0, "decisions": 60}),
               make_record("isolation/gpd/0000", policy="gpd", condition="gpd",
                           extra={"decision_time_s": 2.5, "decisions": 1}),
               make_record("isolation/scripted/0000", policy="scripted", condition="scripted")]
    table = "\n".join(fairness_markdown(records))
    rows = {line.split("|")[1].strip(): line for line in table.splitlines() if line.startswith("| ")}
    # ctr: median of 25 ms and 50 ms per decision; 50 decisions per attempt.
    assert "64x64, 55 deg vertical" in rows["ctr"] and "38 ms" in rows["ctr"] and "| 50 |" in rows["ctr"]
    assert "640x480, 45 deg vertical" in rows["gpd"] and "2500 ms" in rows["gpd"]
    assert "privileged" in rows["scripted"] and rows["scripted"].count("| - |") >= 2


def test_report_counts_gpds_detections_by_their_ground_truth_verdict(tmp_path):
    """The report's detection table: per gpd condition, detections that pass the ground
    truth on 2, 1 and 0 surface samplings, with how many of each succeeded; simulation
    errors and records without the check are left out; no table without any check."""
    from drake_grasp.evaluation.report_tables import detection_markdown

    def gpd(i, passes, success, object_id=None, **kw):
        kw.setdefault("failure_class", "none" if success else "slipped-during-lift")
        check = {"ground_truth_passes": passes, "samplings": 2, "object_id": object_id}
        if object_id == "my_hammer":  # an imported object: its category is recorded
            check["object_category"] = "hammer"
        return make_record(f"isolation/gpd/{i:04d}", policy="gpd", condition="gpd",
                           success=success, extra={"gpd_detection": check}, **kw)

    records = [gpd(0, 2, True, "mug_003"), gpd(1, 2, True, "hammer_002"),
               gpd(2, 2, False, "my_hammer"), gpd(3, 1, True, "mug_010"),
               gpd(4, 0, False, "hammer_004"), gpd(5, 0, True),
               gpd(6, 2, False, failure_class="simulation-error", final_distance_m=None),
               make_record("isolation/gpd/0007", policy="gpd", condition="gpd"),
               make_record("isolation/ctr/0000")]
    records[6].failure_reason = "simulation error: boom"
    lines = detection_markdown(records)
    assert "| gpd | 6 | 3 (2) | 1 (1) | 2 (1) |" in lines
    # By category: built-in ids read as their category, a recorded category wins, and a
    # detection whose pads touch no single object is its own row.
    assert "| gpd | hammer | 3 | 1 | 2 |" in lines
    assert "| gpd | mug | 2 | 2 | 1 |" in lines
    assert "| gpd | (no single object) | 1 | 1 | 0 |" in lines
    assert not any(line.startswith("| ctr") for line in lines)
    assert detection_markdown([make_record("isolation/ctr/0000")]) == []
    d = tmp_path / "iso"
    write_run_info(d, {"experiment": "isolation"})
    for r in records:
        write_record(d, r)
    make_report(d)
    assert "| gpd | 6 | 3 (2) | 1 (1) | 2 (1) |" in (d / "report.md").read_text()
