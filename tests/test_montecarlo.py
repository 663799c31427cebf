"""Monte Carlo runs: records and a report, Dask, kill + resume, errors inside trials."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from drake_grasp.montecarlo import evaluate
from drake_grasp.results import load_records


def _key(records):
    return [(r.trial_id, r.success, r.failure_class, r.final_distance_m) for r in records]


@pytest.fixture(scope="module")
def reference(tmp_path_factory, library):
    out = tmp_path_factory.mktemp("smoke")
    result = evaluate(experiment="smoke", out=out, trials=2, workers=2, seed=3, progress=False)
    return out, result


def test_tiny_experiment_writes_records_and_a_report(reference):
    out, result = reference
    records = load_records(out)
    assert result["records"] == 4 and len(records) == 4
    assert {r.condition for r in records} == {"init", "scripted"}
    for r in records:
        assert r.scenario_yaml and r.config_hash and r.code_version
        assert r.final_distance_m is None or r.final_distance_m >= 0
    scripted = [r for r in records if r.condition == "scripted"]
    assert all(r.failure_class in ("none", "missed", "slipped") for r in scripted)
    summary = result["summary"]
    assert summary["policies"]["scripted"]["n"] == 2
    assert (out / "report.md").is_file() and (out / "summary.json").is_file()


def test_rerun_skips_finished_trials(reference):
    out, _ = reference
    again = evaluate(experiment="smoke", out=out, trials=2, workers=1, seed=3, progress=False,
                     report=False)
    assert again["ran"] == 0 and again["skipped"] == 4 and again["records"] == 4


def test_same_on_a_dask_local_cluster(reference, tmp_path):
    from dask.distributed import LocalCluster

    out, _ = reference
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        result = evaluate(experiment="smoke", out=tmp_path / "dask", trials=2, seed=3,
                          scheduler=cluster.scheduler_address, progress=False, report=False)
    assert result["records"] == 4
    assert _key(load_records(tmp_path / "dask")) == _key(load_records(out))


def test_killed_run_resumes_to_the_same_records(reference, tmp_path):
    out, _ = reference
    killed = tmp_path / "killed"
    code = ("from drake_grasp.montecarlo import evaluate\n"
            f"evaluate(experiment='smoke', out={str(killed)!r}, trials=2, workers=1, seed=3,"
            " progress=False, report=False)\n")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    trials = killed / "trials"
    deadline = time.time() + 180
    while proc.poll() is None and time.time() < deadline:
        if trials.is_dir() and any(not p.name.startswith(".") for p in trials.iterdir()):
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    partial = load_records(killed)
    assert 1 <= len(partial) < 4, len(partial)
    evaluate(experiment="smoke", out=killed, trials=2, workers=1, seed=3, progress=False,
             report=False)
    resumed = load_records(killed)
    assert _key(resumed) == _key(load_records(out))
    assert len({r.trial_id for r in resumed}) == len(resumed)


def test_a_trial_that_throws_is_recorded_and_the_rest_finish(tmp_path):
    out = tmp_path / "err"
    evaluate(experiment="smoke", out=out, trials=2, workers=1, seed=3, progress=False,
             fail_trials=("smoke/scripted/0001",))
    records = {r.trial_id: r for r in load_records(out)}
    assert len(records) == 4
    bad = records["smoke/scripted/0001"]
    assert not bad.success and bad.failure_class == "simulation-error"
    assert "forced failure" in bad.failure_reason and "traceback" in bad.extra
    assert records["smoke/scripted/0000"].failure_class != "simulation-error"
