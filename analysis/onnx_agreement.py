"""How closely the ONNX export of the shipped CNN follows torch's fast path.

    python analysis/onnx_agreement.py [--seeds 5] [--weights W]

Exports the weights with both exporters (dynamo when onnxscript is installed, and
TorchScript) into a temporary folder and scores the inputs of tests/test_onnx.py
(`onnx_runtime.random_check_inputs`: 3 random depth images and 256 actions per seed) with
onnxruntime and with torch.
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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=5, help="input draws (seeds 1..N)")
    p.add_argument("--weights", default="", help="safetensors weights (default: shipped)")
    args = p.parse_args(argv)

    import torch

    from drake_grasp.cnn.onnx_export import export_onnx
    from drake_grasp.cnn.onnx_runtime import OnnxDistanceModel, random_check_inputs
    from drake_grasp.policies.evaluator import load_cnn

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
                depth, actions = random_check_inputs(seed)
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
