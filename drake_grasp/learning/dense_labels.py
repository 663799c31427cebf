"""Dense labels of the grid head (`NetworkConfig(action_fusion="grid")`): the label of a
grid node's action on an image is the distance from the hand pose it leads to, to the
nearest ground-truth grasp of the image's scene (the dataset's own label function,
`grasps.distance_to_nearest_grasp`), computed exactly (to float rounding) with a k-d tree
over the scene's grasps in the metric's coordinates (x, y, 0.001 m/deg x theta, theta
periodic over 180 degrees). This module owns the grid's node actions
(`grid_node_actions`), the tree (`nearest_grasp_tree`, `tree_distances`), the labels of
an image set and of a dataset folder's shards (`label_grids`, `build_labels`, one
``.npz`` part per shard), the view masks that say which nodes are labelled and count in
the loss (`view_masks`), and reading the labels back, all in memory (`load_labels`) or
streamed by groups of parts (`LabelStore`); `drake_grasp.learning.dense_training`
trains on them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from drake_grasp.geometry.grasp_metric import ANGLE_WEIGHT_M_PER_DEG
from drake_grasp.cnn.grid_head import grid_view_mask
from drake_grasp.cnn.net_config import NetworkConfig

GRID_CONFIG = NetworkConfig(theta_unit="deg", action_fusion="grid")
_THETA_PERIOD_M = 180.0 * ANGLE_WEIGHT_M_PER_DEG
_SHIFT_M = 50.0  # x, y moved into the k-d tree's positive box
_BOX_M = 1000.0

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
