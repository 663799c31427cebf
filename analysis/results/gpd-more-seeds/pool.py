"""GPD pooled over the same 50 clutter and 50 clutter-shift runs as the default CTR.

    python analysis/results/gpd-more-seeds/pool.py [--out pooled.json]

Run from the repository root. Seeds whose folder is missing or unfinished are listed as
missing and left out of the pool.
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

from drake_grasp.evaluation.report_stats import clutter_runs
from drake_grasp.evaluation.records import load_records, wilson_interval

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent
# (experiment, seed) -> (folder, condition). Seeds 16 and 8 are Table 1's GPD rows.
GPD = {("clutter", 16): "failure-memory/clutter-seed16-gpd-fallback",
       ("clutter-shift", 8): "failure-memory/clutter-shift-seed8-gpd-fallback",
       **{("clutter", s): f"gpd-more-seeds/gpd-clutter-seed{s}" for s in (25, 26, 27, 28)},
       **{("clutter-shift", s): f"gpd-more-seeds/gpd-clutter-shift-seed{s}"
          for s in (19, 20, 21, 22)}}
CTR = {("clutter", 16): "paper-bn12500-ep3/clutter",
       ("clutter", 25): "bn-paper-scale-ep3/new-clutter-seed25",
       ("clutter", 26): "bn-paper-scale-ep3/new-clutter-seed26",
       ("clutter", 27): "default-more-seeds/cnn-clutter-seed27",
       ("clutter", 28): "default-more-seeds/cnn-clutter-seed28",
       ("clutter-shift", 8): "paper-bn12500-ep3/clutter-shift",
       ("clutter-shift", 19): "bn-paper-scale-ep3/new-clutter-shift-seed19",
       ("clutter-shift", 20): "bn-paper-scale-ep3/new-clutter-shift-seed20",
       ("clutter-shift", 21): "default-more-seeds/cnn-clutter-shift-seed21",
       ("clutter-shift", 22): "default-more-seeds/cnn-clutter-shift-seed22"}


def pool(table: dict, condition: str, experiment: str) -> dict:
    out = {"per_seed": {}, "missing": [], "grasped": 0, "attempts": 0, "runs": 0,
           "failure_classes": collections.Counter(), "run_ends": collections.Counter()}
    for (exp, seed), folder in sorted(table.items()):
        if exp != experiment:
            continue
        path = RESULTS / folder
        recs = ([r for r in load_records(path) if r.condition == condition]
                if (path / "run.json").is_file() else [])
        info = clutter_runs(recs) if recs else None
        if info is None or info["runs"] < 10 or "unfinished" in info["run_ends"]:
            out["missing"].append(seed)
            continue
        real = [r for r in recs if r.failure_class != "simulation-error"]
        g = sum(1 for r in real if r.success)
        out["per_seed"][seed] = f"{g}/{len(real)}"
        out["grasped"] += g
        out["attempts"] += len(real)
        out["runs"] += info["runs"]
        out["failure_classes"].update(r.failure_class for r in real if not r.success)
        out["run_ends"].update(info["run_ends"])
    n = out["attempts"]
    out["rate"] = out["grasped"] / n if n else None
    out["ci95"] = list(wilson_interval(out["grasped"], n)) if n else None
    out["attempts_per_run"] = n / out["runs"] if out["runs"] else None
    out["failure_classes"] = dict(out["failure_classes"])
    out["run_ends"] = dict(out["run_ends"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(HERE / "pooled.json"))
    args = ap.parse_args()
    result = {}
    for experiment in ("clutter", "clutter-shift"):
        for name, table, condition in (("gpd", GPD, "gpd"), ("ctr", CTR, "ctr")):
            p = pool(table, condition, experiment)
            result[f"{name}, {experiment}"] = p
            if p["attempts"]:
                print(f"{name}, {experiment}: {p['grasped']}/{p['attempts']} "
                      f"{100 * p['rate']:.1f}% [{100 * p['ci95'][0]:.1f}, "
                      f"{100 * p['ci95'][1]:.1f}] over {p['runs']} runs "
                      f"({p['attempts_per_run']:.1f} attempts/run), per seed {p['per_seed']}, "
                      f"failures {p['failure_classes']}, ends {p['run_ends']}"
                      + (f"; missing seeds {p['missing']}" if p["missing"] else ""))
        ctr, gpd = result[f"ctr, {experiment}"], result[f"gpd, {experiment}"]
        if ctr["rate"] is not None and gpd["rate"] is not None:
            result[f"ctr minus gpd, {experiment}, points"] = 100 * (ctr["rate"] - gpd["rate"])
            print(f"CTR - GPD, {experiment}: {100 * (ctr['rate'] - gpd['rate']):+.1f} points "
                  f"(GPD seeds {sorted(gpd['per_seed'])})")
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
