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

`train` checkpoints every 5 minutes of training (`--checkpoint-minutes`), at every epoch's
end and after its time budget (`--minutes`); the same command resumes a stopped or killed
run at the batch it had reached (the batches of epoch e are a permutation seeded by e).

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
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drake_grasp.learning.dense_labels import (  # noqa: E402
    GRID_CONFIG, grid_node_actions, load_labels, view_masks)

from drake_grasp.cnn import fcn  # noqa: E402

_LATTICE = fcn.FcnConfig()  # the lattice every net here uses: 5 mm cells, +-18 cm
CELL_M = _LATTICE.cell_m
LATTICE = _LATTICE.lattice  # 73 cells, centres -18..18 cm
HEIGHT_SCALE = _LATTICE.height_scale  # input height in decimetres

# A grid node is a "grasp node" when a true grasp lies within half the diagonal of its
# 1 cm x 1 cm x 10 degree cell (the metric weighs 10 degrees as 1 cm): every grasp over
# the grid has one, and the distance transform of the grasp nodes is the label to within
# that half-diagonal.
GRASP_NODE_M = 0.5 * math.sqrt(3.0) * GRID_CONFIG.grid_step_m
GRASP_POS_WEIGHT = 10.0  # grasp nodes are 0.7% of the in-view nodes


@functools.lru_cache(maxsize=None)
def camera_z_G() -> float:
    """The camera's height in the gripper frame (read once; `_masks` needs it per batch)."""
    from drake_grasp.world.station import gripper_frame_offsets
    return float(gripper_frame_offsets()[2].translation()[2])


def camera_heights(hand_z: np.ndarray) -> np.ndarray:
    """The camera's heights above the table [m] for the labels' hand heights."""
    return np.asarray(hand_z, np.float64) - camera_z_G()


def height_maps(depth: np.ndarray, hand_z: np.ndarray) -> np.ndarray:
    """`fcn.height_maps` of the labels' images (the defaults' lattice)."""
    return fcn.height_maps(depth, camera_heights(hand_z), GRID_CONFIG, fcn.FcnConfig())


def make_fcn(width: int, grasp_head: bool, **kw) -> fcn.HeightmapFCN:
    """A fresh `fcn.HeightmapFCN` (`kw`: other `fcn.FcnConfig` fields, e.g. dilations)."""
    return fcn.HeightmapFCN(fcn.FcnConfig(width=width, grasp_head=grasp_head, **kw), GRID_CONFIG)


def _masks(hand_z: np.ndarray) -> torch.Tensor:
    mx = torch.from_numpy(view_masks(hand_z, GRID_CONFIG, camera_z_G()))
    return mx[:, None, :, None] & mx[:, None, None, :]


def grasp_map_distances(logits: np.ndarray, hand_z: np.ndarray, threshold: float) -> np.ndarray:
    """`fcn.grasp_map_distances` at the labels' hand heights."""
    return fcn.grasp_map_distances(logits, camera_heights(hand_z), GRID_CONFIG, threshold)


def train(labels: list[str], out: Path, *, minutes: float, epochs: int, batch: int,
          lr: float, width: int, seed: int, threads: int, max_images: int = 0,
          grasp_weight: float = 0.0, checkpoint_minutes: float = 5.0) -> None:
    """Adam on the masked L1 over the in-view nodes, cosine decay over `epochs`;
    `max_images` > 0 trains on a random subset of that many images (seeded), for a
    learning curve over data. `grasp_weight` > 0 adds the grasp head, trained with that
    weight on the binary cross-entropy of "label <= GRASP_NODE_M" over the same nodes.
    Checkpoints every `checkpoint_minutes` of training, at every epoch's end and when the
    budget (`minutes`) runs out; a killed run resumes from its last checkpoint at the
    batch it had reached (the batches of epoch e are a permutation seeded by e; a resumed
    epoch's logged train L1 covers the batches after the resume)."""
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
    # Height maps are made per batch (the same maps as made all at once, image by image):
    # held for every image they would add 21 KB each to the labels' 47 KB (6 GB at
    # 300,000 images).
    depth, grids, hand_z = data["depth"], data["grid"], data["hand_z"]
    del data
    print(f"{len(depth)} images read in {time.perf_counter() - t0:.0f} s", flush=True)
    torch.manual_seed(seed)
    model = make_fcn(width, grasp_weight > 0)
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
    start = last_save = time.perf_counter()
    base_s = state["train_s"]
    n = len(depth)
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
            x = torch.from_numpy(height_maps(depth[idx], hand_z[idx]).astype(np.float32))
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
            if time.perf_counter() - last_save >= checkpoint_minutes * 60.0:
                save()
                last_save = time.perf_counter()
        state["log"].append({"epoch": state["epoch"] + 1, "batches_to": state["batch_index"],
                             "train_l1_m": total / max(count, 1), "train_s": state["train_s"]})
        if model.grasp_head:
            state["log"][-1]["train_bce"] = bce_total / max(count, 1)
        print(json.dumps(state["log"][-1]), flush=True)
        if not stopped:
            state["epoch"] += 1
            state["batch_index"] = 0
        save()
        last_save = time.perf_counter()
    torch.save({"model": model.state_dict(), "width": width, "grasp_head": model.grasp_head,
                "state": state, "identity": identity}, out / "model.pt")


def metrics(pred: np.ndarray, data: dict, *, seed: int = 0, images: int = 2000) -> dict:
    """Dense L1 over the in-view nodes, by label bin, and within-image Spearman over the
    nodes the controller's candidates cover (|x|, |y| <= 4 cm from the hand, |theta| <= 45
    degrees, in view)."""
    from drake_grasp.learning.cnn_metrics import spearman

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
    model = make_fcn(saved["width"], saved.get("grasp_head", False))
    model.load_state_dict(saved["model"])
    model.eval()
    dist, logits = [], []
    with torch.inference_mode():
        for lo in range(0, len(data["depth"]), batch):
            maps = height_maps(data["depth"][lo:lo + batch], data["hand_z"][lo:lo + batch])
            d, z = model.outputs(torch.from_numpy(maps.astype(np.float32)))
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
    from drake_grasp.cnn.weights_io import load_weights

    net = load_weights(weights)[0].eval()
    out = []
    with torch.inference_mode():
        for lo in range(0, len(data["depth"]), batch):
            x = net.preprocess(data["depth"][lo:lo + batch].astype(np.float32))
            out.append(net.image_features(x).numpy())  # a grid net's whole grid
    return np.concatenate(out)


def export(model_pt: str, out: str, *, grasp_threshold: float, note: str = "") -> None:
    """Writes a `train` result as `fcn.save_fcn` weights (the net's eval-mode tensors)."""
    import hashlib

    saved = torch.load(model_pt, weights_only=False)
    cfg = fcn.FcnConfig(width=saved["width"], grasp_head=bool(saved.get("grasp_head")),
                        grasp_threshold=grasp_threshold)
    net = fcn.HeightmapFCN(cfg, GRID_CONFIG)
    net.load_state_dict(saved["model"])
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fcn.save_fcn(net.eval(), out, metadata={
        "source": Path(model_pt).name,
        "source_sha256": hashlib.sha256(Path(model_pt).read_bytes()).hexdigest(),
        "training": saved.get("identity", {}), "note": note})
    print(f"{out}: {cfg}")


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
    t.add_argument("--checkpoint-minutes", type=float, default=5.0,
                   help="minutes of training between checkpoints (besides each epoch's end)")
    t.add_argument("--grasp-weight", type=float, default=0.0,
                   help="> 0: add the grasp head, its cross-entropy weighted so")
    e = sub.add_parser("export", help="a trained model.pt as a safetensors weights file "
                       "that `controller.weights` and `evaluate --weights` load")
    e.add_argument("--fcn", required=True, help="a model.pt from `train`")
    e.add_argument("--grasp-threshold", type=float, default=0.0,
                   help="> 0 (a net with a grasp head): score min(distance head, distance "
                   "to the nearest node of at least this grasp probability)")
    e.add_argument("--note", default="", help="a line stored in the file's metadata")
    e.add_argument("--out", required=True)
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
              max_images=a.max_images, grasp_weight=a.grasp_weight,
              checkpoint_minutes=a.checkpoint_minutes)
        return 0
    if a.cmd == "export":
        export(a.fcn, a.out, grasp_threshold=a.grasp_threshold, note=a.note)
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
