"""Benchmarks of a Monte Carlo worker and its trials (`drake-grasp bench --only
worker_rss_mb_per_trial,trial_overhead_fraction`).

Keys:
    worker_rss_mb_per_trial: growth of one worker process's resident memory per trial
        (least-squares slope of its RSS after each trial, the first `WARMUP` trials left
        out), 200 `fast` CTR isolation trials, each in a forked child (`hermetic`), as
        `evaluate` runs them (about 30 min on 2 cores). `_in_process`: the same trials
        run in the worker itself, as before the forked children, in a second worker at the
        same time (side by side on the same machine). `_detail`: trials, the RSS at the start and the end, the mean
        trial wall time of each side, the largest child RSS, and how many trials had the
        same outcome, failure class and control steps on both sides.
    trial_overhead_fraction: the share of a `fast` CTR isolation trial's wall time spent
        outside the plant's advance, timed without a profiler (`bench_trial_overhead`);
        `_profiled`: the same under cProfile, an upper bound.
"""

from __future__ import annotations

import functools
import os
import re
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


# Where a trial's time goes besides the plant's advance (cumulative seconds of these calls):
OVERHEAD_BUCKETS = {
    "cnn": ("evaluator.py", "score_candidates"),
    "final_distance": ("episode.py", "final_distance"),
    "controller_update": ("controller.py", "_Update"),
    "controller_pose_output": ("controller.py", "_CalcPose"),
    "gripper": ("gripper.py", "_CalcDesiredState"),
    "judge": ("judge.py", "_Update"),
    "depth_postprocess": ("depth.py", "_CalcDepthImage"),
    "build_diagram": ("episode.py", "build_episode_diagram"),
    "scene": ("scene.py", "scenario_scene"),
}


class CallbackClock:
    """Times, without a profiler, what a trial spends in the plant's advance and in the
    Python systems the advance calls: while active (a context manager), every
    `_Calc*` / `_Update*` / `_Initialize*` / `_Do*` method of drake_grasp's LeafSystems
    (`CALLBACK_MODULES`) and `Simulator.AdvanceTo` run through a timer. A callback that
    another one calls (through an input port's Eval) counts once, in the outermost.
    Install it before the Diagram is built: a system declares its bound callbacks then.

    Attributes:
        advance_s: wall seconds inside `AdvanceTo`.
        callbacks_s: wall seconds of those inside the outermost Python callbacks
            (rendering, the CNN and anything else they evaluate included).
    """

    CALLBACK_MODULES = ("drake_grasp.systems.depth", "drake_grasp.systems.disturbance",
                        "drake_grasp.systems.frames", "drake_grasp.systems.gripper",
                        "drake_grasp.systems.judge", "drake_grasp.systems.kinematic_noise",
                        "drake_grasp.systems.monitor", "drake_grasp.systems.supervisor",
                        "drake_grasp.policies.controller", "drake_grasp.policies.ctr",
                        "drake_grasp.policies.cnn_first_look", "drake_grasp.policies.evaluator",
                        "drake_grasp.policies.detector_controllers")
    _NAME = re.compile(r"^_(Calc|Update|Initialize|Do)")

    def __init__(self) -> None:
        self.advance_s = self.callbacks_s = 0.0
        self._in_advance, self._depth, self._saved = False, 0, []

    def _timed_callback(self, f):
        @functools.wraps(f)
        def timed(*args, **kwargs):
            if self._depth or not self._in_advance:
                self._depth += 1
                try:
                    return f(*args, **kwargs)
                finally:
                    self._depth -= 1
            self._depth, t0 = 1, time.perf_counter()
            try:
                return f(*args, **kwargs)
            finally:
                self.callbacks_s += time.perf_counter() - t0
                self._depth = 0
        return timed

    def _timed_advance(self, f):
        @functools.wraps(f)
        def timed(simulator, *args, **kwargs):
            self._in_advance, t0 = True, time.perf_counter()
            try:
                return f(simulator, *args, **kwargs)
            finally:
                self.advance_s += time.perf_counter() - t0
                self._in_advance = False
        return timed

    def __enter__(self) -> "CallbackClock":
        import importlib

        from pydrake.systems.analysis import Simulator_
        from pydrake.systems.framework import LeafSystem

        for name in self.CALLBACK_MODULES:
            module = importlib.import_module(name)
            for cls in vars(module).values():
                if (isinstance(cls, type) and issubclass(cls, LeafSystem)
                        and cls.__module__ == name):
                    for attr, f in list(vars(cls).items()):
                        if self._NAME.match(attr) and callable(f):
                            self._saved.append((cls, attr, f))
                            setattr(cls, attr, self._timed_callback(f))
        simulator = Simulator_[float]
        self._saved.append((simulator, "AdvanceTo", simulator.AdvanceTo))
        simulator.AdvanceTo = self._timed_advance(simulator.AdvanceTo)
        return self

    def __exit__(self, *exc) -> None:
        for owner, attr, f in reversed(self._saved):
            setattr(owner, attr, f)
        self._saved.clear()


def bench_trial_overhead(seeds=(0, 1, 2, 3, 4, 5)) -> dict:
    """`trial_overhead_fraction`: the share of a `fast` CTR isolation trial's wall time
    spent outside the plant's advance, 1 - (C++ advance) / (the trial's wall time), over
    `seeds` run one after another in this process after a first pass over the same seeds
    (imports, the first render, each scene's caches). The C++ advance is `AdvanceTo`'s
    wall time less that of the Python systems it calls (`CallbackClock`, timers without
    a profiler). `_profiled`: the same under cProfile, 1 - `AdvanceTo`'s own time / the
    trial's wall time (cProfile slows the Python parts, not the C++ ones, so that one is
    an upper bound); `_detail` has both runs' figures and cProfile's Python buckets per
    trial."""
    import cProfile
    import pstats

    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.objects import load_library
    from drake_grasp.policies.evaluator import load_cnn

    library, model = load_library(), load_cnn("", threads=1)

    def run(seed):
        scenario = load_scenario(scenario_name="isolation",
                                 scenario_text=f"{{seed: {seed}, policy: ctr}}")
        t0 = time.perf_counter()
        simulate_episode(scenario, library=library, record_depth=False, model=model)
        return time.perf_counter() - t0

    for seed in seeds:  # imports, first render, and each scene's caches (its objects)
        run(seed)
    with CallbackClock() as clock:
        timed = sum(run(s) for s in seeds)
    cpp = clock.advance_s - clock.callbacks_s
    profiler, profiled = cProfile.Profile(), 0.0
    for seed in seeds:
        profiler.enable()
        profiled += run(seed)
        profiler.disable()
    stats = pstats.Stats(profiler).stats
    advance = sum(v[2] for k, v in stats.items() if "AdvanceTo" in k[2])
    buckets = {key: round(sum(v[3] for k, v in stats.items()
                              if k[0].endswith(suffix) and k[2] == name) / len(seeds), 3)
               for key, (suffix, name) in OVERHEAD_BUCKETS.items()}
    n = len(seeds)
    return {"trial_overhead_fraction": round(1.0 - cpp / timed, 3),
            "trial_overhead_fraction_profiled": round(1.0 - advance / profiled, 3),
            "trial_overhead_fraction_detail": {
                "trials": n, "physics_profile": "fast",
                "wall_s_per_trial": round(timed / n, 3),
                "advance_s_per_trial": round(clock.advance_s / n, 3),
                "python_in_advance_s_per_trial": round(clock.callbacks_s / n, 3),
                "advance_cpp_s_per_trial": round(cpp / n, 3),
                "wall_s_per_trial_profiled": round(profiled / n, 3),
                "advance_cpp_s_per_trial_profiled": round(advance / n, 3),
                "python_s_per_trial_profiled": buckets}}
