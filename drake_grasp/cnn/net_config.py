"""The distance CNN's configuration and input encoding: `NetworkConfig` (architecture,
the action fusion and its fields, and input normalization: everything that changes what
a weight means, stored in a weights file's metadata), the checks and dict form of that
config, and the two encodings it defines, `normalize_depth` (depth in metres -> the
net's input image) and `action_features` (raw (x, y, theta) -> [x/s, y/s, cos 2theta,
sin 2theta]); the model itself is `drake_grasp.cnn.network.DistanceCNN`.
"""

# No `from __future__ import annotations`: NetworkConfig may be nested in scenario
# dataclasses read by Drake's yaml_load_typed, which needs real annotation objects.

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Optional, Union

import numpy as np
import torch

from drake_grasp.geometry.camera import focal_length_px

ArrayLike = Union[np.ndarray, torch.Tensor]

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
        return focal_length_px(self.image_size, self.camera_fov_deg)

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
