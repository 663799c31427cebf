"""How well each net orders pairs of nearby grid nodes (the pairs `train-grid
--rank-weight` trains on: `dense_rank.rank_pairs`) on dense-label folders - the
training piles and scenes, and the held-out piles - to tell a net that cannot fit the
order from one that fits it and does not carry it to new piles.

    python analysis/results/cnn-rank-loss/pair_order.py --labels data/piles503_grid,data/rand15_grid,data/clutter_test_grid \
        --weights default=models/cnn-grid-bn12500-ep3/weights.safetensors,l1=data/runs/rank-l1/epoch3.safetensors,... \
        --out analysis/results/cnn-rank-loss/pair_order.json

For each folder and net, over up to 2,000 images (every image when fewer) with 1,024
pairs each (seed 0): the share of counted pairs (labels more than 2 mm apart, both nodes
in view) that the net orders as the labels do, and `pairwise_rank_loss` at scale 1 cm.
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from drake_grasp.learning.dense_labels import LabelStore
from drake_grasp.learning.dense_rank import pairwise_rank_loss, rank_pair_gaps, rank_pairs
from drake_grasp.learning.dense_training import batch_tensors
from drake_grasp.cnn.weights_io import load_weights
from drake_grasp.world.station import gripper_frame_offsets


def score(net, folder: str, *, images: int = 2000, batch: int = 50, seed: int = 0) -> dict:
    store = LabelStore([folder])
    rng = np.random.default_rng([seed, 0])
    idx = np.sort(rng.choice(store.n_images, min(images, store.n_images), replace=False))
    camera_z = float(gripper_frame_offsets()[2].translation()[2])
    agree = counted = 0
    loss_sum = 0.0
    net.eval()
    with torch.inference_mode():
        for k, start in enumerate(range(0, len(idx), batch)):
            part = idx[start:start + batch]
            images_t, target, mask = batch_tensors(net, store.take(part), net.config, camera_z, "cpu")
            pred = net.image_features(images_t)
            first, second = rank_pairs(net.config.grid_shape(), len(part), 1024,
                                       np.random.default_rng([seed, 1, k]))
            pred_gap, label_gap, valid = rank_pair_gaps(pred, target, mask, first, second,
                                                        margin_m=0.002)
            order = torch.sign(pred_gap) == torch.sign(label_gap)
            n = int(valid.sum())
            agree += int((order & valid).sum())
            counted += n
            if n:
                loss_sum += float(pairwise_rank_loss(pred, target, mask, first, second,
                                                     scale_m=0.01, margin_m=0.002)) * n
    return {"images": int(len(idx)), "pairs": counted, "order_agreement": agree / counted,
            "rank_loss": loss_sum / counted}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--labels", required=True, help="dense-label folders, comma-separated")
    p.add_argument("--weights", required=True, help="NAME=FILE pairs, comma-separated")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    nets = dict(item.split("=", 1) for item in args.weights.split(","))
    out = {}
    for name, path in nets.items():
        net = load_weights(path)[0]
        out[name] = {folder: score(net, folder) for folder in args.labels.split(",")}
        print(name, json.dumps(out[name]))
    from drake_grasp.core.files import atomic_write_text
    atomic_write_text(args.out, json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
