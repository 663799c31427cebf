"""Pictures of an episode: the controller's view at each control step, as in the paper's
Figure 1 (depth image, candidates coloured by predicted distance, the chosen action, and
the current gripper pose as a red line)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from drake_grasp.geometry.camera import PinholeCamera


def contact_sheet(count: int, max_panels: int, *, cols: int, panel_in: tuple):
    """(figure, axes, picked indices) for a grid showing up to `max_panels` of `count`
    items spread evenly over the sequence; every axis starts switched off."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    idx = np.unique(np.linspace(0, count - 1, min(max_panels, count)).astype(int))
    cols = min(cols, len(idx))
    rows = int(np.ceil(len(idx) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(panel_in[0] * cols, panel_in[1] * rows + 0.5),
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    return fig, axes, idx


def save_depth_contact_sheet(frames, path: Path, *, max_frames: int = 24, title: str = "") -> None:
    """A grid of wrist depth images over the episode (time and mode under each)."""
    import matplotlib.pyplot as plt

    if not frames:
        raise ValueError("no depth frames to draw")
    fig, axes, idx = contact_sheet(len(frames), max_frames, cols=6, panel_in=(2.0, 2.2))
    all_depth = np.concatenate([frames[i][2].ravel() for i in idx])
    vmin, vmax = np.percentile(all_depth, 1), np.percentile(all_depth, 99)
    for ax, i in zip(axes.ravel(), idx):
        t, mode, depth = frames[i]
        ax.imshow(depth, cmap="viridis_r", vmin=vmin, vmax=vmax)
        ax.set_title(f"t={t:.1f}s {mode}", fontsize=8)
    fig.suptitle(title or "wrist depth images (near = yellow)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _pixels(points_G: np.ndarray, *, depth_m: float, X_GC_xyz, cam: PinholeCamera):
    """Pixel (u, v) of points given in the hand frame G at a given depth below the camera
    (camera and G share their orientation; the camera sits at X_GC_xyz in G)."""
    P = np.asarray(points_G, float)
    return cam.project(P[:, 0] - X_GC_xyz[0], P[:, 1] - X_GC_xyz[1], depth_m)


def save_controller_steps(steps, path: str | Path, *, fov_y_deg: float, X_GC_xyz,
                          max_steps: int = 12, title: str = "") -> Path:
    """A contact sheet of control steps (see the module docstring)."""
    import matplotlib.pyplot as plt

    if not steps:
        raise ValueError("no controller steps to draw (the policy took no closed-loop step)")
    fig, axes, idx = contact_sheet(len(steps), max_steps, cols=4, panel_in=(3.0, 3.1))
    sc = None
    for ax, i in zip(axes.ravel(), idx):
        s = steps[i]
        depth = s.depth
        cam = PinholeCamera.of_image(depth, fov_y_deg)
        ax.imshow(depth, cmap="gray_r", vmin=np.percentile(depth, 1), vmax=np.percentile(depth, 99))
        # Candidate hand centres at the depth of the nearest surface in view.
        d = float(np.percentile(depth, 5))
        u, v = _pixels(np.column_stack([s.actions[:, :2], np.zeros(len(s.actions))]),
                       depth_m=d, X_GC_xyz=X_GC_xyz, cam=cam)
        finite = np.isfinite(s.distances)
        sc = ax.scatter(u[finite], v[finite], c=s.distances[finite], cmap="viridis_r", s=6,
                        vmin=0.0, vmax=max(0.02, float(np.percentile(s.distances[finite], 95))))
        # Current gripper: a red line across the closing direction (x_G), 85 mm wide.
        u0, v0 = _pixels(np.array([[-0.0425, 0, 0], [0.0425, 0, 0]]), depth_m=d,
                         X_GC_xyz=X_GC_xyz, cam=cam)
        ax.plot(u0, v0, "-", color="red", lw=2)
        # Chosen action: where the best candidate would put the closing line (green).
        a = s.chosen
        # Rotating by theta about z_G turns x_G toward y_G (camera and G share axes).
        c, sn = np.cos(np.deg2rad(a[2])), np.sin(np.deg2rad(a[2]))
        ends = np.array([[a[0] - 0.0425 * c, a[1] - 0.0425 * sn, 0],
                         [a[0] + 0.0425 * c, a[1] + 0.0425 * sn, 0]])
        u1, v1 = _pixels(ends, depth_m=d, X_GC_xyz=X_GC_xyz, cam=cam)
        ax.plot(u1, v1, "-", color="lime", lw=2)
        ax.set_xlim(-0.5, cam.width - 0.5)
        ax.set_ylim(cam.height - 0.5, -0.5)
        ax.set_title(f"step {s.iteration}  t={s.time_s:.1f}s  best {1000 * np.nanmin(s.distances):.0f} mm",
                     fontsize=8)
    if sc is not None:
        fig.colorbar(sc, ax=axes.ravel().tolist(), shrink=0.6, label="predicted distance [m]")
    fig.suptitle(title or "controller steps: red = gripper now, green = best candidate", fontsize=9)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=80)
    plt.close(fig)
    tmp.replace(path)
    return path
