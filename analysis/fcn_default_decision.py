"""The rule of `results/fcn-default-decision/PLAN.md` (and, on other seeds, of
`results/fcn-all-decision/PLAN.md` and `results/cnn-more-epochs/PLAN.md`), applied to its
runs: should a candidate net (a height-map FCN; `--candidate new`: a CNN trained on)
become CTR's default net?

    python analysis/fcn_default_decision.py analysis/results/fcn-default-decision \
        --out analysis/results/fcn-default-decision/decision.json
    python analysis/fcn_default_decision.py analysis/results/fcn-all-decision \
        --clutter-shift-seeds 13,14 --clutter-seeds 19,20 --isolation-seed 14 \
        --out analysis/results/fcn-all-decision/decision.json
    python analysis/fcn_default_decision.py analysis/results/cnn-more-epochs --candidate new \
        --clutter-shift-seeds 15,16 --clutter-seeds 21,22 --isolation-seed 15 \
        --out analysis/results/cnn-more-epochs/decision.json

Reads each `{fcn,cnn}-{clutter-shift-seedS, clutter-seedS, isolation-seedS}` folder's CTR
summary (by default the first decision's seeds: clutter-shift 11 and 12, clutter 17 and
18, isolation 13), pools the four clutter and clutter-shift runs of each net (grasped /
attempts, Wilson 95%), and applies the rule: the FCN becomes the default if and only if
its pooled rate is strictly higher than the CNN's and it grasps at most 2 fewer of the
120 isolation trials. `--candidate NAME` reads the candidate's runs from `NAME-...`
folders instead of `fcn-...` (the default CNN's stay `cnn-...`). Refuses (naming the
folder) to decide on part of the runs.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

CLUTTER_SHIFT_SEEDS, CLUTTER_SEEDS, ISOLATION_SEED = (11, 12), (17, 18), 13
CANDIDATE, INCUMBENT = "fcn", "cnn"  # the run folders' prefixes
ISOLATION_MARGIN = 2  # the candidate may grasp at most this many fewer isolation trials


def ctr_counts(folder: Path) -> dict:
    """CTR's grasped / attempts and failure classes in one evaluate folder's summary."""
    path = folder / "summary.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (the run is not done; the rule "
                                "decides on all ten runs only)")
    ctr = json.loads(path.read_text())["policies"].get("ctr")
    if ctr is None:
        raise ValueError(f"{path}: no 'ctr' policy in policies")
    return {"successes": int(ctr["successes"]), "attempts": int(ctr["n"]),
            "failure_classes": {k: v for k, v in ctr["failure_classes"].items()
                                if k != "none" and v}}


def decide(root: Path, *, clutter_shift_seeds=CLUTTER_SHIFT_SEEDS,
           clutter_seeds=CLUTTER_SEEDS, isolation_seed=ISOLATION_SEED,
           candidate=CANDIDATE) -> dict:
    from drake_grasp.evaluation.records import wilson_interval

    if not candidate or candidate == INCUMBENT or "/" in candidate:
        raise ValueError(f"candidate {candidate!r}: expected a run-folder prefix other "
                         f"than the default's {INCUMBENT!r}, e.g. 'fcn' or 'new'")
    clutter_runs = ([f"clutter-shift-seed{s}" for s in clutter_shift_seeds]
                    + [f"clutter-seed{s}" for s in clutter_seeds])
    if len(clutter_runs) != 4:
        raise ValueError(f"the rule pools 4 clutter runs per net; got {clutter_runs}")
    out = {"runs": {}, "pooled": {}, "isolation": {}}
    for net in (candidate, INCUMBENT):
        grasped = attempts = 0
        for run in clutter_runs:
            c = ctr_counts(root / f"{net}-{run}")
            out["runs"][f"{net}-{run}"] = c
            grasped, attempts = grasped + c["successes"], attempts + c["attempts"]
        lo, hi = wilson_interval(grasped, attempts)
        out["pooled"][net] = {"successes": grasped, "attempts": attempts,
                              "rate": grasped / attempts, "ci95": [lo, hi]}
        out["isolation"][net] = ctr_counts(root / f"{net}-isolation-seed{isolation_seed}")
    higher = out["pooled"][candidate]["rate"] > out["pooled"][INCUMBENT]["rate"]
    iso_ok = (out["isolation"][candidate]["successes"]
              >= out["isolation"][INCUMBENT]["successes"] - ISOLATION_MARGIN)
    out["rule"] = {f"{candidate}_pooled_rate_higher": higher,
                   f"{candidate}_isolation_within_margin": iso_ok,
                   "isolation_margin": ISOLATION_MARGIN}
    out["decision"] = (f"{candidate} becomes the default" if higher and iso_ok
                       else f"{INCUMBENT} stays the default")
    return out


def main(argv=None) -> int:
    from drake_grasp.core.files import print_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", help="the folder holding the ten runs")
    p.add_argument("--clutter-shift-seeds", default=",".join(map(str, CLUTTER_SHIFT_SEEDS)))
    p.add_argument("--clutter-seeds", default=",".join(map(str, CLUTTER_SEEDS)))
    p.add_argument("--isolation-seed", type=int, default=ISOLATION_SEED)
    p.add_argument("--candidate", default=CANDIDATE,
                   help="the candidate's run-folder prefix (default: fcn)")
    p.add_argument("--out", default=None, help="also write the decision as JSON here")
    args = p.parse_args(argv)
    try:
        seeds = {k: tuple(int(s) for s in getattr(args, k).split(","))
                 for k in ("clutter_shift_seeds", "clutter_seeds")}
    except ValueError:
        sys.exit("fcn_default_decision: --clutter-shift-seeds and --clutter-seeds take "
                 "comma-separated integers, e.g. 11,12")
    try:
        result = decide(Path(args.root), **seeds, isolation_seed=args.isolation_seed,
                        candidate=args.candidate)
    except (FileNotFoundError, ValueError, KeyError) as e:
        sys.exit(f"fcn_default_decision: {e}")
    print_json(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
