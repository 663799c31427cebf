"""Generating the training set: N scenes over shards, in worker processes, resumable.

Each shard holds S scenes (`dataset.shard_scene_range`) and is one task for a worker
(`dataset.fill_scene` per scene, then `dataset_shards.write_shard`); the manifest is rebuilt
from the finished shards, so a re-run counts nothing twice. The folder is held by
`folder_lock.GenerateLock` for the whole run.

Workers write each shard to a temporary name private to the run and the worker process
(`shard-XXXXX.h5.<run>.<host>-<pid>.tmp`), fsync it and rename it when complete (then
fsync the folder), so a killed run leaves no half-written shard and no run ever deletes
a temporary file that another run is writing: a run removes only its own temporary
files, and those of a stale lock's run it takes over. Re-running the same command skips
finished shards.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

from drake_grasp.core.provenance import code_version
from drake_grasp.learning.dataset import (FORMAT_VERSION, MANIFEST, DatasetConfig, _config_dict,
                                          config_hash, fill_scene, shard_scene_range)
from drake_grasp.learning.dataset_shards import read_shard_counts, shard_name, write_shard
from drake_grasp.learning.folder_lock import (GenerateLock, describe_owner, fsync_dir,
                                              process_tag, temp_files)


# Whether this process has run a shard task yet: its first one pays the imports and the
# first meshes' loading (a long run's rate leaves it out: `bench`'s labels_per_s_sustained).
_TASKS_RUN_HERE = 0


def _shard_task(shard_index: int, out: str, seed: int, split: str, scenario_yaml: str,
                config: dict, objects_dir: str | None, attrs: dict, num_scenes: int,
                tmp_tag: str) -> dict:
    """One worker task: generate the shard's scenes and write the shard."""
    global _TASKS_RUN_HERE
    first_here = _TASKS_RUN_HERE == 0
    _TASKS_RUN_HERE += 1
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import Scenario

    scenario = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    cfg = DatasetConfig(**config)
    library = load_library(objects_dir)
    path = Path(out) / shard_name(shard_index)
    scenes = shard_scene_range(shard_index, num_scenes=num_scenes,
                               scenes_per_shard=cfg.scenes_per_shard)
    t0 = time.perf_counter()
    samples, rejected = [], []
    for i in scenes:
        kept, replaced = fill_scene(i, seed=seed, split=split, scenario=scenario, config=cfg,
                                    library=library)
        samples.append(kept)
        rejected.extend(replaced)
    t_write = time.perf_counter()
    shard_attrs = {**attrs, "scene_first": scenes.start, "scene_stop": scenes.stop,
                   "num_attempts": len(samples) + len(rejected),
                   "num_replaced_no_grasp": sum(r.reason == "no_grasp" for r in rejected),
                   "num_replaced_unsettled": sum(r.reason == "unsettled" for r in rejected)}
    write_shard(path, samples, attrs=shard_attrs, tmp_tag=tmp_tag)
    counts = read_shard_counts(path)
    counts["seconds"] = time.perf_counter() - t0
    counts["first_in_process"] = first_here
    timings: dict = {"write": time.perf_counter() - t_write}
    for s in [*samples, *rejected]:
        for k, v in s.timings.items():
            timings[k] = timings.get(k, 0.0) + v
    counts["timings"] = timings
    return counts


# ----------------------------------------------------------------------------
# The whole dataset.


def write_manifest(out: Path, cfg: dict, *, tmp_tag: str | None = None) -> dict:
    """Rebuilds `manifest.json` from the finished shards (so counts are never doubled).

    Keys: num_scenes (labelled scenes), num_images, num_labels, num_shards, shards,
    num_scene_attempts (seeds tried), num_scenes_replaced (attempts not used, the sum
    of num_scenes_unsettled_resampled and num_scenes_no_grasp_resampled), config_hash,
    config, code_version, format_version.
    """
    out = Path(out)
    shards = sorted(out.glob("shard-*.h5"))
    totals = {"num_scenes": 0, "num_images": 0, "num_labels": 0, "num_scene_attempts": 0,
              "num_scenes_replaced": 0, "num_scenes_unsettled_resampled": 0,
              "num_scenes_no_grasp_resampled": 0}
    listing = []
    for path in shards:
        c = read_shard_counts(path)
        unsettled = c["num_replaced_unsettled"] or 0
        # Shards written without the split count their unused scenes in `skipped`.
        no_grasp = c["num_replaced_no_grasp"] if c["num_replaced_no_grasp"] is not None \
            else c["skipped"]
        totals["num_scenes"] += c["num_scenes"]
        totals["num_images"] += c["num_images"]
        totals["num_labels"] += c["num_labels"]
        totals["num_scenes_unsettled_resampled"] += unsettled
        totals["num_scenes_no_grasp_resampled"] += no_grasp
        totals["num_scenes_replaced"] += unsettled + no_grasp
        totals["num_scene_attempts"] += (c["num_attempts"] if c["num_attempts"] is not None
                                         else c["num_scenes"] + c["skipped"])
        entry = {"file": path.name, "num_scenes": c["num_scenes"],
                 "num_images": c["num_images"], "num_labels": c["num_labels"]}
        if c["scene_first"] is not None:
            entry.update(scene_first=c["scene_first"], scene_stop=c["scene_stop"])
        listing.append(entry)
    manifest = {**totals, "num_shards": len(shards), "shards": listing,
                "config_hash": config_hash(cfg), "config": cfg, "code_version": code_version(),
                "format_version": cfg.get("format_version", FORMAT_VERSION)}
    tmp = out / f"{MANIFEST}.{tmp_tag or 'write'}.{process_tag()}.tmp"
    try:
        with open(tmp, "w") as f:
            f.write(json.dumps(manifest, indent=1))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out / MANIFEST)
        fsync_dir(out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return manifest


def _check_existing_shards(out: Path, *, chash: str, num_scenes: int, scenes_per_shard: int,
                           num_shards: int) -> list[int]:
    """Shard indices still to write; refuses a folder holding more scenes than asked."""
    todo = []
    for i in range(num_shards):
        path = out / shard_name(i)
        if not path.exists():
            todo.append(i)
            continue
        c = read_shard_counts(path)
        if c["config_hash"] != chash:
            raise ValueError(f"{path}: made with a different configuration")
        if c["scene_first"] is None:
            raise ValueError(f"{path}: written without its scene range (an older format); "
                             "use another --out")
        want = shard_scene_range(i, num_scenes=num_scenes, scenes_per_shard=scenes_per_shard)
        have = range(c["scene_first"], c["scene_stop"])
        if have == want:
            continue
        if have.start == want.start and have.stop < want.stop:
            todo.append(i)  # the last shard of a smaller run: rewritten with more scenes
            continue
        raise ValueError(
            f"{path}: holds scenes {have.start}..{have.stop - 1} but --scenes {num_scenes} "
            f"puts scenes {want.start}..{want.stop - 1} in it; this folder holds a larger "
            f"dataset: use --scenes >= {have.stop} or another --out")
    beyond = sorted(p.name for p in out.glob("shard-*.h5")
                    if p.name not in {shard_name(i) for i in range(num_shards)})
    if beyond:
        raise ValueError(
            f"{out}: holds {', '.join(beyond)} beyond the {num_shards} shard(s) of --scenes "
            f"{num_scenes}; this folder holds a larger dataset: use a larger --scenes or "
            "another --out")
    return todo


def check_generate_args(*, split: str, num_scenes: int) -> None:
    """The split and scene count of a generator (this dataset's and GPD's).

    Raises:
        ValueError: naming the flag and what was expected.
    """
    if split not in ("train", "test"):
        raise ValueError(f"--split: expected train or test, got {split!r}")
    if num_scenes < 1:
        raise ValueError(f"--scenes: expected >= 1, got {num_scenes}")


def generate_dataset(*, out: str | Path, num_scenes: int, split: str, seed: int,
                     scenario, config: DatasetConfig | None = None, workers: int = 1,
                     scheduler: str | None = None, objects_dir: str | None = None,
                     progress: bool = True) -> dict:
    """Generates (or resumes) a dataset of exactly `num_scenes` scenes; returns the manifest.

    Args:
        out: output folder; finished shards there are kept and skipped.
        num_scenes: number of labelled scenes (the last shard may hold fewer than
            `scenes_per_shard`). A scene that does not settle or has no true grasp is
            replaced by the next seed of its own sequence (`scene_seed`).
        split: "train" or "test": which object instances the scenes use.
        seed: dataset seed; scene i uses `scene_seed(seed, i, attempt)`.
        scenario: the `Scenario` whose camera, depth noise, plant and scene settings apply.
        workers: local worker processes (ignored with `scheduler`).
        scheduler: address of a Dask distributed scheduler; None -> local processes.
        objects_dir: object library folder; None -> built-in objects.

    Raises:
        FolderInUseError: another generator holds `out` (the message names it).
        ValueError: a folder made with another configuration, or holding more scenes.
    """
    from drake_grasp.config.scenario import dump_scenario

    config = config or DatasetConfig()
    config.validate()
    check_generate_args(split=split, num_scenes=num_scenes)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = _config_dict(scenario, config, split, seed)
    chash = config_hash(cfg)
    with GenerateLock(out) as lock:
        if lock.stale_owner is not None:
            stale_token = str(lock.stale_owner.get("token", ""))
            leftovers = temp_files(out, stale_token) if stale_token else []
            print(f"drake-grasp generate: taking over the stale lock {lock.path} of "
                  f"{describe_owner(lock.stale_owner)}, which no longer runs; removing its "
                  f"{len(leftovers)} temporary file(s)", file=sys.stderr)
            for path in leftovers:
                path.unlink(missing_ok=True)
        try:
            return _generate_locked(out, cfg=cfg, chash=chash, num_scenes=num_scenes,
                                    split=split, seed=seed, scenario_yaml=dump_scenario(scenario),
                                    config=config, workers=workers, scheduler=scheduler,
                                    objects_dir=objects_dir, progress=progress,
                                    token=lock.token)
        finally:
            for path in temp_files(out, lock.token):
                path.unlink(missing_ok=True)  # this run's own, from a failed worker


def _generate_locked(out: Path, *, cfg: dict, chash: str, num_scenes: int, split: str,
                     seed: int, scenario_yaml: str, config: DatasetConfig, workers: int,
                     scheduler: str | None, objects_dir, progress: bool, token: str) -> dict:
    old = out / MANIFEST
    if old.exists():
        previous = json.loads(old.read_text())
        if previous.get("config_hash") != chash:
            diff = [k for k in cfg if previous.get("config", {}).get(k) != cfg[k]]
            raise ValueError(f"{out}: holds a dataset made with a different configuration "
                             f"(differs in {diff}); use another --out")
    num_shards = -(-num_scenes // config.scenes_per_shard)
    todo = _check_existing_shards(out, chash=chash, num_scenes=num_scenes,
                                  scenes_per_shard=config.scenes_per_shard,
                                  num_shards=num_shards)
    attrs = {"split": split, "config_hash": chash, "code_version": code_version(),
             "format_version": FORMAT_VERSION}
    args = dict(out=str(out), seed=int(seed), split=split, scenario_yaml=scenario_yaml,
                config=dataclasses.asdict(config),
                objects_dir=str(objects_dir) if objects_dir else None, attrs=attrs,
                num_scenes=int(num_scenes), tmp_tag=token)
    timings, steady = _run_tasks(todo, args, workers=workers, scheduler=scheduler,
                                 progress=progress, total=num_shards,
                                 done=num_shards - len(todo))
    manifest = write_manifest(out, cfg, tmp_tag=token)
    if manifest["num_scenes"] != num_scenes:  # a bookkeeping error, never expected
        raise RuntimeError(f"{out}: holds {manifest['num_scenes']} scenes, expected {num_scenes}")
    # Summed worker seconds per stage of this run's shard tasks, and the labels and seconds
    # of the tasks that were not their process's first (returned, not written).
    manifest["run_timings_s"] = timings
    manifest["run_steady_labels"], manifest["run_steady_seconds"] = steady
    return manifest


def _run_tasks(todo: list[int], args: dict, *, workers: int, scheduler: str | None,
               progress: bool, total: int, done: int) -> tuple[dict, tuple[int, float]]:
    """Runs the shard tasks; returns the summed per-stage worker seconds, and the labels
    and summed seconds of the tasks that were not the first of their process."""
    from tqdm import tqdm

    bar = tqdm(total=total, initial=done, unit="shard", disable=not progress,
               desc="generate", dynamic_ncols=True)
    labels, steady_labels, steady_seconds = 0, 0, 0.0
    t0 = time.perf_counter()
    timings: dict = {}

    def tick(counts):
        nonlocal labels, steady_labels, steady_seconds
        labels += counts["num_labels"]
        if not counts["first_in_process"]:
            steady_labels += counts["num_labels"]
            steady_seconds += counts["seconds"]
        for k, v in counts.get("timings", {}).items():
            timings[k] = timings.get(k, 0.0) + v
        bar.update(1)
        bar.set_postfix(labels_per_s=f"{labels / (time.perf_counter() - t0):.0f}")

    try:
        if not todo:
            return timings, (steady_labels, steady_seconds)
        if scheduler:
            from dask.distributed import Client, as_completed

            with Client(scheduler) as client:
                futures = [client.submit(_shard_task, i, **args, pure=False) for i in todo]
                for fut in as_completed(futures):
                    tick(fut.result())
        elif workers <= 1:
            for i in todo:
                tick(_shard_task(i, **args))
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            ctx = mp.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                futures = [pool.submit(_shard_task, i, **args) for i in todo]
                for fut in as_completed(futures):
                    tick(fut.result())
    finally:
        bar.close()
    return timings, (steady_labels, steady_seconds)
