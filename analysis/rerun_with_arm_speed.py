"""Re-runs recorded trials from their records' scenarios, optionally with other speed
limits for the arm (`arm.max_tcp_angular_speed_rad_s`, `arm.joint_velocity_fraction`), and writes each
trial's outcome and final distance: a paired A/B on the same trials.

    python analysis/rerun_with_arm_speed.py RESULTS_DIR --condition ctr_noise --trials 60 \
        [--angular-speed 3.0] [--joint-velocity-fraction 1.0] --out FILE.json

0 keeps each record's own value (the A side). The CTR servo moves to each new target
within 80 ms, and a yaw turn of up to 22 degrees takes longer than a control period at
the default limits (the wrist joint at half its 3.14 rad/s, the TCP at 2 rad/s); a faster
wrist tells whether that lag matters.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results_dir", help="an `evaluate` results folder (its trials/)")
    ap.add_argument("--condition", required=True, help="condition name, e.g. ctr_noise")
    ap.add_argument("--trials", type=int, default=60, help="N trials of it")
    ap.add_argument("--first", type=int, default=0,
                    help="index of the first (in trial id order), to split a run in parts")
    ap.add_argument("--angular-speed", type=float, default=0.0,
                    help="arm.max_tcp_angular_speed_rad_s to use; 0 keeps the record's")
    ap.add_argument("--joint-velocity-fraction", type=float, default=0.0,
                    help="arm.joint_velocity_fraction to use; 0 keeps the record's")
    ap.add_argument("--out", required=True, help="JSON file to write")
    args = ap.parse_args(argv)

    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.api import load_library, simulate_episode
    from drake_grasp.config.scenario import Scenario
    from drake_grasp.policies.evaluator import load_cnn

    from drake_grasp.evaluation.records import load_records

    records = [r.to_dict() for r in load_records(args.results_dir)
               if r.condition == args.condition]
    records = records[args.first:args.first + args.trials]
    if not records:
        ap.exit(2, f"no trial records of condition {args.condition!r} in {args.results_dir}\n")
    library = load_library()
    model = load_cnn("", threads=1)
    rows = []
    for record in records:
        scenario = yaml_load_typed(schema=Scenario, data=record["scenario_yaml"])
        if args.angular_speed > 0:
            scenario.arm.max_tcp_angular_speed_rad_s = args.angular_speed
        if args.joint_velocity_fraction > 0:
            scenario.arm.joint_velocity_fraction = args.joint_velocity_fraction
        t0 = time.perf_counter()
        run = simulate_episode(scenario, library=library, record_depth=False, model=model)
        rows.append({"trial_id": record["trial_id"], "success": bool(run.result.success),
                     "final_distance_m": run.result.final_distance_m,
                     "recorded_final_distance_m": record["final_distance_m"],
                     "hand_at_close_xy_yaw": run.result.details["hand_at_close_xy_yaw"],
                     "wall_s": time.perf_counter() - t0})
        print(f"{len(rows)}/{len(records)} {record['trial_id']}: "
              f"{'lifted' if rows[-1]['success'] else 'failed'}, "
              f"{rows[-1]['final_distance_m']}", flush=True)
    out = {"results_dir": args.results_dir, "condition": args.condition,
           "angular_speed_rad_s": args.angular_speed or "as recorded",
           "joint_velocity_fraction": args.joint_velocity_fraction or "as recorded",
           "trials": rows}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
