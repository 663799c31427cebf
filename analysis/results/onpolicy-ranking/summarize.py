"""The table of README.md in this folder: for each shipped grid net (and the default's
view averages), the ranking on the dataset's held-out pile images (`analysis/cnn_eval.py`,
1,000 ranking images) beside the ranking on the closed loop's own states
(`analysis/onpolicy_ranking.py score`), and which of the two orders the pairs of nets
whose clutter grasp rates were compared in closed loop (`CLOSED_LOOP_PAIRS`) as the
closed loop did.

    python analysis/results/onpolicy-ranking/summarize.py > analysis/results/onpolicy-ranking/summary.md
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT = "cnn-grid-bn12500-ep3"
NETS = ["cnn-grid", "cnn-grid-bn", "cnn-grid-bn12", "cnn-grid-bn12-ep5", "cnn-grid-bn12500",
        "cnn-grid-bn12500-ep3", "cnn-grid-bn12500-ep3+d4", "cnn-grid-bn12500-ep3+mirror"]
# (better, worse, what the closed loop measured, Fisher's two-sided p): each pair run side
# by side on the same fresh seeds (the models' READMEs; the last: ../cnn-view-average/).
CLOSED_LOOP_PAIRS = [
    ("cnn-grid-bn", "cnn-grid", "clutter 136/160 vs 136/163, p 0.76; models/cnn-grid-bn"),
    ("cnn-grid-bn12", "cnn-grid-bn", "clutter + shift 270/312 vs 246/294, p 0.36; models/cnn-grid-bn12"),
    ("cnn-grid-bn12-ep5", "cnn-grid-bn12", "clutter + shift 258/289 vs 251/292, p 0.26; models/cnn-grid-bn12-ep5"),
    ("cnn-grid-bn12500", "cnn-grid-bn12-ep5", "clutter + shift 257/282 vs 239/282, p 0.027; models/cnn-grid-bn12500"),
    ("cnn-grid-bn12500-ep3", "cnn-grid-bn12500", "clutter + shift 262/287 vs 241/278, p 0.11; models/cnn-grid-bn12500-ep3"),
    ("cnn-grid-bn12500-ep3", "cnn-grid-bn12500-ep3+d4", "clutter 347/396 vs 335/410, p 0.024; ../cnn-view-average"),
]


def load() -> dict:
    rows = {}
    for net in NETS:
        dataset = json.loads((HERE / "dataset" / f"{net}.json").read_text())["ranking"]
        base, _, name = net.partition("+")
        name = name or "none"
        # the default's on-policy scores, with its views, are in one file
        onpolicy = json.loads((HERE / ("plain_states_views.json" if base == DEFAULT
                                       else f"onpolicy/{net}.json")).read_text())
        low = [b for b in onpolicy["by_hand_height"] if b["range_m"][1] <= 0.06]
        rows[net] = {
            "dataset_spearman": dataset["spearman_mean"],
            "dataset_regret_median_mm": 1e3 * dataset["regret_median_m"],
            "onpolicy_spearman": onpolicy["all"][name]["spearman_mean"],
            "onpolicy_regret_median_mm": onpolicy["all"][name]["regret_median_mm"],
            "onpolicy_top1": onpolicy["all"][name]["top1_within_1cm"],
            "onpolicy_low_spearman": low[0][name]["spearman_mean"] if low else float("nan"),
            "onpolicy_failed_spearman": onpolicy["by_outcome"]["failed"][name]["spearman_mean"]}
    return rows


METRICS = [("dataset_spearman", "dataset piles: Spearman", +1),
           ("dataset_regret_median_mm", "dataset piles: median regret mm", -1),
           ("onpolicy_spearman", "closed-loop states: Spearman", +1),
           ("onpolicy_regret_median_mm", "closed-loop states: median regret mm", -1),
           ("onpolicy_top1", "closed-loop states: top-1 within 1 cm", +1),
           ("onpolicy_low_spearman", "closed-loop states, hand below 6 cm: Spearman", +1)]


def main() -> int:
    rows = load()
    cols = [m for m in METRICS]
    print("| net | " + " | ".join(label for _, label, _ in cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for net, r in rows.items():
        print(f"| {net} | " + " | ".join(
            f"{r[k]:.1f}" if k.endswith("_mm") else f"{r[k]:.3f}" for k, _, _ in cols) + " |")
    print()
    print("| closed loop: better > worse | " + " | ".join(label for _, label, _ in cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    agree = {k: 0 for k, _, _ in cols}
    for better, worse, what in CLOSED_LOOP_PAIRS:
        marks = []
        for k, _, sign in cols:
            ok = sign * (rows[better][k] - rows[worse][k]) > 0
            agree[k] += ok
            marks.append("yes" if ok else "**no**")
        print(f"| {better} > {worse} ({what}) | " + " | ".join(marks) + " |")
    print("| agrees with the closed loop | " + " | ".join(
        f"{agree[k]} of {len(CLOSED_LOOP_PAIRS)}" for k, _, _ in cols) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
