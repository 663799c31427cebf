"""Scores distance-CNN weights on a labelled test set: the test L1 over every labelled
offset (and per bin of the true distance), and the within-image ranking metrics
(`drake_grasp.cnn_metrics`), as `train` reports them after each epoch. Puts weights
trained on different sets on one test set.

    git show a027dc1:models/cnn/weights.safetensors > w400.safetensors   # the 400-scene weights
    python analysis/cnn_eval.py --weights w400.safetensors \
        --test-data data/paper_test --out analysis/results/cnn-paper-scale/400-scene-weights_on_paper_test.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from drake_grasp.cnn_metrics import ranking_metrics
from drake_grasp.network import MirrorAveragedCNN, load_weights
from drake_grasp.training import ChunkCache, ShardSet

# Bins of the true distance [mm] for the L1 breakdown: near a grasp (what the controller's
# last steps need), the middle, and far from every grasp (most of the labels).
LABEL_BINS_MM = (0, 30, 60, 100, 150, float("inf"))


def l1_by_label(model, data: ShardSet, *, batch_images: int = 200) -> tuple[float, list[dict]]:
    """One pass over every labelled offset: the mean absolute error [m] (what `train`'s
    `evaluate_l1` reports), and the error [mm] and label count per bin of the true
    distance."""
    import numpy as np

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


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", required=True, help="a weights.safetensors file")
    parser.add_argument("--test-data", required=True, help="a `generate` folder (test split)")
    parser.add_argument("--ranking-images", type=int, default=200,
                        help="test images for the ranking metrics (default 200, as train)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--mirror", action="store_true",
                        help="score as the mean of the image and its mirror image "
                             "(network.MirrorAveragedCNN)")
    parser.add_argument("--out", required=True, help="JSON file to write")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    model, _ = load_weights(args.weights)
    if args.mirror:
        model = MirrorAveragedCNN(model)
    t0 = time.perf_counter()
    data = ShardSet(args.test_data, ChunkCache(int(2e9)))
    l1, by_label = l1_by_label(model, data)
    ranking = ranking_metrics(model, args.test_data, images=args.ranking_images, seed=0)
    out = {"weights": str(args.weights), "mirror_averaged": bool(args.mirror),
           "test_data": str(args.test_data),
           "num_test_images": len(data), "test_l1_m": l1, "l1_by_label": by_label,
           "ranking": ranking,
           "seconds": time.perf_counter() - t0}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k not in ("ranking", "l1_by_label")}))
    return out


if __name__ == "__main__":
    main()
