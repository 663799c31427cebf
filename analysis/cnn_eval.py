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

from drake_grasp.cnn_metrics import l1_by_label, ranking_metrics
from drake_grasp.network import MirrorAveragedCNN, load_weights
from drake_grasp.training import ChunkCache, ShardSet

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
