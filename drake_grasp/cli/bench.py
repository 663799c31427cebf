"""Benchmarks of the hot paths (`drake-grasp bench`). Not tests: they measure, not check.

Keys:
    rtf_isolation: real-time factor (sim time / wall time of the simulation loop) of a
        scripted-grasp episode with one object, wrist depth frames at 10 Hz, one core;
        `_reference`: the same episode with the reference physics profile in the same
        run, `_speedup` the ratio.
    rtf_clutter5: the same with 5 objects in a pile.
    depth_frame_ms: render + post-process one 64x64 wrist depth frame (median).
    labels_per_s: dataset generation, 2 workers, paper settings, start-up included;
        labels_per_s_sustained: the same run without each worker's first task (the rate
        of a long run); `_stable`: the same with stable initial poses
        (`DatasetConfig.initial_pose`), in the same call.
    gpd_detect_s_isolation / _clutter5: the GPD baseline's one decision (image -> grasp).
    cnn: cnn_infer_ms_128 / cnn_infer_direct_ms_128 (one image, 128 actions),
        train_samples_per_s / train_direct_samples_per_s (2 threads).
    cnn_onnx: cnn_onnx_torch_ms_128 / cnn_onnx_ms_128 (`score_candidates`, one depth
        image, 128 actions, shipped weights, 1 thread each; torch vs onnxruntime side by
        side, interleaved), cnn_onnx_speedup = torch / onnxruntime. null without the
        optional packages onnx + onnxruntime.
    worker_rss_mb_per_trial, trial_overhead_fraction: a Monte Carlo worker's memory growth
        per trial, and the share of a trial outside the plant's advance (`bench_scaling`).
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from drake_grasp.cli.bench_scaling import bench_trial_overhead, bench_worker_rss

BENCH_SEED = 3


def _machine() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        drake_version = version("drake")
    except PackageNotFoundError:
        drake_version = "unknown"
    info = {"platform": platform.platform(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "drake": drake_version}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu"] = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return info


def episode_rtf(scenario_name: str, text: str = "", *, physics_profile: str = "",
                record_depth: bool = True) -> dict:
    """One scripted episode: the simulation loop's real-time factor, and the wall time of
    the whole episode (settling and Diagram building included)."""
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.config.scenario import load_scenario, replace

    scenario = replace(load_scenario(scenario_name=scenario_name, scenario_text=text,
                                     physics_profile=physics_profile),
                       seed=BENCH_SEED, visualize=False)
    t0 = time.perf_counter()
    run = simulate_episode(scenario, scenario_name=scenario_name, record_depth=record_depth)
    episode_wall = time.perf_counter() - t0
    r = run.result
    wall = r.details["simulation_wall_time_s"]
    return {"rtf": r.sim_time_s / wall, "sim_time_s": r.sim_time_s, "wall_s": round(wall, 3),
            "episode_wall_s": round(episode_wall, 3), "success": r.success,
            "failure_class": r.details.get("failure_class"),
            "objects": len(r.object_ids), "physics_profile": scenario.physics.profile,
            "time_step_s": scenario.plant.time_step}


def _rtf_side_by_side(key: str, scenario_name: str, text: str) -> dict:
    """The same scripted episode with the reference physics profile, then the default
    one, in this process: `key`, `key_reference` and their ratio `key_speedup`."""
    ref = episode_rtf(scenario_name, text, physics_profile="reference")
    new = episode_rtf(scenario_name, text)
    return {key: round(new["rtf"], 3), f"{key}_detail": new,
            f"{key}_reference": round(ref["rtf"], 3), f"{key}_reference_detail": ref,
            f"{key}_speedup": round(new["rtf"] / ref["rtf"], 2)}


def bench_rtf_isolation() -> dict:
    return _rtf_side_by_side("rtf_isolation", "isolation", "{policy: scripted}")


def bench_rtf_clutter5() -> dict:
    return _rtf_side_by_side("rtf_clutter5", "clutter",
                             "{policy: scripted, scene: {clutter_objects: 5}}")


def bench_rtf_ctr_clutter5() -> dict:
    """A full CTR episode (CNN every 0.1 s, 128 candidates) in a 5-object pile."""
    out = episode_rtf("clutter", "{policy: ctr, scene: {clutter_objects: 5}}")
    return {"rtf_ctr_clutter5": round(out["rtf"], 3), "rtf_ctr_clutter5_detail": out}


def bench_controller_step_ms(repeats: int = 50) -> dict:
    """Latest image -> chosen action: sample 128 candidates, score them with the CNN
    (fast path, 1 thread as in an episode), pick the least (median). For the grid head,
    side by side in the same loop: `controller_step_whole_grid_ms`, the same step with IP2
    evaluated at every grid node (the path before `score_grid_nodes`), and
    `controller_step_fcn_ms`, the step with the height-map FCN (`models/fcn-heightmap/`,
    the image seen from 0.25 m)."""
    import torch

    from drake_grasp.core.assets import model_path
    from drake_grasp.policies.decisions import choose_action, sample_candidates
    from drake_grasp.policies.evaluator import FCN_WEIGHTS, load_cnn, score_candidates

    model = load_cnn("")
    fcn = load_cnn(str(model_path(FCN_WEIGHTS)))  # in the repository's models/ only

    def whole_grid(depth, actions):
        with torch.inference_mode():
            grids = model.image_features(model.preprocess(depth))
            return model.score_actions(grids[0], actions).numpy().astype(float)

    paths = {"controller_step_ms": lambda d, a: score_candidates(model, d, a)}
    if getattr(model, "grid", False):
        paths["controller_step_whole_grid_ms"] = whole_grid
    paths["controller_step_fcn_ms"] = lambda d, a: score_candidates(fcn, d, a,
                                                                    camera_height_m=0.25)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rng = np.random.default_rng(0)
        depth = rng.uniform(0.2, 0.3, (64, 64)).astype(np.float32)
        times = {key: [] for key in paths}
        for _ in range(repeats):
            for key, score in paths.items():
                t0 = time.perf_counter()
                actions = sample_candidates(rng, 128, xy_m=0.04, theta_deg=45.0)
                choose_action(actions, score(depth, actions))
                times[key].append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(threads)
    out = {key: round(1000 * float(np.median(t)), 2) for key, t in times.items()}
    if "controller_step_whole_grid_ms" in out:
        out["controller_step_speedup"] = round(
            out["controller_step_whole_grid_ms"] / out["controller_step_ms"], 2)
    return out


def bench_depth_frame_ms(repeats: int = 200) -> dict:
    """Median time to render and post-process one frame at a new time (cache miss)."""
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario, replace
    from drake_grasp.world.scene import scenario_scene

    scenario = load_scenario(scenario_name="clutter", scenario_text="{policy: scripted}")
    scenario = replace(scenario, seed=BENCH_SEED)
    scenario.depth_noise.enabled = True
    library = load_library(None)
    scene = scenario_scene(scenario, library)
    ed = build_episode_diagram(scenario, scene, library)
    diagram, station = ed.diagram, ed.station
    root = diagram.CreateDefaultContext()
    station.set_initial_state(station.diagram.GetMyMutableContextFromRoot(root))
    sc = station.diagram.GetMyMutableContextFromRoot(root)
    port = station.diagram.GetOutputPort("depth_image")
    port.Eval(sc)
    times = []
    for i in range(repeats):
        root.SetTime(0.1 * (i + 1))  # invalidates the cached render
        t0 = time.perf_counter()
        port.Eval(sc)
        times.append(time.perf_counter() - t0)
    return {"depth_frame_ms": round(1000 * float(np.median(times)), 3)}


def _labels_run(initial_pose: str, num_scenes: int, workers: int) -> dict:
    """One `bench_labels_per_s` generation; its rate, sustained rate and detail."""
    import tempfile

    from drake_grasp.learning.dataset import DatasetConfig
    from drake_grasp.learning.dataset_generate import generate_dataset
    from drake_grasp.config.scenario import load_scenario

    scenario = load_scenario(scenario_name="random", scenario_text=f"{{seed: {BENCH_SEED}}}")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        manifest = generate_dataset(out=tmp, num_scenes=num_scenes, split="train",
                                    seed=BENCH_SEED, scenario=scenario,
                                    config=DatasetConfig(scenes_per_shard=1,
                                                         initial_pose=initial_pose),
                                    workers=workers, progress=False)
        wall = time.perf_counter() - t0
    # A long run amortizes the workers' start-up (process, imports, the first meshes): its
    # rate is what busy workers sustain, the labels of the tasks that were not their
    # process's first over those tasks' seconds, times the workers.
    steady_s = manifest["run_steady_seconds"]
    sustained = workers * manifest["run_steady_labels"] / steady_s if steady_s > 0 else None
    return {"rate": round(manifest["num_labels"] / wall, 1),
            "sustained": round(sustained, 1) if sustained else None,
            "detail": {"scenes": manifest["num_scenes"], "labels": manifest["num_labels"],
                       "wall_s": round(wall, 2), "workers": workers,
                       "initial_pose": initial_pose,
                       "scene_attempts": manifest["num_scene_attempts"],
                       "unsettled_resampled": manifest["num_scenes_unsettled_resampled"],
                       "no_grasp_resampled": manifest["num_scenes_no_grasp_resampled"],
                       "worker_seconds_by_stage": {
                           k: round(v, 2) for k, v in manifest["run_timings_s"].items()}}}


def bench_labels_per_s(num_scenes: int = 24, workers: int = 2) -> dict:
    """Dataset generation rate with 2 local workers, paper settings (40 images x 10
    offsets per scene): labels / wall time of the whole command (worker start-up
    included), plus the worker seconds spent in each stage (where the time goes) and the
    scene attempts thrown away. The default uniform initial poses (`labels_per_s`) and the
    stable ones (`labels_per_s_stable`) side by side in one call, the same scenes; the
    stable poses' cache (`objects.stable_poses`) as this machine has it."""
    out = {}
    for pose, key in (("uniform", "labels_per_s"), ("stable", "labels_per_s_stable")):
        run = _labels_run(pose, num_scenes, workers)
        out[key], out[f"{key}_sustained"] = run["rate"], run["sustained"]
        out[f"{key}_detail"] = run["detail"]
    return out


def bench_cnn(rounds: int = 8) -> dict:
    """The distance CNN on 2 threads, fast path and direct form interleaved in one run:
    scoring 128 candidate actions for one image (control), and forward + backward on
    batches of 100 images x 10 offsets (training, samples = image-offset pairs)."""
    import statistics

    import torch

    from drake_grasp.cnn.network import DistanceCNN

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        g = torch.Generator().manual_seed(0)
        model = DistanceCNN(generator=g)
        image = torch.randn(1, 1, 64, 64, generator=g)
        actions = torch.rand(128, 3, generator=g) * 0.2 - 0.1
        image128 = image.expand(128, 1, 64, 64).contiguous()
        images = torch.randn(100, 1, 64, 64, generator=g)
        offsets = torch.rand(100, 10, 3, generator=g) * 0.2 - 0.1
        labels = torch.rand(100, 10, generator=g) * 0.1
        images_rep = images.repeat_interleave(10, 0)

        def infer_fast():
            with torch.inference_mode():
                model.score_actions(model.image_features(image), actions)

        def infer_direct():
            with torch.inference_mode():
                model.forward_direct(image128, actions)

        def train_fast():
            model.zero_grad(set_to_none=True)
            (model.forward_factored(images, offsets) - labels).abs().mean().backward()

        def train_direct():
            model.zero_grad(set_to_none=True)
            pred = model.forward_direct(images_rep, offsets.reshape(-1, 3))
            (pred - labels.reshape(-1)).abs().mean().backward()

        def timed(f):
            t0 = time.perf_counter()
            f()
            return time.perf_counter() - t0

        runs = {f: [] for f in (infer_fast, infer_direct, train_fast, train_direct)}
        for f in runs:
            f()
        for _ in range(rounds):
            runs[infer_fast] += [timed(infer_fast) for _ in range(10)]
            runs[infer_direct] += [timed(infer_direct) for _ in range(2)]
            runs[train_fast] += [timed(train_fast) for _ in range(3)]
            runs[train_direct] += [timed(train_direct)]
        med = {f.__name__: statistics.median(v) for f, v in runs.items()}
    finally:
        torch.set_num_threads(threads)
    ip1_flops = 2 * 8450 * 500  # IP1 multiply-adds per action, the floor of this net
    return {
        "cnn_infer_ms_128": round(1000 * med["infer_fast"], 2),
        "cnn_infer_direct_ms_128": round(1000 * med["infer_direct"], 2),
        "cnn_infer_speedup": round(med["infer_direct"] / med["infer_fast"], 1),
        "train_samples_per_s": round(1000 / med["train_fast"], 1),
        "train_direct_samples_per_s": round(1000 / med["train_direct"], 1),
        "train_speedup": round(med["train_direct"] / med["train_fast"], 1),
        "cnn_ip1_gflops_infer": round(128 * ip1_flops / med["infer_fast"] / 1e9, 1),
        "cnn_ip1_gflops_train": round(3 * 1000 * ip1_flops / med["train_fast"] / 1e9, 1),
    }


def bench_cnn_onnx(rounds: int = 10, repeats: int = 10) -> dict:
    """`score_candidates` on one depth image with 128 candidates: the torch fast path and
    the ONNX export of the same weights (the shipped paper net, `models/cnn/`: the export
    covers the tiled fusion) under onnxruntime, 1 thread each, the
    same inputs, interleaved in `rounds` x `repeats` (median of each)."""
    import importlib.util
    import logging
    import statistics
    import tempfile

    if any(importlib.util.find_spec(m) is None for m in ("onnx", "onnxruntime")):
        logging.getLogger("drake_grasp").warning(
            "bench cnn_onnx: onnx/onnxruntime not installed (pip install "
            "'drake_grasp[onnx-export]'); printing null")
        return {"cnn_onnx_torch_ms_128": None, "cnn_onnx_ms_128": None, "cnn_onnx_speedup": None}
    import torch

    from drake_grasp.core.assets import model_path
    from drake_grasp.cnn.onnx_export import export_onnx
    from drake_grasp.policies.decisions import sample_candidates
    from drake_grasp.policies.evaluator import PAPER_WEIGHTS, load_cnn, score_candidates

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            onnx_path = export_onnx(out=Path(tmp) / "cnn.onnx").path  # the paper net
            backends = {"torch": load_cnn(str(model_path(PAPER_WEIGHTS))),
                        "onnx": load_cnn(str(onnx_path))}
        rng = np.random.default_rng(BENCH_SEED)
        depth = rng.uniform(0.2, 0.3, (64, 64)).astype(np.float32)
        actions = sample_candidates(rng, 128, xy_m=0.04, theta_deg=45.0)
        times: dict[str, list[float]] = {name: [] for name in backends}
        for model in backends.values():
            score_candidates(model, depth, actions)  # warm-up
        for _ in range(rounds):
            for name, model in backends.items():
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    score_candidates(model, depth, actions)
                    times[name].append(time.perf_counter() - t0)
        med = {name: statistics.median(v) for name, v in times.items()}
    finally:
        torch.set_num_threads(threads)
    return {"cnn_onnx_torch_ms_128": round(1000 * med["torch"], 2),
            "cnn_onnx_ms_128": round(1000 * med["onnx"], 2),
            "cnn_onnx_speedup": round(med["torch"] / med["onnx"], 2)}


def bench_trials_per_hour(trials: int = 6, workers: int = 2) -> dict:
    """Physical CTR trials of the isolation experiment per hour on 2 local workers
    (worker start-up included; each worker keeps the CNN and meshes across trials), with
    the reference physics profile, the default one and `fast10`, in this run.

    `_sustained`: what a long run approaches, `workers` x 3600 s over the mean trial wall
    time of the same trials (the records' `wall_time_s`: scene, Diagram, simulation and
    judge; the workers' start-up, about 3 s each, is left out)."""
    import tempfile

    from drake_grasp.evaluation.montecarlo import evaluate
    from drake_grasp.evaluation.records import load_records

    out = {}
    for key, profile in (("trials_per_hour_reference", "reference"), ("trials_per_hour", ""),
                         ("trials_per_hour_fast10", "fast10")):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            result = evaluate(experiment="isolation", out=tmp, trials=trials, workers=workers,
                              seed=BENCH_SEED, conditions=["ctr"], progress=False,
                              report=False, physics_profile=profile)
            wall = time.perf_counter() - t0
            records = load_records(tmp)
        mean_trial = sum(r.wall_time_s for r in records) / len(records)
        out[key] = round(result["records"] / wall * 3600, 1)
        out[key + "_sustained"] = round(workers * 3600 / mean_trial, 1)
        out[key + "_detail"] = {"trials": result["records"], "wall_s": round(wall, 1),
                                "workers": workers, "physics_profile": profile or "default",
                                "mean_trial_wall_s": round(mean_trial, 3),
                                "successes": sum(bool(r.success) for r in records)}
    out["trials_per_hour_speedup"] = round(out["trials_per_hour"]
                                           / out["trials_per_hour_reference"], 2)
    out["trials_per_hour_sustained_speedup"] = round(
        out["trials_per_hour_sustained"] / out["trials_per_hour_reference_sustained"], 2)
    out["trials_per_hour_fast10_sustained_speedup"] = round(
        out["trials_per_hour_fast10_sustained"] / out["trials_per_hour_reference_sustained"], 2)
    return out


def bench_grasp_checks_per_s(grasps: int = 6) -> dict:
    """Grasp-lab checks per second on one core: sampled ground-truth grasps of one
    settled object (scene settling and grasp sampling excluded), each a full descend,
    close, lift, hold and shake - with the default physics profile and, side by side on
    the same grasps, the reference one (`_reference`) and `fast10` (`_fast10`: 10 ms
    steps), with how often each one's verdicts agree with the default's."""
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.evaluation.lab import LabConfig, check_grasps, isolated_scene
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario

    library = load_library(None)
    rng = np.random.default_rng(BENCH_SEED)
    scene = isolated_scene("can_000", library, lying=True)
    found = find_grasps(scene, library, rng)
    chosen = rng.choice(len(found), size=min(grasps, len(found)), replace=False)
    out, verdicts = {}, {}
    lab = LabConfig()
    for key, profile in (("grasp_checks_per_s", ""), ("grasp_checks_per_s_reference", "reference"),
                         ("grasp_checks_per_s_fast10", "fast10")):
        scenario = load_scenario(physics_profile=profile)
        t0 = time.perf_counter()
        results = check_grasps(None, found.poses[chosen], scene=scene, library=library,
                               object_indices=found.object_index[chosen], lab=lab,
                               scenario=scenario)
        wall = time.perf_counter() - t0
        verdicts[key] = [r.held for r in results]
        out[key] = round(len(results) / wall, 3)
        out[key + "_detail"] = {
            "checks": len(results), "held": int(sum(r.held for r in results)),
            "wall_s": round(wall, 2), "s_per_check": round(wall / len(results), 3),
            "time_step_s": lab.time_step_s or scenario.plant.time_step,
            "physics_profile": scenario.physics.profile,
            "sim_s_per_check": round(float(np.mean([r.details["sim_time_s"] for r in results])), 2)}
    out["grasp_checks_speedup"] = round(out["grasp_checks_per_s"]
                                        / out["grasp_checks_per_s_reference"], 2)
    out["grasp_checks_fast10_speedup"] = round(out["grasp_checks_per_s_fast10"]
                                               / out["grasp_checks_per_s"], 2)
    default = verdicts["grasp_checks_per_s"]
    out["grasp_checks_verdicts_agree"] = int(sum(
        a == b for a, b in zip(default, verdicts["grasp_checks_per_s_reference"])))
    out["grasp_checks_fast10_verdicts_agree"] = int(sum(
        a == b for a, b in zip(default, verdicts["grasp_checks_per_s_fast10"])))
    return out


def bench_gpd_detect(repeats: int = 3) -> dict:
    """The GPD baseline's one decision: GPD sensor image (640x480, rendered at the
    viewpoint of a settled isolation / 5-object pile scene) -> selected grasp, with the
    shipped classifier, one thread (median of `repeats`; per-stage seconds in _detail)."""
    import dataclasses

    import torch

    from drake_grasp.policies import gpd
    from drake_grasp.learning.gpd_training import experiment_view
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario

    library = load_library(None)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    out = {}
    try:
        for key, name in (("isolation", "isolation"), ("clutter5", "clutter")):
            scenario = load_scenario(scenario_name=name)
            settled, X_WC, depth = experiment_view(scenario, BENCH_SEED, library)
            detect = gpd.make_detector(dataclasses.replace(scenario, seed=BENCH_SEED))
            times, runs = [], []
            for _ in range(repeats):
                t0 = time.perf_counter()
                d = detect.detector.detect(depth, X_WC, np.random.default_rng(0))
                times.append(time.perf_counter() - t0)
                runs.append(d)
            d = runs[0]
            out[f"gpd_detect_s_{key}"] = round(float(np.median(times)), 3)
            out[f"gpd_detect_s_{key}_detail"] = {
                "stages_s": {k: round(v, 3) for k, v in d.timings.items()},
                "cloud_points": d.num_cloud_points, "candidates": d.num_candidates,
                "detections": len(d.poses), "objects": len(settled.objects)}
    finally:
        torch.set_num_threads(threads)
    return out


BENCHMARKS = {
    "rtf_isolation": bench_rtf_isolation,
    "rtf_clutter5": bench_rtf_clutter5,
    "depth_frame_ms": bench_depth_frame_ms,
    "labels_per_s": bench_labels_per_s,
    "cnn": bench_cnn,
    "cnn_onnx": bench_cnn_onnx,
    "controller_step_ms": bench_controller_step_ms,
    "rtf_ctr_clutter5": bench_rtf_ctr_clutter5,
    "trials_per_hour": bench_trials_per_hour,
    "grasp_checks_per_s": bench_grasp_checks_per_s,
    "gpd_detect": bench_gpd_detect,
    "worker_rss_mb_per_trial": bench_worker_rss,
    "trial_overhead_fraction": bench_trial_overhead,
}

# Every key each benchmark prints (besides "machine" and "date"), so that `--only` takes
# any printed key as well as a group name. `run_benchmarks` checks a group's output
# against this list, so it cannot drift from the code silently.
PRINTED_KEYS: dict[str, tuple[str, ...]] = {
    "rtf_isolation": ("rtf_isolation", "rtf_isolation_detail", "rtf_isolation_reference",
                      "rtf_isolation_reference_detail", "rtf_isolation_speedup"),
    "rtf_clutter5": ("rtf_clutter5", "rtf_clutter5_detail", "rtf_clutter5_reference",
                     "rtf_clutter5_reference_detail", "rtf_clutter5_speedup"),
    "depth_frame_ms": ("depth_frame_ms",),
    "labels_per_s": ("labels_per_s", "labels_per_s_sustained", "labels_per_s_detail",
                     "labels_per_s_stable", "labels_per_s_stable_sustained",
                     "labels_per_s_stable_detail"),
    "cnn": ("cnn_infer_ms_128", "cnn_infer_direct_ms_128", "cnn_infer_speedup",
            "train_samples_per_s", "train_direct_samples_per_s", "train_speedup",
            "cnn_ip1_gflops_infer", "cnn_ip1_gflops_train"),
    "cnn_onnx": ("cnn_onnx_torch_ms_128", "cnn_onnx_ms_128", "cnn_onnx_speedup"),
    "controller_step_ms": ("controller_step_ms", "controller_step_whole_grid_ms",
                           "controller_step_speedup", "controller_step_fcn_ms"),
    "rtf_ctr_clutter5": ("rtf_ctr_clutter5", "rtf_ctr_clutter5_detail"),
    "trials_per_hour": ("trials_per_hour", "trials_per_hour_detail", "trials_per_hour_reference",
                        "trials_per_hour_reference_detail", "trials_per_hour_speedup",
                        "trials_per_hour_sustained", "trials_per_hour_reference_sustained",
                        "trials_per_hour_sustained_speedup", "trials_per_hour_fast10",
                        "trials_per_hour_fast10_detail", "trials_per_hour_fast10_sustained",
                        "trials_per_hour_fast10_sustained_speedup"),
    "grasp_checks_per_s": ("grasp_checks_per_s", "grasp_checks_per_s_detail",
                           "grasp_checks_per_s_reference", "grasp_checks_per_s_reference_detail",
                           "grasp_checks_speedup", "grasp_checks_verdicts_agree",
                           "grasp_checks_per_s_fast10", "grasp_checks_per_s_fast10_detail",
                           "grasp_checks_fast10_speedup", "grasp_checks_fast10_verdicts_agree"),
    "gpd_detect": ("gpd_detect_s_isolation", "gpd_detect_s_isolation_detail",
                   "gpd_detect_s_clutter5", "gpd_detect_s_clutter5_detail"),
    "worker_rss_mb_per_trial": ("worker_rss_mb_per_trial", "worker_rss_mb_per_trial_in_process",
                                "worker_rss_mb_per_trial_detail"),
    "trial_overhead_fraction": ("trial_overhead_fraction", "trial_overhead_fraction_profiled",
                                "trial_overhead_fraction_detail"),
}


def resolve_only(only: list[str] | None) -> dict[str, list[str] | None]:
    """Maps `--only` names to {group: keys to print (None: all of the group's)}.

    A name is a group ("cnn") or any key a group prints ("cnn_infer_ms_128"); asking for
    several keys of one group runs it once.

    Raises:
        ValueError: naming the unknown names and listing every accepted one.
    """
    if not only:
        return {group: None for group in BENCHMARKS}
    owner = {key: group for group, keys in PRINTED_KEYS.items() for key in keys}
    unknown = [k for k in only if k not in BENCHMARKS and k not in owner]
    if unknown:
        raise ValueError(f"--only: unknown benchmark keys {unknown}; groups: "
                         f"{list(BENCHMARKS)}; keys: {sorted(owner)}")
    plan: dict[str, list[str] | None] = {}
    for name in only:
        if name in BENCHMARKS:
            plan[name] = None
        elif plan.get(owner[name], []) is not None:
            plan.setdefault(owner[name], []).append(name)
    return plan


def run_benchmarks(*, only: list[str] | None = None, out: str | Path | None = None) -> dict:
    """Runs the named benchmarks (all by default); optionally writes JSON to `out`.

    Args:
        only: Group names (`BENCHMARKS`) or printed keys (`PRINTED_KEYS`); a key runs its
            group and keeps that key (and its "_detail" entry, if any).
        out: Also write the JSON here (atomically), with the machine description.
    """
    plan = resolve_only(only)
    results: dict = {}
    for group, keys in plan.items():
        got = BENCHMARKS[group]()
        if set(got) != set(PRINTED_KEYS[group]):
            raise RuntimeError(f"benchmark {group!r} printed {sorted(got)}, but PRINTED_KEYS "
                               f"lists {sorted(PRINTED_KEYS[group])}: update PRINTED_KEYS")
        if keys is not None:
            wanted = set(keys) | {f"{k}_detail" for k in keys}
            got = {k: v for k, v in got.items() if k in wanted}
        results.update(got)
    results["machine"] = _machine()
    results["date"] = time.strftime("%Y-%m-%d")
    if out is not None:
        from drake_grasp.core.files import atomic_write_text

        atomic_write_text(out, json.dumps(results, indent=1))
    return results
