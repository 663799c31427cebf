"""evaluate on a Dask cluster started as separate processes (`dask scheduler`, `dask
worker`), the worker unable to see the driver's folder: the records come back to the
driver, which writes them, and a user object library reaches the worker by content."""

import json
import os
import shutil
import subprocess
import sys
import time

import pytest

from drake_grasp.evaluation.montecarlo import evaluate
from drake_grasp.evaluation.records import load_records

HERE = os.path.dirname(os.path.abspath(__file__))


def _start(args, cwd, env, log):
    return subprocess.Popen([sys.executable, "-m", "dask", *args], cwd=cwd, env=env,
                            stdout=log, stderr=subprocess.STDOUT)


def _wait_for(path, procs, timeout_s=120.0):
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        if os.path.exists(path) and os.path.getsize(path) > 0:
            return json.loads(open(path).read())
        if any(p.poll() is not None for p in procs):
            break
        time.sleep(0.2)
    raise RuntimeError(f"the dask scheduler did not start ({path})")


@pytest.mark.slow
def test_a_separate_scheduler_and_worker_without_the_drivers_folder(tmp_path, library,
                                                                    monkeypatch):
    driver, remote = tmp_path / "driver", tmp_path / "worker"
    for oid in library.ids(split="test")[:2]:  # a user library, only in the driver's folder
        shutil.copytree(library.get(oid).directory, driver / "objects" / oid)
    remote.mkdir()
    env = dict(os.environ, DRAKE_GRASP_TEST_DRIVER_DIR=str(driver),
               DRAKE_GRASP_CACHE=str(remote / "cache"), PYTHONPATH=os.pathsep.join(
                   [os.path.dirname(HERE), HERE, os.environ.get("PYTHONPATH", "")]))
    sched_file = tmp_path / "scheduler.json"
    log = open(tmp_path / "dask.log", "w")
    procs = [_start(["scheduler", "--scheduler-file", str(sched_file), "--port", "0",
                     "--no-dashboard"], remote, env, log)]
    try:
        address = _wait_for(sched_file, procs)["address"]
        procs.append(_start(["worker", address, "--nworkers", "1", "--nthreads", "1",
                             "--no-dashboard", "--preload", "dask_worker_preload",
                             "--local-directory", str(remote / "dask")], remote, env, log))
        monkeypatch.chdir(driver)  # the driver names its folders relative to its own
        result = evaluate(experiment="smoke", out="results", trials=1, seed=3,
                          scheduler=address, objects_dir="objects", progress=False,
                          report=False)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        log.close()
    records = load_records(driver / "results")
    assert result["records"] == len(records) == 2, (tmp_path / "dask.log").read_text()[-3000:]
    assert [r.failure_class for r in records if r.condition == "init"] == ["none"]
    scripted = next(r for r in records if r.condition == "scripted")
    assert scripted.failure_class != "simulation-error", scripted.failure_reason
    assert {r.object_ids[0] for r in records} <= set(library.ids(split="test")[:2])
    # Nothing was written on the worker's side but the unpacked library in its own cache.
    assert not (remote / "results").exists() and not (remote / "objects").exists()
    (bundle,) = (remote / "cache" / "object-bundles").iterdir()
    assert sorted(p.name for p in bundle.iterdir()) == sorted(library.ids(split="test")[:2])
    assert bundle.name == json.loads((driver / "results" / "run.json").read_text())[
        "object_library_hash"]
