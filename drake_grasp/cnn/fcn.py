"""The height-map FCN: a distance function that sees the wrist depth image as a metric
height map (README *A metric height map and a fully convolutional net*).

Each 64x64 depth image is back-projected, every pixel with its own depth (the wrist
camera looks straight down), into the height above the table on a metric lattice (5 mm
cells, +-18 cm around the camera's axis; the highest sample per cell, empty cells from
their neighbours, a second channel marking the camera's footprint). The camera's height
above the table is the hand's own (proprioception: the controller's believed pose, the
`camera_height` port of `GraspController`), not something the image gives. A residual
net of dilated 3x3 convolutions maps the map to the grid head's 18 x 33 x 33 distances
(theta bins x y x x nodes, 1 cm and 10 degrees apart; `net_config.NetworkConfig`'s grid),
and a candidate's distance is the trilinear interpolation there (`grid_head.grid_scores`).

With a grasp head (a second output per node: "a true grasp lies within half a cell's
diagonal") and `FcnConfig.grasp_threshold` > 0, a node's distance is the smaller of the
distance head's and the distance, on the grid's lattice, to the nearest in-view node
whose grasp probability reaches the threshold (`grasp_map_distances`).

Weights are safetensors (`save_fcn` / `load_fcn`): the architecture, the grid and the
threshold in the metadata, a tensor checksum verified on load, no pickle. `load_cnn`
(`systems/evaluator.py`) tells such a file from a `DistanceCNN`'s by its metadata's
``format``.
"""

from __future__ import annotations

import dataclasses
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
import torch.nn as nn
import torch.nn.functional as F

import drake_grasp
from drake_grasp.cnn.grid_head import grid_scores, grid_view_mask
from drake_grasp.cnn.net_config import NetworkConfig, action_features
from drake_grasp.cnn.weights_io import tensors_sha256
from drake_grasp.core.assets import missing_weights_message

FCN_FORMAT = "drake_grasp.HeightmapFCN/1"
_KEYS = ("format", "config", "code_version", "tensors_sha256", "user_metadata")


@dataclass(frozen=True)
class FcnConfig:
    """Everything that changes what an FCN weight means; stored in its weights file."""

    width: int = 32
    dilations: tuple = (1, 2, 4, 8, 4, 2, 1)
    grasp_head: bool = False
    # > 0 (needs the grasp head): a node's distance is min(distance head, distance to the
    # nearest in-view node whose grasp probability is at least this).
    grasp_threshold: float = 0.0
    cell_m: float = 0.005
    lattice_half_m: float = 0.18
    height_scale: float = 10.0  # the net's input height is in units of 1 / height_scale m

    def __post_init__(self) -> None:
        if int(self.width) < 1:
            raise ValueError(f"FcnConfig.width: expected >= 1, got {self.width!r}")
        if not self.dilations or any(int(d) < 1 for d in self.dilations):
            raise ValueError(f"FcnConfig.dilations: expected positive integers, got "
                             f"{self.dilations!r}")
        if not 0.0 <= float(self.grasp_threshold) < 1.0:
            raise ValueError(f"FcnConfig.grasp_threshold: expected in [0, 1), got "
                             f"{self.grasp_threshold!r}")
        if self.grasp_threshold > 0 and not self.grasp_head:
            raise ValueError("FcnConfig.grasp_threshold > 0 needs grasp_head: true")
        if self.cell_m <= 0 or self.lattice_half_m <= 0:
            raise ValueError(f"FcnConfig.cell_m, lattice_half_m: expected > 0, got "
                             f"{self.cell_m!r}, {self.lattice_half_m!r}")
        object.__setattr__(self, "dilations", tuple(int(d) for d in self.dilations))

    @property
    def lattice(self) -> int:
        """Cells per side of the height map (73 for the defaults)."""
        return int(round(2 * self.lattice_half_m / self.cell_m)) + 1

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["dilations"] = list(self.dilations)
        return d

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "config") -> "FcnConfig":
        if not isinstance(data, dict):
            raise ValueError(f"{source}: expected a mapping, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{source}: unknown keys {unknown}; expected some of {sorted(known)}")
        try:
            return cls(**data)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {e}") from e


def height_maps(depth: np.ndarray, camera_height_m, grid: NetworkConfig, cfg: FcnConfig, *,
                batch: int = 2000) -> np.ndarray:
    """(B, 2, L, L) float16: height above the table (x `cfg.height_scale`) on the metric
    lattice, and the mask of the cells the camera's footprint covers, from (B, 64, 64)
    depth [m] and the camera's heights above the table (B,) [m]."""
    depth = np.asarray(depth)
    if depth.ndim == 2:
        depth = depth[None]
    cam_h = np.broadcast_to(np.asarray(camera_height_m, np.float64), (len(depth),))
    if not np.all(np.isfinite(cam_h)) or np.any(cam_h <= 0):
        raise ValueError(f"camera_height_m: expected finite heights > 0, got {cam_h[:4]}...")
    f = grid.focal_px
    size = depth.shape[-1]
    lat = cfg.lattice
    c = np.arange(size) - (size / 2.0 - 0.5)
    out = np.empty((len(depth), 2, lat, lat), np.float16)
    cols = torch.from_numpy(np.tile(c, size)).float()           # pixel u (x_G)
    rows = torch.from_numpy(np.repeat(c, size)).float()         # pixel v (y_G)
    centres = (torch.arange(lat).float() - (lat - 1) / 2) * cfg.cell_m
    for lo in range(0, len(depth), batch):
        d = torch.from_numpy(depth[lo:lo + batch].astype(np.float32)).flatten(1)
        h = torch.tensor(cam_h[lo:lo + batch], dtype=torch.float32)
        b = len(d)
        x = cols[None] * d / f
        y = rows[None] * d / f
        height = (h[:, None] - d).clamp(min=0.0)
        ix = torch.round((x + cfg.lattice_half_m) / cfg.cell_m).long()
        iy = torch.round((y + cfg.lattice_half_m) / cfg.cell_m).long()
        ok = (ix >= 0) & (ix < lat) & (iy >= 0) & (iy < lat)
        flat = torch.where(ok, iy * lat + ix, torch.full_like(ix, lat * lat))
        hm = torch.full((b, lat * lat + 1), -1.0)
        hm.scatter_reduce_(1, flat, height, reduce="amax", include_self=True)
        hm = hm[:, :-1].reshape(b, 1, lat, lat)
        # Empty cells (finer than a pixel near the table at low heights): the highest of
        # their 3x3 neighbours, twice.
        for _ in range(2):
            filled = F.max_pool2d(hm, 3, stride=1, padding=1)
            hm = torch.where(hm < 0, filled, hm)
        # The view: the camera's footprint on the table.
        half = (h * math.tan(math.radians(grid.camera_fov_deg) / 2.0))[:, None]
        inside = (centres.abs()[None] <= half)
        view = (inside[:, :, None] & inside[:, None, :]).float()[:, None]
        hm = torch.where((hm < 0) | (view == 0), torch.zeros_like(hm), hm)
        out[lo:lo + b, 0] = (hm[:, 0] * cfg.height_scale).numpy()
        out[lo:lo + b, 1] = view[:, 0].numpy()
    return out


def in_view_nodes(camera_height_m, grid: NetworkConfig) -> np.ndarray:
    """(B, N, N) mask of the grid's (y, x) nodes inside the camera's footprint on the
    table at each camera height (B,) [m] (the footprint is square)."""
    m = grid_view_mask(camera_height_m, grid)
    return m[:, :, None] & m[:, None, :]


def grasp_map_distances(logits: np.ndarray, camera_height_m, grid: NetworkConfig,
                        threshold: float) -> np.ndarray:
    """(B, T, N, N) distances [m] from each node to the nearest in-view node whose grasp
    probability is at least `threshold` (the Euclidean distance transform on the grid's
    lattice, 1 cm = 10 degrees as the grasp metric weighs them, periodic over theta's
    180 degrees); NaN for an image with none."""
    from scipy.ndimage import distance_transform_edt

    t_bins = grid.grid_shape()[0]
    pos = ((logits >= math.log(threshold / (1.0 - threshold)))
           & in_view_nodes(camera_height_m, grid)[:, None])
    out = np.full(logits.shape, np.nan, np.float32)
    for i in np.flatnonzero(pos.reshape(len(pos), -1).any(axis=1)):
        wrapped = np.concatenate([~pos[i]] * 3, axis=0)  # theta periodic: the middle copy
        edt = distance_transform_edt(wrapped)[t_bins:2 * t_bins]
        out[i] = edt * grid.grid_step_m
    return out


class HeightmapFCN(nn.Module):
    """(B, 2, L, L) height map -> (B, T, N, N) distances [m] at the grid's nodes; with a
    grasp head, also (B, T, N, N) logits of "a true grasp lies near this node"
    (`outputs`)."""

    def __init__(self, cfg: FcnConfig = FcnConfig(), grid: Optional[NetworkConfig] = None):
        super().__init__()
        self.cfg = cfg
        self.grid = grid or NetworkConfig(theta_unit="deg", action_fusion="grid")
        self.grasp_head = cfg.grasp_head
        width = cfg.width
        self.stem = nn.Sequential(
            nn.Conv2d(2, width, 3, padding=1), nn.BatchNorm2d(width), nn.LeakyReLU(0.01),
            nn.Conv2d(width, width, 3, stride=2, padding=1), nn.BatchNorm2d(width),
            nn.LeakyReLU(0.01))  # half the lattice's resolution: the grid's 1 cm nodes
        self.blocks = nn.ModuleList(
            nn.Sequential(nn.Conv2d(width, width, 3, padding=d, dilation=d),
                          nn.BatchNorm2d(width), nn.LeakyReLU(0.01)) for d in cfg.dilations)
        t_bins = self.grid.grid_shape()[0]
        self.head = nn.Conv2d(width, t_bins * (2 if cfg.grasp_head else 1), 1)

    def outputs(self, x: torch.Tensor) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """The distances [m] and the grasp logits (None without a grasp head)."""
        h = self.stem(x)
        for block in self.blocks:
            h = h + block(h)
        t_bins, n, _ = self.grid.grid_shape()
        crop = (h.shape[-1] - n) // 2
        z = self.head(h)[:, :, crop:crop + n, crop:crop + n]
        distances = self.grid.output_scale_m * F.softplus(z[:, :t_bins])
        return distances, (z[:, t_bins:] if self.grasp_head else None)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.outputs(x)[0]


class FcnDistanceModel:
    """A loaded height-map FCN as the controller's distance function: `score(depth,
    actions, camera_height_m)`. Unlike the CNN it needs the camera's height above the
    table, which `score_candidates` takes as `camera_height_m`."""

    needs_camera_height = True

    def __init__(self, net: HeightmapFCN, path: str = "") -> None:
        self.net = net.eval()
        self.path = path

    @property
    def cfg(self) -> FcnConfig:
        return self.net.cfg

    def grids(self, depth: np.ndarray, camera_height_m) -> np.ndarray:
        """(B, T, N, N) distances [m] at every grid node of each image."""
        cfg, grid = self.net.cfg, self.net.grid
        maps = torch.from_numpy(height_maps(depth, camera_height_m, grid, cfg).astype(np.float32))
        with torch.inference_mode():
            dist, logits = self.net.outputs(maps)
        dist = dist.numpy()
        if cfg.grasp_threshold > 0:
            edt = grasp_map_distances(logits.numpy(), camera_height_m, grid, cfg.grasp_threshold)
            dist = np.fmin(edt, dist)  # fmin: NaN (no grasp node) keeps the distance head
        return dist

    def score(self, depth: np.ndarray, actions: np.ndarray, camera_height_m: float) -> np.ndarray:
        """Predicted distance [m] for each of K candidate actions (K, 3) [x, y, theta_deg]
        on one depth image (64, 64) seen from `camera_height_m` above the table."""
        actions = np.asarray(actions, np.float32)
        if actions.ndim != 2 or actions.shape[1] != 3:
            raise ValueError(f"actions: expected shape (K, 3), got {actions.shape}")
        grids = torch.from_numpy(self.grids(np.asarray(depth, np.float32)[None],
                                            [float(camera_height_m)]))
        feats = action_features(actions, self.net.grid)
        return grid_scores(self.net.grid, grids, feats[None])[0].numpy().astype(float)


def save_fcn(net: HeightmapFCN, path: Union[str, os.PathLike], *, metadata: dict) -> None:
    """Writes an FCN as safetensors: ``format`` (`FCN_FORMAT`), ``config`` ({"fcn":
    FcnConfig, "grid": NetworkConfig} as JSON), ``code_version``, ``tensors_sha256``,
    ``user_metadata``; to a temporary name, then renamed (never half-written)."""
    if not isinstance(metadata, dict):
        raise ValueError(f"metadata: expected a dict, got {type(metadata).__name__}")
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in net.state_dict().items()}
    header = {
        "format": FCN_FORMAT,
        "config": json.dumps({"fcn": net.cfg.to_dict(), "grid": net.grid.to_dict()},
                             sort_keys=True),
        "code_version": drake_grasp.__version__,
        "tensors_sha256": tensors_sha256(tensors),
        "user_metadata": json.dumps(metadata, sort_keys=True, allow_nan=False),
    }
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        safetensors.torch.save_file(tensors, tmp, metadata=header)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def weights_format(path: Union[str, os.PathLike]) -> str:
    """The ``format`` in a safetensors weights file's metadata ("" when it has none)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(missing_weights_message(path))
    try:
        with safetensors.safe_open(str(path), framework="pt") as f:
            return (f.metadata() or {}).get("format", "")
    except Exception as e:
        raise ValueError(f"{path}: not a valid safetensors file ({type(e).__name__}: {e})") from e


def load_fcn(path: Union[str, os.PathLike]) -> tuple[FcnDistanceModel, dict]:
    """Loads and verifies a file from `save_fcn`: (model, user metadata). Errors name the
    file and the key."""
    path = Path(path)
    fmt = weights_format(path)
    if fmt != FCN_FORMAT:
        raise ValueError(f"{path}: metadata 'format' is {fmt!r}, expected {FCN_FORMAT!r}")
    with safetensors.safe_open(str(path), framework="pt") as f:
        header = f.metadata() or {}
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    missing = [k for k in _KEYS if k not in header]
    if missing:
        raise ValueError(f"{path}: metadata keys {missing} missing")
    digest = tensors_sha256(tensors)
    if digest != header["tensors_sha256"]:
        raise ValueError(f"{path}: tensor data does not match metadata 'tensors_sha256' (file "
                         f"corrupted or modified): stored {header['tensors_sha256']}, "
                         f"computed {digest}")
    try:
        config = json.loads(header["config"])
        user = json.loads(header["user_metadata"])
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: metadata 'config' or 'user_metadata' is not valid JSON: {e}") from e
    if not isinstance(config, dict) or set(config) != {"fcn", "grid"}:
        raise ValueError(f"{path}: metadata 'config': expected the keys 'fcn' and 'grid'")
    cfg = FcnConfig.from_dict(config["fcn"], source=f"{path}: metadata 'config.fcn'")
    grid = NetworkConfig.from_dict(config["grid"], source=f"{path}: metadata 'config.grid'")
    net = HeightmapFCN(cfg, grid)
    expected = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in tensors.items()}
    if expected != found:
        diff = sorted(set(expected) ^ set(found)) or sorted(
            k for k in expected if expected[k] != found[k])
        raise ValueError(f"{path}: tensors do not match the architecture in its config "
                         f"(first differences: {diff[:4]})")
    net.load_state_dict(tensors)
    return FcnDistanceModel(net, str(path)), user
