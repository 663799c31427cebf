"""The geometric detector's view and occlusion tests on probe points of the open hand.

`PROBES_G` are points inside the open hand, in the grasp frame: each finger (inner face,
middle, outer face) x (both edges, middle) x (tip, centre, pad top), the palm's front
face and the housing's front ring. `view_and_occlusion` projects them into the depth
image for every candidate: out of the view nothing is known, so a probe beyond the
border next to an object rejects the hand (the object may go on under it), and
optionally every probe in the view must be seen as free space, in front of the
measured depth (stricter than the column model of `gpd_geometric_hands`). Pure numpy.
"""

from __future__ import annotations

import numpy as np

from drake_grasp.geometry.hand_model import (FINGER_OUTER_X_M, FINGERTIP_Z_M, HOUSING_FRONT_Z_M,
                                             HOUSING_RADIUS_M, PAD_HALF_LENGTH_M, PAD_HALF_WIDTH_M,
                                             PALM_FRONT_Z_M, PALM_HALF_X_M, PALM_HALF_Y_M)
from drake_grasp.geometry.camera import PinholeCamera
from drake_grasp.policies.gpd_geometric_cloud import OrganizedCloud
from drake_grasp.policies.gpd_geometric_hands import HALF_STROKE_M

# Probe points on the open hand for the view and occlusion checks, in G [m]: each finger
# (inner face, middle, outer face) x (both edges, middle) x (tip, centre, pad top),
# the palm's front face and the housing's front ring. Inset 1 mm from the faces so
# that a probe is inside the part, not on its boundary.
_FX = np.array([HALF_STROKE_M + 0.001, 0.5 * (HALF_STROKE_M + FINGER_OUTER_X_M),
                FINGER_OUTER_X_M - 0.001])
_FY = np.array([-PAD_HALF_WIDTH_M + 0.001, 0.0, PAD_HALF_WIDTH_M - 0.001])
_FZ = np.array([FINGERTIP_Z_M - 0.001, 0.0, -PAD_HALF_LENGTH_M])


def _probe_points() -> np.ndarray:
    fx = np.concatenate([_FX, -_FX])
    fingers = np.stack(np.meshgrid(fx, _FY, _FZ, indexing="ij"), axis=-1).reshape(-1, 3)
    px = np.linspace(-PALM_HALF_X_M + 0.001, PALM_HALF_X_M - 0.001, 9)
    py = np.array([-PALM_HALF_Y_M + 0.001, 0.0, PALM_HALF_Y_M - 0.001])
    palm = np.stack(np.meshgrid(px, py, [PALM_FRONT_Z_M - 0.001], indexing="ij"),
                    axis=-1).reshape(-1, 3)
    phi = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
    r = HOUSING_RADIUS_M - 0.001
    ring = np.column_stack([r * np.cos(phi), r * np.sin(phi),
                            np.full(8, HOUSING_FRONT_Z_M - 0.001)])
    return np.concatenate([fingers, palm, ring])


PROBES_G = _probe_points()


def view_and_occlusion(yaw: np.ndarray, centre: np.ndarray, R_WC: np.ndarray, p_WC: np.ndarray,
                       cloud: OrganizedCloud, obj: np.ndarray, fov_y_deg: float, *,
                       occlusion_check: bool, occ_tol: float, st_: dict) -> np.ndarray:
    """Which hands (yaw [rad], centre [m]) pass the view test and, with
    `occlusion_check`, the occlusion test; counts them in ``st_["in_view"]`` and
    ``st_["visible"]``.

    Out of the view nothing is known. Where the image border next to a probe shows
    an object, the object may go on under that part of the hand (an object cut by
    the border looks narrower or lower than it is): rejected. Where it shows the
    table, the table is taken to go on. Optionally (`occlusion_check`) every probe in
    the view must be seen as free space: in front of the measured depth.
    """
    cy_, sy_ = np.cos(yaw), np.sin(yaw)
    # R_WG = Rz(yaw) Rx(pi): x_G = (c, s, 0), y_G = (s, -c, 0), z_G = (0, 0, -1).
    pw = np.empty((len(yaw), len(PROBES_G), 3))
    pw[..., 0] = centre[:, None, 0] + cy_[:, None] * PROBES_G[:, 0] + sy_[:, None] * PROBES_G[:, 1]
    pw[..., 1] = centre[:, None, 1] + sy_[:, None] * PROBES_G[:, 0] - cy_[:, None] * PROBES_G[:, 1]
    pw[..., 2] = centre[:, None, 2] - PROBES_G[:, 2]
    pc = (pw - p_WC) @ R_WC
    H, W = cloud.depth.shape
    front = pc[..., 2] > 1e-6  # behind the camera: nothing known
    zc_safe = np.where(front, pc[..., 2], 1.0)
    u, v = (np.rint(p) for p in PinholeCamera.from_fov(W, H, fov_y_deg).project(
        pc[..., 0], pc[..., 1], zc_safe))
    inside = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    ui = np.clip(np.where(front, u, 0), 0, W - 1).astype(np.int64)
    vi = np.clip(np.where(front, v, 0), 0, H - 1).astype(np.int64)
    view_ok = front & (inside | ~obj[vi, ui])
    keep = view_ok.all(axis=1)
    st_["in_view"] = int(keep.sum())
    if occlusion_check:
        # No reading (depth 0): unknown; far (+inf or the far value): seen free.
        measured = np.where(cloud.valid, cloud.depth, np.where(cloud.depth > 0, np.inf, 0.0))
        seen_free = ~inside | (pc[..., 2] <= measured[vi, ui] + occ_tol)
        keep &= (front & seen_free).all(axis=1)
    st_["visible"] = int(keep.sum())
    return keep
