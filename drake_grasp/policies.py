"""The policies' decisions as pure functions (numpy; the CNN through `network`).

CTR, the paper's Algorithm 1: on each control step take the latest depth image, score
candidate actions sampled near the current pose, pick the least predicted distance, move
a fraction r of the way there in (x, y, theta) and step down in z; stop when an object
is within 14 cm of the sensor, the hand reaches its lowest height, or the iterations
are spent. The baselines decide once, from the first image: `cnn-only` the CNN's global
best action over the whole view, `gpd` a geometric one-shot grasp detection.
"""

from __future__ import annotations

import numpy as np

from drake_grasp.grasps import ANGLE_WEIGHT_M_PER_DEG as METRES_PER_DEGREE


def sample_candidates(rng: np.random.Generator, count: int, *, xy_m: float,
                      theta_deg: float) -> np.ndarray:
    """Actions (count, 3) uniform in [-xy, xy]^2 x [-theta, theta] (degrees)."""
    a = np.empty((count, 3))
    a[:, :2] = rng.uniform(-xy_m, xy_m, (count, 2))
    a[:, 2] = rng.uniform(-theta_deg, theta_deg, count)
    return a


def displacement_norm(delta) -> np.ndarray:
    """|delta| in the paper's (x, y, theta) metric [m]."""
    d = np.asarray(delta, dtype=float)
    return np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2 + (METRES_PER_DEGREE * d[..., 2]) ** 2)


def gaussian_noisy_displacement(delta, rng: np.random.Generator, scale: float = 0.4) -> np.ndarray:
    """The paper's kinematic noise: delta + scale * w * |delta|, w ~ N(0, I) per dimension
    (theta's noise in degrees, through the 0.001 m/deg weighting)."""
    d = np.asarray(delta, dtype=float)
    w = rng.standard_normal(3)
    size = float(displacement_norm(d))
    noise = scale * w * size
    noise[2] /= METRES_PER_DEGREE
    return d + noise


def offset_fraction(moved_m: float, ramp_m: float) -> float:
    """How much of the constant offset applies after the hand moved `moved_m` from where
    it observed the scene (0 at the observation pose, 1 after `ramp_m`)."""
    if ramp_m <= 0:
        return 1.0
    return float(min(1.0, max(0.0, moved_m / ramp_m)))


def choose_action(actions: np.ndarray, distances: np.ndarray) -> tuple[np.ndarray, float]:
    """The candidate with the least predicted distance (first one on ties)."""
    d = np.asarray(distances, dtype=float)
    if d.ndim != 1 or len(d) != len(actions) or len(d) == 0:
        raise ValueError(f"distances: expected one per action ({len(actions)}), got shape {d.shape}")
    i = int(np.argmin(d))
    return np.asarray(actions[i], dtype=float), float(d[i])


def central_min_depth(depth: np.ndarray, fraction: float) -> float:
    """Nearest reading in the central `fraction` of the image (the 14 cm stop rule)."""
    h, w = depth.shape[:2]
    fh, fw = max(1, int(round(h * fraction))), max(1, int(round(w * fraction)))
    r0, c0 = (h - fh) // 2, (w - fw) // 2
    window = depth[r0:r0 + fh, c0:c0 + fw]
    valid = window[np.isfinite(window) & (window > 0)]
    return float(valid.min()) if valid.size else float("inf")


def wrap_theta_deg(theta) -> np.ndarray:
    """Angles to [-90, 90): the hand is symmetric under 180 degrees."""
    return (np.asarray(theta, dtype=float) + 90.0) % 180.0 - 90.0
