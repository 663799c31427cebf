"""The rules of PLAN.md in this folder, applied to its runs: does `controller.view_average:
d4` (the default net's grid averaged over the wrist image's 8 symmetric views) grasp
more in clutter than the image as shown, and does it become CTR's default?

    python analysis/results/cnn-view-average/decide.py analysis/results/cnn-view-average \
        --out analysis/results/cnn-view-average/decision.json

Reads each `{plain,d4}-clutter-seedS` folder (S = 29..33; stage 2 also
`{plain,d4}-clutter-shift-seedS`, S = 23..27, and `{plain,d4}-isolation-seed19`),
pools CTR's grasped / attempts per arm (Wilson 95%), Fisher's exact test (two-sided)
on the pooled counts, and CTR's CNN time per decision from the trial records. Refuses,
naming the folder, to decide on part of a stage's runs; stage 2 is read only when all of
its folders are there.

The same rules decide other candidates against the default (`../cnn-onpolicy-finetune/`):

    python analysis/results/cnn-view-average/decide.py analysis/results/cnn-onpolicy-finetune \
        --candidate onpolicy --clutter-seeds 34,35,36,37,38 --out .../decision.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

CLUTTER_SEEDS = (29, 30, 31, 32, 33)
SHIFT_SEEDS = (23, 24, 25, 26, 27)
ISOLATION_SEED = 19
ARMS = ("plain", "d4")
MIN_GAIN = 0.03  # rule 1: at least 3.0 points ...
MAX_P = 0.05  # ... and Fisher's two-sided p below this
ISOLATION_MARGIN = 2  # rule 2: at most this many fewer of the 120 isolation trials


def run_counts(folder: Path) -> dict:
    """CTR's counts in one evaluate folder: grasped / attempts, runs and attempts per run
    (clutter), failure classes, and the CNN time per decision from the trial records."""
    from drake_grasp.evaluation.records import load_records

    path = folder / "summary.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (the run is not done; the rule "
                                "decides on all of a stage's runs only)")
    ctr = json.loads(path.read_text())["policies"].get("ctr")
    if ctr is None:
        raise ValueError(f"{path}: no 'ctr' policy in policies")
    seconds = decisions = 0.0
    for r in load_records(folder):
        extra = r.extra or {}
        if extra.get("decisions"):
            seconds += float(extra.get("decision_time_s") or 0.0)
            decisions += int(extra["decisions"])
    out = {"successes": int(ctr["successes"]), "attempts": int(ctr["n"]),
           "failure_classes": {k: v for k, v in ctr["failure_classes"].items()
                               if k != "none" and v},
           "trial_wall_time_s": ctr["trial_wall_time_s"]["sum"],
           "decisions": int(decisions),
           "ms_per_decision": 1e3 * seconds / decisions if decisions else None}
    if ctr.get("clutter_runs"):
        runs = ctr["clutter_runs"]
        out.update(runs=runs["runs"], attempts_per_run=runs["attempts_per_run"]["mean"],
                   run_ends=runs["run_ends"])
    return out


def pool(root: Path, arm: str, folders: list[str]) -> dict:
    from drake_grasp.evaluation.records import wilson_interval

    per = {f: run_counts(root / f"{arm}-{f}") for f in folders}
    k = sum(c["successes"] for c in per.values())
    n = sum(c["attempts"] for c in per.values())
    lo, hi = wilson_interval(k, n)
    return {"runs": per, "successes": k, "attempts": n, "rate": k / n, "ci95": [lo, hi]}


def compare(root: Path, folders: list[str], arms=ARMS) -> dict:
    from scipy.stats import fisher_exact

    base, cand = arms
    arms = {arm: pool(root, arm, folders) for arm in arms}
    a, b = arms[cand], arms[base]
    table = [[a["successes"], a["attempts"] - a["successes"]],
             [b["successes"], b["attempts"] - b["successes"]]]
    return {**arms, "gain": a["rate"] - b["rate"],
            "fisher_p_two_sided": float(fisher_exact(table, alternative="two-sided")[1])}


def decide(root: Path, candidate: str = "d4", clutter_seeds=CLUTTER_SEEDS,
           shift_seeds=SHIFT_SEEDS, isolation_seed: int = ISOLATION_SEED) -> dict:
    """The rules of PLAN.md for `candidate` (the run folders' prefix) against `plain`."""
    arms = ("plain", candidate)
    what = ("view_average d4" if candidate == "d4" else candidate,
            "the image as shown" if candidate == "d4" else "the shipped net")
    out = {"stage1_clutter": compare(root, [f"clutter-seed{s}" for s in clutter_seeds], arms)}
    s1 = out["stage1_clutter"]
    passed = s1["gain"] >= MIN_GAIN and s1["fisher_p_two_sided"] < MAX_P
    out["rule1"] = {"min_gain": MIN_GAIN, "max_p": MAX_P, "passed": passed}
    stage2 = ([f"{arm}-clutter-shift-seed{s}" for arm in arms for s in shift_seeds]
              + [f"{arm}-isolation-seed{isolation_seed}" for arm in arms])
    present = [f for f in stage2 if (root / f / "summary.json").is_file()]
    if not passed:
        out["decision"] = f"stage 1 failed: {what[1]} stays the default"
        if present:
            out["note"] = f"stage 2 folders present though stage 1 failed: {present}"
        return out
    if len(present) < len(stage2):
        missing = sorted(set(stage2) - set(present))
        out["decision"] = f"stage 1 passed; stage 2 not complete (missing {missing})"
        return out
    s2 = compare(root, [f"clutter-shift-seed{s}" for s in shift_seeds], arms)
    iso = {arm: run_counts(root / f"{arm}-isolation-seed{isolation_seed}") for arm in arms}
    shift_ok = s2[candidate]["rate"] >= s2["plain"]["rate"]
    iso_ok = iso[candidate]["successes"] >= iso["plain"]["successes"] - ISOLATION_MARGIN
    out.update(stage2_clutter_shift=s2, stage2_isolation=iso,
               rule2={"clutter_shift_not_lower": shift_ok, "isolation_within_margin": iso_ok,
                      "isolation_margin": ISOLATION_MARGIN})
    out["decision"] = (f"{what[0]} becomes CTR's default" if shift_ok and iso_ok
                       else f"stage 2 failed: {what[1]} stays the default")
    return out


def main(argv=None) -> int:
    from drake_grasp.core.files import print_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", help="the folder holding the runs")
    p.add_argument("--out", default=None, help="also write the decision as JSON here")
    p.add_argument("--candidate", default="d4", help="the candidate arm's folder prefix")
    p.add_argument("--clutter-seeds", default=",".join(map(str, CLUTTER_SEEDS)))
    p.add_argument("--shift-seeds", default=",".join(map(str, SHIFT_SEEDS)))
    p.add_argument("--isolation-seed", type=int, default=ISOLATION_SEED)
    args = p.parse_args(argv)

    def seeds(text):
        return tuple(int(v) for v in text.split(",") if v)
    try:
        result = decide(Path(args.root), args.candidate, seeds(args.clutter_seeds),
                        seeds(args.shift_seeds), args.isolation_seed)
    except (FileNotFoundError, ValueError, KeyError) as e:
        sys.exit(f"decide: {e}")
    print_json(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
