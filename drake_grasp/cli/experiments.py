"""`drake-grasp` commands: the paper's experiments: Monte Carlo runs, reports, replays (evaluate, report, replay)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _cmd_evaluate(args) -> int:
    from drake_grasp.evaluation.experiments import ScenarioPatch, option_patches
    from drake_grasp.evaluation.montecarlo import evaluate

    patches = option_patches(
        weights=args.weights or "", gpd_weights=args.gpd_weights or "",
        mirror_average=args.mirror_average,
        converge_iterations=-1 if args.converge is None else args.converge,
        distance_samples=0 if args.distance_samples is None else args.distance_samples,
        hand_check=args.hand_check, ctr_text=args.ctr_text or "",
        failure_memory_m=args.failure_memory, gpd_fallback=args.gpd_fallback)
    for given in args.patch or []:
        group, _, text = given.partition("=")
        patches += (ScenarioPatch(group.strip(), text, source=f"--patch {given!r}"),)
    result = evaluate(experiment=args.experiment, out=args.out, trials=args.trials,
                      workers=args.workers, scheduler=args.scheduler, seed=args.seed,
                      objects_dir=args.objects,
                      conditions=[c for c in args.conditions.split(",") if c] or None,
                      force_new=args.force_new, physics_profile=args.physics_profile,
                      patches=patches)
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
    from drake_grasp.evaluation.replay import replay_trial

    from drake_grasp.evaluation.replay import machine_note
    from drake_grasp.evaluation.records import RUN_INFO_FILE, read_run_info

    result, out = replay_trial(args.results, trial_id=args.trial, out=args.out)
    run_json = Path(args.results) / RUN_INFO_FILE
    note = machine_note(read_run_info(args.results)) if run_json.is_file() else None
    if note:
        print(f"drake-grasp replay: note: {note}", file=sys.stderr)
    print(json.dumps({"success": result.success, "failure_reason": result.failure_reason,
                      "out": str(out)}))
    return 0


def _parser_evaluate(sub) -> None:
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
                        "models/cnn-grid-bn12500-ep3-fp16/weights.safetensors (stored in "
                        "float16; in float32: models/cnn-grid-bn12500-ep3/; the grid heads "
                        "before it: models/cnn-grid-bn12500/, models/cnn-grid-bn12-ep5/, "
                        "models/cnn-grid-bn12/, models/cnn-grid-bn/ and models/cnn-grid/; "
                        "the paper's net: "
                        "models/cnn/; each weights.safetensors, in the repository's models/ "
                        "only, not installed with the package); FILE,FILE,... scores with the "
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
    p.add_argument("--patch", action="append", metavar="GROUP=YAML",
                   help="scenario settings for one group of conditions: GROUP is all, cnn "
                        "(ctr, cnn-only, cnn-ctr), closed-loop (ctr, cnn-ctr) or gpd; YAML a "
                        "mapping of scenario keys, e.g. "
                        "'closed-loop={controller: {stop_distance_m: 0.2}}'; repeatable, applied "
                        "in order after the other options (which are patches too); part of "
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


def _parser_report(sub) -> None:
    p = sub.add_parser("report", help="(re)write summary.json and report.md of a results folder")
    p.add_argument("results", help="results folder of 'drake-grasp evaluate'")
    p.set_defaults(func=_cmd_report)


def _parser_replay(sub) -> None:
    p = sub.add_parser("replay", help="re-run one recorded trial exactly, with its replay page")
    p.add_argument("results", help="results folder")
    p.add_argument("--trial", required=True, help="trial id, e.g. isolation/ctr/0003")
    p.add_argument("--out", default=None, help="output folder (default: RESULTS/replays/<id>)")
    p.set_defaults(func=_cmd_replay)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    _parser_evaluate(sub)
    _parser_report(sub)
    _parser_replay(sub)
