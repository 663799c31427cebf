"""The detector's point cloud: a depth image back-projected with its pixel grid kept.

`organized_points` turns one depth image, the camera's field of view and its pose into
world points and camera-facing normals per pixel (`OrganizedCloud`), with Drake's
pinhole model (`geometry.camera.PinholeCamera`); `depth_to_points` flattens the valid pixels and
`remove_table` masks the table and sheet away. `_contact_normals` gives the normals the
antipodal test uses: the measured surface inside an object, and at a silhouette, where
the surface below the edge is hidden, a wall whose azimuth follows the depth gradient
and whose tilt follows the drop to the neighbouring pixels. Pure numpy / scipy, no Drake.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from drake_grasp.geometry.camera import PinholeCamera
from drake_grasp.policies.gpd_geometric_checks import _check_depth, _check_pose, _finite

# Default far value of the post-processed wrist images (`WristCameraConfig.depth_max_m`).
DEFAULT_MAX_DEPTH_M = 1.5
# The sheet (2 mm) plus 2 mm: the same clearance `grasps.check_grasp_poses` demands of
# the fingertips above the sheet's top, and the cut below which points are "table".
DEFAULT_TABLE_MARGIN_M = 0.004


# ----------------------------------------------------------------------------
# Point cloud.


@dataclass(frozen=True)
class OrganizedCloud:
    """Back-projected depth image, one entry per pixel (row, column).

    Attributes:
        points: (H, W, 3) world positions [m] (NaN where not `valid`).
        normals: (H, W, 3) unit surface normals in the world, facing the camera
            (zero where not `valid`).
        valid: (H, W) pixels with a depth reading (0 < depth < far value).
        depth: (H, W) the checked depth image [m].
        focal_px: Focal length [pixels].
        outer_normals: (H, W, 3) unit normals of the surface from each pixel to its
            deeper neighbours (the hidden side of a silhouette; see
            `organized_points`).
    """

    points: np.ndarray
    normals: np.ndarray
    valid: np.ndarray
    depth: np.ndarray
    focal_px: float
    outer_normals: np.ndarray


def organized_points(depth, *, fov_y_deg: float, X_WC,
                     max_depth_m: float = DEFAULT_MAX_DEPTH_M) -> OrganizedCloud:
    """Back-projects a depth image into world points and normals, keeping its grid.

    Pixel (row v, column u) with depth d (along the optical axis, as Drake renders)
    is the camera-frame point d * ((u - cu) / f, (v - cv) / f, 1) (x right, y down,
    z forward). Normals come from the cross product of neighbour differences along
    the rows and the columns; of the two neighbours on each axis the one with the
    smaller depth step is used, so that normals at an object's silhouette describe
    the object, not the jump to the table behind it. They are turned toward the
    camera (a camera sees only surfaces facing it).

    Args:
        depth: (H, W) or (H, W, 1) depths [m]; values <= 0 (no reading) and values
            >= `max_depth_m` or +inf (nothing within range) are dropped.
        fov_y_deg: Vertical field of view [deg].
        X_WC: (4, 4) pose of the camera in the world (or a Drake RigidTransform).
        max_depth_m: The far value of the image [m].

    Raises:
        ValueError: a bad shape, NaN / -inf depths, or a bad pose or field of view.
    """
    d = _check_depth(depth)
    X = _check_pose(X_WC)
    far = _finite("max_depth_m", max_depth_m, low=0.0, low_inclusive=False)
    H, W = d.shape
    camera = PinholeCamera.from_fov(W, H, fov_y_deg)
    f = camera.focal_px
    # A hair below the far value: post-processing writes exactly `far` (float32).
    valid = (d > 0.0) & (d < far * (1.0 - 1e-6))
    v, u = np.mgrid[0:H, 0:W]
    dn = np.where(valid, d, np.nan)
    P_C = np.stack([*camera.back_project(u, v, dn), dn], axis=-1)

    # One-sided differences. `normals`: per axis the neighbour with the smaller depth
    # step (the pixel's own surface, not the jump to the table behind a silhouette).
    # `outer_normals`: per axis the deeper neighbour, i.e. the surface between this
    # pixel and what lies beyond it: on a continuous surface the same normal, at a
    # silhouette the "skin" from the edge down to the background, whose tilt tells
    # a step (a near-vertical skin) from a sloped flank.
    pad = np.pad(P_C, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    c = pad[1:-1, 1:-1]
    fu, bu = pad[1:-1, 2:] - c, c - pad[1:-1, :-2]
    fv, bv = pad[2:, 1:-1] - c, c - pad[:-2, 1:-1]

    def pick(fwd: np.ndarray, bwd: np.ndarray, deeper: bool) -> np.ndarray:
        # Forward differences grow with depth when the neighbour is deeper, backward
        # ones when it is shallower; NaN (no neighbour) never wins.
        jf, jb = fwd[..., 2], -bwd[..., 2]
        if deeper:
            use_f = np.nan_to_num(jf, nan=-np.inf) >= np.nan_to_num(jb, nan=-np.inf)
        else:
            use_f = (np.nan_to_num(np.abs(jf), nan=np.inf)
                     <= np.nan_to_num(np.abs(jb), nan=np.inf))
        return np.where(use_f[..., None], fwd, bwd)

    toward = -P_C / np.linalg.norm(np.nan_to_num(P_C), axis=-1, keepdims=True).clip(1e-12)
    R, t = X[:3, :3], X[:3, 3]
    out = []
    for deeper in (False, True):
        n = np.cross(pick(fu, bu, deeper), pick(fv, bv, deeper))
        n_len = np.linalg.norm(n, axis=-1, keepdims=True)
        ok = np.isfinite(n_len) & (n_len > 1e-12)
        # Isolated pixels (no valid neighbour on an axis): assume they face the camera.
        n = np.where(ok, n / np.where(ok, n_len, 1.0), toward)
        n = np.where(np.sum(n * np.nan_to_num(P_C), axis=-1, keepdims=True) > 0.0, -n, n)
        out.append(np.where(valid[..., None], n @ R.T, 0.0))
    P_W = P_C @ R.T + t
    return OrganizedCloud(P_W, out[0], valid, d, f, out[1])


def depth_to_points(depth, *, fov_y_deg: float, X_WC,
                    max_depth_m: float = DEFAULT_MAX_DEPTH_M) -> tuple[np.ndarray, np.ndarray]:
    """World points of a depth image's valid pixels and their normals.

    See `organized_points` for the camera model and the normals.

    Returns:
        points (N, 3) [m] and unit normals (N, 3) facing the camera, in row-major
        pixel order, far and invalid pixels dropped.
    """
    cloud = organized_points(depth, fov_y_deg=fov_y_deg, X_WC=X_WC, max_depth_m=max_depth_m)
    return cloud.points[cloud.valid], cloud.normals[cloud.valid]


def remove_table(points, *, table_z: float = 0.0,
                 table_margin_m: float = DEFAULT_TABLE_MARGIN_M) -> np.ndarray:
    """Mask of the points above the table plane (z >= table_z + table_margin_m).

    The default margin removes the 2 mm sheet the objects lie on and 2 mm of noise.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points: expected an (N, 3) array, got shape {P.shape}")
    cut = _finite("table_z", table_z) + _finite("table_margin_m", table_margin_m, low=0.0)
    return P[:, 2] >= cut



def _contact_normals(cloud: OrganizedCloud, R_WC: np.ndarray, step_threshold_m: float,
                     far: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel normals for the contact test and the silhouette (step) mask.

    A pixel with an 8-neighbour deeper by more than `step_threshold_m` is on a
    silhouette: what lies below it is hidden, and (occluded space counting as
    occupied) a wall goes down from it. The wall's steepness: the largest height drop
    to a neighbour over the pixel's footprint (its width at the pixel's depth times
    the neighbour's distance in pixels), i.e. with no perspective shift, which a
    vertical wall seen from off its axis shows but which says nothing about a slope:
    a step onto the table gives a near-vertical wall, a steep but continuous flank
    (a sphere's) its true slope. Its azimuth: the direction in which the depth grows,
    from a Sobel filter (which averages a 3 x 3 neighbourhood and resolves an edge's
    direction to a few degrees, better than one-sided differences on a pixel
    staircase). Elsewhere the normal of the surface toward the deeper neighbours
    (`OrganizedCloud.outer_normals`).

    Returns:
        (H, W, 3) unit normals and the (H, W) step mask.
    """
    d = np.where(cloud.valid, cloud.depth, far)
    deepest = ndimage.maximum_filter(d, size=3, mode="nearest")
    step = (deepest - d > step_threshold_m) & cloud.valid
    gu = ndimage.sobel(d, axis=1, mode="nearest")  # d(depth)/d(column)
    gv = ndimage.sobel(d, axis=0, mode="nearest")  # d(depth)/d(row)
    # Image columns / rows run along the camera's x / y axes: the world direction in
    # which the depth grows, i.e. away from the raised object, made horizontal.
    g = gu[..., None] * R_WC[:, 0] + gv[..., None] * R_WC[:, 1]
    g[..., 2] = 0.0
    g_len = np.linalg.norm(g, axis=-1, keepdims=True)
    step &= g_len[..., 0] > 1e-9
    # Steepest drop per footprint to any 8-neighbour; no neighbour surface (far /
    # invalid): a drop to far below, i.e. a vertical wall.
    z = np.where(cloud.valid, cloud.points[..., 2], -np.inf)
    zp = np.pad(z, 1, constant_values=-np.inf)
    H, W = z.shape
    slope = np.zeros((H, W))
    with np.errstate(invalid="ignore"):
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di or dj:
                    drop = z - zp[1 + di:1 + di + H, 1 + dj:1 + dj + W]
                    slope = np.fmax(slope, drop / np.hypot(di, dj))
    footprint = cloud.depth / cloud.focal_px
    elevation = np.arctan2(footprint, np.where(np.isfinite(slope), slope, 1e9))
    wall = g / np.maximum(g_len, 1e-12) * np.cos(elevation)[..., None]
    wall[..., 2] = np.sin(elevation)
    return np.where(step[..., None], wall, cloud.outer_normals), step
