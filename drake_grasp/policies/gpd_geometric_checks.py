"""Argument checks of the geometric grasp detector (`gpd_geometric.detect_grasps`).

The detector's inputs come from callers and scenario files, so every one is checked
before use and a bad one is named in a ValueError: the RNG (a numpy Generator), finite
numbers within a range, positive integers, the depth image (numeric, (H, W) or
(H, W, 1), no NaN or -inf) and the camera pose (a rigid 4 x 4 transform or a Drake
RigidTransform). Pure numpy; `gpd_geometric`, its point cloud (`gpd_geometric_cloud`)
and its score weights (`gpd_geometric_results`) use these checks.
"""

from __future__ import annotations

import numpy as np


def _check_rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    return rng


def _finite(name: str, value, *, low: float | None = None, low_inclusive: bool = True,
            high: float | None = None) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a finite number, got {value!r}") from None
    ok = np.isfinite(v)
    if ok and low is not None:
        ok = v >= low if low_inclusive else v > low
    if ok and high is not None:
        ok = v < high
    if not ok:
        rng_txt = ""
        if low is not None:
            rng_txt += f" {'>=' if low_inclusive else '>'} {low}"
        if high is not None:
            rng_txt += f"{' and' if low is not None else ''} < {high}"
        raise ValueError(f"{name}: expected a finite number{rng_txt}, got {value!r}")
    return v


def _positive_int(name: str, value) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
    return int(value)


def _check_depth(depth) -> np.ndarray:
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    if d.ndim != 2 or min(d.shape) < 3 or not np.issubdtype(d.dtype, np.number):
        raise ValueError(
            f"depth: expected a numeric (H, W) or (H, W, 1) image of depths [m] with "
            f"H, W >= 3, got shape {d.shape} and dtype {d.dtype}")
    d = d.astype(np.float64)
    bad = np.isnan(d) | np.isneginf(d)
    if bad.any():
        raise ValueError(
            f"depth: expected depths [m] (> 0; 0 or +inf mark invalid / far pixels), got "
            f"{int(bad.sum())} NaN or -inf pixels (post-process the image first)")
    return d


def _check_pose(X_WC) -> np.ndarray:
    if hasattr(X_WC, "GetAsMatrix4"):  # a Drake RigidTransform (no Drake import here)
        X_WC = X_WC.GetAsMatrix4()
    X = np.asarray(X_WC, dtype=float)
    if X.shape != (4, 4) or not np.all(np.isfinite(X)):
        raise ValueError(
            f"X_WC: expected a finite 4x4 homogeneous transform of the camera in the world, "
            f"got shape {X.shape}" + ("" if X.shape != (4, 4) else " with non-finite entries"))
    R = X[:3, :3]
    if (not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0
            or not np.allclose(X[3], [0.0, 0.0, 0.0, 1.0])):
        raise ValueError("X_WC: expected a rigid transform (orthonormal rotation with det +1, "
                         "last row [0, 0, 0, 1])")
    return X
