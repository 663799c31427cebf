"""The `drake-grasp` command line. Thin: parses flags and calls library functions."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _policy_arg(text: str) -> str:
    """--policy: a built-in policy name or MODULE:FACTORY (a user policy)."""
    from drake_grasp.policies.plugins import is_policy_spec, parse_policy_spec
    from drake_grasp.config.scenario import POLICIES

    if text in POLICIES:
        return text
    if not is_policy_spec(text):
        raise argparse.ArgumentTypeError(
            f"invalid choice: {text!r} (choose from {', '.join(POLICIES)}, or MODULE:FACTORY "
            "for your own policy)")
    try:
        parse_policy_spec(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def _add_scenario_flags(p: argparse.ArgumentParser, default: str = "isolation") -> None:
    p.add_argument("--scenario-file", default=None,
                   help="a *.scenarios.yaml file (default: the shipped diagrams/default.scenarios.yaml)")
    p.add_argument("--scenario", default=default,
                   help=f"name of the scenario in the scenarios file (default: {default})")
    p.add_argument("--scenario-text", default="",
                   help="inline YAML overriding keys of the named scenario, "
                        "e.g. '{gripper: {grip_force_n: 5.0}}'")
    p.add_argument("--objects", default=None, metavar="DIR",
                   help="object library folder made by 'drake-grasp objects import' "
                        "(default: the built-in procedural objects)")


def _load(args, **overrides):
    from drake_grasp.config.scenario import load_scenario, replace

    scenario = load_scenario(scenario_name=args.scenario, scenario_file=args.scenario_file,
                             scenario_text=args.scenario_text)
    if args.objects:
        overrides["objects_dir"] = str(args.objects)
    return replace(scenario, **overrides) if overrides else scenario


def _cmd_demo(args) -> int:
    from drake_grasp.evaluation.episode import run_episode

    import dataclasses

    overrides = {}
    if args.policy is not None:
        overrides["policy"] = args.policy
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.target is not None:
        overrides["target"] = args.target
    scenario = _load(args, **overrides)
    if args.noise is not None:
        scenario = dataclasses.replace(
            scenario, noise=dataclasses.replace(scenario.noise, kind=args.noise))
    if args.weights is not None:
        scenario = dataclasses.replace(
            scenario, controller=dataclasses.replace(scenario.controller, weights=args.weights))
    scenario.validate()
    result = run_episode(scenario, out_dir=args.out, scenario_name=args.scenario,
                         replay=not args.no_replay)
    print(json.dumps({"success": result.success, "failure_reason": result.failure_reason,
                      "final_distance_m": result.final_distance_m,
                      "control_steps": result.control_steps,
                      "object_ids": result.object_ids, "sim_time_s": round(result.sim_time_s, 3),
                      "wall_time_s": round(result.wall_time_s, 2), "out": str(args.out)}))
    return 0


def _cmd_diagram(args) -> int:
    from drake_grasp.evaluation.graphviz import write_diagram

    scenario = _load(args)
    path = write_diagram(scenario, out=args.out, depth=args.depth)
    print(path)
    return 0


def _cmd_bench(args) -> int:
    from drake_grasp.cli.bench import run_benchmarks

    only = [k for k in args.only.split(",") if k] if args.only else None
    results = run_benchmarks(only=only, out=args.out)
    print(json.dumps(results, indent=1))
    return 0


def _cmd_objects_import(args) -> int:
    from drake_grasp.objects import import_mesh

    info = import_mesh(args.mesh, name=args.name, library_dir=args.library, scale=args.scale,
                       density_kg_m3=args.density, overwrite=args.overwrite)
    print(json.dumps({"id": info.id, "mass_kg": info.mass_kg,
                      "extents_m": list(info.extents_m), "model": str(info.model_path)}))
    for warning in info.read_meta().get("warnings", []):
        print(f"drake-grasp objects import: warning: {warning}", file=sys.stderr)
    return 0


def _cmd_objects_list(args) -> int:
    from drake_grasp.objects import load_library

    library = load_library(args.objects)
    for object_id in library.ids(split=args.split or None):
        print(object_id)
    return 0


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def _non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}") from None
    if not (value >= 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def _trunk_widths(text: str) -> tuple[int, int, int]:
    parts = text.split(",")
    try:
        widths = tuple(int(v) for v in parts)
    except ValueError:
        widths = ()
    if len(widths) != 3 or min(widths) < 1:
        raise argparse.ArgumentTypeError(
            f"expected three integers >= 1 (conv1 filters, conv2 filters, ip1 width), e.g. "
            f"40,100,1000; got {text!r}")
    return widths


def _add_torque_ratio_flag(p) -> None:
    from drake_grasp.learning.dataset import DatasetConfig

    default = DatasetConfig().max_torque_ratio
    p.add_argument("--max-torque-ratio", type=_positive_float, default=default, metavar="R",
                   help="the ground truth's torque test: the largest torque about the "
                   "contact axis under gravity and the lab's shake, per unit of the pads' "
                   f"torsional friction lever, a true grasp may need (default {default:g}, "
                   "README *Grip force*)")


def _cmd_generate(args) -> int:
    from drake_grasp.learning.dataset import DatasetConfig, generate_dataset

    scenario = _load(args, seed=args.seed)
    config = DatasetConfig(images_per_scene=args.images_per_scene,
                           offsets_per_image=args.offsets_per_image,
                           scenes_per_shard=args.scenes_per_shard,
                           max_torque_ratio=args.max_torque_ratio,
                           grasp_samples=args.grasp_samples,
                           near_grasp_fraction=args.near_grasp_fraction,
                           scene_kind=args.scene_kind,
                           settle_max_time_s=args.settle_max_time)
    manifest = generate_dataset(out=args.out, num_scenes=args.scenes, split=args.split,
                                seed=args.seed, scenario=scenario, config=config,
                                workers=args.workers, scheduler=args.scheduler,
                                objects_dir=args.objects)
    print(json.dumps({k: manifest[k] for k in (
        "num_scenes", "num_images", "num_labels", "num_shards", "num_scene_attempts",
        "num_scenes_unsettled_resampled", "num_scenes_no_grasp_resampled")}))
    return 0


def _cmd_inspect_data(args) -> int:
    from drake_grasp.learning.datavis import inspect_dataset

    print(inspect_dataset(args.data, out=args.out, num_images=args.images, seed=args.seed))
    return 0


def _cmd_train(args) -> int:
    from drake_grasp.learning.training import TrainConfig, train

    config = TrainConfig.from_recipe(
        args.recipe, epochs=args.epochs, batch_instances=args.batch, optimizer=args.optimizer,
        learning_rate=args.lr, momentum=args.momentum, lr_decay_per_epoch=args.lr_decay,
        seed=args.seed, device=args.device, threads=args.threads,
        max_memory_gb=args.max_memory_gb, checkpoint_minutes=args.checkpoint_minutes,
        ranking_images=args.ranking_images, init_weights=args.init_weights,
        loss=args.loss, loss_offset_m=args.loss_offset)
    if args.loss_offset is not None and args.loss != "log-l1":
        print("--loss-offset: needs --loss log-l1", file=sys.stderr)
        return 2
    network = None  # the default net (or the --init-weights file's)
    if args.context_side and args.action_fusion != "window":
        print("--context-side: needs --action-fusion window", file=sys.stderr)
        return 2
    if args.action_fusion == "window":
        from drake_grasp.cnn.network import NetworkConfig
        try:
            network = NetworkConfig(theta_unit="deg", action_fusion="window",
                                    context_side_m=args.context_side)
        except ValueError as e:
            print(f"--context-side {args.context_side}: {e}", file=sys.stderr)
            return 2
    metrics = train(data=args.data, test_data=args.test_data, out=args.out, config=config,
                    network=network)
    print(json.dumps({"test_l1_m": metrics.get("test_l1_m"), "epochs": len(metrics["epochs"]),
                      "device": metrics["device"], "out": str(args.out)}))
    return 0


def _cmd_dense_labels(args) -> int:
    from drake_grasp.learning.dense_training import build_labels

    images = build_labels(args.data, args.out, workers=args.workers)
    print(json.dumps({"out": str(args.out), "images_labelled_now": images}))
    return 0


def _cmd_train_grid(args) -> int:
    from drake_grasp.learning.dense_training import train as train_grid

    metrics = train_grid([f for f in args.labels.split(",") if f], args.out,
                         test_data=args.test_data, init=args.init_weights, epochs=args.epochs,
                         batch=args.batch, lr=args.lr, lr_decay=args.lr_decay, seed=args.seed,
                         threads=args.threads, checkpoint_minutes=args.checkpoint_minutes,
                         trunk=args.trunk, batch_norm=args.batch_norm, device=args.device,
                         stream_shards=args.stream_shards, augment=args.augment,
                         rank_weight=args.rank_weight, rank_scale_m=args.rank_scale_m)
    last = metrics["epochs"][-1] if metrics["epochs"] else {}
    print(json.dumps({"out": str(args.out), "epochs": len(metrics["epochs"]),
                      **{k: last[k] for k in ("train_l1_m", "test_l1_m") if k in last}}))
    return 0


def _cmd_checkpoint_weights(args) -> int:
    from drake_grasp.learning.training import export_checkpoint_weights

    meta = export_checkpoint_weights(args.run, args.out)
    print(json.dumps({"out": str(args.out), **{k: meta[k] for k in (
        "checkpoint_epoch", "checkpoint_next_batch", "iterations")}}))
    return 0


def _cmd_gpd_generate(args) -> int:
    from drake_grasp.learning.gpd_training import GpdDataConfig, generate

    kinds = tuple(k for k in args.scene_kinds.split(",") if k)
    allowed = GpdDataConfig().scene_kinds
    if not kinds or any(k not in allowed for k in kinds):
        print(f"--scene-kinds {args.scene_kinds!r}: expected a comma-separated list of "
              f"{', '.join(allowed)}", file=sys.stderr)
        return 2
    if not args.settle_max_time > 0:
        print(f"--settle-max-time {args.settle_max_time}: expected seconds > 0", file=sys.stderr)
        return 2
    focus = tuple(c for c in args.focus_categories.split(",") if c)
    scenario = _load(args, seed=args.seed)
    summary = generate(out=args.out, num_scenes=args.scenes, split=args.split, seed=args.seed,
                       scenario=scenario,
                       config=GpdDataConfig(candidates_per_scene=args.candidates_per_scene,
                                            scene_kinds=kinds,
                                            settle_max_time_s=args.settle_max_time,
                                            focus_categories=focus),
                       workers=args.workers, objects_dir=args.objects)
    print(json.dumps({k: summary[k] for k in ("num_scenes", "candidates", "positives")}))
    return 0


def _cmd_gpd_train(args) -> int:
    from drake_grasp.learning.gpd_training import GpdTrainConfig, train

    metrics = train(data=args.data, test_data=args.test_data, out=args.out,
                    config=GpdTrainConfig(epochs=args.epochs, seed=args.seed,
                                          threads=args.threads))
    print(json.dumps(metrics["held_out"]))
    return 0


def _cmd_gpd_eval(args) -> int:
    from drake_grasp.learning.gpd_training import evaluate_classifier

    result = evaluate_classifier(weights=args.weights or "", data=args.data, threads=args.threads)
    if args.out:
        from drake_grasp.core.files import atomic_write_text

        atomic_write_text(args.out, json.dumps(result, indent=1))
    rows = [("all", result["held_out"])] + list(result["by_category"].items())
    print(f"{'category':18s} {'candidates':>10s} {'positives':>9s}  precision / recall "
          "at 0.5 | 0.9")
    for name, m in rows:
        a, b = m["0.5"], m["0.9"]
        print(f"{name:18s} {a['num']:10d} {a['positives']:9d}  {a['precision']:.3f} / "
              f"{a['recall']:.3f} | {b['precision']:.3f} / {b['recall']:.3f}")
    return 0


def _cmd_gpd_combine(args) -> int:
    from drake_grasp.policies.gpd import combine_classifiers
    from drake_grasp.core.provenance import file_sha256

    model = combine_classifiers(args.weights, args.out)
    print(f"{args.out}: mean of {len(model.members)} classifiers, sha256 {file_sha256(args.out)}")
    return 0


def _cmd_evaluate(args) -> int:
    from drake_grasp.evaluation.montecarlo import evaluate

    result = evaluate(experiment=args.experiment, out=args.out, trials=args.trials,
                      workers=args.workers, scheduler=args.scheduler, seed=args.seed,
                      objects_dir=args.objects,
                      conditions=[c for c in args.conditions.split(",") if c] or None,
                      force_new=args.force_new, physics_profile=args.physics_profile,
                      weights=args.weights or "", gpd_weights=args.gpd_weights or "",
                      mirror_average=args.mirror_average,
                      converge_iterations=-1 if args.converge is None else args.converge,
                      distance_samples=0 if args.distance_samples is None
                      else args.distance_samples, hand_check=args.hand_check,
                      ctr_text=args.ctr_text or "", failure_memory_m=args.failure_memory,
                      gpd_fallback=args.gpd_fallback)
    if result["new_folder_because"]:
        print(f"--force-new: {args.out} holds another run ({result['new_folder_because']}); "
              f"this run is in {result['out']}", file=sys.stderr)
    print(json.dumps({k: result[k] for k in ("out", "records", "ran", "skipped")}))
    print(f"report: {Path(result['out']) / 'report.md'}")
    return 0


def _cmd_report(args) -> int:
    from drake_grasp.evaluation.report import make_report

    make_report(args.results)
    print(Path(args.results) / "report.md")
    return 0


def _cmd_replay(args) -> int:
    from drake_grasp.evaluation.montecarlo import replay_trial

    from drake_grasp.evaluation.montecarlo import machine_note
    from drake_grasp.evaluation.records import RUN_INFO_FILE, read_run_info

    result, out = replay_trial(args.results, trial_id=args.trial, out=args.out)
    run_json = Path(args.results) / RUN_INFO_FILE
    note = machine_note(read_run_info(args.results)) if run_json.is_file() else None
    if note:
        print(f"drake-grasp replay: note: {note}", file=sys.stderr)
    print(json.dumps({"success": result.success, "failure_reason": result.failure_reason,
                      "out": str(out)}))
    return 0


def _cmd_grasp_check(args) -> int:
    from drake_grasp.evaluation.lab import run_grasp_checks
    from drake_grasp.objects import load_library

    scenario = _load(args)
    library = load_library(args.objects)
    object_ids = [i for item in args.object for i in item.split(",") if i]
    if not object_ids:
        raise ValueError("--object: give at least one object id")
    summary = run_grasp_checks(object_ids=object_ids, num_grasps=args.grasps, seed=args.seed,
                               out=args.out, scenario=scenario, library=library)
    print(json.dumps({k: summary[k] for k in ("checked", "held", "hold_rate", "failures")}))
    return 0


def _cmd_label_check(args) -> int:
    from drake_grasp.evaluation.labelcheck import LabelCheckConfig, run_label_check
    from drake_grasp.objects import load_library

    scenario = _load(args)
    library = load_library(args.objects)
    config = LabelCheckConfig(grasps_per_scene=args.grasps_per_scene,
                              rejected_per_scene=args.rejected_per_scene, split=args.split,
                              max_torque_ratio=args.max_torque_ratio)
    summary = run_label_check(num_scenes=args.scenes, seed=args.seed, out=args.out,
                              scenario=scenario, library=library, config=config,
                              workers=args.workers, objects_dir=args.objects or "")
    print(json.dumps({k: summary[k] for k in (
        "scenes", "checked", "held", "precision", "precision_ci95", "min_category_precision",
        "rejected_checked", "rejected_held", "failures")}))
    return 0


def _cmd_grasp_tolerance(args) -> int:
    from drake_grasp.objects import load_library
    from drake_grasp.evaluation.tolerance import run_grasp_tolerance

    offsets = [float(v) for v in args.offsets_mm.split(",") if v.strip()]
    summary = run_grasp_tolerance(num_scenes=args.scenes, seed=args.seed, out=args.out,
                                  scenario=_load(args), library=load_library(args.objects),
                                  offsets_mm=offsets, workers=args.workers,
                                  objects_dir=args.objects or "")
    print(json.dumps({k: summary[k] for k in ("scenes", "scenes_with_verified_grasp", "trials",
                                                "by_offset_mm")}))
    return 0


def _cmd_export_onnx(args) -> int:
    from drake_grasp.cnn.onnx_export import export_onnx

    try:
        result = export_onnx(out=args.out, weights=args.weights, exporter=args.exporter)
    except ImportError as e:  # onnx / onnxruntime / onnxscript not installed
        print(f"drake-grasp export-onnx: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({"out": str(result.path), "head": str(result.head_path),
                      "exporter": result.exporter,
                      "source_tensors_sha256": result.source_tensors_sha256,
                      "probe_max_abs_error_m": result.probe_max_abs_error_m}))
    return 0


def _cmd_scenarios(args) -> int:
    from drake_grasp.config.scenario import list_scenarios, scenario_file_path

    print(f"# {scenario_file_path(args.scenario_file)}")
    for name in list_scenarios(args.scenario_file):
        print(name)
    return 0


def _cmd_bridge(args) -> int:
    from drake_grasp.evaluation import bridge

    if args.bridge_command == "controller":
        bridge.run_controller(args.port, host=args.host, timeout_s=args.timeout)
        return 0
    overrides = {}
    if args.policy is not None:
        overrides["policy"] = args.policy
    if args.seed is not None:
        overrides["seed"] = args.seed
    scenario = _load(args, **overrides)
    run = bridge.simulate_split_episode(
        scenario, scenario_name=args.scenario, timeout_s=args.timeout,
        port=args.port if args.bridge_command == "station" else 0,
        spawn_controller=args.bridge_command == "episode")
    text = run.result.to_json()
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    print(text)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="drake-grasp",
        description="Closed-loop visuomotor grasping (Viereck et al., CoRL 2017) as a Drake diagram.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="run one grasp episode and write episode.json, "
                                    "replay.html and depth.png")
    _add_scenario_flags(p)
    p.add_argument("--policy", default=None, type=_policy_arg,
                   metavar="{ctr,gpd,gpd-geometric,cnn-only,cnn-ctr,init,scripted,MODULE:FACTORY}",
                   help="ctr: the paper's closed-loop controller (shipped CNN); gpd: the "
                        "paper's baseline: learned GPD on one image from the Structure-IO-like "
                        "sensor at a fixed viewpoint, a 6-DOF grasp executed open loop; "
                        "gpd-geometric: the older hand-tuned geometric score on the 64x64 "
                        "wrist image at the start, top-down, open loop; cnn-only: the CNN's "
                        "global best action, open loop; cnn-ctr: cnn-only then ctr; init: no "
                        "motion; scripted: grasp from above using the true object pose; "
                        "MODULE:FACTORY: your own policy, FACTORY(scenario) -> LeafSystem "
                        "from a module on sys.path or MODULE.py in the current folder "
                        "(README 'Bring your own policy'; e.g. centroid_policy:make_policy "
                        "from examples/) (default: the scenario's policy)")
    p.add_argument("--noise", default=None, choices=["none", "gaussian", "offset"],
                   help="kinematic noise on commanded displacements (default: the scenario's)")
    p.add_argument("--target", default=None, metavar="OBJECT_ID",
                   help="grasp this object: candidates restricted to its image region")
    p.add_argument("--weights", default=None,
                   help="CNN weights file (default: models/cnn-grid-bn12500-ep3/, the "
                   "grid head trained with BatchNorm, last on the paper's 12,500 scenes; "
                   "models/cnn-grid-bn12500/, models/cnn-grid-bn12-ep5/, "
                   "models/cnn-grid-bn12/, models/cnn-grid-bn/ and models/cnn-grid/ are the "
                   "grid heads before it, models/cnn/ the paper's "
                   "net, each weights.safetensors); FILE,FILE,... "
                   "scores with the mean of several nets (an ensemble)")
    p.add_argument("--seed", type=int, default=None,
                   help="trial seed (scene and noise); default: the scenario's seed")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--no-replay", action="store_true",
                   help="skip the Meshcat replay page (faster)")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("diagram", help="write the station Diagram as Graphviz (SVG if 'dot' is "
                                       "installed, else .dot)")
    _add_scenario_flags(p)
    p.add_argument("--out", required=True, help="output file (.svg, .png or .dot)")
    p.add_argument("--depth", type=int, default=2,
                   help="how many levels of nested diagrams to expand (default 2: the "
                        "episode and the station inside it)")
    p.set_defaults(func=_cmd_diagram)

    p = sub.add_parser("bench", help="run the benchmarks and print one JSON object")
    p.add_argument("--only", default="",
                   help="comma-separated benchmark groups (rtf_isolation, rtf_clutter5, "
                        "depth_frame_ms, labels_per_s, cnn, cnn_onnx, controller_step_ms, "
                        "rtf_ctr_clutter5, trials_per_hour) or any key that bench prints "
                        "(e.g. cnn_infer_ms_128, train_samples_per_s): a key runs its group "
                        "and prints only that key (default: everything)")
    p.add_argument("--out", default=None, help="also write the JSON (with the machine) here")
    p.set_defaults(func=_cmd_bench)

    p = sub.add_parser("generate", help="generate the simulated training set (HDF5 shards + "
                                         "manifest.json); re-running resumes")
    _add_scenario_flags(p, default="random")
    p.add_argument("--scenes", type=int, required=True,
                   help="number of labelled scenes, exactly: a scene that does not settle "
                        "or has no true grasp is replaced by the next seed reserved for it "
                        "(counted in manifest.json); re-running with a larger N extends the "
                        "dataset. One generator per folder: a second one is refused")
    p.add_argument("--split", required=True, choices=["train", "test"],
                   help="object instances to use (the split is by instance)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the tasks on this Dask distributed scheduler instead")
    p.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
    p.add_argument("--out", required=True, help="dataset folder")
    p.add_argument("--images-per-scene", type=int, default=40,
                   help="camera poses per scene (paper: 40)")
    _add_torque_ratio_flag(p)
    from drake_grasp.learning.dataset import SCENE_KINDS, DatasetConfig

    p.add_argument("--grasp-samples", type=_positive_int, default=DatasetConfig().grasp_samples,
                   metavar="N",
                   help="surface points of the ground-truth grasp search per scene (default "
                        f"{DatasetConfig().grasp_samples}, ~0.12 s; more gives less noisy labels "
                        "at proportional cost: README *How exact the labels are*)")
    p.add_argument("--near-grasp-fraction", type=float, default=0.0, metavar="F",
                   help="draw this fraction of each scene's hand poses near a true grasp "
                        "(within the controller's candidate range: 4 cm, 45 degrees) instead "
                        "of at random (default 0, the paper's random poses; README *Views "
                        "near a grasp*)")
    p.add_argument("--scene-kind", choices=list(SCENE_KINDS), default="random",
                   help="random: the paper's scenes, 1-5 objects spread out (default); "
                        "clutter: the scenario's scene.clutter_objects poured into a pile "
                        "as in the clutter experiments (set them with --scenario-text, e.g. "
                        "'{scene: {clutter_objects: 10, region_half_extent_m: 0.06}}'; "
                        "README *Training on piles*)")
    p.add_argument("--settle-max-time", type=float, default=DatasetConfig().settle_max_time_s,
                   metavar="S",
                   help="simulated seconds a scene may take to come to rest before the next "
                        f"seed reserved for it is drawn (default {DatasetConfig().settle_max_time_s};"
                        " 10-object pours need about 6)")
    p.add_argument("--offsets-per-image", type=int, default=10,
                   help="labelled offsets per image (paper: 10)")
    p.add_argument("--scenes-per-shard", type=int, default=4,
                   help="scenes per shard file, i.e. per worker task (default 4); the "
                        "last shard holds the rest")
    p.set_defaults(func=_cmd_generate)

    p = sub.add_parser("inspect-data", help="picture of a dataset: depth images with true "
                                            "grasps and labelled offsets, label histogram")
    p.add_argument("data", help="dataset folder")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--images", type=int, default=12, help="images to draw (default 12)")
    p.add_argument("--seed", type=int, default=0, help="which images (default 0)")
    p.set_defaults(func=_cmd_inspect_data)

    p = sub.add_parser("train", help="train the distance CNN (L1 loss); re-running resumes")
    p.add_argument("--data", required=True,
                   help="train-split dataset folder, or a folder holding train/ and test/")
    p.add_argument("--test-data", default=None,
                   help="test-split dataset folder (held-out object instances)")
    p.add_argument("--out", required=True, help="output folder (checkpoints, metrics, weights)")
    p.add_argument("--epochs", type=int, default=10, help="epochs (default 10)")
    p.add_argument("--recipe", choices=["fast", "paper"], default="fast",
                   help="fast (default): Adam, lr 0.0001 decaying x0.8 per epoch; paper: SGD "
                        "lr 0.001, momentum 0.9, constant. The flags below override it")
    p.add_argument("--optimizer", choices=["sgd", "adam"], default=None,
                   help="optimizer (default: the recipe's)")
    p.add_argument("--batch", type=int, default=None,
                   help="instances (image, offset, label) per batch (both recipes and the "
                        "paper: 1000)")
    p.add_argument("--lr", type=float, default=None,
                   help="learning rate of the first epoch (fast: 0.0001, paper: 0.001)")
    p.add_argument("--lr-decay", type=float, default=None,
                   help="learning-rate factor per epoch, in (0, 1] (fast: 0.8, paper: 1)")
    p.add_argument("--momentum", type=float, default=None,
                   help="SGD momentum (paper: 0.9); Adam ignores it")
    p.add_argument("--checkpoint-minutes", type=float, default=None,
                   help="checkpoint at least this often within an epoch (default 5); a "
                        "killed run resumes from it with the batches still to come. May "
                        "differ when resuming")
    p.add_argument("--ranking-images", type=int, default=None,
                   help="held-out images for the within-image rank correlation after each "
                        "epoch (default 200; 0: none)")
    p.add_argument("--seed", type=int, default=0, help="initial weights and shuffling seed")
    p.add_argument("--device", default="auto",
                   help="auto (GPU when present), cpu or cuda; may differ when resuming "
                        "(a run started on a CPU continues on a GPU and back)")
    p.add_argument("--threads", type=int, default=0,
                   help="CPU threads (0: torch default); may differ when resuming")
    p.add_argument("--max-memory-gb", type=float, default=8.0,
                   help="most memory the data loader may hold, in GB (default 8): cached "
                        "HDF5 chunks of both sets plus the batch being assembled; larger "
                        "datasets stream from the shards (slower epochs, the same batches). "
                        "Too small for one batch is an error. May differ when resuming")
    p.add_argument("--init-weights", default=None, metavar="FILE",
                   help="start from these weights (e.g. the shipped "
                        "models/cnn/weights.safetensors) instead of a fresh initialization, "
                        "with a fresh optimizer; their tensors' sha256 is part of the run's "
                        "identity")
    p.add_argument("--loss", choices=("l1", "log-l1"), default=None,
                   help="training loss: l1 (default, the paper's) or log-l1, the L1 of "
                        "log(distance + c), whose weight falls as 1/(distance + c): errors "
                        "near a grasp cost more than far ones (README *Near-weighted loss*)")
    p.add_argument("--loss-offset", type=float, default=None, metavar="M",
                   help="c of --loss log-l1, in metres (default 0.01)")
    p.add_argument("--action-fusion", choices=("tiled", "window"), default="tiled",
                   help="how the candidate action enters the net: tiled (default, the "
                        "paper's: IP(a) added to every Pool1 cell) or window (the net reads "
                        "its Conv2 features in a 12 cm window placed and turned where the "
                        "candidate grasp would be; README *Window fusion*)")
    p.add_argument("--context-side", type=float, default=0.0, metavar="M",
                   help="with --action-fusion window: side in metres of a second, coarser "
                        "window around the candidate (as many samples as the 12 cm one), "
                        "so the net sees what lies beyond it; 0 (default): none")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("dense-labels", help="label every node of the grid head's action grid "
                       "on every image of a dataset (for train-grid); re-running skips the "
                       "shards already done")
    p.add_argument("--data", required=True, help="dataset folder (generate --out)")
    p.add_argument("--out", required=True, help="folder for the labels (one .npz per shard)")
    p.add_argument("--workers", type=_positive_int, default=2, help="worker processes (default 2)")
    p.set_defaults(func=_cmd_dense_labels)

    p = sub.add_parser("train-grid", help="train the grid-head distance CNN on dense labels "
                       "(L1 over every in-view grid node); re-running resumes")
    p.add_argument("--labels", required=True,
                   help="dense-labels folders, comma-separated (the same grid)")
    p.add_argument("--out", required=True, help="run folder: epochN.safetensors, metrics.json, "
                   "checkpoint.pt")
    p.add_argument("--test-data", default=None, help="dataset folder for the test L1 and "
                   "ranking metrics after every epoch (e.g. a generate --split test folder)")
    p.add_argument("--init-weights", default=None, metavar="FILE",
                   help="start from these weights: a paper (tiled) net's Conv1, Conv2 and "
                        "IP1 with its distance for staying put on every node, or a grid net")
    p.add_argument("--epochs", type=_positive_int, default=3)
    p.add_argument("--batch", type=_positive_int, default=50, help="images per batch")
    p.add_argument("--lr", type=_positive_float, default=2e-4, help="Adam's learning rate")
    p.add_argument("--lr-decay", type=_positive_float, default=0.7,
                   help="learning-rate factor after every epoch")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=_positive_int, default=2)
    p.add_argument("--checkpoint-minutes", type=_positive_float, default=5.0)
    p.add_argument("--trunk", type=_trunk_widths, default=None, metavar="C1,C2,H",
                   help="Conv1 filters, Conv2 filters and IP1 width (default: the paper's "
                        "20,50,500), e.g. 40,100,1000 for a wider net; --init-weights must "
                        "then have the same trunk")
    p.add_argument("--batch-norm", action="store_true",
                   help="train with a BatchNorm after Conv1, Conv2 and IP1 (folded into "
                        "them in the weights written: a plain grid net); from "
                        "--init-weights they start as the identity")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                   help="where the batches run: auto (a GPU when torch sees one), cpu or "
                        "cuda; may differ when resuming")
    p.add_argument("--stream-shards", type=_positive_int, default=None, metavar="G",
                   help="keep the labels on disk and hold only groups of G label parts at "
                        "a time (an epoch permutes the parts, then the images within each "
                        "group): for label sets larger than memory (300,000 images take "
                        "14 GB in memory); default: every label in memory")
    p.add_argument("--augment", default="none", choices=("none", "mirror", "d4"),
                   help="train on each image (and its labels) under a random symmetry of "
                        "the wrist camera: mirror (flipped left-right or not) or d4 (also "
                        "turned 0, 90, 180 or 270 degrees about the optical axis); "
                        "default none")
    p.add_argument("--rank-weight", type=_non_negative_float, default=0.0, metavar="W",
                   help="add W times a pairwise ranking loss to the L1: 1,024 pairs of "
                        "nearby grid nodes per image (within 4 cm and 40 degrees), the "
                        "logistic loss of ordering each pair as its labels do "
                        "(dense_training.pairwise_rank_loss); default 0 (L1 only)")
    p.add_argument("--rank-scale-m", type=_positive_float, default=0.01, metavar="S",
                   help="with --rank-weight: the distance difference [m] the logistic "
                        "loss counts as one unit (default 0.01)")
    p.set_defaults(func=_cmd_train_grid)

    p = sub.add_parser("checkpoint-weights", help="write the weights of a training run's "
                       "latest checkpoint (an unfinished run) as a weights file for the "
                       "controller; the run may go on")
    p.add_argument("run", help="the run's output folder (train --out or train-grid --out)")
    p.add_argument("--out", required=True, help="weights file to write (*.safetensors)")
    p.set_defaults(func=_cmd_checkpoint_weights)

    p = sub.add_parser("gpd-generate", help="training data of the GPD baseline's grasp "
                                             "classifier (labelled candidates and grasp "
                                             "images in .npz shards); re-running resumes")
    _add_scenario_flags(p, default="random")
    p.add_argument("--scenes", type=int, required=True,
                   help="number of scenes (isolation, random and clutter in turn)")
    p.add_argument("--split", required=True, choices=["train", "test"],
                   help="object instances to use (test: held-out instances)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    p.add_argument("--seed", type=int, default=0, help="data seed (default 0)")
    p.add_argument("--out", required=True, help="data folder")
    p.add_argument("--candidates-per-scene", type=int, default=600,
                   help="labelled candidates kept per scene: positives up to a quarter, "
                        "negatives fill up (default 600)")
    p.add_argument("--focus-categories", default="", metavar="A,B",
                   help="object categories every scene holds one instance of (e.g. "
                        "hammer,flashlight: more data where the classifier is weakest, see "
                        "gpd-eval); default: objects drawn as the experiments draw them")
    p.add_argument("--scene-kinds", default="isolation,random,clutter",
                   help="scene kinds drawn in turn (default isolation,random,clutter); "
                        "'clutter' piles have the scenario's scene.clutter_objects objects")
    p.add_argument("--settle-max-time", type=float, default=2.0, metavar="S",
                   help="simulated seconds a scene may take to come to rest before another "
                        "seed is drawn (default 2.0; 10-object pours can need the "
                        "experiments' 4)")
    p.set_defaults(func=_cmd_gpd_generate)

    p = sub.add_parser("gpd-train", help="train the GPD baseline's grasp classifier (Adam, "
                                          "class-weighted cross-entropy); re-running resumes")
    p.add_argument("--data", required=True, help="gpd-generate folder of the train split, or "
                                                  "several, comma-separated (concatenated)")
    p.add_argument("--test-data", required=True,
                   help="gpd-generate folder of the test split (held-out object instances)")
    p.add_argument("--out", required=True,
                   help="output folder (checkpoint.pt, metrics.json, weights.safetensors)")
    p.add_argument("--epochs", type=int, default=12, help="epochs (default 12)")
    p.add_argument("--seed", type=int, default=0, help="initial weights and shuffling seed")
    p.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    p.set_defaults(func=_cmd_gpd_train)

    p = sub.add_parser("gpd-eval", help="held-out precision and recall of a GPD classifier, "
                                         "over all candidates and per object category")
    p.add_argument("--data", required=True, help="gpd-generate folder(s) to score, "
                                                  "comma-separated (e.g. a test split)")
    p.add_argument("--weights", default="", help="classifier weights (a gpd-train "
                                                  "weights.safetensors); default: the shipped one")
    p.add_argument("--out", default="", help="also write the metrics as JSON to this file")
    p.add_argument("--threads", type=int, default=2, help="CPU threads (default 2)")
    p.set_defaults(func=_cmd_gpd_eval)

    p = sub.add_parser("gpd-combine", help="one GPD weights file whose probabilities are the "
                                            "mean of several classifiers' (an ensemble)")
    p.add_argument("weights", nargs="+", help="classifier weights files (gpd-train "
                                               "weights.safetensors), at least 2")
    p.add_argument("--out", required=True, help="the ensemble's safetensors file")
    p.set_defaults(func=_cmd_gpd_combine)

    p = sub.add_parser("evaluate", help="run one of the paper's experiments (Monte Carlo) and "
                                         "write its report; re-running resumes")
    p.add_argument("--experiment", required=True,
                   help="smoke, sim-distance, perception, isolation, clutter, clutter-shift, "
                        "sweep-noise, sweep-depth-noise, sweep-offset, sweep-latency, "
                        "sweep-control-period, sweep-dropped-frames, "
                        "sweep-camera-translation or sweep-camera-rotation")
    p.add_argument("--trials", type=int, default=None,
                   help="trials per condition (clutter: runs); default: the experiment's. "
                        "The report written covers trials 0..N-1 of the conditions asked, "
                        "also when the folder holds more")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the trials on this Dask distributed scheduler instead")
    p.add_argument("--seed", type=int, default=0, help="base seed of the trials (default 0)")
    p.add_argument("--out", required=True,
                   help="results folder; re-running into it resumes the same run (finished "
                        "trials are skipped)")
    p.add_argument("--objects", default=None, metavar="DIR",
                   help="object library folder (default: built-in objects)")
    p.add_argument("--conditions", default="",
                   help="comma-separated subset of the experiment's conditions (default: "
                        "all); an entry MODULE:FACTORY adds your own policy as a condition "
                        "on the same seeds, e.g. ctr,centroid_policy:make_policy; a built-in "
                        "policy the experiment does not list (ctr, cnn-ctr, cnn-only, gpd, "
                        "gpd-geometric, init) is added the same way, e.g. clutter's cnn-ctr")
    p.add_argument("--force-new", action="store_true",
                   help="when --out holds a different run (another experiment, seed, object "
                        "library, resolved scenario, CNN or GPD weights or code version: "
                        "without "
                        "this flag that is an error naming the first difference), run in a "
                        "new folder next to it instead: the first of OUT-2, OUT-3, ... that "
                        "does not exist or already holds this same run (printed)")
    p.add_argument("--physics-profile", default="", metavar="NAME",
                   help="contact-simulation settings of every trial: 'fast' (the default "
                        "profile: 5 ms steps, ...), 'fast10' (10 ms steps with Drake's "
                        "'similar' approximation: the grasp lab 1.8x faster, episodes 1.27x; "
                        "README *Physics profiles*) or 'reference' (2 ms, the settings of "
                        "results measured before the fast profile); default: the scenarios'")
    p.add_argument("--weights", default=None, metavar="FILE",
                   help="distance-CNN weights (safetensors or ONNX) for the conditions that "
                        "use the CNN (ctr, cnn-only, cnn-ctr); default: the shipped grid head "
                        "models/cnn-grid-bn12500-ep3/weights.safetensors (the grid heads "
                        "before it: models/cnn-grid-bn12500/, models/cnn-grid-bn12-ep5/, "
                        "models/cnn-grid-bn12/, models/cnn-grid-bn/ and models/cnn-grid/; "
                        "the paper's net: "
                        "models/cnn/; each weights.safetensors); FILE,FILE,... scores with the "
                        "mean of several nets (an ensemble). Its sha256 is part of the run's "
                        "identity")
    p.add_argument("--gpd-weights", default=None, metavar="FILE",
                   help="GPD grasp-classifier weights (safetensors from 'drake-grasp "
                        "gpd-train') for the gpd conditions; default: the shipped "
                        "models/gpd/weights.safetensors. Its sha256 is part of the run's "
                        "identity")
    p.add_argument("--mirror-average", action="store_true",
                   help="the CNN conditions score every candidate as the mean over the "
                        "wrist image and its mirror image (controller.mirror_average)")
    p.add_argument("--converge", type=int, default=None, metavar="N",
                   help="the closed-loop conditions (ctr, cnn-ctr) keep servoing for up to "
                        "N iterations at the height where the stop rule fired, until the "
                        "commanded move stays below controller.converge_step_m "
                        "(controller.converge_iterations; default: the scenarios', 20; 0 grasps as "
                        "soon as the stop rule fires, as the paper's robot did)")
    p.add_argument("--distance-samples", type=int, default=None, metavar="N",
                   help="measure every trial's final distance (the paper's metric) against a "
                        "ground-truth search of N surface points (judge.distance_grasp_samples; "
                        "default: the scenarios', 400, the dataset's labels' search)")
    p.add_argument("--hand-check", action="store_true",
                   help="the closed-loop conditions (ctr, cnn-ctr), while servoing at the stop "
                        "height, follow the best-scored candidate whose open hand (fingers, palm, "
                        "housing) comes down clear of the surfaces the depth image shows under it "
                        "(controller.hand_check; not in the paper)")
    p.add_argument("--ctr-text", default="", metavar="YAML",
                   help="controller settings for the closed-loop conditions (ctr, cnn-ctr), "
                        "a YAML mapping of controller.* keys applied after the experiment's "
                        "(e.g. '{stop_distance_m: 0.2, end_camera_height_m: 0.21}'); part of "
                        "the run's identity")
    p.add_argument("--failure-memory", type=float, default=0.0, metavar="M",
                   help="in clutter runs every policy avoids, within M metres of the grasp "
                        "metric, the grasps of its earlier attempts of the run that held "
                        "nothing (failure_memory.radius_m; not in the paper; default off)")
    p.add_argument("--gpd-fallback", action=argparse.BooleanOptionalAction, default=None,
                   help="the gpd conditions take their best-ranked candidate when none "
                        "reaches the classifier's threshold (gpd.fallback_best; the "
                        "scenario's default: on); --no-gpd-fallback: GPD detects nothing "
                        "then and closes on nothing, as in the records before 2026-11-28")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("report", help="(re)write summary.json and report.md of a results folder")
    p.add_argument("results", help="results folder of 'drake-grasp evaluate'")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("replay", help="re-run one recorded trial exactly, with its replay page")
    p.add_argument("results", help="results folder")
    p.add_argument("--trial", required=True, help="trial id, e.g. isolation/ctr/0003")
    p.add_argument("--out", default=None, help="output folder (default: RESULTS/replays/<id>)")
    p.set_defaults(func=_cmd_replay)

    p = sub.add_parser("grasp-check", help="execute sampled ground-truth grasps in the grasp "
                       "physics lab (floating 2F-85, one object) and write summary.json")
    _add_scenario_flags(p)
    p.add_argument("--object", action="append", required=True, metavar="ID",
                   help="object id; repeat the flag or give a comma-separated list")
    p.add_argument("--grasps", type=int, default=10,
                   help="ground-truth grasps sampled per object (default: 10)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the objects' drop rotations and the grasp sampling (default: 0)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for summary.json")
    p.set_defaults(func=_cmd_grasp_check)

    p = sub.add_parser("label-check", help="execute the dataset's ground-truth grasps (and "
                       "rejected candidates) of sampled scenes in the grasp physics lab, with "
                       "the neighbours present -> summary.json (precision), report.md")
    _add_scenario_flags(p)
    p.add_argument("--scenes", type=int, required=True,
                   help="scenes sampled and labelled as `generate` does (1-5 objects)")
    p.add_argument("--seed", type=int, required=True, help="seed of the scenes and the picks")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="folder for run.json, scenes/*.json, summary.json, report.md; "
                   "re-running the same command resumes")
    p.add_argument("--grasps-per-scene", type=int, default=3,
                   help="ground-truth grasps executed per scene (default: 3)")
    p.add_argument("--rejected-per-scene", type=int, default=1,
                   help="rejected candidates executed per scene (default: 1)")
    p.add_argument("--split", choices=("train", "test"), default="train",
                   help="object split of the scenes (default: train)")
    _add_torque_ratio_flag(p)
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default: 1)")
    p.set_defaults(func=_cmd_label_check)

    p = sub.add_parser("grasp-tolerance", help="physical success vs the paper's distance "
                       "metric: lab-verified grasps of isolation scenes executed again "
                       "displaced by known (x, y, theta) offsets -> summary.json, "
                       "tolerance.png, report.md")
    _add_scenario_flags(p)
    p.add_argument("--scenes", type=int, required=True, help="isolation scenes (test objects)")
    p.add_argument("--seed", type=int, required=True, help="seed of the scenes and offsets")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="results folder; re-running the same command resumes")
    p.add_argument("--offsets-mm", default=",".join(f"{v:g}" for v in (0, 5, 10, 15, 20, 30, 40)),
                   help="offset lengths in the paper's metric [mm, 1 mm = 1 degree], "
                   "comma-separated (default: 0,5,10,15,20,30,40)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default: 1)")
    p.set_defaults(func=_cmd_grasp_tolerance)

    p = sub.add_parser("export-onnx", help="write the distance CNN as ONNX for onnxruntime: "
                       "FILE (image part, with the metadata) and FILE's .head.onnx sibling "
                       "(per-action head); 'controller.weights: FILE' then runs it without torch")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="the image part, ending in .onnx; the head goes to the same name with "
                        ".head.onnx (X.onnx -> X.head.onnx); both are replaced if present")
    p.add_argument("--weights", default="", metavar="W",
                   help="safetensors weights to export, a tiled (paper) net (default: the "
                        "shipped paper net models/cnn/weights.safetensors; the grid head, "
                        "the episodes' default, has no ONNX export)")
    p.add_argument("--exporter", default="auto", choices=["auto", "dynamo", "torchscript"],
                   help="torch.onnx.export path: dynamo (needs onnxscript) or torchscript "
                        "(dynamo=False); auto (default): dynamo when onnxscript is installed")
    p.set_defaults(func=_cmd_export_onnx)

    p = sub.add_parser("scenarios", help="list the named scenarios of a scenarios file")
    p.add_argument("--scenario-file", default=None, help="a *.scenarios.yaml file")
    p.set_defaults(func=_cmd_scenarios)

    pb = sub.add_parser("bridge", help="the controller and the simulated station in two "
                                       "processes, talking robot-driver LCM messages over TCP "
                                       "on 127.0.0.1 (README: Across a process boundary)")
    bsub = pb.add_subparsers(dest="bridge_command", required=True)
    for name, text in (("episode", "run one episode: the station here, the controller in a "
                                   "process it starts; prints episode.json"),
                       ("station", "run the station side of one episode and wait for a "
                                   "controller started by hand ('bridge controller')")):
        p = bsub.add_parser(name, help=text)
        _add_scenario_flags(p)
        p.add_argument("--policy", default=None, choices=["ctr", "cnn-ctr", "cnn-only", "gpd",
                                                          "gpd-geometric", "init"],
                       help="the controller policy (default: the scenario's)")
        p.add_argument("--seed", type=int, default=None, help="trial seed (default: the scenario's)")
        p.add_argument("--out", default=None, metavar="FILE",
                       help="also write the episode's JSON (episode.json's content) here")
        p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                       help="seconds to wait for the controller to connect and for each of "
                            "its replies before giving up (default: 60)")
        if name == "station":
            p.add_argument("--port", type=int, default=0,
                           help="TCP port on 127.0.0.1 to listen on (default 0: the OS "
                                "chooses; the port is printed on stderr)")
        p.set_defaults(func=_cmd_bridge)
    p = bsub.add_parser("controller", help="the controller side: connect to a station, take "
                                           "its task (scenario, start pose, camera extrinsics) "
                                           "and run the policy and the arm's IK until it ends")
    p.add_argument("--port", type=int, required=True, help="the station's TCP port")
    p.add_argument("--host", default="127.0.0.1",
                   help="the station's address (default: 127.0.0.1, the loopback)")
    p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="seconds to keep trying to connect, and to wait for each message of "
                        "the station (default: 60)")
    p.set_defaults(func=_cmd_bridge)

    po = sub.add_parser("objects", help="object libraries")
    osub = po.add_subparsers(dest="objects_command", required=True)
    p = osub.add_parser("import", help="bring an OBJ/STL/PLY/glTF mesh into an object library")
    p.add_argument("mesh", help="mesh file")
    p.add_argument("--name", required=True, help="object id (letters, digits, _ and -)")
    p.add_argument("--library", required=True, help="library folder (created if missing)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="multiply coordinates by this (e.g. 0.001 for millimetres)")
    p.add_argument("--density", type=float, default=500.0, help="density in kg/m^3")
    p.add_argument("--overwrite", action="store_true", help="replace an object of that name")
    p.set_defaults(func=_cmd_objects_import)
    p = osub.add_parser("list", help="list object ids")
    p.add_argument("--objects", default=None, help="library folder (default: built-in)")
    p.add_argument("--split", default="", choices=["", "train", "test"], help="only this split")
    p.set_defaults(func=_cmd_objects_list)
    return parser


def _log_to_stderr() -> None:
    """The package's informational messages (e.g. "replaced the earlier episode") go to
    stderr, prefixed like the CLI's errors; other libraries' logging is left alone."""
    import logging

    log = logging.getLogger("drake_grasp")
    for h in [h for h in log.handlers if getattr(h, "_drake_grasp_cli", False)]:
        log.removeHandler(h)  # an earlier main() in this process; sys.stderr may differ now
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("drake-grasp: %(message)s"))
    handler._drake_grasp_cli = True
    log.addHandler(handler)
    log.setLevel(logging.INFO)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _log_to_stderr()
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError, KeyError) as e:  # OSError: a file exists, a full disk, ...
        print(f"drake-grasp {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
