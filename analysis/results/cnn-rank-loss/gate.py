"""PLAN.md's gate in this folder, applied to `cnn_eval.py` files: does a ranking-loss
fine-tune rank the held-out piles better than the default and than the same fine-tune
with the L1 alone, without losing the paper scenes?

    python analysis/results/cnn-rank-loss/gate.py analysis/results/cnn-rank-loss/eval \
        --out analysis/results/cnn-rank-loss/gate.json

Reads `{default,l1,rank01,rank05}_on_{clutter_test,paper_test}.json` from the folder.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ARMS = ("default", "l1", "rank01", "rank05")
CANDIDATES = ("rank01", "rank05")
SPEARMAN_OVER_DEFAULT = 0.05
SPEARMAN_OVER_L1 = 0.03
PAPER_L1_SLACK_M = 0.001


def read(folder: Path) -> dict:
    out = {}
    for arm in ARMS:
        piles = json.loads((folder / f"{arm}_on_clutter_test.json").read_text())
        paper = json.loads((folder / f"{arm}_on_paper_test.json").read_text())
        out[arm] = {"piles_spearman": piles["ranking"]["spearman_mean"],
                    "piles_regret_median_m": piles["ranking"]["regret_median_m"],
                    "piles_l1_m": piles["test_l1_m"],
                    "piles_ranking_images": piles["ranking"]["images"],
                    "paper_l1_m": paper["test_l1_m"],
                    "paper_spearman": paper["ranking"]["spearman_mean"]}
    return out


def gate(scores: dict) -> dict:
    d, l1 = scores["default"], scores["l1"]
    verdicts = {}
    for arm in CANDIDATES:
        s = scores[arm]
        checks = {
            "spearman_over_default": s["piles_spearman"] >= d["piles_spearman"] + SPEARMAN_OVER_DEFAULT,
            "spearman_over_l1": s["piles_spearman"] >= l1["piles_spearman"] + SPEARMAN_OVER_L1,
            "regret": s["piles_regret_median_m"] <= min(d["piles_regret_median_m"],
                                                         l1["piles_regret_median_m"]),
            "paper_l1": s["paper_l1_m"] <= d["paper_l1_m"] + PAPER_L1_SLACK_M}
        verdicts[arm] = {"checks": checks, "passed": all(checks.values())}
    passing = [a for a in CANDIDATES if verdicts[a]["passed"]]
    candidate = max(passing, key=lambda a: scores[a]["piles_spearman"]) if passing else None
    return {"scores": scores, "verdicts": verdicts, "candidate": candidate,
            "stage1": candidate is not None}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", type=Path)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    try:
        result = gate(read(args.folder))
    except FileNotFoundError as e:
        sys.exit(f"gate.py: {e.filename}: not found (score every arm with cnn_eval.py first)")
    from drake_grasp.core.files import print_json

    print_json(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
