"""Runs an experiment's trials on a local process pool or a Dask cluster, resumably.

Every finished trial is one record file (`drake_grasp.evaluation.records`), written atomically by
the worker that ran it; re-running into the same folder skips finished trials, so a
killed run loses nothing and counts nothing twice. An exception inside a trial - building
its scenario or scene, simulating, settling the pile left for the next clutter attempt -
becomes a failed trial ("simulation-error") with its reason; the run goes on. Reports leave
simulation errors out of success rates (`drake_grasp.evaluation.report`).

A folder holds one experiment setup: `run.json` records the run's identity (`run_identity`:
experiment, base seed, object library and its content hash, every condition's resolved
scenario without the per-trial seed, the CNN weights' checksum, the code version), and
`evaluate` refuses to add trials to a folder whose identity differs, naming the first
differing key; `force_new=True` (`--force-new`) puts the run into a new folder next to it.

Each worker process keeps what does not change between trials - the CNN, the object
library and its meshes - and builds only the plant per trial (the objects differ from
trial to trial, and a MultibodyPlant cannot change its bodies once finalized).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from drake_grasp.evaluation.experiments import (CNN_POLICIES, EXTRA_POLICIES, Condition, Experiment,
                                     condition_scenario, get_experiment, plugin_condition,
                                     trial_scenario, trial_seed)
from drake_grasp.core.provenance import code_tree, code_version, file_sha256, machine

# A clutter run ends after this many simulation errors in a row (see `clutter_run_status`).
MAX_CONSECUTIVE_SIMULATION_ERRORS = 3
# No clutter run goes beyond this many attempts (the paper: 74 CTR attempts in 10 runs).
MAX_ATTEMPTS_PER_RUN = 60
# A clutter run ends when no object is left within +-15 cm (x and y) of the pile's centre:
# what the wrist camera sees from its start pose (0.3 m above the table, 55 degrees of
# vertical field of view: +-0.156 m).
IN_VIEW_HALF_EXTENT_M = 0.15


@dataclass(frozen=True)
class TrialTask:
    """One unit of work: an episode, or a whole clutter run (several attempts)."""

    experiment: str
    condition: str
    index: int
    base_seed: int
    # A `PHYSICS_PROFILES` name the trial runs with; "" = the scenario's (the default).
    physics_profile: str = ""
    # A user policy's ``MODULE:FACTORY`` (`drake_grasp.policies.plugins`), or a built-in policy of
    # `experiments.EXTRA_POLICIES` the experiment does not list, when `condition` is one
    # (its condition is `experiments.plugin_condition`); "" for the experiment's own.
    policy_spec: str = ""
    # `Experiment.patches`: the settings its condition runs with (weights, options).
    patches: tuple = ()

    @property
    def trial_id(self) -> str:
        return f"{self.experiment}/{self.condition}/{self.index:04d}"


def task_experiment(task: TrialTask) -> Experiment:
    """The experiment a task belongs to, with the settings the task carries (physics
    profile, CNN and GPD weights, the closed-loop options, the failure memory)."""
    experiment = get_experiment(task.experiment)
    if task.physics_profile:
        experiment = dataclasses.replace(experiment, physics_profile=task.physics_profile)
    if task.patches:
        experiment = dataclasses.replace(experiment, patches=tuple(task.patches))
    return experiment


def plan_tasks(experiment: Experiment, *, trials: int | None, seed: int,
               conditions: list[str] | None = None) -> list[TrialTask]:
    """The tasks of a run: trial i of every condition asked (the experiment's order, then
    the user policies, ``MODULE:FACTORY`` entries of `conditions`, and the built-in
    policies of `experiments.EXTRA_POLICIES` that the experiment does not list, in the
    order given), all with trial i's seed."""
    from drake_grasp.policies.plugins import is_policy_spec

    n = experiment.trials if trials is None else int(trials)
    if n < 1:
        raise ValueError(f"--trials: expected >= 1, got {n}")
    names = [c.name for c in experiment.conditions]
    specs = []
    if conditions:
        specs = list(dict.fromkeys(
            c for c in conditions
            if is_policy_spec(c) or (c in EXTRA_POLICIES and c not in names)))
        unknown = [c for c in conditions if c not in names and c not in specs]
        if unknown:
            raise ValueError(f"--conditions: {unknown} not in experiment "
                             f"{experiment.name}; its conditions: {names}, a built-in "
                             f"policy {list(EXTRA_POLICIES)} or a user policy "
                             "MODULE:FACTORY (see drake_grasp.policies.plugins)")
        names = [c for c in names if c in conditions]
    asked = [(c, "") for c in names] + [(plugin_condition(experiment, s).name, s) for s in specs]
    return [TrialTask(experiment.name, c, i, int(seed), experiment.physics_profile, spec,
                      experiment.patches)
            for i in range(n) for c, spec in asked]


def task_condition(task: TrialTask, experiment: Experiment) -> Condition:
    """The condition a task runs: the experiment's, or a user policy's."""
    if task.policy_spec:
        return plugin_condition(experiment, task.policy_spec)
    return _condition(experiment, task.condition)


def _condition(experiment: Experiment, name: str) -> Condition:
    for c in experiment.conditions:
        if c.name == name:
            return c
    raise ValueError(f"experiment {experiment.name}: no condition {name!r}")


_SEED_LINE = re.compile(r"^seed:[^\n]*$", re.MULTILINE)


def config_hash(scenario_yaml: str) -> str:
    """First 16 hex digits of the SHA-256 of a scenario's YAML with its top-level `seed`
    set to 0.

    The seed is per trial (and per clutter attempt); leaving it out makes the hash name
    the settings under test. Records carry the hash of their condition's shared scenario
    (`experiments.condition_scenario`), so all trials of a condition share one hash, also
    in experiments that choose the object and pose per trial.
    """
    normalised = _SEED_LINE.sub("seed: 0", scenario_yaml, count=1)
    return hashlib.sha256(normalised.encode()).hexdigest()[:16]


def weights_path(scenario) -> str | None:
    """The CNN weights file a scenario's policy loads (comma-separated files for an
    ensemble, `evaluator.weights_files`), None for policies without the CNN."""
    if scenario.policy not in CNN_POLICIES:
        return None
    from drake_grasp.policies.evaluator import weights_files

    return ",".join(weights_files(scenario.controller.weights))


def gpd_weights_path(scenario) -> str | None:
    """The GPD classifier weights file a scenario's policy loads (`gpd.weights`, "" = the
    shipped file), None for policies without it."""
    if scenario.policy != "gpd":
        return None
    from drake_grasp.policies.gpd import default_weights_path

    return scenario.gpd.weights or str(default_weights_path())


def condition_identity(experiment: Experiment, condition: Condition, *,
                       objects_dir: str | None = None) -> dict:
    """What run.json records of one condition, and what a resume compares: the condition's
    fields, its resolved scenario without the per-trial seed (`condition_scenario`), the
    sha256 of the CNN weights file it uses and of the GPD classifier weights file (each
    None when its policy uses none) and its config hash."""
    from pydrake.common.yaml import yaml_load_data

    from drake_grasp.config.scenario import dump_scenario
    from drake_grasp.policies.evaluator import weights_files

    scenario = condition_scenario(experiment, condition, objects_dir=objects_dir)
    yaml = dump_scenario(scenario)
    resolved = yaml_load_data(yaml)
    resolved.pop("seed", None)
    weights = weights_path(scenario)
    gpd_weights = gpd_weights_path(scenario)
    return {**dataclasses.asdict(condition), "scenario": resolved,
            "weights_sha256": None if weights is None else ",".join(
                file_sha256(f) for f in weights_files(weights)),
            "gpd_weights_sha256": None if gpd_weights is None else file_sha256(gpd_weights),
            "config_hash": config_hash(yaml)}


def run_identity(experiment: Experiment, *, seed: int, objects_dir: str | None = None,
                 library=None) -> dict:
    """The identity of a run as run.json records it; two runs may share a folder only when
    theirs are equal (the trial count and the conditions asked for may differ).

    Keys, in the order a resume compares them: experiment, seed (the base seed),
    objects_dir, object_library_hash (`ObjectLibrary.content_hash`), conditions (every
    condition of the experiment: see `condition_identity`), code_tree
    (`provenance.code_tree`: the package, models and diagrams as committed, plus any
    uncommitted change to them - commits that touch only tests, docs or analysis scripts
    leave it, so a long run resumes across them).
    """
    if library is None:
        from drake_grasp.objects import load_library

        library = load_library(objects_dir)
    return {
        "experiment": experiment.name,
        "seed": int(seed),
        "objects_dir": objects_dir,
        "object_library_hash": library.content_hash(),
        "conditions": [condition_identity(experiment, c, objects_dir=objects_dir)
                       for c in experiment.conditions],
        "code_tree": code_tree(),
    }


def plugin_identity(experiment: Experiment, spec: str, *, objects_dir: str | None = None) -> dict:
    """What run.json records of a user policy's condition (under "plugin_conditions", by
    condition name): `condition_identity` plus its code (`plugins.policy_source`: module,
    file, sha256 of the file), so a resume with an edited policy file is refused."""
    from drake_grasp.policies.plugins import policy_source

    condition = plugin_condition(experiment, spec)
    identity = condition_identity(experiment, condition, objects_dir=objects_dir)
    if spec in EXTRA_POLICIES:  # a built-in: its code is the package's (`code_tree`)
        return identity
    return {**identity, "policy_source": policy_source(spec)}


def check_user_policy(experiment: Experiment, spec: str, *, objects_dir: str | None = None) -> None:
    """Builds a user policy once, with its condition's scenario, and checks its ports
    (`plugins.make_policy_system`), so a bad spec fails before any trial runs."""
    from drake_grasp.policies.plugins import make_policy_system

    if spec in EXTRA_POLICIES:  # a built-in policy: nothing of the user's to check
        return
    make_policy_system(spec, condition_scenario(experiment, plugin_condition(experiment, spec),
                                                objects_dir=objects_dir))


_MISSING = object()


def _differences(old, new, path: str = ""):
    """(key path, value in old, value in new) for every leaf where two JSON values differ;
    dict keys in `new`'s order, then those only in `old`."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in list(new) + [k for k in old if k not in new]:
            sub = f"{path}.{key}" if path else str(key)
            yield from _differences(old.get(key, _MISSING), new.get(key, _MISSING), sub)
    elif isinstance(old, list) and isinstance(new, list) and path.endswith("conditions"):
        for i in range(max(len(old), len(new))):
            yield from _differences(old[i] if i < len(old) else _MISSING,
                                    new[i] if i < len(new) else _MISSING, f"{path}[{i}]")
    elif old is _MISSING or new is _MISSING or old != new or type(old) is not type(new):
        yield path, old, new


def _show(value) -> str:
    if value is _MISSING:
        return "missing"
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= 120 else text[:119] + "…"


def folder_conflict(out: str | Path, identity: dict) -> str | None:
    """Why `out` cannot take trials of the run `identity` (see `run_identity`), or None
    when it can (it does not exist, is empty, or its run.json has the same identity).

    The reason names the first differing key, e.g. "conditions[1].scenario.controller.
    step_ratio: 0.2 in the folder, 0.3 now (and 2 more differences)".
    """
    from drake_grasp.evaluation.records import RUN_INFO_FILE, TRIALS_DIR, read_run_info

    out = Path(out)
    if not out.exists():
        return None
    if not out.is_dir():
        return f"{out}: exists and is not a folder"
    try:
        old = read_run_info(out)
    except FileNotFoundError:
        trials = out / TRIALS_DIR
        if trials.is_dir() and any(not p.name.startswith(".") for p in trials.iterdir()):
            return (f"{out}: holds trial records but no {RUN_INFO_FILE}, so what they were "
                    "run with is unknown")
        return None
    except ValueError as e:
        return str(e)
    base = {k: v for k, v in identity.items() if k != "plugin_conditions"}
    diffs = list(_differences({k: old.get(k, _MISSING) for k in base}, base))
    # User policies: only those both runs have are compared (a resume may add or leave out
    # user policies, as it may other conditions).
    old_plugins = old.get("plugin_conditions") or {}
    for name, ident in (identity.get("plugin_conditions") or {}).items():
        if name in old_plugins:
            diffs += list(_differences(old_plugins[name], ident, f"plugin_conditions.{name}"))
    if not diffs:
        return None
    key, was, now = diffs[0]
    more = f" (and {len(diffs) - 1} more difference{'s' if len(diffs) > 2 else ''})" \
        if len(diffs) > 1 else ""
    return f"{out / RUN_INFO_FILE}: {key}: {_show(was)} in the folder, {_show(now)} now{more}"


def choose_folder(out: str | Path, identity: dict, *, force_new: bool = False,
                  max_tries: int = 1000) -> tuple[Path, str | None]:
    """The folder a run goes to: `out` when it can take the run (`folder_conflict`).

    Otherwise, with `force_new`, the first of `OUT-2`, `OUT-3`, ... next to it that can:
    one that does not exist yet, or one that already holds this very run (so repeating a
    `--force-new` command after a kill resumes the folder it started, instead of starting
    yet another one).

    Returns:
        (folder, why `out` was not used or None).

    Raises:
        ValueError: `out` holds another run and not `force_new`; the message names the
            first differing key and says to use --force-new.
    """
    out = Path(out)
    conflict = folder_conflict(out, identity)
    if conflict is None:
        return out, None
    if not force_new:
        raise ValueError(f"{conflict}. Resuming into {out} would mix two different runs in "
                         "one folder; use --force-new to start a new run folder next to it "
                         f"({out.name}-2, ...), or choose another --out.")
    for k in range(2, max_tries + 2):
        candidate = out.with_name(f"{out.name}-{k}")
        if folder_conflict(candidate, identity) is None:
            return candidate, conflict
    raise ValueError(f"--force-new: {out.name}-2 ... {out.name}-{max_tries + 1} next to {out} "
                     "all hold other runs; choose another --out")


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
               **(extra or {})})


def run_task(task: TrialTask, out: str, objects_dir: str | None = None,
             fail_trials: tuple = ()) -> list[dict]:
    """Runs one task in this process and writes its record(s); returns them as dicts.

    `fail_trials` (for testing the error path): "<trial id>" makes that trial's (or clutter
    attempt's) simulation raise; "<trial id>:scene" makes building its scenario and scene
    raise (for a clutter run: the run's trial id, e.g. "clutter/ctr/0000:scene");
    "<attempt id>:settle" makes settling the pile that clutter attempt leaves raise.
    """
    from drake_grasp.evaluation.records import write_record

    experiment = task_experiment(task)
    condition = task_condition(task, experiment)
    library = _library(objects_dir)
    if experiment.kind == "clutter-runs":
        records = _run_clutter(task, experiment, condition, out, objects_dir, library,
                               tuple(fail_trials))
    else:
        records = [_run_episode_task(task, experiment, condition, objects_dir, library,
                                     tuple(fail_trials))]
        write_record(out, records[0])
    return [r.to_dict() for r in records]


def _simulate(scenario, library, *, scene=None):
    from drake_grasp.evaluation.episode import simulate_episode

    model = (_model(scenario.controller.weights, scenario.controller.torch_threads)
             if scenario.policy in CNN_POLICIES else None)
    return simulate_episode(scenario, library=library, scene=scene, record_depth=False,
                            visualize=False, model=model)


def _run_episode_task(task, experiment, condition, objects_dir, library, fail_trials):
    t0 = time.perf_counter()
    scenario = None
    stage = "scene"
    try:
        _forced(fail_trials, task.trial_id, "scene")
        scenario = trial_scenario(experiment, condition, task.index, base_seed=task.base_seed,
                                  objects_dir=objects_dir, library=library)
        stage = "simulation"
        _forced(fail_trials, task.trial_id)
        run = _simulate(scenario, library)
        return _record_for(task, condition, scenario, run.result, objects_dir=objects_dir,
                           wall=time.perf_counter() - t0)
    except Exception as e:  # noqa: BLE001 - any failure inside a trial is recorded
        return _record_for(task, condition, scenario, error=e, objects_dir=objects_dir,
                           stage=stage, wall=time.perf_counter() - t0)


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
    - the run ends after `experiment.max_consecutive_failures` failed grasps in a row;
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


def _run_clutter(task, experiment, condition, out, objects_dir, library, fail_trials):
    """One clutter run: attempts on one pile, each grasped object removed, until
    `clutter_run_status` says it has ended (its docstring has the rule). Resumes after the
    last recorded attempt (each record carries the scene left for the next one). Building
    the scenario and pile, every attempt and the settling of the pile it leaves run inside
    the error capture: an exception becomes a "simulation-error" record. The record that
    ends the run has the reason in `extra["run_end"]`."""
    from drake_grasp.evaluation.records import load_records, write_record
    from drake_grasp.world.scene import SceneSpec, scenario_scene, settle_options, settle_scene

    prefix = f"{task.trial_id}/attempt"
    records = sorted((r for r in load_records(out)
                      if r.trial_id.startswith(prefix)), key=lambda r: r.attempt_index)
    status = clutter_run_status(records, experiment)
    if status is not None:
        return records
    attempt = len(records)

    def finish(rec):
        nonlocal status
        status = clutter_run_status(records + [rec], experiment)
        if status is not None:
            rec.extra["run_end"] = status
        write_record(out, rec)
        records.append(rec)

    t0 = time.perf_counter()
    scenario = None
    try:
        if not records:
            _forced(fail_trials, task.trial_id, "scene")
        scenario = trial_scenario(experiment, condition, task.index, base_seed=task.base_seed,
                                  objects_dir=objects_dir, library=library)
        if records:
            scene = SceneSpec.from_dict(records[-1].extra["next_scene"])
        else:
            scene = scenario_scene(scenario, library)
    except Exception as e:  # noqa: BLE001 - any failure inside a trial is recorded
        finish(_record_for(task, condition, scenario, error=e, wall=time.perf_counter() - t0,
                           run_index=task.index, attempt_index=attempt,
                           trial_id=f"{prefix}{attempt:02d}", objects_dir=objects_dir,
                           stage="scene", extra={"scene": None, "next_scene": None}))
        return records

    while status is None:
        t0 = time.perf_counter()
        attempt_scenario = dataclasses.replace(scenario, seed=scenario.seed + 1000 * attempt)
        if scenario.failure_memory.radius_m > 0.0:
            attempt_scenario.failure_memory = dataclasses.replace(
                scenario.failure_memory, failed_xy_yaw=failed_closings(records))
        trial_id = f"{prefix}{attempt:02d}"
        stage = "simulation"
        try:
            _forced(fail_trials, trial_id)
            run = _simulate(attempt_scenario, library, scene=scene)
            remaining = run.final_scene
            grasped = run.result.details.get("grasped_object_id") if run.result.success else None
            objects = [o for o in remaining.objects
                       if o.object_id != grasped and o.xyz[2] > -0.05]
            stage = "settle"
            _forced(fail_trials, trial_id, "settle")
            next_scene = settle_scene(dataclasses.replace(remaining, objects=objects), library,
                                      plant_config=scenario.plant,
                                      physics=scenario.physics,
                                      sheet_moves=scenario.sheet_moves,
                                      **settle_options(scenario.scene)) if objects else \
                dataclasses.replace(remaining, objects=[], settled=True)
            rec = _record_for(task, condition, attempt_scenario, run.result,
                              wall=time.perf_counter() - t0, run_index=task.index,
                              attempt_index=attempt, trial_id=trial_id, objects_dir=objects_dir,
                              extra={"next_scene": next_scene.to_dict(),
                                     "scene": scene.to_dict()})
        except Exception as e:  # noqa: BLE001 - any failure inside a trial is recorded
            next_scene = scene  # the pile is as it was; try again
            rec = _record_for(task, condition, attempt_scenario, error=e, stage=stage,
                              wall=time.perf_counter() - t0, run_index=task.index,
                              attempt_index=attempt, trial_id=trial_id, objects_dir=objects_dir,
                              extra={"next_scene": scene.to_dict(), "scene": scene.to_dict()})
        finish(rec)
        scene = next_scene
        attempt += 1
    return records


# ----------------------------------------------------------------------------
# Driver side.


def _clutter_run_finished(out: Path, task: TrialTask, experiment: Experiment, records) -> bool:
    mine = [r for r in records if r.trial_id.startswith(f"{task.trial_id}/attempt")]
    return clutter_run_status(mine, experiment) is not None


def evaluate(*, experiment: str, out: str | Path, trials: int | None = None, workers: int = 2,
             scheduler: str | None = None, seed: int = 0, objects_dir: str | None = None,
             conditions: list[str] | None = None, progress: bool = True, report: bool = True,
             fail_trials: tuple = (), force_new: bool = False,
             physics_profile: str = "", patches=()) -> dict:
    """Runs (or resumes) an experiment into `out` and writes its report.

    A folder holds one run: before anything is added, `run_identity` of this call is
    compared with the folder's run.json (`folder_conflict`). A resume may ask for more or
    fewer trials, or other conditions, of the same run; anything else that differs is
    refused.

    Args:
        experiment: Name in `drake_grasp.evaluation.experiments.EXPERIMENTS`.
        out: Results folder (created; resumed when it holds this run).
        trials: Trials per condition (clutter: runs); default the experiment's.
        workers: Local worker processes (1: in this process).
        scheduler: Address of a Dask scheduler to run on instead.
        seed: Base seed.
        objects_dir: Object library folder; None for the built-in objects.
        conditions: Subset of the experiment's conditions; None for all. An entry
            ``MODULE:FACTORY`` adds a user policy (`drake_grasp.policies.plugins`) as a condition
            of its own (`experiments.plugin_condition`): same seeds and scenes, judged by
            the same judge, in the same report. It is built and checked once before any
            trial runs; run.json records its code's sha256 ("plugin_conditions"). A
            built-in policy of `experiments.EXTRA_POLICIES` that the experiment does not
            list (`cnn-ctr` in clutter) is added the same way, recorded there too.
        progress: Show a progress bar.
        report: Write the report of the trials this call asked for: trials 0..trials-1 of
            the conditions asked (`make_report(..., trials=...)`); other records in the
            folder are left out of it (`drake-grasp report DIR` reports them all).
        fail_trials: Forced failures, for tests (see `run_task`).
        force_new: When `out` holds another run, run in the first free `OUT-2`, `OUT-3`,
            ... next to it (or the one already holding this run: see `choose_folder`).
        physics_profile: A `scenario.PHYSICS_PROFILES` name every trial runs with; ""
            keeps the scenarios' (the default profile).
        patches: `experiments.ScenarioPatch`es every trial of their groups runs with,
            after the experiment's own: other CNN or GPD weights, controller settings of
            the closed-loop conditions, the judge's search, the failure memory
            (`experiments.option_patches` makes them of the command's options). They are
            part of the run's identity through the conditions' resolved scenarios (and
            the weights files' sha256).

    Returns:
        {"out": the folder used, "new_folder_because": why `out` was not used (None when it
        was), "records": trial records in the folder, "ran": tasks run now, "skipped":
        tasks already done, "summary": the report's summary (when `report`)}.

    Raises:
        ValueError: Unknown experiment/condition, a user policy that cannot be loaded or
            breaks the port contract (the message names its spec), --trials < 1, or `out`
            holds another run and not `force_new` (the message names the first differing
            key).
    """
    from drake_grasp.evaluation.records import done_trial_ids, load_records, read_run_info, write_run_info

    exp = get_experiment(experiment)
    if physics_profile:
        exp = dataclasses.replace(exp, physics_profile=physics_profile)
    if patches:
        exp = dataclasses.replace(exp, patches=exp.patches + tuple(patches))
    tasks = plan_tasks(exp, trials=trials, seed=seed, conditions=conditions)
    identity = run_identity(exp, seed=seed, objects_dir=objects_dir)
    specs = list(dict.fromkeys(t.policy_spec for t in tasks if t.policy_spec))
    for spec in specs:
        check_user_policy(exp, spec, objects_dir=objects_dir)
    if specs:
        identity["plugin_conditions"] = {
            plugin_condition(exp, spec).name: plugin_identity(exp, spec, objects_dir=objects_dir)
            for spec in specs}
    out, replaced = choose_folder(Path(out), identity, force_new=force_new)
    out.mkdir(parents=True, exist_ok=True)
    try:
        old = read_run_info(out)
    except FileNotFoundError:
        old = {}
    n = trials or exp.trials
    plugins = {**(old.get("plugin_conditions") or {}), **identity.get("plugin_conditions", {})}
    info = {**identity, **({"plugin_conditions": plugins} if plugins else {}),
            # Informational: the most trials per condition any call asked for.
            "trials": max(n, int(old.get("trials") or 0)),
            # Informational: the commit of the latest call (records carry their own).
            "code_version": code_version(),
            "created": old.get("created") or time.strftime("%Y-%m-%dT%H:%M:%S"),
            # Set here, not by write_run_info, so that the rewrite at the end of the call
            # keeps the time the folder was created.
            "created_utc": old.get("created_utc")
            or datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "sessions": list(old.get("sessions") or [])}
    write_run_info(out, info)
    records = load_records(out) if exp.kind == "clutter-runs" else []
    done_ids = done_trial_ids(out)
    if exp.kind == "clutter-runs":
        todo = [t for t in tasks if not _clutter_run_finished(out, t, exp, records)]
    else:
        todo = [t for t in tasks if t.trial_id not in done_ids]
    started = datetime.now(timezone.utc)
    t0 = time.perf_counter()
    completed = False
    try:
        _execute(todo, out=str(out), workers=workers, scheduler=scheduler,
                 objects_dir=objects_dir, progress=progress, fail_trials=tuple(fail_trials),
                 total=len(tasks), initial=len(tasks) - len(todo))
        completed = True
    finally:
        # The wall time of this call, for the report's experiment time (a call killed
        # outright leaves no entry; one interrupted by Ctrl-C or an error does).
        if todo:
            info["sessions"].append({
                "started_utc": started.isoformat(timespec="seconds"),
                "wall_s": round(time.perf_counter() - t0, 3),
                "workers": 0 if scheduler else max(1, workers),
                "scheduler": bool(scheduler),
                # Trial files that parse, as `done_trial_ids` counts them: a corrupt
                # file left by a killed run is re-run, not an error here.
                "records_added": len(done_trial_ids(out)) - len(done_ids),
                "completed": completed,
                # Where these records were computed (`provenance.machine`): a replay on
                # another kind of machine reproduces outcomes, not every last bit.
                "machine": machine()})
            write_run_info(out, info)
    result = {"out": str(out), "new_folder_because": replaced,
              "records": len(load_records(out)), "ran": len(todo),
              "skipped": len(tasks) - len(todo)}
    if report:
        from drake_grasp.evaluation.report import make_report

        result["summary"] = make_report(out, trials=[t.trial_id for t in tasks])
    return result


def _execute(todo, *, out, workers, scheduler, objects_dir, progress, fail_trials, total,
             initial):
    from tqdm import tqdm

    # Running successes / attempts / simulation errors per condition, this session
    # (attempts exclude simulation errors, as in the report).
    stats: dict = {}
    bar = tqdm(total=total, initial=initial, unit="trial", disable=not progress,
               desc="evaluate", dynamic_ncols=True)

    def tick(recs):
        for r in recs:
            s = stats.setdefault(r["condition"], [0, 0, 0])
            if r["failure_class"] == "simulation-error":
                s[2] += 1
                continue
            s[0] += int(r["success"])
            s[1] += 1
        bar.update(1)
        bar.set_postfix_str(" ".join(f"{k}:{v[0]}/{v[1]}" + (f"({v[2]} err)" if v[2] else "")
                                     for k, v in sorted(stats.items())))

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
            pooled_map(run_task, [(t, out, objects_dir, fail_trials) for t in todo],
                       workers=workers, on_result=tick)
    finally:
        bar.close()


# A worker's memory grows by about 15 MB per trial (2,000 sim-distance trials on 2 workers:
# one worker reached 12 GB and was killed by the kernel): with drake 1.51 a Python
# LeafSystem that declares a port is never freed, and the episode Diagram holding it stays
# alive with its plant, SceneGraph and renderer (Drake issues 22515 and 24162). So worker
# processes are replaced after about this many trials; a fresh one reloads the CNN and
# meshes in seconds.
WORKER_MAX_TRIALS = 200


def pooled_map(fn, arg_tuples, *, workers: int, on_result,
               per_worker: int = WORKER_MAX_TRIALS) -> None:
    """Calls `fn(*args)` for every tuple on `workers` spawned processes and
    `on_result(value)` in completion order, with fresh processes for every
    `workers * per_worker` tasks (so no process runs more than that many).

    Not ProcessPoolExecutor's `max_tasks_per_child`: in Python 3.11 to 3.15.0b3 a pool
    with a backlog deadlocks once a worker exits at that limit (CPython gh-115634): an
    `evaluate` on 2 workers hung after exactly 400 of 480 trials, both workers gone. A new
    pool per chunk needs no worker replacement."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    arg_tuples = list(arg_tuples)
    chunk = max(1, int(workers) * int(per_worker))
    for start in range(0, len(arg_tuples), chunk):
        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
            futures = [pool.submit(fn, *a) for a in arg_tuples[start:start + chunk]]
            for fut in as_completed(futures):
                on_result(fut.result())


def parallel_map(fn, arg_tuples, *, workers: int = 2, desc: str = "") -> list:
    """`fn(*args)` for each of `arg_tuples`, in order, on `workers` spawned processes
    (in this process when `workers` <= 1), with a progress bar: for analysis scripts
    that run their own kind of trial. `fn` must be importable by the workers (a
    module-level function)."""
    from tqdm import tqdm

    arg_tuples = list(arg_tuples)
    if workers <= 1:
        return [fn(*a) for a in tqdm(arg_tuples, desc=desc)]
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        futures = [pool.submit(fn, *a) for a in arg_tuples]
        return [f.result() for f in tqdm(futures, desc=desc)]


def recorded_scenario(scenario_yaml: str):
    """The `Scenario` a trial record's YAML describes. A record written before physics
    profiles existed has no `physics:` entry: it ran the reference settings (its
    `plant.time_step` is in the record), so it gets the `reference` profile. One written
    before `physics.table_collision` existed ran with the table's box (the `fast`
    profile's half-space table came later), so it gets "box". One written before
    `gripper.force_mode` existed pressed with at most the grip force, so it gets
    "limit"; one written before `gpd.fallback_best` existed ran GPD's strict threshold,
    so it gets false."""
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.config.scenario import Scenario, apply_physics_profile

    try:
        scenario = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    except RuntimeError as e:
        # e.g. "The fields ['stop_window_fraction'] were unknown to the schema": a key
        # this version of the package no longer has.
        raise ValueError(f"the recorded scenario does not load in drake_grasp {code_version()}: "
                         f"{e}") from None
    if not re.search(r"^physics:", scenario_yaml, re.MULTILINE):
        scenario = apply_physics_profile(scenario, "reference", keep={
            "plant.time_step", "plant.discrete_contact_approximation"})
    elif not re.search(r"^physics:\n(?:  .*\n)*  table_collision:", scenario_yaml, re.MULTILINE):
        # Recorded before `physics.table_collision` existed: the table had its box.
        scenario.physics.table_collision = "box"
    if not re.search(r"^gripper:\n(?:  .*\n)*  force_mode:", scenario_yaml, re.MULTILINE):
        # Recorded before `gripper.force_mode` existed: the grip force was a limit.
        scenario.gripper.force_mode = "limit"
    if not re.search(r"^gpd:\n(?:  .*\n)*  fallback_best:", scenario_yaml, re.MULTILINE):
        # Recorded before `gpd.fallback_best` existed: no detection over the threshold
        # was no detection (the fallback became the default later).
        scenario.gpd.fallback_best = False
    return scenario


def recorded_weights(scenario, run_info: dict, condition: str, *, source: str = "run.json"):
    """The scenario with the CNN weights its run loaded. A record written with
    `controller.weights: ""` ran the default of its day; run.json holds that file's sha256
    (`condition_identity`). When it is not today's default, the shipped weights file with
    that sha256 (any `models/*/weights.safetensors`) is named instead, so that the record
    replays as it ran. A record that named its weights (`--weights`, one file or an
    ensemble's) keeps them where the files exist; a named file that does not exist here
    (a path of another machine or working directory) is replaced by the shipped file with
    its recorded sha256. Records without a sha256 (older run.json, no CNN) are returned as
    they are. Raises ValueError (naming `source`, the condition and the sha256) when no
    shipped file has it."""
    from drake_grasp.policies.evaluator import weights_files

    if scenario.policy not in CNN_POLICIES:
        return scenario
    shas = next((c.get("weights_sha256") for c in run_info.get("conditions", [])
                 if c.get("name") == condition), None)
    if not shas:
        return scenario
    named = scenario.controller.weights
    files = weights_files(named)
    shas = shas.split(",")
    if named:
        if all(Path(f).is_file() for f in files) or len(shas) != len(files):
            return scenario
        resolved = [f if Path(f).is_file() else str(_shipped_weights(sha, source, condition, f))
                    for f, sha in zip(files, shas)]
        weights = ",".join(resolved)
    else:
        if shas[0] == file_sha256(files[0]):
            return scenario
        weights = str(_shipped_weights(shas[0], source, condition, None))
    return dataclasses.replace(
        scenario, controller=dataclasses.replace(scenario.controller, weights=weights))


def _shipped_weights(sha: str, source: str, condition: str, missing: str | None) -> Path:
    """The shipped `models/*/weights.safetensors` whose sha256 is `sha` (for
    `recorded_weights`); ValueError naming what was looked for when none is."""
    from drake_grasp.core.assets import models_dir

    for f in sorted(models_dir().glob("*/weights.safetensors")):
        if file_sha256(f) == sha:
            return f
    if missing is None:
        raise ValueError(f"{source}: condition {condition!r} ran the default CNN of its day "
                         f"(weights sha256 {sha}), which no shipped "
                         "models/*/weights.safetensors is; replay it with the package that "
                         "recorded it")
    raise ValueError(f"{source}: condition {condition!r} ran {missing} (weights sha256 "
                     f"{sha}), which does not exist here and is no shipped "
                     "models/*/weights.safetensors; put the file at that path to replay it")


def recorded_pile(path: str | Path) -> tuple:
    """(record, scenario, scene) of a clutter attempt: its trial record (the JSON file, as
    a dict), its scenario and the pile it began on (`extra.scene`); what the analysis
    scripts replay an attempt from. The scenario names the weights the attempt ran
    (`recorded_weights`, from the run.json of the record's results folder,
    `RESULTS/trials/RECORD.json`, when there is one).

    Raises:
        ValueError: The record holds no pile (the message names the file).
    """
    from drake_grasp.evaluation.records import RUN_INFO_FILE, read_run_info
    from drake_grasp.world.scene import SceneSpec

    rec = json.loads(Path(path).read_text())
    if not (rec.get("extra") or {}).get("scene"):
        raise ValueError(f"{path}: no extra.scene (expected a clutter attempt's record)")
    scenario = recorded_scenario(rec["scenario_yaml"])
    run_json = Path(path).parent.parent / RUN_INFO_FILE
    if run_json.is_file():
        scenario = recorded_weights(scenario, read_run_info(run_json.parent), rec["condition"],
                                    source=str(run_json))
    return rec, scenario, SceneSpec.from_dict(rec["extra"]["scene"])


# Measured in analysis/results/machine-repro/ (README *Reproducibility*).
_ACROSS_MACHINES = ("a replay is bit for bit only on a machine like the recording one; across "
                    "machines isolation trials kept every outcome, clutter attempts did not "
                    "(their poured piles settle apart)")


def machine_note(run_info: dict) -> str | None:
    """What a replay on this machine can promise for a run folder's records: None when one
    of its evaluate sessions ran on a machine like this one (`provenance.machine`: the same
    CPU and package versions), else a one-line note naming the recorded machines (or
    saying that none was recorded: folders written before sessions carried one)."""
    here = machine()
    seen = [s["machine"] for s in run_info.get("sessions") or []
            if isinstance(s, dict) and isinstance(s.get("machine"), dict)]
    key = ("cpu", "packages")
    if any(all(m.get(k) == here[k] for k in key) for m in seen):
        return None
    if not seen:
        return ("the run folder does not say which machine made its records (written before "
                f"run.json's sessions carried one): {_ACROSS_MACHINES}")
    named = "; ".join(sorted({f"{m.get('cpu')} with {m.get('packages')}" for m in seen}))
    return (f"recorded on {named}; this machine is {here['cpu']} with {here['packages']}: "
            f"{_ACROSS_MACHINES}")


def replay_trial(results_dir: str | Path, *, trial_id: str, out: str | Path | None = None):
    """Re-runs one recorded trial exactly (its resolved scenario, and for clutter attempts
    the pile it started from) and writes its episode files with the replay page."""
    from drake_grasp.evaluation.episode import run_episode
    from drake_grasp.evaluation.records import RUN_INFO_FILE, load_records, read_run_info, replay_path
    from drake_grasp.world.scene import SceneSpec

    results_dir = Path(results_dir)
    matches = [r for r in load_records(results_dir) if r.trial_id == trial_id]
    if not matches:
        raise ValueError(f"{results_dir}: no trial {trial_id!r}")
    rec = matches[0]
    if not rec.scenario_yaml:
        raise ValueError(f"{results_dir}: trial {trial_id!r} has no scenario to replay (building "
                         f"it failed: {rec.failure_reason})")
    try:
        scenario = recorded_scenario(rec.scenario_yaml)
    except ValueError as e:
        raise ValueError(f"{results_dir}: trial {trial_id!r} was recorded by drake_grasp "
                         f"{rec.code_version}; {e}. Replay it with that version.") from None
    if (results_dir / RUN_INFO_FILE).is_file():
        scenario = recorded_weights(scenario, read_run_info(results_dir), rec.condition,
                                    source=str(results_dir / RUN_INFO_FILE))
    scene = SceneSpec.from_dict(rec.extra["scene"]) if "scene" in rec.extra else None
    page = replay_path(results_dir, trial_id)
    out = Path(out) if out else page.with_suffix("")
    result = run_episode(scenario, out_dir=out, scenario_name=rec.scenario_name, scene=scene)
    if out == page.with_suffix(""):
        # The report links failed trials to replays/<trial>.html; the episode's other
        # files stay in the folder beside it.
        os.replace(out / "replay.html", page)
    return result, out
