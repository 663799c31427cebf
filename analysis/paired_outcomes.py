"""Two `evaluate` runs of the same trials (same experiment, seed and trial count), compared
trial by trial: how many only one of them grasped, and the exact McNemar test on those;
how many ended at the same final distance (to 1 um) and with the same failure class;
and the same paired count for Figure 5's measure, the final distance within 3 cm.

Two policies (or two weights files for one policy) run on the same scenes differ by less
than their two success rates' intervals suggest: most trials succeed or fail under both.
The paired count says what the unpaired intervals cannot.

    python analysis/paired_outcomes.py RUN_A RUN_B [--names A,B] [--condition C] [--out FILE.json]

Each RUN is a results folder of `drake-grasp evaluate` (its `trials/`); trials are paired
by trial id (experiment/condition/index), and only ids present in both count;
`--condition C` counts only condition C's trials (a run of several conditions, e.g.
`perception`'s cnn-only and cnn-ctr, would otherwise be pooled).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from drake_grasp.evaluation.records import load_records, mcnemar_exact_p

from drake_grasp.core.files import print_json


def paired(run_a: Path, run_b: Path, condition: str | None = None) -> dict:
    """The paired outcome counts of two runs (see the module docstring)."""
    keep = (lambda r: True) if condition is None else (lambda r: r.condition == condition)
    a = {r.trial_id: r for r in load_records(run_a) if keep(r)}
    b = {r.trial_id: r for r in load_records(run_b) if keep(r)}
    ids = sorted(set(a) & set(b))
    if not ids:
        which = "" if condition is None else f" of condition '{condition}'"
        raise ValueError(f"{run_a} and {run_b}: no trial id{which} in both (expected two "
                         "runs of the same experiment, seed and trials)")
    both = sum(a[i].success and b[i].success for i in ids)
    only_a = sum(a[i].success and not b[i].success for i in ids)
    only_b = sum(b[i].success and not a[i].success for i in ids)
    # The final distance (Figure 5's measure): agreement to 1 um, where both have one.
    dist = [(a[i].final_distance_m, b[i].final_distance_m) for i in ids]
    measured = [(x, y) for x, y in dist if x is not None and y is not None]
    # Figure 5's count: within 3 cm of a true grasp (no distance: not within).
    near = [(x is not None and x < 0.03, y is not None and y < 0.03) for x, y in dist]
    near_a = sum(x and not y for x, y in near)
    near_b = sum(y and not x for x, y in near)
    return {"paired_trials": len(ids), "successes_a": both + only_a,
            "successes_b": both + only_b, "both": both, "only_a": only_a, "only_b": only_b,
            "neither": len(ids) - both - only_a - only_b,
            "mcnemar_exact_p": round(mcnemar_exact_p(only_a, only_b), 4),
            "final_distance_in_both": len(measured),
            "same_final_distance": sum(abs(x - y) <= 1e-6 for x, y in measured),
            "same_failure_class": sum(a[i].failure_class == b[i].failure_class for i in ids),
            "within_3cm_a": sum(x for x, _ in near), "within_3cm_b": sum(y for _, y in near),
            "within_3cm_only_a": near_a, "within_3cm_only_b": near_b,
            "within_3cm_mcnemar_exact_p": round(mcnemar_exact_p(near_a, near_b), 4),
            "only_a_trials": [i for i in ids if a[i].success and not b[i].success],
            "only_b_trials": [i for i in ids if b[i].success and not a[i].success]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", type=Path, help="an `evaluate` results folder")
    parser.add_argument("run_b", type=Path, help="another one, of the same trials")
    parser.add_argument("--names", default="a,b", help="names of the two runs (default a,b)")
    parser.add_argument("--condition", default=None,
                        help="count only this condition's trials (default: every one)")
    parser.add_argument("--out", type=Path, default=None, help="JSON file to write")
    args = parser.parse_args(argv)
    names = args.names.split(",")
    if len(names) != 2:
        parser.error(f"--names {args.names}: expected two names separated by a comma")
    try:
        result = {"runs": {names[0]: str(args.run_a), names[1]: str(args.run_b)},
                  **({"condition": args.condition} if args.condition else {}),
                  **paired(args.run_a, args.run_b, args.condition)}
    except (ValueError, OSError) as e:
        print(f"paired_outcomes: error: {e}", file=sys.stderr)
        return 2
    print_json(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
