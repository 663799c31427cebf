"""Drives an experiment's trials on a local process pool or a Dask cluster, resumably.

Workers (`drake_grasp.evaluation.trial_worker`) return each task's records and this
process, the driver, writes them, one atomic file per trial
(`drake_grasp.evaluation.records`): workers need no access to the results folder, and a
user object library reaches Dask workers by content (`objects.bundle`). Re-running into
the same folder skips finished trials, so a killed run loses at most the trials (clutter
attempts: one per task) in flight and counts nothing twice; an exception inside a trial,
or a trial process that dies, becomes a "simulation-error" record, the run going on.
`evaluate` applies the call's settings to the experiment, plans its tasks (`trial_plan`),
checks that the folder holds this very run (`run_folder`: run.json's identity, refused
naming the first differing key unless `force_new`), runs what is left with a progress
bar and records the session in run.json; `pooled_map` / `parallel_map` are the spawned
process pools it and the analysis scripts run on.
"""

from __future__ import annotations

import dataclasses
import time
from datetime import datetime, timezone
from pathlib import Path

from drake_grasp.evaluation.experiments import Experiment, get_experiment, plugin_condition
from drake_grasp.evaluation.run_folder import (check_user_policy, choose_folder, plugin_identity,
                                               run_identity)
from drake_grasp.evaluation.trial_plan import TrialTask, plan_tasks
from drake_grasp.evaluation.trial_worker import clutter_run_status, run_task
from drake_grasp.core.provenance import code_version, machine


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
        out: Results folder (created; resumed when it holds this run). Trials are written
            one file each while the call runs and packed into its `trials.parquet` when
            the call finishes (`records.pack_records`).
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
        patches (Sequence[ScenarioPatch]): `experiments.ScenarioPatch`es every trial of
            their groups runs with, after the experiment's own: other CNN or GPD weights,
            controller settings of the closed-loop conditions, the judge's search, the
            failure memory (`experiments.option_patches` makes them of the command's
            options, checking each). They are part of the run's identity through the
            conditions' resolved scenarios (and the weights files' sha256).

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
    exp = get_experiment(experiment)
    if physics_profile:
        exp = dataclasses.replace(exp, physics_profile=physics_profile)
    if patches:
        exp = dataclasses.replace(exp, patches=exp.patches + tuple(patches))
    tasks, identity = _planned_run(exp, trials=trials, seed=seed, conditions=conditions,
                                   objects_dir=objects_dir)
    out, replaced = choose_folder(Path(out), identity, force_new=force_new)
    info = _open_run_info(out, exp, identity, trials)
    todo, done_ids = _pending_tasks(out, exp, tasks)
    _run_session(todo, info, done_ids, experiment=exp, out=out, workers=workers,
                 scheduler=scheduler, objects_dir=objects_dir, progress=progress,
                 fail_trials=fail_trials, total=len(tasks))
    # The per-trial files were the crash-safe path while the call ran; a finished call
    # packs them into the folder's table (an interrupted one leaves them for its resume).
    from drake_grasp.evaluation.records import pack_records

    pack_records(out)
    return _result(out, tasks, todo, replaced, report)


def _planned_run(exp: Experiment, *, trials, seed, conditions, objects_dir) -> tuple:
    """(the tasks of the run, its identity): `plan_tasks`, `run_identity`, and each user
    policy asked built and checked once, its identity under "plugin_conditions"."""
    tasks = plan_tasks(exp, trials=trials, seed=seed, conditions=conditions)
    identity = run_identity(exp, seed=seed, objects_dir=objects_dir)
    specs = list(dict.fromkeys(t.policy_spec for t in tasks if t.policy_spec))
    for spec in specs:
        check_user_policy(exp, spec, objects_dir=objects_dir)
    if specs:
        identity["plugin_conditions"] = {
            plugin_condition(exp, spec).name: plugin_identity(exp, spec, objects_dir=objects_dir)
            for spec in specs}
    return tasks, identity


def _open_run_info(out: Path, exp: Experiment, identity: dict, trials) -> dict:
    """Creates `out` and writes its run.json: this run's identity, the user policies of
    earlier calls kept, the informational keys, the sessions so far. Returns it."""
    from drake_grasp.evaluation.records import read_run_info, write_run_info

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
    return info


def _pending_tasks(out: Path, exp: Experiment, tasks) -> tuple:
    """(the tasks not finished in `out`, the trial ids done there before this call)."""
    from drake_grasp.evaluation.records import done_trial_ids, load_records

    records = load_records(out) if exp.kind == "clutter-runs" else []
    done_ids = done_trial_ids(out)
    if exp.kind == "clutter-runs":
        todo = [t for t in tasks if not _clutter_run_finished(out, t, exp, records)]
    else:
        todo = [t for t in tasks if t.trial_id not in done_ids]
    return todo, done_ids


def _run_session(todo, info: dict, done_ids, *, experiment, out: Path, workers, scheduler,
                 objects_dir, progress, fail_trials, total) -> None:
    """Runs `todo` (`_execute`) and, when there was anything to run, adds this session to
    run.json, also when it was interrupted."""
    from drake_grasp.evaluation.records import done_trial_ids, write_run_info

    started = datetime.now(timezone.utc)
    t0 = time.perf_counter()
    completed = False
    try:
        _execute(todo, experiment=experiment, out=str(out), workers=workers,
                 scheduler=scheduler, objects_dir=objects_dir, progress=progress,
                 fail_trials=tuple(fail_trials), total=total, initial=total - len(todo))
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


def _result(out: Path, tasks, todo, replaced, report: bool) -> dict:
    """What `evaluate` returns, with the report of the trials asked when `report`."""
    from drake_grasp.evaluation.records import load_records

    result = {"out": str(out), "new_folder_because": replaced,
              "records": len(load_records(out)), "ran": len(todo),
              "skipped": len(tasks) - len(todo)}
    if report:
        from drake_grasp.evaluation.report import make_report

        result["summary"] = make_report(out, trials=[t.trial_id for t in tasks])
    return result


def _execute(todo, *, experiment, out, workers, scheduler, objects_dir, progress, fail_trials,
             total, initial):
    """Runs `todo` and writes every record as it comes back. A clutter run goes one
    attempt per task: when an attempt's record is written and `clutter_run_status` says
    the run goes on, its next attempt is submitted with the attempts so far, so a killed
    run loses at most the attempts in flight."""
    from tqdm import tqdm

    from drake_grasp.evaluation.records import TrialRecord, write_record

    # Running successes / attempts / simulation errors per condition, this session
    # (attempts exclude simulation errors, as in the report).
    stats: dict = {}
    bar = tqdm(total=total, initial=initial, unit="trial", disable=not progress,
               desc="evaluate", dynamic_ncols=True)
    per_attempt = experiment.kind == "clutter-runs"

    def done(recs, args):
        """Writes a task's records; returns its run's next attempt's args, or None."""
        for r in recs:  # the driver owns the folder: it writes what the workers return
            write_record(out, TrialRecord.from_dict(r, source=f"worker result {r.get('trial_id')}"))
            s = stats.setdefault(r["condition"], [0, 0, 0])
            if r["failure_class"] == "simulation-error":
                s[2] += 1
                continue
            s[0] += int(r["success"])
            s[1] += 1
        bar.set_postfix_str(" ".join(f"{k}:{v[0]}/{v[1]}" + (f"({v[2]} err)" if v[2] else "")
                                     for k, v in sorted(stats.items())))
        if per_attempt:
            so_far = tuple(args[3]) + tuple(recs)
            if recs and clutter_run_status([TrialRecord.from_dict(r, source="record")
                                            for r in so_far], experiment) is None:
                return args[:3] + (so_far, 1)
        bar.update(1)
        return None

    try:
        if not todo:
            return
        prior = _prior_attempts(out, todo)
        args = [(t, objects_dir, fail_trials, prior.get(t.trial_id, ()), 1 if per_attempt else 0)
                for t in todo]
        if scheduler:
            _on_dask(scheduler, args, objects_dir, done)
        elif workers <= 1:
            queue = list(args)
            while queue:
                follow = done(run_task(*queue[0]), queue[0])
                queue = queue[1:] + ([follow] if follow is not None else [])
        else:
            pooled_map(run_task, args, workers=workers, on_result=done)
    finally:
        bar.close()


def _prior_attempts(out, todo) -> dict:
    """{clutter run's trial id: its attempt records written before (dicts)}: what a
    resumed run continues from, handed to the worker with the task."""
    from drake_grasp.evaluation.records import load_records

    runs = {t.trial_id for t in todo}
    prior: dict = {}
    for r in load_records(out):
        run_id = r.trial_id.rsplit("/attempt", 1)[0]
        if r.attempt_index is not None and run_id in runs:
            prior.setdefault(run_id, []).append(r.to_dict())
    return {k: tuple(v) for k, v in prior.items()}


def _on_dask(scheduler: str, args, objects_dir, done) -> None:
    """Runs the tasks on a Dask cluster (`done` as `pooled_map`'s on_result); a user object
    library goes to the workers once, by content (`objects.bundle`), so they need not see
    `objects_dir`."""
    from dask.distributed import Client, as_completed

    with Client(scheduler) as client:
        objects = None
        if objects_dir:
            from drake_grasp.objects.bundle import make_bundle

            objects = client.scatter(make_bundle(objects_dir), broadcast=True)

        def submit(a):
            fut = client.submit(run_task, *a, objects=objects, pure=False)
            submitted[fut.key] = a
            return fut

        submitted: dict = {}
        pending = as_completed([submit(a) for a in args])
        for fut in pending:
            follow = done(fut.result(), submitted.pop(fut.key))
            fut.release()  # written by this process: the cluster may forget it
            if follow is not None:
                pending.add(submit(follow))


# With drake 1.51 a Python LeafSystem that declares a port is never freed, and the episode
# Diagram holding it stays alive with its plant, SceneGraph and renderer (Drake issues 22515
# and 24162): about 6-15 MB per trial run in one process. Trials run in forked children
# (`hermetic`), which take that memory with them; where fork is unavailable they run in
# the worker itself, so the local pool still replaces its workers after this many trials.
WORKER_MAX_TRIALS = 200


def pooled_map(fn, arg_tuples, *, workers: int, on_result,
               per_worker: int = WORKER_MAX_TRIALS) -> None:
    """Calls `fn(*args)` for every tuple on `workers` spawned processes and
    `on_result(value, args)` in completion order, with fresh processes for every
    `workers * per_worker` tasks (so no process runs much more than that many).
    `on_result` may return the arguments of a follow-up task (a clutter run's next
    attempt), which runs in the same pool; None otherwise.

    Not ProcessPoolExecutor's `max_tasks_per_child`: in Python 3.11 to 3.15.0b3 a pool
    with a backlog deadlocks once a worker exits at that limit (CPython gh-115634): an
    `evaluate` on 2 workers hung after exactly 400 of 480 trials, both workers gone. A new
    pool per chunk needs no worker replacement."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    arg_tuples = list(arg_tuples)
    chunk = max(1, int(workers) * int(per_worker))
    for start in range(0, len(arg_tuples), chunk):
        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
            pending = {pool.submit(fn, *a): a for a in arg_tuples[start:start + chunk]}
            try:
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        follow = on_result(fut.result(), pending.pop(fut))
                        if follow is not None:
                            pending[pool.submit(fn, *follow)] = follow
            except BaseException:
                # Do not wait for the rest of the chunk when its results cannot be kept.
                pool.shutdown(wait=False, cancel_futures=True)
                raise


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
