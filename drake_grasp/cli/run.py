"""`drake-grasp` commands: one episode, its Diagram, the benchmarks (demo, diagram, bench)."""

from __future__ import annotations

import json

from drake_grasp.cli.args import policy_arg, add_scenario_flags, load_scenario_from_args


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
    scenario = load_scenario_from_args(args, **overrides)
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

    scenario = load_scenario_from_args(args)
    path = write_diagram(scenario, out=args.out, depth=args.depth)
    print(path)
    return 0


def _cmd_bench(args) -> int:
    from drake_grasp.cli.bench import run_benchmarks

    only = [k for k in args.only.split(",") if k] if args.only else None
    results = run_benchmarks(only=only, out=args.out)
    print(json.dumps(results, indent=1))
    return 0


def _parser_demo(sub) -> None:
    p = sub.add_parser("demo", help="run one grasp episode and write episode.json, "
                                    "replay.html and depth.png")
    add_scenario_flags(p)
    p.add_argument("--policy", default=None, type=policy_arg,
                   metavar="{ctr,gpd,gpd-track,gpd-geometric,cnn-only,cnn-ctr,init,scripted,MODULE:FACTORY}",
                   help="ctr: the paper's closed-loop controller (shipped CNN); gpd: the "
                        "paper's baseline: learned GPD on one image from the Structure-IO-like "
                        "sensor at a fixed viewpoint, a 6-DOF grasp executed open loop; "
                        "gpd-track: gpd's grasp, followed in the wrist camera on the way down; "
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
                   help="CNN weights file (default: models/cnn-grid-bn12500-ep3-fp16/, the "
                   "grid head trained with BatchNorm, last on the paper's 12,500 scenes, "
                   "stored in float16; in float32: models/cnn-grid-bn12500-ep3/; "
                   "models/cnn-grid-bn12500/, models/cnn-grid-bn12-ep5/, "
                   "models/cnn-grid-bn12/, models/cnn-grid-bn/ and models/cnn-grid/ are the "
                   "grid heads before it, models/cnn/ the paper's "
                   "net, each weights.safetensors, in the repository's models/ only, not "
                   "installed with the package); FILE,FILE,... "
                   "scores with the mean of several nets (an ensemble)")
    p.add_argument("--seed", type=int, default=None,
                   help="trial seed (scene and noise); default: the scenario's seed")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--no-replay", action="store_true",
                   help="skip the Meshcat replay page (faster)")
    p.set_defaults(func=_cmd_demo)


def _parser_diagram(sub) -> None:
    p = sub.add_parser("diagram", help="write the station Diagram as Graphviz (SVG if 'dot' is "
                                       "installed, else .dot)")
    add_scenario_flags(p)
    p.add_argument("--out", required=True, help="output file (.svg, .png or .dot)")
    p.add_argument("--depth", type=int, default=2,
                   help="how many levels of nested diagrams to expand (default 2: the "
                        "episode and the station inside it)")
    p.set_defaults(func=_cmd_diagram)


def _parser_bench(sub) -> None:
    from drake_grasp.cli.bench import BENCHMARKS

    p = sub.add_parser("bench", help="run the benchmarks and print one JSON object")
    p.add_argument("--only", default="",
                   help=f"comma-separated benchmark groups ({', '.join(BENCHMARKS)}) "
                        "or any key that bench prints "
                        "(e.g. cnn_infer_ms_128, train_samples_per_s): a key runs its group "
                        "and prints only that key (default: everything)")
    p.add_argument("--out", default=None, help="also write the JSON (with the machine) here")
    p.set_defaults(func=_cmd_bench)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    _parser_demo(sub)
    _parser_diagram(sub)
    _parser_bench(sub)
