"""The policies' decisions as pure functions (numpy; the CNN through `network`).

CTR, the paper's Algorithm 1: on each control step take the latest depth image, score
candidate actions sampled near the current pose, pick the least predicted distance, move
a fraction r of the way there in (x, y, theta) and step down in z; stop when an object
is within 14 cm of the sensor, the hand reaches its lowest height, or the iterations
are spent, then (`controller.converge_iterations`) servo on at that height until the
commanded move is small. The baselines decide once, from the first image: `cnn-only` the CNN's global
best action over the whole view, `gpd` a geometric one-shot grasp detection.
"""

from __future__ import annotations

import numpy as np

from drake_grasp.geometry.camera import PinholeCamera
from drake_grasp.geometry.hand_model import (FINGER_OUTER_X_M, FINGERTIP_Z_M, HOUSING_FRONT_Z_M,
                                             HOUSING_RADIUS_M, PAD_HALF_WIDTH_M, PALM_FRONT_Z_M,
                                             PALM_HALF_X_M, PALM_HALF_Y_M, STROKE_M)

# The policies that decide at every control step (CTR, and CTR after a one-shot start).
CLOSED_LOOP_POLICIES = ("ctr", "cnn-ctr")
# The built-in policies that act on the station's sensors alone: all of
# `scenario.POLICIES` but `scripted`, which reads the true object poses. The bridge runs
# these across a process boundary; `evaluate --conditions` may add them to an experiment.
SENSOR_POLICIES = ("ctr", "cnn-ctr", "cnn-only", "gpd", "gpd-track", "gpd-geometric", "init")
# The policies that take GPD's one look from its sensor at the viewpoint (its classifier
# weights, its image, its detection's record).
GPD_POLICIES = ("gpd", "gpd-track")
# The failure reason of a policy that found no grasp to attempt (a one-shot detector);
# clutter-removal rounds end on it (`evaluation.experiments.Experiment.end_on_no_detection`).
NO_GRASP_FOUND = "missed: no grasp detected"
# What gpd-track's record keeps of its tracking (`gpd_track.GPDTrackController` outcome).
TRACK_RECORD_KEYS = ("tracked_motion", "tracked_rms_m", "registrations")


def sample_candidates(rng: np.random.Generator, count: int, *, xy_m: float,
                      theta_deg: float) -> np.ndarray:
    """Actions (count, 3) uniform in [-xy, xy]^2 x [-theta, theta] (degrees)."""
    a = np.empty((count, 3))
    a[:, :2] = rng.uniform(-xy_m, xy_m, (count, 2))
    a[:, 2] = rng.uniform(-theta_deg, theta_deg, count)
    return a


def memory_penalty(hand_xy_yaw, actions: np.ndarray, failed_xy_yaw: np.ndarray,
                   radius_m: float) -> np.ndarray:
    """(M,) how far inside `radius_m` of the nearest remembered failed grasp each action
    takes the hand [m] (0 outside; `scenario.FailureMemoryConfig`): added to the
    predicted distances, it fills the CNN's valley at a grasp that already failed."""
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.geometry.grasp_metric import grasp_distance

    actions = np.asarray(actions, float)
    failed = np.asarray(failed_xy_yaw, float).reshape(-1, 3)
    if radius_m <= 0.0 or len(failed) == 0 or len(actions) == 0:
        return np.zeros(len(actions))
    poses = apply_actions(hand_xy_yaw, actions)
    nearest = grasp_distance(poses[:, None, :], failed[None, :, :]).min(axis=1)
    return np.maximum(0.0, radius_m - nearest)


def choose_action(actions: np.ndarray, distances: np.ndarray) -> tuple[np.ndarray, float]:
    """The candidate with the least predicted distance (first one on ties)."""
    d = np.asarray(distances, dtype=float)
    if d.ndim != 1 or len(d) != len(actions) or len(d) == 0:
        raise ValueError(f"distances: expected one per action ({len(actions)}), got shape {d.shape}")
    i = int(np.argmin(d))
    return np.asarray(actions[i], dtype=float), float(d[i])


def grasp_axis_pixel(shape, focal_px: float, camera_xy_G, depth_m: float) -> tuple[float, float]:
    """Pixel (u, v) where the grasp axis (x_G = y_G = 0) is seen at `depth_m` from the
    sensor, for a camera looking along z_G with its axes parallel to G and its centre
    at `camera_xy_G` in G (the wrist camera sits beside the grasp axis)."""
    h, w = shape[:2]
    return PinholeCamera.centred(w, h, focal_px).project(
        -float(camera_xy_G[0]), -float(camera_xy_G[1]), depth_m)


def min_depth_under_axis(depth: np.ndarray, focal_px: float, camera_xy_G, at_depth_m: float,
                         half_window_m: float) -> float:
    """Nearest reading in the square window around the grasp axis as seen at `at_depth_m`
    (the 14 cm stop rule): half side `half_window_m` at that depth, at least one pixel."""
    h, w = depth.shape[:2]
    u, v = grasp_axis_pixel(depth.shape, focal_px, camera_xy_G, at_depth_m)
    half = max(0.5, PinholeCamera.centred(w, h, focal_px).metres_to_pixels(half_window_m,
                                                                       at_depth_m))
    c0, c1 = max(0, int(np.ceil(u - half))), min(w - 1, int(np.floor(u + half)))
    r0, r1 = max(0, int(np.ceil(v - half))), min(h - 1, int(np.floor(v + half)))
    if c0 > c1 or r0 > r1:
        return float("inf")
    window = depth[r0:r1 + 1, c0:c1 + 1]
    valid = window[np.isfinite(window) & (window > 0)]
    return float(valid.min()) if valid.size else float("inf")


def image_points_W(depth: np.ndarray, focal_px: float, X_WC: np.ndarray,
                 max_depth_m: float = np.inf) -> np.ndarray:
    """World points (4, N), homogeneous, of the depth image's valid pixels (finite,
    positive, nearer than `max_depth_m`), seen from the camera at `X_WC` (4x4, Drake's
    camera frame: x right, y down, z along the view)."""
    h, w = depth.shape[:2]
    d = np.asarray(depth, float).reshape(h, w)
    v, u = np.mgrid[0:h, 0:w]
    ok = np.isfinite(d) & (d > 0) & (d < max_depth_m)
    z = d[ok]
    x, y = PinholeCamera.centred(w, h, focal_px).back_project(u[ok], v[ok], z)
    P_C = np.stack([x, y, z, np.ones_like(z)])
    return np.asarray(X_WC, float) @ P_C


def heights_in_hand_box(P_W: np.ndarray, X_WG: np.ndarray, half_x_m: float, half_y_m: float,
                        *, return_x: bool = False):
    """World heights of the points `P_W` (4, N, from `image_points_W`) that lie in the box
    |x_G| <= half_x, |y_G| <= half_y of the grasp frame at `X_WG` (4x4). With `return_x`,
    also each point's x_G (along the closing direction): (heights, x_G)."""
    P_G = np.linalg.inv(np.asarray(X_WG, float)) @ P_W
    keep = (np.abs(P_G[0]) <= half_x_m) & (np.abs(P_G[1]) <= half_y_m)
    if return_x:
        return P_W[2, keep], P_G[0, keep]
    return P_W[2, keep]


def hand_overlap_m(P_W: np.ndarray, X_WG: np.ndarray, *, margin_m: float = 0.0) -> float:
    """How far the points `P_W` (4, N, from `image_points_W`) under the open top-down hand
    at `X_WG` (4x4) rise above the part of the hand over them [m]; -inf when none lies
    under it. The parts and their fronts are the ground truth's collision model
    (`grasps.py`): the fingers (tips `FINGERTIP_Z_M` below the grasp centre), the palm
    (`PALM_FRONT_Z_M`) and the housing (`HOUSING_FRONT_Z_M`), each swept straight down,
    their outlines widened by `margin_m`. The closing strip between the pads is left out:
    that is the object to grasp, which `grasp_height` places the pads on. A positive
    value: the descent would bring that part down on a surface the image shows."""
    m = float(margin_m)
    P_G = np.linalg.inv(np.asarray(X_WG, float)) @ P_W
    ax, ay = np.abs(P_G[0]), np.abs(P_G[1])
    centre = float(X_WG[2, 3])
    strip = (ax < 0.5 * STROKE_M) & (ay <= PAD_HALF_WIDTH_M)
    finger = (ax >= 0.5 * STROKE_M) & (ax <= FINGER_OUTER_X_M + m) & (ay <= PAD_HALF_WIDTH_M + m)
    palm = (ax <= PALM_HALF_X_M + m) & (ay <= PALM_HALF_Y_M + m)
    housing = ax * ax + ay * ay <= (HOUSING_RADIUS_M + m) ** 2
    # The lowest part over each point (z_G points down: a front at z_G is at height
    # centre - z_G).
    bottom = np.full(ax.shape, np.inf)
    bottom[housing] = centre - HOUSING_FRONT_Z_M
    bottom[palm] = centre - PALM_FRONT_Z_M
    bottom[finger] = centre - FINGERTIP_Z_M
    keep = ~strip & np.isfinite(bottom)
    return float(np.max(P_W[2, keep] - bottom[keep])) if keep.any() else -np.inf


def widest_section_height(heights: np.ndarray, x_G: np.ndarray, *,
                          edge_m: float = 0.003) -> float | None:
    """Height of the object's widest section between the pads, seen from above.

    Seen from above, the outermost points of a convex section along the closing
    direction lie where the object is widest (a lying can's sides at its axis, an
    apple's equator); a box's vertical walls are not seen, so its outermost points are
    its top edges. Near a curved silhouette the surface is steep, so the points within
    `edge_m` of the outermost x_G on each side span a range of heights; the lower
    quartile of each side is taken (about 3 mm above a 3 cm can's axis). Returns the
    mean of the two sides, or None when no points are given.

    Returns None too when that height lies deeper below the highest point than the
    points span along the closing direction: a convex section lying on the table is
    about half as deep to its widest part as it is wide (a lying can: its radius against
    its diameter), while an object standing taller than it is wide shows the camera a
    side wall, whose lower points are not a widest section but the wall. The descent
    would bring the palm (2.5 cm above the pad centres) down on that object's top, and a
    tall one topples (the standing flashlight of isolation seeds 5 and 6).
    """
    z = np.asarray(heights, float)
    x = np.asarray(x_G, float)
    ok = np.isfinite(z) & np.isfinite(x)
    z, x = z[ok], x[ok]
    if z.size == 0:
        return None
    left = z[x <= x.min() + edge_m]
    right = z[x >= x.max() - edge_m]
    widest = 0.5 * (float(np.percentile(left, 25)) + float(np.percentile(right, 25)))
    if float(z.max()) - widest > float(x.max() - x.min()):
        return None
    return widest


def grasp_height(between: np.ndarray, around: np.ndarray, *, depth_below_top_m: float,
                 fingertip_below_centre_m: float, support_margin_m: float,
                 table_z: float = 0.0, widest_z: float | None = None) -> float:
    """Grasp-centre height from the heights seen under the open hand.

    `between`: heights between the pads; `around`: heights under the whole hand, fingers
    included. The support (the table or sheet top) is the lowest surface seen under the
    hand, never below `table_z`; the fingertips stay `support_margin_m` above it. The pad
    centres go `depth_below_top_m` below the highest surface between them (the object's
    top), or lower, to the object's widest section between the pads (`widest_z`, from
    `widest_section_height`) where that lies deeper: there the surface normals face the
    pads (a lying can grasped high on its curve is squeezed out of the grip). Never lower
    than the support margin allows.
    """
    a = np.asarray(around, float)
    a = a[np.isfinite(a)]
    b = np.asarray(between, float)
    b = b[np.isfinite(b)]
    support = max(float(table_z), float(a.min())) if a.size else float(table_z)
    top = float(b.max()) if b.size else support
    floor = support + support_margin_m + fingertip_below_centre_m
    centre = top - depth_below_top_m
    if widest_z is not None and np.isfinite(widest_z):
        centre = min(centre, float(widest_z))
    return max(floor, centre)
