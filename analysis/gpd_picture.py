"""Picture of one GPD detection: the sensor's image and the candidates on the cloud.

For a settled held-out scene (isolation or a 5-object pile), the GPD sensor's image at the
experiments' viewpoint (left) and, seen from above, the object cloud with every
candidate that passed the geometric filters coloured by the classifier's probability and
the selected grasp drawn as its closing stroke (right).

    python analysis/gpd_picture.py --out analysis/results/gpd_detection.png
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drake_grasp.policies import gpd, gpd_ranking
    from drake_grasp.learning.gpd_training import experiment_view
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    library = load_library(None)
    fig, axes = plt.subplots(2, 2, figsize=(11, 10))
    for row, name in enumerate(("isolation", "clutter")):
        scenario = load_scenario(scenario_name=name)
        settled, X_WC, depth = experiment_view(scenario, args.seed, library)
        detector = gpd.make_detector(dataclasses.replace(scenario, seed=args.seed)).detector
        rng = np.random.default_rng([args.seed, 59])
        cloud = gpd.cloud_from_depth(depth, fov_y_deg=scenario.gpd.fov_y_deg, X_WC=X_WC,
                                     depth_min_m=scenario.gpd.depth_min_m,
                                     depth_max_m=scenario.gpd.depth_max_m,
                                     center_xy=settled.center_xy_m)
        hands = gpd.sample_hands(cloud, rng, detector.search)
        prob = detector.classifier.probabilities(gpd.grasp_images(cloud, hands.poses))
        order = gpd_ranking.select(hands.poses, prob, detector.selection)
        shown = np.where(np.isfinite(depth) & (depth < scenario.gpd.depth_max_m), depth, np.nan)
        ax = axes[row, 0]
        im = ax.imshow(shown, cmap="viridis")
        fig.colorbar(im, ax=ax, fraction=0.04, label="depth [m]")
        ax.set_title(f"{name}: GPD sensor image at the viewpoint", fontsize=10)
        ax.axis("off")
        ax = axes[row, 1]
        ax.scatter(cloud.points[:, 0], cloud.points[:, 1], s=0.2, c="0.75")
        c = hands.poses[:, :3, 3]
        sc = ax.scatter(c[:, 0], c[:, 1], s=4, c=prob, cmap="coolwarm", vmin=0, vmax=1)
        fig.colorbar(sc, ax=ax, fraction=0.04, label="classifier probability")
        if len(order):
            X = hands.poses[order[0]]
            x = X[:3, 0] * 0.0425
            ax.plot([X[0, 3] - x[0], X[0, 3] + x[0]], [X[1, 3] - x[1], X[1, 3] + x[1]],
                    "k-", lw=3, label="selected grasp (closing stroke)")
            tilt = np.degrees(np.arccos(-X[2, 2]))
            ax.legend(loc="upper right", fontsize=8)
            ax.set_title(f"{len(hands)} candidates, {len(order)} detections\nselected: "
                         f"p = {prob[order[0]]:.2f}, tilt {tilt:.0f} deg (world frame, from above)",
                         fontsize=10)
        else:
            ax.set_title(f"{len(hands)} candidates, no detection", fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
