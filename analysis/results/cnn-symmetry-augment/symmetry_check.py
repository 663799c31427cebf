"""Which transform of the label grid goes with each symmetry of the image, by the net?

For each of the 8 symmetries of the square image (`dense_training.turn_images`: k quarter
turns about the optical axis, with or without a left-right flip), the net's grids on the
turned images are compared with the labels under each of the 32 candidate grid transforms
(the 8 symmetries of the (y, x) nodes x theta -> +-theta (+ 90 degrees)); the best one
should be `turn_grids(grid, k, flip)`, and its L1 says how far the net is from treating
the turned views as it treats the originals.

    python analysis/results/cnn-symmetry-augment/symmetry_check.py \
        --labels DENSE_LABELS_DIR --weights W [--images 1500] --out X.json
"""
import argparse
import itertools
import json

import numpy as np
import torch

from drake_grasp.learning.dense_labels import load_labels
from drake_grasp.cnn.views import turn_images
from drake_grasp.cnn.weights_io import load_weights


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--labels", required=True)
    ap.add_argument("--weights", default="models/cnn-grid-bn12500-ep3/weights.safetensors")
    ap.add_argument("--images", type=int, default=1500)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    data = load_labels([a.labels])
    idx = np.sort(np.random.default_rng(0).choice(len(data["depth"]), a.images, replace=False))
    depth = data["depth"][idx].astype(np.float32)
    grid = data["grid"][idx].astype(np.float32)
    net = load_weights(a.weights)[0].eval()
    t_bins = grid.shape[1]

    def grid_op(g, k, flip, sign, shift):
        g = np.rot90(g[..., ::-1] if flip else g, k, axes=(2, 3))
        out = np.empty_like(g)
        out[:, (sign * np.arange(t_bins) + shift) % t_bins] = g
        return out

    rows = []
    for k, flip in itertools.product(range(4), (False, True)):
        with torch.inference_mode():
            pred = net.image_features(net.preprocess(turn_images(depth, k, flip))).numpy()
        scores = []
        for k2, f2, sign, shift in itertools.product(range(4), (False, True), (1, -1),
                                                      (0, t_bins // 2)):
            g = grid_op(grid, k2, f2, sign, shift)
            m = np.isfinite(g)
            scores.append((float(np.abs(pred - g)[m].mean()), k2, f2, sign, shift))
        scores.sort()
        best, second = scores[0], scores[1]
        rows.append({"image_k": k, "image_flip": flip,
                     "best_grid_op": {"k": best[1], "flip": best[2], "theta_sign": best[3],
                                      "theta_shift_bins": best[4]},
                     "l1_mm": 1000 * best[0], "second_l1_mm": 1000 * second[0],
                     "matches_turn_grids": (best[1], best[2], best[3], best[4])
                     == (k, flip, -1 if flip else 1, (k % 2) * (t_bins // 2))})
        print(json.dumps(rows[-1]), flush=True)
    with open(a.out, "w") as f:
        json.dump({"labels": a.labels, "weights": a.weights, "images": a.images, "rows": rows},
                  f, indent=1)


if __name__ == "__main__":
    main()
