"""What several `drake-grasp` commands share: argument types, the scenario flags and
the scenario they select."""

from __future__ import annotations

import argparse


def policy_arg(text: str) -> str:
    """--policy: a built-in policy name or MODULE:FACTORY (a user policy)."""
    from drake_grasp.policies.plugins import is_policy_spec, parse_policy_spec
    from drake_grasp.config.sections import POLICIES

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


def add_scenario_flags(p: argparse.ArgumentParser, default: str = "isolation") -> None:
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


def load_scenario_from_args(args, **overrides):
    from drake_grasp.config.scenario import load_scenario, replace

    scenario = load_scenario(scenario_name=args.scenario, scenario_file=args.scenario_file,
                             scenario_text=args.scenario_text)
    if args.objects:
        overrides["objects_dir"] = str(args.objects)
    return replace(scenario, **overrides) if overrides else scenario


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}") from None
    if not (value >= 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def trunk_widths(text: str) -> tuple[int, int, int]:
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


def add_initial_pose_flag(p) -> None:
    """`--initial-pose` of `generate` and `label-check` (`DatasetConfig.initial_pose`)."""
    from drake_grasp.learning.dataset import INITIAL_POSES, DatasetConfig

    default = DatasetConfig().initial_pose
    p.add_argument("--initial-pose", choices=list(INITIAL_POSES), default=default,
                   help="the objects' orientation before the settle: uniform, a uniformly "
                   "random rotation that tumbles when dropped (every dataset and label check "
                   "so far); stable, a resting pose of each object drawn with its "
                   "probability and a random yaw: faster, fewer scenes replaced, label "
                   f"precision still being measured (default {default}; docs/guide/"
                   "data-training.md *Stable initial poses*)")


def add_torque_ratio_flag(p) -> None:
    from drake_grasp.learning.dataset import DatasetConfig

    default = DatasetConfig().max_torque_ratio
    p.add_argument("--max-torque-ratio", type=positive_float, default=default, metavar="R",
                   help="the ground truth's torque test: the largest torque about the "
                   "contact axis under gravity and the lab's shake, per unit of the pads' "
                   f"torsional friction lever, a true grasp may need (default {default:g}, "
                   "README *Grip force*)")
