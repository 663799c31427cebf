"""Runs an experiment's trials on a local process pool or a Dask cluster, resumably.

Every finished trial is one record file (`drake_grasp.results`), written atomically by
the worker that ran it; re-running into the same folder skips finished trials, so a
killed run loses nothing and counts nothing twice. An exception inside a trial becomes a
failed trial ("simulation-error") with its reason; the run goes on.

Each worker process keeps what does not change between trials - the CNN, the object
library and its meshes - and builds only the plant per trial (the objects differ from
trial to trial, and a MultibodyPlant cannot change its bodies once finalized).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drake_grasp import __version__
from drake_grasp.experiments import Condition, Experiment, get_experiment, trial_scenario


@dataclass(frozen=True)
class TrialTask:
    """One unit of work: an episode, or a whole clutter run (several attempts)."""

    experiment: str
    condition: str
    index: int
    base_seed: int

    @property
    def trial_id(self) -> str:
        return f"{self.experiment}/{self.condition}/{self.index:04d}"


def plan_tasks(experiment: Experiment, *, trials: int | None, seed: int,
               conditions: list[str] | None = None) -> list[TrialTask]:
    n = experiment.trials if trials is None else int(trials)
    if n < 1:
        raise ValueError(f"--trials: expected >= 1, got {n}")
    names = [c.name for c in experiment.conditions]
    if conditions:
        unknown = [c for c in conditions if c not in names]
        if unknown:
            raise ValueError(f"--conditions: {unknown} not in experiment "
                             f"{experiment.name}; its conditions: {names}")
        names = [c for c in names if c in conditions]
    return [TrialTask(experiment.name, c, i, int(seed)) for i in range(n) for c in names]


def _condition(experiment: Experiment, name: str) -> Condition:
    for c in experiment.conditions:
        if c.name == name:
            return c
    raise ValueError(f"experiment {experiment.name}: no condition {name!r}")


def config_hash(scenario_yaml: str) -> str:
    return hashlib.sha256(scenario_yaml.encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------
# Worker side.

_WORKER_CACHE: dict = {}


def _cached(key, make):
    if key not in _WORKER_CACHE:
        _WORKER_CACHE[key] = make()
    return _WORKER_CACHE[key]


def _library(objects_dir):
    from drake_grasp.objects import load_library

    return _cached(("library", objects_dir), lambda: load_library(objects_dir))


def _model(weights: str):
    from drake_grasp.systems.evaluator import load_cnn

    return _cached(("cnn", weights), lambda: load_cnn(weights))


def _record_for(task: TrialTask, condition: Condition, scenario, result=None, *,
                error: BaseException | None = None, wall: float = 0.0, run_index=None,
                attempt_index=None, trial_id=None, extra=None):
    from drake_grasp.results import TrialRecord, classify_failure
    from drake_grasp.scenario import dump_scenario

    yaml = dump_scenario(scenario)
    if result is None:
        reason = f"simulation error: {type(error).__name__}: {error}"
        return TrialRecord(
            trial_id=trial_id or task.trial_id, experiment=task.experiment,
            condition=task.condition, policy=condition.policy, noise=condition.noise,
            noise_scale=condition.noise_scale, depth_noise=condition.depth_noise > 0,
            offset_m=condition.offset_m, disturbance={"kind": condition.disturbance},
            scenario_name=get_experiment(task.experiment).scenario, scenario_yaml=yaml,
            seed=int(scenario.seed), config_hash=config_hash(yaml), code_version=__version__,
            success=False, failure_class=classify_failure(False, reason, exception=error),
            failure_reason=reason, final_distance_m=None, sim_time_s=0.0, wall_time_s=wall,
            control_steps=0, object_ids=[], grasped_object_id=None, run_index=run_index,
            attempt_index=attempt_index,
            extra={"traceback": "".join(traceback.format_exception(error))[-4000:],
                   **(extra or {})})
    r = result
    return TrialRecord(
        trial_id=trial_id or task.trial_id, experiment=task.experiment,
        condition=task.condition, policy=condition.policy, noise=condition.noise,
        noise_scale=condition.noise_scale, depth_noise=condition.depth_noise > 0,
        offset_m=condition.offset_m, disturbance=r.disturbance,
        scenario_name=get_experiment(task.experiment).scenario, scenario_yaml=yaml,
        seed=int(scenario.seed), config_hash=config_hash(yaml), code_version=__version__,
        success=bool(r.success),
        failure_class=classify_failure(r.success, r.failure_reason, disturbance=r.disturbance),
        failure_reason=r.failure_reason, final_distance_m=r.final_distance_m,
        sim_time_s=r.sim_time_s, wall_time_s=wall, control_steps=r.control_steps,
        object_ids=r.object_ids, grasped_object_id=r.details.get("grasped_object_id"),
        run_index=run_index, attempt_index=attempt_index,
        extra={"stop_reason": r.details.get("stop_reason"), **(extra or {})})


def run_task(task: TrialTask, out: str, objects_dir: str | None = None,
             fail_trials: tuple = ()) -> list[dict]:
    """Runs one task in this process and writes its record(s); returns them as dicts.

    `fail_trials`: trial ids forced to raise (for testing the error path).
    """
    from drake_grasp.results import write_record

    experiment = get_experiment(task.experiment)
    condition = _condition(experiment, task.condition)
    library = _library(objects_dir)
    if experiment.kind == "clutter-runs":
        records = _run_clutter(task, experiment, condition, out, objects_dir, library, fail_trials)
    else:
        records = [_run_episode_task(task, experiment, condition, objects_dir, library, fail_trials)]
        write_record(out, records[0])
    return [r.to_dict() for r in records]


def _simulate(scenario, library, *, scene=None):
    from drake_grasp.episode import simulate_episode

    model = _model(scenario.controller.weights) if scenario.policy in ("ctr", "cnn-only", "cnn-ctr") else None
    return simulate_episode(scenario, library=library, scene=scene, record_depth=False,
                            visualize=False, model=model)


def _run_episode_task(task, experiment, condition, objects_dir, library, fail_trials):
    t0 = time.perf_counter()
    scenario = trial_scenario(experiment, condition, task.index, base_seed=task.base_seed,
                              objects_dir=objects_dir, library=library)
    try:
        if task.trial_id in fail_trials:
            raise RuntimeError("forced failure (test)")
        run = _simulate(scenario, library)
    except Exception as e:  # noqa: BLE001 - any failure inside a trial is recorded
        return _record_for(task, condition, scenario, error=e, wall=time.perf_counter() - t0)
    return _record_for(task, condition, scenario, run.result, wall=time.perf_counter() - t0)


def _objects_in_view(scene, half_extent_m: float = 0.15) -> bool:
    c = np.asarray(scene.center_xy_m)
    return any(np.all(np.abs(np.asarray(o.xyz[:2]) - c) < half_extent_m) and o.xyz[2] > -0.01
               for o in scene.objects)


def _run_clutter(task, experiment, condition, out, objects_dir, library, fail_trials):
    """One clutter run: attempts on one pile, each grasped object removed, until
    `max_consecutive_failures` failures in a row or nothing left in view. Resumes after
    the last recorded attempt (each record carries the scene left for the next one)."""
    from drake_grasp.results import load_records, write_record
    from drake_grasp.scene import SceneSpec, make_scene, settle_scene

    scenario = trial_scenario(experiment, condition, task.index, base_seed=task.base_seed,
                              objects_dir=objects_dir, library=library)
    prefix = f"{task.trial_id}/attempt"
    done = sorted((r for r in load_records(out)
                   if r.trial_id.startswith(prefix)), key=lambda r: r.attempt_index)
    records = list(done)
    failures = 0
    for r in done:
        failures = 0 if r.success else failures + 1
    if done:
        scene = SceneSpec.from_dict(done[-1].extra["next_scene"])
    else:
        scene = make_scene(scenario.scene, scenario.seed, library, scenario.plant)
    attempt = len(done)
    while failures < experiment.max_consecutive_failures and scene.objects and _objects_in_view(scene):
        t0 = time.perf_counter()
        attempt_scenario = dataclasses.replace(scenario, seed=scenario.seed + 1000 * attempt)
        trial_id = f"{prefix}{attempt:02d}"
        try:
            if trial_id in fail_trials:
                raise RuntimeError("forced failure (test)")
            run = _simulate(attempt_scenario, library, scene=scene)
            remaining = run.final_scene
            grasped = run.result.details.get("grasped_object_id") if run.result.success else None
            objects = [o for o in remaining.objects
                       if o.object_id != grasped and o.xyz[2] > -0.05]
            next_scene = settle_scene(dataclasses.replace(remaining, objects=objects), library,
                                      plant_config=scenario.plant) if objects else \
                dataclasses.replace(remaining, objects=[], settled=True)
            rec = _record_for(task, condition, attempt_scenario, run.result,
                              wall=time.perf_counter() - t0, run_index=task.index,
                              attempt_index=attempt, trial_id=trial_id,
                              extra={"next_scene": next_scene.to_dict(),
                                     "scene": scene.to_dict()})
        except Exception as e:  # noqa: BLE001
            next_scene = scene  # the pile is as it was; try again
            rec = _record_for(task, condition, attempt_scenario, error=e,
                              wall=time.perf_counter() - t0, run_index=task.index,
                              attempt_index=attempt, trial_id=trial_id,
                              extra={"next_scene": scene.to_dict(), "scene": scene.to_dict()})
        write_record(out, rec)
        records.append(rec)
        failures = 0 if rec.success else failures + 1
        scene = next_scene
        attempt += 1
    return records


# ----------------------------------------------------------------------------
# Driver side.


def _clutter_run_finished(out: Path, task: TrialTask, experiment: Experiment, records) -> bool:
    mine = sorted((r for r in records if r.trial_id.startswith(f"{task.trial_id}/attempt")),
                  key=lambda r: r.attempt_index)
    if not mine:
        return False
    failures = 0
    for r in mine:
        failures = 0 if r.success else failures + 1
    if failures >= experiment.max_consecutive_failures:
        return True
    from drake_grasp.scene import SceneSpec

    nxt = SceneSpec.from_dict(mine[-1].extra["next_scene"])
    return not nxt.objects or not _objects_in_view(nxt)


def evaluate(*, experiment: str, out: str | Path, trials: int | None = None, workers: int = 2,
             scheduler: str | None = None, seed: int = 0, objects_dir: str | None = None,
             conditions: list[str] | None = None, progress: bool = True, report: bool = True,
             fail_trials: tuple = ()) -> dict:
    """Runs (or resumes) an experiment into `out` and writes its report.

    Returns:
        {"records": number of trial records, "ran": tasks run now, "skipped": tasks
        already done, "summary": the report's summary (when `report`)}.
    """
    from drake_grasp.results import done_trial_ids, load_records, read_run_info, write_run_info

    exp = get_experiment(experiment)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    info = {"experiment": exp.name, "seed": int(seed), "trials": trials or exp.trials,
            "objects_dir": objects_dir, "code_version": __version__,
            "conditions": [dataclasses.asdict(c) for c in exp.conditions]}
    try:
        old = read_run_info(out)
    except FileNotFoundError:
        old = None
    if old is not None:
        for key in ("experiment", "seed", "objects_dir"):
            if old.get(key) != info[key]:
                raise ValueError(f"{out}: holds a run with {key}={old.get(key)!r}, not "
                                 f"{info[key]!r}; use another --out")
    info["created"] = old.get("created") if old else time.strftime("%Y-%m-%dT%H:%M:%S")
    write_run_info(out, info)
    tasks = plan_tasks(exp, trials=trials, seed=seed, conditions=conditions)
    records = load_records(out) if exp.kind == "clutter-runs" else []
    done_ids = done_trial_ids(out)
    if exp.kind == "clutter-runs":
        todo = [t for t in tasks if not _clutter_run_finished(out, t, exp, records)]
    else:
        todo = [t for t in tasks if t.trial_id not in done_ids]
    _execute(todo, out=str(out), workers=workers, scheduler=scheduler, objects_dir=objects_dir,
             progress=progress, fail_trials=tuple(fail_trials), total=len(tasks),
             initial=len(tasks) - len(todo))
    result = {"records": len(load_records(out)), "ran": len(todo),
              "skipped": len(tasks) - len(todo)}
    if report:
        from drake_grasp.report import make_report

        result["summary"] = make_report(out)
    return result


def _execute(todo, *, out, workers, scheduler, objects_dir, progress, fail_trials, total,
             initial):
    from tqdm import tqdm

    stats: dict = {}  # running successes / attempts per condition, this session
    bar = tqdm(total=total, initial=initial, unit="trial", disable=not progress,
               desc="evaluate", dynamic_ncols=True)

    def tick(recs):
        for r in recs:
            s = stats.setdefault(r["condition"], [0, 0])
            s[0] += int(r["success"])
            s[1] += 1
        bar.update(1)
        bar.set_postfix_str(" ".join(f"{k}:{v[0]}/{v[1]}" for k, v in sorted(stats.items())))

    try:
        if not todo:
            return
        if scheduler:
            from dask.distributed import Client, as_completed

            with Client(scheduler) as client:
                futures = [client.submit(run_task, t, out, objects_dir, fail_trials, pure=False)
                           for t in todo]
                for fut in as_completed(futures):
                    tick(fut.result())
        elif workers <= 1:
            for t in todo:
                tick(run_task(t, out, objects_dir, fail_trials))
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            with ProcessPoolExecutor(max_workers=workers,
                                     mp_context=mp.get_context("spawn")) as pool:
                futures = [pool.submit(run_task, t, out, objects_dir, fail_trials) for t in todo]
                for fut in as_completed(futures):
                    tick(fut.result())
    finally:
        bar.close()


def replay_trial(results_dir: str | Path, *, trial_id: str, out: str | Path | None = None):
    """Re-runs one recorded trial exactly (its resolved scenario, and for clutter attempts
    the pile it started from) and writes its episode files with the replay page."""
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.episode import run_episode
    from drake_grasp.results import load_records, replay_path
    from drake_grasp.scenario import Scenario
    from drake_grasp.scene import SceneSpec

    results_dir = Path(results_dir)
    matches = [r for r in load_records(results_dir) if r.trial_id == trial_id]
    if not matches:
        raise ValueError(f"{results_dir}: no trial {trial_id!r}")
    rec = matches[0]
    scenario = yaml_load_typed(schema=Scenario, data=rec.scenario_yaml)
    scene = SceneSpec.from_dict(rec.extra["scene"]) if "scene" in rec.extra else None
    page = replay_path(results_dir, trial_id)
    out = Path(out) if out else page.with_suffix("")
    result = run_episode(scenario, out_dir=out, scenario_name=rec.scenario_name, scene=scene)
    if out == page.with_suffix(""):
        # The report links failed trials to replays/<trial>.html; the episode's other
        # files stay in the folder beside it.
        os.replace(out / "replay.html", page)
    return result, out
