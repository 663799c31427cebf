"""Puts training runs of the distance CNN side by side, epoch by epoch: train and test
L1, the within-image Spearman and the regret of the top-ranked candidate, as each run's
`metrics.json` has them. Writes `summary.json`, `comparison.png` and a copy of each
run's `metrics.json` and `train_config.json` under OUT/NAME/.

    python analysis/cnn_fusion_compare.py --out analysis/results/cnn-window \\
        tiled=data/fusion_tiled window=data/fusion_window context=data/fusion_context
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

COLUMNS = (  # key in the summary, label, how to read it from one epoch's metrics
    ("train_l1_mm", "train L1 [mm]", lambda e: 1000 * e["train_l1_m"]),
    ("test_l1_mm", "test L1 [mm]", lambda e: 1000 * e["test_l1_m"]),
    ("spearman_mean", "Spearman, mean", lambda e: e["ranking"]["spearman_mean"]),
    ("spearman_median", "Spearman, median", lambda e: e["ranking"]["spearman_median"]),
    ("regret_mean_mm", "regret of the top-ranked candidate, mean [mm]",
     lambda e: 1000 * e["ranking"]["regret_mean_m"]),
    ("top1_within_1cm", "top-ranked within 1 cm of the best", lambda e: e["ranking"]["top1_within_1cm"]),
)


def _run(arg: str) -> tuple[str, Path]:
    name, sep, folder = arg.partition("=")
    if not sep or not name or not folder:
        raise argparse.ArgumentTypeError(f"{arg!r}: expected NAME=RUN_DIR")
    path = Path(folder)
    if not (path / "metrics.json").is_file():
        raise argparse.ArgumentTypeError(f"{path / 'metrics.json'}: no such file (a `train` run)")
    return name, path


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=_run, metavar="NAME=RUN_DIR",
                        help="a name and a `drake-grasp train` output folder")
    parser.add_argument("--out", required=True, help="folder to write")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary = {}
    for name, run in args.runs:
        metrics = json.loads((run / "metrics.json").read_text())
        config = json.loads((run / "train_config.json").read_text())
        summary[name] = {
            "network": config["network"],
            "train_manifest_sha256": config.get("train_manifest_sha256"),
            "test_manifest_sha256": config.get("test_manifest_sha256"),
            "epochs": [{"epoch": e["epoch"], "iterations": e.get("iterations"),
                        "seconds": round(e["seconds"], 1),
                        **{key: round(read(e), 4) for key, _, read in COLUMNS}}
                       for e in metrics["epochs"]],
        }
        (out / name).mkdir(exist_ok=True)
        for file in ("metrics.json", "train_config.json"):
            shutil.copyfile(run / file, out / name / file)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for ax, key in zip(axes, ("test_l1_mm", "spearman_mean", "regret_mean_mm", "top1_within_1cm")):
        label = next(lab for k, lab, _ in COLUMNS if k == key)
        for name, run in summary.items():
            epochs = [e["epoch"] for e in run["epochs"]]
            ax.plot(epochs, [e[key] for e in run["epochs"]], "o-", label=name)
        ax.set_xticks(sorted({e["epoch"] for r in summary.values() for e in r["epochs"]}))
        ax.set_xlabel("epoch")
        ax.set_title(label, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "comparison.png", dpi=110)
    for name, run in summary.items():
        for e in run["epochs"]:
            print(name, json.dumps(e))
    return summary


if __name__ == "__main__":
    main()
