"""Pictures of a generated dataset, like the paper's Figure 3: depth images with the true
grasps (green) and the sampled offsets coloured by their label, plus a label histogram."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drake_grasp.geometry.camera import PinholeCamera
from drake_grasp.learning.dataset_shards import DepthGraspDataset


def camera_projector(hand_pose, *, width: int, height: int, fov_y_deg: float, X_GC):
    """A function mapping world points (N, 3) to pixel (u, v) for the camera on a hand."""
    from drake_grasp.world.station import topdown_pose

    x, y, z, yaw = (float(v) for v in hand_pose)
    X_CW = (topdown_pose([x, y], z, np.deg2rad(yaw)) @ X_GC).inverse()
    cam = PinholeCamera.from_fov(width, height, fov_y_deg)

    def project(P_W: np.ndarray) -> np.ndarray:
        P_C = (X_CW.rotation().matrix() @ np.asarray(P_W, float).T).T + X_CW.translation()
        return np.stack(cam.project(P_C[:, 0], P_C[:, 1], P_C[:, 2]), axis=1)

    return project


def inspect_dataset(data_dir: str | Path, *, out: str | Path, num_images: int = 12,
                    seed: int = 0) -> Path:
    """Draws a grid of depth images with grasps and labelled offsets, and a histogram."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drake_grasp.geometry.actions import apply_actions, hand_axes
    from drake_grasp.config.scenario import Scenario
    from drake_grasp.world.station import gripper_frame_offsets
    from pydrake.common.yaml import yaml_load_typed

    ds = DepthGraspDataset(data_dir)
    if len(ds) == 0:
        raise ValueError(f"{data_dir}: the dataset has no images")
    scenario = yaml_load_typed(schema=Scenario, data=ds.manifest["config"]["scenario"])
    cam = scenario.camera
    X_GC = gripper_frame_offsets()[2]
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.choice(len(ds), size=min(num_images, len(ds)), replace=False))
    cols = min(4, len(picks))
    rows = int(np.ceil(len(picks) / cols)) + 1
    fig = plt.figure(figsize=(3.0 * cols, 3.0 * rows))
    all_labels = []
    for n, index in enumerate(picks):
        rec = ds.image_record(int(index))
        ax = fig.add_subplot(rows, cols, n + 1)
        ax.imshow(rec["depth"], cmap="gray_r")
        project = camera_projector(rec["hand_pose"], width=cam.width, height=cam.height,
                                   fov_y_deg=cam.fov_y_deg, X_GC=X_GC)
        # True grasps: a green line across the closing direction, as wide as the grasp.
        for T, w in zip(rec["grasp_pose"], rec["grasp_width"]):
            c, xa = T[:3, 3], T[:3, 0]
            uv = project(np.stack([c - 0.5 * w * xa, c + 0.5 * w * xa]))
            ax.plot(uv[:, 0], uv[:, 1], "-", color="lime", lw=0.8, alpha=0.6)
        # Offsets: where each action takes the hand, drawn at the grasps' mean height.
        z = float(np.mean(rec["grasp_pose"][:, 2, 3])) if len(rec["grasp_pose"]) else 0.02
        hand = rec["hand_pose"][[0, 1, 3]]
        moved = apply_actions(hand, rec["offsets"])
        ex, _ = hand_axes(moved[:, 2])
        centers = np.column_stack([moved[:, :2], np.full(len(moved), z)])
        uv = project(centers)
        tips = project(centers + 0.02 * np.column_stack([ex, np.zeros(len(ex))]))
        sc = ax.scatter(uv[:, 0], uv[:, 1], c=rec["labels"], cmap="plasma", vmin=0, vmax=0.1, s=18)
        for a, b in zip(uv, tips):
            ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="white", lw=0.6)
        ax.set_xlim(-0.5, cam.width - 0.5)
        ax.set_ylim(cam.height - 0.5, -0.5)
        ax.set_title(f"image {index} (scene {rec['scene_index']})", fontsize=8)
        ax.axis("off")
        all_labels.append(rec["labels"])
    fig.colorbar(sc, ax=fig.axes, shrink=0.5, label="distance to nearest grasp [m]")
    ax = fig.add_subplot(rows, 1, rows)
    labels = np.concatenate([ds[i]["labels"] for i in rng.choice(len(ds), min(len(ds), 2000), replace=False)])
    ax.hist(labels[np.isfinite(labels)], bins=60, color="tab:blue")
    ax.set_xlabel("label: distance to the nearest true grasp [m]")
    ax.set_ylabel("offsets")
    m = ds.manifest
    ax.set_title(f"{m['num_scenes']} scenes, {m['num_images']} images, {m['num_labels']} labels",
                 fontsize=9)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(out)
    return out
