"""Where the distance CNN's test error lies: labels whose nearest grasp the image shows,
and labels whose nearest grasp lies outside the camera's view.

    python analysis/label_observability.py --weights models/cnn-grid/weights.safetensors \
        --test-data data/paper_test --out analysis/results/cnn-observability/cnn-grid.json

A label is the distance from the displaced hand to the nearest ground-truth grasp of the
scene (`grasps.distance_to_nearest_grasp`). The offsets are drawn inside the camera's
footprint, but the grasp that attains the minimum need not be: where it lies outside the
view, the image cannot show it, and no net that sees only the image can know how far
away it is - only that it is not in the view. This splits the test L1 by whether that
grasp's centre lies in the footprint on the table (the view's widest extent), and by
whether the view holds any grasp of the scene at all.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from drake_grasp.geometry.actions import apply_actions, hand_axes
from drake_grasp.geometry.camera import view_half_extent_m
from drake_grasp.geometry.grasp_metric import grasp_distance
from drake_grasp.cnn.weights_io import load_weights
from drake_grasp.config.scenario import Scenario
from drake_grasp.world.station import gripper_frame_offsets

BINS_MM = (0, 30, 60, 100, 150, float("inf"))


def in_view(points_xy: np.ndarray, hand: np.ndarray, X_GC_xyz: np.ndarray,
            fov_deg: float) -> np.ndarray:
    """Whether world points (..., 2) lie in the table footprint of the camera on `hand`
    ([x, y, z, yaw_deg]); the footprint is square and aligned with the hand's axes."""
    ex, ey = hand_axes(hand[3])
    centre = hand[:2] + X_GC_xyz[0] * ex + X_GC_xyz[1] * ey
    half = view_half_extent_m(hand[2] - X_GC_xyz[2], fov_deg)
    d = points_xy - centre
    return (np.abs(d @ ex) <= half) & (np.abs(d @ ey) <= half)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", required=True, help="a weights.safetensors file")
    parser.add_argument("--test-data", required=True, help="a `generate` folder (test split)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", required=True, help="JSON file to write")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    model, _ = load_weights(args.weights)
    model.eval()
    fov = Scenario().camera.fov_y_deg
    X_GC = gripper_frame_offsets()[2].translation()
    shards = sorted(Path(args.test_data).glob("shard-*.h5"))
    if not shards:
        raise SystemExit(f"--test-data {args.test_data}: no shard-*.h5 files")
    t0 = time.perf_counter()
    rows = []  # (label, prediction - label, nearest grasp in view, any grasp in view)
    for path in shards:
        with h5py.File(path, "r") as f:
            depth = np.asarray(f["depth"], np.float32)
            hand = np.asarray(f["hand_pose"], float)
            offsets = np.asarray(f["offsets"], np.float32)
            labels = np.asarray(f["labels"], float)
            image_scene = np.asarray(f["image_scene"])
            grasp_scene = np.asarray(f["grasp_scene"])
            grasps = np.asarray(f["grasp_xy_theta"], float)
        with torch.no_grad():
            pred = model.forward_factored(model.preprocess(depth),
                                          torch.as_tensor(offsets, dtype=model.dtype))
        pred = pred.double().numpy()
        moved = apply_actions(hand[:, [0, 1, 3]], offsets.astype(float))  # (I, M, 3)
        for i in range(len(hand)):
            G = grasps[grasp_scene == image_scene[i]]
            d = grasp_distance(moved[i][:, None, :], G[None, :, :])  # (M, N)
            nearest = G[d.argmin(axis=1)]
            recomputed = d.min(axis=1)
            if not np.allclose(recomputed, labels[i], atol=1e-5):
                raise SystemExit(f"{path.name} image {i}: the stored labels do not match the "
                                 f"distance to the stored grasps (max diff "
                                 f"{np.abs(recomputed - labels[i]).max():.2e} m)")
            # The offsets were drawn inside the footprint (`sample_actions_in_view`): a
            # check that `in_view` places the footprint where the dataset did.
            if not in_view(moved[i][:, :2], hand[i], X_GC, fov).all():
                raise SystemExit(f"{path.name} image {i}: a labelled offset lies outside "
                                 "the computed footprint; the view geometry is wrong")
            vis = in_view(nearest[:, :2], hand[i], X_GC, fov)
            any_vis = bool(in_view(G[:, :2], hand[i], X_GC, fov).any())
            for m in range(len(labels[i])):
                rows.append((labels[i, m], pred[i, m] - labels[i, m], vis[m], any_vis))
    r = np.array(rows, dtype=float)
    label, signed, vis, any_vis = r[:, 0], r[:, 1], r[:, 2] > 0, r[:, 3] > 0
    err = np.abs(signed)

    def summary(mask: np.ndarray) -> dict:
        out = {"labels": int(mask.sum()), "share": float(mask.mean()),
               "l1_mm": float(1000 * err[mask].mean()) if mask.any() else None,
               "label_mean_mm": float(1000 * label[mask].mean()) if mask.any() else None,
               "bins": []}
        for lo, hi in zip(BINS_MM[:-1], BINS_MM[1:]):
            b = mask & (label >= lo / 1000) & (label < hi / 1000)
            out["bins"].append({"label_mm": [lo, hi if np.isfinite(hi) else None],
                                "labels": int(b.sum()),
                                "l1_mm": float(1000 * err[b].mean()) if b.any() else None,
                                "bias_mm": float(1000 * signed[b].mean()) if b.any() else None})
        return out

    result = {
        "weights": str(args.weights), "test_data": str(args.test_data),
        "fov_deg": fov, "X_GC_m": X_GC.tolist(),
        "all": summary(np.ones_like(vis)),
        "nearest_grasp_in_view": summary(vis),
        "nearest_grasp_out_of_view": summary(~vis),
        "view_holds_no_grasp": summary(~any_vis),
        "error_share_out_of_view": float(err[~vis].sum() / err.sum()),
        "seconds": time.perf_counter() - t0,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    for key in ("all", "nearest_grasp_in_view", "nearest_grasp_out_of_view",
                "view_holds_no_grasp"):
        s = result[key]
        print(f"{key:28s} {s['labels']:7d} labels ({100 * s['share']:5.1f}%)  L1 "
              f"{s['l1_mm'] or float('nan'):5.1f} mm  bins "
              + " / ".join(f"{b['l1_mm']:.1f}" if b["l1_mm"] is not None else "-"
                           for b in s["bins"]))
    print(f"share of the summed error out of view: {100 * result['error_share_out_of_view']:.1f}%")
    return result


if __name__ == "__main__":
    main()
