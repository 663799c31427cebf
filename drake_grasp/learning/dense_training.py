"""Training the grid head (`NetworkConfig(action_fusion="grid")`) on dense labels.

The paper's net takes the action as an input, so every labelled offset costs a pass
through IP1: the dataset stores 10 per image. The grid head predicts the distance at
every node of a fixed grid of actions (18 x 33 x 33 for the defaults) from one pass per
image, so every image can be labelled at every node: the label of an action is the
distance from the hand pose it leads to, to the nearest ground-truth grasp of the scene
(the dataset's own label function, `grasps.distance_to_nearest_grasp`), and the shards
store each scene's grasps. A k-d tree over a scene's grasps in the metric's coordinates
(x, y, 0.001 m/deg x theta, theta periodic over 180 degrees) gives those distances
exactly (to float rounding) and fast (`drake_grasp.learning.dense_labels`).

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

from drake_grasp.cnn.net_config import NetworkConfig
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.cnn.weights_io import load_weights, save_weights
from drake_grasp.cnn.views import AUGMENTATIONS, turn_grids, turn_images
from drake_grasp.core.files import atomic_write_text
from drake_grasp.learning.common import (ChunkCache, ShardSet, full_float32, load_checkpoint,
                                         torch_device)
from drake_grasp.learning.dense_labels import LabelStore, build_labels, view_masks
from drake_grasp.learning.dense_rank import RANK_REACH_CELLS, pairwise_rank_loss, rank_pairs


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
        return self.net.head.grid_from_hidden(self.net._lrelu(self.bn3(z3)))

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
    from drake_grasp.cnn.weights_io import tensors_sha256

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


def batch_tensors(model, data: dict, cfg: NetworkConfig, camera_z: float, device):
    """A batch of `LabelStore.take` on `device`: the normalized images, the label grids,
    and the mask of the nodes the loss counts (in the camera's view at the image's
    height, and labelled)."""
    images = model.preprocess(data["depth"].astype(np.float32)).to(device)
    target = torch.from_numpy(data["grid"].astype(np.float32)).to(device)
    mx = torch.from_numpy(view_masks(data["hand_z"], cfg, camera_z)).to(device)
    mask = (mx[:, None, :, None] & mx[:, None, None, :]).expand_as(target)
    return images, target, mask & torch.isfinite(target)


def _rank_settings(augment: str, rank_weight: float, rank_pairs_per_image: int,
                   rank_scale_m: float, rank_margin_m: float) -> dict | None:
    """`train`'s augmentation and rank-loss arguments checked; the rank loss's settings
    as the run's identity records them, None without a rank loss."""
    if augment not in AUGMENTATIONS:
        raise ValueError(f"augment: expected one of {sorted(AUGMENTATIONS)}, got {augment!r}")
    if not (rank_weight >= 0.0 and math.isfinite(rank_weight)):
        raise ValueError(f"rank_weight: expected a finite number >= 0, got {rank_weight!r}")
    if rank_weight > 0 and not (rank_pairs_per_image >= 1 and rank_scale_m > 0
                                and rank_margin_m >= 0):
        raise ValueError("rank loss: expected rank_pairs_per_image >= 1, rank_scale_m > 0 "
                         f"and rank_margin_m >= 0, got {rank_pairs_per_image!r}, "
                         f"{rank_scale_m!r}, {rank_margin_m!r}")
    return ({"weight": float(rank_weight), "pairs_per_image": int(rank_pairs_per_image),
             "scale_m": float(rank_scale_m), "margin_m": float(rank_margin_m),
             "reach_cells": RANK_REACH_CELLS} if rank_weight > 0 else None)


def _run_config(labels_dir, trunk) -> tuple[list, NetworkConfig]:
    """The label folders of a `train` run and its net's config: the folders' grid, with
    `trunk` (conv1 filters, conv2 filters, ip1 width) in place of theirs if given."""
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
    return folders, cfg


def _init_net(init, cfg: NetworkConfig) -> DistanceCNN | None:
    """The net `init` names (None for none), checked to have the run's trunk."""
    init_net = load_weights(init)[0] if init else None
    if init_net is not None:
        have = _trunk(init_net.config)
        if have != _trunk(cfg):
            raise ValueError(f"{init}: its trunk (conv1, conv2, ip1) is {have}, this run's is "
                             f"{_trunk(cfg)}; start a run with another trunk from scratch")
    return init_net


def _start_state(model, net: DistanceCNN, ckpt: dict | None, identity: dict, out: Path,
                 init_net: DistanceCNN | None, cfg: NetworkConfig, *, batch_norm: bool,
                 seed: int, store: LabelStore) -> tuple:
    """Where a `train` run starts: resumed from its checkpoint `ckpt` (which must be this
    run's), else the model started from `init_net` if given. Returns (epoch, batch_index,
    total, count, rank_total, metrics)."""
    n_images = store.n_images
    epoch, batch_index, total, count, rank_total = 0, 0, 0.0, 0, 0.0
    metrics = {"identity": identity, "epochs": []}
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
    return epoch, batch_index, total, count, rank_total, metrics


def _batch_objective(model, data: dict, cfg: NetworkConfig, camera_z: float, device,
                     rank_terms: tuple | None, images_n: int, rank_rng) -> tuple:
    """One batch's masked L1 `loss`, the `objective` to minimise (the L1 plus the
    weighted rank loss if `rank_terms` = (weight, pairs per image, scale_m, margin_m),
    its pairs drawn from `rank_rng`) and the rank loss (None without one)."""
    images, target, mask = batch_tensors(model, data, cfg, camera_z, device)
    pred = model.image_features(images)
    loss = (pred - target).abs()[mask].mean()
    objective = loss
    rank_loss = None
    if rank_terms is not None:
        rank_weight, rank_pairs_per_image, rank_scale_m, rank_margin_m = rank_terms
        first, second = rank_pairs(cfg.grid_shape(), images_n, rank_pairs_per_image, rank_rng)
        rank_loss = pairwise_rank_loss(pred, target, mask, first, second,
                                       scale_m=rank_scale_m, margin_m=rank_margin_m)
        objective = loss + rank_weight * rank_loss
    return loss, objective, rank_loss


def _end_epoch(model, sched, out: Path, identity: dict, test_data, *, epoch: int, lr: float,
               lr_decay: float, total: float, count: int, rank_total: float,
               rank: dict | None) -> dict:
    """The end of epoch `epoch` (0-based) of a `train` run: the schedule stepped, the
    epoch's weights file written and the test metrics; returns the epoch's metrics row."""
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
    return row


def _model_state(ckpt_path: Path, cfg: NetworkConfig, identity: dict, out: Path, init_net,
                 store, *, batch_norm: bool, seed: int, device, lr: float,
                 lr_decay: float) -> tuple:
    """(model, Adam, its learning-rate schedule, the run's state: `_start_state`), from the
    checkpoint when there is one. The optimizer is made (and its state loaded) after the
    model's move to `device`, so that its state lives where the parameters do."""
    net = DistanceCNN(cfg, generator=torch.Generator().manual_seed(seed))
    model = BatchNormTrunk(net) if batch_norm else net
    ckpt = load_checkpoint(ckpt_path) if ckpt_path.exists() else None
    state = _start_state(model, net, ckpt, identity, out, init_net, cfg,
                         batch_norm=batch_norm, seed=seed, store=store)
    model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=lr_decay)
    if ckpt is not None:
        opt.load_state_dict(ckpt["opt"])
        sched.load_state_dict(ckpt["sched"])
        del ckpt  # its tensors are copied into the model and optimizer
    return model, opt, sched, state


def _train_batch(model, opt, store, rows, cfg: NetworkConfig, camera_z: float, device, *,
                 augment: str, rank_terms, key: tuple) -> tuple:
    """One Adam step on the images `rows` of the epoch's order (their augmentation and
    rank pairs drawn from `key` = (seed, epoch, batch)): (their L1 times their count, the
    rank loss times their count or None, their count)."""
    seed, epoch, batch_index = key
    idx = np.sort(rows)
    store.release_before(idx)
    data = store.take(idx)
    if augment != "none":
        data = augment_batch(data, augment,
                             np.random.default_rng([seed, 3, epoch, batch_index]))
    loss, objective, rank_loss = _batch_objective(
        model, data, cfg, camera_z, device, rank_terms, len(idx),
        np.random.default_rng([seed, 4, epoch, batch_index]) if rank_terms is not None else None)
    rank_sum = float(rank_loss.detach()) * len(idx) if rank_terms is not None else None
    opt.zero_grad(set_to_none=True)
    objective.backward()
    opt.step()
    return float(loss.detach()) * len(idx), rank_sum, len(idx)


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

    from drake_grasp.world.station import gripper_frame_offsets

    rank = _rank_settings(augment, rank_weight, rank_pairs_per_image, rank_scale_m, rank_margin_m)
    rank_terms = (rank_weight, rank_pairs_per_image, rank_scale_m, rank_margin_m) if rank else None
    torch.set_num_threads(threads)
    device = torch_device(device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    folders, cfg = _run_config(labels_dir, trunk)
    init_net = _init_net(init, cfg)
    store = LabelStore(folders, stream_shards)
    identity = _identity(folders, store.n_images, cfg, init_net, batch=batch, lr=lr,
                         lr_decay=lr_decay, seed=seed, batch_norm=batch_norm,
                         stream_shards=stream_shards, augment=augment, rank=rank)
    ckpt_path = out / "checkpoint.pt"
    model, opt, sched, (epoch, batch_index, total, count, rank_total, metrics) = _model_state(
        ckpt_path, cfg, identity, out, init_net, store, batch_norm=batch_norm, seed=seed,
        device=device, lr=lr, lr_decay=lr_decay)
    camera_z = float(gripper_frame_offsets()[2].translation()[2])

    def checkpoint():
        _save_checkpoint(ckpt_path, {
            "identity": identity, "epoch": epoch, "batch_index": batch_index,
            "total": total, "count": count, "rank_total": rank_total,
            "metrics": json.dumps(metrics),
            "model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict()})

    starts = list(range(0, store.n_images, batch))
    done_batches = 0
    last_ckpt = time.perf_counter()
    while epoch < epochs:
        order = store.epoch_order(seed, epoch)
        model.train()
        bar = tqdm(starts, initial=batch_index, total=len(starts), desc=f"epoch {epoch + 1}",
                   unit="batch", disable=not progress)
        for start in starts[batch_index:]:
            loss_sum, rank_sum, n = _train_batch(
                model, opt, store, order[start:start + batch], cfg, camera_z, device,
                augment=augment, rank_terms=rank_terms, key=(seed, epoch, batch_index))
            if rank is not None:
                rank_total += rank_sum
            total, count = total + loss_sum, count + n
            batch_index, done_batches = batch_index + 1, done_batches + 1
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
        row = _end_epoch(model, sched, out, identity, test_data, epoch=epoch, lr=lr,
                         lr_decay=lr_decay, total=total, count=count, rank_total=rank_total,
                         rank=rank)
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
