"""evaluation/hermetic: every trial in a forked child of its worker. A child that dies
becomes a simulation-error record naming the signal and stage, and the run goes on; what a
child allocates leaves with it."""

import os
import signal

import pytest

from drake_grasp.evaluation import hermetic as H
from drake_grasp.evaluation.montecarlo import evaluate
from drake_grasp.evaluation.records import load_records

pytestmark = pytest.mark.skipif(not H.available(), reason="needs os.fork (POSIX)")


def _stages_then(how):
    H.stage("scene")
    H.stage("simulation")
    if how == "segv":
        os.kill(os.getpid(), signal.SIGSEGV)
    if how == "exit":
        os._exit(3)
    if how == "raise":
        raise KeyError("no such object (test)")
    return {"pid": os.getpid(), "big": list(range(5))}


def _rss_kb():
    with open(f"/proc/{os.getpid()}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))


def _allocate(mb):
    block = bytearray(mb << 20)
    block[::4096] = b"x" * len(block[::4096])  # touch every page
    return len(block)


def test_a_child_returns_raises_or_dies_by_name():
    got = H.run_forked(_stages_then, "return")
    assert got["big"] == [0, 1, 2, 3, 4] and got["pid"] != os.getpid()
    with pytest.raises(KeyError, match="no such object"):
        H.run_forked(_stages_then, "raise")
    with pytest.raises(H.TrialProcessDied, match=r"killed by signal SIGSEGV \(11\) in stage "
                                                 r"'simulation'") as died:
        H.run_forked(_stages_then, "segv")
    assert (died.value.signal_name, died.value.stage, died.value.exit_code) == (
        "SIGSEGV", "simulation", None)
    with pytest.raises(H.TrialProcessDied, match="exited with code 3 without a result") as died:
        H.run_forked(_stages_then, "exit")
    assert died.value.exit_code == 3
    import pickle

    again = pickle.loads(pickle.dumps(died.value))
    assert (str(again), again.stage, again.exit_code) == (str(died.value), "simulation", 3)
    H.stage("outside a child")  # a no-op here


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux /proc")
def test_what_a_child_allocates_leaves_with_it():
    before = _rss_kb()
    for _ in range(3):
        assert H.run_forked(_allocate, 200) == 200 << 20
    assert _rss_kb() - before < 20 * 1024  # KB: 600 MB allocated in children, none here


_SEGFAULT_RUN = """
import sys
from drake_grasp.evaluation.montecarlo import evaluate
from drake_grasp.evaluation.records import load_records
evaluate(experiment="smoke", out=sys.argv[1], trials=2, workers=int(sys.argv[2]), seed=3,
         progress=False, report=False, fail_trials=("smoke/scripted/0001:segfault",))
print("records", len(load_records(sys.argv[1])))
"""


@pytest.mark.parametrize("workers", [1, 2])
def test_a_trial_that_segfaults_is_recorded_and_the_run_goes_on(tmp_path, workers):
    """In a fresh process (workers=1 runs the trials in it: this one may have rendered,
    and a process that has rendered does not fork its trials)."""
    import subprocess
    import sys

    out = tmp_path / f"w{workers}"
    done = subprocess.run([sys.executable, "-c", _SEGFAULT_RUN, str(out), str(workers)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and "records 4" in done.stdout, done.stderr[-2000:]
    records = {r.trial_id: r for r in load_records(out)}
    bad = records["smoke/scripted/0001"]
    assert (bad.success, bad.failure_class) == (False, "simulation-error")
    assert "killed by signal SIGSEGV (11) in stage 'simulation'" in bad.failure_reason
    assert bad.extra["error_stage"] == "simulation" and bad.seed == records[
        "smoke/init/0001"].seed and bad.scenario_yaml  # named by its scenario
    good = records["smoke/scripted/0000"]
    assert good.failure_class != "simulation-error" and good.sim_time_s > 0


def test_a_process_that_has_rendered_runs_its_trials_itself(tmp_path):
    """A GL driver's threads do not survive a fork: once this process has rendered, its
    trials run in it (a forced segfault is then refused, not done)."""
    from drake_grasp.api import load_library, load_scenario, simulate_episode
    from drake_grasp.core.native import gl_driver_loaded

    simulate_episode(load_scenario(scenario_name="isolation", scenario_text="{seed: 3}"),
                     library=load_library(), record_depth=False)
    assert gl_driver_loaded()
    evaluate(experiment="smoke", out=tmp_path / "r", trials=1, workers=1, seed=3,
             progress=False, report=False, fail_trials=("smoke/scripted/0000:segfault",))
    bad = {r.trial_id: r for r in load_records(tmp_path / "r")}["smoke/scripted/0000"]
    assert "forced segfault (test) asked of a trial not in a forked child" in bad.failure_reason


_WARM_THEN_FORK = """
import signal, torch
from drake_grasp.evaluation import hermetic as H, trial_worker
from drake_grasp.evaluation.experiments import get_experiment
from drake_grasp.evaluation.trial_plan import plan_tasks, task_condition

def parallel_copy():
    signal.alarm(60)  # a hung child dies of SIGALRM instead of hanging the test
    x = torch.ones(1 << 22)
    y = torch.empty_like(x)
    y.copy_(x)  # a parallel region: torch has 2 threads
    return float(y.sum())

torch.set_num_threads(2)
experiment = get_experiment("sim-distance")
(task,) = plan_tasks(experiment, trials=1, seed=0, conditions=["ctr"])
trial_worker._warm(experiment, task_condition(task, experiment), None)
assert torch.get_num_threads() == 2
print("child copied", H.run_forked(parallel_copy))
"""


def test_a_warm_worker_leaves_its_children_free_to_run_torch_on_threads():
    """GNU OpenMP's thread team does not survive a fork: `_warm` loads the CNN without
    one, so a child's multi-threaded torch op (GPD's classifier) does not hang. In a fresh
    process: this one may have run torch on threads already."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", _WARM_THEN_FORK], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"child copied {float(1 << 22)}" in done.stdout


def _fds():
    return len(os.listdir("/proc/self/fd"))


@pytest.mark.skipif(not os.path.exists("/proc/self/fd"), reason="Linux /proc")
def test_a_hung_child_is_killed_at_the_limit_and_a_failed_fork_is_named(monkeypatch):
    import time

    before = _fds()
    with pytest.raises(H.TrialProcessDied, match=r"killed after 1 s \(the time limit\) in "
                                                 r"stage 'simulation'"):
        H.run_forked(_sleep_in_stage, 30, timeout_s=1.0)
    assert _fds() == before

    def no_fork():
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(os, "fork", no_fork)
    with pytest.raises(H.TrialProcessDied, match="could not fork a trial process: .*"
                                                 "Resource temporarily unavailable") as died:
        H.run_forked(time.sleep, 0, stage="scene")
    assert died.value.stage == "scene" and _fds() == before


def _sleep_in_stage(seconds):
    import time

    H.stage("simulation")
    time.sleep(seconds)
