"""Training of the distance CNN (the paper: L1 loss, SGD lr 0.001, momentum 0.9, batches
of 1000 instances), resumable after a kill.

An instance is one (image, offset, label) triple. A batch of 1000 instances is 100 images
with their 10 labelled offsets each, which the factored fast path scores with one image
pass per image (`DistanceCNN.forward_factored`).

Output folder:

    checkpoint.pt        model + optimizer + epoch + RNG state after the last finished
                         epoch (torch.save; loaded with weights_only=True)
    metrics.json         per-epoch train/test L1 [m], timing, and the final test_l1_m
    learning_curves.png  train and test L1 per epoch
    weights.safetensors  final weights with metadata (network.save_weights)
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

from drake_grasp import __version__
from drake_grasp.dataset import DepthGraspDataset, load_manifest
from drake_grasp.network import DistanceCNN, NetworkConfig, save_weights


@dataclass
class TrainConfig:
    """Training settings (defaults from the paper where it gives them)."""

    epochs: int = 10
    batch_instances: int = 1000
    learning_rate: float = 0.001
    momentum: float = 0.9
    seed: int = 0
    # Largest dataset held in memory [GB]; both sets are loaded once (fast epochs).
    max_memory_gb: float = 8.0
    device: str = "auto"
    threads: int = 0  # 0 = torch default

    def validate(self) -> None:
        if self.epochs < 1:
            raise ValueError(f"epochs: expected >= 1, got {self.epochs}")
        if self.batch_instances < 1:
            raise ValueError(f"batch_instances: expected >= 1, got {self.batch_instances}")
        if self.learning_rate <= 0:
            raise ValueError(f"learning_rate: expected > 0, got {self.learning_rate}")


@dataclass
class ArraySet:
    """A dataset loaded into memory: depth (N, H, W), offsets (N, M, 3), labels (N, M)."""

    depth: np.ndarray
    offsets: np.ndarray
    labels: np.ndarray
    manifest_sha256: str

    def __len__(self) -> int:
        return len(self.depth)


def load_arrays(data_dir: str | Path, *, max_memory_gb: float) -> ArraySet:
    """Reads every shard of a dataset into memory (chunk-wise, not image by image)."""
    import h5py

    ds = DepthGraspDataset(data_dir)
    m = ds.manifest
    size_gb = m["num_images"] * (64 * 64 * 4 + 10 * 16) / 1e9
    if size_gb > max_memory_gb:
        raise ValueError(f"{data_dir}: {size_gb:.1f} GB exceeds max_memory_gb={max_memory_gb}")
    depth, offsets, labels = [], [], []
    for shard in m["shards"]:
        path = Path(data_dir) / shard["file"]
        try:
            with h5py.File(path, "r") as f:
                depth.append(f["depth"][:])
                offsets.append(f["offsets"][:])
                labels.append(f["labels"][:])
        except (OSError, KeyError) as e:
            raise ValueError(f"corrupt dataset shard {path}: {e}") from None
    if not depth or sum(len(d) for d in depth) == 0:
        raise ValueError(f"{data_dir}: the dataset has no images")
    sha = hashlib.sha256((Path(data_dir) / "manifest.json").read_bytes()).hexdigest()
    return ArraySet(np.concatenate(depth), np.concatenate(offsets).astype(np.float32),
                    np.concatenate(labels).astype(np.float32), sha)


def resolve_data_dirs(data: str | Path, test_data: str | Path | None) -> tuple[Path, Path]:
    """(train, test) dataset folders: `data` + `test_data`, or `data/train` + `data/test`."""
    data = Path(data)
    if (data / "manifest.json").is_file():
        if test_data is None:
            raise ValueError(f"{data} is one dataset; give the test-split dataset with "
                             "--test-data (the split is by object instance)")
        return data, Path(test_data)
    train, test = data / "train", Path(test_data) if test_data else data / "test"
    for d in (train, test):
        load_manifest(d)  # clear error if missing
    return train, test


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def evaluate_l1(model: DistanceCNN, data: ArraySet, *, device, batch_images: int = 200) -> float:
    """Mean absolute error [m] over every labelled offset of a set."""
    model.eval()
    total, count = 0.0, 0
    with torch.no_grad():
        for start in range(0, len(data), batch_images):
            sl = slice(start, start + batch_images)
            images = model.preprocess(data.depth[sl]).to(device)
            actions = torch.as_tensor(data.offsets[sl], device=device, dtype=model.dtype)
            labels = torch.as_tensor(data.labels[sl], device=device, dtype=model.dtype)
            pred = model.forward_factored(images, actions)
            total += float((pred - labels).abs().sum())
            count += labels.numel()
    return total / max(count, 1)


def _save_checkpoint(path: Path, model, optimizer, epoch: int, generator: torch.Generator,
                     metrics: dict, config_hash: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "epoch": epoch, "generator": generator.get_state(),
                "metrics_json": json.dumps(metrics), "config_hash": config_hash}, tmp)
    os.replace(tmp, path)


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
    ax.legend()
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)


def train(*, data: str | Path, out: str | Path, test_data: str | Path | None = None,
          config: TrainConfig | None = None, network: NetworkConfig | None = None,
          progress: bool = True) -> dict:
    """Trains (or resumes training of) the distance CNN; returns the metrics.

    Re-running into the same `out` continues after the last finished epoch, provided the
    configuration and datasets are the same (else an error names what differs).
    """
    from tqdm import tqdm

    config = config or TrainConfig()
    config.validate()
    network = network or NetworkConfig(theta_unit="deg")
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    train_dir, test_dir = resolve_data_dirs(data, test_data)
    train_set = load_arrays(train_dir, max_memory_gb=config.max_memory_gb)
    test_set = load_arrays(test_dir, max_memory_gb=config.max_memory_gb)
    m = train_set.offsets.shape[1]
    images_per_batch = max(1, config.batch_instances // m)
    device = _device(config.device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    resolved = {"train": dataclasses.asdict(config), "network": network.to_dict(),
                "train_data": str(train_dir), "test_data": str(test_dir),
                "train_manifest_sha256": train_set.manifest_sha256,
                "test_manifest_sha256": test_set.manifest_sha256}
    # Epoch count may grow on resume; everything else must match.
    hashed = {**resolved, "train": {k: v for k, v in resolved["train"].items() if k != "epochs"}}
    config_hash = hashlib.sha256(json.dumps(hashed, sort_keys=True).encode()).hexdigest()[:16]

    generator = torch.Generator().manual_seed(config.seed)
    model = DistanceCNN(network, generator=torch.Generator().manual_seed(config.seed)).to(device)
    optimizer = torch.optim.SGD(model.parameters(), lr=config.learning_rate,
                                momentum=config.momentum)
    metrics = {"epochs": [], "device": str(device), "code_version": __version__,
               "num_train_images": len(train_set), "num_test_images": len(test_set),
               "num_train_labels": int(train_set.labels.size),
               "num_test_labels": int(test_set.labels.size)}
    start_epoch = 1
    ckpt_path = out / "checkpoint.pt"
    if ckpt_path.exists():
        ckpt = torch.load(ckpt_path, weights_only=True, map_location=device)
        if ckpt["config_hash"] != config_hash:
            raise ValueError(f"{ckpt_path}: made with another configuration or dataset; "
                             "use another --out")
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        generator.set_state(ckpt["generator"])
        metrics = json.loads(ckpt["metrics_json"])
        start_epoch = int(ckpt["epoch"]) + 1
    (out / "train_config.json").write_text(json.dumps(resolved, indent=1))

    for epoch in range(start_epoch, config.epochs + 1):
        model.train()
        t0 = time.perf_counter()
        order = torch.randperm(len(train_set), generator=generator).numpy()
        total, count = 0.0, 0
        batches = range(0, len(order), images_per_batch)
        bar = tqdm(batches, desc=f"epoch {epoch}/{config.epochs}", disable=not progress,
                   unit="batch", dynamic_ncols=True)
        for start in bar:
            idx = np.sort(order[start:start + images_per_batch])
            images = model.preprocess(train_set.depth[idx]).to(device)
            actions = torch.as_tensor(train_set.offsets[idx], device=device, dtype=model.dtype)
            labels = torch.as_tensor(train_set.labels[idx], device=device, dtype=model.dtype)
            loss = (model.forward_factored(images, actions) - labels).abs().mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * labels.numel()
            count += labels.numel()
            bar.set_postfix(l1_mm=f"{1000 * total / count:.1f}")
        train_seconds = time.perf_counter() - t0
        test_l1 = evaluate_l1(model, test_set, device=device)
        metrics["epochs"].append({"epoch": epoch, "train_l1_m": total / max(count, 1),
                                  "test_l1_m": test_l1, "seconds": train_seconds,
                                  "samples_per_s": count / train_seconds})
        metrics["test_l1_m"] = test_l1
        _save_checkpoint(ckpt_path, model, optimizer, epoch, generator, metrics, config_hash)
        tmp = out / "metrics.json.tmp"
        tmp.write_text(json.dumps(metrics, indent=1))
        os.replace(tmp, out / "metrics.json")
        plot_learning_curves(metrics, out / "learning_curves.png")

    save_weights(model.cpu(), out / "weights.safetensors", metadata={
        "train_manifest_sha256": train_set.manifest_sha256,
        "test_manifest_sha256": test_set.manifest_sha256,
        "epochs": len(metrics["epochs"]), "test_l1_m": metrics.get("test_l1_m"),
        "num_train_labels": metrics["num_train_labels"]})
    return metrics
