"""Training the grid head (`NetworkConfig(action_fusion="grid")`) on dense labels.

The paper's net takes the action as an input, so every labelled offset costs a pass
through IP1: the dataset stores 10 per image. The grid head predicts the distance at
every node of a fixed grid of actions (18 x 33 x 33 for the defaults) from one pass per
image, so every image can be labelled at every node: the label of an action is the
distance from the hand pose it leads to, to the nearest ground-truth grasp of the scene
(the dataset's own label function, `grasps.distance_to_nearest_grasp`), and the shards
store each scene's grasps. A k-d tree over a scene's grasps in the metric's coordinates
(x, y, 0.001 m/deg x theta, theta periodic over 180 degrees) gives those distances
exactly (to float rounding) and fast.

    python -m drake_grasp.learning.dense_training labels --data data/ft_dense --out data/ft_dense_grid
    python -m drake_grasp.learning.dense_training train --labels data/ft_dense_grid \
        --test-data data/paper_test --init models/cnn/weights.safetensors --out data/grid_run

Only the nodes inside the image's view (the camera's footprint on the table at the image's
camera height) count in the loss: beyond it the net cannot see what decides the label.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from drake_grasp.geometry.grasp_metric import ANGLE_WEIGHT_M_PER_DEG
from drake_grasp.cnn.network import (DistanceCNN, NetworkConfig, grid_view_mask, load_weights,
                                  save_weights)
from drake_grasp.cnn.views import AUGMENTATIONS, turn_grids, turn_images
from drake_grasp.learning.common import full_float32

GRID_CONFIG = NetworkConfig(theta_unit="deg", action_fusion="grid")
_THETA_PERIOD_M = 180.0 * ANGLE_WEIGHT_M_PER_DEG
_SHIFT_M = 50.0  # x, y moved into the k-d tree's positive box
_BOX_M = 1000.0


def augment_batch(data: dict, augment: str, rng: np.random.Generator) -> dict:
    """A batch of `LabelStore.take` with each image (and its label grid) under a symmetry
    of `AUGMENTATIONS[augment]` drawn from `rng`; hand heights (and so the view masks,
    which are square about the camera's centre) are unchanged."""
    ops = AUGMENTATIONS[augment]
    if len(ops) == 1:
        return data
    pick = rng.integers(0, len(ops), len(data["depth"]))
    depth, grid = data["depth"].copy(), data["grid"].copy()
    for j, (k, flip) in enumerate(ops):
        rows = np.flatnonzero(pick == j)
        if len(rows) and (k or flip):
            depth[rows] = turn_images(depth[rows], k, flip)
            grid[rows] = turn_grids(grid[rows], k, flip)
    return {**data, "depth": depth, "grid": grid}


def grid_node_actions(cfg: NetworkConfig) -> np.ndarray:
    """The grid head's node actions (T * N * N, 3) = (x [m], y [m], theta [deg]) in the
    order of its output (theta, y, x)."""
    t_bins, n, _ = cfg.grid_shape()
    half = (n - 1) // 2
    xs = cfg.camera_x_G_m + (np.arange(n) - half) * cfg.grid_step_m
    ys = cfg.camera_y_G_m + (np.arange(n) - half) * cfg.grid_step_m
    ts = -90.0 + np.arange(t_bins) * cfg.grid_theta_step_deg
    T, Y, X = np.meshgrid(ts, ys, xs, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), T.ravel()], axis=1)


def _tree_coords(xy_theta: np.ndarray) -> np.ndarray:
    return np.column_stack([xy_theta[:, 0] + _SHIFT_M, xy_theta[:, 1] + _SHIFT_M,
                            np.mod(xy_theta[:, 2], 180.0) * ANGLE_WEIGHT_M_PER_DEG])


def nearest_grasp_tree(grasps_xy_theta: np.ndarray):
    """A k-d tree for `distance_to_nearest_grasp` against these grasps (N >= 1)."""
    from scipy.spatial import cKDTree

    # The periodic box wraps theta; x and y never come near their (huge) box's edge.
    return cKDTree(_tree_coords(np.asarray(grasps_xy_theta, float)),
                   boxsize=[_BOX_M, _BOX_M, _THETA_PERIOD_M])


def tree_distances(tree, poses_xy_theta: np.ndarray) -> np.ndarray:
    """Distances from planar poses (M, 3) to the nearest grasp of `tree` [m]."""
    return tree.query(_tree_coords(np.asarray(poses_xy_theta, float)))[0]


def _label_shard(path: str, cfg_dict: dict) -> dict:
    """Dense labels of one shard's images (float16 grids), with what training needs."""
    import h5py

    cfg = NetworkConfig.from_dict(cfg_dict)
    with h5py.File(path, "r") as f:
        depth = f["depth"][:]
        hand = f["hand_pose"][:]
        image_scene = f["image_scene"][:]
        grasp_scene = f["grasp_scene"][:]
        grasps = f["grasp_xy_theta"][:]
    grids = np.full((len(depth), *cfg.grid_shape()), np.nan, np.float16)
    keep = np.ones(len(depth), bool)
    for scene in np.unique(image_scene):
        rows = np.flatnonzero(image_scene == scene)
        g = grasps[grasp_scene == scene]
        if len(g) == 0:
            keep[rows] = False
            continue
        grids[rows] = label_grids(hand[rows], g, cfg)
    return {"depth": depth[keep].astype(np.float16), "grid": grids[keep],
            "hand_z": hand[keep, 2].astype(np.float32)}


def label_grids(hand: np.ndarray, grasps_xy_theta: np.ndarray,
                cfg: NetworkConfig = GRID_CONFIG) -> np.ndarray:
    """The dense labels of images taken at hand poses `hand` (N, 4) = (x, y, z, theta
    [deg]) over one scene whose ground-truth grasps are `grasps_xy_theta` (G >= 1, 3):
    (N, T, n, n) float16 grids, the distance from each node's moved hand pose to the
    nearest grasp. Only the nodes in the image's view are labelled (the loss uses no
    others), NaN elsewhere; the view is taken a hair wider than the loss takes it."""
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.world.station import gripper_frame_offsets

    hand = np.asarray(hand, float).reshape(-1, 4)
    if len(grasps_xy_theta) == 0:
        raise ValueError("label_grids: the scene has no ground-truth grasp to label against")
    nodes = grid_node_actions(cfg)
    camera_z = float(gripper_frame_offsets()[2].translation()[2])
    grids = np.full((len(hand), *cfg.grid_shape()), np.nan, np.float16)
    in_view = view_masks(hand[:, 2], cfg, camera_z, slack_m=1e-6)
    tree = nearest_grasp_tree(grasps_xy_theta)
    for i in range(len(hand)):
        inside = in_view[i]
        node_in = (inside[None, :, None] & inside[None, None, :]).repeat(
            cfg.grid_shape()[0], axis=0).ravel()
        moved = apply_actions(hand[i, [0, 1, 3]], nodes[node_in])
        grids[i].reshape(-1)[node_in] = tree_distances(tree, moved)
    return grids


def build_labels(data_dir: str | Path, out: str | Path, *, cfg: NetworkConfig = GRID_CONFIG,
                 workers: int = 2, progress: bool = True) -> int:
    """Dense labels of every shard of `data_dir` into `out`/<shard>.npz (one file per
    shard, written atomically; a re-run skips the shards already done). Returns the
    number of images."""
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    data_dir, out = Path(data_dir), Path(out)
    shards = sorted(data_dir.glob("shard-*.h5"))
    if not shards:
        raise ValueError(f"{data_dir}: no shard-*.h5 files (a `drake-grasp generate` folder?)")
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    todo = [s for s in shards if not (out / f"{s.stem}.npz").exists()]
    images = 0
    with ProcessPoolExecutor(max_workers=workers) as pool, \
            tqdm(total=len(shards), initial=len(shards) - len(todo), disable=not progress,
                 desc="dense labels", unit="shard") as bar:
        futures = {pool.submit(_label_shard, str(s), cfg.to_dict()): s for s in todo}
        for fut, shard in futures.items():
            part = fut.result()
            tmp = out / f"{shard.stem}.tmp.npz"
            np.savez(tmp, **part)
            tmp.replace(out / f"{shard.stem}.npz")
            images += len(part["depth"])
            bar.update(1)
    return images


def _label_parts(folders) -> list[Path]:
    """The shard files of one or more `build_labels` folders, in order."""
    folders = [folders] if isinstance(folders, (str, Path)) else list(folders)
    parts = []
    for folder in folders:
        # A write killed midway leaves its temporary file (`*.tmp.npz`): not a part.
        found = sorted(p for p in Path(folder).glob("shard-*.npz")
                       if not p.name.endswith(".tmp.npz"))
        if not found:
            raise ValueError(f"{folder}: no shard-*.npz label files (run `labels` first)")
        parts += found
    return parts


def load_labels(folders) -> dict:
    """All parts of one or more `build_labels` folders, concatenated."""
    parts = _label_parts(folders)
    # Filled in place: concatenating lists of parts would hold every label twice at the
    # peak (300,000 images, float16 depth and grids, take 14 GB).
    counts = []
    for p in parts:
        with np.load(p) as z:
            counts.append(len(z["hand_z"]))
    offsets = np.concatenate([[0], np.cumsum(counts)])
    data = None
    for p, lo, hi in zip(parts, offsets[:-1], offsets[1:]):
        with np.load(p) as z:
            if data is None:
                data = {k: np.empty((offsets[-1], *z[k].shape[1:]), z[k].dtype)
                        for k in ("depth", "grid", "hand_z")}
            for k in data:
                part = z[k]
                if part.shape[1:] != data[k].shape[1:] or len(part) != hi - lo:
                    raise ValueError(f"{p}: '{k}' has shape {part.shape}, expected "
                                     f"({hi - lo}, {', '.join(map(str, data[k].shape[1:]))})")
                data[k][lo:hi] = part
    return data


class LabelStore:
    """The training images of one or more `build_labels` folders, and the order an epoch
    takes them in.

    `stream_shards=None`: every label in memory (`load_labels`), each epoch a permutation
    of all images seeded by (seed, epoch). 300,000 images take 14 GB that way, so the
    paper's 500,000 would not fit a 24 GB machine. `stream_shards=G`: the parts stay on
    disk; each epoch permutes the parts (seeded by (seed, epoch)), cuts them into groups
    of G parts and permutes the images within each group, and only the parts of the one
    or two groups a batch draws from are held (a part of `generate`'s default 4 scenes,
    160 images, takes 7.5 MB). A batch then mixes the images of G parts instead of the
    whole set.
    """

    KEYS = ("depth", "grid", "hand_z")

    def __init__(self, folders, stream_shards: int | None = None):
        if stream_shards is not None and stream_shards < 1:
            raise ValueError(f"stream_shards: expected a positive number of parts per "
                             f"group, got {stream_shards}")
        self.stream_shards = stream_shards
        self.parts = _label_parts(folders)
        if stream_shards is None:
            self._data = load_labels(folders)
            self.n_images = len(self._data["hand_z"])
            return
        counts = []
        for p in self.parts:
            with np.load(p) as z:
                counts.append(len(z["hand_z"]))
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.n_images = int(self.offsets[-1])
        with np.load(self.parts[0]) as z:
            self._shapes = {k: (z[k].shape[1:], z[k].dtype) for k in self.KEYS}
        self._held: dict[int, dict] = {}
        self._group_of = np.zeros(len(self.parts), np.int64)

    def epoch_order(self, seed: int, epoch: int) -> np.ndarray:
        """The image indices of epoch `epoch` in the order its batches take them."""
        rng = np.random.default_rng([seed, epoch])
        if self.stream_shards is None:
            return rng.permutation(self.n_images)
        shards = rng.permutation(len(self.parts))
        order = []
        for g, lo in enumerate(range(0, len(shards), self.stream_shards)):
            group = shards[lo:lo + self.stream_shards]
            self._group_of[group] = g
            images = np.concatenate([np.arange(self.offsets[s], self.offsets[s + 1])
                                     for s in group])
            order.append(rng.permutation(images))
        self._held.clear()
        return np.concatenate(order)

    def take(self, idx: np.ndarray, keys=KEYS) -> dict:
        """`keys` of the images `idx` (sorted global indices)."""
        if self.stream_shards is None:
            return {k: self._data[k][idx] for k in keys}
        shard = np.searchsorted(self.offsets, idx, side="right") - 1
        out = {k: np.empty((len(idx), *self._shapes[k][0]), self._shapes[k][1]) for k in keys}
        for s in np.unique(shard):
            part = self._part(int(s), keys)
            rows = shard == s
            for k in keys:
                out[k][rows] = part[k][idx[rows] - self.offsets[s]]
        return out

    def release_before(self, idx: np.ndarray) -> None:
        """Drop the held parts of the groups before the first one `idx` draws from (the
        epoch's order visits groups in turn)."""
        if self.stream_shards is None or not self._held:
            return
        shard = np.searchsorted(self.offsets, idx, side="right") - 1
        first = self._group_of[shard].min()
        for s in [s for s in self._held if self._group_of[s] < first]:
            del self._held[s]

    def _part(self, s: int, keys) -> dict:
        held = self._held.get(s)
        if held is not None and all(k in held for k in keys):
            return held
        path, n = self.parts[s], int(self.offsets[s + 1] - self.offsets[s])
        with np.load(path) as z:
            part = {k: z[k] for k in keys}
        for k in keys:
            if part[k].shape != (n, *self._shapes[k][0]):
                raise ValueError(f"{path}: '{k}' has shape {part[k].shape}, expected "
                                 f"({n}, {', '.join(map(str, self._shapes[k][0]))})")
        if tuple(keys) == self.KEYS:
            self._held[s] = part
        return part


def view_masks(hand_z, cfg: NetworkConfig, camera_z_G_m: float, *,
               slack_m: float = 1e-9) -> np.ndarray:
    """(B, N) mask of the grid's x (and, by symmetry of the square view, y) nodes inside
    the camera's footprint on the table at each image's camera height (hand heights
    `hand_z`, (B,)), widened by `slack_m`."""
    return grid_view_mask(np.asarray(hand_z, float) - camera_z_G_m, cfg, slack_m=slack_m)


def init_from_tiled(grid_net: DistanceCNN, tiled: DistanceCNN) -> None:
    """Starts a grid net from a trained paper ("tiled") net: the same Conv1, Conv2 (its
    bias taking the tiled action shift of the zero action) and IP1, and IP2's single
    output copied to every grid node (the grid starts flat at the tiled net's
    distance for staying put)."""
    with torch.no_grad():
        grid_net.conv1.load_state_dict(tiled.conv1.state_dict())
        grid_net.conv2.weight.copy_(tiled.conv2.weight)
        zero = torch.zeros(1, 3, dtype=tiled.dtype)
        grid_net.conv2.bias.copy_(tiled.conv2.bias + tiled.action_offsets(zero)[0])
        grid_net.ip1.load_state_dict(tiled.ip1.state_dict())
        grid_net.ip2.weight.copy_(tiled.ip2.weight.expand_as(grid_net.ip2.weight))
        grid_net.ip2.bias.fill_(float(tiled.ip2.bias[0]))


class BatchNormTrunk(torch.nn.Module):
    """Batch normalization for training a grid net: a BatchNorm after Conv1, Conv2 and IP1,
    each before its leaky ReLU. In eval mode a BatchNorm is a per-channel affine map, so
    `folded` merges it into the layer before it: the trained result is a plain grid
    `DistanceCNN` (same file format, same fast paths, nothing new to load or run), equal
    to this module in eval mode up to float rounding.

    Measured on the same data and batches at Adam 1e-3: after 2 epochs the paper's trunk
    ranks the controller's candidates better with it than without (README,
    *Batch-normalized training*).
    """

    def __init__(self, net: DistanceCNN):
        super().__init__()
        if not net.grid:
            raise ValueError(f"BatchNormTrunk: a grid net expected, got action_fusion="
                             f"{net.config.action_fusion!r}")
        cfg = net.config
        self.net = net
        self.bn1 = torch.nn.BatchNorm2d(cfg.conv1_channels, dtype=net.dtype)
        self.bn2 = torch.nn.BatchNorm2d(cfg.conv2_channels, dtype=net.dtype)
        self.bn3 = torch.nn.BatchNorm1d(cfg.ip1, dtype=net.dtype)

    @property
    def dtype(self):
        return self.net.dtype

    def preprocess(self, depth):
        return self.net.preprocess(depth)

    def _pre_activations(self, images: torch.Tensor):
        """Conv1's, Conv2's and IP1's outputs, each before its BatchNorm (the layers between
        them with theirs)."""
        lrelu = self.net._lrelu
        z1 = self.net.conv1(images)
        x = F.max_pool2d(lrelu(self.bn1(z1)), 2)
        z2 = self.net.conv2(x)
        h = F.max_pool2d(lrelu(self.bn2(z2)), 2).flatten(1)
        return z1, z2, self.net.ip1(h)

    def image_features(self, images: torch.Tensor) -> torch.Tensor:
        """The grid of distances, (B, T, N, N), as `DistanceCNN.image_features`."""
        self.net._check_images(images)
        z3 = self._pre_activations(images)[2]
        return self.net._after_ip1_grid(self.net._lrelu(self.bn3(z3)))

    @torch.no_grad()
    def start_as_identity(self, images: torch.Tensor) -> None:
        """Sets every BatchNorm to the identity in eval mode for the net's present weights:
        running mean and variance from `images` (one batch of normalized depth), scale the
        standard deviation and shift the mean. Training from trained weights then starts
        from their function (in train mode the batch's own statistics stand in for these,
        close for a large batch). Done layer by layer, each on the identity before it."""
        was_training = self.training
        self.eval()
        for bn, index in ((self.bn1, 0), (self.bn2, 1), (self.bn3, 2)):
            z = self._pre_activations(images)[index]
            dims = (0, 2, 3) if z.ndim == 4 else (0,)
            mean, var = z.mean(dim=dims), z.var(dim=dims, unbiased=False)
            bn.running_mean.copy_(mean)
            bn.running_var.copy_(var)
            bn.weight.copy_(torch.sqrt(var + bn.eps))
            bn.bias.copy_(mean)
        self.train(was_training)

    @torch.no_grad()
    def folded(self) -> DistanceCNN:
        """A plain grid net equal to this module in eval mode: each BatchNorm's
        scale / sqrt(running variance + eps) multiplies the rows of the layer before it,
        and its shift goes into that layer's bias."""
        import copy

        out = copy.deepcopy(self.net).eval()
        for layer, bn in ((out.conv1, self.bn1), (out.conv2, self.bn2), (out.ip1, self.bn3)):
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            shape = (-1,) + (1,) * (layer.weight.ndim - 1)
            layer.weight.mul_(scale.reshape(shape))
            layer.bias.copy_((layer.bias - bn.running_mean) * scale + bn.bias)
        return out


def _fingerprint(folder) -> str:
    """A label folder's content, not its place: the sha256 of its parts' names and bytes
    (a moved folder still resumes its run; relabelled data of the same shapes does not -
    names and sizes alone could not tell `near0_grid` from `near50_grid`). About 1 s per
    GB."""
    import hashlib

    from drake_grasp.core.provenance import file_sha256

    h = hashlib.sha256()
    for part in sorted(Path(folder).glob("shard-*.npz")):
        h.update(f"{part.name}:{file_sha256(part)};".encode())
    return h.hexdigest()


def _identity(folders, n_images, cfg, init_net: DistanceCNN | None, *, batch, lr, lr_decay,
              seed, batch_norm=False, stream_shards=None, augment="none",
              rank=None) -> dict:
    from drake_grasp.cnn.network import tensors_sha256

    init_sha = tensors_sha256(init_net.state_dict()) if init_net is not None else None
    return {"labels": [_fingerprint(f) for f in folders], "images": int(n_images),
            "config": cfg.to_dict(), "init_sha256": init_sha, "batch": int(batch),
            "lr": float(lr), "lr_decay": float(lr_decay), "seed": int(seed),
            # only when on, so that runs made before the option keep their identity
            **({"batch_norm": True} if batch_norm else {}),
            # streaming takes the images in another order: another run
            **({"stream_shards": int(stream_shards)} if stream_shards is not None else {}),
            **({"augment": augment} if augment != "none" else {}),
            **({"rank": rank} if rank is not None else {})}


def _trunk(cfg: NetworkConfig) -> tuple[int, int, int]:
    return (cfg.conv1_channels, cfg.conv2_channels, cfg.ip1)


def _save_checkpoint(path: Path, state: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def _plain_net(model) -> DistanceCNN:
    """The plain grid net a training model stands for, as the epoch files hold it: a
    `BatchNormTrunk` folded, a plain net copied (training goes on with the original)."""
    return model.folded() if isinstance(model, BatchNormTrunk) else copy.deepcopy(model)


def export_checkpoint_weights(run_dir: str | Path, path: str | Path) -> dict:
    """`checkpoint-weights` for a `train-grid` run: the weights of its checkpoint.pt
    (within an epoch, or after its last finished one) as a plain grid net (a BatchNorm
    run's BatchNorms folded in, as its epoch files are). Reads only; the run may go on.

    Returns the weights' metadata: {"trainer", "checkpoint_epoch" (epochs finished),
    "checkpoint_next_batch" (batches done in the unfinished epoch), "iterations"
    (batches done in all), "identity"}.

    Raises:
        FileNotFoundError: No checkpoint.pt in `run_dir`.
        ValueError: A checkpoint that is not a `train-grid` one (named).
    """
    ckpt_path = Path(run_dir) / "checkpoint.pt"
    if not ckpt_path.is_file():
        raise FileNotFoundError(f"{ckpt_path}: not found (is {run_dir} a `drake-grasp "
                                "train-grid` output folder?)")
    from drake_grasp.learning.common import load_checkpoint

    ckpt = load_checkpoint(ckpt_path)
    identity = ckpt.get("identity") if isinstance(ckpt, dict) else None
    if not isinstance(identity, dict) or "config" not in identity or "model" not in ckpt:
        raise ValueError(f"{ckpt_path}: not a `train-grid` checkpoint (expected the keys "
                         "'identity' with a 'config', and 'model')")
    net = DistanceCNN(NetworkConfig.from_dict(identity["config"]))
    model = BatchNormTrunk(net) if identity.get("batch_norm") else net
    model.load_state_dict(ckpt["model"])
    trained = _plain_net(model)
    batches_per_epoch = math.ceil(int(identity["images"]) / int(identity["batch"]))
    metadata = {"trainer": "dense_training", "checkpoint_epoch": int(ckpt["epoch"]),
                "checkpoint_next_batch": int(ckpt["batch_index"]),
                "iterations": int(ckpt["epoch"]) * batches_per_epoch + int(ckpt["batch_index"]),
                "identity": identity}
    save_weights(trained, path, metadata=metadata)
    return metadata


# The controller picks the lowest-scored of candidates near the hand (within 4 cm and 45
# degrees: `ControllerConfig.sample_xy_m`, `sample_theta_deg`), so what it needs of the net
# is the order of nearby nodes. `rank_pairs` draws pairs of grid nodes that near each other
# (4 cells = 4 cm in x and y, 4 bins = 40 degrees in theta, theta wrapping over 180).
RANK_REACH_CELLS = 4


def rank_pairs(grid_shape: tuple[int, int, int], images: int, pairs: int,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`pairs` pairs of nearby grid nodes per image, as flat node indices (images, pairs)
    into a (theta, y, x) grid of `grid_shape`: an anchor anywhere on the grid and a
    partner at most `RANK_REACH_CELLS` away along each axis (theta wrapping over 180
    degrees), never the anchor itself. Partners off the grid in x or y get index -1."""
    t_bins, n, _ = grid_shape
    r = RANK_REACH_CELLS
    anchor = np.stack([rng.integers(0, t_bins, (images, pairs)),
                       rng.integers(0, n, (images, pairs)),
                       rng.integers(0, n, (images, pairs))])
    step = rng.integers(-r, r + 1, (3, images, pairs))
    still = (step == 0).all(axis=0)
    step[2][still] = rng.choice([-1, 1], int(still.sum()))  # never the anchor itself
    t = np.mod(anchor[0] + step[0], t_bins)
    y, x = anchor[1] + step[1], anchor[2] + step[2]
    first = (anchor[0] * n + anchor[1]) * n + anchor[2]
    second = np.where((y >= 0) & (y < n) & (x >= 0) & (x < n), (t * n + y) * n + x, -1)
    return first, second


def pairwise_rank_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                       first: np.ndarray, second: np.ndarray, *, scale_m: float,
                       margin_m: float) -> torch.Tensor:
    """The mean logistic loss of ordering pairs of grid nodes of each image as their
    labels do: for nodes i, j of one image with labels t_i < t_j - `margin_m`, both counted
    by `mask`, softplus(-(p_j - p_i) / `scale_m`) (RankNet's loss on the predicted
    distances p). `first`, `second`: (images, pairs) flat node indices (`rank_pairs`; -1
    = no partner). 0 when no pair counts. Added to the L1 by `train(rank_weight=...)`:
    the L1 asks every node for its distance, this asks only that nearby nodes come in the
    order of their distances, which is all the controller's choice uses."""
    pred_gap, label_gap, valid = rank_pair_gaps(pred, target, mask, first, second,
                                                margin_m=margin_m)
    if not bool(valid.any()):
        return pred.sum() * 0.0
    z = torch.sign(label_gap) * pred_gap / scale_m
    return F.softplus(-z)[valid].mean()


def rank_pair_gaps(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                   first: np.ndarray, second: np.ndarray, *, margin_m: float) -> tuple:
    """For the pairs (`first`, `second`) of `rank_pairs`: the predicted gaps p_j - p_i,
    the label gaps t_j - t_i, and which pairs count (both nodes counted by `mask`, a
    partner on the grid, labels more than `margin_m` apart); each (images, pairs)."""
    b = pred.shape[0]
    p, t, m = pred.reshape(b, -1), target.reshape(b, -1), mask.reshape(b, -1)
    i = torch.from_numpy(first).to(pred.device)
    j_raw = torch.from_numpy(second).to(pred.device)
    j = j_raw.clamp(min=0)
    label_gap = t.gather(1, j) - t.gather(1, i)
    valid = m.gather(1, i) & m.gather(1, j) & (j_raw >= 0) & (label_gap.abs() > margin_m)
    return p.gather(1, j) - p.gather(1, i), label_gap, valid


def batch_tensors(model, data: dict, cfg: NetworkConfig, camera_z: float, device):
    """A batch of `LabelStore.take` on `device`: the normalized images, the label grids,
    and the mask of the nodes the loss counts (in the camera's view at the image's
    height, and labelled)."""
    images = model.preprocess(data["depth"].astype(np.float32)).to(device)
    target = torch.from_numpy(data["grid"].astype(np.float32)).to(device)
    mx = torch.from_numpy(view_masks(data["hand_z"], cfg, camera_z)).to(device)
    mask = (mx[:, None, :, None] & mx[:, None, None, :]).expand_as(target)
    return images, target, mask & torch.isfinite(target)


@full_float32()
def train(labels_dir, out: str | Path, *, test_data: str | Path | None,
          init: str | Path | None, epochs: int = 3, batch: int = 50, lr: float = 2e-4,
          lr_decay: float = 0.7, seed: int = 0, threads: int = 2,
          checkpoint_minutes: float = 5.0, progress: bool = True,
          trunk: tuple[int, int, int] | None = None, batch_norm: bool = False,
          device: str = "cpu", stream_shards: int | None = None, augment: str = "none",
          rank_weight: float = 0.0, rank_pairs_per_image: int = 1024,
          rank_scale_m: float = 0.01, rank_margin_m: float = 0.002,
          _stop_after_batches: int | None = None) -> dict:
    """Adam on the masked L1 over every in-view grid node, the learning rate times
    `lr_decay` after every epoch; `out`/epochN.safetensors after every epoch, and
    `out`/checkpoint.pt every `checkpoint_minutes` and after every epoch: re-running the
    same command resumes where it stopped (the batches of epoch e are a permutation
    seeded by (seed, e), so a resumed run takes the batches an unbroken one would).

    `labels_dir`: one `build_labels` folder or a list of them (same grid). `init`: a
    paper ("tiled") net to start from (`init_from_tiled`) or a grid net to go on
    training. `trunk`: (Conv1 filters, Conv2 filters, IP1 width) in place of the label
    folder's (the paper's 20, 50, 500), e.g. a wider net to test whether the trunk's
    capacity limits the fit; `init` must then have the same trunk. `batch_norm`: train
    through a `BatchNormTrunk` (from `init`, its BatchNorms start as the identity on 1,000
    of the training images); the epoch files hold the folded plain grid net. `device`:
    where the batches run, "cpu", "cuda" or "auto" (a GPU when torch sees one); the
    labels stay in memory on the CPU, the test metrics run on the CPU, and a run may
    resume on another device (in full float32 there: `common.full_float32`).
    `stream_shards`: hold only the label parts of groups of this many at a time
    (`LabelStore`) instead of every label in memory. `augment`: "none", "mirror" (each
    image flipped left-right or not) or "d4" (also turned by 0, 90, 180 or 270 degrees),
    with its label grid (`augment_batch`); the draws are seeded by (seed, epoch, batch),
    so a resumed run takes the ones an unbroken run would. `rank_weight` > 0 adds that
    times `pairwise_rank_loss` (over `rank_pairs_per_image` pairs of nearby nodes per
    image, `rank_pairs`, with `rank_scale_m` and `rank_margin_m`) to the L1, the pairs
    drawn from (seed, epoch, batch) as the augmentation's are.
    """
    from tqdm import tqdm

    from drake_grasp.core.files import atomic_write_text
    from drake_grasp.world.station import gripper_frame_offsets
    from drake_grasp.learning.common import load_checkpoint, torch_device

    if augment not in AUGMENTATIONS:
        raise ValueError(f"augment: expected one of {sorted(AUGMENTATIONS)}, got {augment!r}")
    if not (rank_weight >= 0.0 and math.isfinite(rank_weight)):
        raise ValueError(f"rank_weight: expected a finite number >= 0, got {rank_weight!r}")
    if rank_weight > 0 and not (rank_pairs_per_image >= 1 and rank_scale_m > 0
                                and rank_margin_m >= 0):
        raise ValueError("rank loss: expected rank_pairs_per_image >= 1, rank_scale_m > 0 "
                         f"and rank_margin_m >= 0, got {rank_pairs_per_image!r}, "
                         f"{rank_scale_m!r}, {rank_margin_m!r}")
    rank = ({"weight": float(rank_weight), "pairs_per_image": int(rank_pairs_per_image),
             "scale_m": float(rank_scale_m), "margin_m": float(rank_margin_m),
             "reach_cells": RANK_REACH_CELLS} if rank_weight > 0 else None)
    torch.set_num_threads(threads)
    device = torch_device(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    folders = [labels_dir] if isinstance(labels_dir, (str, Path)) else list(labels_dir)
    for f in folders:
        if not (Path(f) / "config.json").is_file():
            raise ValueError(f"{f}: not a dense-labels folder (no config.json; run "
                             "`drake-grasp dense-labels` first)")
    configs = [json.loads((Path(f) / "config.json").read_text()) for f in folders]
    if any(c != configs[0] for c in configs):
        raise ValueError(f"{folders}: label folders made for different grids")
    cfg = NetworkConfig.from_dict(configs[0])
    if trunk is not None:
        if len(trunk) != 3:
            raise ValueError(f"trunk: expected (conv1 filters, conv2 filters, ip1 width), "
                             f"got {trunk!r}")
        cfg = dataclasses.replace(cfg, conv1_channels=int(trunk[0]),
                                  conv2_channels=int(trunk[1]), ip1=int(trunk[2]))
    init_net = load_weights(init)[0] if init else None
    if init_net is not None:
        have = _trunk(init_net.config)
        if have != _trunk(cfg):
            raise ValueError(f"{init}: its trunk (conv1, conv2, ip1) is {have}, this run's is "
                             f"{_trunk(cfg)}; start a run with another trunk from scratch")
    store = LabelStore(folders, stream_shards)
    n_images = store.n_images
    identity = _identity(folders, n_images, cfg, init_net, batch=batch, lr=lr, lr_decay=lr_decay,
                         seed=seed, batch_norm=batch_norm, stream_shards=stream_shards,
                         augment=augment, rank=rank)
    net = DistanceCNN(cfg, generator=torch.Generator().manual_seed(seed))
    model = BatchNormTrunk(net) if batch_norm else net
    ckpt_path = out / "checkpoint.pt"
    epoch, batch_index, total, count, rank_total = 0, 0, 0.0, 0, 0.0
    metrics = {"identity": identity, "epochs": []}
    ckpt = load_checkpoint(ckpt_path) if ckpt_path.exists() else None
    if ckpt is not None:
        if ckpt["identity"] != identity:
            diff = sorted(k for k in {**ckpt["identity"], **identity}
                          if ckpt["identity"].get(k) != identity.get(k))
            raise ValueError(f"{out}: holds another training run (differs in {diff}); "
                             "use another out folder")
        model.load_state_dict(ckpt["model"])
        epoch, batch_index = ckpt["epoch"], ckpt["batch_index"]
        total, count = ckpt["total"], ckpt["count"]
        rank_total = ckpt.get("rank_total", 0.0)
        metrics = json.loads(ckpt["metrics"])
    elif init_net is not None:
        if init_net.config == cfg:  # a grid net: go on training it
            net.load_state_dict(init_net.state_dict())
        else:
            init_from_tiled(net, init_net)
        if batch_norm:
            sample = np.sort(np.random.default_rng([seed, 1]).choice(
                n_images, min(n_images, 1000), replace=False))
            depth = store.take(sample, keys=("depth",))["depth"]
            model.start_as_identity(model.preprocess(depth.astype(np.float32)))
    # The optimizer is made (and its state loaded) after the move, so that its state
    # lives where the parameters do.
    model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=lr_decay)
    if ckpt is not None:
        opt.load_state_dict(ckpt["opt"])
        sched.load_state_dict(ckpt["sched"])
        del ckpt  # its tensors are copied into the model and optimizer
    camera_z = float(gripper_frame_offsets()[2].translation()[2])

    def checkpoint():
        _save_checkpoint(ckpt_path, {
            "identity": identity, "epoch": epoch, "batch_index": batch_index,
            "total": total, "count": count, "rank_total": rank_total,
            "metrics": json.dumps(metrics),
            "model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict()})

    starts = list(range(0, n_images, batch))
    done_batches = 0
    last_ckpt = time.perf_counter()
    while epoch < epochs:
        order = store.epoch_order(seed, epoch)
        model.train()
        bar = tqdm(starts, initial=batch_index, total=len(starts), desc=f"epoch {epoch + 1}",
                   unit="batch", disable=not progress)
        for start in starts[batch_index:]:
            idx = np.sort(order[start:start + batch])
            store.release_before(idx)
            data = store.take(idx)
            if augment != "none":
                data = augment_batch(data, augment,
                                     np.random.default_rng([seed, 3, epoch, batch_index]))
            images, target, mask = batch_tensors(model, data, cfg, camera_z, device)
            pred = model.image_features(images)
            loss = (pred - target).abs()[mask].mean()
            objective = loss
            if rank is not None:
                first, second = rank_pairs(cfg.grid_shape(), len(idx), rank_pairs_per_image,
                                           np.random.default_rng([seed, 4, epoch, batch_index]))
                rank_loss = pairwise_rank_loss(pred, target, mask, first, second,
                                               scale_m=rank_scale_m, margin_m=rank_margin_m)
                objective = loss + rank_weight * rank_loss
                rank_total += float(rank_loss.detach()) * len(idx)
            opt.zero_grad(set_to_none=True)
            objective.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
            count += len(idx)
            batch_index += 1
            done_batches += 1
            bar.update(1)
            bar.set_postfix(l1_mm=f"{1000 * total / count:.1f}")
            if time.perf_counter() - last_ckpt > 60 * checkpoint_minutes:
                checkpoint()
                last_ckpt = time.perf_counter()
            if _stop_after_batches is not None and done_batches >= _stop_after_batches:
                checkpoint()
                bar.close()
                return metrics  # a simulated kill (tests)
        bar.close()
        with warnings.catch_warnings():
            # A run resumed right at an epoch's end steps the schedule without an
            # optimizer step in this process; the schedule is still the unbroken run's.
            warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step",
                                    category=UserWarning)
            sched.step()
        row = {"epoch": epoch + 1, "train_l1_m": total / max(count, 1), "images": count,
               "lr": lr * lr_decay ** epoch,
               **({"train_rank_loss": rank_total / max(count, 1)} if rank is not None else {})}
        trained = _plain_net(model).cpu()
        save_weights(trained, out / f"epoch{epoch + 1}.safetensors",
                     metadata={"trainer": "dense_training", "epoch": epoch + 1,
                               "identity": identity})
        if test_data:
            row.update(evaluate(trained, test_data))
        metrics["epochs"].append(row)
        epoch, batch_index, total, count, rank_total = epoch + 1, 0, 0.0, 0, 0.0
        checkpoint()
        last_ckpt = time.perf_counter()
        atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=1))
        if progress:
            print(json.dumps(row))
    return metrics


def evaluate(model: DistanceCNN, test_data: str | Path, *, ranking_images: int = 200) -> dict:
    """Test L1 over every stored labelled offset and the controller's ranking metrics."""
    from drake_grasp.learning.cnn_metrics import l1_by_label, ranking_metrics
    from drake_grasp.learning.common import ChunkCache, ShardSet

    model.eval()
    l1, bins = l1_by_label(model, ShardSet(test_data, ChunkCache(int(2e9))))
    ranks = ranking_metrics(model, test_data, images=ranking_images)
    return {"test_l1_m": l1, "test_l1_bins": bins, "ranking": ranks}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("labels")
    a.add_argument("--data", required=True)
    a.add_argument("--out", required=True)
    a.add_argument("--workers", type=int, default=2)
    b = sub.add_parser("train")
    b.add_argument("--labels", required=True, help="label folders, comma-separated")
    b.add_argument("--out", required=True)
    b.add_argument("--test-data", default=None)
    b.add_argument("--init", default=None)
    b.add_argument("--epochs", type=int, default=3)
    b.add_argument("--batch", type=int, default=50)
    b.add_argument("--lr", type=float, default=2e-4)
    b.add_argument("--lr-decay", type=float, default=0.7)
    b.add_argument("--threads", type=int, default=2)
    b.add_argument("--checkpoint-minutes", type=float, default=5.0)
    args = p.parse_args(argv)
    if args.cmd == "labels":
        print(build_labels(args.data, args.out, workers=args.workers), "images")
    else:
        train(args.labels.split(","), args.out, test_data=args.test_data, init=args.init,
              epochs=args.epochs, batch=args.batch, lr=args.lr, lr_decay=args.lr_decay,
              threads=args.threads, checkpoint_minutes=args.checkpoint_minutes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
