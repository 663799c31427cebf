"""`drake-grasp` commands: ONNX export, scenario files, the process boundary, object libraries (export-onnx, scenarios, bridge, objects)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from drake_grasp.cli.args import add_scenario_flags, load_scenario_from_args


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
    scenario = load_scenario_from_args(args, **overrides)
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


def _cmd_objects_import(args) -> int:
    from drake_grasp.objects import import_mesh

    info = import_mesh(args.mesh, name=args.name, library_dir=args.library, scale=args.scale,
                       density_kg_m3=args.density, overwrite=args.overwrite,
                       up_axis=args.up_axis)
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


def _parser_export_onnx(sub) -> None:
    p = sub.add_parser("export-onnx", help="write the distance CNN as ONNX for onnxruntime: "
                       "FILE (image part, with the metadata) and FILE's .head.onnx sibling "
                       "(per-action head); 'controller.weights: FILE' then runs it without torch")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="the image part, ending in .onnx; the head goes to the same name with "
                        ".head.onnx (X.onnx -> X.head.onnx); both are replaced if present")
    p.add_argument("--weights", default="", metavar="W",
                   help="safetensors weights to export, a tiled (paper) net (default: the "
                        "paper net models/cnn/weights.safetensors, in the repository's models/ "
                        "only, not installed with the package; the grid head, "
                        "the episodes' default, has no ONNX export)")
    p.add_argument("--exporter", default="auto", choices=["auto", "dynamo", "torchscript"],
                   help="torch.onnx.export path: dynamo (needs onnxscript) or torchscript "
                        "(dynamo=False); auto (default): dynamo when onnxscript is installed")
    p.set_defaults(func=_cmd_export_onnx)


def _parser_scenarios(sub) -> None:
    p = sub.add_parser("scenarios", help="list the named scenarios of a scenarios file")
    p.add_argument("--scenario-file", default=None, help="a *.scenarios.yaml file")
    p.set_defaults(func=_cmd_scenarios)


def _parser_bridge(sub) -> None:
    pb = sub.add_parser("bridge", help="the controller and the simulated station in two "
                                       "processes, talking robot-driver LCM messages over TCP "
                                       "on 127.0.0.1 (README: Across a process boundary)")
    bsub = pb.add_subparsers(dest="bridge_command", required=True)
    for name, text in (("episode", "run one episode: the station here, the controller in a "
                                   "process it starts; prints episode.json"),
                       ("station", "run the station side of one episode and wait for a "
                                   "controller started by hand ('bridge controller')")):
        p = bsub.add_parser(name, help=text)
        add_scenario_flags(p)
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


def _parser_objects(sub) -> None:
    po = sub.add_parser("objects", help="object libraries")
    osub = po.add_subparsers(dest="objects_command", required=True)
    p = osub.add_parser("import", help="bring an OBJ/STL/PLY/glTF mesh into an object library")
    p.add_argument("mesh", help="mesh file")
    p.add_argument("--name", required=True, help="object id (letters, digits, _ and -)")
    p.add_argument("--library", required=True, help="library folder (created if missing)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="multiply coordinates by this (e.g. 0.001 for millimetres)")
    p.add_argument("--density", type=float, default=500.0, help="density in kg/m^3")
    p.add_argument("--up-axis", choices=("z", "y"), default=None,
                   help="the file's up axis, turned to z (default: y for glTF/GLB, as their "
                        "specification and Drake have it; z for OBJ, STL and PLY)")
    p.add_argument("--overwrite", action="store_true", help="replace an object of that name")
    p.set_defaults(func=_cmd_objects_import)
    p = osub.add_parser("list", help="list object ids")
    p.add_argument("--objects", default=None, help="library folder (default: built-in)")
    p.add_argument("--split", default="", choices=["", "train", "test"], help="only this split")
    p.set_defaults(func=_cmd_objects_list)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    _parser_export_onnx(sub)
    _parser_scenarios(sub)
    _parser_bridge(sub)
    _parser_objects(sub)
