"""Benchmarks of a Monte Carlo worker over many trials (`drake-grasp bench --only
worker_rss_mb_per_trial`).

Keys:
    worker_rss_mb_per_trial: growth of one worker process's resident memory per trial
        (least-squares slope of its RSS after each trial, the first `WARMUP` trials left
        out), `fast` CTR isolation trials, each in a forked child (`hermetic`), as
        `evaluate` runs them. `_in_process`: the same trials run in the worker itself, as
        before the forked children, in a second worker at the same time (side by side on
        the same machine). `_detail`: trials, the RSS at the start and the end, the mean
        trial wall time of each side, the largest child RSS, and how many trials had the
        same outcome, failure class and control steps on both sides.
"""

from __future__ import annotations

import os
import resource
import time

WARMUP = 10


def _rss_mb() -> float:
    """This process's resident set size [MB] (Linux /proc; ru_maxrss elsewhere)."""
    try:
        with open(f"/proc/{os.getpid()}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # pragma: no cover


def worker_series(trials: int, seed: int, hermetic: bool) -> dict:
    """In this process (a worker): `trials` isolation CTR trials one after the other, and
    the RSS after each. Returns {"rss_mb": [...], "wall_s": [...], "outcomes": [...],
    "child_max_rss_mb"}."""
    from drake_grasp.evaluation.experiments import get_experiment
    from drake_grasp.evaluation.trial_plan import plan_tasks
    from drake_grasp.evaluation.trial_worker import run_task

    tasks = plan_tasks(get_experiment("isolation"), trials=trials, seed=seed,
                       conditions=["ctr"])
    rss, wall, outcomes = [], [], []
    for task in tasks:
        t0 = time.perf_counter()
        (rec,) = run_task(task, hermetic=hermetic)
        wall.append(time.perf_counter() - t0)
        rss.append(round(_rss_mb(), 2))
        outcomes.append((rec["success"], rec["failure_class"], rec["control_steps"]))
    child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return {"rss_mb": rss, "wall_s": wall, "outcomes": outcomes,
            "child_max_rss_mb": round(child, 1) if hermetic else None}


def rss_slope_mb(rss: list[float], warmup: int = WARMUP) -> float:
    """Least-squares slope [MB per trial] of the RSS series after `warmup` trials."""
    import numpy as np

    y = np.asarray(rss[warmup:], dtype=float)
    if len(y) < 2:
        raise ValueError(f"rss: expected more than {warmup + 1} samples, got {len(rss)}")
    return float(np.polyfit(np.arange(len(y), dtype=float), y, 1)[0])


def bench_worker_rss(trials: int = 200, seed: int = 3) -> dict:
    """The module docstring's keys: two worker processes side by side, forked trials in
    one, trials in the worker itself in the other."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=2, mp_context=mp.get_context("spawn")) as pool:
        forked = pool.submit(worker_series, trials, seed, True)
        inproc = pool.submit(worker_series, trials, seed, False)
        a, b = forked.result(), inproc.result()
    same = sum(x == y for x, y in zip(a["outcomes"], b["outcomes"]))

    def side(s):
        return {"rss_start_mb": s["rss_mb"][0], "rss_end_mb": s["rss_mb"][-1],
                "mean_trial_wall_s": round(sum(s["wall_s"]) / len(s["wall_s"]), 3),
                "successes": sum(bool(o[0]) for o in s["outcomes"])}

    return {"worker_rss_mb_per_trial": round(rss_slope_mb(a["rss_mb"]), 3),
            "worker_rss_mb_per_trial_in_process": round(rss_slope_mb(b["rss_mb"]), 3),
            "worker_rss_mb_per_trial_detail": {
                "trials": trials, "warmup_trials_left_out": WARMUP,
                "forked": {**side(a), "child_max_rss_mb": a["child_max_rss_mb"]},
                "in_process": side(b), "same_outcome_class_steps": same}}
