"""The rule of `results/fcn-default-decision/PLAN.md`, applied to its runs: should the
height-map FCN become CTR's default net?

    python analysis/fcn_default_decision.py analysis/results/fcn-default-decision \
        --out analysis/results/fcn-default-decision/decision.json

Reads each `{fcn,cnn}-{clutter-shift-seed11,clutter-shift-seed12,clutter-seed17,
clutter-seed18,isolation-seed13}` folder's CTR summary, pools the four clutter and
clutter-shift runs of each net (grasped / attempts, Wilson 95%), and applies the rule:
the FCN becomes the default if and only if its pooled rate is strictly higher than the
CNN's and it grasps at most 2 fewer of the 120 isolation trials. Refuses (naming the
folder) to decide on part of the runs.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

CLUTTER_RUNS = ("clutter-shift-seed11", "clutter-shift-seed12", "clutter-seed17", "clutter-seed18")
ISOLATION_RUN = "isolation-seed13"
NETS = ("fcn", "cnn")
ISOLATION_MARGIN = 2  # the FCN may grasp at most this many fewer isolation trials


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


def decide(root: Path) -> dict:
    from drake_grasp.results import wilson_interval

    out = {"runs": {}, "pooled": {}, "isolation": {}}
    for net in NETS:
        grasped = attempts = 0
        for run in CLUTTER_RUNS:
            c = ctr_counts(root / f"{net}-{run}")
            out["runs"][f"{net}-{run}"] = c
            grasped, attempts = grasped + c["successes"], attempts + c["attempts"]
        lo, hi = wilson_interval(grasped, attempts)
        out["pooled"][net] = {"successes": grasped, "attempts": attempts,
                              "rate": grasped / attempts, "ci95": [lo, hi]}
        out["isolation"][net] = ctr_counts(root / f"{net}-{ISOLATION_RUN}")
    higher = out["pooled"]["fcn"]["rate"] > out["pooled"]["cnn"]["rate"]
    iso_ok = (out["isolation"]["fcn"]["successes"]
              >= out["isolation"]["cnn"]["successes"] - ISOLATION_MARGIN)
    out["rule"] = {"fcn_pooled_rate_higher": higher, "fcn_isolation_within_margin": iso_ok,
                   "isolation_margin": ISOLATION_MARGIN}
    out["decision"] = "fcn becomes the default" if higher and iso_ok else "cnn stays the default"
    return out


def main(argv=None) -> int:
    from drake_grasp.results import print_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", help="the folder holding the ten runs")
    p.add_argument("--out", default=None, help="also write the decision as JSON here")
    args = p.parse_args(argv)
    try:
        result = decide(Path(args.root))
    except (FileNotFoundError, ValueError, KeyError) as e:
        sys.exit(f"fcn_default_decision: {e}")
    print_json(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
