"""The paper's label metric between planar grasps ("CNN Model"; pure numpy).

Owns `grasp_distance`, Euclidean in (x, y, 0.001 m/deg * theta) with theta taken modulo
180 degrees (`angle_difference_deg`, `ANGLE_WEIGHT_M_PER_DEG`), the label built on it
(`distance_to_nearest_grasp`), and `planar_grasp_xy_yaw`, the planar (x, y, yaw) of a
grasp-frame pose that such distances compare.
"""

from __future__ import annotations

import numpy as np

# Paper: "weighting the angular component (by 0.001 meter/degree)".
ANGLE_WEIGHT_M_PER_DEG = 0.001


def angle_difference_deg(theta1, theta2) -> np.ndarray:
    """|theta1 - theta2| in degrees modulo 180 (a parallel jaw turned by 180 degrees is
    the same grasp), in [0, 90]."""
    d = np.mod(np.abs(np.asarray(theta1, dtype=float) - np.asarray(theta2, dtype=float)), 180.0)
    return np.minimum(d, 180.0 - d)


def planar_grasp_xy_yaw(X_WG) -> np.ndarray:
    """(..., 3) [x, y, yaw_deg] of grasp-frame poses (..., 4, 4): the grasp centre's (x, y)
    and the yaw of the closing direction x_G projected onto the table (so a tilted grasp,
    e.g. gpd's, is compared with the planar ground truth by where it grasps and how it
    closes)."""
    X = np.asarray(X_WG, dtype=float)
    yaw = np.rad2deg(np.arctan2(X[..., 1, 0], X[..., 0, 0]))
    return np.stack([X[..., 0, 3], X[..., 1, 3], yaw], axis=-1)


def grasp_distance(a, b, *, angle_weight_m_per_deg: float = ANGLE_WEIGHT_M_PER_DEG) -> np.ndarray:
    """Distance between planar grasps (x, y, theta_deg), broadcast over leading axes.

    Euclidean in (x, y, w * theta) with w = 0.001 m/deg and the angle difference
    taken modulo 180 degrees: sqrt(dx^2 + dy^2 + (w dtheta)^2) [m] (paper, "CNN
    Model": "Distance is measured in meters in the (x, y, theta) pose space by
    weighting the angular component (by 0.001 meter/degree)").
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape[-1:] != (3,) or b.shape[-1:] != (3,):
        raise ValueError(f"a, b: expected arrays of shape (..., 3) = (x, y, theta_deg), got "
                         f"{a.shape} and {b.shape}")
    dth = angle_difference_deg(a[..., 2], b[..., 2]) * float(angle_weight_m_per_deg)
    return np.sqrt((a[..., 0] - b[..., 0]) ** 2 + (a[..., 1] - b[..., 1]) ** 2 + dth**2)


def distance_to_nearest_grasp(
    poses_xy_theta,
    grasps_xy_theta,
    *,
    angle_weight_m_per_deg: float = ANGLE_WEIGHT_M_PER_DEG,
    chunk_elements: int = 4_000_000,
) -> np.ndarray:
    """The paper's label: distance from each pose to the nearest grasp [m].

    Args:
        poses_xy_theta: (M, 3) planar poses (x [m], y [m], theta [deg]).
        grasps_xy_theta: (N, 3) ground-truth grasps, e.g. `GraspSet.xy_theta`.
        angle_weight_m_per_deg: Weight of the angle (paper: 0.001 m/deg).
        chunk_elements: Largest M x N block computed at once (memory bound).

    Returns:
        (M,) distances `grasp_distance` to the nearest grasp; +inf for every pose
        when there are no grasps.
    """
    Q = np.asarray(poses_xy_theta, dtype=float)
    G = np.asarray(grasps_xy_theta, dtype=float)
    if Q.ndim != 2 or Q.shape[1] != 3:
        raise ValueError(f"poses_xy_theta: expected an (M, 3) array, got shape {Q.shape}")
    if G.ndim != 2 or G.shape[1] != 3:
        raise ValueError(f"grasps_xy_theta: expected an (N, 3) array, got shape {G.shape}")
    out = np.full(len(Q), np.inf)
    if len(G) == 0 or len(Q) == 0:
        return out
    step = max(1, int(chunk_elements) // len(G))
    for i in range(0, len(Q), step):
        out[i:i + step] = grasp_distance(Q[i:i + step, None, :], G[None, :, :],
                                         angle_weight_m_per_deg=angle_weight_m_per_deg).min(axis=1)
    return out
