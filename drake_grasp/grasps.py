"""Grasp geometry for the 2F-85 parallel-jaw gripper (pure numpy).

Conventions: the grasp frame G sits at the centre between the two pads; its z axis
is the approach direction and its x axis the closing direction. A top-down grasp has
z_G = -z_W and is described by (x, y, z, yaw) with R_WG = Rz(yaw) Rx(pi).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STROKE_M = 0.085
# Pad geometry (models/robotiq_2f85/README.md): half length along the approach axis
# and half width across it.
PAD_HALF_LENGTH_M = 0.019
PAD_HALF_WIDTH_M = 0.011


def topdown_rotation(yaw: float) -> np.ndarray:
    """R_WG of a grasp that approaches straight down with closing direction at `yaw`."""
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    Rx_pi = np.diag([1.0, -1.0, -1.0])
    return Rz @ Rx_pi


@dataclass(frozen=True)
class TopDownGrasp:
    """A planned top-down grasp: grasp-centre position, closing yaw, object width."""

    position: np.ndarray
    yaw: float
    width: float

    def rotation(self) -> np.ndarray:
        return topdown_rotation(self.yaw)


def plan_topdown_grasp(
    points_W: np.ndarray,
    *,
    table_z: float = 0.0,
    depth_below_top: float = 0.025,
    min_height: float = 0.02,
    max_width: float = STROKE_M - 0.01,
    angle_step_deg: float = 2.0,
) -> TopDownGrasp:
    """Plans a top-down grasp of one object from points on its surface (true pose).

    The grasp centre is `depth_below_top` under the object's top (at least
    `min_height` above the table). Everything from the pads' lower edge upward ends up
    between the fingers, so the closing direction is the one in which those points are
    narrowest (a rotating-calipers search over yaw), and the centre is the middle of
    their extent in both planar directions.

    Raises:
        ValueError: no direction is narrower than `max_width` (the object cannot be
            grasped from above by the 85 mm stroke).
    """
    P = np.asarray(points_W, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise ValueError(f"points_W: expected an (N, 3) array, got shape {P.shape}")
    z_top = P[:, 2].max()
    z_grasp = max(table_z + min_height, z_top - depth_below_top)
    inside = P[P[:, 2] >= z_grasp - PAD_HALF_LENGTH_M]
    yaws = np.deg2rad(np.arange(0.0, 180.0, angle_step_deg))
    dirs = np.stack([np.cos(yaws), np.sin(yaws)], axis=1)  # (A, 2)
    proj = inside[:, :2] @ dirs.T  # (N, A)
    widths = proj.max(axis=0) - proj.min(axis=0)
    best = int(np.argmin(widths))
    if widths[best] > max_width:
        raise ValueError(
            f"object is {widths[best] * 1000:.0f} mm wide at its narrowest; the gripper "
            f"opens {max_width * 1000:.0f} mm"
        )
    d = dirs[best]
    e = np.array([-d[1], d[0]])
    along = proj[:, best]
    across = inside[:, :2] @ e
    c_d = 0.5 * (along.max() + along.min())
    c_e = 0.5 * (across.max() + across.min())
    xy = c_d * d + c_e * e
    return TopDownGrasp(np.array([xy[0], xy[1], z_grasp]), float(yaws[best]), float(widths[best]))


def points_between_pads(points_G: np.ndarray, width: float, margin: float = 0.005) -> int:
    """How many points (in the grasp frame) lie in the box swept by the closing pads."""
    P = np.asarray(points_G, dtype=float)
    inside = (
        (np.abs(P[:, 0]) <= 0.5 * width + margin)
        & (np.abs(P[:, 1]) <= PAD_HALF_WIDTH_M + margin)
        & (np.abs(P[:, 2]) <= PAD_HALF_LENGTH_M + margin)
    )
    return int(inside.sum())
