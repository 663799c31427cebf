"""`drake-grasp` commands: the grasp physics lab: grasp checks, label checks, tolerance (grasp-check, label-check, grasp-tolerance)."""

from __future__ import annotations

import json

from drake_grasp.cli.args import (add_scenario_flags, load_scenario_from_args, add_torque_ratio_flag,
                                  add_initial_pose_flag)


def _cmd_grasp_check(args) -> int:
    from drake_grasp.evaluation.lab import run_grasp_checks
    from drake_grasp.objects import load_library

    scenario = load_scenario_from_args(args)
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

    scenario = load_scenario_from_args(args)
    library = load_library(args.objects)
    config = LabelCheckConfig(grasps_per_scene=args.grasps_per_scene,
                              rejected_per_scene=args.rejected_per_scene, split=args.split,
                              max_torque_ratio=args.max_torque_ratio,
                              initial_pose=args.initial_pose)
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
                                  scenario=load_scenario_from_args(args), library=load_library(args.objects),
                                  offsets_mm=offsets, workers=args.workers,
                                  objects_dir=args.objects or "")
    print(json.dumps({k: summary[k] for k in ("scenes", "scenes_with_verified_grasp", "trials",
                                                "by_offset_mm")}))
    return 0


def _parser_grasp_check(sub) -> None:
    p = sub.add_parser("grasp-check", help="execute sampled ground-truth grasps in the grasp "
                       "physics lab (floating 2F-85, one object) and write summary.json")
    add_scenario_flags(p)
    p.add_argument("--object", action="append", required=True, metavar="ID",
                   help="object id; repeat the flag or give a comma-separated list")
    p.add_argument("--grasps", type=int, default=10,
                   help="ground-truth grasps sampled per object (default: 10)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the objects' drop rotations and the grasp sampling (default: 0)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for summary.json")
    p.set_defaults(func=_cmd_grasp_check)


def _parser_label_check(sub) -> None:
    p = sub.add_parser("label-check", help="execute the dataset's ground-truth grasps (and "
                       "rejected candidates) of sampled scenes in the grasp physics lab, with "
                       "the neighbours present -> summary.json (precision), report.md")
    add_scenario_flags(p)
    p.add_argument("--scenes", type=int, required=True,
                   help="scenes sampled and labelled as `generate` does (1-5 objects)")
    p.add_argument("--seed", type=int, required=True, help="seed of the scenes and the picks")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="folder for run.json, the scene records (scenes/*.json while it "
                   "runs, scenes.parquet when done), summary.json, report.md; re-running "
                   "the same command resumes")
    p.add_argument("--grasps-per-scene", type=int, default=3,
                   help="ground-truth grasps executed per scene (default: 3)")
    p.add_argument("--rejected-per-scene", type=int, default=1,
                   help="rejected candidates executed per scene (default: 1)")
    p.add_argument("--split", choices=("train", "test"), default="train",
                   help="object split of the scenes (default: train)")
    add_torque_ratio_flag(p)
    add_initial_pose_flag(p)
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default: 1)")
    p.set_defaults(func=_cmd_label_check)


def _parser_grasp_tolerance(sub) -> None:
    p = sub.add_parser("grasp-tolerance", help="physical success vs the paper's distance "
                       "metric: lab-verified grasps of isolation scenes executed again "
                       "displaced by known (x, y, theta) offsets -> summary.json, "
                       "tolerance.png, report.md")
    add_scenario_flags(p)
    p.add_argument("--scenes", type=int, required=True, help="isolation scenes (test objects)")
    p.add_argument("--seed", type=int, required=True, help="seed of the scenes and offsets")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="results folder; re-running the same command resumes")
    p.add_argument("--offsets-mm", default=",".join(f"{v:g}" for v in (0, 5, 10, 15, 20, 30, 40)),
                   help="offset lengths in the paper's metric [mm, 1 mm = 1 degree], "
                   "comma-separated (default: 0,5,10,15,20,30,40)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default: 1)")
    p.set_defaults(func=_cmd_grasp_tolerance)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    _parser_grasp_check(sub)
    _parser_label_check(sub)
    _parser_grasp_tolerance(sub)
