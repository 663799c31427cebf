"""Export of the distance CNN to ONNX, fast path kept: an image part and a head part.

`export_onnx` writes ``X.onnx`` (the image part, with the metadata) and ``X.head.onnx``
(the per-action head); `drake_grasp.cnn.onnx_runtime` describes the two files and runs them
with onnxruntime and numpy only. ``controller.weights: X.onnx`` selects that backend in
an episode (`drake_grasp.policies.evaluator.load_cnn`).

Needs torch, onnx and onnxruntime (``pip install 'drake_grasp[onnx-export]'``). With
onnxscript installed the default exporter is torch's dynamo-based one
(``torch.onnx.export(..., dynamo=True)``); without it, the TorchScript one
(``dynamo=False``). Both give the same numbers within float32 rounding.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import logging
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np
import torch
from torch import nn

import drake_grasp
from drake_grasp.core.assets import model_path
from drake_grasp.cnn.fcn import FCN_FORMAT, weights_format
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.cnn.weights_io import load_weights, tensors_sha256
from drake_grasp.cnn.onnx_runtime import ONNX_FORMAT, OnnxDistanceModel, head_path, probe_inputs
from drake_grasp.core.provenance import file_sha256

SHIPPED_WEIGHTS = "cnn/weights.safetensors"
"""Default weights, under `models_dir()`: the paper's tiled net (=
`systems.evaluator.PAPER_WEIGHTS`); the export covers the tiled fusion only, so the
episode's default, the grid head (`systems.evaluator.DEFAULT_WEIGHTS`), is not exported."""

EXPORTERS = ("auto", "dynamo", "torchscript")
OPSET = 18  # onnxruntime >= 1.14 runs it; the dynamo exporter's own default


@dataclass(frozen=True)
class OnnxExport:
    """What `export_onnx` wrote.

    Attributes:
        path: The image file (``X.onnx``; name this one in ``controller.weights``).
        head_path: The head file (``X.head.onnx``).
        exporter: "dynamo" or "torchscript".
        source_tensors_sha256: `tensors_sha256` of the exported weights.
        probe_max_abs_error_m: max |onnxruntime - torch| on the probe, measured after
            writing [m].
    """

    path: Path
    head_path: Path
    exporter: str
    source_tensors_sha256: str
    probe_max_abs_error_m: float


class _ImagePart(nn.Module):
    """images (B, 1, S, S) -> features (B, C2, P, P): `DistanceCNN.image_features`."""

    def __init__(self, model: DistanceCNN):
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.model.image_features(images)


class _HeadPart(nn.Module):
    """features (B, C2, P, P), raw actions (B, K, 3) -> distances (B, K).

    `DistanceCNN.forward_factored` after its image part, with IP1 on the plain
    (exportable) path instead of the cached oneDNN weights.
    """

    def __init__(self, model: DistanceCNN):
        super().__init__()
        self.model = model

    def forward(self, features: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        offsets = self.model.action_offsets(actions)  # (B, K, C2)
        h = self.model._lrelu(features[:, None] + offsets[..., None, None])
        return self.model.head.mlp(h.flatten(2))


def _resolve_exporter(exporter: str) -> str:
    if exporter not in EXPORTERS:
        raise ValueError(f"exporter: expected one of {EXPORTERS}, got {exporter!r}")
    if exporter == "auto":
        return "dynamo" if importlib.util.find_spec("onnxscript") is not None else "torchscript"
    return exporter


def _export(module: nn.Module, args: tuple, path: Path, *, exporter: str, input_names: list,
            output_names: list, axes: dict[str, dict[int, str]]) -> None:
    if exporter == "dynamo":
        dims: dict[str, torch.export.Dim] = {}
        shapes = {name: {i: dims.setdefault(n, torch.export.Dim(n)) for i, n in axes[name].items()}
                  for name in input_names}
        torch.onnx.export(module, args, str(path), dynamo=True, external_data=False,
                          input_names=input_names, output_names=output_names,
                          dynamic_shapes=shapes, opset_version=OPSET, verbose=False)
    else:
        torch.onnx.export(module, args, str(path), dynamo=False, input_names=input_names,
                          output_names=output_names, dynamic_axes=axes,
                          opset_version=OPSET, do_constant_folding=True)


def _set_metadata(path: Path, metadata: dict[str, str]) -> None:
    import onnx

    model = onnx.load(str(path))
    del model.metadata_props[:]
    for key, value in sorted(metadata.items()):
        model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _export_parts(model, exporter: str, *, tmp_head: Path, tmp_image: Path, features,
                  example_actions, images) -> None:
    """Exports the head part, then the image part, with the exporters' noise silenced."""
    # The exporters' tracer warnings (shape checks become constants: the shapes they
    # check are the fixed ones) and notes about torchvision are noise for this net.
    onnx_log = logging.getLogger("torch.onnx")
    level = onnx_log.level
    onnx_log.setLevel(logging.ERROR)
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _export(_HeadPart(model).eval(), (features, example_actions), tmp_head,
                    exporter=exporter, input_names=["features", "actions"],
                    output_names=["distances"],
                    axes={"features": {0: "B"}, "actions": {0: "B", 1: "K"},
                          "distances": {0: "B", 1: "K"}})
            _export(_ImagePart(model).eval(), (images,), tmp_image, exporter=exporter,
                    input_names=["images"], output_names=["features"],
                    axes={"images": {0: "B"}, "features": {0: "B"}})
    finally:
        onnx_log.setLevel(level)


def export_onnx(
    *, out: Union[str, os.PathLike], weights: Union[str, os.PathLike] = "",
    exporter: str = "auto",
) -> OnnxExport:
    """Writes the distance CNN as ``out`` (image part) and ``out``'s ``.head.onnx`` sibling.

    Both files are written in a temporary folder beside `out`, checked there with
    onnxruntime against torch on the built-in probe, and only then moved into place
    (the head first), so a failure leaves the previous files untouched. Existing files
    are replaced.

    Args:
        out: Destination of the image part; must end in ``.onnx``.
        weights: A safetensors weights file (`drake_grasp.cnn.weights_io.save_weights`);
            "" = the shipped paper net ``models/cnn/weights.safetensors`` (not the
            episode's default grid head, which the export does not cover). Exported in
            float32.
        exporter: "auto" (dynamo when onnxscript is installed, else torchscript),
            "dynamo" or "torchscript".

    Returns:
        What was written (`OnnxExport`).

    Raises:
        FileNotFoundError: No weights file, or `out`'s folder does not exist.
        ValueError: A bad weights file, a window-fusion net, `out` not ending in ``.onnx``, an unknown
            exporter, or an export that does not reproduce torch.
        ImportError: onnx / onnxruntime (or onnxscript for "dynamo") missing.
    """
    out = Path(out)
    head = head_path(out)  # raises unless out ends in .onnx
    if not out.parent.is_dir():
        raise FileNotFoundError(f"{out.parent}: no such folder (for --out {out})")
    exporter = _resolve_exporter(exporter)
    needed = ("onnx", "onnxruntime") + (("onnxscript",) if exporter == "dynamo" else ())
    missing = [m for m in needed if importlib.util.find_spec(m) is None]
    if missing:
        raise ImportError(f"exporting to ONNX needs {missing}: pip install "
                          "'drake_grasp[onnx-export]'")
    # The paper's net is in the repository's models/ only: model_path names it when missing.
    source = Path(weights) if weights else model_path(SHIPPED_WEIGHTS)
    if weights_format(source) == FCN_FORMAT:
        raise ValueError(f"{source}: a height-map FCN ({FCN_FORMAT}); the ONNX export "
                         "covers the distance CNN with the tiled (paper) fusion only")
    model, _ = load_weights(source)
    if model.config.action_fusion != "tiled":
        raise ValueError(f"{source}: action_fusion {model.config.action_fusion!r}; the ONNX "
                         "export covers the tiled (paper) fusion only")
    source_sha = tensors_sha256(model.state_dict())
    model = model.float().eval()
    cfg = model.config
    s, (c2, p, _) = cfg.image_size, cfg.feature_shape()

    depth, actions = probe_inputs(s, cfg.theta_unit)
    with torch.inference_mode():
        probe = model.score_actions(model.image_features(model.preprocess(depth))[0],
                                    torch.from_numpy(actions)).double().numpy()

    g = torch.Generator().manual_seed(0)
    images = torch.randn(2, 1, s, s, generator=g)
    features = torch.randn(2, c2, p, p, generator=g)
    example_actions = torch.rand(2, 5, 3, generator=g)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        tmp_image, tmp_head = tmp / out.name, tmp / head.name
        _export_parts(model, exporter, tmp_head=tmp_head, tmp_image=tmp_image,
                      features=features, example_actions=example_actions, images=images)
        common = {"format": ONNX_FORMAT, "code_version": drake_grasp.__version__,
                  "exporter": exporter, "torch_version": torch.__version__,
                  "source_tensors_sha256": source_sha}
        _set_metadata(tmp_head, {**common, "part": "head"})
        _set_metadata(tmp_image, {
            **common, "part": "image",
            "config": json.dumps(dataclasses.asdict(cfg), sort_keys=True),
            "head_file": head.name, "head_sha256": file_sha256(tmp_head),
            "source_weights": source.name,
            "probe_distances_m": json.dumps([float(v) for v in probe]),
        })
        # Load through the runtime: checks metadata, checksum and the probe (1e-4 m); the
        # measured error is reported as well.
        onnx_model = OnnxDistanceModel(tmp_image)
        error = float(np.max(np.abs(onnx_model.score(depth, actions) - probe)))
        del onnx_model
        os.replace(tmp_head, head)
        os.replace(tmp_image, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return OnnxExport(path=out, head_path=head, exporter=exporter,
                      source_tensors_sha256=source_sha, probe_max_abs_error_m=error)
