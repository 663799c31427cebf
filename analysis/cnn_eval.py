"""Scores distance-CNN weights on a labelled test set: the test L1 over every labelled
offset (and per bin of the true distance), and the within-image ranking metrics
(`drake_grasp.learning.cnn_metrics`), as `train` reports them after each epoch. Puts weights
trained on different sets on one test set.

    git show a027dc1:models/cnn/weights.safetensors > w400.safetensors   # the 400-scene weights
    python analysis/cnn_eval.py --weights w400.safetensors \
        --test-data data/paper_test --out analysis/results/cnn-paper-scale/400-scene-weights_on_paper_test.json

Several files separated by commas score as their mean (what `controller.weights: A,B`
does in an episode, `evaluator.CnnEnsemble`); the members must share the input config.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from torch import nn

from drake_grasp.learning.cnn_metrics import l1_by_label, ranking_metrics
from drake_grasp.cnn.mirror import MirrorAveragedCNN
from drake_grasp.cnn.weights_io import load_weights
from drake_grasp.learning.common import ChunkCache, ShardSet


class MeanCNN(nn.Module):
    """Distance CNNs of one input config scored as their mean, with the interface the
    metrics use (`preprocess`, `forward_factored`, `image_features`, `score_actions`)."""

    def __init__(self, members) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)
        first = self.members[0].config
        for i, m in enumerate(self.members[1:], 1):
            for key in ("image_size", "depth_reference", "depth_offset_m", "depth_scale_m",
                        "depth_clip_near_m", "depth_clip_far_m"):
                if getattr(m.config, key) != getattr(first, key):
                    raise ValueError(f"--weights: member {i} has {key} = "
                                     f"{getattr(m.config, key)!r}, member 0 "
                                     f"{getattr(first, key)!r}; expected one input config")
        self.config = first

    @property
    def dtype(self) -> torch.dtype:
        return self.members[0].dtype

    def preprocess(self, depth):
        return self.members[0].preprocess(depth)

    def forward_factored(self, images, actions):
        return torch.stack([m.forward_factored(images, actions) for m in self.members]).mean(0)

    def image_features(self, images):
        return [m.image_features(images) for m in self.members]

    def score_actions(self, features, actions):
        return torch.stack([m.score_actions(f, actions).reshape(-1)
                            for m, f in zip(self.members, features)]).mean(0)


def view_averaged(net, views: str):
    """A grid net whose distance grid is the mean over the symmetric views of each image
    (`dense_training.view_averaged_grids`: "mirror" 2, "d4" 8 views, each view's grid
    turned back to the image as shown). The net is copied (sharing its tensors);
    `views="none"` returns it unchanged."""
    import copy
    import types

    from drake_grasp.cnn.views import AUGMENTATIONS, view_averaged_grids

    if views not in AUGMENTATIONS:
        raise SystemExit(f"--views: expected one of {sorted(AUGMENTATIONS)}, got {views!r}")
    if len(AUGMENTATIONS[views]) == 1:
        return net
    if not getattr(net, "grid", False):
        raise SystemExit(f"--views {views}: needs grid-head nets (the whole grid turns with "
                         f"the view), got a {net.config.action_fusion!r} net")
    plain = copy.copy(net)
    out = copy.copy(net)

    def image_features(self, images):
        return view_averaged_grids(plain, images, views)

    out.image_features = types.MethodType(image_features, out)
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", required=True, help="a weights.safetensors file, or several "
                        "separated by commas (scored as their mean)")
    parser.add_argument("--test-data", required=True, help="a `generate` folder (test split)")
    parser.add_argument("--ranking-images", type=int, default=200,
                        help="test images for the ranking metrics (default 200, as train)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--mirror", action="store_true",
                        help="score as the mean of the image and its mirror image "
                             "(network.MirrorAveragedCNN)")
    parser.add_argument("--views", default="none", choices=("none", "mirror", "d4"),
                        help="grid nets: average each image's grid over its mirror image "
                             "(mirror) or also its quarter turns about the optical axis (d4), "
                             "each turned back (README, *The camera's symmetries*)")
    parser.add_argument("--out", required=True, help="JSON file to write")
    args = parser.parse_args(argv)
    if args.mirror and args.views != "none":
        raise SystemExit("--mirror and --views: choose one (--views mirror averages the "
                         "grid over the mirror image)")
    torch.set_num_threads(max(1, args.threads))
    files = [f.strip() for f in args.weights.split(",")]
    if not all(files):
        raise SystemExit(f"--weights: {args.weights!r} has an empty item; expected FILE or "
                         "FILE,FILE,...")
    models = [view_averaged(load_weights(f)[0], args.views) for f in files]
    if args.mirror:  # each member mirror-averaged, as in an episode
        models = [MirrorAveragedCNN(m) for m in models]
    model = models[0] if len(models) == 1 else MeanCNN(models)
    t0 = time.perf_counter()
    data = ShardSet(args.test_data, ChunkCache(int(2e9)))
    l1, by_label = l1_by_label(model, data)
    ranking = ranking_metrics(model, args.test_data, images=args.ranking_images, seed=0)
    out = {"weights": str(args.weights), "mirror_averaged": bool(args.mirror),
           **({"views": args.views} if args.views != "none" else {}),
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
