"""Where the 8-view average helps and where it hurts: the controller's ranking metrics on
the held-out piles (`data/clutter_test`, the 1,000 ranking images of
`analysis/cnn_eval.py`: same images, same 128 candidates each, seed 0) for the default
net on the image as shown and with `views="d4"`, split by the hand's height above the
table and by how near the best candidate is to a true grasp.

    python analysis/results/cnn-view-average/by_height.py --test-data data/clutter_test \
        --out analysis/results/cnn-view-average/by_height.json
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from drake_grasp.geometry.actions import apply_actions
from drake_grasp.learning.cnn_metrics import regret_m, sample_image_indices, spearman
from drake_grasp.learning.dataset_shards import DepthGraspDataset
from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
from drake_grasp.policies.decisions import sample_candidates
from drake_grasp.core.files import print_json
from drake_grasp.policies.evaluator import load_cnn, score_candidates

HEIGHT_EDGES_M = (0.0, 0.06, 0.09, 0.12, 0.15, 1.0)  # the grasp frame's z above the table
BEST_EDGES_M = (0.0, 0.01, 0.03, 0.06, 1.0)  # the best candidate's true distance


def per_image(test_data: str, images: int, seed: int = 0) -> dict:
    """Per ranking image: hand height, the candidates' true distances and both arms'
    predictions (the sampling of `cnn_metrics.ranking_metrics`, so the same images and
    candidates as `analysis/cnn_eval.py`)."""
    net = load_cnn("")
    data = DepthGraspDataset(test_data)
    rng = np.random.default_rng([seed, 11])
    rows = {"z": [], "true": [], "plain": [], "d4": []}
    for index in sample_image_indices(len(data), images, seed):
        rec = data.image_record(int(index))
        if len(rec["grasp_xy_theta"]) == 0:
            continue
        pose = np.asarray(rec["hand_pose"], float)
        actions = sample_candidates(rng, 128, xy_m=0.04, theta_deg=45.0)
        rows["true"].append(distance_to_nearest_grasp(
            apply_actions(pose[[0, 1, 3]][None], actions[None])[0], rec["grasp_xy_theta"]))
        rows["z"].append(pose[2])
        for arm in ("plain", "d4"):
            rows[arm].append(score_candidates(net, rec["depth"], actions,
                                              views="none" if arm == "plain" else arm))
    return {k: np.array(v) for k, v in rows.items()}


def metrics(true: np.ndarray, pred: np.ndarray) -> dict:
    regret = regret_m(pred, true)
    return {"images": len(true), "spearman_mean": float(np.nanmean(spearman(pred, true))),
            "regret_mean_mm": 1e3 * float(regret.mean()),
            "regret_median_mm": 1e3 * float(np.median(regret)),
            "top1_within_1cm": float(np.mean(regret <= 0.01))}


def split(rows: dict, key: np.ndarray, edges) -> list:
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (key >= lo) & (key < hi)
        if m.any():
            out.append({"range_m": [lo, hi], **{arm: metrics(rows["true"][m], rows[arm][m])
                                                for arm in ("plain", "d4")}})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--test-data", required=True)
    p.add_argument("--images", type=int, default=1000)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if not Path(args.test_data).is_dir():
        sys.exit(f"by_height: --test-data {args.test_data}: no such folder")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    rows = per_image(args.test_data, args.images)
    print_json({"test_data": args.test_data, "images": len(rows["z"]),
                "all": {arm: metrics(rows["true"], rows[arm]) for arm in ("plain", "d4")},
                "by_hand_height": split(rows, rows["z"], HEIGHT_EDGES_M),
                "by_best_true_distance": split(rows, rows["true"].min(axis=1), BEST_EDGES_M),
                "seconds": time.perf_counter() - t0}, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
