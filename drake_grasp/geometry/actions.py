"""Planar hand actions a = (x, y, theta) and where they take a top-down hand (pure numpy).

The paper's action is "a candidate planar pose offset relative to the depth sensor".
Here it is expressed in the hand's grasp frame G (the wrist camera shares G's
orientation): x along the closing direction x_G, y along y_G, theta a rotation about the
approach axis z_G, in degrees. A top-down hand has z_G = -z_W, so a positive theta turns
the closing direction clockwise seen from above (world yaw decreases by theta).

A hand pose in the plane is (x, y, yaw_deg): the grasp centre's world position and the
world yaw of the closing direction.
"""

from __future__ import annotations

import numpy as np

from drake_grasp.geometry.camera import view_half_extent_m
from drake_grasp.geometry.grasp_metric import ANGLE_WEIGHT_M_PER_DEG


def hand_axes(yaw_deg) -> tuple[np.ndarray, np.ndarray]:
    """World xy of the hand's x_G and y_G axes for top-down hands, each (..., 2)."""
    yaw = np.deg2rad(np.asarray(yaw_deg, dtype=float))
    c, s = np.cos(yaw), np.sin(yaw)
    # R_WG = Rz(yaw) Rx(pi): x_G = (c, s, 0), y_G = (s, -c, 0).
    return np.stack([c, s], axis=-1), np.stack([s, -c], axis=-1)


def apply_actions(hand_xy_yaw, actions) -> np.ndarray:
    """Hand poses after displacing each hand by each action (in its own frame).

    Args:
        hand_xy_yaw: (3,) or (N, 3) hand poses [x, y, yaw_deg].
        actions: (M, 3) or (N, M, 3) actions [dx, dy, dtheta_deg] in the hand frame.

    Returns:
        (M, 3) or (N, M, 3) world hand poses [x, y, yaw_deg].
    """
    hand = np.asarray(hand_xy_yaw, dtype=float)
    a = np.asarray(actions, dtype=float)
    if hand.shape[-1] != 3 or a.shape[-1] != 3:
        raise ValueError(f"expected [..., 3] arrays, got hand {hand.shape} and actions {a.shape}")
    single = hand.ndim == 1
    if single:
        hand = hand[None]
        a = a[None] if a.ndim == 2 else a
    ex, ey = hand_axes(hand[:, 2])  # (N, 2)
    xy = hand[:, None, :2] + a[..., 0:1] * ex[:, None] + a[..., 1:2] * ey[:, None]
    yaw = hand[:, None, 2] - a[..., 2]
    out = np.concatenate([xy, yaw[..., None]], axis=-1)
    return out[0] if single else out


def displacement_norm(delta) -> np.ndarray:
    """|delta| of actions [dx, dy, dtheta_deg] in the paper's (x, y, theta) metric [m]
    (0.001 m per degree)."""
    d = np.asarray(delta, dtype=float)
    return np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + (ANGLE_WEIGHT_M_PER_DEG * d[..., 2]) ** 2)


def action_between(hand_xy_yaw, target_xy_yaw) -> np.ndarray:
    """The action that takes `hand` to `target` (inverse of `apply_actions`), theta
    wrapped to [-90, 90) since the parallel-jaw hand is symmetric under 180 degrees."""
    hand = np.asarray(hand_xy_yaw, dtype=float)
    target = np.asarray(target_xy_yaw, dtype=float)
    ex, ey = hand_axes(hand[..., 2])
    d = target[..., :2] - hand[..., :2]
    dtheta = hand[..., 2] - target[..., 2]
    dtheta = (dtheta + 90.0) % 180.0 - 90.0
    return np.stack([np.sum(d * ex, -1), np.sum(d * ey, -1), dtheta], axis=-1)


def sample_actions_in_view(rng: np.random.Generator, count: int, *, camera_height_m: float,
                           fov_deg: float, camera_offset_xy_G, margin_m: float = 0.0) -> np.ndarray:
    """Actions drawn uniformly so the displaced hand centre lies in the camera's view.

    The camera is off the grasp axis by `camera_offset_xy_G` (in G), so the footprint is
    centred there; theta is uniform in [-90, 90) degrees.
    """
    half = float(view_half_extent_m(camera_height_m, fov_deg)) - margin_m
    if half <= 0:
        raise ValueError(f"camera_height_m {camera_height_m}: the view is empty after the margin")
    cx, cy = (float(v) for v in camera_offset_xy_G)
    a = np.empty((count, 3))
    a[:, 0] = rng.uniform(cx - half, cx + half, count)
    a[:, 1] = rng.uniform(cy - half, cy + half, count)
    a[:, 2] = rng.uniform(-90.0, 90.0, count)
    return a
