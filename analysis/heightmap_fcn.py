"""Pilot: does a fully convolutional net on a metric height map fit the dense distance
labels better than the LeNet grid head?

The grid head maps the whole 64x64 depth image through one 500-wide layer to all
18 x 33 x 33 grid nodes, and must learn for itself that the image's scale changes with
the camera's height (0.15-0.30 m) and that a node's label depends mostly on what lies
near it. Here each depth image is first turned into a height map on a metric lattice
(5 mm cells, +-18 cm around the camera's axis): every pixel is back-projected with its
own depth (the wrist camera looks straight down; Drake's depth is along its axis), its
height above the table is `camera height - depth`, the highest sample per cell is kept,
empty cells take their neighbours' highest, and a second channel marks the cells the
view covers. The camera height is the hand's (proprioception, which the controller has).
A small residual net of dilated 3x3 convolutions (receptive field about 45 cm) maps the
map to 18 distances (one per theta bin) at every 1 cm node: translation-equivariant and
scale-free by construction.

Both nets are measured on the held-out dense grids (`data/paper_test_grid`, the nodes in
each image's view, as the training loss takes them):

    python analysis/heightmap_fcn.py train --labels data/near0_grid,data/clutter_train_grid \
        --out data/fcn_pilot --minutes 40
    python analysis/heightmap_fcn.py compare --test data/paper_test_grid \
        --fcn data/fcn_pilot/model.pt --weights models/cnn-grid-bn12/weights.safetensors \
        --out analysis/results/heightmap-fcn/compare.json

`train` checkpoints every epoch and after its time budget (`--minutes`); the same command
resumes a stopped run (the batches of epoch e are a permutation seeded by e).

`train --grasp-weight W` adds a grasp head: per node, "a true grasp lies within half a
cell's diagonal" (`GRASP_NODE_M`), whose distance transform on the grid's lattice is a
second prediction of the labels (`grasp_map_distances`; `compare --val FOLDER` picks its
threshold on validation scenes). `compare --oracle` measures that transform of the test
labels' own grasp nodes: what a perfect grasp head would score.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drake_grasp.dense_training import (  # noqa: E402
    GRID_CONFIG, grid_node_actions, load_labels, view_masks)

CELL_M = 0.005
LATTICE_HALF_M = 0.18
LATTICE = int(round(2 * LATTICE_HALF_M / CELL_M)) + 1  # 73 cells, centres -18..18 cm
HEIGHT_SCALE = 10.0  # input height in decimetres
# A grid node is a "grasp node" when a true grasp lies within half the diagonal of its
# 1 cm x 1 cm x 10 degree cell (the metric weighs 10 degrees as 1 cm): every grasp over
# the grid has one, and the distance transform of the grasp nodes is the label to within
# that half-diagonal.
GRASP_NODE_M = 0.5 * math.sqrt(3.0) * GRID_CONFIG.grid_step_m
GRASP_POS_WEIGHT = 10.0  # grasp nodes are 0.7% of the in-view nodes


@functools.lru_cache(maxsize=None)
def camera_z_G() -> float:
    """The camera's height in the gripper frame (read once; `_masks` needs it per batch)."""
    from drake_grasp.station import gripper_frame_offsets
    return float(gripper_frame_offsets()[2].translation()[2])


def height_maps(depth: np.ndarray, hand_z: np.ndarray, *, batch: int = 2000) -> np.ndarray:
    """(B, 2, L, L) float16: height above the table [dm] on the metric lattice, and the
    mask of the cells the view covers, from (B, 64, 64) depth [m] and hand heights [m]."""
    cfg = GRID_CONFIG
    f = cfg.focal_px
    size = depth.shape[-1]
    c = np.arange(size) - (size / 2.0 - 0.5)
    cam_h = np.asarray(hand_z, np.float64) - camera_z_G()
    out = np.empty((len(depth), 2, LATTICE, LATTICE), np.float16)
    cols = torch.from_numpy(np.tile(c, size)).float()           # pixel u (x_G)
    rows = torch.from_numpy(np.repeat(c, size)).float()         # pixel v (y_G)
    centres = (torch.arange(LATTICE).float() - (LATTICE - 1) / 2) * CELL_M
    for lo in range(0, len(depth), batch):
        d = torch.from_numpy(depth[lo:lo + batch].astype(np.float32)).flatten(1)
        h = torch.from_numpy(cam_h[lo:lo + batch]).float()
        b = len(d)
        x = cols[None] * d / f
        y = rows[None] * d / f
        height = (h[:, None] - d).clamp(min=0.0)
        ix = torch.round((x + LATTICE_HALF_M) / CELL_M).long()
        iy = torch.round((y + LATTICE_HALF_M) / CELL_M).long()
        ok = (ix >= 0) & (ix < LATTICE) & (iy >= 0) & (iy < LATTICE)
        flat = torch.where(ok, iy * LATTICE + ix, torch.full_like(ix, LATTICE * LATTICE))
        hm = torch.full((b, LATTICE * LATTICE + 1), -1.0)
        hm.scatter_reduce_(1, flat, height, reduce="amax", include_self=True)
        hm = hm[:, :-1].reshape(b, 1, LATTICE, LATTICE)
        # Empty cells (finer than a pixel near the table at low heights): the highest of
        # their 3x3 neighbours, twice.
        for _ in range(2):
            filled = F.max_pool2d(hm, 3, stride=1, padding=1)
            hm = torch.where(hm < 0, filled, hm)
        # The view: the camera's footprint on the table.
        half = (h * math.tan(math.radians(cfg.camera_fov_deg) / 2.0))[:, None]
        inside = (centres.abs()[None] <= half)
        view = (inside[:, :, None] & inside[:, None, :]).float()[:, None]
        hm = torch.where((hm < 0) | (view == 0), torch.zeros_like(hm), hm)
        out[lo:lo + b, 0] = (hm[:, 0] * HEIGHT_SCALE).numpy()
        out[lo:lo + b, 1] = view[:, 0].numpy()
    return out


class HeightmapFCN(nn.Module):
    """(B, 2, 73, 73) height map -> (B, 18, 33, 33) distances [m] at the grid's nodes;
    with `grasp_head`, also (B, 18, 33, 33) logits of "a true grasp lies within
    `GRASP_NODE_M` of this node" (`outputs`)."""

    def __init__(self, width: int = 32, dilations=(1, 2, 4, 8, 4, 2, 1), *,
                 grasp_head: bool = False):
        super().__init__()
        self.grasp_head = grasp_head
        self.stem = nn.Sequential(
            nn.Conv2d(2, width, 3, padding=1), nn.BatchNorm2d(width), nn.LeakyReLU(0.01),
            nn.Conv2d(width, width, 3, stride=2, padding=1), nn.BatchNorm2d(width),
            nn.LeakyReLU(0.01))  # 37 x 37 at 1 cm, centres -18..18 cm
        self.blocks = nn.ModuleList(
            nn.Sequential(nn.Conv2d(width, width, 3, padding=d, dilation=d),
                          nn.BatchNorm2d(width), nn.LeakyReLU(0.01)) for d in dilations)
        t_bins = GRID_CONFIG.grid_shape()[0]
        self.head = nn.Conv2d(width, t_bins * (2 if grasp_head else 1), 1)

    def outputs(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The distances [m] and the grasp logits (None without a grasp head)."""
        h = self.stem(x)
        for block in self.blocks:
            h = h + block(h)
        n = GRID_CONFIG.grid_shape()[1]
        crop = (h.shape[-1] - n) // 2
        z = self.head(h)[:, :, crop:crop + n, crop:crop + n]
        t_bins = GRID_CONFIG.grid_shape()[0]
        distances = GRID_CONFIG.output_scale_m * F.softplus(z[:, :t_bins])
        return distances, (z[:, t_bins:] if self.grasp_head else None)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.outputs(x)[0]


def _masks(hand_z: np.ndarray) -> torch.Tensor:
    mx = torch.from_numpy(view_masks(hand_z, GRID_CONFIG, camera_z_G()))
    return mx[:, None, :, None] & mx[:, None, None, :]


def grasp_map_distances(logits: np.ndarray, hand_z: np.ndarray, threshold: float) -> np.ndarray:
    """(B, 18, 33, 33) distances [m] from each node to the nearest in-view node whose
    grasp probability is at least `threshold` (the Euclidean distance transform on the
    grid's 1 cm lattice, periodic over theta's 180 degrees); NaN for an image with none."""
    from scipy.ndimage import distance_transform_edt

    t_bins = GRID_CONFIG.grid_shape()[0]
    pos = (logits >= math.log(threshold / (1.0 - threshold))) & _masks(hand_z).numpy()
    out = np.full(logits.shape, np.nan, np.float32)
    for i in np.flatnonzero(pos.reshape(len(pos), -1).any(axis=1)):
        wrapped = np.concatenate([~pos[i]] * 3, axis=0)  # theta periodic: the middle copy
        edt = distance_transform_edt(wrapped)[t_bins:2 * t_bins]
        out[i] = edt * GRID_CONFIG.grid_step_m
    return out


def train(labels: list[str], out: Path, *, minutes: float, epochs: int, batch: int,
          lr: float, width: int, seed: int, threads: int, max_images: int = 0,
          grasp_weight: float = 0.0) -> None:
    """Adam on the masked L1 over the in-view nodes, cosine decay over `epochs`;
    `max_images` > 0 trains on a random subset of that many images (seeded), for a
    learning curve over data. `grasp_weight` > 0 adds the grasp head, trained with that
    weight on the binary cross-entropy of "label <= GRASP_NODE_M" over the same nodes."""
    from tqdm import tqdm

    if max_images < 0:
        raise ValueError(f"max_images: expected >= 0 (0 = all), got {max_images}")
    identity = {"labels": [str(x) for x in labels], "max_images": int(max_images),
                "epochs": int(epochs), "batch": int(batch), "lr": float(lr),
                "width": int(width), "seed": int(seed)}
    if grasp_weight:
        identity["grasp_weight"] = float(grasp_weight)
    ckpt = out / "checkpoint.pt"
    saved = torch.load(ckpt, weights_only=False) if ckpt.exists() else None
    if saved is not None and saved.get("identity") != identity:
        theirs = saved.get("identity") or {}
        diff = sorted(k for k in identity if theirs.get(k) != identity[k])
        raise ValueError(f"{ckpt}: holds another training run (differs in {diff}); "
                         "use another --out folder")
    torch.set_num_threads(threads)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    data = load_labels(labels)
    if 0 < max_images < len(data["hand_z"]):
        keep = np.sort(np.random.default_rng([seed, 7]).choice(
            len(data["hand_z"]), max_images, replace=False))
        data = {k: v[keep] for k, v in data.items()}
    maps = height_maps(data["depth"], data["hand_z"])
    grids, hand_z = data["grid"], data["hand_z"]
    del data
    print(f"{len(maps)} images; height maps in {time.perf_counter() - t0:.0f} s", flush=True)
    torch.manual_seed(seed)
    model = HeightmapFCN(width, grasp_head=grasp_weight > 0)
    pos_weight = torch.tensor(GRASP_POS_WEIGHT)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    state = {"epoch": 0, "batch_index": 0, "train_s": 0.0, "log": []}
    if saved is not None:
        model.load_state_dict(saved["model"])
        opt.load_state_dict(saved["opt"])
        state = saved["state"]
        print(f"resumed at epoch {state['epoch']} batch {state['batch_index']}", flush=True)

    def save():
        tmp = out / "checkpoint.pt.tmp"
        torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "state": state,
                    "width": width, "grasp_head": model.grasp_head, "identity": identity}, tmp)
        tmp.replace(ckpt)

    budget_s = minutes * 60.0
    start = time.perf_counter()
    base_s = state["train_s"]
    n = len(maps)
    stopped = False
    while state["epoch"] < epochs and not stopped:
        order = np.random.default_rng([seed, state["epoch"]]).permutation(n)
        starts = list(range(0, n, batch))
        for g in opt.param_groups:
            g["lr"] = lr * 0.5 * (1 + math.cos(math.pi * state["epoch"] / epochs))
        model.train()
        total = count = bce_total = 0.0
        bar = tqdm(starts[state["batch_index"]:], desc=f"epoch {state['epoch'] + 1}",
                   mininterval=30)
        for s in bar:
            idx = np.sort(order[s:s + batch])
            x = torch.from_numpy(maps[idx].astype(np.float32))
            target = torch.from_numpy(grids[idx].astype(np.float32))
            mask = _masks(hand_z[idx]).expand_as(target) & torch.isfinite(target)
            pred, logits = model.outputs(x)
            loss = (pred - target).abs()[mask].mean()
            l1 = loss.item()
            if logits is not None:
                is_grasp = (target <= GRASP_NODE_M).float()
                bce = F.binary_cross_entropy_with_logits(logits[mask], is_grasp[mask],
                                                         pos_weight=pos_weight)
                loss = loss + grasp_weight * bce
                bce_total += bce.item() * len(idx)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += l1 * len(idx)
            count += len(idx)
            state["batch_index"] += 1
            state["train_s"] = base_s + time.perf_counter() - start
            if state["train_s"] - base_s > budget_s:
                stopped = True
                break
        state["log"].append({"epoch": state["epoch"] + 1, "batches_to": state["batch_index"],
                             "train_l1_m": total / max(count, 1), "train_s": state["train_s"]})
        if model.grasp_head:
            state["log"][-1]["train_bce"] = bce_total / max(count, 1)
        print(json.dumps(state["log"][-1]), flush=True)
        if not stopped:
            state["epoch"] += 1
            state["batch_index"] = 0
        save()
    torch.save({"model": model.state_dict(), "width": width, "grasp_head": model.grasp_head,
                "state": state, "identity": identity}, out / "model.pt")


def metrics(pred: np.ndarray, data: dict, *, seed: int = 0, images: int = 2000) -> dict:
    """Dense L1 over the in-view nodes, by label bin, and within-image Spearman over the
    nodes the controller's candidates cover (|x|, |y| <= 4 cm from the hand, |theta| <= 45
    degrees, in view)."""
    from drake_grasp.cnn_metrics import spearman

    grid = data["grid"].astype(np.float32)
    mask = _masks(data["hand_z"]).expand(grid.shape).numpy() & np.isfinite(grid)
    err = np.abs(pred - grid)[mask]
    lab = grid[mask]
    bins = []
    for lo, hi in ((0, 0.03), (0.03, 0.06), (0.06, 0.10), (0.10, 0.15), (0.15, np.inf)):
        sel = (lab >= lo) & (lab < hi)
        bins.append({"label_mm": [lo * 1e3, None if hi == np.inf else hi * 1e3],
                     "nodes": int(sel.sum()), "l1_mm": float(err[sel].mean() * 1e3)})
    # A node's action is the hand's displacement (x, y, theta), so "near" reads off it.
    actions = grid_node_actions(GRID_CONFIG).reshape(*GRID_CONFIG.grid_shape(), 3)
    near = ((np.abs(actions[..., 2]) <= 45.0) & (np.abs(actions[..., 0]) <= 0.04)
            & (np.abs(actions[..., 1]) <= 0.04))
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(grid), min(images, len(grid)), replace=False)
    rhos, top1 = [], []
    for i in chosen:
        m = near & mask[i]
        if m.sum() < 10:
            continue
        p, t = pred[i][m], grid[i][m]
        if np.ptp(t) == 0:
            continue
        rhos.append(float(spearman(p[None], t[None])[0]))
        top1.append(float(t[np.argmin(p)] - t.min() <= 0.01))
    return {"dense_l1_mm": float(err.mean() * 1e3), "nodes": int(mask.sum()),
            "l1_by_label": bins, "spearman_images": len(rhos),
            "spearman_mean": float(np.mean(rhos)), "spearman_median": float(np.median(rhos)),
            "top1_within_1cm": float(np.mean(top1))}


def predict_fcn(path: str, data: dict, *, batch: int = 200) -> tuple[np.ndarray, np.ndarray | None]:
    """A trained FCN's distances and (with a grasp head; else None) grasp logits."""
    saved = torch.load(path, weights_only=False)
    model = HeightmapFCN(saved["width"], grasp_head=saved.get("grasp_head", False))
    model.load_state_dict(saved["model"])
    model.eval()
    maps = height_maps(data["depth"], data["hand_z"])
    dist, logits = [], []
    with torch.inference_mode():
        for lo in range(0, len(maps), batch):
            d, z = model.outputs(torch.from_numpy(maps[lo:lo + batch].astype(np.float32)))
            dist.append(d.numpy())
            logits.append(None if z is None else z.numpy())
    return np.concatenate(dist), (None if logits[0] is None else np.concatenate(logits))


GRASP_THRESHOLDS = (0.5, 0.7, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995)


def grasp_map_variants(dist: np.ndarray, logits: np.ndarray, hand_z: np.ndarray,
                       threshold: float) -> dict:
    """Distances from the grasp head at `threshold`: the grasp map's distance transform
    (the distance head in images without a grasp node), and the smaller of the two."""
    edt = grasp_map_distances(logits, hand_z, threshold)
    return {"grasp map": np.where(np.isnan(edt), dist, edt),
            "min(grasp map, distance head)": np.fmin(edt, dist)}


def grasp_node_oracle(data: dict) -> dict:
    """The grasp map's floor: the distance transform of the labels' own grasp nodes
    (label <= GRASP_NODE_M, in view), measured on the images that have one."""
    grid = data["grid"].astype(np.float32)
    logits = np.where(grid <= GRASP_NODE_M, 10.0, -10.0).astype(np.float32)  # NaN: -10
    edt = grasp_map_distances(logits, data["hand_z"], 0.5)
    has = ~np.isnan(edt.reshape(len(edt), -1)).all(axis=1)
    kept = {k: v[has] for k, v in data.items()}
    return {"images_with_a_grasp_node": int(has.sum()), "images": len(has),
            **metrics(edt[has], kept)}


def compare_grasp_head(fcn: str, test: dict, val: dict) -> dict:
    """The grasp head's variants, each at the probability threshold with the lowest
    dense L1 on `val` (never on the test set), measured on `test`."""
    val_dist, val_logits = predict_fcn(fcn, val)
    by_threshold = {}
    for t in GRASP_THRESHOLDS:
        for name, pred in grasp_map_variants(val_dist, val_logits, val["hand_z"], t).items():
            by_threshold.setdefault(name, {})[t] = metrics(pred, val, images=500)["dense_l1_mm"]
    del val_dist, val_logits
    dist, logits = predict_fcn(fcn, test)
    result = {"distance head": metrics(dist, test)}
    for name, l1s in by_threshold.items():
        best = min(l1s, key=l1s.get)
        pred = grasp_map_variants(dist, logits, test["hand_z"], best)[name]
        result[name] = {"threshold": best, "val_dense_l1_mm_by_threshold": l1s,
                        **metrics(pred, test)}
        del pred
    return result


def predict_grid_net(weights: str, data: dict, *, batch: int = 200) -> np.ndarray:
    from drake_grasp.network import load_weights

    net = load_weights(weights)[0].eval()
    out = []
    with torch.inference_mode():
        for lo in range(0, len(data["depth"]), batch):
            x = net.preprocess(data["depth"][lo:lo + batch].astype(np.float32))
            out.append(net.image_features(x).numpy())  # a grid net's whole grid
    return np.concatenate(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--labels", required=True, help="comma-separated dense-labels folders")
    t.add_argument("--out", required=True)
    t.add_argument("--max-images", type=int, default=0,
                   help="train on a seeded random subset of this many images (0: all)")
    t.add_argument("--minutes", type=float, default=40.0)
    t.add_argument("--epochs", type=int, default=4)
    t.add_argument("--batch", type=int, default=32)
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--width", type=int, default=32)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--grasp-weight", type=float, default=0.0,
                   help="> 0: add the grasp head, its cross-entropy weighted so")
    c = sub.add_parser("compare")
    c.add_argument("--test", required=True)
    c.add_argument("--fcn", default="")
    c.add_argument("--val", default="", help="dense-labels folder(s) on which a grasp "
                   "head's threshold is chosen (required for an FCN with a grasp head)")
    c.add_argument("--weights", default="", help="comma-separated grid-head weights files")
    c.add_argument("--oracle", action="store_true",
                   help="also the distance transform of the labels' own grasp nodes")
    c.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    if a.cmd == "train":
        train(a.labels.split(","), Path(a.out), minutes=a.minutes, epochs=a.epochs,
              batch=a.batch, lr=a.lr, width=a.width, seed=a.seed, threads=a.threads,
              max_images=a.max_images, grasp_weight=a.grasp_weight)
        return 0
    data = load_labels([a.test])
    result = {"test": a.test, "images": len(data["grid"])}
    if a.fcn and torch.load(a.fcn, weights_only=False).get("grasp_head"):
        if not a.val:
            raise SystemExit(f"{a.fcn} has a grasp head: --val FOLDER[,FOLDER] is needed "
                             "to choose its threshold")
        result[a.fcn] = compare_grasp_head(a.fcn, data, load_labels(a.val.split(",")))
        result["val"] = a.val
        print(a.fcn, json.dumps(result[a.fcn]), flush=True)
    elif a.fcn:
        result[a.fcn] = metrics(predict_fcn(a.fcn, data)[0], data)
        print(a.fcn, json.dumps(result[a.fcn]), flush=True)
    if a.oracle:
        result["grasp-node oracle"] = grasp_node_oracle(data)
        print("grasp-node oracle", json.dumps(result["grasp-node oracle"]), flush=True)
    for w in filter(None, a.weights.split(",")):
        result[w] = metrics(predict_grid_net(w, data), data)
        print(w, json.dumps(result[w]), flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
