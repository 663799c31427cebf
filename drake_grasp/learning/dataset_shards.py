"""The training set on disk: shard files, the manifest, and the torch `Dataset` that reads them.

On disk (this module owns the format; `dataset_generate` writes it):

    DIR/manifest.json           counts, resolved config, code version, shard list
    DIR/shard-00000.h5          scenes [0, S), one file per task of S scenes
    DIR/shard-00001.h5          ...; the last shard holds the rest (may be smaller)
    DIR/generate.lock           while a generator runs: its pid, host and start time

Shard layout (HDF5, chunked + gzip):

    depth        (I, H, W) float16   post-processed depth [m] (float32 in format 2)
    hand_pose    (I, 4)    float64   [x, y, z, yaw_deg] of the grasp frame G (camera rigid on G)
    offsets      (I, M, 3) float32   actions [dx, dy, dtheta_deg] in the hand frame
    labels       (I, M)    float32   distance to the nearest true grasp [m]
    image_scene  (I,)      int64     global scene index of each image
    scene_index  (S,)      int64     global scene indices in this shard
    scene_attempt (S,)     int64     which attempt of the scene's seed sequence was kept
    scene_spec   (S,)      str       SceneSpec JSON (re-render any sample from it)
    grasp_scene  (G,)      int64     global scene index of each grasp
    grasp_pose   (G, 4, 4) float64   world grasp-frame poses
    grasp_width  (G,)      float32
    grasp_xy_theta (G, 3)  float64   [x, y, theta_deg mod 180]
    attrs: split, config_hash, code_version, format_version, num_scenes, num_images,
           num_labels, skipped, scene_first, scene_stop, num_attempts,
           num_replaced_no_grasp, num_replaced_unsettled
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from drake_grasp.learning.dataset import DEPTH_DTYPE, MANIFEST, SceneSamples
from drake_grasp.learning.folder_lock import process_tag, replace_durably



# ----------------------------------------------------------------------------
# Shards.


def shard_name(shard_index: int) -> str:
    return f"shard-{shard_index:05d}.h5"


def write_shard(path: Path, samples: list[SceneSamples], *, attrs: dict,
                tmp_tag: str | None = None) -> None:
    """Writes a shard atomically and durably: a temporary name private to this process
    (`path.<tmp_tag>.<host>-<pid>.tmp`), fsync, rename to `path`, fsync the folder.

    `samples` entries that are None are counted in the `skipped` attr (older callers).
    """
    import h5py

    path = Path(path)
    tmp = path.with_name(f"{path.name}.{tmp_tag or 'write'}.{process_tag()}.tmp")
    kept = [s for s in samples if s is not None]
    try:
        with h5py.File(tmp, "w") as f:
            def put(name, arrays, dtype, shape_tail):
                data = np.concatenate(arrays) if arrays else np.zeros((0, *shape_tail), dtype)
                chunks = (min(64, max(1, len(data))), *shape_tail) if len(data) else None
                f.create_dataset(name, data=data.astype(dtype), chunks=chunks,
                                 compression="gzip" if len(data) else None,
                                 compression_opts=4 if len(data) else None)

            hw = kept[0].depth.shape[1:] if kept else (0, 0)
            m = kept[0].offsets.shape[1] if kept else 0
            put("depth", [s.depth for s in kept], DEPTH_DTYPE, hw)
            put("hand_pose", [s.hand_pose for s in kept], np.float64, (4,))
            put("offsets", [s.offsets for s in kept], np.float32, (m, 3))
            put("labels", [s.labels for s in kept], np.float32, (m,))
            put("image_scene", [np.full(len(s.depth), s.scene_index) for s in kept], np.int64, ())
            put("grasp_scene", [np.full(len(s.grasp_width), s.scene_index) for s in kept],
                np.int64, ())
            put("grasp_pose", [s.grasp_pose for s in kept], np.float64, (4, 4))
            put("grasp_width", [s.grasp_width for s in kept], np.float32, ())
            put("grasp_xy_theta", [s.grasp_xy_theta for s in kept], np.float64, (3,))
            f.create_dataset("scene_index", data=np.array([s.scene_index for s in kept], np.int64))
            f.create_dataset("scene_attempt", data=np.array([s.attempt for s in kept], np.int64))
            f.create_dataset("scene_spec", data=[s.spec_json for s in kept],
                             dtype=h5py.string_dtype())
            num_images = int(sum(len(s.depth) for s in kept))
            f.attrs.update(attrs)
            f.attrs["num_scenes"] = len(kept)
            f.attrs["num_images"] = num_images
            f.attrs["num_labels"] = int(sum(s.labels.size for s in kept))
            f.attrs["skipped"] = len(samples) - len(kept)
        replace_durably(tmp, path)
    except OSError as e:
        message = f"cannot write dataset shard {path}: {e.strerror or e}"  # e.g. a full disk
        raise (OSError(e.errno, message) if e.errno else OSError(message)) from e
    finally:
        if tmp.exists():
            tmp.unlink()  # a failed write leaves nothing behind


_COUNT_ATTRS = ("num_scenes", "num_images", "num_labels", "skipped")
# Written since format 2; 0/absent in shards written without them.
_OPTIONAL_ATTRS = ("scene_first", "scene_stop", "num_attempts", "num_replaced_no_grasp",
                   "num_replaced_unsettled")


def read_shard_counts(path: Path) -> dict:
    """Counts and attrs of a finished shard; a corrupt file is reported by name."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            counts = {k: int(f.attrs[k]) for k in _COUNT_ATTRS}
            for k in _OPTIONAL_ATTRS:
                counts[k] = int(f.attrs[k]) if k in f.attrs else None
            counts["config_hash"] = str(f.attrs["config_hash"])
            if f["depth"].shape[0] != counts["num_images"]:
                raise ValueError("depth rows do not match num_images")
            return counts
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"corrupt dataset shard {path}: {e}; delete it and re-run to regenerate it") from None



# ----------------------------------------------------------------------------
# Reading.


def load_manifest(data_dir: str | Path) -> dict:
    path = Path(data_dir) / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no manifest; is {data_dir} a dataset folder?")
    return json.loads(path.read_text())


class DepthGraspDataset(Dataset):
    """A torch-style Dataset over shards, read lazily: item i is one depth image with its
    M labelled offsets: {"depth": (H, W), "offsets": (M, 3), "labels": (M,)} (float32).

    Shards are opened on first use in each process (safe with DataLoader workers).
    """

    def __init__(self, data_dir: str | Path):
        self.root = Path(data_dir)
        self.manifest = load_manifest(self.root)
        self._files = [self.root / s["file"] for s in self.manifest["shards"]]
        for path in self._files:
            if not path.is_file():
                raise FileNotFoundError(f"{path}: listed in the manifest but missing")
        counts = np.array([s["num_images"] for s in self.manifest["shards"]], dtype=np.int64)
        self._starts = np.concatenate([[0], np.cumsum(counts)])
        self._handles: dict = {}

    def __len__(self) -> int:
        return int(self._starts[-1])

    def _file(self, k: int):
        import h5py

        h = self._handles.get(k)
        if h is None:
            try:
                h = h5py.File(self._files[k], "r")
            except OSError as e:
                raise ValueError(f"corrupt dataset shard {self._files[k]}: {e}") from None
            self._handles[k] = h
        return h

    def locate(self, index: int) -> tuple[int, int]:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} images")
        k = int(np.searchsorted(self._starts, index, side="right") - 1)
        return k, int(index - self._starts[k])

    def __getitem__(self, index: int) -> dict:
        k, row = self.locate(int(index))
        f = self._file(k)
        try:
            return {"depth": np.asarray(f["depth"][row], np.float32),
                    "offsets": np.asarray(f["offsets"][row], np.float32),
                    "labels": np.asarray(f["labels"][row], np.float32)}
        except (OSError, KeyError) as e:
            raise ValueError(f"corrupt dataset shard {self._files[k]}: {e}") from None

    def image_record(self, index: int) -> dict:
        """The image with its hand pose, scene spec and the scene's grasps (for pictures)."""
        k, row = self.locate(int(index))
        f = self._file(k)
        scene = int(f["image_scene"][row])
        s_row = int(np.nonzero(f["scene_index"][:] == scene)[0][0])
        g = f["grasp_scene"][:] == scene
        spec = f["scene_spec"][s_row]
        return {**self[index], "hand_pose": f["hand_pose"][row], "scene_index": scene,
                "scene_spec": json.loads(spec.decode() if isinstance(spec, bytes) else spec),
                "grasp_pose": f["grasp_pose"][g], "grasp_width": f["grasp_width"][g],
                "grasp_xy_theta": f["grasp_xy_theta"][g]}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_handles"] = {}
        return state
