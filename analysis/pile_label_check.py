"""Do one object's ground-truth grasps hold in the grasp lab, in the pile a clutter attempt
began on?

Takes a clutter attempt's record (its `extra.scene`, scenario and seed), computes the
pile's ground truth as the judge and the oracle do (`grasps.find_grasps`, rng [seed, 61]),
and executes K of the named object's true grasps (drawn with rng 0) in the grasp lab
twice: with every object of the pile present as settled, and with the object alone. A
label the lab holds with its neighbours but the station does not points at execution
(the pose reached, the approach), not at the label.

    python analysis/pile_label_check.py analysis/results/paper-bn12/clutter/trials/clutter__ctr__0007__attempt02.json \
        toy_car_004 --grasps 6 --out analysis/results/oracle-ctr-clutter-bn12/pile_label_check.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def check(record_path: str | Path, object_id: str, grasps: int) -> dict:
    """{"objects", "true_grasps", "on_object", "checks": [{"grasp", "neighbours",
    "alone"}], "held_with_neighbours", "held_alone"}; ValueError for a record without a
    pile or an object not in it."""
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.evaluation.lab import check_grasp
    from drake_grasp.evaluation.replay import recorded_pile
    from drake_grasp.objects import load_library

    _, scenario, scene = recorded_pile(record_path)
    library = load_library(None)
    ids = [o.object_id for o in scene.objects]
    if object_id not in ids:
        raise ValueError(f"{record_path}: object {object_id!r} not in the pile; it holds {ids}")
    index = ids.index(object_id)
    truth = find_grasps(scene, library, np.random.default_rng([scenario.seed, 61]))
    mine = np.flatnonzero(np.asarray(truth.object_index) == index)
    chosen = np.random.default_rng(0).choice(mine, size=min(grasps, len(mine)), replace=False) \
        if len(mine) else []
    checks = []
    for i in chosen:
        row = {"grasp": int(i)}
        for name, neighbours in (("neighbours", True), ("alone", False)):
            r = check_grasp(None, truth.poses[int(i)], scene=scene, scenario=scenario,
                            library=library, object_index=index, neighbours=neighbours)
            row[name] = {"held": bool(r.held), "failure": r.failure}
        checks.append(row)
    return {"record": str(record_path), "object_id": object_id, "objects": ids,
            "true_grasps": int(len(truth.poses)), "on_object": int(len(mine)), "checks": checks,
            "held_with_neighbours": sum(c["neighbours"]["held"] for c in checks),
            "held_alone": sum(c["alone"]["held"] for c in checks)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("record", help="a clutter attempt's trial record (JSON)")
    p.add_argument("object_id", help="the object of the pile whose true grasps to execute")
    p.add_argument("--grasps", type=int, default=6, help="how many of its true grasps (default 6)")
    p.add_argument("--out", type=Path, default=None, help="JSON file to write")
    args = p.parse_args(argv)
    if args.grasps < 1:
        p.error(f"--grasps: expected >= 1, got {args.grasps}")
    t0 = time.perf_counter()
    try:
        result = check(args.record, args.object_id, args.grasps)
    except (ValueError, OSError, KeyError) as e:
        print(f"pile_label_check: error: {e}", file=sys.stderr)
        return 2
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    from drake_grasp.core.files import print_json

    print_json(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
