"""The scripted single-object top-down grasp (pure numpy).

Owns `plan_topdown_grasp`, which plans a grasp from an object's surface points in its
true pose (a rotating-calipers search for the narrowest closing direction, or the
slice under the fingers nearest the centre of mass for an object wider than the
stroke), the `TopDownGrasp` it returns, and `points_between_pads`, the count of points
in the box the closing pads sweep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drake_grasp.geometry.hand_model import (PAD_HALF_LENGTH_M, PAD_HALF_WIDTH_M, STROKE_M,
                                             topdown_rotation)


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
    com_W: np.ndarray | None = None,
    slice_step_m: float = 0.004,
    finger_margin_m: float = 0.005,
    max_com_offset_m: float = 0.04,
) -> TopDownGrasp:
    """Plans a top-down grasp of one object from points on its surface (true pose).

    The grasp centre is `depth_below_top` under the object's top (at least
    `min_height` above the table). Everything from the pads' lower edge upward ends up
    between the fingers, so the closing direction is the one in which those points are
    narrowest (a rotating-calipers search over yaw), and the centre is the middle of
    their extent in both planar directions.

    When the whole object is wider than `max_width` in every direction (a hammer lying
    flat: its 87 mm head), only the slice the fingers sweep has to fit: the points within
    a finger's half width plus `finger_margin_m` of the closing line. Every slice
    (`slice_step_m` apart, every yaw) that fits and whose centre lies within
    `max_com_offset_m` of `com_W` (horizontally; the points' centroid when None) is a
    candidate - farther out, the object's weight would twist it out of the pads, and
    the slice would be a corner of a wide object. The plan is the candidate nearest the
    centre of mass, the narrowest of those within 5 mm of that distance.

    Raises:
        ValueError: no slice near the centre of mass is narrower than `max_width` (the
            object cannot be grasped from above by the 85 mm stroke).
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
    if widths[best] <= max_width:
        d = dirs[best]
        e = np.array([-d[1], d[0]])
        along = proj[:, best]
        across = inside[:, :2] @ e
        c_d = 0.5 * (along.max() + along.min())
        c_e = 0.5 * (across.max() + across.min())
        xy = c_d * d + c_e * e
        return TopDownGrasp(np.array([xy[0], xy[1], z_grasp]), float(yaws[best]),
                            float(widths[best]))
    target = (np.asarray(com_W, dtype=float)[:2] if com_W is not None
              else inside[:, :2].mean(axis=0))
    half = PAD_HALF_WIDTH_M + finger_margin_m
    found = []  # (distance to target, width, yaw, centre xy)
    for k, yaw in enumerate(yaws):
        d = dirs[k]
        e = np.array([-d[1], d[0]])
        along, across = proj[:, k], inside[:, :2] @ e
        for s in np.arange(across.min(), across.max() + 1e-9, slice_step_m):
            strip = np.abs(across - s) <= half
            if not strip.any():
                continue
            lo, hi = along[strip].min(), along[strip].max()
            if hi - lo > max_width:
                continue
            xy = 0.5 * (lo + hi) * d + s * e
            if np.linalg.norm(xy - target) > max_com_offset_m:
                continue
            found.append((float(np.linalg.norm(xy - target)), float(hi - lo), float(yaw), xy))
    if not found:
        raise ValueError(
            f"object is {widths[best] * 1000:.0f} mm wide at its narrowest, and so is every "
            f"slice under the fingers within {max_com_offset_m * 1000:.0f} mm of its centre "
            f"of mass; the gripper opens {max_width * 1000:.0f} mm"
        )
    nearest = min(f[0] for f in found)
    _, width, yaw, xy = min((f for f in found if f[0] <= nearest + 0.005), key=lambda f: f[1])
    return TopDownGrasp(np.array([xy[0], xy[1], z_grasp]), yaw, width)


def points_between_pads(points_G: np.ndarray, width: float, margin: float = 0.005) -> int:
    """How many points (in the grasp frame) lie in the box swept by the closing pads."""
    P = np.asarray(points_G, dtype=float)
    inside = (
        (np.abs(P[:, 0]) <= 0.5 * width + margin)
        & (np.abs(P[:, 1]) <= PAD_HALF_WIDTH_M + margin)
        & (np.abs(P[:, 2]) <= PAD_HALF_LENGTH_M + margin)
    )
    return int(inside.sum())
