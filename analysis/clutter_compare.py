"""Two clutter runs on the same piles (same experiment and seed), compared run by run.

Clutter attempts cannot be paired one to one once two runs diverge (a different grasp
leaves a different pile), so this compares, per policy: grasps and attempts, the
repeated failures (a failed attempt that moved no object by more than 1 cm, followed by
another failure: the pile the next attempt saw was the same), the objects left in the
pile at each run's end, and how many runs agree attempt for attempt up to the first
failure (where nothing in the runs can differ yet, so they must: a check that the two
packages simulate the same).

    python analysis/clutter_compare.py RUN_A RUN_B [--names A,B] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

from drake_grasp.evaluation.records import load_records, wilson_interval

STILL_M = 0.01  # a pile whose objects all moved less than this is "the same pile"


def _moved_m(record) -> float:
    before = {o["object_id"]: np.asarray(o["xyz"]) for o in record.extra["scene"]["objects"]}
    after = {o["object_id"]: np.asarray(o["xyz"]) for o in record.extra["next_scene"]["objects"]}
    shared = [k for k in after if k in before]
    return max((float(np.linalg.norm(after[k] - before[k])) for k in shared), default=0.0)


def runs_of(folder: Path) -> dict:
    """{(condition, run index): its attempts in order}, simulation errors left out."""
    runs = collections.defaultdict(list)
    for r in load_records(folder):
        if r.run_index is not None:
            runs[(r.condition, r.run_index)].append(r)
    return {k: sorted(v, key=lambda r: r.attempt_index) for k, v in runs.items()}


def summary(runs: dict, condition: str) -> dict:
    mine = [v for (c, _), v in sorted(runs.items()) if c == condition]
    attempts = [r for v in mine for r in v if r.failure_class != "simulation-error"]
    grasped = sum(r.success for r in attempts)
    repeats = 0
    for v in mine:
        tried = [r for r in v if r.failure_class != "simulation-error"]
        for a, b in zip(tried, tried[1:]):
            if not a.success and not b.success and _moved_m(a) < STILL_M:
                repeats += 1
    left = [len(v[-1].extra["next_scene"]["objects"]) if v[-1].extra.get("next_scene") else None
            for v in mine]
    lo, hi = wilson_interval(grasped, len(attempts))
    failures = collections.Counter(r.failure_class for r in attempts if not r.success)
    return {"runs": len(mine), "attempts": len(attempts), "grasped": grasped,
            "success_rate": grasped / max(len(attempts), 1), "wilson95": [lo, hi],
            "repeated_failures": repeats, "failure_classes": dict(failures),
            "objects_left": sum(x for x in left if x is not None)}


def agree_until_first_failure(a: dict, b: dict, condition: str) -> dict:
    """Runs whose attempts agree (success, grasped object) in both folders up to and
    including each run's first failure in `a`."""
    same = checked = 0
    for key, ra in a.items():
        if key[0] != condition or key not in b:
            continue
        rb = b[key]
        first = next((i for i, r in enumerate(ra) if not r.success), len(ra) - 1)
        checked += 1
        same += len(rb) > first and all(
            (x.success, x.grasped_object_id) == (y.success, y.grasped_object_id)
            for x, y in zip(ra[:first + 1], rb[:first + 1]))
    return {"runs": checked, "agree": same}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_a")
    ap.add_argument("run_b")
    ap.add_argument("--names", default="a,b")
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    names = args.names.split(",")
    if len(names) != 2:
        raise SystemExit(f"--names: expected two comma-separated names, got {args.names!r}")
    a, b = runs_of(Path(args.run_a)), runs_of(Path(args.run_b))
    if not a or not b:
        raise SystemExit(f"no clutter attempts in {args.run_a if not a else args.run_b} "
                         "(a results folder of `drake-grasp evaluate --experiment clutter...`)")
    conditions = sorted({c for c, _ in a} & {c for c, _ in b})
    result = {"runs": {names[0]: args.run_a, names[1]: args.run_b}}
    for c in conditions:
        result[c] = {names[0]: summary(a, c), names[1]: summary(b, c),
                     "agree_until_first_failure": agree_until_first_failure(a, b, c)}
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
