"""The distance CNN of Viereck et al. (CoRL 2017) and its exact factored fast path.

The network estimates d(I, a) >= 0, the distance (metres in the paper's weighted
(x, y, theta) pose space) from the hand, after a planar displacement a = (x, y, theta),
to the nearest viable grasp, given a 64x64 wrist depth image I.

Architecture (the paper's LeNet variant)::

    I (1x64x64) -> Conv1 20@5x5 -> lrelu -> maxpool2 -> (+ tile(IP_a(a)))      30x30
                -> Conv2 50@5x5 -> lrelu -> maxpool2 -> flatten (8450)          13x13
                -> IP1 500 -> lrelu -> IP2 1 -> output_scale_m * softplus -> d

The fast path rests on two exact identities (DESIGN.md, "The CNN, and why it can be
fast"):

1. Conv2 is linear and unpadded, so for a spatially constant per-channel shift b,
   ``Conv2(P + tile(b)) = Conv2(P) + c`` with ``c[o] = sum_i b[i] * sum_taps W2[o, i]``:
   one number per output channel, the conv bias staying inside ``Conv2(P)``.
2. Max-pooling commutes with adding a per-channel constant and with any
   non-decreasing function, so ``pool(lrelu(Z + c)) = lrelu(pool(Z) + c)``.

Hence ``Zp = pool(Conv2(Pool1(lrelu(Conv1(I)))))`` (50x13x13) is computed once per
image (`DistanceCNN.image_features`), and each action costs an affine 4 -> 50 map, a
broadcast add, lrelu and the IP layers (`DistanceCNN.score_actions` for control,
`DistanceCNN.forward_factored` for training). Results equal the direct form up to
floating-point rounding, gradients included.

For control (one image, K candidates, no gradient) IP1 is split further
(`DistanceCNN._ip1_split`). IP1's input is ``lrelu(Zp[j, p] + c_k[j])``; an input whose
argument has the same sign for all K candidates (``Zp[j, p] + min_k c_k[j] > 0``, or
``Zp[j, p] + max_k c_k[j] <= 0``) is affine in c_k, so its share of IP1 is one
matrix-vector pass over the weights for all K together. Only the remaining inputs
(about 20-30% on the wrist images measured) go through the per-candidate product.
Same numbers up to summation order.

Weights are stored with safetensors only (no pickle), with the architecture and input
normalization in the file's metadata and a SHA-256 of the tensor data, so a corrupted
or mismatched file fails loudly instead of loading garbage (`save_weights`,
`load_weights`).

This module knows nothing of Drake; `drake_grasp.systems` wraps it.
"""

# No `from __future__ import annotations`: NetworkConfig may be nested in scenario
# dataclasses read by Drake's yaml_load_typed, which needs real annotation objects.

import dataclasses
import hashlib
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np
import safetensors
import safetensors.torch
import torch
import torch.nn.functional as F
from torch import nn

import drake_grasp

ArrayLike = Union[np.ndarray, torch.Tensor]

WEIGHTS_FORMAT = "drake_grasp.DistanceCNN/1"
"""Value of the ``format`` metadata key of a weights file written by `save_weights`."""

# Metadata keys written by `save_weights`; user metadata goes in its own JSON entry so
# it can never shadow these.
_KEY_FORMAT = "format"
_KEY_CONFIG = "config"
_KEY_CODE_VERSION = "code_version"
_KEY_TENSORS_SHA256 = "tensors_sha256"
_KEY_USER = "user_metadata"

# load_weights adds these to the returned metadata, so users may not set them.
_RESERVED_USER_KEYS = ("config", "code_version", "format")

_DEPTH_REFERENCES = ("fixed", "median")
_THETA_UNITS = ("rad", "deg")
_THETA_ENCODINGS = ("double_angle",)
_ACTION_FUSIONS = ("tiled", "window", "grid")
# Fields that only the window fusion uses: absent from a "tiled" net's dict.
_WINDOW_FIELDS = ("action_fusion", "window_side_m", "window_samples", "camera_fov_deg",
                  "camera_x_G_m", "camera_y_G_m", "context_side_m")
# Fields added after the window fusion, with the value that means "as before": left out
# of the dict at that value, read as it when missing.
_LATER_FIELDS = {"context_side_m": 0.0}
# The grid head's fields: in the dict of "grid" nets only (older files have none).
_GRID_FIELDS = ("grid_half_m", "grid_step_m", "grid_theta_step_deg")


@dataclass
class NetworkConfig:
    """Architecture and input normalization of `DistanceCNN`.

    Everything that changes what a weight means lives here; `save_weights` stores it
    in the file and `load_weights` rebuilds the net from it.

    Depth normalization (`normalize_depth`), applied to a depth image in metres::

        d = clip(depth, depth_clip_near_m, depth_clip_far_m)     (+inf -> far)
        n = (d - ref) / depth_scale_m
        ref = depth_offset_m                  if depth_reference == "fixed"
            = median of the image's d         if depth_reference == "median"

    The default is "fixed": the net sees absolute depth. Invariance to camera height
    is *not* what the task wants: the actions are metric (metres) while the image is
    in pixels, and the metres-per-pixel scale grows linearly with the camera height
    (the controller descends from ~0.3 m to ~0.15 m). The net needs the absolute depth
    to relate an offset in metres to image content; subtracting the image's median
    depth removes the most direct cue for that scale and leaves only object sizes,
    which vary. Height variation is instead covered by the training set (cameras at
    random heights, as in the paper). "median" is kept for experiments; it makes the
    input invariant to a pure height shift. The clip keeps empty pixels (the depth
    pipeline's far value, ~1.5 m) from dominating the input range: beyond
    `depth_clip_far_m` nothing matters for a grasp from 0.1-0.4 m.

    Action features (`action_features`)::

        a = (x, y, theta) -> [x / action_xy_scale_m, y / action_xy_scale_m,
                              cos(2 theta), sin(2 theta)]

    x, y are the planar offsets in metres in the camera frame (~ +-0.1 m), theta the
    yaw offset in `theta_unit`. Encoding the *double* angle makes theta and
    theta + 180 degrees identical inputs, which is exact for a parallel-jaw gripper.

    Attributes:
        image_size: Side of the square input image [pixels].
        conv1_channels: Conv1 filters (paper: 20).
        conv2_channels: Conv2 filters (paper: 50).
        kernel: Conv kernel side (paper: 5), stride 1, no padding.
        ip1: Width of the hidden inner-product layer (LeNet: 500).
        leaky_slope: Negative slope of every leaky ReLU (the PyTorch/Caffe-style
            default 0.01; the paper gives no value).
        output_scale_m: The output is ``output_scale_m * softplus(IP2)``, in metres.
            Softplus rather than ReLU: the paper's d is > 0, and a ReLU output would
            pass no gradient to a sample whose prediction fell below zero (L1 loss).
            The scale puts an untrained net's output (softplus(0) * 0.05 = 35 mm) in
            the range of the labels instead of at 0.69 m.
        depth_reference: "fixed" or "median" (see above).
        depth_offset_m: Reference depth for "fixed" [m], the middle of the working range.
        depth_scale_m: Depth units per normalized unit [m].
        depth_clip_near_m: Depths below are clipped up to this [m] (0 = invalid pixel).
        depth_clip_far_m: Depths above (and +inf) are clipped down to this [m].
        action_xy_scale_m: x and y are divided by this [m].
        theta_unit: Unit of a raw action's theta: "rad" (as `drake_grasp.geometry.grasps`) or
            "deg".
        theta_encoding: Only "double_angle" (cos 2theta, sin 2theta); recorded so a
            future encoding cannot silently load old weights.
        action_fusion: How the action enters the net. "tiled" (the paper): IP_a(a) is
            added to every Pool1 cell. "window": the net looks where the candidate
            grasp would be (see `DistanceCNN`, "Window fusion"); the fields below
            belong to it and are left out of `to_dict` for "tiled" nets, so files and
            run identities written before they existed are unchanged.
        window_side_m: Side of the square window around the candidate grasp [m].
        context_side_m: Side of a second, coarser window around the candidate [m], with
            as many samples; 0 = none. It shows the net what lies beyond the fine
            window (a candidate far from any object has its nearest grasp there).
        window_samples: Samples per window side (even); pooled 2x2 into IP1's input.
        camera_fov_deg: The wrist camera's field of view (square image) [deg].
        camera_x_G_m, camera_y_G_m: The camera's centre in the grasp frame G [m]
            (the camera looks along z_G with its axes parallel to G's).
        grid_half_m, grid_step_m, grid_theta_step_deg: The "grid" head (see
            `DistanceCNN`, "Grid head"): IP2 predicts the distance at every node of a
            grid of actions, x and y within `grid_half_m` of the camera's centre (the
            widest view in the data: 0.156 m at 0.30 m) every `grid_step_m`, theta
            over 180 degrees every `grid_theta_step_deg`; a candidate's distance is the
            grid's trilinear interpolation (periodic in theta).
    """

    image_size: int = 64
    conv1_channels: int = 20
    conv2_channels: int = 50
    kernel: int = 5
    ip1: int = 500
    leaky_slope: float = 0.01
    output_scale_m: float = 0.05
    depth_reference: str = "fixed"
    depth_offset_m: float = 0.3
    depth_scale_m: float = 0.1
    depth_clip_near_m: float = 0.05
    depth_clip_far_m: float = 0.8
    action_xy_scale_m: float = 0.1
    theta_unit: str = "rad"
    theta_encoding: str = "double_angle"
    action_fusion: str = "tiled"
    window_side_m: float = 0.12
    window_samples: int = 20
    camera_fov_deg: float = 55.0
    camera_x_G_m: float = 0.0
    camera_y_G_m: float = -0.05
    context_side_m: float = 0.0
    grid_half_m: float = 0.16
    grid_step_m: float = 0.01
    grid_theta_step_deg: float = 10.0

    def __post_init__(self) -> None:
        for name in ("image_size", "conv1_channels", "conv2_channels", "kernel", "ip1",
                     "window_samples"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"NetworkConfig.{name}: expected an int >= 1, got {value!r}")
        for name in (
            "output_scale_m",
            "depth_scale_m",
            "depth_clip_far_m",
            "action_xy_scale_m",
        ):
            value = getattr(self, name)
            if not _is_real(value) or not (math.isfinite(value) and value > 0.0):
                raise ValueError(
                    f"NetworkConfig.{name}: expected a finite number > 0, got {value!r}"
                )
        for name in ("leaky_slope", "depth_offset_m", "depth_clip_near_m"):
            value = getattr(self, name)
            if not _is_real(value) or not math.isfinite(value):
                raise ValueError(f"NetworkConfig.{name}: expected a finite number, got {value!r}")
        # The fast path needs lrelu non-decreasing (slope >= 0); slope 1 would make it
        # linear, which is legal but pointless, so only the sign is checked.
        if self.leaky_slope < 0.0:
            raise ValueError(f"NetworkConfig.leaky_slope: expected >= 0, got {self.leaky_slope!r}")
        if not self.depth_clip_near_m < self.depth_clip_far_m:
            raise ValueError(
                "NetworkConfig.depth_clip_near_m: expected < depth_clip_far_m "
                f"({self.depth_clip_far_m!r}), got {self.depth_clip_near_m!r}"
            )
        if self.window_samples % 2:
            raise ValueError(
                f"NetworkConfig.window_samples: expected an even int, got {self.window_samples!r}")
        for name in ("window_side_m", "camera_fov_deg"):
            value = getattr(self, name)
            if not _is_real(value) or not (math.isfinite(value) and value > 0.0):
                raise ValueError(
                    f"NetworkConfig.{name}: expected a finite number > 0, got {value!r}")
        if not self.camera_fov_deg < 180.0:
            raise ValueError(
                f"NetworkConfig.camera_fov_deg: expected < 180, got {self.camera_fov_deg!r}")
        if (not _is_real(self.context_side_m) or not math.isfinite(self.context_side_m)
                or self.context_side_m < 0.0):
            raise ValueError("NetworkConfig.context_side_m: expected a finite number >= 0, "
                             f"got {self.context_side_m!r}")
        for name in ("camera_x_G_m", "camera_y_G_m"):
            if not _is_real(getattr(self, name)) or not math.isfinite(getattr(self, name)):
                raise ValueError(
                    f"NetworkConfig.{name}: expected a finite number, got {getattr(self, name)!r}")
        if self.action_fusion == "window" and self.depth_reference != "fixed":
            raise ValueError(
                "NetworkConfig.depth_reference: the window fusion needs \"fixed\" (it reads "
                f"the image's depth back in metres), got {self.depth_reference!r}")
        for name, allowed in (
            ("action_fusion", _ACTION_FUSIONS),
            ("depth_reference", _DEPTH_REFERENCES),
            ("theta_unit", _THETA_UNITS),
            ("theta_encoding", _THETA_ENCODINGS),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"NetworkConfig.{name}: expected one of {allowed}, got {getattr(self, name)!r}"
                )
        for name in _GRID_FIELDS:
            value = getattr(self, name)
            if not _is_real(value) or not (math.isfinite(value) and value > 0.0):
                raise ValueError(
                    f"NetworkConfig.{name}: expected a finite number > 0, got {value!r}")
        if self.action_fusion == "grid":
            half = self.grid_half_m / self.grid_step_m
            bins = 180.0 / self.grid_theta_step_deg
            if abs(half - round(half)) > 1e-6 or abs(bins - round(bins)) > 1e-6:
                raise ValueError(
                    "NetworkConfig.grid_half_m / grid_step_m and 180 / grid_theta_step_deg: "
                    f"expected whole numbers, got {half:g} and {bins:g}")
        self.feature_shape()  # raises if the image is too small for the two conv/pools

    def grid_shape(self) -> tuple[int, int, int]:
        """(theta bins, y nodes, x nodes) of the "grid" head's output."""
        n = 2 * round(self.grid_half_m / self.grid_step_m) + 1
        return (round(180.0 / self.grid_theta_step_deg), n, n)

    def feature_shape(self) -> tuple[int, int, int]:
        """Shape (C, H, W) of `DistanceCNN.image_features`: Pool2's output (the grid
        head: its distance grid, `grid_shape`).

        Raises:
            ValueError: The image is too small for two conv + pool stages.
        """
        k = self.kernel
        side = self.image_size - k + 1  # Conv1, unpadded
        pool1 = side // 2
        conv2 = pool1 - k + 1
        pool2 = conv2 // 2
        if side < 2 or conv2 < 2 or pool2 < 1:
            raise ValueError(
                f"NetworkConfig.image_size: {self.image_size} is too small for two "
                f"{k}x{k} conv + 2x2 pool stages"
            )
        if self.action_fusion == "window":
            # lrelu(Conv2) before pooling, plus one channel holding the reference depth.
            return (self.conv2_channels + 1, conv2, conv2)
        if self.action_fusion == "grid":
            return self.grid_shape()
        return (self.conv2_channels, pool2, pool2)

    @property
    def pool1_size(self) -> int:
        """Side of Pool1's output (where the action's IP layer is tiled)."""
        return (self.image_size - self.kernel + 1) // 2

    @property
    def num_features(self) -> int:
        """Length of IP1's input: the flattened Pool2 output (8450 for the defaults), or
        for the window fusion the pooled window, C2 x (window_samples / 2)^2."""
        if self.action_fusion == "window":
            windows = 2 if self.context_side_m > 0 else 1
            return windows * self.conv2_channels * (self.window_samples // 2) ** 2
        pool2 = ((self.image_size - self.kernel + 1) // 2 - self.kernel + 1) // 2
        return self.conv2_channels * pool2 * pool2

    @property
    def focal_px(self) -> float:
        """The wrist camera's focal length in pixels (square image, `camera_fov_deg`)."""
        return (self.image_size / 2.0) / math.tan(math.radians(self.camera_fov_deg) / 2.0)

    def to_dict(self) -> dict[str, Any]:
        """The config as a plain dict (JSON-able); a "tiled" net's leaves out the window
        fields (`action_fusion` and after)."""
        d = dataclasses.asdict(self)
        if self.action_fusion == "tiled":
            for name in _WINDOW_FIELDS:
                d.pop(name)
        if self.action_fusion != "grid":
            for name in _GRID_FIELDS:
                d.pop(name)
        for name, before in _LATER_FIELDS.items():
            if d.get(name, None) == before:
                d.pop(name)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "config") -> "NetworkConfig":
        """Builds a config from a dict that must name every field exactly once.

        Missing fields are errors rather than defaults: a weights file written with a
        different default must not load as if it had this one.

        Raises:
            ValueError: Unknown or missing fields, or invalid values; the message starts
                with `source`.
        """
        if not isinstance(data, dict):
            raise ValueError(f"{source}: expected a JSON object, got {type(data).__name__}")
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"{source}: unknown NetworkConfig field(s) {unknown}; known: {names}")
        missing = [n for n in names if n not in data]
        if "action_fusion" not in data:  # a "tiled" net's dict (`to_dict`)
            missing = [n for n in missing if n not in _WINDOW_FIELDS]
        missing = [n for n in missing if n not in _LATER_FIELDS]
        if data.get("action_fusion") != "grid":
            missing = [n for n in missing if n not in _GRID_FIELDS]
        if missing:
            raise ValueError(f"{source}: missing NetworkConfig field(s) {missing}")
        try:
            return cls(**data)
        except ValueError as e:
            raise ValueError(f"{source}: {e}") from e


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# ----------------------------------------------------------------------------------
# Input normalization
# ----------------------------------------------------------------------------------


def normalize_depth(
    depth: ArrayLike,
    config: Optional[NetworkConfig] = None,
    *,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Maps depth images in metres to the network's input (see `NetworkConfig`).

    Args:
        depth: Depth [m], shape (H, W), (B, H, W) or (B, 1, H, W). +inf (nothing
            there) is allowed and clipped to `depth_clip_far_m`; values <= 0 (invalid
            pixels, which `drake_grasp.geometry.sensing.postprocess_depth` should already have
            filled) are clipped to `depth_clip_near_m`.
        config: Normalization parameters; defaults to `NetworkConfig()`.
        dtype: Floating dtype of the result.

    Returns:
        The normalized images, shape (B, 1, H, W).

    Raises:
        ValueError: A bad shape, or NaN pixels (they would silently poison training).
    """
    config = config if config is not None else NetworkConfig()
    t = torch.as_tensor(depth).to(dtype=dtype)
    if t.ndim == 2:
        t = t[None, None]
    elif t.ndim == 3:
        t = t[:, None]
    elif not (t.ndim == 4 and t.shape[1] == 1):
        raise ValueError(
            f"depth: expected shape (H, W), (B, H, W) or (B, 1, H, W), got {tuple(t.shape)}"
        )
    if torch.isnan(t).any():
        raise ValueError("depth: contains NaN pixels; fill invalid pixels first")
    d = t.clamp(config.depth_clip_near_m, config.depth_clip_far_m)
    if config.depth_reference == "median":
        # torch.median returns the lower of the two middle values: deterministic.
        ref = d.flatten(1).median(dim=1).values[:, None, None, None]
    else:
        ref = config.depth_offset_m
    return (d - ref) / config.depth_scale_m


def action_features(
    actions: ArrayLike,
    config: Optional[NetworkConfig] = None,
    *,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Encodes raw actions (x, y, theta) as [x/s, y/s, cos 2theta, sin 2theta].

    Args:
        actions: Shape (..., 3) raw actions (x, y in metres, theta in
            `config.theta_unit`), or (..., 4) features, returned unchanged (cast).
        config: Normalization parameters; defaults to `NetworkConfig()`.
        dtype: Floating dtype of the result.

    Returns:
        Shape (..., 4).

    Raises:
        ValueError: The last dimension is neither 3 nor 4.
    """
    config = config if config is not None else NetworkConfig()
    a = torch.as_tensor(actions).to(dtype=dtype)
    if a.ndim == 0 or a.shape[-1] not in (3, 4):
        raise ValueError(
            "actions: expected last dimension 3 (x, y, theta) or 4 (features), "
            f"got shape {tuple(a.shape)}"
        )
    if a.shape[-1] == 4:
        return a
    theta = a[..., 2]
    if config.theta_unit == "deg":
        # = torch.deg2rad bit for bit; the TorchScript ONNX exporter has no deg2rad.
        theta = theta * (math.pi / 180.0)
    s = config.action_xy_scale_m
    return torch.stack(
        (a[..., 0] / s, a[..., 1] / s, torch.cos(2.0 * theta), torch.sin(2.0 * theta)), dim=-1
    )


# ----------------------------------------------------------------------------------
# The network
# ----------------------------------------------------------------------------------


def grid_corners(cfg: "NetworkConfig", feats: torch.Tensor) -> list:
    """The 8 grid nodes around each of M actions on B images and their trilinear
    weights: [(flat node index (B, M), weight (B, M))] (see `grid_scores`); the grid is
    `cfg`'s (`NetworkConfig.grid_shape`, its step, theta step and camera offset)."""
    t_bins, n, _ = cfg.grid_shape()
    b, m = feats.shape[:2]
    half = (n - 1) / 2.0
    # Node coordinates: x = camera_x + (i - half) step, theta = -90 + k step.
    u = (feats[..., 0] * cfg.action_xy_scale_m - cfg.camera_x_G_m) / cfg.grid_step_m + half
    v = (feats[..., 1] * cfg.action_xy_scale_m - cfg.camera_y_G_m) / cfg.grid_step_m + half
    theta_deg = torch.rad2deg(0.5 * torch.atan2(feats[..., 3], feats[..., 2]))
    w = torch.remainder((theta_deg + 90.0) / cfg.grid_theta_step_deg, float(t_bins))
    u = u.clamp(0.0, n - 1.0)
    v = v.clamp(0.0, n - 1.0)
    iu = u.detach().floor().clamp(max=n - 2).long()
    iv = v.detach().floor().clamp(max=n - 2).long()
    iw = w.detach().floor().long().clamp(0, t_bins - 1)
    fu, fv, fw = u - iu, v - iv, w - iw
    iw1 = torch.remainder(iw + 1, t_bins)
    corners = []
    for kw, gw in ((iw, 1.0 - fw), (iw1, fw)):
        for kv, gv in ((iv, 1.0 - fv), (iv + 1, fv)):
            for ku, gu in ((iu, 1.0 - fu), (iu + 1, fu)):
                corners.append(((kw * n + kv) * n + ku, gw * gv * gu))
    return corners


def grid_view_mask(camera_height_m, cfg: "NetworkConfig", *, slack_m: float = 1e-9) -> np.ndarray:
    """(B, N) mask of the grid's x (and, the view being square, y) nodes inside the
    camera's footprint on the table at each of B camera heights above it [m], widened by
    `slack_m`."""
    n = cfg.grid_shape()[1]
    half_view = (np.atleast_1d(np.asarray(camera_height_m, float))
                 * math.tan(math.radians(cfg.camera_fov_deg) / 2.0))
    offsets = (np.arange(n) - (n - 1) / 2.0) * cfg.grid_step_m
    return np.abs(offsets)[None, :] <= half_view[:, None] + slack_m


def grid_scores(cfg: "NetworkConfig", grids: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
    """Distances for M actions on each of B images from their distance grids: the
    trilinear interpolation between the 8 grid nodes around each action, periodic in
    theta (a parallel jaw turned by 180 degrees is the same grasp); x and y beyond
    the grid are clamped to its edge.

    Args:
        grids: (B, T, N, N) from `image_features` (theta, y, x).
        feats: (B, M, 4) action features.

    Returns:
        (B, M).
    """
    flat = grids.reshape(grids.shape[0], -1)
    out = 0.0
    for idx, weight in grid_corners(cfg, feats):
        out = out + torch.gather(flat, 1, idx) * weight
    return out


class _WeightsMemo:
    """A memo of something computed from parameters, for inference.

    Keyed on the parameters' storage and version counters, so an optimizer step,
    `load_state_dict` or a dtype/device move invalidates it. A pure cache of a function
    of the weights (results do not depend on whether it is warm); dropped on copy and
    pickle (oneDNN tensors are not copyable).
    """

    def __init__(self) -> None:
        self._key: Optional[tuple] = None
        self._value = None

    def _cached(self, tensors: tuple, make):
        """`make()`, recomputed when any of `tensors` changed; None where they have no
        version counter (inference tensors: no safe key, so no cache)."""
        try:
            key = tuple((t.data_ptr(), t._version) for t in tensors)
        except RuntimeError:
            return None
        if key != self._key:
            with torch.no_grad():
                self._value = make()
            self._key = key
        return self._value

    def __deepcopy__(self, memo: dict):
        return type(self)()

    def __reduce__(self):
        return (type(self), ())


class _PackedWeights(_WeightsMemo):
    """(weight, bias) converted to oneDNN tensors (`DistanceCNN._ip1_packed`)."""

    def __init__(self) -> None:
        super().__init__()
        # torch builds without oneDNN, or a failing conversion, use the default path.
        self._usable = torch.backends.mkldnn.is_available()

    def get(self, weight: torch.Tensor, bias: torch.Tensor):
        """The oneDNN (weight, bias) pair, or None if unavailable."""
        if not self._usable:
            return None
        try:
            return self._cached((weight, bias),
                                lambda: (weight.detach().to_mkldnn(), bias.detach().to_mkldnn()))
        except RuntimeError:
            self._usable = False
            return None


class _SplitWeights(_WeightsMemo):
    """IP1's weight in the two layouts `DistanceCNN._ip1_split` reads: ``by_channel``
    (C2, P*P, out) for the per-channel weighted sums in one batched product, and
    ``by_input`` (C2*P*P, out), whose rows are gathered for the ambiguous inputs."""

    def get(self, weight: torch.Tensor, channels: int):
        """(by_channel, by_input), or None where the weight has no version counter."""
        def make():
            by_input = weight.detach().t().contiguous()
            return by_input.reshape(channels, -1, weight.shape[0]).contiguous(), by_input

        return self._cached((weight,), make)


class DistanceCNN(nn.Module):
    """The paper's distance-to-nearest-grasp CNN, with an exact factored fast path.

    Inputs are *normalized* images (`normalize_depth`, or `preprocess`) and actions
    as raw (x, y, theta) or as features (`action_features`).

    Three equal forms (up to rounding):

    * `forward` / `forward_direct`: the paper's graph, (B images, B actions) -> (B,).
    * `image_features` + `score_actions`: control; one image, K candidate actions.
    * `forward_factored`: training; B images, each with M labelled actions -> (B, M).

    Construction never touches torch's global RNG: the layers are created on the meta
    device and initialised from `generator` (a fresh generator seeded 0 by default).

    Args:
        config: Architecture and normalization; defaults to `NetworkConfig()`.
        generator: Source of the initial weights.
        dtype: Floating dtype of the parameters.
    """

    def __init__(
        self,
        config: Optional[NetworkConfig] = None,
        *,
        generator: Optional[torch.Generator] = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        self.config = config if config is not None else NetworkConfig()
        cfg = self.config
        meta = {"device": "meta", "dtype": dtype}
        self.window = cfg.action_fusion == "window"
        self.grid = cfg.action_fusion == "grid"
        self.conv1 = nn.Conv2d(1, cfg.conv1_channels, cfg.kernel, **meta)
        # Window fusion: the action's angle and the reference depth go to IP1's output
        # (not x, y: where the candidate lies is where the window lies). The grid head
        # has no action input.
        self.ip_action = (nn.Linear(3, cfg.ip1, **meta) if self.window
                          else None if self.grid
                          else nn.Linear(4, cfg.conv1_channels, **meta))
        self.conv2 = nn.Conv2d(cfg.conv1_channels, cfg.conv2_channels, cfg.kernel, **meta)
        self.ip1 = nn.Linear(cfg.num_features, cfg.ip1, **meta)
        outputs = math.prod(cfg.grid_shape()) if self.grid else 1
        self.ip2 = nn.Linear(cfg.ip1, outputs, **meta)
        # Module.to_empty would do the same, but its first call imports torch's symbolic
        # shape machinery (~0.4 s of every worker process's start).
        for layer in self.children():
            for name, p in list(layer.named_parameters(recurse=False)):
                setattr(layer, name, nn.Parameter(torch.empty(p.shape, dtype=p.dtype)))
        self.reset_parameters(generator)

    @torch.no_grad()
    def reset_parameters(self, generator: Optional[torch.Generator] = None) -> None:
        """He-uniform weights (for leaky ReLU), uniform +-1/sqrt(fan_in) biases.

        Args:
            generator: Random source; None means a fresh generator seeded 0.
        """
        g = generator if generator is not None else torch.Generator().manual_seed(0)
        for layer in (self.conv1, self.ip_action, self.conv2, self.ip1, self.ip2):
            if layer is None:
                continue
            nn.init.kaiming_uniform_(
                layer.weight, a=self.config.leaky_slope, nonlinearity="leaky_relu", generator=g
            )
            fan_in = layer.weight[0].numel()
            bound = 1.0 / math.sqrt(fan_in)
            layer.bias.uniform_(-bound, bound, generator=g)

    # -- helpers -------------------------------------------------------------------

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the parameters."""
        return self.conv1.weight.dtype

    def preprocess(self, depth: ArrayLike) -> torch.Tensor:
        """`normalize_depth` with this net's config and dtype -> (B, 1, H, W)."""
        return normalize_depth(depth, self.config, dtype=self.dtype)

    def _lrelu(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(x, self.config.leaky_slope)

    def _check_images(self, images: torch.Tensor) -> None:
        s = self.config.image_size
        if images.ndim != 4 or tuple(images.shape[1:]) != (1, s, s):
            raise ValueError(
                f"images: expected shape (B, 1, {s}, {s}) (normalized depth), "
                f"got {tuple(images.shape)}"
            )

    def _features(self, actions: ArrayLike) -> torch.Tensor:
        return action_features(actions, self.config, dtype=self.dtype)

    def _head(self, h: torch.Tensor, *, fast_ip1: bool = False) -> torch.Tensor:
        """IP1 -> lrelu -> IP2 -> scaled softplus on flattened Pool2 activations."""
        y = self._ip1_packed(h) if fast_ip1 else None
        if y is None:
            y = self.ip1(h)
        return self._after_ip1(y)

    def _after_ip1(self, y: torch.Tensor) -> torch.Tensor:
        """lrelu -> IP2 -> scaled softplus on IP1's pre-activation."""
        z = self.ip2(self._lrelu(y)).squeeze(-1)
        return self.config.output_scale_m * F.softplus(z)

    def _ip1_packed(self, h: torch.Tensor) -> Optional[torch.Tensor]:
        """IP1 through oneDNN with cached weights, or None where that does not apply.

        IP1 is the per-action floor. On the machines measured (AMD EPYC, torch's MKL
        build) oneDNN's fp32 GEMM runs this (K, 8450) @ (8450, 500) product about 2x
        faster than the default MKL path. It has no autograd, so it is used only when
        no gradient is wanted, for float32 on CPU. The result is the same float32
        product up to summation order (~1e-6 relative).
        """
        w, b = self.ip1.weight, self.ip1.bias
        if (
            h.dtype != torch.float32
            or w.dtype != torch.float32
            or h.device.type != "cpu"
            or (torch.is_grad_enabled() and (h.requires_grad or w.requires_grad or b.requires_grad))
        ):
            return None
        packed = self._ip1_cache.get(w, b)
        if packed is None:
            return None
        return F.linear(h.contiguous().to_mkldnn(), *packed).to_dense()

    def _weights_memo(self, kind: type):
        # Created lazily so modules built by other means (e.g. deepcopy) get one too.
        key = f"_memo_{kind.__name__}"
        memo = self.__dict__.get(key)
        if memo is None:
            memo = self.__dict__[key] = kind()
        return memo

    @property
    def _ip1_cache(self) -> "_PackedWeights":
        return self._weights_memo(_PackedWeights)

    @property
    def _ip1_split_cache(self) -> "_SplitWeights":
        return self._weights_memo(_SplitWeights)

    # Above this fraction of ambiguous IP1 inputs the dense product is cheaper (the split
    # costs two passes over the weights plus the per-candidate product on those inputs).
    _SPLIT_MAX_AMBIGUOUS = 0.6

    def _ip1_split(self, features: torch.Tensor, offsets: torch.Tensor) -> Optional[torch.Tensor]:
        """IP1 for K actions on one image, split by the sign of lrelu's argument.

        ``h_k[j, p] = lrelu(Z[j, p] + c_k[j])`` (Z: `image_features`, c_k:
        `action_offsets`). Where ``Z[j, p] + min_k c_k[j] > 0`` every candidate is on the
        identity branch; where ``Z[j, p] + max_k c_k[j] <= 0`` every candidate is on the
        ``slope`` branch. On both, ``h_k = s (Z + c_k)`` with s = 1 or slope, so their
        share of IP1 is ``W_s Z + M c_k`` with ``M[:, j] = sum_p s W[:, j, p]``: one
        pass over W for all K. The ambiguous inputs go through the per-candidate
        product. Returns None (use the dense product) where it does not apply: gradient
        wanted, not float32 on CPU, no candidates, or too many ambiguous inputs.

        Args:
            features: (C2, P, P) of one image.
            offsets: (K, C2).

        Returns:
            IP1's pre-activation, (K, out).
        """
        w, b = self.ip1.weight, self.ip1.bias
        if (
            features.dtype != torch.float32
            or w.dtype != torch.float32
            or features.device.type != "cpu"
            or (torch.is_grad_enabled()
                and (features.requires_grad or offsets.requires_grad or w.requires_grad))
            or offsets.shape[0] == 0
        ):
            return None
        channels = features.shape[0]
        z = features.reshape(channels, -1)  # (C2, P*P)
        lo = offsets.min(dim=0).values[:, None]
        hi = offsets.max(dim=0).values[:, None]
        on = z + lo > 0
        off = z + hi <= 0
        ambiguous = (~(on | off)).reshape(-1).nonzero().squeeze(1)
        if ambiguous.numel() > self._SPLIT_MAX_AMBIGUOUS * z.numel():
            return None
        layouts = self._ip1_split_cache.get(w, channels)
        if layouts is None:
            return None
        by_channel, by_input = layouts
        slope = self.config.leaky_slope
        s = torch.where(on, 1.0, torch.where(off, slope, 0.0)).to(z.dtype)
        # One batched pass over W: row 0 gives sum_p s Z W[:, j, p], row 1 gives M[:, j].
        sums = torch.bmm(torch.stack((s * z, s), dim=1), by_channel)  # (C2, 2, out)
        y = b + sums[:, 0].sum(dim=0) + offsets @ sums[:, 1]
        if ambiguous.numel():
            h = F.leaky_relu(z.reshape(-1)[ambiguous] + offsets[:, ambiguous // z.shape[1]], slope)
            y = y + h @ by_input.index_select(0, ambiguous)
        return y

    # -- direct form -----------------------------------------------------------------

    def forward_direct(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """The paper's graph, literally: one image and one action per row.

        Args:
            images: Normalized depth, (B, 1, S, S).
            actions: (B, 3) raw or (B, 4) features.

        Returns:
            Distances [m], (B,), > 0.
        """
        self._check_images(images)
        feats = self._features(actions)
        if feats.ndim != 2 or feats.shape[0] != images.shape[0]:
            raise ValueError(
                f"actions: expected shape ({images.shape[0]}, 3 or 4) to match "
                f"{images.shape[0]} images, got {tuple(feats.shape)}"
            )
        if self.window:
            return self._window_scores(self.image_features(images), feats[:, None])[:, 0]
        if self.grid:
            return self._grid_scores(self.image_features(images), feats[:, None])[:, 0]
        x = F.max_pool2d(self._lrelu(self.conv1(images)), 2)
        x = x + self.ip_action(feats)[:, :, None, None]  # tiled over Pool1's H, W
        x = F.max_pool2d(self._lrelu(self.conv2(x)), 2)
        return self._head(x.flatten(1))

    def forward(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Same as `forward_direct`."""
        return self.forward_direct(images, actions)

    # -- factored (fast) form ----------------------------------------------------------

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """The action-independent part: pool2(Conv2(Pool1(lrelu(Conv1(I))))).

        Conv2's bias is included; Conv2's leaky ReLU is *not* (it comes after the
        action's per-channel shift, see the module docstring).

        Args:
            images: Normalized depth, (B, 1, S, S).

        Returns:
            (B, C2, P, P): (B, 50, 13, 13) for the defaults.
        """
        if self.grid:
            return self._after_ip1_grid(self.grid_hidden(images))
        self._check_images(images)
        x = F.max_pool2d(self._lrelu(self.conv1(images)), 2)
        if self.window:
            fmap = self._lrelu(self.conv2(x))
            ref = self._reference_depth(images)[:, None, None, None]
            return torch.cat((fmap, ref.expand(-1, 1, *fmap.shape[2:])), dim=1)
        return F.max_pool2d(self.conv2(x), 2)

    def action_offsets(self, actions: ArrayLike) -> torch.Tensor:
        """Per-channel Conv2-output shift c(a) caused by the tiled action input.

        ``c = S @ IP_a(f)`` with ``S[o, i] = sum over taps of W2[o, i]``, folded into one
        affine map 4 -> C2 (so K actions cost a (K, 4) @ (4, C2) product).

        Args:
            actions: (..., 3) raw or (..., 4) features.

        Returns:
            (..., C2).
        """
        if self.window or self.grid:
            raise ValueError(f"action_offsets: a {self.config.action_fusion!r} net has no "
                             "per-channel action shift")
        feats = self._features(actions)
        tap_sums = self.conv2.weight.sum(dim=(2, 3))  # (C2, C1)
        weight = tap_sums @ self.ip_action.weight  # (C2, 4)
        bias = tap_sums @ self.ip_action.bias  # (C2,)
        return F.linear(feats, weight, bias)

    # -- window fusion -----------------------------------------------------------------

    def _reference_depth(self, images: torch.Tensor) -> torch.Tensor:
        """Each image's median depth [m] (clipped as the input is): the depth at which a
        candidate's (x, y) in metres is placed in the image. (B,)"""
        cfg = self.config
        depth = images.flatten(1) * cfg.depth_scale_m + cfg.depth_offset_m
        return depth.median(dim=1).values

    def _window_grid(self, feats: torch.Tensor, ref: torch.Tensor,
                     side_m: Optional[float] = None) -> torch.Tensor:
        """grid_sample coordinates of every candidate's window on the lrelu(Conv2) map.

        Args:
            feats: (B, M, 4) action features; ref: (B,) reference depths [m].
            side_m: The window's side [m]; default `window_side_m`.

        Returns:
            (B, M * n, n, 2), n = `window_samples`, in align_corners=True units.
        """
        cfg = self.config
        n = cfg.window_samples
        side = cfg.feature_shape()[1]  # the Conv2 map's side (26 for the defaults)
        centre = feats[..., :2] * cfg.action_xy_scale_m  # (B, M, 2) in G [m]
        # theta from (cos 2theta, sin 2theta), in (-90, 90] degrees: the window's x axis
        # (the closing direction) is at +theta in the (x_G, y_G) = (u, v) plane.
        theta = 0.5 * torch.atan2(feats[..., 3], feats[..., 2])
        e1 = torch.stack((torch.cos(theta), torch.sin(theta)), dim=-1)  # (B, M, 2)
        e2 = torch.stack((-torch.sin(theta), torch.cos(theta)), dim=-1)
        step = (cfg.window_side_m if side_m is None else side_m) / n
        s = (torch.arange(n, dtype=feats.dtype, device=feats.device) - (n - 1) / 2.0) * step
        # points[b, m, i, j] = centre + s[j] e1 + s[i] e2 (row i along e2, column j along e1)
        pts = (centre[:, :, None, None, :] + s[None, None, None, :, None] * e1[:, :, None, None, :]
               + s[None, None, :, None, None] * e2[:, :, None, None, :])
        cam = torch.tensor([cfg.camera_x_G_m, cfg.camera_y_G_m], dtype=feats.dtype,
                           device=feats.device)
        pixels = ((pts - cam) * (cfg.focal_px / ref[:, None, None, None, None])
                  + (cfg.image_size / 2.0 - 0.5))  # (u, v) in input pixels
        # Conv2 output j sees input pixels centred at 2j + 3 (k - 1) / 2 + 0.5 (k = 5: 2j + 6.5).
        k = cfg.kernel
        centre0 = (k - 1) / 2.0 + 2.0 * (k - 1) / 2.0 + 0.5
        grid = (pixels - centre0) / 2.0 * (2.0 / (side - 1)) - 1.0
        b, m = feats.shape[:2]
        return grid.reshape(b, m * n, n, 2)

    def _window_scores(self, features: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Distances for M actions on each of B images from `image_features` (window).

        Args:
            features: (B, C2 + 1, S, S): lrelu(Conv2) and the reference-depth channel.
            feats: (B, M, 4) action features.

        Returns:
            (B, M).
        """
        cfg = self.config
        b, m = feats.shape[:2]
        n = cfg.window_samples
        fmap, ref = features[:, :-1], features[:, -1, 0, 0]
        c2, half = fmap.shape[1], n // 2
        sides = [cfg.window_side_m] + ([cfg.context_side_m] if cfg.context_side_m > 0 else [])
        parts = []
        for side_m in sides:
            grid = self._window_grid(feats, ref, side_m)
            win = F.grid_sample(fmap, grid, mode="bilinear", padding_mode="zeros",
                                align_corners=True)  # (B, C2, M * n, n)
            # 2x2 max-pool in place (n is even: no block straddles two windows), then
            # the 4x smaller result goes to one row per candidate. (Four strided maxima:
            # ~10x faster on CPU than max_pool2d or amax here.)
            w = win.reshape(b, c2, m * half, 2, half, 2)
            win = torch.maximum(torch.maximum(w[:, :, :, 0, :, 0], w[:, :, :, 0, :, 1]),
                                torch.maximum(w[:, :, :, 1, :, 0], w[:, :, :, 1, :, 1]))
            parts.append(win.reshape(b, c2, m, half * half).transpose(1, 2)
                         .reshape(b * m, c2 * half * half))
        h = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)
        z = (ref - cfg.depth_offset_m) / cfg.depth_scale_m
        extra = torch.cat((feats[..., 2:], z[:, None, None].expand(b, m, 1)),
                          dim=-1).reshape(b * m, 3)
        y = self.ip1(h) + self.ip_action(extra)
        return self._after_ip1(y).reshape(b, m)

    # -- grid head ---------------------------------------------------------------------

    def _grid_corners(self, feats: torch.Tensor) -> list:
        return grid_corners(self.config, feats)

    def _grid_scores(self, grids: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        return grid_scores(self.config, grids, feats)

    def _after_ip1_grid(self, hidden: torch.Tensor) -> torch.Tensor:
        """The whole distance grid, (..., T, N, N), from `grid_hidden` (..., ip1)."""
        z = self.ip2(hidden)
        return (self.config.output_scale_m * F.softplus(z)).reshape(
            *hidden.shape[:-1], *self.config.grid_shape())

    def grid_hidden(self, images: torch.Tensor) -> torch.Tensor:
        """Grid head: the trunk up to IP2's input, lrelu(IP1(...)), (B, ip1). IP2 maps it
        to the distance at every grid node; `score_grid_nodes` evaluates only the nodes
        a set of actions needs."""
        self._check_images(images)
        if not self.grid:
            raise ValueError(f"grid_hidden: a {self.config.action_fusion!r} net has no grid head")
        x = F.max_pool2d(self._lrelu(self.conv1(images)), 2)
        h = F.max_pool2d(self._lrelu(self.conv2(x)), 2).flatten(1)
        return self._lrelu(self.ip1(h))

    def score_grid_nodes(self, hidden: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Distances for K actions on one image from `grid_hidden`, computing IP2 only at
        the grid nodes around them (the controller's candidates lie within a few cm and
        tens of degrees of the hand: about 1/20 of the 18 x 33 x 33 nodes; for more than
        1/32 as many actions as nodes, IP2 runs over the whole grid). Equal to
        `score_actions(image_features(...))` (same interpolation of the same node values;
        IP2's rows are the same dot products, so the values agree to float rounding).

        Args:
            hidden: (ip1,) or (1, ip1), `grid_hidden` of one image.
            actions: (K, 3) raw or (K, 4) features.

        Returns:
            Distances [m], (K,).
        """
        if hidden.ndim == 2 and hidden.shape[0] == 1:
            hidden = hidden[0]
        if tuple(hidden.shape) != (self.config.ip1,):
            raise ValueError(f"hidden: expected shape ({self.config.ip1},) or (1, "
                             f"{self.config.ip1}) (grid_hidden of one image), got "
                             f"{tuple(hidden.shape)}")
        feats = self._features(actions)
        if feats.ndim != 2:
            raise ValueError(
                f"actions: expected shape (K, 3 or 4), got {tuple(torch.as_tensor(actions).shape)}")
        if 4 * 8 * feats.shape[0] > self.ip2.out_features:
            # Many actions (e.g. 2,048 over the whole view need ~40% of the nodes):
            # gathering rows costs more than IP2 over the whole grid.
            grids = self._after_ip1_grid(hidden)
            return self._grid_scores(grids[None], feats[None])[0]
        corners = self._grid_corners(feats[None])
        nodes, where = torch.unique(torch.cat([idx for idx, _ in corners], dim=1),
                                    return_inverse=True)
        z = F.linear(hidden, self.ip2.weight[nodes], self.ip2.bias[nodes])
        values = self.config.output_scale_m * F.softplus(z)
        k = feats.shape[0]
        out = 0.0
        for j, (_, weight) in enumerate(corners):
            out = out + values[where[:, j * k:(j + 1) * k]] * weight
        return out[0]

    def _score_features(self, features: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        # features (..., C2, P, P) broadcast against offsets (..., C2): one row of IP1
        # input per action, then the head as a single (N, 8450) @ (8450, 500) product.
        h = self._lrelu(features + offsets[..., None, None])
        lead = h.shape[:-3]
        out = self._head(h.reshape(-1, self.config.num_features), fast_ip1=True)
        return out.reshape(lead)

    def score_actions(self, features: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Distances for K candidate actions on one image (control).

        Call under `torch.inference_mode()` in a controller: no autograd graph is
        kept and, for float32 on CPU, IP1 is split (`_ip1_split`): the inputs whose
        leaky ReLU branch is the same for all K candidates cost one pass over IP1's
        weights for all of them, and only the others go through the per-candidate
        product (about 2x faster for the controller's candidates on the machines
        measured). Where that does not apply, all K actions go through IP1 as one
        (K, 8450) @ (8450, 500) product on cached oneDNN weights. The result is
        differentiable when a gradient is wanted.

        Args:
            features: `image_features` of one image, (C2, P, P) or (1, C2, P, P).
            actions: (K, 3) raw or (K, 4) features.

        Returns:
            Distances [m], (K,).
        """
        expected = self.config.feature_shape()
        if features.ndim == 4 and features.shape[0] == 1:
            features = features[0]
        if tuple(features.shape) != expected:
            raise ValueError(
                f"features: expected shape {expected} or (1, *{expected}) "
                f"(image_features of one image), got {tuple(features.shape)}"
            )
        if self.window or self.grid:
            feats = self._features(actions)
            if feats.ndim != 2:
                raise ValueError(
                    f"actions: expected shape (K, 3 or 4), got {tuple(torch.as_tensor(actions).shape)}")
            scores = self._grid_scores if self.grid else self._window_scores
            return scores(features[None], feats[None])[0]
        offsets = self.action_offsets(actions)
        if offsets.ndim != 2:
            raise ValueError(
                f"actions: expected shape (K, 3 or 4), got {tuple(torch.as_tensor(actions).shape)}"
            )
        y = self._ip1_split(features, offsets)
        if y is None:
            return self._score_features(features[None], offsets)
        return self._after_ip1(y)

    def forward_factored(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        """Distances for M actions on each of B images (training), differentiable.

        The image part runs once per image and is expanded over its M actions.

        Args:
            images: Normalized depth, (B, 1, S, S).
            actions: (B, M, 3) raw or (B, M, 4) features.

        Returns:
            Distances [m], (B, M).
        """
        features = self.image_features(images)
        if self.window or self.grid:
            feats = self._features(actions)
            if feats.ndim != 3 or feats.shape[0] != images.shape[0]:
                raise ValueError(
                    f"actions: expected shape ({images.shape[0]}, M, 3 or 4) to match "
                    f"{images.shape[0]} images, got {tuple(torch.as_tensor(actions).shape)}")
            scores = self._grid_scores if self.grid else self._window_scores
            return scores(features, feats)
        offsets = self.action_offsets(actions)
        if offsets.ndim != 3 or offsets.shape[0] != images.shape[0]:
            raise ValueError(
                f"actions: expected shape ({images.shape[0]}, M, 3 or 4) to match "
                f"{images.shape[0]} images, got {tuple(torch.as_tensor(actions).shape)}"
            )
        return self._score_features(features[:, None], offsets)


# ----------------------------------------------------------------------------------
# The mirror symmetry (test-time averaging)
# ----------------------------------------------------------------------------------


def mirror_actions(actions: ArrayLike) -> ArrayLike:
    """Actions reflected in the hand's y-z plane: (x, y, theta) -> (-x, y, -theta);
    features [x/s, y/s, cos 2theta, sin 2theta] -> [-x/s, y/s, cos 2theta, -sin 2theta].

    The wrist camera sits on that plane (`X_GC` = (0, -0.05, -0.115), axes along the
    grasp frame's), the 2F-85's fingers are mirror images across it, and gravity and
    friction do not care, so the distance to the nearest grasp of a mirrored scene, seen
    in the image flipped left-right (`mirror_images`), for the mirrored action, is the
    distance of the original: d(flip(I), mirror(a)) = d(I, a).
    """
    a = actions.clone() if isinstance(actions, torch.Tensor) else np.array(actions, copy=True)
    if a.shape[-1] not in (3, 4):
        raise ValueError(f"actions: expected last dimension 3 or 4, got shape {tuple(a.shape)}")
    a[..., 0] = -a[..., 0]
    a[..., a.shape[-1] - 1] = -a[..., a.shape[-1] - 1]
    return a


def mirror_images(images: ArrayLike) -> ArrayLike:
    """Depth images flipped left-right (the last axis: image columns, the camera's x)."""
    if isinstance(images, torch.Tensor):
        return images.flip(-1)
    return np.ascontiguousarray(np.asarray(images)[..., ::-1])


class MirrorAveragedCNN(nn.Module):
    """A `DistanceCNN` whose every distance is the mean of d(I, a) and
    d(flip(I), mirror(a)) (`mirror_actions`): test-time averaging over the one symmetry
    that the wrist camera, the gripper and physics share. The same interface as the
    network it wraps (`preprocess`, `image_features`, `score_actions`, `forward`,
    `forward_factored`), twice its cost; no weights of its own.

    `image_features` returns both images' features, (B, 2, C2, P, P); `score_actions`
    takes them for one image ((2, C2, P, P) or (1, 2, C2, P, P)).
    """

    def __init__(self, base: "DistanceCNN") -> None:
        super().__init__()
        if isinstance(base, MirrorAveragedCNN):
            raise ValueError("base: already mirror-averaged")
        self.base = base
        self.config = base.config

    @property
    def dtype(self) -> torch.dtype:
        return self.base.dtype

    def preprocess(self, depth: ArrayLike) -> torch.Tensor:
        return self.base.preprocess(depth)

    def forward(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        return 0.5 * (self.base.forward(images, actions)
                      + self.base.forward(mirror_images(images), mirror_actions(actions)))

    def forward_factored(self, images: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        return 0.5 * (self.base.forward_factored(images, actions)
                      + self.base.forward_factored(mirror_images(images), mirror_actions(actions)))

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        return torch.stack((self.base.image_features(images),
                            self.base.image_features(mirror_images(images))), dim=1)

    def score_actions(self, features: torch.Tensor, actions: ArrayLike) -> torch.Tensor:
        if features.ndim == 5 and features.shape[0] == 1:
            features = features[0]
        if features.ndim != 4 or features.shape[0] != 2:
            raise ValueError(
                "features: expected MirrorAveragedCNN.image_features of one image, "
                f"(2, C2, P, P) or (1, 2, C2, P, P), got {tuple(features.shape)}")
        return 0.5 * (self.base.score_actions(features[0], actions)
                      + self.base.score_actions(features[1], mirror_actions(actions)))


# ----------------------------------------------------------------------------------
# Weights I/O (safetensors only: a weights file cannot run code)
# ----------------------------------------------------------------------------------


def tensors_sha256(tensors: dict[str, torch.Tensor]) -> str:
    """SHA-256 over names, dtypes, shapes and raw bytes of tensors, in sorted name order.

    safetensors has no checksum, so a flipped byte inside the tensor data would load
    as different weights without this.
    """
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}\0{t.dtype}\0{tuple(t.shape)}\0".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def save_weights(
    model: DistanceCNN, path: Union[str, os.PathLike], *, metadata: dict[str, Any]
) -> None:
    """Writes the weights as a safetensors file with self-describing metadata.

    The file's metadata holds: ``format`` (`WEIGHTS_FORMAT`), ``config`` (the
    `NetworkConfig` as JSON: architecture and input normalization), ``code_version``
    (`drake_grasp.__version__`), ``tensors_sha256`` (`tensors_sha256`) and
    ``user_metadata`` (`metadata` as JSON; put e.g. ``dataset_manifest_sha256``,
    training run id, epoch there). The file is written to a temporary name in the
    same folder and renamed, so a crash never leaves a half-written file at `path`.

    Args:
        model: The network.
        path: Destination, conventionally ``*.safetensors``.
        metadata: JSON-serialisable user metadata (may be empty).

    Raises:
        ValueError: `metadata` is not a dict or not JSON-serialisable.
    """
    if not isinstance(metadata, dict):
        raise ValueError(f"metadata: expected a dict, got {type(metadata).__name__}")
    reserved = sorted(set(metadata) & set(_RESERVED_USER_KEYS))
    if reserved:
        raise ValueError(f"metadata: keys {reserved} are reserved (load_weights fills them in)")
    try:
        user_json = json.dumps(metadata, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"metadata: must be JSON-serialisable: {e}") from e
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in model.state_dict().items()}
    header = {
        _KEY_FORMAT: WEIGHTS_FORMAT,
        _KEY_CONFIG: json.dumps(model.config.to_dict(), sort_keys=True),
        _KEY_CODE_VERSION: drake_grasp.__version__,
        _KEY_TENSORS_SHA256: tensors_sha256(tensors),
        _KEY_USER: user_json,
    }
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        safetensors.torch.save_file(tensors, tmp, metadata=header)
        os.chmod(tmp, 0o644)  # mkstemp makes it owner-only; weights are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_weights(
    path: Union[str, os.PathLike], *, expected_config: Optional[NetworkConfig] = None
) -> tuple[DistanceCNN, dict[str, Any]]:
    """Loads and verifies a file written by `save_weights`.

    Checks, in order: the file exists; it parses as safetensors; its metadata has the
    expected format and parses; the tensor data matches its SHA-256; the stored config
    is valid and (if given) equals `expected_config`; the tensors' names and shapes
    equal the state dict of the net that config builds. The model gets the dtype of
    the stored tensors and is returned in eval mode.

    Args:
        path: A ``.safetensors`` file from `save_weights`.
        expected_config: If given, every field must match the stored config.

    Returns:
        (model, metadata): metadata is the user metadata given to `save_weights`,
        plus ``config`` (dict), ``code_version`` and ``format``.

    Raises:
        FileNotFoundError: No file at `path`.
        ValueError: Anything else wrong; the message names the file and the key/field.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such weights file")
    try:
        with safetensors.safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:  # SafetensorError, truncated buffers, bad JSON header, ...
        raise ValueError(f"{path}: not a valid safetensors file ({type(e).__name__}: {e})") from e

    for key in (_KEY_FORMAT, _KEY_CONFIG, _KEY_CODE_VERSION, _KEY_TENSORS_SHA256, _KEY_USER):
        if key not in header:
            raise ValueError(
                f"{path}: metadata key {key!r} missing (not a drake_grasp DistanceCNN "
                f"weights file? found keys {sorted(header)})"
            )
    if header[_KEY_FORMAT] != WEIGHTS_FORMAT:
        raise ValueError(
            f"{path}: metadata 'format' is {header[_KEY_FORMAT]!r}, expected {WEIGHTS_FORMAT!r}"
        )
    digest = tensors_sha256(tensors)
    if digest != header[_KEY_TENSORS_SHA256]:
        raise ValueError(
            f"{path}: tensor data does not match metadata 'tensors_sha256' (file corrupted "
            f"or modified): stored {header[_KEY_TENSORS_SHA256]}, computed {digest}"
        )
    parsed = {}
    for key in (_KEY_CONFIG, _KEY_USER):
        try:
            parsed[key] = json.loads(header[key])
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: metadata {key!r} is not valid JSON: {e}") from e
    if not isinstance(parsed[_KEY_USER], dict):
        raise ValueError(f"{path}: metadata 'user_metadata' must be a JSON object")
    config = NetworkConfig.from_dict(parsed[_KEY_CONFIG], source=f"{path}: metadata 'config'")

    if expected_config is not None:
        for field in dataclasses.fields(NetworkConfig):
            stored, wanted = getattr(config, field.name), getattr(expected_config, field.name)
            if stored != wanted:
                raise ValueError(
                    f"{path}: config field {field.name!r} is {stored!r} in the file, "
                    f"expected {wanted!r}"
                )

    dtypes = {t.dtype for t in tensors.values()}
    if len(dtypes) != 1 or not next(iter(dtypes)).is_floating_point:
        raise ValueError(
            f"{path}: expected all tensors to share one floating dtype, got "
            + ", ".join(f"{k}: {t.dtype}" for k, t in sorted(tensors.items()))
        )
    model = DistanceCNN(config, dtype=next(iter(dtypes)))
    expected = model.state_dict()
    for key in sorted(set(expected) | set(tensors)):
        if key not in tensors:
            raise ValueError(f"{path}: tensor {key!r} missing (the stored config needs it)")
        if key not in expected:
            raise ValueError(f"{path}: unexpected tensor {key!r} (not in the stored config's net)")
        if tuple(tensors[key].shape) != tuple(expected[key].shape):
            raise ValueError(
                f"{path}: tensor {key!r} has shape {tuple(tensors[key].shape)}, the stored "
                f"config needs {tuple(expected[key].shape)}"
            )
    model.load_state_dict(tensors, strict=True)
    model.eval()
    metadata = dict(parsed[_KEY_USER])
    metadata.update(
        config=config.to_dict(),
        code_version=header[_KEY_CODE_VERSION],
        format=header[_KEY_FORMAT],
    )
    return model, metadata
