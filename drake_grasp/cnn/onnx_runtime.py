"""The distance CNN run by onnxruntime from an exported ONNX pair: numpy only, no torch.

`drake_grasp.cnn.onnx_export` writes the CNN's two parts (the fast path of
`drake_grasp.cnn.network`, the image part once per image and the per-action head) as two
ONNX files:

* ``X.onnx``, the image part: ``images`` (B, 1, S, S) normalized depth ->
  ``features`` (B, C2, P, P), equal to `DistanceCNN.image_features`. Its ONNX metadata
  (``metadata_props``) holds everything else: ``format`` (`ONNX_FORMAT`), ``config``
  (the `NetworkConfig` as JSON: the depth normalization lives there and is applied here
  in numpy), ``head_sha256`` (the SHA-256 of the head file's bytes; ``head_file``
  records its name at export; the pair may be renamed together),
  ``source_tensors_sha256`` (the safetensors weights it came from), ``code_version``,
  ``exporter`` and ``probe_distances_m`` (torch's distances for the built-in
  `probe_inputs`, checked on load).
* ``X.head.onnx`` (`head_path`), the action part: ``features`` (B, C2, P, P) and raw
  ``actions`` (B, K, 3) -> ``distances`` (B, K) [m], equal to
  `DistanceCNN.forward_factored` given the features.

Only ``X.onnx`` is named anywhere (``controller.weights: X.onnx``): its bytes pin the
head through ``head_sha256``, so one file's checksum identifies the whole model (the
Monte Carlo run identity hashes ``controller.weights``).

This module imports numpy at import time and onnxruntime when a model is loaded, never
torch: install ``drake_grasp[onnx]`` (onnxruntime) to run the CNN where torch is absent.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping, Union

import numpy as np

from drake_grasp.core.provenance import file_sha256

ONNX_FORMAT = "drake_grasp.DistanceCNN.onnx/1"
"""Value of the ``format`` metadata key of both files written by `onnx_export`."""

PROBE_TOLERANCE_M = 1e-4
"""Largest accepted |onnxruntime - recorded torch| distance on the probe at load [m]."""

HEAD_SUFFIX = ".head.onnx"

# Keys of the image file's metadata that `OnnxDistanceModel` needs.
REQUIRED_KEYS = ("format", "part", "config", "head_sha256",
                 "source_tensors_sha256", "code_version", "probe_distances_m")

# NetworkConfig fields this module reads (the rest describe the graph, already fixed).
_CONFIG_KEYS = ("image_size", "conv2_channels", "depth_reference", "depth_offset_m",
                "depth_scale_m", "depth_clip_near_m", "depth_clip_far_m", "theta_unit")


def head_path(path: Union[str, os.PathLike]) -> Path:
    """The head file that belongs to image file `path`: ``X.onnx`` -> ``X.head.onnx``.

    Raises:
        ValueError: `path` does not end in ``.onnx``.
    """
    path = Path(path)
    if path.suffix != ".onnx":
        raise ValueError(f"{path}: expected a file name ending in '.onnx'")
    return path.with_name(path.name[: -len(".onnx")] + HEAD_SUFFIX)


def normalize_depth(depth: Any, config: Mapping[str, Any]) -> np.ndarray:
    """numpy twin of `drake_grasp.cnn.net_config.normalize_depth`, bit for bit in float32.

    Args:
        depth: Depth [m], shape (H, W), (B, H, W) or (B, 1, H, W). +inf is clipped to
            ``depth_clip_far_m``, values <= 0 to ``depth_clip_near_m``.
        config: A `NetworkConfig` as a dict (``config`` of the ONNX metadata).

    Returns:
        float32 (B, 1, H, W).

    Raises:
        ValueError: A bad shape, or NaN pixels.
    """
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim == 2:
        d = d[None, None]
    elif d.ndim == 3:
        d = d[:, None]
    elif not (d.ndim == 4 and d.shape[1] == 1):
        raise ValueError(
            f"depth: expected shape (H, W), (B, H, W) or (B, 1, H, W), got {tuple(d.shape)}")
    if np.isnan(d).any():
        raise ValueError("depth: contains NaN pixels; fill invalid pixels first")
    # torch clamps a float32 tensor with the bounds cast to float32, then subtracts and
    # divides in float32: the same operations here give the same bits.
    d = np.clip(d, np.float32(config["depth_clip_near_m"]), np.float32(config["depth_clip_far_m"]))
    if config["depth_reference"] == "median":
        flat = d.reshape(d.shape[0], -1)
        k = (flat.shape[1] - 1) // 2  # torch.median: the lower of the two middle values
        ref = np.partition(flat, k, axis=1)[:, k][:, None, None, None]
    else:
        ref = np.float32(config["depth_offset_m"])
    return np.ascontiguousarray((d - ref) / np.float32(config["depth_scale_m"]), dtype=np.float32)


def random_check_inputs(seed: int, images: int = 3, k: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """Random inputs on which an export is compared with torch (tests/test_onnx.py,
    analysis/onnx_agreement.py): depth images in 0.1-1.2 m with +inf (nothing seen) and 0
    (invalid) pixels, and 2k actions, k in the controller's sampling ranges (+-4 cm,
    +-45 deg) and k in the cnn-only policy's wider ones (+-10 cm, +-90 deg).

    Returns:
        depth (images, 64, 64) float32 [m], actions (2k, 3) float32 (x, y [m], theta [deg]).
    """
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.1, 1.2, (images, 64, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.05] = np.inf
    depth[rng.random(depth.shape) < 0.03] = 0.0
    near = np.column_stack([rng.uniform(-0.04, 0.04, (k, 2)), rng.uniform(-45, 45, k)])
    wide = np.column_stack([rng.uniform(-0.1, 0.1, (k, 2)), rng.uniform(-90, 90, k)])
    return depth, np.concatenate([near, wide]).astype(np.float32)


def probe_inputs(image_size: int, theta_unit: str) -> tuple[np.ndarray, np.ndarray]:
    """A fixed depth image and 8 actions whose distances the export records.

    A tilted plane with a box and a cylinder on it, a strip of +inf and a few 0 pixels,
    so every part of the normalization and of the net is exercised.

    Returns:
        depth (S, S) float32 [m], actions (8, 3) float32 (x, y [m], theta in `theta_unit`).
    """
    s = int(image_size)
    v, u = np.mgrid[0:s, 0:s].astype(np.float64) / max(s - 1, 1)
    depth = 0.32 + 0.04 * u - 0.02 * v
    depth[(abs(u - 0.35) < 0.12) & (abs(v - 0.55) < 0.2)] = 0.26
    depth[(u - 0.7) ** 2 + (v - 0.3) ** 2 < 0.015] = 0.22
    depth[:, -3:] = np.inf
    depth[:2, :4] = 0.0
    theta = np.linspace(-60.0, 75.0, 8)
    actions = np.column_stack([np.linspace(-0.04, 0.035, 8), np.linspace(0.03, -0.04, 8),
                               theta if theta_unit == "deg" else np.deg2rad(theta)])
    return depth.astype(np.float32), actions.astype(np.float32)


class OnnxDistanceModel:
    """The distance CNN of an exported ONNX pair, scored by onnxruntime (no torch).

    The same interface as the torch fast path: `preprocess` (depth [m] -> net input),
    `image_features` (once per image), `score_actions` (K actions on one image), and
    `score` (the three in one call, what `DistanceEvaluator` runs).

    On load it checks the metadata, the head file's SHA-256 and that the pair reproduces
    the distances torch computed on `probe_inputs` at export (within
    `PROBE_TOLERANCE_M`), so a modified or corrupted pair fails here, not in a trial.

    Args:
        path: The image file ``X.onnx`` written by `drake_grasp.cnn.onnx_export`.
        threads: onnxruntime intra-op threads (1 suits one simulation per core).
        verify: Run the probe check.

    Attributes:
        path: The image file.
        head_path: The head file.
        config: The `NetworkConfig` as a dict.
        metadata: The image file's metadata (``config`` and ``probe_distances_m``
            parsed).

    Raises:
        FileNotFoundError: Either file is missing.
        ValueError: Anything else wrong; the message names the file and the key.
        ImportError: onnxruntime is not installed.
    """

    def __init__(self, path: Union[str, os.PathLike], *, threads: int = 1, verify: bool = True):
        self.path = Path(path)
        self.head_path = head_path(self.path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such ONNX model file")
        try:
            import onnxruntime as ort
        except ImportError as e:
            raise ImportError(
                f"{self.path}: running an ONNX CNN needs onnxruntime: "
                "pip install 'drake_grasp[onnx]'") from e
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads: expected an int >= 1, got {threads!r}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.log_severity_level = 3  # errors only
        self._image = _session(ort, self.path, options)
        self.metadata = _read_metadata(self._image, self.path)
        if self.metadata["part"] != "image":
            raise ValueError(
                f"{self.path}: metadata 'part' is {self.metadata['part']!r}, expected 'image' "
                f"(give the image file X.onnx, not its {HEAD_SUFFIX} sibling)")
        if not self.head_path.is_file():
            raise FileNotFoundError(
                f"{self.head_path}: no such file (the head part of {self.path}; export both "
                "with 'drake-grasp export-onnx')")
        digest = file_sha256(self.head_path)
        if digest != self.metadata["head_sha256"]:
            raise ValueError(
                f"{self.head_path}: does not match metadata 'head_sha256' of {self.path} "
                f"(file corrupted, modified or from another export): stored "
                f"{self.metadata['head_sha256']}, computed {digest}")
        self._head = _session(ort, self.head_path, options)
        head_meta = _read_metadata(self._head, self.head_path)
        if head_meta["part"] != "head":
            raise ValueError(f"{self.head_path}: metadata 'part' is {head_meta['part']!r}, "
                             "expected 'head'")
        self.config = self.metadata["config"]
        s, c2 = int(self.config["image_size"]), int(self.config["conv2_channels"])
        for where, sess, expected in (
                (self.path, self._image, (["images"], ["features"])),
                (self.head_path, self._head, (["features", "actions"], ["distances"]))):
            got = ([i.name for i in sess.get_inputs()], [o.name for o in sess.get_outputs()])
            if got != expected:
                raise ValueError(f"{where}: graph inputs/outputs are {got}, expected {expected}")
        self._image_size = s
        feature_shape = self._head.get_inputs()[0].shape[1:]
        if len(feature_shape) != 3 or feature_shape[0] != c2:
            raise ValueError(f"{self.head_path}: input 'features' has shape "
                             f"{self._head.get_inputs()[0].shape}, expected (B, {c2}, P, P)")
        self.feature_shape = tuple(int(n) for n in feature_shape)
        if verify:
            self._verify_probe()

    # -- scoring -------------------------------------------------------------------

    def preprocess(self, depth: Any) -> np.ndarray:
        """`normalize_depth` with this model's config -> float32 (B, 1, H, W)."""
        return normalize_depth(depth, self.config)

    def image_features(self, images: np.ndarray) -> np.ndarray:
        """The action-independent part, as `DistanceCNN.image_features`.

        Args:
            images: Normalized depth (`preprocess`), (B, 1, S, S).

        Returns:
            float32 (B, C2, P, P).
        """
        s = self._image_size
        images = np.ascontiguousarray(images, dtype=np.float32)
        if images.ndim != 4 or images.shape[1:] != (1, s, s):
            raise ValueError(f"images: expected shape (B, 1, {s}, {s}) (normalized depth), "
                             f"got {tuple(images.shape)}")
        return self._image.run(None, {"images": images})[0]

    def score_actions(self, features: np.ndarray, actions: Any) -> np.ndarray:
        """Distances [m] for K candidate actions on one image, as `DistanceCNN.score_actions`.

        Args:
            features: `image_features` of one image, (C2, P, P) or (1, C2, P, P).
            actions: (K, 3) raw actions (x, y [m], theta in the config's ``theta_unit``).

        Returns:
            float32 (K,).
        """
        features = np.asarray(features, dtype=np.float32)
        if features.ndim == 4 and features.shape[0] == 1:
            features = features[0]
        if features.shape != self.feature_shape:
            raise ValueError(f"features: expected shape {self.feature_shape} or "
                             f"(1, *{self.feature_shape}) (image_features of one image), got "
                             f"{tuple(features.shape)}")
        actions = np.asarray(actions, dtype=np.float32)
        if actions.ndim != 2 or actions.shape[1] != 3:
            raise ValueError(f"actions: expected shape (K, 3) raw (x, y, theta), got "
                             f"{tuple(actions.shape)}")
        if len(actions) == 0:
            return np.zeros(0, np.float32)
        out = self._head.run(None, {"features": np.ascontiguousarray(features[None]),
                                    "actions": np.ascontiguousarray(actions[None])})[0]
        return out[0]

    def score(self, depth: Any, actions: Any) -> np.ndarray:
        """Predicted distance [m] for each action on one depth image [m], float64 (K,)."""
        features = self.image_features(self.preprocess(np.asarray(depth, np.float32)))
        return self.score_actions(features[0], actions).astype(float)

    def _verify_probe(self) -> None:
        depth, actions = probe_inputs(self._image_size, self.config["theta_unit"])
        expected = np.asarray(self.metadata["probe_distances_m"], dtype=float)
        got = self.score(depth, actions)
        err = float(np.max(np.abs(got - expected))) if got.shape == expected.shape else math.inf
        if not err <= PROBE_TOLERANCE_M:
            raise ValueError(
                f"{self.path}: distances on the built-in probe differ from metadata "
                f"'probe_distances_m' by {err:.3g} m (> {PROBE_TOLERANCE_M} m): the files "
                "are corrupted or modified")

    def __repr__(self) -> str:
        return f"OnnxDistanceModel({str(self.path)!r})"


def _session(ort, path: Path, options):
    try:
        return ort.InferenceSession(str(path), sess_options=options,
                                    providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for bad files
        raise ValueError(f"{path}: not a valid ONNX model ({type(e).__name__}: "
                         f"{str(e).strip()[:300]})") from e


def _read_metadata(session, path: Path) -> dict[str, Any]:
    meta = dict(session.get_modelmeta().custom_metadata_map)
    if meta.get("format") != ONNX_FORMAT:
        raise ValueError(f"{path}: metadata 'format' is {meta.get('format')!r}, expected "
                         f"{ONNX_FORMAT!r} (not exported by 'drake-grasp export-onnx'?)")
    if meta.get("part") == "head":
        return meta
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise ValueError(f"{path}: metadata key(s) {missing} missing")
    for key in ("config", "probe_distances_m"):
        try:
            meta[key] = json.loads(meta[key])
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: metadata {key!r} is not valid JSON: {e}") from e
    if not isinstance(meta["config"], dict) or any(k not in meta["config"] for k in _CONFIG_KEYS):
        raise ValueError(f"{path}: metadata 'config' must be a NetworkConfig object with the "
                         f"keys {list(_CONFIG_KEYS)}")
    return meta
