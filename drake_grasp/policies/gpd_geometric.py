"""One-shot grasp pose detection (GPD) from a single depth image: the paper's baseline.

Viereck et al. (CoRL 2017) compare their closed-loop controller with grasp pose
detection (Gualtieri, ten Pas, Saenko & Platt, IROS 2016), run once from one depth
view: the hand moves to a fixed pose above the table, takes one image, and executes
the top detection open loop. GPD proposes hand candidates geometrically (ten Pas &
Platt, ISRR 2015) and ranks them with a CNN. This module keeps the geometric part and
ranks with a documented geometric score instead of a learned classifier, so it needs
no training and runs anywhere: pure numpy / scipy, no Drake, no meshes, no ground
truth. Its input is what a robot has: one depth image, the camera intrinsics (the
pinhole model of `drake_grasp.world.station.make_depth_camera`) and the camera pose the
robot believes it has.

Pipeline (`detect_grasps`):

1. Back-projection (`organized_points`, `depth_to_points`): world points of the valid
   pixels and surface normals from neighbour differences in the organised image.
2. Table removal (`remove_table`): points below ``table_z + table_margin_m`` are the
   table and the 2 mm sheet.
3. Candidates, as in ten Pas & Platt: `num_samples` cloud points drawn with the
   given `rng`; about each, `num_rotations` top-down hands whose first closing
   direction is the local surface normal projected to the horizontal plane (or, on
   flat tops where the normal is vertical, the minor axis of the local footprint),
   the others evenly spaced over 180 degrees (so the perpendicular is among them);
   each at several `depths` below the local top (the highest point between the
   pads), raised where needed to keep the fingertips at ``table_z + table_margin_m``.
4. Tests per hand (vectorised over hands x neighbouring points):
   * collision: one view sees only the top of things, so the space below every
     visible point is taken as occupied (a column down to the table). A finger, the
     palm or the housing, swept straight down to its final pose, is free only if no
     visible point lies inside its footprint at or above its lowest face. Around
     silhouette points the parts are grown by a pixel (the true edge lies up to a
     pixel beyond the last pixel seen on the object) and the fingers' inner faces
     by `finger_margin_m`.
   * closing region: at least `min_points_between` visible points whose columns
     cross the box the pads sweep (85 mm x 22 mm x 38 mm), spanning at least
     `min_width_m`; the pads close to its extent along x_G.
   * antipodal contacts: the extreme points along -x_G and +x_G (patches one pixel
     deep) must lie on the same connected object and pass the two-contact
     force-closure test (`grasps.force_closure`, friction `mu`). At a silhouette
     the surface below the edge is hidden: its normal gets the azimuth of the depth
     gradient and the tilt of the drop to the neighbouring pixels (a near-vertical
     wall for a step onto the table, the true slope for a steep, curved flank);
     elsewhere it is the measured normal.
   * view: the fingers and the palm must lie inside the image (nothing is known
     beyond its border; an object cut by it looks narrower than it is).
   * occlusion (optional, `occlusion_check`): probe points on the open hand must
     be seen as free space, i.e. in front of the measured depth; stricter than the
     column model (it also keeps fingers out of the shadows beside tall objects,
     where a box's side is empty but a sphere's bulge hides).
5. Score (`ScoreWeights`; each term in [0, 1], returned per grasp in `terms`):
   ``score = sum_i w_i * term_i`` over
   * antipodal (w 1): ``1 - max(angle_1, angle_2) / atan(mu)``, the contact normals'
     margin inside the friction cone;
   * centring (w 1): ``1 - d / r``, d the xy distance from the grasp centre to the
     centroid of the grasped object's visible points (its connected component in
     the image), r that object's largest distance from it: grasps near the middle
     of an object hold it balanced;
   * balance (w 1): ``1 - |y_mid| / 40 mm``, y_mid the middle of the object's
     extent along y_G between the fingers, within the pads' reach and 40 mm of the
     centre: the pads centred on the part they hold (across a cap, not its rim);
   * clearance (w 0.5): ``min(42.5 mm + x_min, 42.5 mm - x_max) / 42.5 mm``, the
     smaller gap between a contact and its open finger (largest for a hand centred
     on the object: the most tolerance to errors along the closing direction);
   * fill (w 0.5): the fraction of the pads' closing area (width x 22 mm) that
     visible points cover (low where the pads hang over an object's end);
   * depth (w 1): the fraction of the 38 mm pads below the local top (more contact
     area; pads that stick out above an object touch its top edges);
   * view (w 0.05): ``1 - d / h``, d the xy distance to the camera, h the half width
     of the view at the table: only a tie-breaker.
   Detections come sorted by score, best first.

Conventions (`drake_grasp.geometry.grasps`): the grasp frame G sits between the pads, z_G is
the approach (down for top-down grasps), x_G the closing direction, R_WG = Rz(yaw)
Rx(pi). A detection's ``theta`` is the yaw of x_G in degrees modulo 180.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from drake_grasp.geometry.contact_physics import force_closure
from drake_grasp.geometry.hand_model import (
    FINGERTIP_Z_M,
    FINGER_OUTER_X_M,
    HAND_FOOTPRINT_RADIUS_M,
    HOUSING_FRONT_Z_M,
    HOUSING_RADIUS_M,
    PAD_HALF_LENGTH_M,
    PAD_HALF_WIDTH_M,
    PALM_FRONT_Z_M,
    PALM_HALF_X_M,
    PALM_HALF_Y_M,
    STROKE_M,
    topdown_rotation,
)

HALF_STROKE_M = 0.5 * STROKE_M
# Default far value of the post-processed wrist images (`WristCameraConfig.depth_max_m`).
DEFAULT_MAX_DEPTH_M = 1.5
# The sheet (2 mm) plus 2 mm: the same clearance `grasps.check_grasp_poses` demands of
# the fingertips above the sheet's top, and the cut below which points are "table".
DEFAULT_TABLE_MARGIN_M = 0.004
DEFAULT_DEPTHS_M = (0.0, 0.01, 0.02)
# Below this horizontal component a normal gives no closing direction (flat tops):
# sin(12 deg), as `grasps.sample_grasp_candidates`.
_MIN_HORIZONTAL_NORMAL = 0.2
# Half length along y_G of the window in which the balance term measures the
# object's extent [m]: the hand's half width, roughly.
_BALANCE_HALF_WINDOW_M = 0.04
# Radius of the footprint whose minor axis orients hands on flat tops [m].
_FOOTPRINT_RADIUS_M = 0.03

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


# ----------------------------------------------------------------------------
# Argument checks.


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


def camera_intrinsics(height: int, width: int, fov_y_deg: float) -> tuple[float, float, float]:
    """Pinhole intrinsics of Drake's `CameraInfo(width, height, fov_y)`.

    Args:
        height, width: Image size [pixels].
        fov_y_deg: Vertical field of view [deg], in (0, 180).

    Returns:
        (f, cu, cv): focal length [pixels] (square pixels) and the principal point
        (column, row) = (W / 2 - 0.5, H / 2 - 0.5).
    """
    fov = _finite("fov_y_deg", fov_y_deg, low=0.0, low_inclusive=False, high=180.0)
    f = 0.5 * height / np.tan(np.deg2rad(fov) / 2.0)
    return float(f), width / 2.0 - 0.5, height / 2.0 - 0.5


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
    f, cu, cv = camera_intrinsics(H, W, fov_y_deg)
    # A hair below the far value: post-processing writes exactly `far` (float32).
    valid = (d > 0.0) & (d < far * (1.0 - 1e-6))
    v, u = np.mgrid[0:H, 0:W]
    dn = np.where(valid, d, np.nan)
    P_C = np.stack([dn * (u - cu) / f, dn * (v - cv) / f, dn], axis=-1)

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


# ----------------------------------------------------------------------------
# Results.


@dataclass(frozen=True)
class ScoreWeights:
    """Weights of the score terms (each term in [0, 1]; see the module docstring)."""

    antipodal: float = 1.0
    centring: float = 1.0
    balance: float = 1.0
    clearance: float = 0.5
    fill: float = 0.5
    depth: float = 1.0
    view: float = 0.05

    def validate(self) -> None:
        for name in SCORE_TERMS:
            _finite(f"weights.{name}", getattr(self, name), low=0.0)


SCORE_TERMS = ("antipodal", "centring", "balance", "clearance", "fill", "depth", "view")


@dataclass(frozen=True)
class Grasp:
    """One detected top-down grasp.

    Attributes:
        xy_theta: (3,) grasp centre x, y [m] and closing-direction yaw theta [deg] in
            [0, 180).
        z: Height of the grasp centre [m].
        width: What the pads close to [m].
        score: Its score (higher is better).
    """

    xy_theta: np.ndarray
    z: float
    width: float
    score: float

    @property
    def hand_pose(self) -> np.ndarray:
        """[x, y, z, yaw_deg] of the grasp frame (the format `SceneRenderer` takes)."""
        return np.array([self.xy_theta[0], self.xy_theta[1], self.z, self.xy_theta[2]])

    @property
    def pose(self) -> np.ndarray:
        """(4, 4) X_WG of the grasp frame."""
        X = np.eye(4)
        X[:3, :3] = topdown_rotation(np.deg2rad(self.xy_theta[2]))
        X[:3, 3] = [self.xy_theta[0], self.xy_theta[1], self.z]
        return X


@dataclass(frozen=True)
class DetectedGrasps:
    """Detections of one image, best first.

    Attributes:
        xy_theta: (N, 3) grasp centres x, y [m] and yaw theta [deg] in [0, 180) of
            the closing direction x_G, in the world.
        z: (N,) heights of the grasp centres [m].
        width: (N,) what the pads close to (extent of the closing region) [m].
        score: (N,) scores, descending.
        contacts: (N, 2, 3) centroids of the two contact patches as seen (-x_G side
            first) [m].
        contact_normals: (N, 2, 3) their mean outward unit normals.
        terms: Score terms by name (`SCORE_TERMS`), each (N,) in [0, 1].
    """

    xy_theta: np.ndarray
    z: np.ndarray
    width: np.ndarray
    score: np.ndarray
    contacts: np.ndarray
    contact_normals: np.ndarray
    terms: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.score)

    @classmethod
    def empty(cls) -> DetectedGrasps:
        return cls(np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0),
                   np.zeros((0, 2, 3)), np.zeros((0, 2, 3)), {k: np.zeros(0) for k in SCORE_TERMS})

    def poses(self) -> np.ndarray:
        """(N, 4, 4) X_WG of the grasp frames (top-down: R_WG = Rz(theta) Rx(pi))."""
        th = np.deg2rad(self.xy_theta[:, 2])
        c, s = np.cos(th), np.sin(th)
        X = np.zeros((len(self), 4, 4))
        X[:, 0, 0], X[:, 1, 0] = c, s
        X[:, 0, 1], X[:, 1, 1] = s, -c
        X[:, 2, 2] = -1.0
        X[:, :2, 3] = self.xy_theta[:, :2]
        X[:, 2, 3] = self.z
        X[:, 3, 3] = 1.0
        return X

    def hand_poses(self) -> np.ndarray:
        """(N, 4) [x, y, z, yaw_deg] of the grasp frames."""
        return np.column_stack([self.xy_theta[:, :2], self.z, self.xy_theta[:, 2]])

    def best(self) -> Grasp | None:
        """The top detection, or None when there is none."""
        if len(self) == 0:
            return None
        return Grasp(self.xy_theta[0].copy(), float(self.z[0]), float(self.width[0]),
                     float(self.score[0]))


# ----------------------------------------------------------------------------
# Detection.


def _segments(sorted_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs of equal ids in a sorted array: (start positions, run ids, run index of
    every element)."""
    flag = np.empty(len(sorted_ids), dtype=bool)
    if len(sorted_ids):
        flag[0] = True
        np.not_equal(sorted_ids[1:], sorted_ids[:-1], out=flag[1:])
    starts = np.flatnonzero(flag)
    return starts, sorted_ids[starts], np.cumsum(flag) - 1


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


def detect_grasps(
    depth,
    *,
    fov_y_deg: float,
    X_WC,
    rng: np.random.Generator,
    mu: float = 0.5,
    num_samples: int = 200,
    num_rotations: int = 8,
    depths=DEFAULT_DEPTHS_M,
    table_z: float = 0.0,
    table_margin_m: float = DEFAULT_TABLE_MARGIN_M,
    max_depth_m: float = DEFAULT_MAX_DEPTH_M,
    min_points_between: int = 5,
    min_width_m: float = 0.005,
    contact_tolerance_m: float = 0.002,
    finger_margin_m: float = 0.004,
    step_threshold_m: float = 0.008,
    occlusion_check: bool = False,
    occlusion_tolerance_m: float = 0.003,
    weights: ScoreWeights | None = None,
    stats: dict | None = None,
) -> DetectedGrasps:
    """Detects top-down parallel-jaw grasps in one depth image (see the module doc).

    Args:
        depth: (H, W) depth image [m], e.g. `sensing.postprocess_depth`'s output.
        fov_y_deg: The camera's vertical field of view [deg].
        X_WC: (4, 4) camera pose the robot believes it has (or a RigidTransform).
        rng: Draws the sample points (the only randomness: the same seed and image
            give the same detections).
        mu: Friction coefficient of the antipodal (force-closure) test.
        num_samples: Cloud points to place hands at (all points if fewer). 200 on a
            64 x 64 image covers a 5 cm object with ~1 sample per pixel.
        num_rotations: Closing directions per sample, over 180 degrees (8: 22.5 deg).
        depths: Grasp-centre depths below the local top [m] (non-negative).
        table_z: Height of the table top in the world [m].
        table_margin_m: Points below table_z + this are the table / sheet, and the
            fingertips must stay at or above it [m].
        max_depth_m: The image's far value [m]; pixels at or beyond it are empty.
        min_points_between: Fewest visible points in the closing region.
        min_width_m: Narrowest graspable width [m].
        contact_tolerance_m: Depth of a contact patch along x_G [m]; at least one
            pixel's footprint is used (the cloud cannot resolve less).
        finger_margin_m: Free space demanded between the open fingers and any
            visible point [m]: the widths and positions seen in a 64 x 64 image
            are uncertain by a few millimetres.
        step_threshold_m: Depth jump between neighbouring pixels that marks a
            silhouette [m].
        occlusion_check: Reject hands whose probe points the camera cannot see as
            free space (occluded: unknown, maybe occupied).
        occlusion_tolerance_m: How far behind the measured surface a probe may lie
            and still count as free [m] (noise, fingertips just above the table).
        weights: Score weights (default `ScoreWeights()`).
        stats: Optional dict, filled with how many candidates reached each stage
            ("points", "samples", "hands", "collision_free", "closing_region",
            "antipodal", "in_view", "visible") and the run time ("seconds").

    Returns:
        `DetectedGrasps`, sorted best first (empty when nothing passes).

    Raises:
        ValueError: a bad argument (named in the message).
    """
    t_start = time.perf_counter()
    _check_rng(rng)
    mu = _finite("mu", mu, low=0.0)
    S_max = _positive_int("num_samples", num_samples)
    K = _positive_int("num_rotations", num_rotations)
    dep = np.atleast_1d(np.asarray(depths, dtype=float))
    if dep.ndim != 1 or len(dep) == 0 or not np.all(np.isfinite(dep)) or np.any(dep < 0):
        raise ValueError(f"depths: expected a non-empty 1-D sequence of finite depths >= 0 [m], "
                         f"got {depths!r}")
    dep = np.unique(dep)  # sorted: a clamped depth then repeats the one before it
    table_z = _finite("table_z", table_z)
    table_margin_m = _finite("table_margin_m", table_margin_m, low=0.0)
    min_points_between = _positive_int("min_points_between", min_points_between)
    min_width_m = _finite("min_width_m", min_width_m, low=0.0)
    tol = _finite("contact_tolerance_m", contact_tolerance_m, low=0.0)
    margin = _finite("finger_margin_m", finger_margin_m, low=0.0, high=HALF_STROKE_M)
    step_threshold_m = _finite("step_threshold_m", step_threshold_m, low=0.0, low_inclusive=False)
    occ_tol = _finite("occlusion_tolerance_m", occlusion_tolerance_m, low=0.0)
    weights = ScoreWeights() if weights is None else weights
    if not isinstance(weights, ScoreWeights):
        raise ValueError(f"weights: expected a ScoreWeights, got {type(weights).__name__}")
    weights.validate()
    far = _finite("max_depth_m", max_depth_m, low=0.0, low_inclusive=False)
    if stats is not None and not isinstance(stats, dict):
        raise ValueError(f"stats: expected a dict or None, got {type(stats).__name__}")
    st_ = {k: 0 for k in ("points", "samples", "hands", "collision_free", "closing_region",
                          "antipodal", "in_view", "visible")}

    def done(result: DetectedGrasps) -> DetectedGrasps:
        if stats is not None:
            stats.update(st_, seconds=time.perf_counter() - t_start)
        return result

    cloud = organized_points(depth, fov_y_deg=fov_y_deg, X_WC=X_WC, max_depth_m=far)
    X = _check_pose(X_WC)
    R_WC, p_WC = X[:3, :3], X[:3, 3]
    floor = table_z + table_margin_m
    obj = cloud.valid & (cloud.points[..., 2] >= floor)
    if not obj.any():
        return done(DetectedGrasps.empty())

    # --- Per-pixel attributes of the object points --------------------------------
    cn, use_wall = _contact_normals(cloud, R_WC, step_threshold_m, far)
    labels_img, n_labels = ndimage.label(obj, structure=np.ones((3, 3), dtype=int))
    P = cloud.points[obj]  # (M, 3)
    Nc = cn[obj]
    is_wall = use_wall[obj]
    label = labels_img[obj]
    # Area each point stands for, across the optical axis (for the fill term).
    area = (cloud.depth[obj] / cloud.focal_px) ** 2
    # A silhouette's true edge lies between its last pixel's centre and the next
    # pixel's: up to one pixel footprint beyond the point (the collision tests grow
    # the hand by that much around such points), half a pixel on average (widths and
    # contacts are pushed out by that much).
    px_all = np.sqrt(area)
    px_wall = np.where(is_wall, px_all, 0.0)
    half_px = 0.5 * px_wall
    M = len(P)
    st_["points"] = M
    # Objects (connected components): centroid and radius for the centring term.
    cnt_l = np.bincount(label, minlength=n_labels + 1).astype(float)
    cx_l = np.bincount(label, P[:, 0], minlength=n_labels + 1) / np.maximum(cnt_l, 1)
    cy_l = np.bincount(label, P[:, 1], minlength=n_labels + 1) / np.maximum(cnt_l, 1)
    r_pt = np.hypot(P[:, 0] - cx_l[label], P[:, 1] - cy_l[label])
    rad_l = np.zeros(n_labels + 1)
    np.maximum.at(rad_l, label, r_pt)

    # --- Samples and their hands' first closing directions --------------------------
    S = min(S_max, M)
    st_["samples"] = S
    samples = np.sort(rng.choice(M, size=S, replace=False))
    C = P[samples]  # hand axes pass through these points
    dx = (P[None, :, 0] - C[:, None, 0]).astype(np.float32)
    dy = (P[None, :, 1] - C[:, None, 1]).astype(np.float32)
    r2 = dx * dx + dy * dy
    near = r2 <= np.float32(HAND_FOOTPRINT_RADIUS_M + px_wall.max() + 1e-6) ** 2
    s_idx, p_idx = np.nonzero(near)  # sorted by sample: contiguous runs per sample
    pdx, pdy, pr2 = dx[near], dy[near], r2[near]
    pz = P[p_idx, 2]
    starts = np.flatnonzero(np.r_[True, s_idx[1:] != s_idx[:-1]])  # every sample has itself

    h = Nc[samples, :2]
    h_len = np.linalg.norm(h, axis=1)
    # Flat tops: the minor axis of the local footprint (points within 3 cm).
    fp = pr2 <= _FOOTPRINT_RADIUS_M**2
    cnt = np.bincount(s_idx[fp], minlength=S).astype(float)
    mx = np.bincount(s_idx[fp], pdx[fp], minlength=S) / cnt
    my = np.bincount(s_idx[fp], pdy[fp], minlength=S) / cnt
    cxx = np.bincount(s_idx[fp], pdx[fp] ** 2, minlength=S) / cnt - mx**2
    cyy = np.bincount(s_idx[fp], pdy[fp] ** 2, minlength=S) / cnt - my**2
    cxy = np.bincount(s_idx[fp], pdx[fp] * pdy[fp], minlength=S) / cnt - mx * my
    minor = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy) + 0.5 * np.pi
    base = np.where(h_len > _MIN_HORIZONTAL_NORMAL, np.arctan2(h[:, 1], h[:, 0]), minor)
    base = np.mod(base, np.pi)

    # --- Hand-frame coordinates of the neighbours, all K rotations: (K, pairs) -------
    cb, sb = np.cos(base[s_idx]).astype(np.float32), np.sin(base[s_idx]).astype(np.float32)
    x0 = pdx * cb + pdy * sb  # along x_G at rotation 0
    w0 = pdy * cb - pdx * sb  # along -y_G at rotation 0 (only |y| matters)
    phase = np.pi * np.arange(K) / K
    c, s = np.cos(phase).astype(np.float32)[:, None], np.sin(phase).astype(np.float32)[:, None]
    Xg = c * x0 + s * w0
    Yg = c * w0 - s * x0  # -y_G (only symmetric tests and extents use it)
    aY = np.abs(Yg)
    aX = np.abs(Xg)
    zf = pz.astype(np.float32)[None, :]
    ninf = np.float32(-np.inf)
    strip = (aY <= PAD_HALF_WIDTH_M) & (aX <= HALF_STROKE_M)
    # Collisions: the hand's parts are grown by a pixel around silhouette points.
    hp = px_wall[p_idx].astype(np.float32)[None, :]
    finger = ((aY - hp <= PAD_HALF_WIDTH_M) & (aX + hp > HALF_STROKE_M - margin)
              & (aX - hp <= FINGER_OUTER_X_M))
    palm = (aX - hp <= PALM_HALF_X_M) & (aY - hp <= PALM_HALF_Y_M)
    top = np.maximum.reduceat(np.where(strip, zf, ninf), starts, axis=1)  # (K, S)
    finger_z = np.maximum.reduceat(np.where(finger, zf, ninf), starts, axis=1)
    palm_z = np.maximum.reduceat(np.where(palm, zf, ninf), starts, axis=1)
    house = np.where(np.sqrt(pr2) - hp[0] <= HOUSING_RADIUS_M, pz, -np.inf)
    house_z = np.maximum.reduceat(house, starts)[None, :]  # (1, S): round, any rotation

    # Centre heights (K, S, D): `depths` below the local top, fingertips above the floor.
    zc = np.maximum(top[..., None].astype(float) - dep, floor + FINGERTIP_Z_M)
    free = ((finger_z[..., None] < zc - FINGERTIP_Z_M)
            & (palm_z[..., None] < zc - PALM_FRONT_Z_M)
            & (house_z[..., None] < zc - HOUSING_FRONT_Z_M))
    distinct = np.ones(zc.shape, dtype=bool)
    distinct[..., 1:] = zc[..., 1:] < zc[..., :-1] - 1e-9  # clamped depths: one copy
    free &= distinct
    st_["hands"] = int(distinct.sum())
    st_["collision_free"] = int(free.sum())
    A = K * S
    zc = zc.reshape(A, -1)
    free = free.reshape(A, -1)
    top = top.reshape(A).astype(float)
    D = len(dep)

    # --- Closing region and contacts of the collision-free hands --------------------
    e = np.flatnonzero(strip)  # k-major, then by pair: axis ids a = k * S + s sorted
    e_k, e_pair = np.divmod(e, len(s_idx))
    e_axis = e_k * S + s_idx[e_pair]
    e_x = Xg.ravel()[e]
    e_pt = p_idx[e_pair]
    e_z = pz[e_pair]
    out = {k: [] for k in ("axis", "d", "count", "xmin", "xmax", "c0", "c1", "n0", "n1",
                           "label", "area")}
    for di in range(D):  # a handful of depths
        z_lo = zc[:, di] - PAD_HALF_LENGTH_M
        m = np.flatnonzero((e_z >= z_lo[e_axis]) & free[e_axis, di])
        if len(m) == 0:
            continue
        ids = e_axis[m]
        st, grp, gi = _segments(ids)
        G = len(grp)
        pt = e_pt[m]
        # Silhouette points pushed out by half a pixel: unbiased widths, clearances.
        x = e_x[m].astype(float)
        x_lo = np.maximum(x - half_px[pt], -HALF_STROKE_M)
        x_hi = np.minimum(x + half_px[pt], HALF_STROKE_M)
        xmin = np.minimum.reduceat(x_lo, st)
        xmax = np.maximum.reduceat(x_hi, st)
        count = np.diff(np.r_[st, len(m)])
        lo_m, hi_m = z_lo[ids], z_lo[ids] + 2.0 * PAD_HALF_LENGTH_M
        zp = P[pt, 2]
        # Contact height: on a wall, the middle of its part within the pads; on a
        # visible surface, the point itself (clipped to the pads).
        zcon = np.where(is_wall[pt], 0.5 * (lo_m + np.minimum(zp, hi_m)),
                        np.clip(zp, lo_m, hi_m))
        sides = []
        lab_sum = np.zeros(G)
        lab_sq = np.zeros(G)
        lab_n = np.zeros(G)
        tol_pt = np.maximum(tol, px_all[pt])
        for patch in (x_lo <= xmin[gi] + tol_pt, x_hi >= xmax[gi] - tol_pt):
            g = gi[patch]
            q = pt[patch]
            num = np.bincount(g, minlength=G).astype(float)
            pos = np.stack([np.bincount(g, P[q, 0], minlength=G),
                            np.bincount(g, P[q, 1], minlength=G),
                            np.bincount(g, zcon[patch], minlength=G)], axis=1) / num[:, None]
            nrm = np.stack([np.bincount(g, Nc[q, j], minlength=G) for j in range(3)], axis=1)
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            lq = label[q].astype(float)
            lab_sum += np.bincount(g, lq, minlength=G)
            lab_sq += np.bincount(g, lq * lq, minlength=G)
            lab_n += num
            sides.append((pos, nrm))
        mean_l = lab_sum / lab_n
        one_object = np.abs(lab_sq / lab_n - mean_l**2) < 1e-6
        width = xmax - xmin
        ok = (count >= min_points_between) & (width >= min_width_m) & one_object
        st_["closing_region"] += int(ok.sum())
        ok &= force_closure(sides[0][0], sides[0][1], sides[1][0], sides[1][1], mu=mu)
        keep = np.flatnonzero(ok)
        st_["antipodal"] += len(keep)
        out["axis"].append(grp[keep])
        out["d"].append(np.full(len(keep), di))
        out["count"].append(count[keep])
        out["xmin"].append(xmin[keep])
        out["xmax"].append(xmax[keep])
        out["c0"].append(sides[0][0][keep])
        out["c1"].append(sides[1][0][keep])
        out["n0"].append(sides[0][1][keep])
        out["n1"].append(sides[1][1][keep])
        out["label"].append(np.rint(mean_l[keep]).astype(np.int64))
        out["area"].append(np.bincount(gi, area[pt], minlength=G)[keep])
    if not out["axis"] or sum(len(a) for a in out["axis"]) == 0:
        return done(DetectedGrasps.empty())
    r = {k: np.concatenate(v) for k, v in out.items()}
    axis, di = r["axis"], r["d"]
    k_of, s_of = np.divmod(axis, S)
    yaw = base[s_of] + phase[k_of]
    centre = np.column_stack([C[s_of, :2], zc[axis, di]])

    # --- View and occlusion: probe points on the open hand -------------------------
    # Out of the view nothing is known. Where the image border next to a probe shows
    # an object, the object may go on under that part of the hand (an object cut by
    # the border looks narrower or lower than it is): rejected. Where it shows the
    # table, the table is taken to go on.
    # Optionally (`occlusion_check`) every probe in the view must be seen as free
    # space: in front of the measured depth.
    cy_, sy_ = np.cos(yaw), np.sin(yaw)
    # R_WG = Rz(yaw) Rx(pi): x_G = (c, s, 0), y_G = (s, -c, 0), z_G = (0, 0, -1).
    pw = np.empty((len(axis), len(PROBES_G), 3))
    pw[..., 0] = centre[:, None, 0] + cy_[:, None] * PROBES_G[:, 0] + sy_[:, None] * PROBES_G[:, 1]
    pw[..., 1] = centre[:, None, 1] + sy_[:, None] * PROBES_G[:, 0] - cy_[:, None] * PROBES_G[:, 1]
    pw[..., 2] = centre[:, None, 2] - PROBES_G[:, 2]
    pc = (pw - p_WC) @ R_WC
    H, W = cloud.depth.shape
    f, cu, cv = camera_intrinsics(H, W, fov_y_deg)
    front = pc[..., 2] > 1e-6  # behind the camera: nothing known
    zc_safe = np.where(front, pc[..., 2], 1.0)
    u = np.rint(f * pc[..., 0] / zc_safe + cu)
    v = np.rint(f * pc[..., 1] / zc_safe + cv)
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
    r = {k: v_[keep] for k, v_ in r.items()}
    axis, di, yaw, centre = axis[keep], di[keep], yaw[keep], centre[keep]
    if len(axis) == 0:
        return done(DetectedGrasps.empty())

    # --- Score ------------------------------------------------------------------------
    width = r["xmax"] - r["xmin"]
    c0, c1, n0, n1 = r["c0"], r["c1"], r["n0"], r["n1"]
    line = c1 - c0
    line /= np.maximum(np.linalg.norm(line, axis=1, keepdims=True), 1e-12)
    ang0 = np.arccos(np.clip(-np.sum(line * n0, axis=1), -1.0, 1.0))
    ang1 = np.arccos(np.clip(np.sum(line * n1, axis=1), -1.0, 1.0))
    cone = np.arctan(mu)
    antipodal = (np.clip(1.0 - np.maximum(ang0, ang1) / cone, 0.0, 1.0) if cone > 0
                 else np.ones(len(axis)))
    lab = r["label"]
    d_obj = np.hypot(centre[:, 0] - cx_l[lab], centre[:, 1] - cy_l[lab])
    centring = 1.0 - np.clip(d_obj / np.maximum(rad_l[lab], 1e-6), 0.0, 1.0)
    # Balance: the object's extent along y_G between the fingers, within the pads'
    # reach (z >= their lower edge) and `_BALANCE_HALF_WINDOW_M` of the centre,
    # should be symmetric about the centre (a bottle's cap held across its middle,
    # not by its rim). Over each survivor's neighbour pairs, grouped by survivor.
    k_of, s_of = np.divmod(axis, S)
    ends = np.r_[starts[1:], len(s_idx)]
    lens = ends[s_of] - starts[s_of]
    owner = np.repeat(np.arange(len(axis)), lens)
    pos = starts[s_of][owner] + np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
    bx, by = Xg[k_of[owner], pos], Yg[k_of[owner], pos]
    inb = ((np.abs(bx) <= HALF_STROKE_M) & (np.abs(by) <= _BALANCE_HALF_WINDOW_M)
           & (pz[pos] >= (centre[:, 2] - PAD_HALF_LENGTH_M)[owner]))
    first = np.r_[0, np.cumsum(lens)[:-1]]
    y_lo = np.minimum.reduceat(np.where(inb, by, np.inf), first)
    y_hi = np.maximum.reduceat(np.where(inb, by, -np.inf), first)
    with np.errstate(invalid="ignore"):
        mid = np.abs(0.5 * (y_lo + y_hi))
    balance = 1.0 - np.clip(np.nan_to_num(mid, nan=0.0) / _BALANCE_HALF_WINDOW_M, 0.0, 1.0)
    clearance = np.clip(np.minimum(HALF_STROKE_M + r["xmin"], HALF_STROKE_M - r["xmax"])
                        / HALF_STROKE_M, 0.0, 1.0)
    fill = np.clip(r["area"] / (np.maximum(width, 1e-3) * 2.0 * PAD_HALF_WIDTH_M), 0.0, 1.0)
    depth_term = np.clip((np.minimum(centre[:, 2] + PAD_HALF_LENGTH_M, top[axis])
                          - (centre[:, 2] - PAD_HALF_LENGTH_M)) / (2.0 * PAD_HALF_LENGTH_M),
                         0.0, 1.0)
    half_view = max(p_WC[2] - table_z, 1e-3) * np.tan(np.deg2rad(float(fov_y_deg)) / 2.0)
    view = 1.0 - np.clip(np.hypot(centre[:, 0] - p_WC[0], centre[:, 1] - p_WC[1]) / half_view,
                         0.0, 1.0)
    terms = {"antipodal": antipodal, "centring": centring, "balance": balance,
             "clearance": clearance,
             "fill": fill, "depth": depth_term, "view": view}
    score = sum(getattr(weights, k) * terms[k] for k in SCORE_TERMS)
    order = np.argsort(-score, kind="stable")
    yaw_deg = np.mod(np.rad2deg(yaw), 360.0)
    theta = np.mod(yaw_deg, 180.0)
    theta = np.where(theta >= 180.0, 0.0, theta)  # mod of a tiny negative can give 180
    # Reported x_G is at theta: list the contacts along it (-x_G side first).
    flip = (yaw_deg >= 180.0) & (yaw_deg < 360.0)
    c0, c1 = np.where(flip[:, None], c1, c0), np.where(flip[:, None], c0, c1)
    n0, n1 = np.where(flip[:, None], n1, n0), np.where(flip[:, None], n0, n1)
    return done(DetectedGrasps(
        xy_theta=np.column_stack([centre[:, :2], theta])[order],
        z=centre[order, 2],
        width=width[order],
        score=score[order],
        contacts=np.stack([c0, c1], axis=1)[order],
        contact_normals=np.stack([n0, n1], axis=1)[order],
        terms={k: v_[order] for k, v_ in terms.items()},
    ))


def best_grasp(depth, *, fov_y_deg: float, X_WC, rng: np.random.Generator,
               **kwargs) -> Grasp | None:
    """The top detection of `detect_grasps` (same arguments), or None."""
    return detect_grasps(depth, fov_y_deg=fov_y_deg, X_WC=X_WC, rng=rng, **kwargs).best()
