"""Monte Carlo runs: records and a report, Dask, kill + resume, errors inside trials."""

import dataclasses
import re
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

import drake_grasp.evaluation.montecarlo as m
import drake_grasp.evaluation.run_folder as run_folder
import drake_grasp.evaluation.trial_plan as trial_plan
import drake_grasp.evaluation.trial_worker as trial_worker
from drake_grasp.evaluation.experiments import EXPERIMENTS, Condition, Experiment, option_patches
from drake_grasp.evaluation.montecarlo import evaluate
from drake_grasp.evaluation.run_folder import config_hash
from drake_grasp.core.provenance import code_version, file_sha256
from drake_grasp.evaluation.report import make_report
from drake_grasp.evaluation.records import load_records, read_run_info

ROOT = Path(__file__).resolve().parents[1]


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
    assert all(r.failure_class in ("none", "missed", "pushed-away", "collision",
                                   "slipped-during-lift", "slipped-during-hold")
               for r in scripted)
    summary = result["summary"]
    assert summary["policies"]["scripted"]["n"] == 2
    assert (out / "report.md").is_file() and (out / "summary.json").is_file()


def test_a_finished_call_packs_its_records_into_the_table(reference):
    out, _ = reference
    # The per-trial files were the write path while the call ran; it packed them.
    assert (out / "trials.parquet").is_file() and not (out / "trials").exists()
    assert len(load_records(out)) == 4


def test_rerun_skips_finished_trials(reference):
    out, _ = reference
    again = evaluate(experiment="smoke", out=out, trials=2, workers=1, seed=3, progress=False,
                     report=False)
    assert again["ran"] == 0 and again["skipped"] == 4 and again["records"] == 4
    # run.json: the first call's wall time is recorded; a call with nothing to run adds
    # no entry, and the run keeps its creation time.
    info = read_run_info(out)
    assert [(s["records_added"], s["workers"], s["completed"]) for s in info["sessions"]] == \
        [(4, 2, True)]
    assert info["sessions"][0]["wall_s"] > 0
    assert info["created_utc"] <= info["sessions"][0]["started_utc"]
    assert "Elapsed: " in (out / "report.md").read_text()
    # each session names the machine its records were computed on
    from drake_grasp.evaluation.replay import machine_note
    from drake_grasp.core.provenance import MACHINE_PACKAGES, machine

    assert info["sessions"][0]["machine"] == machine()
    assert set(machine()["packages"]) == set(MACHINE_PACKAGES)
    assert machine()["packages"]["drake"] and machine()["cpu"]
    assert machine_note(info) is None


def test_a_replay_says_when_its_records_came_from_another_machine():
    from drake_grasp.evaluation.replay import machine_note
    from drake_grasp.core.provenance import machine

    here = machine()
    other = {**here, "cpu": "Some CPU (family 25, model 17, stepping 1)"}
    newer = {**here, "packages": {**here["packages"], "numpy": "9.9.9"}}
    assert machine_note({"sessions": [{"machine": other}, {"machine": here}]}) is None
    note = machine_note({"sessions": [{"machine": other}, {"machine": newer}]})
    assert "Some CPU (family 25, model 17, stepping 1)" in note and "9.9.9" in note
    assert here["cpu"] in note and "bit for bit only on a machine like the recording" in note
    old = machine_note({"sessions": [{"records_added": 4}]})
    assert "does not say which machine" in old
    assert "does not say which machine" in machine_note({})


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
    # The child runs the same code; pin its code version to this process's, which is
    # computed once per process, so a commit landing in the checkout meanwhile cannot make
    # the resume below a different run.
    code = ("import drake_grasp.evaluation.montecarlo as m\n"
            "import drake_grasp.evaluation.run_folder as run_folder\n"
            "import drake_grasp.evaluation.trial_worker as trial_worker\n"
            f"m.code_version = lambda: {m.code_version()!r}\n"
            f"trial_worker.code_version = lambda: {m.code_version()!r}\n"
            f"run_folder.code_tree = lambda: {run_folder.code_tree()!r}\n"
            f"m.evaluate(experiment='smoke', out={str(killed)!r}, trials=2, workers=1, seed=3,"
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
    created = read_run_info(killed)["created_utc"]
    evaluate(experiment="smoke", out=killed, trials=2, workers=1, seed=3, progress=False,
             report=False)
    resumed = load_records(killed)
    assert _key(resumed) == _key(load_records(out))
    # The killed call left no wall time; the resume records its own, and the run keeps
    # its creation time.
    info = read_run_info(killed)
    assert [(s["records_added"], s["workers"]) for s in info["sessions"]] == \
        [(4 - len(partial), 1)]
    assert info["created_utc"] == created
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


# --------------------------------------------------------------------------- resume never mixes runs

def _boom(*args, **kwargs):
    raise RuntimeError("solver diverged (test)")


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_all_trials_of_a_condition_share_one_config_hash(reference):
    out, _ = reference
    records = load_records(out)
    info = read_run_info(out)
    by_condition = {}
    for r in records:
        by_condition.setdefault(r.condition, set()).add(r.config_hash)
    # two trials per condition, with different seeds (and objects), one hash each
    assert {c: len(h) for c, h in by_condition.items()} == {"init": 1, "scripted": 1}
    assert by_condition["init"] != by_condition["scripted"]
    assert {c["name"]: {c["config_hash"]} for c in info["conditions"]} == by_condition
    # the hash ignores the seed and nothing else
    yaml = records[0].scenario_yaml
    assert config_hash(yaml) == config_hash(yaml.replace(f"seed: {records[0].seed}\n", "seed: 5\n", 1))
    assert config_hash(yaml) != config_hash(yaml.replace("step_ratio: 0.2", "step_ratio: 0.3"))


def test_run_json_records_the_full_identity(reference):
    out, _ = reference
    info = read_run_info(out)
    assert info["code_version"] == code_version() and "+" in info["code_version"]
    assert len(info["object_library_hash"]) == 64
    scripted = next(c for c in info["conditions"] if c["name"] == "scripted")
    assert scripted["policy"] == "scripted" and scripted["weights_sha256"] is None
    assert "seed" not in scripted["scenario"]
    assert scripted["scenario"]["controller"]["step_ratio"] == 0.2
    # Records carry the version of the process that ran them (the workers here).
    assert all(r.code_version.startswith("0.1.0+") for r in load_records(out))


def test_resume_with_another_scenario_is_refused_and_force_new_starts_a_new_folder(
        reference, tmp_path, monkeypatch):
    out = _copy(reference[0], tmp_path / "OUT")
    before = (out / "run.json").read_text()
    smoke = EXPERIMENTS["smoke"]
    monkeypatch.setitem(EXPERIMENTS, "smoke", dataclasses.replace(
        smoke, scenario_text="{controller: {step_ratio: 0.3}}"))
    monkeypatch.setattr(trial_worker, "_simulate", _boom)  # nothing here needs physics
    with pytest.raises(ValueError) as e:
        evaluate(experiment="smoke", out=out, trials=2, workers=1, seed=3, progress=False,
                 report=False)
    msg = str(e.value)
    assert (f"{out / 'run.json'}: conditions[0].scenario.controller.step_ratio: 0.2 in the "
            "folder, 0.3 now") in msg
    assert "--force-new" in msg
    assert (out / "run.json").read_text() == before and len(load_records(out)) == 4

    new = evaluate(experiment="smoke", out=out, trials=1, workers=1, seed=3, progress=False,
                   report=False, conditions=["scripted"], force_new=True,
                   fail_trials=("smoke/scripted/0000:scene",))
    assert new["out"] == str(tmp_path / "OUT-2") and new["ran"] == 1
    assert "conditions[0].scenario.controller.step_ratio" in new["new_folder_because"]
    assert read_run_info(tmp_path / "OUT-2")["conditions"][1]["scenario"]["controller"][
        "step_ratio"] == 0.3
    (rec,) = load_records(tmp_path / "OUT-2")
    assert rec.failure_class == "simulation-error" and rec.extra["error_stage"] == "scene"
    # the old folder is untouched; repeating the command resumes OUT-2, it makes no OUT-3
    assert (out / "run.json").read_text() == before and len(load_records(out)) == 4
    again = evaluate(experiment="smoke", out=out, trials=1, workers=1, seed=3, progress=False,
                     report=False, conditions=["scripted"], force_new=True)
    assert again["out"] == str(tmp_path / "OUT-2") and again["ran"] == 0
    assert not (tmp_path / "OUT-3").exists()


def test_resume_refuses_other_weights_objects_or_code(tmp_path, monkeypatch, library):
    weights = tmp_path / "w.safetensors"
    shutil.copy(ROOT / "models" / "cnn" / "weights.safetensors", weights)
    objects = tmp_path / "objects"
    for oid in library.ids(split="test")[:2]:
        shutil.copytree(library.get(oid).directory, objects / oid)
    monkeypatch.setitem(EXPERIMENTS, "tiny-ctr", Experiment(
        name="tiny-ctr", scenario="isolation", trials=1, per_object_poses=True,
        description="test", conditions=(Condition("ctr", "ctr"),),
        scenario_text=f"{{controller: {{weights: {str(weights)!r}}}}}"))
    monkeypatch.setattr(trial_worker, "_simulate", _boom)
    out = tmp_path / "run"
    kw = dict(experiment="tiny-ctr", out=out, workers=1, seed=0, progress=False, report=False,
              objects_dir=str(objects))
    first = evaluate(**kw)
    assert first["ran"] == 1 and evaluate(**kw)["ran"] == 0  # same run: resumes

    weights.write_bytes(weights.read_bytes() + b"\0")
    with pytest.raises(ValueError, match=r"conditions\[0\]\.weights_sha256: \"[0-9a-f]{64}\" in "
                                         r"the folder, \"[0-9a-f]{64}\" now.*--force-new"):
        evaluate(**kw)
    weights.write_bytes(weights.read_bytes()[:-1])
    assert evaluate(**kw)["ran"] == 0
    info = read_run_info(out)
    assert info["conditions"][0]["weights_sha256"] == file_sha256(weights)
    assert load_records(out)[0].code_version == info["code_version"] == code_version()

    mesh = next((objects).glob("*/visual.obj"))
    mesh.write_text(mesh.read_text() + "\n")
    with pytest.raises(ValueError, match=r"object_library_hash: .* in the folder, .* now"):
        evaluate(**kw)
    mesh.write_text(mesh.read_text()[:-1])
    assert evaluate(**kw)["ran"] == 0

    # Another commit of the same package code (tests or docs changed): the same run.
    monkeypatch.setattr(m, "code_version", lambda: "0.1.0+git.000000000000")
    assert evaluate(**kw)["ran"] == 0
    monkeypatch.setattr(run_folder, "code_tree", lambda: "0.1.0+tree.000000000000")
    with pytest.raises(ValueError, match=r"code_tree: \"[^\"]+\" in the folder, "
                                         r"\"0\.1\.0\+tree\.000000000000\" now"):
        evaluate(**kw)
    assert len(load_records(out)) == 1


def test_smaller_trials_on_resume_reports_only_the_trials_asked(reference, tmp_path):
    out = _copy(reference[0], tmp_path / "copy")
    result = evaluate(experiment="smoke", out=out, trials=1, workers=1, seed=3, progress=False)
    assert result["ran"] == 0 and result["records"] == 4
    policies = result["summary"]["policies"]
    assert {c: s["trials"] for c, s in policies.items()} == {"init": 1, "scripted": 1}
    assert result["summary"]["selection"] == {"trials": 2, "records_in_folder": 4}
    assert "this report covers the trials of one `evaluate` call (2 of the 4 records" in \
        (out / "report.md").read_text()
    only = evaluate(experiment="smoke", out=out, trials=2, workers=1, seed=3, progress=False,
                    conditions=["scripted"])
    assert list(only["summary"]["policies"]) == ["scripted"]
    assert only["summary"]["policies"]["scripted"]["trials"] == 2
    # `drake-grasp report DIR` reports every record
    everything = make_report(out)
    assert {c: s["trials"] for c, s in everything["policies"].items()} == {"init": 2, "scripted": 2}
    assert everything["selection"] is None


# --------------------------------------------------------------------------- errors never abort a run

def test_a_trial_whose_scenario_cannot_be_built_is_recorded(tmp_path, monkeypatch):
    def no_scenario(*args, **kwargs):
        raise ValueError("the object library has no 'test' objects")

    monkeypatch.setattr(trial_worker, "trial_scenario", no_scenario)
    result = evaluate(experiment="smoke", out=tmp_path / "err", trials=1, workers=1, seed=3,
                      progress=False)
    records = load_records(tmp_path / "err")
    assert [r.trial_id for r in records] == ["smoke/init/0000", "smoke/scripted/0000"]
    for r in records:
        assert r.failure_class == "simulation-error" and r.extra["error_stage"] == "scene"
        assert "no 'test' objects" in r.failure_reason and r.scenario_yaml == ""
    scripted = result["summary"]["policies"]["scripted"]
    assert (scripted["simulation_errors"], scripted["n"], scripted["success_rate"]) == (1, 0, None)


def _pile(n=3):
    from drake_grasp.world.scene import ObjectPlacement, SceneSpec

    return SceneSpec(kind="clutter", seed=1, center_xy_m=[0.5, 0.0], settled=True, objects=[
        ObjectPlacement(f"apple_00{i}", [0.5 + 0.02 * i, 0.0, 0.03], [1.0, 0.0, 0.0, 0.0])
        for i in range(n)])


def _scripted_simulate(outcomes, calls, grasped=None, *, seen=lambda scenario, scene: scene,
                       details=lambda k, what: {}):
    """A stand-in for montecarlo._simulate: attempt k does outcomes[k] ("fail", "ok" or
    "raise"; "fail" after the script; any other word fails too) and appends
    `seen(scenario, scene)` to `calls`; `details(k, what)` adds to the result's details."""
    def simulate(scenario, library, *, scene=None):
        k = len(calls)
        calls.append(seen(scenario, scene))
        what = outcomes[k] if k < len(outcomes) else "fail"
        if what == "raise":
            raise RuntimeError("solver diverged (test)")
        ok = what == "ok"
        result = SimpleNamespace(
            success=ok, failure_reason=None if ok else "missed: nothing between the pads",
            disturbance={}, final_distance_m=0.01, sim_time_s=1.0, control_steps=3,
            object_ids=scene.object_ids(),
            details={"grasped_object_id": (grasped or scene.objects[0].object_id) if ok else None,
                     **details(k, what)})
        return SimpleNamespace(result=result, final_scene=scene)
    return simulate


def _fake_clutter(monkeypatch, outcomes, grasped=None):
    import drake_grasp.world.scene as scene_module

    from drake_grasp.evaluation import hermetic

    calls = []
    # The scripted attempts count their calls in this process: run them here, as on a
    # platform without fork (forked attempts are tested with real trials).
    monkeypatch.setattr(hermetic, "available", lambda: False)
    monkeypatch.setattr(scene_module, "make_scene", lambda *a, **k: _pile())
    monkeypatch.setattr(scene_module, "settle_scene",
                        lambda spec, *a, **k: dataclasses.replace(spec, settled=True))
    monkeypatch.setattr(trial_worker, "_simulate", _scripted_simulate(outcomes, calls, grasped))
    return calls


def _clutter(out, **kw):
    return evaluate(experiment="clutter", out=out, trials=1, workers=1, seed=0, progress=False,
                    conditions=["ctr"], **kw)


def test_clutter_scene_error_is_recorded_and_ends_the_run(tmp_path, monkeypatch):
    import drake_grasp.world.scene as scene_module

    def no_pile(*args, **kwargs):
        raise RuntimeError("pile did not settle (test)")

    monkeypatch.setattr(scene_module, "make_scene", no_pile)
    monkeypatch.setattr(trial_worker, "_simulate", _boom)
    result = _clutter(tmp_path / "c")
    (rec,) = load_records(tmp_path / "c")
    assert rec.trial_id == "clutter/ctr/0000/attempt00" and rec.failure_class == "simulation-error"
    assert "pile did not settle" in rec.failure_reason
    assert rec.extra["error_stage"] == "scene" and rec.extra["run_end"] == "scene could not be built"
    ctr = result["summary"]["policies"]["ctr"]
    assert (ctr["trials"], ctr["simulation_errors"], ctr["n"]) == (1, 1, 0)
    assert _clutter(tmp_path / "c", report=False)["ran"] == 0


def test_clutter_simulation_errors_are_not_failed_grasps(tmp_path, monkeypatch):
    # attempt 0 fails, 1 raises in the simulation, 2 grasps but settling the pile it
    # leaves raises, 3 and 4 fail: three failed grasps in a row, not counting the errors.
    calls = _fake_clutter(monkeypatch, ["fail", "raise", "ok", "fail", "fail", "fail"])
    result = _clutter(tmp_path / "c", fail_trials=("clutter/ctr/0000/attempt02:settle",))
    records = load_records(tmp_path / "c")
    assert [r.failure_class for r in records] == [
        "missed", "simulation-error", "simulation-error", "missed", "missed"]
    assert [r.extra["error_stage"] for r in records[1:3]] == ["simulation", "settle"]
    assert "forced failure (test) in settle" in records[2].failure_reason
    # an attempt that raised leaves the pile as it was: the next one starts from it
    assert [len(s.objects) for s in calls] == [3, 3, 3, 3, 3]
    assert records[-1].extra["run_end"] == "3 consecutive failed grasps"
    assert all("run_end" not in r.extra for r in records[:-1])
    ctr = result["summary"]["policies"]["ctr"]
    assert (ctr["trials"], ctr["simulation_errors"], ctr["n"], ctr["successes"]) == (5, 2, 3, 0)
    assert _clutter(tmp_path / "c", report=False)["ran"] == 0  # finished, on resume too


def test_a_clutter_runs_attempts_are_written_as_they_finish(tmp_path, monkeypatch):
    """The driver runs a clutter run one attempt per task and writes each record before
    the next attempt starts: a killed run loses at most the attempt in flight."""
    _fake_clutter(monkeypatch, ["fail", "ok", "fail", "fail", "fail"])
    scripted, on_disk = trial_worker._simulate, []

    def spy(scenario, library, *, scene=None):
        on_disk.append(len(load_records(tmp_path / "c")))
        return scripted(scenario, library, scene=scene)

    monkeypatch.setattr(trial_worker, "_simulate", spy)
    _clutter(tmp_path / "c", report=False)
    assert on_disk == [0, 1, 2, 3, 4] and len(load_records(tmp_path / "c")) == 5


def test_clutter_run_whose_attempts_keep_raising_ends(tmp_path, monkeypatch):
    calls = _fake_clutter(monkeypatch, ["ok"] + ["raise"] * 20)
    _clutter(tmp_path / "c", report=False)
    records = load_records(tmp_path / "c")
    assert [r.failure_class for r in records] == ["none"] + ["simulation-error"] * 3
    assert records[-1].extra["run_end"] == "3 consecutive simulation errors"
    assert len(calls) == 4 and [len(s.objects) for s in calls] == [3, 2, 2, 2]
    assert _clutter(tmp_path / "c", report=False)["ran"] == 0
    assert len(calls) == 4


def test_clutter_run_whose_successes_remove_nothing_ends(tmp_path, monkeypatch):
    calls = _fake_clutter(monkeypatch, ["ok"] * 200, grasped="not_in_the_pile")
    _clutter(tmp_path / "c", report=False)
    records = load_records(tmp_path / "c")
    assert len(records) == 1 and len(calls) == 1
    assert records[-1].extra["run_end"].startswith("a successful grasp removed no object")
    assert _clutter(tmp_path / "c", report=False)["ran"] == 0


def test_weights_option_sets_the_cnn_conditions_weights_and_their_identity(tmp_path):
    """`evaluate --weights FILE`: the CNN conditions load FILE and the run's identity
    holds its sha256 (so a resume with other weights is refused); the other conditions
    are unchanged; a missing file is refused before any folder is made."""
    from drake_grasp.core.assets import models_dir

    shipped = models_dir() / "cnn" / "weights.safetensors"
    other = tmp_path / "other.safetensors"
    shutil.copy(shipped, other)  # same tensors, another path
    exp = dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(weights=str(other)))
    ident = {c["name"]: c for c in run_folder.run_identity(exp, seed=0)["conditions"]}
    base = {c["name"]: c for c in run_folder.run_identity(EXPERIMENTS["isolation"], seed=0)["conditions"]}
    assert ident["ctr"]["scenario"]["controller"]["weights"] == str(other)
    assert ident["ctr"]["weights_sha256"] == file_sha256(other) == file_sha256(shipped)
    assert ident["ctr"]["config_hash"] != base["ctr"]["config_hash"]
    assert ident["gpd"] == base["gpd"] and ident["scripted"] == base["scripted"]
    # What the workers run: each task carries the weights into its trial's scenario.
    from drake_grasp.evaluation.experiments import trial_scenario

    for task in trial_plan.plan_tasks(exp, trials=2, seed=0, conditions=["ctr", "gpd"]):
        run_exp = trial_plan.task_experiment(task)
        s = trial_scenario(run_exp, trial_plan.task_condition(task, run_exp), task.index, base_seed=0)
        assert s.controller.weights == (str(other) if task.condition == "ctr" else "")
        assert run_folder.weights_path(s) == (str(other) if task.condition == "ctr" else None)
    with pytest.raises(ValueError, match="--weights .*nope.safetensors: no such file"):
        evaluate(experiment="isolation", out=tmp_path / "run", trials=1,
                 patches=option_patches(weights=str(tmp_path / "nope.safetensors")),
                 progress=False)
    assert not (tmp_path / "run").exists()


def test_weights_option_takes_an_ensemble_and_records_every_members_sha256(tmp_path):
    """`evaluate --weights A,B`: the run's identity holds both files' sha256 in order; a
    missing member or an empty item is refused, naming it, before any folder is made."""
    from drake_grasp.core.assets import models_dir

    grid = models_dir() / "cnn-grid" / "weights.safetensors"
    paper = models_dir() / "cnn" / "weights.safetensors"
    exp = dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(weights=f"{grid},{paper}"))
    ident = {c["name"]: c for c in run_folder.run_identity(exp, seed=0)["conditions"]}
    assert ident["ctr"]["weights_sha256"] == f"{file_sha256(grid)},{file_sha256(paper)}"
    assert ident["gpd"]["weights_sha256"] is None
    missing = tmp_path / "nope.safetensors"
    with pytest.raises(ValueError, match=f"--weights .*: {missing}: no such file"):
        evaluate(experiment="isolation", out=tmp_path / "run", trials=1,
                 patches=option_patches(weights=f"{grid},{missing}"), progress=False)
    with pytest.raises(ValueError, match="--weights .*empty item"):
        evaluate(experiment="isolation", out=tmp_path / "run", trials=1,
                 patches=option_patches(weights=f"{grid},"), progress=False)
    assert not (tmp_path / "run").exists()


def test_gpd_weights_option_sets_the_gpd_conditions_classifier_and_its_identity(tmp_path):
    """`evaluate --gpd-weights FILE`: the gpd conditions load FILE, the run's identity
    holds its sha256, so a folder run with one classifier refuses a resume with a file
    changed in place; the other conditions are unchanged; a missing file is refused
    before any folder is made."""
    from drake_grasp.evaluation.experiments import trial_scenario
    from drake_grasp.policies.gpd import default_weights_path, load_classifier
    from drake_grasp.evaluation.records import write_run_info

    shipped = default_weights_path()
    other = tmp_path / "gpd.safetensors"
    shutil.copy(shipped, other)
    exp = dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(gpd_weights=str(other)))
    ident = {c["name"]: c for c in run_folder.run_identity(exp, seed=0)["conditions"]}
    base = {c["name"]: c for c in run_folder.run_identity(EXPERIMENTS["isolation"], seed=0)["conditions"]}
    assert base["gpd"]["gpd_weights_sha256"] == file_sha256(shipped)
    assert ident["gpd"]["scenario"]["gpd"]["weights"] == str(other)
    assert ident["gpd"]["gpd_weights_sha256"] == file_sha256(other)
    assert ident["ctr"] == base["ctr"] and ident["scripted"] == base["scripted"]
    assert base["ctr"]["gpd_weights_sha256"] is None
    for task in trial_plan.plan_tasks(exp, trials=2, seed=0, conditions=["ctr", "gpd"]):
        run_exp = trial_plan.task_experiment(task)
        s = trial_scenario(run_exp, trial_plan.task_condition(task, run_exp), task.index, base_seed=0)
        assert s.gpd.weights == (str(other) if task.condition == "gpd" else "")
        assert run_folder.gpd_weights_path(s) == (str(other) if task.condition == "gpd" else None)
    # The same path with other tensors is another run.
    out = tmp_path / "run"
    out.mkdir()
    write_run_info(out, run_folder.run_identity(exp, seed=0))
    import torch

    from drake_grasp.policies.gpd import save_classifier

    model = load_classifier(other)
    with torch.no_grad():
        next(model.parameters()).mul_(0.5)
    save_classifier(model, other)
    conflict = run_folder.folder_conflict(out, run_folder.run_identity(exp, seed=0))
    assert conflict is not None and "gpd_weights_sha256" in conflict
    with pytest.raises(ValueError, match="--gpd-weights .*nope.safetensors: no such file"):
        evaluate(experiment="isolation", out=tmp_path / "run2", trials=1,
                 patches=option_patches(gpd_weights=str(tmp_path / "nope.safetensors")), progress=False)
    assert not (tmp_path / "run2").exists()


def _check_controller_option(exp, field: str, on=True, off=False) -> None:
    """An `Experiment` option that sets `controller.<field>` from `off` (the isolation
    experiment's) to `on` for the CTR conditions: it reaches their resolved scenarios and
    each trial's, changes their config hash, and leaves the gpd and scripted conditions
    as they were."""
    from drake_grasp.evaluation.experiments import trial_scenario

    ident = {c["name"]: c for c in run_folder.run_identity(exp, seed=0)["conditions"]}
    base = {c["name"]: c for c in run_folder.run_identity(EXPERIMENTS["isolation"], seed=0)["conditions"]}
    assert ident["ctr"]["scenario"]["controller"][field] == on
    assert base["ctr"]["scenario"]["controller"][field] == off
    assert ident["ctr"]["config_hash"] != base["ctr"]["config_hash"]
    assert ident["gpd"] == base["gpd"] and ident["scripted"] == base["scripted"]
    for task in trial_plan.plan_tasks(exp, trials=2, seed=0, conditions=["ctr", "gpd"]):
        run_exp = trial_plan.task_experiment(task)
        s = trial_scenario(run_exp, trial_plan.task_condition(task, run_exp), task.index, base_seed=0)
        assert getattr(s.controller, field) == (on if task.condition == "ctr" else off)


def test_mirror_average_option_reaches_the_cnn_conditions_and_their_identity(tmp_path):
    """`evaluate --mirror-average`: the CNN conditions' trials score with
    controller.mirror_average on, the run's identity differs (a resume without the flag
    is refused), the other conditions are unchanged."""
    exp = dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(mirror_average=True))
    _check_controller_option(exp, "mirror_average")
    out = tmp_path / "run"
    out.mkdir()
    from drake_grasp.evaluation.records import write_run_info

    write_run_info(out, run_folder.run_identity(exp, seed=0))
    assert run_folder.folder_conflict(out, run_folder.run_identity(EXPERIMENTS["isolation"], seed=0)) is not None


def test_converge_option_reaches_the_ctr_conditions_and_their_identity(tmp_path):
    """`evaluate --converge N`: the closed-loop conditions run with
    controller.converge_iterations = N, the run's identity differs, the others are
    unchanged; a negative N is refused before anything is written."""
    from drake_grasp.evaluation.experiments import trial_scenario

    exp = dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(converge_iterations=0))
    ident = {c["name"]: c for c in run_folder.run_identity(exp, seed=0)["conditions"]}
    base = {c["name"]: c for c in run_folder.run_identity(EXPERIMENTS["isolation"], seed=0)["conditions"]}
    assert ident["ctr"]["scenario"]["controller"]["converge_iterations"] == 0
    assert base["ctr"]["scenario"]["controller"]["converge_iterations"] == 20
    assert ident["ctr"]["config_hash"] != base["ctr"]["config_hash"]
    assert ident["ctr-sim"]["config_hash"] != base["ctr-sim"]["config_hash"]
    assert ident["gpd"] == base["gpd"] and ident["scripted"] == base["scripted"]
    for task in trial_plan.plan_tasks(exp, trials=1, seed=0, conditions=["ctr", "gpd"]):
        run_exp = trial_plan.task_experiment(task)
        s = trial_scenario(run_exp, trial_plan.task_condition(task, run_exp), task.index, base_seed=0)
        assert s.controller.converge_iterations == (0 if task.condition == "ctr" else 20)
    with pytest.raises(ValueError, match="--converge: expected >= 0 iterations, got -2"):
        evaluate(experiment="isolation", out=tmp_path / "run", trials=1, patches=option_patches(converge_iterations=-2),
                 progress=False)
    assert not (tmp_path / "run").exists()


def test_distance_samples_option_reaches_every_condition_and_the_identity(tmp_path):
    """`evaluate --distance-samples N`: every condition's judge searches the ground truth
    behind the final distance from N surface points; the identity differs; N <= 0 other
    than the 0 that keeps the scenarios' is refused before anything is written."""
    from drake_grasp.evaluation.experiments import trial_scenario

    exp = dataclasses.replace(EXPERIMENTS["sim-distance"], patches=option_patches(distance_samples=1600))
    ident = {c["name"]: c for c in run_folder.run_identity(exp, seed=0)["conditions"]}
    base = {c["name"]: c for c in run_folder.run_identity(EXPERIMENTS["sim-distance"], seed=0)["conditions"]}
    for name in ("init", "ctr", "ctr_noise", "gpd", "gpd_noise"):
        assert ident[name]["scenario"]["judge"]["distance_grasp_samples"] == 1600
        assert base[name]["scenario"]["judge"]["distance_grasp_samples"] == 400
        assert ident[name]["config_hash"] != base[name]["config_hash"]
    for task in trial_plan.plan_tasks(exp, trials=1, seed=0, conditions=["ctr", "gpd"]):
        run_exp = trial_plan.task_experiment(task)
        s = trial_scenario(run_exp, trial_plan.task_condition(task, run_exp), task.index, base_seed=0)
        assert s.judge.distance_grasp_samples == 1600
    with pytest.raises(ValueError, match="--distance-samples: expected a positive number"):
        evaluate(experiment="sim-distance", out=tmp_path / "run", trials=1, patches=option_patches(distance_samples=-5),
                 progress=False)
    assert not (tmp_path / "run").exists()


def test_a_denser_distance_search_finds_more_true_grasps_for_the_same_episode():
    """The judge's `distance_grasp_samples` is the search behind `final_distance_m`: the
    same INIT episode (same seed, same hand pose) measured against a 4x denser search
    counts more than twice the true grasps. (Its nearest one is not always nearer: the
    two searches draw independent points.)"""
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.config.scenario import load_scenario

    runs = {}
    for n in (400, 1600):
        s = load_scenario(scenario_name="isolation",
                          scenario_text=f"{{policy: init, seed: 3, judge: {{distance_grasp_samples: {n}}}}}")
        runs[n] = simulate_episode(s, record_depth=False, visualize=False).result
    sparse, dense = runs[400], runs[1600]
    assert dense.details["num_true_grasps"] > 2 * sparse.details["num_true_grasps"] > 0
    assert dense.details["hand_at_close_xy_yaw"] == sparse.details["hand_at_close_xy_yaw"]
    assert dense.final_distance_m is not None and sparse.final_distance_m is not None


def test_parallel_map_keeps_the_order_in_and_out_of_process():
    import operator

    args = [(2, 5), (3, 2), (10, 0), (7, 1)]
    assert m.parallel_map(operator.pow, args, workers=2) == [32, 9, 1, 7]
    assert m.parallel_map(operator.pow, args, workers=1) == [32, 9, 1, 7]


def test_pool_workers_are_recycled_without_deadlock():
    """`pooled_map` runs every task and replaces its worker processes every
    workers * per_worker tasks. With ProcessPoolExecutor's max_tasks_per_child (Python
    3.11-3.15.0b3, CPython gh-115634) this backlog deadlocked once a worker exited at
    its limit, so it runs in a subprocess with a time limit."""
    code = ("import collections, os\n"
            "from drake_grasp.evaluation.montecarlo import pooled_map\n"
            "pids = []\n"
            "pooled_map(os.getpid, [()] * 10, workers=2, per_worker=2,\n"
            "           on_result=lambda pid, args: pids.append(pid))\n"
            "print(len(pids), len(set(pids)), max(collections.Counter(pids).values()))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    results, processes, most = (int(v) for v in done.stdout.split())
    assert results == 10
    assert processes >= 3  # 3 chunks of 4 tasks, each on fresh processes
    assert most <= 4


@pytest.mark.parametrize("experiment,moves", [("clutter", False), ("clutter-shift", True)])
def test_clutter_piles_are_settled_with_the_episode_sheet(tmp_path, monkeypatch, experiment,
                                                          moves):
    """The pile and every pile an attempt leaves are settled with the sheet collision of
    the episode (the box where the sheet is shifted): see tests/test_table.py."""
    import drake_grasp.world.scene as scene_module

    seen = []

    def make_scene(*a, **k):
        seen.append(("make", k.get("sheet_moves")))
        return _pile()

    def settle_scene(spec, *a, **k):
        seen.append(("settle", k.get("sheet_moves")))
        return dataclasses.replace(spec, settled=True)

    from drake_grasp.evaluation import hermetic

    monkeypatch.setattr(hermetic, "available", lambda: False)  # `seen` is this process's
    monkeypatch.setattr(scene_module, "make_scene", make_scene)
    monkeypatch.setattr(scene_module, "settle_scene", settle_scene)
    monkeypatch.setattr(trial_worker, "_simulate", _scripted_simulate(["ok", "fail", "fail", "fail"], []))
    evaluate(experiment=experiment, out=tmp_path / "c", trials=1, workers=1, seed=0,
             progress=False, conditions=["ctr"], report=False)
    assert seen[0] == ("make", moves)
    assert [s for s in seen[1:]] == [("settle", moves)] * 4


def test_hand_check_option_reaches_the_closed_loop_conditions_and_their_identity():
    """`evaluate --hand-check`: the closed-loop conditions' trials run with
    controller.hand_check on, the run's identity differs, the others are unchanged."""
    from drake_grasp.cli.main import build_parser

    _check_controller_option(dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(hand_check=True)),
                             "hand_check")
    args = build_parser().parse_args(["evaluate", "--experiment", "clutter", "--out", "x",
                                      "--hand-check"])
    assert args.hand_check is True


def test_ctr_text_option_sets_controller_settings_of_the_closed_loop_conditions(tmp_path):
    """`evaluate --ctr-text YAML`: the closed-loop conditions' trials run with those
    controller settings, the run's identity differs, the others are unchanged; an unknown
    key or a value out of range is refused by name before anything is written."""
    from drake_grasp.cli.main import build_parser

    exp = dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(ctr_text="{stop_distance_m: 0.2}"))
    _check_controller_option(exp, "stop_distance_m", on=0.2, off=0.14)
    _check_controller_option(dataclasses.replace(  # the test-time views of the grid net
        EXPERIMENTS["isolation"], patches=option_patches(ctr_text="{view_average: d4}")),
        "view_average", on="d4", off="none")
    for text, message in [("{stop_distanc_m: 0.2}", "unknown key 'controller.stop_distanc_m'"),
                          ("{end_camera_height_m: 0.5}", "controller.end_camera_height_m: got 0.5"),
                          ("[0.2]", "expected a mapping of controller settings")]:
        with pytest.raises(ValueError, match=re.escape(message)):
            evaluate(experiment="isolation", out=tmp_path / "run", trials=1, patches=option_patches(ctr_text=text),
                     progress=False)
    assert not (tmp_path / "run").exists()
    args = build_parser().parse_args(["evaluate", "--experiment", "clutter", "--out", "x",
                                      "--ctr-text", "{stop_distance_m: 0.2}"])
    assert args.ctr_text == "{stop_distance_m: 0.2}"


def test_a_patch_is_the_general_form_of_the_evaluate_options(tmp_path, capsys):
    """`evaluate --patch GROUP=YAML`: a scenario patch of one group of conditions; the
    options are patches of the same kind (`--hand-check` is the closed-loop patch
    `{controller: {hand_check: true}}`: the same identity); an unknown group or key is
    refused by name before anything is written."""
    from drake_grasp.cli.main import main
    from drake_grasp.evaluation.experiments import ScenarioPatch

    patch = ScenarioPatch("closed-loop", "{controller: {hand_check: true}}")
    by_patch = dataclasses.replace(EXPERIMENTS["isolation"], patches=(patch,))
    by_flag = dataclasses.replace(EXPERIMENTS["isolation"], patches=option_patches(hand_check=True))
    ident, flag, base = (
        {c["name"]: c["config_hash"] for c in run_folder.run_identity(e, seed=0)["conditions"]}
        for e in (by_patch, by_flag, EXPERIMENTS["isolation"]))
    assert ident == flag
    assert ident["ctr"] != base["ctr"] and ident["gpd"] == base["gpd"]
    _check_controller_option(by_patch, "hand_check")
    with pytest.raises(ValueError, match=r"scenario patch group: expected one of \['all', "):
        ScenarioPatch("ctr", "{controller: {hand_check: true}}")
    rc = main(["evaluate", "--experiment", "isolation", "--trials", "1", "--out",
               str(tmp_path / "run"), "--patch", "closed-loop={controller: {hand_chek: true}}"])
    assert rc != 0
    assert re.search(r"--patch .*unknown key 'controller.hand_chek'", capsys.readouterr().err)
    assert not (tmp_path / "run").exists()


def test_sensor_policies_are_every_builtin_policy_but_scripted():
    """`policies.SENSOR_POLICIES` (what the bridge runs and `evaluate --conditions` may
    add) stays `scenario.POLICIES` less `scripted`, the one that reads the true poses."""
    from drake_grasp.evaluation.bridge_protocol import BRIDGE_POLICIES
    from drake_grasp.evaluation.experiments import EXTRA_POLICIES
    from drake_grasp.policies.decisions import SENSOR_POLICIES
    from drake_grasp.config.sections import POLICIES

    assert set(SENSOR_POLICIES) == set(POLICIES) - {"scripted"}
    assert len(set(SENSOR_POLICIES)) == len(SENSOR_POLICIES)
    assert BRIDGE_POLICIES == EXTRA_POLICIES == SENSOR_POLICIES


def test_a_builtin_policy_the_experiment_does_not_list_runs_as_an_extra_condition(
        tmp_path, monkeypatch):
    """`--conditions cnn-ctr` in clutter (whose conditions are ctr and gpd): the built-in
    policy runs as a condition of its own on the same seeds, with the settings every
    clutter condition shares (robot profile) and the closed-loop options; run.json records
    its identity; a listed name stays the experiment's own condition; an unknown name is
    refused naming what is allowed."""
    exp = dataclasses.replace(EXPERIMENTS["clutter"], patches=option_patches(ctr_text="{converge_step_ratio: 0.2}"))
    tasks = trial_plan.plan_tasks(exp, trials=2, seed=5, conditions=["ctr", "cnn-ctr"])
    assert [(t.condition, t.index, t.policy_spec) for t in tasks] == [
        ("ctr", 0, ""), ("cnn-ctr", 0, "cnn-ctr"), ("ctr", 1, ""), ("cnn-ctr", 1, "cnn-ctr")]
    extra = trial_plan.task_condition(tasks[1], exp)
    assert (extra.name, extra.policy, extra.noise) == ("cnn-ctr", "cnn-ctr", "none")
    from drake_grasp.evaluation.experiments import condition_scenario
    s = condition_scenario(exp, extra)
    assert s.policy == "cnn-ctr"
    assert (s.controller.step_ratio, s.controller.converge_step_ratio) == (0.5, 0.2)
    assert s.scene.clutter_objects == 10
    # perception lists cnn-ctr: it is that experiment's own condition, not an extra one
    own = trial_plan.plan_tasks(EXPERIMENTS["perception"], trials=1, seed=0, conditions=["cnn-ctr"])
    assert [(t.condition, t.policy_spec) for t in own] == [("cnn-ctr", "")]
    with pytest.raises(ValueError, match=r"\['scripted2'\] not in experiment clutter; its "
                                         r"conditions: \['ctr', 'gpd'\], a built-in policy "
                                         r"\['ctr', 'cnn-ctr'"):
        trial_plan.plan_tasks(exp, trials=1, seed=0, conditions=["scripted2"])

    def no_physics(*args, **kwargs):
        raise RuntimeError("no physics here (test)")

    monkeypatch.setattr(trial_worker, "_simulate", no_physics)
    kw = dict(experiment="smoke", out=tmp_path / "run", trials=1, workers=1, seed=3,
              progress=False, report=False)
    assert m.evaluate(conditions=["init", "cnn-only"], **kw)["ran"] == 2
    records = load_records(tmp_path / "run")
    assert {(r.condition, r.policy) for r in records} == {("init", "init"),
                                                          ("cnn-only", "cnn-only")}
    assert len({(r.seed, tuple(r.object_ids)) for r in records}) == 1  # the same trial
    ident = read_run_info(tmp_path / "run")["plugin_conditions"]["cnn-only"]
    assert ident["policy"] == "cnn-only" and "policy_source" not in ident
    assert len(ident["weights_sha256"]) == 64
    # a resume may leave it out or bring it back; other weights for it are another run
    assert m.evaluate(conditions=["init"], **kw)["ran"] == 0
    assert m.evaluate(conditions=["cnn-only"], **kw)["ran"] == 0
    other = tmp_path / "other.safetensors"
    shutil.copy(ROOT / "models" / "cnn" / "weights.safetensors",
                other)
    with pytest.raises(ValueError, match=r"plugin_conditions.cnn-only.scenario.controller.weights"):
        m.evaluate(conditions=["cnn-only"], patches=option_patches(weights=str(other)), **kw)


def test_the_replay_command_notes_a_record_from_another_machine(reference, tmp_path, capsys):
    import shutil

    from drake_grasp.cli.main import main
    from drake_grasp.evaluation.records import RUN_INFO_FILE, write_run_info

    out, _ = reference
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    trial = next(r.trial_id for r in load_records(copy) if r.condition == "init")
    assert main(["replay", str(copy), "--trial", trial, "--out", str(tmp_path / "a")]) == 0
    assert "note:" not in capsys.readouterr().err  # recorded on this machine
    info = read_run_info(copy)
    for s in info["sessions"]:
        s["machine"] = {**s["machine"], "cpu": "Another CPU (family 25, model 17, stepping 1)"}
    write_run_info(copy, info)
    assert (copy / RUN_INFO_FILE).is_file()
    assert main(["replay", str(copy), "--trial", trial, "--out", str(tmp_path / "b")]) == 0
    err = capsys.readouterr().err
    assert "drake-grasp replay: note: recorded on Another CPU (family 25" in err
