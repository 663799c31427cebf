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

Pipeline (`detect_grasps`; its stages live beside it: the point cloud in
`gpd_geometric_cloud`, the candidates and their geometric tests in
`gpd_geometric_hands`, the view and occlusion tests in `gpd_geometric_view`, the score
in `gpd_geometric_score`, the results in `gpd_geometric_results`, the argument checks
in `gpd_geometric_checks`):

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
from dataclasses import dataclass

import numpy as np

from drake_grasp.policies.gpd_geometric_checks import (
    _check_pose,
    _check_rng,
    _finite,
    _positive_int,
)
from drake_grasp.policies.gpd_geometric_cloud import (
    DEFAULT_MAX_DEPTH_M,
    DEFAULT_TABLE_MARGIN_M,
    organized_points,
)
from drake_grasp.policies.gpd_geometric_hands import (
    HALF_STROKE_M,
    closing_contacts,
    collision_free_heights,
    first_closing_directions,
    object_points,
    sample_neighbourhoods,
    survivor_poses,
    sweep_hands,
)
from drake_grasp.policies.gpd_geometric_results import DetectedGrasps, Grasp, ScoreWeights
from drake_grasp.policies.gpd_geometric_score import score_terms, sorted_detections
from drake_grasp.policies.gpd_geometric_view import view_and_occlusion

DEFAULT_DEPTHS_M = (0.0, 0.01, 0.02)
STAT_KEYS = ("points", "samples", "hands", "collision_free", "closing_region", "antipodal",
             "in_view", "visible")


@dataclass(frozen=True)
class _DetectionParams:
    """`detect_grasps`'s checked arguments (see its docstring)."""

    mu: float
    S_max: int
    K: int
    dep: np.ndarray
    table_z: float
    table_margin_m: float
    min_points_between: int
    min_width_m: float
    tol: float
    margin: float
    step_threshold_m: float
    occ_tol: float
    weights: ScoreWeights
    far: float


def _detection_params(rng, mu, num_samples, num_rotations, depths, table_z, table_margin_m,
                      min_points_between, min_width_m, contact_tolerance_m, finger_margin_m,
                      step_threshold_m, occlusion_tolerance_m, weights, max_depth_m,
                      stats) -> _DetectionParams:
    """Checks `detect_grasps`'s arguments in order, the first bad one named in a
    ValueError; the depths come sorted and unique."""
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
    return _DetectionParams(mu, S_max, K, dep, table_z, table_margin_m, min_points_between,
                            min_width_m, tol, margin, step_threshold_m, occ_tol, weights, far)


def detect_grasps(depth, *, fov_y_deg: float, X_WC, rng: np.random.Generator, mu: float = 0.5,
                  num_samples: int = 200, num_rotations: int = 8, depths=DEFAULT_DEPTHS_M,
                  table_z: float = 0.0, table_margin_m: float = DEFAULT_TABLE_MARGIN_M,
                  max_depth_m: float = DEFAULT_MAX_DEPTH_M, min_points_between: int = 5,
                  min_width_m: float = 0.005, contact_tolerance_m: float = 0.002,
                  finger_margin_m: float = 0.004, step_threshold_m: float = 0.008,
                  occlusion_check: bool = False, occlusion_tolerance_m: float = 0.003,
                  weights: ScoreWeights | None = None, stats: dict | None = None
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
    p = _detection_params(rng, mu, num_samples, num_rotations, depths, table_z, table_margin_m,
                          min_points_between, min_width_m, contact_tolerance_m,
                          finger_margin_m, step_threshold_m, occlusion_tolerance_m, weights,
                          max_depth_m, stats)
    st_ = {k: 0 for k in STAT_KEYS}

    def done(result: DetectedGrasps) -> DetectedGrasps:
        if stats is not None:
            stats.update(st_, seconds=time.perf_counter() - t_start)
        return result

    # 1-2. Point cloud, table removed.
    cloud = organized_points(depth, fov_y_deg=fov_y_deg, X_WC=X_WC, max_depth_m=p.far)
    X = _check_pose(X_WC)
    R_WC, p_WC = X[:3, :3], X[:3, 3]
    floor = p.table_z + p.table_margin_m
    obj = cloud.valid & (cloud.points[..., 2] >= floor)
    if not obj.any():
        return done(DetectedGrasps.empty())
    pts = object_points(cloud, obj, R_WC, p.step_threshold_m, p.far, st_)

    # 3. Samples, their hands' first closing directions, the hands swept over them.
    nb = sample_neighbourhoods(pts, p.S_max, rng, st_)
    S = nb.S
    base = first_closing_directions(pts.Nc, nb)
    sw = sweep_hands(nb, base, p.K, pts.px_wall, p.margin)

    # 4. Collision, closing region and contacts, view and occlusion.
    zc, free, top = collision_free_heights(sw, p.dep, floor, p.K, S, st_)
    r = closing_contacts(nb, sw, pts, zc, free, len(p.dep),
                         min_points_between=p.min_points_between, min_width_m=p.min_width_m,
                         tol=p.tol, mu=p.mu, st_=st_)
    if r is None:
        return done(DetectedGrasps.empty())
    yaw, centre = survivor_poses(r, S, base, sw.phase, nb.C, zc)
    keep = view_and_occlusion(yaw, centre, R_WC, p_WC, cloud, obj, fov_y_deg,
                              occlusion_check=occlusion_check, occ_tol=p.occ_tol, st_=st_)
    r = {k: v_[keep] for k, v_ in r.items()}
    axis, yaw, centre = r["axis"], yaw[keep], centre[keep]
    if len(axis) == 0:
        return done(DetectedGrasps.empty())

    # 5. Score, best first.
    width = r["xmax"] - r["xmin"]
    terms = score_terms(r, axis, centre, width, top, S=S, nb=nb, sw=sw, pts=pts, mu=p.mu,
                        p_WC=p_WC, table_z=p.table_z, fov_y_deg=fov_y_deg)
    return done(sorted_detections(r, yaw, centre, width, terms, p.weights))


def best_grasp(depth, *, fov_y_deg: float, X_WC, rng: np.random.Generator,
               **kwargs) -> Grasp | None:
    """The top detection of `detect_grasps` (same arguments), or None."""
    return detect_grasps(depth, fov_y_deg=fov_y_deg, X_WC=X_WC, rng=rng, **kwargs).best()
