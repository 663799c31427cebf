"""What the controller needs from the distance CNN, measured on a labelled dataset.

L1 says how far the predicted distances are from the labels on average. Algorithm 1 only
ever *ranks* candidates: on each step it scores K actions sampled near the current pose
on one image and moves toward the least predicted distance. So the measure that matters
is the order of the predictions among the candidates of one image:

- `spearman`: Spearman's rank correlation between predicted and true distance among the
  K candidates of one image, drawn as the controller draws them (`policies.
  sample_candidates` with the controller's `num_candidates`, `sample_xy_m` and
  `sample_theta_deg`); mean and median over images. The true distances of these new
  candidates come from the scene's ground-truth grasps stored in the shard
  (`grasps.distance_to_nearest_grasp`, the dataset's own label function).
- `spearman_labelled`: the same among the image's stored labelled offsets (10 per image,
  drawn over the whole view).
- `regret_m`: the true distance of the candidate the CNN ranks first minus the least true
  distance among the K (0 when it picks the best one); mean and median.
- `top1_within_1cm`: share of images whose top-ranked candidate is within 1 cm (true
  distance) of the best candidate's.
- `l1_m`: mean |predicted - true| over the K candidates.

Images are a seeded random sample of the set; same seed, same images and candidates.
Images of scenes stored without grasps are skipped (`images` counts those used).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from drake_grasp.geometry.actions import apply_actions
from drake_grasp.learning.dataset_shards import DepthGraspDataset
from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.policies.decisions import sample_candidates


def _ranks(x: np.ndarray) -> np.ndarray:
    """Ranks along the last axis, ties sharing their mean rank (as Spearman's rho needs)."""
    from scipy.stats import rankdata

    return rankdata(x, axis=-1)


def spearman(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Spearman's rho between rows of `a` and `b` (shape (N, K) -> (N,)); NaN for a row
    that is constant in either (no order to compare)."""
    ra, rb = _ranks(np.asarray(a, float)), _ranks(np.asarray(b, float))
    ra -= ra.mean(axis=-1, keepdims=True)
    rb -= rb.mean(axis=-1, keepdims=True)
    den = np.sqrt((ra ** 2).sum(-1) * (rb ** 2).sum(-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (ra * rb).sum(-1) / np.where(den > 0, den, 1.0), np.nan)


def sample_image_indices(num_images: int, count: int, seed: int) -> np.ndarray:
    """`count` distinct image indices (sorted), or all of them when the set is smaller."""
    if count >= num_images:
        return np.arange(num_images)
    return np.sort(np.random.default_rng([seed, 7]).choice(num_images, count, replace=False))


def regret_m(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Per image (row): the true distance [m] of the candidate ranked best by `pred` minus
    the least true distance among its candidates (0: the ranking's top is the best)."""
    pred, true = np.asarray(pred), np.asarray(true)
    return true[np.arange(len(true)), pred.argmin(axis=1)] - true.min(axis=1)


def ranking_metrics(model: DistanceCNN, data_dir: str | Path, *, images: int = 500,
                    candidates: int = 128, xy_m: float = 0.04, theta_deg: float = 45.0,
                    seed: int = 0, device: str | torch.device = "cpu") -> dict:
    """The within-image ranking quality of `model` on a labelled dataset (see the module
    docstring for each key). Candidate defaults are the controller's
    (`ControllerConfig.num_candidates`, `sample_xy_m`, `sample_theta_deg`).

    Raises:
        ValueError: for `images` or `candidates` < 2.
    """
    if images < 1:
        raise ValueError(f"images: expected >= 1, got {images}")
    if candidates < 2:
        raise ValueError(f"candidates: expected >= 2 (a ranking), got {candidates}")
    data = DepthGraspDataset(data_dir)
    chosen = sample_image_indices(len(data), images, seed)
    rng = np.random.default_rng([seed, 11])
    pred, true, pred_lab, true_lab = [], [], [], []
    model = model.to(device).eval()
    with torch.inference_mode():
        for index in chosen:
            rec = data.image_record(int(index))
            if len(rec["grasp_xy_theta"]) == 0:
                continue  # no true grasp stored (not in generated data): no distances
            hand = np.asarray(rec["hand_pose"], float)[[0, 1, 3]]
            actions = sample_candidates(rng, candidates, xy_m=xy_m, theta_deg=theta_deg)
            true.append(distance_to_nearest_grasp(apply_actions(hand[None], actions[None])[0],
                                                  rec["grasp_xy_theta"]))
            feats = model.image_features(model.preprocess(rec["depth"][None]).to(device))
            both = np.concatenate([actions, rec["offsets"]]).astype(np.float32)
            p = model.score_actions(feats, both).float().cpu().numpy().reshape(-1)
            pred.append(p[:candidates])
            pred_lab.append(p[candidates:])
            true_lab.append(rec["labels"])
    if not pred:
        return {"images": 0, "candidates": int(candidates), "seed": int(seed)}
    pred, true = np.array(pred), np.array(true)
    rho = spearman(pred, true)
    rho_lab = spearman(np.array(pred_lab), np.array(true_lab))
    best = true.min(axis=1)
    regret = regret_m(pred, true)
    return {
        "images": len(pred), "candidates": int(candidates), "seed": int(seed),
        "spearman_mean": float(np.nanmean(rho)), "spearman_median": float(np.nanmedian(rho)),
        "spearman_labelled_mean": float(np.nanmean(rho_lab)),
        "regret_mean_m": float(regret.mean()), "regret_median_m": float(np.median(regret)),
        "top1_within_1cm": float(np.mean(regret <= 0.01)),
        "l1_m": float(np.abs(pred - true).mean()),
        "best_true_mean_m": float(best.mean()),
    }


# Bins of the true distance [mm] for the L1 breakdown: near a grasp (what the controller's
# last steps need), the middle, and far from every grasp (most of the labels).
LABEL_BINS_MM = (0, 30, 60, 100, 150, float("inf"))


def l1_by_label(model, data, *, batch_images: int = 200) -> tuple[float, list[dict]]:
    """One pass over every labelled offset of `data` (a `common.ShardSet`): the mean
    absolute error [m] (what `train`'s `evaluate_l1` reports), and the error [mm] and
    label count per bin of the true distance (`LABEL_BINS_MM`)."""
    edges = np.array(LABEL_BINS_MM) / 1000.0
    total = np.zeros(len(edges) - 1)
    count = np.zeros(len(edges) - 1, dtype=np.int64)
    model.eval()
    with torch.no_grad():
        for start in range(0, len(data), batch_images):
            depth, offsets, labels = data.gather(np.arange(start, min(start + batch_images,
                                                                      len(data))))
            pred = model.forward_factored(model.preprocess(depth),
                                          torch.as_tensor(offsets, dtype=model.dtype))
            err = (pred.double().numpy() - labels).ravel()
            k = np.digitize(labels.ravel(), edges[1:-1])
            np.add.at(total, k, np.abs(err))
            np.add.at(count, k, 1)
    upper = [b if np.isfinite(b) else None for b in LABEL_BINS_MM]  # None: no upper bound
    bins = [{"label_mm": [upper[i], upper[i + 1]], "labels": int(count[i]),
             "l1_mm": float(1000 * total[i] / count[i]) if count[i] else None}
            for i in range(len(count))]
    return float(total.sum() / max(count.sum(), 1)), bins
