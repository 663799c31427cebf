"""The worker side of a Monte Carlo run: `run_task` runs one `TrialTask` and returns its
record(s) - an episode, or a whole clutter run of attempts on one pile that ends by
`clutter_run_status` - for the driver to write (the driver owns the results folder).

Any exception inside a trial (building its scenario or scene, simulating, settling the
pile left for the next attempt) becomes a "simulation-error" record with its reason and
stage. Each episode or clutter attempt runs in a child forked from the worker
(`hermetic.run_forked`): a child that dies (a signal, the out-of-memory killer) becomes a
"simulation-error" record naming the signal and stage, and what a trial allocates goes
with its child, so the worker's memory stays flat. The worker caches what does not change
between trials (the object library and its meshes, the CNN) before it forks, so every
child starts warm.
"""

from __future__ import annotations

import dataclasses
import time
import traceback

import numpy as np

from drake_grasp.evaluation.experiments import (CNN_POLICIES, Condition, Experiment,
                                                condition_scenario, trial_scenario, trial_seed)
from drake_grasp.evaluation.run_folder import config_hash
from drake_grasp.evaluation.trial_plan import TrialTask, task_condition, task_experiment
from drake_grasp.core.provenance import code_version
from drake_grasp.policies.decisions import NO_GRASP_FOUND, TRACK_RECORD_KEYS

# A clutter run ends after this many simulation errors in a row (see `clutter_run_status`).
MAX_CONSECUTIVE_SIMULATION_ERRORS = 3
# No clutter run goes beyond this many attempts (the paper: 74 CTR attempts in 10 runs).
MAX_ATTEMPTS_PER_RUN = 60
# A clutter run ends when no object is left within +-15 cm (x and y) of the pile's centre:
# what the wrist camera sees from its start pose (0.3 m above the table, 55 degrees of
# vertical field of view: +-0.156 m).
IN_VIEW_HALF_EXTENT_M = 0.15


_WORKER_CACHE: dict = {}


def _cached(key, make):
    if key not in _WORKER_CACHE:
        _WORKER_CACHE[key] = make()
    return _WORKER_CACHE[key]


def _library(objects_dir, objects=None):
    """The object library of `objects_dir` (None: the built-in objects). `objects`, an
    `object_bundle.ObjectBundle` from the driver, makes it reach a worker that cannot see
    that folder: by content, checked by hash."""
    if objects is not None:
        from drake_grasp.objects.bundle import library_from_bundle

        return _cached(("library", objects.content_hash), lambda: library_from_bundle(objects))
    from drake_grasp.objects import load_library

    return _cached(("library", objects_dir), lambda: load_library(objects_dir))


def _warm(experiment, condition, objects_dir) -> None:
    """Loads in this process what every trial of the condition uses (the CNN, the modules
    of an episode), so that forked trial children start with it.

    Nothing here runs torch on more than one thread: GNU OpenMP's thread team does not
    survive a fork, and a child whose parent had one hangs in its first parallel torch op
    (seen: GPD's classifier after the CNN was loaded with 2 threads)."""
    import torch

    import drake_grasp.evaluation.episode  # noqa: F401 - imported once, before forking

    try:
        scenario = condition_scenario(experiment, condition, objects_dir=objects_dir)
    except Exception:  # noqa: BLE001 - the trial records its own error
        return
    if scenario.policy in CNN_POLICIES:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            _model(scenario.controller.weights, scenario.controller.torch_threads)
        finally:
            torch.set_num_threads(threads)  # what the children start with, as before


def _model(weights: str, threads: int = 1):
    from drake_grasp.policies.evaluator import load_cnn

    return _cached(("cnn", weights, threads), lambda: load_cnn(weights, threads=threads))


def _condition_hash(task: TrialTask, condition: Condition, objects_dir) -> str:
    """config_hash of the condition's shared scenario ("unresolved" when it cannot be built)."""
    from drake_grasp.config.scenario import dump_scenario

    try:
        experiment = task_experiment(task)
        return config_hash(dump_scenario(
            condition_scenario(experiment, condition, objects_dir=objects_dir)))
    except Exception:  # noqa: BLE001 - the trial records its own error
        return "unresolved"


def _forced(fail_trials, trial_id: str, stage: str | None = None) -> None:
    """Raises where `fail_trials` asks for it (see `run_task`)."""
    if (f"{trial_id}:{stage}" if stage else trial_id) in fail_trials:
        raise RuntimeError(f"forced failure (test) in {stage or 'simulation'}")


def _record_for(task: TrialTask, condition: Condition, scenario, result=None, *,
                error: BaseException | None = None, wall: float = 0.0, run_index=None,
                attempt_index=None, trial_id=None, extra=None, objects_dir=None,
                stage: str = "simulation"):
    """The record of a finished trial (`result`) or of one that raised (`error`, raised
    in `stage`: "scene", "simulation" or "settle"). `scenario` is None when the trial's
    scenario could not be built; the record then has an empty scenario_yaml and the
    trial's seed."""
    from drake_grasp.evaluation.records import TrialRecord, classify_failure
    from drake_grasp.config.scenario import dump_scenario

    yaml = dump_scenario(scenario) if scenario is not None else ""
    seed = int(scenario.seed) if scenario is not None else trial_seed(task.base_seed, task.index)
    chash = _condition_hash(task, condition, objects_dir)
    if result is None:
        reason = f"simulation error: {type(error).__name__}: {error}"
        return TrialRecord(
            trial_id=trial_id or task.trial_id, experiment=task.experiment,
            condition=task.condition, policy=condition.policy, noise=condition.noise,
            noise_scale=condition.noise_scale, depth_noise=condition.depth_noise > 0,
            offset_m=condition.offset_m, disturbance={"kind": condition.disturbance},
            scenario_name=task_experiment(task).scenario, scenario_yaml=yaml,
            seed=seed, config_hash=chash, code_version=code_version(),
            success=False, failure_class=classify_failure(False, reason, exception=error),
            failure_reason=reason, final_distance_m=None, sim_time_s=0.0, wall_time_s=wall,
            control_steps=0, object_ids=[], grasped_object_id=None, run_index=run_index,
            attempt_index=attempt_index,
            extra={"traceback": "".join(traceback.format_exception(error))[-4000:],
                   "error_stage": stage, **(extra or {})})
    r = result
    return TrialRecord(
        trial_id=trial_id or task.trial_id, experiment=task.experiment,
        condition=task.condition, policy=condition.policy, noise=condition.noise,
        noise_scale=condition.noise_scale, depth_noise=condition.depth_noise > 0,
        offset_m=condition.offset_m, disturbance=r.disturbance,
        scenario_name=task_experiment(task).scenario, scenario_yaml=yaml,
        seed=seed, config_hash=chash, code_version=code_version(),
        success=bool(r.success),
        failure_class=classify_failure(r.success, r.failure_reason, disturbance=r.disturbance),
        failure_reason=r.failure_reason, final_distance_m=r.final_distance_m,
        sim_time_s=r.sim_time_s, wall_time_s=wall, control_steps=r.control_steps,
        object_ids=r.object_ids, grasped_object_id=r.details.get("grasped_object_id"),
        run_index=run_index, attempt_index=attempt_index,
        extra={"stop_reason": r.details.get("stop_reason"),
               "decision_time_s": r.details.get("decision_time_s"),
               "decisions": r.details.get("decisions", 0),
               # Where the hand closed (None when it never closed).
               "hand_at_close_xy_yaw": (r.details.get("hand_at_close_xy_yaw")
                                        if r.details.get("gripper_closed") else None),
               **({"policy_inputs": r.details["policy_inputs"]}
                  if "policy_inputs" in r.details else {}),
               **({"gpd_detection": r.details["gpd_detection"]}
                  if "gpd_detection" in r.details else {}),
               # gpd-track's last estimate of the scene's motion (`policies.gpd_track`).
               **{key: r.details[key] for key in TRACK_RECORD_KEYS if key in r.details},
               **(extra or {})})


def run_task(task: TrialTask, objects_dir: str | None = None, fail_trials: tuple = (),
             prior: tuple = (), attempts: int = 0, *, objects=None,
             hermetic: bool = True) -> list[dict]:
    """Runs one task and returns its record(s) as dicts, in order; writes nothing.

    Args:
        task: The trial (or clutter run: its next `attempts`) to run.
        objects_dir: The run's object library folder as the driver names it (recorded in
            the scenarios); None for the built-in objects.
        fail_trials: For testing the error paths: "<trial id>" makes that trial's (or
            clutter attempt's) simulation raise; "<trial id>:scene" makes building its
            scenario and scene raise (for a clutter run: the run's trial id, e.g.
            "clutter/ctr/0000:scene"); "<attempt id>:settle" makes settling the pile that
            clutter attempt leaves raise; "<trial id>:segfault" makes its process die of
            SIGSEGV in the simulation.
        prior: A clutter run's attempt records written before (dicts), to resume after.
        attempts: A clutter run's attempts to run in this call at most (0: until the run
            ends); the driver runs one per task.
        objects: The library's `ObjectBundle` when the worker may not see `objects_dir`.
        hermetic: Run each episode / attempt in a forked child (`hermetic.run_forked`);
            False runs it in this process (so does a process without fork, or one that
            has rendered: `core.native.gl_driver_loaded`).
    """
    from drake_grasp.core.native import gl_driver_loaded
    from drake_grasp.evaluation import hermetic as H

    experiment = task_experiment(task)
    condition = task_condition(task, experiment)
    library = _library(objects_dir, objects)
    # A process that has rendered (a GL driver's threads and contexts do not survive a
    # fork) runs its trials itself, as before: a worker of `evaluate` never renders, but
    # workers=1 runs in the caller's process, which may have.
    fork = hermetic and H.available() and not gl_driver_loaded()
    if fork:
        _warm(experiment, condition, objects_dir)
    ctx = _TrialContext(task, experiment, condition, objects_dir, library, tuple(fail_trials),
                        fork)
    if experiment.kind == "clutter-runs":
        from drake_grasp.evaluation.records import TrialRecord

        records = _run_clutter(ctx, [TrialRecord.from_dict(d, source="prior record")
                                     for d in prior], attempts)
    else:
        records = [ctx.isolated(_run_episode_task, ctx, stage="scene")]
    return [r.to_dict() for r in records]


@dataclasses.dataclass
class _TrialContext:
    """What every stage of one task needs, and how it isolates a trial."""

    task: TrialTask
    experiment: Experiment
    condition: Condition
    objects_dir: str | None
    library: object
    fail_trials: tuple
    fork: bool

    def error_record(self, error, *, scenario=None, stage="simulation", wall=0.0, **kw):
        return _record_for(self.task, self.condition, scenario, error=error, stage=stage,
                           wall=wall, objects_dir=self.objects_dir, **kw)

    def isolated(self, fn, *args, stage: str, scenario=None, **record_kw):
        """`fn(*args)` (which returns a record and records its own exceptions), in a forked
        child when `fork`; a child that dies becomes a simulation-error record naming the
        signal (or exit code) and the last stage it reported (`stage` until it reports
        one)."""
        from drake_grasp.evaluation import hermetic as H

        if not self.fork:
            return fn(*args)
        t0 = time.perf_counter()
        try:
            return H.run_forked(fn, *args, stage=stage)
        except H.TrialProcessDied as e:
            if scenario is None:
                scenario = self._scenario_or_none()
            return self.error_record(e, scenario=scenario, stage=e.stage,
                                     wall=time.perf_counter() - t0, **record_kw)

    def _scenario_or_none(self):
        try:
            return trial_scenario(self.experiment, self.condition, self.task.index,
                                  base_seed=self.task.base_seed, objects_dir=self.objects_dir,
                                  library=self.library)
        except Exception:  # noqa: BLE001 - the record then has no scenario
            return None


def _simulate(scenario, library, *, scene=None):
    from drake_grasp.evaluation.episode import simulate_episode

    model = (_model(scenario.controller.weights, scenario.controller.torch_threads)
             if scenario.policy in CNN_POLICIES else None)
    return simulate_episode(scenario, library=library, scene=scene, record_depth=False,
                            visualize=False, model=model)


def _stage(ctx: _TrialContext, trial_id: str, stage: str) -> None:
    """Enters `stage` of a trial: reported to the worker (named if the child dies), and
    the forced failures of tests (`run_task`'s fail_trials) raised or died of here."""
    from drake_grasp.evaluation import hermetic as H

    H.stage(stage)
    _forced(ctx.fail_trials, trial_id, None if stage == "simulation" else stage)
    if stage == "simulation" and f"{trial_id}:segfault" in ctx.fail_trials:
        if not ctx.fork:
            raise RuntimeError("forced segfault (test) asked of a trial not in a forked child")
        import ctypes

        ctypes.string_at(0)  # reads address 0: SIGSEGV, as a crash in a native library


def _run_episode_task(ctx: _TrialContext):
    task = ctx.task
    t0 = time.perf_counter()
    scenario = None
    stage = "scene"
    try:
        stage = "scene"
        _stage(ctx, task.trial_id, stage)
        scenario = trial_scenario(ctx.experiment, ctx.condition, task.index,
                                  base_seed=task.base_seed, objects_dir=ctx.objects_dir,
                                  library=ctx.library)
        stage = "simulation"
        _stage(ctx, task.trial_id, stage)
        run = _simulate(scenario, ctx.library)
        return _record_for(task, ctx.condition, scenario, run.result,
                           objects_dir=ctx.objects_dir, wall=time.perf_counter() - t0)
    except Exception as e:  # noqa: BLE001 - any failure inside a trial is recorded
        return ctx.error_record(e, scenario=scenario, stage=stage, wall=time.perf_counter() - t0)


def _objects_in_view(scene, half_extent_m: float = IN_VIEW_HALF_EXTENT_M) -> bool:
    c = np.asarray(scene.center_xy_m)
    return any(np.all(np.abs(np.asarray(o.xyz[:2]) - c) < half_extent_m) and o.xyz[2] > -0.01
               for o in scene.objects)


def clutter_run_status(records, experiment: Experiment) -> str | None:
    """Why a clutter run has ended, from its attempt records; None while it goes on.

    The one rule, used both to run (`_run_clutter`) and to decide on resume which runs
    are finished:

    - a run whose scene (scenario, poured and settled pile) could not be built ends with
      its first record, a simulation error ("scene could not be built");
    - simulation errors (failure_class "simulation-error") neither count towards nor reset
      the run of consecutive failed grasps: they are failures of the simulator, not of the
      policy, and the attempt is retried on the same pile (with the next attempt's seed);
    - the run ends after `experiment.max_consecutive_failures` failed grasps in a row,
      and, with `experiment.end_on_no_detection`, when the policy found no grasp;
    - so that a pile on which every attempt raises cannot loop for ever, it ends after
      `MAX_CONSECUTIVE_SIMULATION_ERRORS` (3) simulation errors in a row;
    - it ends when no object is left, or none is left in view;
    - a successful grasp that left the pile as large as it was (the judge named an object
      that the pile does not hold) ends it, since the next attempt would face the same
      pile; and no run goes beyond `MAX_ATTEMPTS_PER_RUN` attempts.

    Args:
        records: The run's attempt records (any order).
        experiment: The experiment.
    """
    from drake_grasp.world.scene import SceneSpec

    records = sorted(records, key=lambda r: r.attempt_index)
    if not records:
        return None
    failures = errors = 0
    for r in records:
        if r.failure_class == "simulation-error":
            errors += 1
        else:
            errors = 0
            failures = 0 if r.success else failures + 1
    nxt = records[-1].extra.get("next_scene")
    if nxt is None:
        return "scene could not be built"
    if experiment.end_on_no_detection and records[-1].failure_reason == NO_GRASP_FOUND:
        return "no grasp found"
    if failures >= experiment.max_consecutive_failures:
        return f"{experiment.max_consecutive_failures} consecutive failed grasps"
    if errors >= MAX_CONSECUTIVE_SIMULATION_ERRORS:
        return f"{MAX_CONSECUTIVE_SIMULATION_ERRORS} consecutive simulation errors"
    if len(records) >= MAX_ATTEMPTS_PER_RUN:
        return f"{MAX_ATTEMPTS_PER_RUN} attempts (the cap per run)"
    last = records[-1]
    if last.success and "scene" in last.extra and (
            len(nxt.get("objects", [])) >= len(last.extra["scene"].get("objects", []))):
        return (f"a successful grasp removed no object from the pile (grasped object "
                f"{last.grasped_object_id!r})")
    nxt = SceneSpec.from_dict(nxt)
    if not nxt.objects:
        return "no objects left"
    if not _objects_in_view(nxt):
        return "no objects left in view"
    return None


def failed_closings(records) -> list[float]:
    """The hand's poses (x, y, yaw_deg, flat) where a clutter run's earlier attempts
    closed the gripper and held nothing: what `FailureMemoryConfig` remembers. Attempts
    that never closed (no detection, a simulation error) leave nothing."""
    out: list[float] = []
    for r in sorted(records, key=lambda r: r.attempt_index):
        pose = r.extra.get("hand_at_close_xy_yaw")
        if not r.success and r.failure_class != "simulation-error" and pose is not None:
            out += [float(v) for v in pose]
    return out


def _run_clutter(ctx: _TrialContext, prior: list, attempts: int = 0) -> list:
    """One clutter run: attempts on one pile, each grasped object removed, until
    `clutter_run_status` says it has ended (its docstring has the rule). Resumes after the
    `prior` attempts (each record carries the scene left for the next one). Building the
    scenario and pile, every attempt and the settling of the pile it leaves run inside the
    error capture, each attempt in its own forked child: an exception, or a child that
    dies, becomes a "simulation-error" record. The record that ends the run has the reason
    in `extra["run_end"]`. Runs at most `attempts` attempts (0: until the run ends) and
    returns the attempts run now."""
    from drake_grasp.world.scene import SceneSpec

    task = ctx.task
    prefix = f"{task.trial_id}/attempt"
    records = sorted(prior, key=lambda r: r.attempt_index)
    status = clutter_run_status(records, ctx.experiment)
    new: list = []
    if status is not None:
        return new
    attempt = len(records)

    def finish(rec):
        nonlocal status
        status = clutter_run_status(records + [rec], ctx.experiment)
        if status is not None:
            rec.extra["run_end"] = status
        records.append(rec)
        new.append(rec)

    t0 = time.perf_counter()
    scenario = None
    try:
        if not records:
            _forced(ctx.fail_trials, task.trial_id, "scene")
        scenario = trial_scenario(ctx.experiment, ctx.condition, task.index,
                                  base_seed=task.base_seed, objects_dir=ctx.objects_dir,
                                  library=ctx.library)
        if records:
            scene = SceneSpec.from_dict(records[-1].extra["next_scene"])
        elif ctx.fork:  # a child that dies pouring raises TrialProcessDied here
            from drake_grasp.evaluation import hermetic as H

            scene = H.run_forked(_pour_pile, scenario, ctx.library, stage="scene")
        else:
            scene = _pour_pile(scenario, ctx.library)
    except Exception as e:  # noqa: BLE001 - any failure inside a trial is recorded
        finish(ctx.error_record(e, scenario=scenario, stage="scene",
                                wall=time.perf_counter() - t0, run_index=task.index,
                                attempt_index=attempt, trial_id=f"{prefix}{attempt:02d}",
                                extra={"scene": None, "next_scene": None}))
        return new

    while status is None and not (attempts and len(new) >= attempts):
        attempt_scenario = dataclasses.replace(scenario, seed=scenario.seed + 1000 * attempt)
        if scenario.failure_memory.radius_m > 0.0:
            attempt_scenario.failure_memory = dataclasses.replace(
                scenario.failure_memory, failed_xy_yaw=failed_closings(records))
        trial_id = f"{prefix}{attempt:02d}"
        rec = ctx.isolated(_clutter_attempt, ctx, attempt_scenario, scene, attempt,
                           stage="simulation", scenario=attempt_scenario, run_index=task.index,
                           attempt_index=attempt, trial_id=trial_id,
                           extra={"next_scene": scene.to_dict(), "scene": scene.to_dict()})
        finish(rec)
        scene = SceneSpec.from_dict(rec.extra["next_scene"])
        attempt += 1
    return new


def _pour_pile(scenario, library):
    """The scenario's pile, poured and settled (a clutter run's first scene)."""
    from drake_grasp.evaluation import hermetic as H
    from drake_grasp.world.scene import scenario_scene

    H.stage("scene")
    return scenario_scene(scenario, library)


def _clutter_attempt(ctx: _TrialContext, attempt_scenario, scene, attempt: int):
    """One clutter attempt on `scene` and the settling of the pile it leaves: its record,
    with the scene it faced and the next one (the same pile when it raised)."""
    from drake_grasp.world.scene import settle_options, settle_scene

    task, scenario = ctx.task, attempt_scenario
    trial_id = f"{task.trial_id}/attempt{attempt:02d}"
    t0 = time.perf_counter()
    stage = "simulation"
    try:
        stage = "simulation"
        _stage(ctx, trial_id, stage)
        run = _simulate(attempt_scenario, ctx.library, scene=scene)
        remaining = run.final_scene
        grasped = run.result.details.get("grasped_object_id") if run.result.success else None
        objects = [o for o in remaining.objects if o.object_id != grasped and o.xyz[2] > -0.05]
        stage = "settle"
        _stage(ctx, trial_id, stage)
        next_scene = settle_scene(dataclasses.replace(remaining, objects=objects), ctx.library,
                                  plant_config=scenario.plant, physics=scenario.physics,
                                  sheet_moves=scenario.sheet_moves,
                                  **settle_options(scenario.scene)) if objects else \
            dataclasses.replace(remaining, objects=[], settled=True)
        return _record_for(task, ctx.condition, attempt_scenario, run.result,
                           wall=time.perf_counter() - t0, run_index=task.index,
                           attempt_index=attempt, trial_id=trial_id,
                           objects_dir=ctx.objects_dir,
                           extra={"next_scene": next_scene.to_dict(), "scene": scene.to_dict()})
    except Exception as e:  # noqa: BLE001 - any failure inside a trial is recorded
        return ctx.error_record(e, scenario=attempt_scenario, stage=stage,
                                wall=time.perf_counter() - t0, run_index=task.index,
                                attempt_index=attempt, trial_id=trial_id,
                                extra={"next_scene": scene.to_dict(), "scene": scene.to_dict()})
