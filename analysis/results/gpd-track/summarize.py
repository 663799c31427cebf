"""PLAN.md's goals and rule on PLAN-v2.md's runs of gpd-track (issue 69 item 1).

    python analysis/results/gpd-track/summarize.py [--out analysis/results/gpd-track/summary.json]

Run from the repository root. Each goal is reported with its Wilson 95% interval, its
records' failure classes and the `evaluate` sessions' wall time; still clutter also
with GPD's rate on the same seeds and Fisher's exact test (two-sided). A goal whose
runs are not all there yet is reported with what there is and marked incomplete; the
rule (all four goals met at the point estimate) is applied only when all are complete.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

from drake_grasp.evaluation.records import load_records, wilson_interval
from drake_grasp.evaluation.report_stats import clutter_runs

HERE = Path(__file__).resolve().parent
SEEDS = (110, 111, 112, 113, 114)
RUNS_PER_SEED = 10


def _counts(records, *, within_3cm: bool = False) -> dict:
    """Successes (or final distances within 3 cm) over the attempts that are not
    simulation errors, with the Wilson interval and the failure classes."""
    attempts = [r for r in records if r.failure_class != "simulation-error"]
    if within_3cm:
        k = sum(r.final_distance_m is not None and r.final_distance_m < 0.03 for r in attempts)
    else:
        k = sum(bool(r.success) for r in attempts)
    n = len(attempts)
    lo, hi = wilson_interval(k, n) if n else (None, None)
    return {"successes": k, "n": n, "rate": k / n if n else None, "ci95": [lo, hi],
            "simulation_errors": len(records) - n,
            "failure_classes": dict(collections.Counter(
                r.failure_class for r in records if not r.success))}


def _wall_s(folder: Path) -> float:
    info = json.loads((folder / "run.json").read_text())
    return round(sum(float(s.get("wall_s") or 0.0) for s in info.get("sessions") or []), 1)


def _single(folder: Path, condition: str, trials: int, *, within_3cm: bool = False) -> dict:
    """A one-folder goal (isolation, Figure 5): its counts, complete when all trials are in."""
    if not (folder / "run.json").is_file():
        return {"complete": False, "records": 0}
    recs = [r for r in load_records(folder) if r.condition == condition]
    out = _counts(recs, within_3cm=within_3cm)
    if within_3cm:
        out["grasped"] = sum(bool(r.success) for r in recs)
    return {"complete": len(recs) >= trials, "records": len(recs), "wall_s": _wall_s(folder),
            **out}


def _clutter(prefix: str, condition: str) -> dict:
    """Attempts pooled over the seeds' folders `<prefix>-<seed>`, complete seeds only."""
    records, walls, done, missing = [], 0.0, [], []
    for seed in SEEDS:
        folder = HERE / f"{prefix}-{seed}"
        if not (folder / "run.json").is_file():
            missing.append(seed)
            continue
        recs = [r for r in load_records(folder) if r.condition == condition]
        info = clutter_runs(recs)
        if info is None or "unfinished" in info["run_ends"] or info["runs"] < RUNS_PER_SEED:
            missing.append(seed)
            continue
        records += recs
        walls += _wall_s(folder)
        done.append(seed)
    return {"complete": not missing, "seeds": done, "seeds_missing": missing,
            "runs": RUNS_PER_SEED * len(done), "wall_s": round(walls, 1), **_counts(records)}


def summarize() -> dict:
    from scipy.stats import fisher_exact

    goals = {
        "clutter": {"goal": 0.95, **_clutter("clutter", "gpd-track")},
        "clutter-shift": {"goal": 0.90, **_clutter("clutter-shift", "gpd-track")},
        "isolation": {"goal": 0.975, **_single(HERE / "isolation", "gpd-track", 120)},
        "sim-distance-noise": {"goal": 0.85, "measure": "final distance within 3 cm",
                               **_single(HERE / "sim-distance-noise", "gpd-track_noise", 400,
                                         within_3cm=True)},
    }
    gpd = _clutter("clutter", "gpd")
    track = goals["clutter"]
    goals["clutter"]["gpd_same_seeds"] = gpd
    if gpd["n"] and track["n"]:
        table = [[track["successes"], track["n"] - track["successes"]],
                 [gpd["successes"], gpd["n"] - gpd["successes"]]]
        goals["clutter"]["fisher_p_against_gpd"] = float(fisher_exact(table)[1])
        goals["clutter"]["at_or_above_gpd"] = track["rate"] >= gpd["rate"]
    for g in goals.values():
        g["met"] = None if g.get("rate") is None else g["rate"] >= g["goal"]
    goals["clutter"]["met"] = (goals["clutter"]["met"] is True
                               and goals["clutter"].get("at_or_above_gpd") is True)
    complete = all(g["complete"] for g in goals.values())
    rule = ("all four goals met: gpd-track joins Table 1" if complete and
            all(g["met"] for g in goals.values()) else
            "not all goals met: gpd-track stays out of Table 1" if complete else
            "runs incomplete: no decision")
    return {"plan": "PLAN.md (goals, rule), PLAN-v2.md (seeds, version)", "goals": goals,
            "complete": complete, "decision": rule}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=HERE / "summary.json",
                        help="JSON file to write (default: summary.json beside this script)")
    args = parser.parse_args(argv)
    summary = summarize()
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(summary, indent=1) + "\n")
    tmp.replace(args.out)
    for name, g in summary["goals"].items():
        rate = "-" if g.get("rate") is None else f"{100 * g['rate']:.1f}%"
        print(f"{name}: {g.get('successes')}/{g.get('n')} {rate} (goal {100 * g['goal']:.1f}%, "
              f"{'complete' if g['complete'] else 'incomplete'})")
    print(summary["decision"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
