"""Training of the distance CNN with the L1 loss, resumable after a kill.

Two recipes (`RECIPES`): `paper`, the paper's SGD (lr 0.001, momentum 0.9, batches of 1000
instances, a constant rate), and `fast`, the default: Adam (lr 0.0001) with a per-epoch
decaying rate.

An instance is one (image, offset, label) triple. A batch of 1000 instances is 100 images
with their 10 labelled offsets each, which the factored fast path scores with one image
pass per image (`DistanceCNN.forward_factored`).

Data loading. Both sets are read from their HDF5 shards through one least-recently-used
cache of decoded HDF5 chunks (`ChunkCache`), bounded by `TrainConfig.max_memory_gb`
(`--max-memory-gb`) together with the batch being assembled. A set that fits stays in
memory after its first pass; a larger one streams, re-reading chunks as they are evicted
(slower epochs, the same batches). The bound covers what the loader holds: the cached
chunks and the batch (counted twice: as gathered and as the network's normalized copy);
the network's activations and the Python/torch runtime come on top.

Identity of a run. Resuming into an output folder requires the same configuration and
datasets; the number of epochs may grow, and `device`, `threads` and `max_memory_gb` may
differ (a run started on a CPU can continue on a GPU and back). Checkpoints are loaded
with `weights_only=True` and `map_location="cpu"`, so a checkpoint written on a GPU loads
on a machine without one.

Output folder:

    checkpoint.pt        model + optimizer + RNG state after the last finished epoch, or
                         within an epoch (every `checkpoint_minutes`: the batches still to
                         come are those an unbroken run would take); torch.save, loaded
                         with weights_only=True
    metrics.json         per-epoch train/test L1 [m], the within-image ranking metrics on
                         the test set (`cnn_metrics`), learning rate, timing, device, and
                         the final test_l1_m
    learning_curves.png  train and test L1 per epoch
    weights.safetensors  final weights with metadata (weights_io.save_weights); an
                         unfinished run's latest checkpoint as weights:
                         `export_checkpoint_weights` (`drake-grasp checkpoint-weights`)
    train_config.json    the resolved training configuration
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from drake_grasp.learning.cnn_metrics import ranking_metrics
from drake_grasp.learning.common import (ShardSet, full_float32, load_checkpoint, open_training_sets,
                                         resolve_data_dirs, torch_device)
from drake_grasp.learning.folder_lock import GenerateLock, replace_durably
from drake_grasp.core.native import load_llvm_users_first
from drake_grasp.cnn.net_config import NetworkConfig
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.cnn.weights_io import load_weights, save_weights, tensors_sha256
from drake_grasp.core.provenance import code_version

# Settings that say where and how fast a run computes, not what it computes: they may
# change when a run is resumed (with `epochs`, which may grow).
NOT_IDENTITY = ("epochs", "device", "threads", "max_memory_gb", "checkpoint_minutes",
                "ranking_images", "init_weights")

OPTIMIZERS = ("sgd", "adam")

# Training losses. "l1" (the paper's): |d_pred - d_true|. "log-l1":
# |log(d_pred + c) - log(d_true + c)| with c = `loss_offset_m`, an L1 whose weight falls as
# 1/(d + c): an error of 1 cm costs about as much at 2 cm from a grasp as 10 cm at 20 cm.
# The controller ranks candidates near a grasp (README *The distance CNN*: the paper's L1
# is dominated by labels over 10 cm); any monotone transform keeps the net's output a
# distance, so nothing downstream changes.
LOSSES = ("l1", "log-l1")
# Fields added after runs were made: left out of an L1 run's identity, so runs made before
# them resume (and keep their identity) as before.
_LATER_FIELDS = ("loss", "loss_offset_m")

# Named recipes. `paper`: the paper's SGD (lr 0.001, momentum 0.9, batches of 1000), a
# constant rate, for its 900k iterations. `fast` (the default): Adam with a rate that
# decays per epoch, for the few epochs a CPU affords; compared with `paper` side by side
# on the same data in models/cnn/README.md.
RECIPES = {
    "paper": {"optimizer": "sgd", "learning_rate": 0.001, "momentum": 0.9,
              "lr_decay_per_epoch": 1.0, "batch_instances": 1000},
    # Adam at 0.001 drove the scaled-softplus output into saturation within 10 batches
    # (every prediction 0, no gradient: a dead net) on the 400-scene set; 0.0001 recovered
    # from its early dip and learned.
    "fast": {"optimizer": "adam", "learning_rate": 0.0001, "momentum": 0.9,
             "lr_decay_per_epoch": 0.8, "batch_instances": 1000},
}


@dataclass
class TrainConfig:
    """Training settings; the defaults are the `fast` recipe (`RECIPES`)."""

    epochs: int = 10
    recipe: str = "fast"  # the name of the recipe these settings came from (a label)
    optimizer: str = "adam"  # "sgd" (the paper's) or "adam"
    batch_instances: int = 1000
    learning_rate: float = 0.0001
    momentum: float = 0.9  # SGD only
    # The rate of epoch e is learning_rate * lr_decay_per_epoch ** (e - 1).
    lr_decay_per_epoch: float = 0.8
    seed: int = 0
    # Most memory the data loader may hold [GB]: cached HDF5 chunks of both sets plus
    # the batch being assembled. Data beyond it is streamed from the shards.
    max_memory_gb: float = 8.0
    device: str = "auto"
    threads: int = 0  # 0 = torch default
    # A checkpoint at least this often within an epoch (and after every epoch); a killed
    # run resumes from the last one with the same batches still to come.
    checkpoint_minutes: float = 5.0
    # Test images for the within-image ranking metrics after each epoch (0: none).
    ranking_images: int = 200
    # Start from these weights (a `save_weights` file, e.g. the shipped ones) instead of a
    # fresh initialization: training continues on `data` with a fresh optimizer. The
    # file's tensors' sha256, not its path, is part of the run's identity.
    init_weights: str = ""
    # The training loss (`LOSSES`): "l1", the paper's, or "log-l1" (its offset c [m]).
    loss: str = "l1"
    loss_offset_m: float = 0.01

    @classmethod
    def from_recipe(cls, name: str, **overrides) -> "TrainConfig":
        """The settings of recipe `name` (`RECIPES`), with `overrides` (None = keep)."""
        if name not in RECIPES:
            raise ValueError(f"recipe: expected one of {sorted(RECIPES)}, got {name!r}")
        given = {k: v for k, v in overrides.items() if v is not None}
        return cls(**{**RECIPES[name], "recipe": name, **given})

    def validate(self) -> None:
        if self.epochs < 1:
            raise ValueError(f"epochs: expected >= 1, got {self.epochs}")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer: expected one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.batch_instances < 1:
            raise ValueError(f"batch_instances: expected >= 1, got {self.batch_instances}")
        if self.learning_rate <= 0:
            raise ValueError(f"learning_rate: expected > 0, got {self.learning_rate}")
        if not 0 < self.lr_decay_per_epoch <= 1:
            raise ValueError(f"lr_decay_per_epoch: expected in (0, 1], got "
                             f"{self.lr_decay_per_epoch}")
        if not self.checkpoint_minutes >= 0:
            raise ValueError(f"checkpoint_minutes: expected >= 0, got {self.checkpoint_minutes}")
        if self.ranking_images < 0:
            raise ValueError(f"ranking_images: expected >= 0, got {self.ranking_images}")
        if not self.max_memory_gb > 0:
            raise ValueError(f"max_memory_gb: expected > 0, got {self.max_memory_gb}")
        if self.threads < 0:
            raise ValueError(f"threads: expected >= 0 (0: torch default), got {self.threads}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss: expected one of {LOSSES}, got {self.loss!r}")
        if not self.loss_offset_m > 0:
            raise ValueError(f"loss_offset_m: expected > 0 [m], got {self.loss_offset_m}")

    def identity_dict(self) -> dict:
        """The settings as a dict; an L1 run's leaves out the loss fields
        (`_LATER_FIELDS`), so a run made before they existed keeps its identity."""
        d = dataclasses.asdict(self)
        if d["loss"] == "l1":  # the offset means nothing without the log loss
            for key in _LATER_FIELDS:
                d.pop(key)
        return d


def training_loss(pred: torch.Tensor, target: torch.Tensor, config: TrainConfig) -> torch.Tensor:
    """The mean training loss of `config.loss` over a batch (`LOSSES`)."""
    if config.loss == "log-l1":
        c = config.loss_offset_m
        return (torch.log(pred + c) - torch.log(target + c)).abs().mean()
    return (pred - target).abs().mean()


def evaluate_l1(model: DistanceCNN, data: ShardSet, *, device, batch_images: int = 200) -> float:
    """Mean absolute error [m] over every labelled offset of a set."""
    model.eval()
    total, count = 0.0, 0
    with torch.no_grad():
        for start in range(0, len(data), batch_images):
            depth, offsets, labels = data.gather(np.arange(start, min(start + batch_images, len(data))))
            images = model.preprocess(depth).to(device)
            actions = torch.as_tensor(offsets, device=device, dtype=model.dtype)
            targets = torch.as_tensor(labels, device=device, dtype=model.dtype)
            del depth, offsets, labels
            pred = model.forward_factored(images, actions)
            total += float((pred - targets).abs().sum())
            count += targets.numel()
            del images, actions, targets, pred
    return total / max(count, 1)


def _save_checkpoint(path: Path, model, optimizer, epoch: int, generator_state: torch.Tensor,
                     metrics: dict, config_hash: str, in_epoch: dict | None = None) -> None:
    """`epoch`: the last finished epoch. `in_epoch`: where an unfinished epoch stands
    (its number, the next batch, running sums); `generator_state` is then the shuffling
    generator's state at that epoch's start, so its order is drawn again on resume."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "epoch": epoch, "generator": generator_state,
                "in_epoch_json": json.dumps(in_epoch),
                "metrics_json": json.dumps(metrics), "config_hash": config_hash}, tmp)
    replace_durably(tmp, path)


def export_checkpoint_weights(run_dir: str | Path, path: str | Path) -> dict:
    """Writes the weights of a training run's latest checkpoint (an unfinished run: after
    its last finished epoch, or within an epoch) as a weights file, so that a long run
    can be tried in the controller before it ends. Reads only; the run may go on.

    Args:
        run_dir: The run's output folder: `train`'s (checkpoint.pt and
            train_config.json) or `train-grid`'s (checkpoint.pt alone;
            `dense_training.export_checkpoint_weights`).
        path: The weights file to write (``*.safetensors``).

    Returns:
        The weights' user metadata: {"checkpoint_epoch": last finished epoch,
        "checkpoint_next_batch": batches done in the unfinished epoch (0 at an epoch's
        end), "iterations": batches done in all, "train_manifest_sha256", ...}.

    Raises:
        FileNotFoundError: No checkpoint.pt or train_config.json in `run_dir` (named).
        ValueError: train_config.json without a valid "network" entry (named).
    """
    run_dir = Path(run_dir)
    ckpt_path, config_path = run_dir / "checkpoint.pt", run_dir / "train_config.json"
    if ckpt_path.is_file() and not config_path.exists():
        # No train_config.json: a `train-grid` run (its config is in the checkpoint).
        from drake_grasp.learning import dense_training

        return dense_training.export_checkpoint_weights(run_dir, path)
    for f in (ckpt_path, config_path):
        if not f.is_file():
            raise FileNotFoundError(f"{f}: not found (is {run_dir} a `drake-grasp train` "
                                    "output folder?)")
    try:
        resolved = json.loads(config_path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{config_path}: not valid JSON ({e})") from None
    if not isinstance(resolved, dict) or "network" not in resolved:
        raise ValueError(f"{config_path}: expected a JSON object with a \"network\" entry")
    network = NetworkConfig.from_dict(resolved["network"], source=f"{config_path}: network")
    ckpt = load_checkpoint(ckpt_path)
    model = DistanceCNN(network)
    model.load_state_dict(ckpt["model"])
    in_epoch = json.loads(ckpt.get("in_epoch_json", "null")) or {}
    metrics = json.loads(ckpt["metrics_json"])
    finished = metrics.get("epochs", [])
    next_batch = int(in_epoch.get("next_batch", 0))
    iterations = (int(finished[-1]["iterations"]) if finished else 0) + next_batch
    metadata = {"checkpoint_epoch": int(ckpt["epoch"]), "checkpoint_next_batch": next_batch,
                "iterations": iterations,
                "train_manifest_sha256": resolved.get("train_manifest_sha256"),
                "test_manifest_sha256": resolved.get("test_manifest_sha256"),
                "test_l1_m": metrics.get("test_l1_m"),
                "num_train_labels": metrics.get("num_train_labels")}
    save_weights(model, path, metadata=metadata)
    return metadata


def plot_learning_curves(metrics: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [e["epoch"] for e in metrics["epochs"]]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(epochs, [1000 * e["train_l1_m"] for e in metrics["epochs"]], "o-", label="train")
    ax.plot(epochs, [1000 * e["test_l1_m"] for e in metrics["epochs"]], "s-", label="test (held-out objects)")
    ax.set_xlabel("epoch")
    ax.set_ylabel("L1 error [mm]")
    ax.set_title("distance CNN learning curves")
    ax.grid(alpha=0.3)
    ranked = [(e["epoch"], e["ranking"]["spearman_mean"]) for e in metrics["epochs"]
              if e.get("ranking", {}).get("images")]
    if ranked:
        ax2 = ax.twinx()
        ax2.plot(*zip(*ranked), "^--", color="tab:green", label="test within-image Spearman")
        ax2.set_ylabel("within-image rank correlation")
        ax2.set_ylim(0, 1)
        ax2.legend(loc="upper center")
    ax.legend()
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def _identity_hash(resolved: dict, *, exclude: tuple[str, ...]) -> str:
    hashed = {**resolved, "train": {k: v for k, v in resolved["train"].items()
                                    if k not in exclude}}
    return hashlib.sha256(json.dumps(hashed, sort_keys=True).encode()).hexdigest()[:16]


class TrainLock(GenerateLock):
    """`train.lock` in a training output folder: one training run at a time."""

    FILE = "train.lock"
    WHAT = "training run"


@full_float32()
def train(*, data: str | Path, out: str | Path, test_data: str | Path | None = None,
          config: TrainConfig | None = None, network: NetworkConfig | None = None,
          progress: bool = True) -> dict:
    """Trains (or resumes training of) the distance CNN; returns the metrics.

    Re-running into the same `out` continues after the last finished epoch, provided the
    configuration and the datasets' contents (their manifests' sha256, not their paths:
    a dataset may be moved) are the same, else an error says so; the epochs may grow,
    and device, threads and max_memory_gb may differ. One run at a time per `out`
    (`train.lock`): a second is refused with the first one's pid, host and start time.
    """
    config = config or TrainConfig()
    config.validate()
    # Bad --data or --init-weights is refused before `out` is created.
    train_dir, test_dir = resolve_data_dirs(data, test_data)
    if config.init_weights and not Path(config.init_weights).is_file():
        raise ValueError(f"init_weights {config.init_weights}: no such file (expected a "
                         "weights file from `train`, e.g. the shipped "
                         "models/cnn/weights.safetensors)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with TrainLock(out):
        return _train_locked(train_dir=train_dir, test_dir=test_dir, out=out, config=config,
                             network=network, progress=progress)


def _train_locked(*, train_dir: Path, test_dir: Path, out: Path, config: TrainConfig,
                  network: NetworkConfig | None, progress: bool) -> dict:
    """`train` once `out` is locked and the config validated."""
    from tqdm import tqdm

    init, network = _initial_network(config, network)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    train_set, test_set, cache = open_training_sets(
        train_dir, test_dir, max_memory_gb=config.max_memory_gb,
        batch_instances=config.batch_instances)
    images_per_batch = max(1, config.batch_instances // train_set.offsets_per_image)
    device = torch_device(config.device)
    located, hashes = _identity(config, network, train_dir, test_dir, train_set, test_set, init)
    config_hash = hashes[0]

    generator = torch.Generator().manual_seed(config.seed)
    model = (init if init is not None
             else DistanceCNN(network, generator=torch.Generator().manual_seed(config.seed)))
    model = model.to(device)
    # Creating an optimizer loads triton's LLVM; keep it apart from a renderer's
    # (drake_grasp.core.native).
    load_llvm_users_first()
    optimizer = _optimizer(model, config)
    metrics = {"epochs": [], "num_train_images": len(train_set),
               "num_test_images": len(test_set), "num_train_labels": train_set.num_labels,
               "num_test_labels": test_set.num_labels}
    ckpt_path = out / "checkpoint.pt"
    metrics, start_epoch, in_epoch = _resume(ckpt_path, hashes, model, optimizer, generator,
                                             metrics)
    metrics.update(device=str(device), code_version=code_version())
    (out / "train_config.json").write_text(json.dumps(located, indent=1))

    for epoch in range(start_epoch, config.epochs + 1):
        model.train()
        lr = config.learning_rate * config.lr_decay_per_epoch ** (epoch - 1)
        for group in optimizer.param_groups:
            group["lr"] = lr
        epoch_generator_state = generator.get_state()
        order = torch.randperm(len(train_set), generator=generator).numpy()
        total, count, done_seconds, first_batch = 0.0, 0, 0.0, 0
        if in_epoch is not None:  # an unfinished epoch: its order again, the rest of it
            total, count = in_epoch["total"], in_epoch["count"]
            done_seconds, first_batch = in_epoch["seconds"], in_epoch["next_batch"]
            in_epoch = None
        t0 = time.perf_counter()
        last_save = t0
        batches = range(0, len(order), images_per_batch)
        bar = tqdm(batches, desc=f"epoch {epoch}/{config.epochs}", disable=not progress,
                   unit="batch", dynamic_ncols=True, initial=first_batch, total=len(batches))
        for b, start in enumerate(batches):
            if b < first_batch:
                continue
            if time.perf_counter() - last_save >= 60 * config.checkpoint_minutes and b > 0:
                _save_checkpoint(ckpt_path, model, optimizer, epoch - 1, epoch_generator_state,
                                 metrics, config_hash, in_epoch={
                                     "epoch": epoch, "next_batch": b, "total": total,
                                     "count": count,
                                     "seconds": done_seconds + time.perf_counter() - t0})
                last_save = time.perf_counter()
            bar.update(1)
            idx = np.sort(order[start:start + images_per_batch])
            l1_sum, n = _train_batch(model, optimizer, train_set, idx, device, config)
            total += l1_sum
            count += n
            bar.set_postfix(l1_mm=f"{1000 * total / count:.1f}")
        bar.close()
        train_seconds = done_seconds + time.perf_counter() - t0
        _end_epoch(model, optimizer, metrics, epoch=epoch, lr=lr, total=total, count=count,
                   train_seconds=train_seconds, iterations=epoch * len(batches),
                   test_set=test_set, test_dir=test_dir, train_set=train_set, cache=cache,
                   config=config, device=device, images_per_batch=images_per_batch)
        _save_checkpoint(ckpt_path, model, optimizer, epoch, generator.get_state(), metrics,
                         config_hash)
        tmp = out / f"metrics.json.{os.getpid()}.tmp"
        tmp.write_text(json.dumps(metrics, indent=1))
        replace_durably(tmp, out / "metrics.json")
        plot_learning_curves(metrics, out / "learning_curves.png")
    train_set.close()
    test_set.close()

    save_weights(model.cpu(), out / "weights.safetensors", metadata={
        "train_manifest_sha256": train_set.manifest_sha256,
        "test_manifest_sha256": test_set.manifest_sha256,
        "epochs": len(metrics["epochs"]), "test_l1_m": metrics.get("test_l1_m"),
        "num_train_labels": metrics["num_train_labels"]})
    return metrics


def _initial_network(config: TrainConfig, network: NetworkConfig | None) -> tuple:
    """(the model to start from or None, its network config): `init_weights`' model and
    config (a different `network` asked for is refused), else `network` or the paper's."""
    init = None
    if config.init_weights:
        path = Path(config.init_weights)
        init, _ = load_weights(path)
        if network is not None and network != init.config:
            raise ValueError(f"init_weights {path}: its network config differs from the "
                             "one asked for")
        network = init.config
    return init, network or NetworkConfig(theta_unit="deg")


def _identity(config, network, train_dir, test_dir, train_set, test_set, init) -> tuple:
    """(the resolved run config with the datasets' folders, the hashes a checkpoint may
    carry to resume: this config's, the one with the folders, the legacy one)."""
    resolved = {"train": config.identity_dict(), "network": network.to_dict(),
                "train_data": str(train_dir), "test_data": str(test_dir),
                "train_manifest_sha256": train_set.manifest_sha256,
                "test_manifest_sha256": test_set.manifest_sha256}
    if init is not None:
        resolved["init_weights_sha256"] = tensors_sha256(init.state_dict())
    # The datasets are identified by their manifests' content, not by where they lie.
    located = resolved
    resolved = {k: v for k, v in located.items() if k not in ("train_data", "test_data")}
    config_hash = _identity_hash(resolved, exclude=NOT_IDENTITY)
    # Checkpoints that hashed the dataset paths as well resume where the paths match.
    located_hash = _identity_hash(located, exclude=NOT_IDENTITY)
    # Checkpoints written before device, threads and max_memory_gb left the identity
    # hashed them too: such a checkpoint resumes when they are given as they were.
    legacy_hash = _identity_hash(located, exclude=("epochs",))
    return located, (config_hash, located_hash, legacy_hash)


def _optimizer(model, config: TrainConfig):
    if config.optimizer == "sgd":
        return torch.optim.SGD(model.parameters(), lr=config.learning_rate,
                               momentum=config.momentum)
    return torch.optim.Adam(model.parameters(), lr=config.learning_rate)


def _resume(ckpt_path: Path, hashes: tuple, model, optimizer, generator, metrics: dict) -> tuple:
    """(metrics, first epoch to run, the unfinished epoch's state or None): from the
    checkpoint when there is one (model, optimizer and generator restored), else as given."""
    if not ckpt_path.exists():
        return metrics, 1, None
    ckpt = load_checkpoint(ckpt_path)
    if ckpt["config_hash"] not in hashes:
        raise ValueError(f"{ckpt_path}: made with another configuration or dataset; "
                         "use another --out")
    model.load_state_dict(ckpt["model"])  # copies onto the model's device
    optimizer.load_state_dict(ckpt["optimizer"])  # state follows the parameters
    generator.set_state(ckpt["generator"])
    metrics = json.loads(ckpt["metrics_json"])
    return (metrics, int(ckpt["epoch"]) + 1,
            json.loads(ckpt.get("in_epoch_json", "null")))


def _train_batch(model, optimizer, train_set, idx, device, config: TrainConfig) -> tuple:
    """One optimizer step on the images `idx`: (their L1 [m] times their label count, the
    label count)."""
    depth, offsets, labels = train_set.gather(idx)
    images = model.preprocess(depth).to(device)
    actions = torch.as_tensor(offsets, device=device, dtype=model.dtype)
    targets = torch.as_tensor(labels, device=device, dtype=model.dtype)
    del depth, offsets, labels  # one batch at a time within --max-memory-gb
    pred = model.forward_factored(images, actions)
    loss = training_loss(pred, targets, config)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    # The running figure is the L1 [m] whatever the loss, comparable across runs.
    l1 = loss if config.loss == "l1" else (pred.detach() - targets).abs().mean()
    return float(l1.detach()) * targets.numel(), targets.numel()


def _end_epoch(model, optimizer, metrics: dict, *, epoch, lr, total, count, train_seconds,
               iterations, test_set, test_dir, train_set, cache, config, device,
               images_per_batch) -> None:
    """Adds the finished epoch's figures (test L1, ranking, what the loader held) to
    `metrics`."""
    test_l1 = evaluate_l1(model, test_set, device=device, batch_images=images_per_batch)
    ranking = {}
    if config.ranking_images:
        ranking = ranking_metrics(model, test_dir, images=config.ranking_images,
                                  seed=config.seed, device=device)
    metrics["epochs"].append({"epoch": epoch, "train_l1_m": total / max(count, 1),
                              "test_l1_m": test_l1, "seconds": train_seconds,
                              "samples_per_s": count / train_seconds, "learning_rate": lr,
                              "iterations": iterations, "ranking": ranking,
                              "device": str(device), "chunk_loads": cache.loads})
    metrics["test_l1_m"] = test_l1
    # What the data loader held (bytes); depends on --max-memory-gb, not the result.
    metrics["loader"] = {"max_memory_bytes": int(config.max_memory_gb * 1e9),
                         "batch_reserve_bytes": cache.reserved_bytes,
                         "cache_budget_bytes": cache.budget_bytes,
                         "cache_peak_bytes": cache.peak_bytes,
                         "dataset_bytes": (len(train_set) + len(test_set))
                         * train_set.bytes_per_image,
                         "chunk_loads": cache.loads}
