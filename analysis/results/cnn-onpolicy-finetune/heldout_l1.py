"""The training loss (masked L1 over every in-view grid node) of grid nets on a dense-label
folder: how well a fine-tune fits held-out closed-loop states, beside its train L1.

    python analysis/onpolicy_ranking.py labels data/onpolicy/train-grasps --only cnn-clutter-seed28 \
        --out data/onpolicy/val_grid
    python analysis/results/cnn-onpolicy-finetune/heldout_l1.py data/onpolicy/val_grid \
        models/cnn-grid-bn12500-ep3/weights.safetensors data/runs/onpolicy-c/epoch4.safetensors ...
"""
from __future__ import annotations

import json
import sys

import numpy as np
import torch


def heldout_l1(labels: str, weights: str, batch: int = 200) -> float:
    """Mean absolute error [m] over every labelled in-view node of every image, as
    `dense_training.train`'s loss counts them."""
    from drake_grasp.learning.dense_labels import LabelStore
    from drake_grasp.learning.dense_training import batch_tensors
    from drake_grasp.cnn.weights_io import load_weights
    from drake_grasp.world.station import gripper_frame_offsets

    net = load_weights(weights)[0].eval()
    store = LabelStore([labels])
    camera_z = float(gripper_frame_offsets()[2].translation()[2])
    total, count = 0.0, 0
    with torch.no_grad():
        for lo in range(0, store.n_images, batch):
            data = store.take(np.arange(lo, min(lo + batch, store.n_images)))
            images, target, mask = batch_tensors(net, data, net.config, camera_z, "cpu")
            err = (net.image_features(images) - target).abs()[mask]
            total += float(err.sum())
            count += int(err.numel())
    return total / count


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        sys.exit(__doc__)
    torch.set_num_threads(2)
    out = {"labels": argv[0], "l1_mm": {w: 1e3 * heldout_l1(argv[0], w) for w in argv[1:]}}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
