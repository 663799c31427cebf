"""How a half-precision copy of a distance CNN changes the controller's decisions, offline.

    drake-grasp generate --out /tmp/fp16data --scenes 12 --split test --seed 5 \\
        --images-per-scene 10 --scenes-per-shard 4
    python analysis/half_precision_check.py --data /tmp/fp16data \\
        --weights models/cnn-grid-bn12500-ep3/weights.safetensors \\
        --half models/cnn-grid-bn12500-ep3-fp16/weights.safetensors

Scores, on every depth image of a dataset, the same `--candidates` candidate actions
(CTR's default sampling range, one seeded Generator) with both nets through the
controller's own scoring (`evaluator.score_candidates`), and prints one JSON object: the
largest and median |difference| of a predicted distance, how many of the decisions pick
another candidate (the argmin), and the gap between the best and second-best candidate
under the full-precision net (the margin a rounding must overcome to change a decision).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def depth_images(folder: Path) -> np.ndarray:
    """Every depth image of a dataset folder's shards, (N, 64, 64) float32."""
    import h5py

    shards = sorted(folder.glob("shard-*.h5"))
    if not shards:
        raise FileNotFoundError(f"{folder}: no shard-*.h5 files (a `drake-grasp generate` folder)")
    images = []
    for shard in shards:
        with h5py.File(shard, "r") as h:
            if "depth" not in h:
                raise KeyError(f"{shard}: no 'depth' dataset (keys: {sorted(h.keys())})")
            images.append(np.asarray(h["depth"], np.float32))
    return np.concatenate(images).reshape(-1, 64, 64)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="dataset folder (drake-grasp generate)")
    p.add_argument("--weights", required=True, help="the full-precision weights file")
    p.add_argument("--half", required=True, help="its half-precision copy")
    p.add_argument("--candidates", type=int, default=128, help="candidates per image")
    p.add_argument("--seed", type=int, default=0, help="seed of the candidates' Generator")
    args = p.parse_args(argv)

    from drake_grasp.config.sections import ControllerConfig
    from drake_grasp.policies.decisions import sample_candidates
    from drake_grasp.policies.evaluator import load_cnn, score_candidates

    full, half = load_cnn(args.weights, threads=1), load_cnn(args.half, threads=1)
    controller = ControllerConfig()
    rng = np.random.default_rng(args.seed)
    diffs, flips, gaps = [], 0, []
    images = depth_images(Path(args.data))
    for depth in images:
        actions = sample_candidates(rng, args.candidates, xy_m=controller.sample_xy_m,
                                    theta_deg=controller.sample_theta_deg)
        a, b = score_candidates(full, depth, actions), score_candidates(half, depth, actions)
        diffs.append(np.abs(a - b))
        flips += int(np.argmin(a) != np.argmin(b))
        best_two = np.sort(a)[:2]
        gaps.append(best_two[1] - best_two[0])
    diffs = np.concatenate(diffs)
    print(json.dumps({
        "images": len(images), "candidates_per_image": args.candidates,
        "max_abs_difference_mm": round(1000 * float(diffs.max()), 4),
        "median_abs_difference_mm": round(1000 * float(np.median(diffs)), 5),
        "decisions_changed": flips,
        "median_best_second_gap_mm": round(1000 * float(np.median(gaps)), 3),
        "min_best_second_gap_mm": round(1000 * float(np.min(gaps)), 5)}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
