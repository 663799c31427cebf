"""Two evaluate folders of the same experiment and seed, trial by trial: how many trials
have the same outcome, failure class, control steps and final distance (to the last
digit, and within 1 mm) - e.g. a committed reference folder and its re-run on another
machine (README *Reproducibility*).

    python analysis/compare_records.py analysis/results/paper-bn12500-ep3/isolation \
        data/repro/isolation --condition ctr --out analysis/results/machine-repro/isolation.json

Trials present in only one folder are counted, not compared (a clutter run whose
attempts diverge has other attempts after the first difference).
"""
from __future__ import annotations

import argparse


def compare(a_dir: str, b_dir: str, condition: str) -> dict:
    from drake_grasp.evaluation.records import load_records, wilson_interval

    a = {r.trial_id: r for r in load_records(a_dir) if r.condition == condition}
    b = {r.trial_id: r for r in load_records(b_dir) if r.condition == condition}
    both = sorted(set(a) & set(b))
    if not both:
        raise SystemExit(f"{a_dir}, {b_dir}: no trial of condition {condition!r} in both")
    same = {"success": 0, "failure_class": 0, "control_steps": 0, "final_distance_exact": 0,
            "final_distance_within_1mm": 0, "all_exact": 0}
    differing = []
    for t in both:
        x, y = a[t], b[t]
        s = x.success == y.success
        fc = x.failure_class == y.failure_class
        cs = x.control_steps == y.control_steps
        dx, dy = x.final_distance_m, y.final_distance_m
        exact = dx == dy
        near = exact or (dx is not None and dy is not None and abs(dx - dy) <= 0.001)
        same["success"] += s
        same["failure_class"] += fc
        same["control_steps"] += cs
        same["final_distance_exact"] += exact
        same["final_distance_within_1mm"] += near
        same["all_exact"] += s and fc and cs and exact
        if not (s and fc):
            differing.append({"trial_id": t, "a": [x.success, x.failure_class],
                              "b": [y.success, y.failure_class]})

    def rate(records):
        k = sum(r.success for r in records)
        return {"successes": k, "n": len(records), "ci95": list(wilson_interval(k, len(records)))}

    return {"a": a_dir, "b": b_dir, "condition": condition, "compared": len(both),
            "only_a": len(set(a) - set(b)), "only_b": len(set(b) - set(a)), "same": same,
            "outcome_differs": differing, "a_rate": rate(list(a.values())),
            "b_rate": rate(list(b.values()))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--condition", default="ctr")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    from drake_grasp.core.files import print_json

    print_json(compare(args.a, args.b, args.condition), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
