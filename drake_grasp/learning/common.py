"""What both training loops share: the device, full-float32 arithmetic, checkpoints, and
reading dataset shards within a memory budget.

`drake_grasp.learning.training` (the paper's tiled net) and
`drake_grasp.learning.dense_training` (the grid head) import it; it imports neither.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
from pathlib import Path

import numpy as np
import torch

from drake_grasp.learning.dataset_shards import load_manifest


# ----------------------------------------------------------------------------
# Data loading, bounded in memory.


class ChunkCache:
    """Decoded HDF5 chunks, least recently used evicted first, at most `budget_bytes`.

    `held_bytes` is what the cache holds now and `peak_bytes` the most it held;
    `loads` counts chunks read from disk (more than the number of chunks means some
    were evicted and read again).
    """

    def __init__(self, budget_bytes: int):
        self.budget_bytes = int(budget_bytes)
        self.reserved_bytes = 0  # kept free beside the cache (for the batch)
        self._items: collections.OrderedDict = collections.OrderedDict()
        self.held_bytes = 0
        self.peak_bytes = 0
        self.loads = 0

    def get(self, key, load, nbytes: int):
        """The arrays cached under `key`, loaded by `load()` (`nbytes` in all) if absent."""
        item = self._items.get(key)
        if item is not None:
            self._items.move_to_end(key)
            return item[0]
        if nbytes > self.budget_bytes:
            raise ValueError(f"a chunk of {nbytes} bytes exceeds the cache of "
                             f"{self.budget_bytes} bytes")
        while self._items and self.held_bytes + nbytes > self.budget_bytes:
            # No local name may keep the evicted arrays alive while the next one loads.
            self.held_bytes -= self._items.popitem(last=False)[1][1]
        arrays = load()
        size = int(sum(a.nbytes for a in arrays))
        self._items[key] = (arrays, size)
        self.held_bytes += size
        self.peak_bytes = max(self.peak_bytes, self.held_bytes)
        self.loads += 1
        return arrays

    def clear(self) -> None:
        self._items.clear()
        self.held_bytes = 0


class ShardSet:
    """A dataset read from its shards through a `ChunkCache`: `gather(indices)` gives
    (depth (B, H, W), offsets (B, M, 3), labels (B, M)) float32 for sorted image indices."""

    MAX_OPEN_FILES = 2

    def __init__(self, data_dir: str | Path, cache: ChunkCache):
        import h5py

        self.root = Path(data_dir)
        self.manifest = load_manifest(self.root)
        self.cache = cache
        self._files: list[Path] = []
        self._chunk_rows: list[int] = []
        counts = []
        shapes = set()
        depth_itemsize = 0  # depth is cached as stored: float16 (format 3) or float32
        for shard in self.manifest["shards"]:
            path = self.root / shard["file"]
            if not path.is_file():
                raise FileNotFoundError(f"{path}: listed in the manifest but missing")
            try:
                with h5py.File(path, "r") as f:
                    depth, offsets = f["depth"], f["offsets"]
                    n = depth.shape[0]
                    if n != shard["num_images"] or f["labels"].shape[0] != n \
                            or offsets.shape[0] != n:
                        raise ValueError(f"holds {n} images, the manifest says "
                                         f"{shard['num_images']}")
                    if n:
                        shapes.add((depth.shape[1:], offsets.shape[1:]))
                        depth_itemsize = max(depth_itemsize, depth.dtype.itemsize)
                    self._chunk_rows.append(int(depth.chunks[0]) if depth.chunks else max(n, 1))
            except (OSError, KeyError, ValueError) as e:
                raise ValueError(f"corrupt dataset shard {path}: {e}") from None
            self._files.append(path)
            counts.append(n)
        if not sum(counts):
            raise ValueError(f"{data_dir}: the dataset has no images")
        if len(shapes) != 1:
            raise ValueError(f"{data_dir}: shards disagree on image or offset shapes: {shapes}")
        (self.image_shape, offsets_shape), = shapes
        self.offsets_per_image = int(offsets_shape[0])
        self.depth_itemsize = depth_itemsize
        self._counts = np.array(counts, dtype=np.int64)
        self._starts = np.concatenate([[0], np.cumsum(self._counts)])
        self._open: collections.OrderedDict = collections.OrderedDict()
        self.manifest_sha256 = hashlib.sha256((self.root / "manifest.json").read_bytes()).hexdigest()

    def __len__(self) -> int:
        return int(self._starts[-1])

    @property
    def num_labels(self) -> int:
        return len(self) * self.offsets_per_image

    @property
    def bytes_per_image(self) -> int:
        """Depth (as stored) and float32 offsets and labels of one image, as cached."""
        m = self.offsets_per_image
        return self.depth_itemsize * int(np.prod(self.image_shape)) + 4 * (3 * m + m)

    def max_chunk_bytes(self) -> int:
        rows = max(min(r, int(c)) for r, c in zip(self._chunk_rows, self._counts))
        return rows * self.bytes_per_image

    def _file(self, k: int):
        import h5py

        f = self._open.get(k)
        if f is not None:
            self._open.move_to_end(k)
            return f
        while len(self._open) >= self.MAX_OPEN_FILES:
            _, old = self._open.popitem(last=False)
            old.close()
        try:
            # No HDF5 chunk cache: whole chunks are read once into ChunkCache.
            f = h5py.File(self._files[k], "r", rdcc_nbytes=0)
        except OSError as e:
            raise ValueError(f"corrupt dataset shard {self._files[k]}: {e}") from None
        self._open[k] = f
        return f

    def _chunk(self, k: int, c: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows = self._chunk_rows[k]
        lo, hi = c * rows, min((c + 1) * rows, int(self._counts[k]))

        def load():
            f = self._file(k)
            try:
                return (np.asarray(f["depth"][lo:hi]),  # converted to float32 in gather
                        np.asarray(f["offsets"][lo:hi], np.float32),
                        np.asarray(f["labels"][lo:hi], np.float32))
            except (OSError, KeyError) as e:
                raise ValueError(f"corrupt dataset shard {self._files[k]}: {e}") from None

        return self.cache.get((id(self), k, c), load, (hi - lo) * self.bytes_per_image)

    def gather(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Images `indices` (sorted, in range) with their offsets and labels, in order."""
        indices = np.asarray(indices, dtype=np.int64)
        n, m = len(indices), self.offsets_per_image
        depth = np.empty((n, *self.image_shape), np.float32)
        offsets = np.empty((n, m, 3), np.float32)
        labels = np.empty((n, m), np.float32)
        shard = np.searchsorted(self._starts, indices, side="right") - 1
        row = indices - self._starts[shard]
        chunk = row // np.asarray(self._chunk_rows, dtype=np.int64)[shard]
        key = shard * (1 << 32) + chunk
        # Runs of one chunk (indices are sorted, so each chunk is one run).
        cuts = np.flatnonzero(np.diff(key)) + 1
        for lo, hi in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [n]])):
            k, c = int(shard[lo]), int(chunk[lo])
            d, o, lab = self._chunk(k, c)
            r = row[lo:hi] - c * self._chunk_rows[k]
            depth[lo:hi], offsets[lo:hi], labels[lo:hi] = d[r], o[r], lab[r]
            del d, o, lab  # so that an evicted chunk is freed before the next one loads
        return depth, offsets, labels

    def close(self) -> None:
        for f in self._open.values():
            f.close()
        self._open.clear()


def open_training_sets(train_dir: str | Path, test_dir: str | Path, *, max_memory_gb: float,
                       images_per_batch: int | None = None,
                       batch_instances: int = 1000) -> tuple[ShardSet, ShardSet, ChunkCache]:
    """Both sets over one chunk cache sized so that it and one batch fit `max_memory_gb`.

    Raises:
        ValueError: when `max_memory_gb` cannot hold even one batch and one chunk.
    """
    budget = int(max_memory_gb * 1e9)
    cache = ChunkCache(budget)  # resized below, once the batch size is known
    train_set, test_set = ShardSet(train_dir, cache), ShardSet(test_dir, cache)
    if images_per_batch is None:
        images_per_batch = max(1, batch_instances // train_set.offsets_per_image)
    m = max(train_set.offsets_per_image, test_set.offsets_per_image)
    per_image = 4 * (int(np.prod(train_set.image_shape)) + 4 * m)  # float32 in the batch
    batch_bytes = 2 * images_per_batch * per_image  # gathered + the network's copy
    chunk = max(train_set.max_chunk_bytes(), test_set.max_chunk_bytes())
    if batch_bytes + chunk > budget:
        need = batch_bytes + chunk
        raise ValueError(
            f"--max-memory-gb {max_memory_gb:g}: too small for even one batch: "
            f"{images_per_batch} images with their offsets and labels take "
            f"{batch_bytes / 1e6:.2f} MB (counted twice: as read and as the network's "
            f"input) and the HDF5 chunk they are read from up to {chunk / 1e6:.2f} MB, "
            f"{need / 1e6:.2f} MB in all; raise --max-memory-gb to at least "
            f"{np.ceil(need / 1e6) / 1e3:g} or lower --batch")
    cache.budget_bytes = budget - batch_bytes
    cache.reserved_bytes = batch_bytes
    return train_set, test_set, cache


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


@contextlib.contextmanager
def full_float32():
    """cuDNN's convolutions and CUDA's matrix products in full float32 while inside.

    PyTorch lets cuDNN run float32 convolutions in TF32 (a 10-bit mantissa) by default on
    Ampere and later GPUs, so a run resumed across devices would change its arithmetic
    mid-run. Measured on an H200 (`analysis/results/device-train-check/`): a CPU run and
    the same run resumed on the GPU after 4 of 6 steps ended 1.1e-4 apart in the weights
    with TF32 and 1.7e-6 apart without it; full float32 cost at most 6% of the GPU step's
    speed (batch 1000), and `train-grid`, bound by building batches on the CPU, was not
    slower. Restores the flags on the way out. Used as a decorator by both trainers; no
    effect on the CPU.
    """
    saved = (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)
    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def torch_device(name: str) -> torch.device:
    """The torch device a `device` setting names ("auto": CUDA when there is one)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def load_checkpoint(path: str | Path) -> dict:
    """A training checkpoint, its tensors on the CPU whatever device wrote them.

    `weights_only=True`: a checkpoint file cannot run code when loaded.
    """
    return torch.load(path, weights_only=True, map_location="cpu")
