"""learning.png: the prototype runs' held-out metrics against training batches."""
import json
from pathlib import Path

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt

HERE = Path(__file__).parent
RUNS = [("paper_2e-4", "paper trunk, Adam 2e-4"), ("paper_1e-3", "paper trunk, Adam 1e-3"),
        ("bn_1e-3", "paper trunk + BatchNorm, 1e-3"), ("deep_1e-3", "3 convs + BatchNorm, 1e-3"),
        ("ft_paper_1e-3", "shipped, fine-tuned 1e-3"), ("ft_pkgbn_1e-3", "shipped + BatchNorm (identity start), 1e-3")]
fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
for name, label in RUNS:
    log = json.loads((HERE / "prototype" / f"{name}.json").read_text())["log"]
    steps = [r["step"] for r in log]
    style = "--" if name.startswith("ft_") else "-"
    for ax, key in zip(axes, ("test_l1_mm", "spearman", "top1_1cm")):
        ax.plot(steps, [r[key] for r in log], style, marker="o", ms=3, label=label)
for ax, title in zip(axes, ("held-out L1 [mm] (in-view nodes)", "within-image Spearman (candidate region)",
                            "top-ranked node within 1 cm of the best")):
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("batches of 50 images (near0_grid: 1,200 per epoch)")
    ax.grid(alpha=0.3)
axes[0].set_ylim(24, 45)
axes[1].set_ylim(0.2, 0.7)
axes[0].legend(fontsize=7)
fig.tight_layout()
fig.savefig(HERE / "learning.png", dpi=110)
