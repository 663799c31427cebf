"""How closely the ONNX export of the shipped CNN follows torch's fast path.

    python analysis/onnx_agreement.py [--seeds 5] [--weights W]

Exports the weights with both exporters (dynamo when onnxscript is installed, and
TorchScript) into a temporary folder and scores the inputs of tests/test_onnx.py (random
depth images in 0.1-1.2 m with +inf and 0 pixels; 3 images per seed, 128 actions within
+-4 cm / +-45 deg and 128 within +-10 cm / +-90 deg) with onnxruntime and with torch.
Prints, per exporter, the number of distances compared, the largest |difference| [m] and
the largest feature difference relative to the largest feature. Needs '.[onnx-export]'.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np


def _inputs(seed: int, images: int = 3, k: int = 128):
    # The same draw as tests/test_onnx.py's _random_inputs.
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.1, 1.2, (images, 64, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.05] = np.inf
    depth[rng.random(depth.shape) < 0.03] = 0.0
    near = np.column_stack([rng.uniform(-0.04, 0.04, (k, 2)), rng.uniform(-45, 45, k)])
    wide = np.column_stack([rng.uniform(-0.1, 0.1, (k, 2)), rng.uniform(-90, 90, k)])
    return depth, np.concatenate([near, wide]).astype(np.float32)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=5, help="input draws (seeds 1..N)")
    p.add_argument("--weights", default="", help="safetensors weights (default: shipped)")
    args = p.parse_args(argv)

    import torch

    from drake_grasp.onnx_export import export_onnx
    from drake_grasp.onnx_runtime import OnnxDistanceModel
    from drake_grasp.systems.evaluator import load_cnn

    torch_model = load_cnn(args.weights)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for exporter in ("dynamo", "torchscript"):
            path = Path(tmp) / f"{exporter}.onnx"
            try:
                export_onnx(out=path, weights=args.weights, exporter=exporter)
            except Exception as e:  # noqa: BLE001 - e.g. onnxscript missing for dynamo
                print(f"{exporter}: export failed: {e}", file=sys.stderr)
                continue
            model = OnnxDistanceModel(path)
            n, dist_err, feat_err = 0, 0.0, 0.0
            for seed in range(1, args.seeds + 1):
                depth, actions = _inputs(seed)
                images = model.preprocess(depth)
                features = model.image_features(images)
                with torch.inference_mode():
                    tf = torch_model.image_features(torch.from_numpy(images))
                    feat_err = max(feat_err, float(np.abs(features - tf.numpy()).max()
                                                   / np.abs(tf.numpy()).max()))
                    for i in range(len(depth)):
                        want = torch_model.score_actions(tf[i], torch.from_numpy(actions)).numpy()
                        got = model.score_actions(features[i], actions)
                        dist_err = max(dist_err, float(np.abs(got - want).max()))
                        n += len(actions)
            rows[exporter] = {"distances": n, "max_abs_difference_m": dist_err,
                              "max_feature_difference_relative": feat_err}
    print(json.dumps(rows, indent=1))
    return 0 if rows else 1


if __name__ == "__main__":
    raise SystemExit(main())
