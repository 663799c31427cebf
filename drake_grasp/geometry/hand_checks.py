"""The analytic tests of hands against a scene's surface samples (pure numpy).

Owns `_evaluate`, which tests S approach axes x K rotations x D depths at once: the
fully open hand swept in along its approach touches no sample and clears the table,
object surface lies between the pads, both pads touch one object, and the contact
patches pass the force-closure and torque tests (`contact_physics`). On top of it:
`evaluate_hands` (the same tests on any point set, e.g. a camera's cloud) with
`evaluation_poses`, and `check_grasp_poses` / `GraspCheck` for explicit poses.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from drake_grasp.geometry.contact_physics import _gravity_torque_ratio, force_closure
from drake_grasp.geometry.hand_model import (
    FINGER_OUTER_X_M,
    FINGERTIP_Z_M,
    HAND_FOOTPRINT_RADIUS_M,
    HOUSING_FRONT_Z_M,
    HOUSING_RADIUS_M,
    PAD_HALF_LENGTH_M,
    PAD_HALF_WIDTH_M,
    PALM_FRONT_Z_M,
    PALM_HALF_X_M,
    PALM_HALF_Y_M,
    STRIP_RADIUS_M,
    STROKE_M,
    TABLE_TOP_Z_M,
)
from drake_grasp.geometry.point_grid import (_group_max, _group_min, _in_hand_frame,
                                             _neighbour_pairs, _Scene)
from drake_grasp.geometry.scene_samples import ObjectMasses, ScenePoints, _positive, _positive_int


@dataclass(frozen=True)
class _Evaluation:
    """Per-candidate results, each of shape (S, K, D) (plus (2, 3) for contacts)."""

    centers: np.ndarray  # (S, K, D, 3)
    x_axis: np.ndarray  # (S, K, 3)
    collision_free: np.ndarray
    num_points_between: np.ndarray
    width: np.ndarray
    object_index: np.ndarray
    contacts: np.ndarray
    contact_normals: np.ndarray
    force_closure: np.ndarray
    torque_ratio: np.ndarray
    valid: np.ndarray



@dataclass(frozen=True)
class _HandFrames:
    """The A = S * K hands along S axes (hand g = s * K + k), each at D depths."""

    S: int
    D: int
    depth_arr: np.ndarray  # (D,) depths below the local top; [0] for explicit poses
    A: int
    n: int  # A * D
    s_of: np.ndarray  # (A,) the axis of each hand
    e2: np.ndarray  # (S, 3) approach x basis_x
    x_axis: np.ndarray  # (A, 3) closing direction
    y_axis: np.ndarray  # (A, 3)
    z_axis: np.ndarray  # (A, 3) approach
    w_max: float  # furthest offset along an axis that can touch the hand


def _hand_frames(origins: np.ndarray, approach: np.ndarray, basis_x: np.ndarray,
                 base_angle: np.ndarray, K: int, depths: np.ndarray | None) -> _HandFrames:
    """The grasp frames of all hands and how far ahead of the origins they reach."""
    S = len(origins)
    D = 1 if depths is None else len(depths)
    depth_arr = np.zeros(1) if depths is None else np.asarray(depths, dtype=float)
    A = S * K
    n = A * D
    s_of = np.repeat(np.arange(S), K)
    e2 = np.cross(approach, basis_x)
    angles = (base_angle[:, None] + np.pi * np.arange(K)[None, :] / K).ravel()
    cos_a, sin_a = np.cos(angles), np.sin(angles)
    # x_G = cos e1 + sin e2, y_G = z_G x x_G (right-handed grasp frame).
    x_axis = cos_a[:, None] * basis_x[s_of] + sin_a[:, None] * e2[s_of]
    z_axis = approach[s_of]
    y_axis = np.cross(z_axis, x_axis)
    # No point further ahead than the deepest fingertip can touch the hand. The local
    # top is at w <= ~0 (the origin is a surface point on the axis); a few mm of slack
    # for the sampling.
    w_max = (0.0 if depths is None else max(0.0, float(depth_arr.max())) + 0.005) + FINGERTIP_Z_M
    return _HandFrames(S, D, depth_arr, A, n, s_of, e2, x_axis, y_axis, z_axis, w_max)


def _collision_limits(axis, u, v, w_pair, base_angle: np.ndarray, K: int,
                      hf: _HandFrames) -> tuple[np.ndarray, np.ndarray]:
    """Per hand (A,): the largest centre offset along the approach that the coarse
    samples near its axis allow, and the local top (the coarse strip point furthest
    back), from the (axis, point) pairs of `_neighbour_pairs`."""
    S, A, s_of = hf.S, hf.A, hf.s_of
    x, y, g, pair = _in_hand_frame(axis, u, v, base_angle, K, PALM_HALF_Y_M)
    w = w_pair[pair]
    # Every bound is the largest centre offset along the approach that a point
    # allows (that hand part's front must stay behind it). The housing's outline is
    # round: one bound per axis for all rotations.
    inside = u * u + v * v <= HOUSING_RADIUS_M**2
    limit_s = _group_min(w_pair[inside] - HOUSING_FRONT_Z_M, axis[inside], S)
    ax = np.abs(x)
    in_pad_y = np.abs(y) <= PAD_HALF_WIDTH_M
    finger = in_pad_y & (ax > 0.5 * STROKE_M) & (ax <= FINGER_OUTER_X_M)
    palm = ax <= PALM_HALF_X_M
    bound = np.where(finger, w - FINGERTIP_Z_M, np.where(palm, w - PALM_FRONT_Z_M, np.inf))
    limit = np.minimum(_group_min(bound, g, A), limit_s[s_of])
    # Local top from the coarse strip points (only the depth reference).
    strip = in_pad_y & (ax <= 0.5 * STROKE_M)
    top = _group_min(w[strip], g[strip], A)
    return limit, top


def _collision_free(origins: np.ndarray, hf: _HandFrames, depths: np.ndarray | None,
                    top: np.ndarray, limit: np.ndarray, table_z: float,
                    table_clearance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre offsets along the axes (A, D) and which of those hands reach their pose
    without touching a sample and stay above the table (A, D)."""
    A, s_of, x_axis, y_axis, z_axis = hf.A, hf.s_of, hf.x_axis, hf.y_axis, hf.z_axis
    # Centre offsets along the axis, (A, D).
    if depths is None:
        shift = np.zeros((A, 1))
    else:
        shift = top[:, None] + hf.depth_arr[None, :]
    # Lowest point of the hand: a fingertip corner or a palm corner.
    tip = (z_axis[:, 2] * FINGERTIP_Z_M - FINGER_OUTER_X_M * np.abs(x_axis[:, 2])
           - PAD_HALF_WIDTH_M * np.abs(y_axis[:, 2]))
    palm_low = (z_axis[:, 2] * PALM_FRONT_Z_M - PALM_HALF_X_M * np.abs(x_axis[:, 2])
                - PALM_HALF_Y_M * np.abs(y_axis[:, 2]))
    with np.errstate(invalid="ignore"):
        center_z = origins[s_of, 2][:, None] + shift * z_axis[:, 2][:, None]
        lowest = center_z + np.minimum(tip, palm_low)[:, None]
        free = (np.isfinite(shift) & (shift <= limit[:, None] + 1e-12)
                & (lowest >= table_z + table_clearance_m))
    return shift, free


def _closing_region(scene: _Scene, origins: np.ndarray, approach: np.ndarray,
                    basis_x: np.ndarray, base_angle: np.ndarray, K: int, hf: _HandFrames,
                    free: np.ndarray, top: np.ndarray, depths: np.ndarray | None):
    """The fine samples between the pads of the collision-free hands at each depth.

    Returns:
        Per (sample, hand at a depth) entry: the fine sample's index, the hand id
        g * D + d, and the sample's x, y (float64) in the hand frame and its offset w
        along the axis.
    """
    S, D, depth_arr, s_of, e2 = hf.S, hf.D, hf.depth_arr, hf.s_of, hf.e2
    any_free = free.any(axis=1)
    seeds_free = np.zeros(S, dtype=bool)
    seeds_free[s_of[any_free]] = True
    sel = np.flatnonzero(seeds_free)
    f_axis, f_point, f_u, f_v, f_w = _neighbour_pairs(scene.fine_grid, origins[sel], approach[sel],
                                                      basis_x[sel], e2[sel], STRIP_RADIUS_M, hf.w_max)
    f_axis = sel[f_axis]
    xs, ys, gs, f_pair = _in_hand_frame(f_axis, f_u, f_v, base_angle, K, PAD_HALF_WIDTH_M,
                                        hands=any_free.reshape(S, K))
    keep = np.abs(xs) <= 0.5 * STROKE_M
    f_pair = f_pair[keep]
    xs, ys, ws, gs, ps = xs[keep], ys[keep], f_w[f_pair], gs[keep], f_point[f_pair]
    # Within the pads' length: |w - shift| <= 19 mm, shift = top + depth.
    rel_top = ws - (0.0 if depths is None else top[gs])
    free_t = np.ascontiguousarray(free.T)
    q_parts, id_parts = [], []
    for d in range(D):  # D is a handful of depths
        qd = np.flatnonzero((np.abs(rel_top - depth_arr[d]) <= PAD_HALF_LENGTH_M) & free_t[d][gs])
        q_parts.append(qd)
        id_parts.append(gs[qd].astype(np.int64) * D + d)
    q = np.concatenate(q_parts)
    ids = np.concatenate(id_parts)
    xq = xs[q]
    yq = ys[q].astype(np.float64)
    wq = ws[q]
    return ps[q], ids, xq, yq, wq


def _contact_patches(fs: ScenePoints, pts, ids, xq, yq, wq, xmin, xmax, n: int,
                     contact_tolerance_m: float):
    """Contact patches: what the pads touch first (within the pads' compliance).

    Returns:
        Per hand at a depth (n): the patches' centroids (n, 2, 3) and summed normals
        (n, 2, 3), their spread (n, 2), and the lowest and highest object index that
        either patch touches (n,) each.
    """
    # Their centroids and mean normals. Both pads must touch one and the same object.
    objs = fs.object_index[pts].astype(float)
    contacts = np.zeros((n, 2, 3))
    normals = np.zeros((n, 2, 3))
    obj_lo = np.full(n, np.inf)
    obj_hi = np.full(n, -np.inf)
    # Patch spread in the pad's plane (y_G, z_G): the RMS distance of the patch samples
    # from their centroid, the lever arm of the pad's torsional friction.
    spread = np.zeros((n, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        for side, patch in enumerate((xq <= xmin[ids] + contact_tolerance_m,
                                      xq >= xmax[ids] - contact_tolerance_m)):
            i_sel = ids[patch]
            num = np.bincount(i_sel, minlength=n)
            P_sel, N_sel = fs.points[pts[patch]], fs.normals[pts[patch]]
            for j in range(3):
                contacts[:, side, j] = np.bincount(i_sel, P_sel[:, j], minlength=n) / num
                normals[:, side, j] = np.bincount(i_sel, N_sel[:, j], minlength=n)
            var = 0.0
            for c in (yq[patch], wq[patch]):
                mean = np.bincount(i_sel, c, minlength=n) / num
                var = var + np.bincount(i_sel, c * c, minlength=n) / num - mean * mean
            spread[:, side] = np.sqrt(np.clip(var, 0.0, None))
            obj_lo = np.minimum(obj_lo, _group_min(objs[patch], i_sel, n))
            obj_hi = np.maximum(obj_hi, _group_max(objs[patch], i_sel, n))
    return contacts, normals, spread, obj_lo, obj_hi


def _evaluate(
    scene: _Scene,
    origins: np.ndarray,
    approach: np.ndarray,
    basis_x: np.ndarray,
    base_angle: np.ndarray,
    K: int,
    depths: np.ndarray | None,
    *,
    mu: float,
    min_width_m: float,
    max_width_m: float,
    min_points_between: int,
    contact_tolerance_m: float,
    table_z: float,
    table_clearance_m: float,
    timings: dict | None,
    objects: ObjectMasses | None = None,
    grip_force_n: float = 60.0,
    max_torque_ratio: float | None = None,
) -> _Evaluation:
    """Tests hands along S axes x K rotations x D depths against the scene points.

    Hands are numbered g = s * K + k, hands at a depth g * D + d. Offsets along an
    axis are `w` (positive along the approach, from the axis origin). `depths` None:
    the centre is the origin itself (D = 1; explicit poses). Otherwise it lies
    `depths[d]` beyond the local top (the strip point furthest back).
    """
    t0 = time.perf_counter()
    hf = _hand_frames(origins, approach, basis_x, base_angle, K, depths)
    S, D, n, s_of = hf.S, hf.D, hf.n, hf.s_of

    # --- Collisions (coarse samples) --------------------------------------------
    axis, _, u, v, w_pair = _neighbour_pairs(scene.coarse_grid, origins, approach, basis_x, hf.e2,
                                             HAND_FOOTPRINT_RADIUS_M, hf.w_max)
    t1 = time.perf_counter()
    limit, top = _collision_limits(axis, u, v, w_pair, base_angle, K, hf)
    t2 = time.perf_counter()
    shift, free = _collision_free(origins, hf, depths, top, limit, table_z, table_clearance_m)

    # --- Closing region (fine samples), collision-free hands only ------------------
    pts, ids, xq, yq, wq = _closing_region(scene, origins, approach, basis_x, base_angle, K, hf,
                                           free, top, depths)
    count = np.bincount(ids, minlength=n)
    xmin = _group_min(xq, ids, n)
    xmax = _group_max(xq, ids, n)
    with np.errstate(invalid="ignore"):
        width = xmax - xmin
    contacts, normals, spread, obj_lo, obj_hi = _contact_patches(
        scene.fine, pts, ids, xq, yq, wq, xmin, xmax, n, contact_tolerance_m)
    with np.errstate(invalid="ignore", divide="ignore"):
        one_object = obj_lo == obj_hi
        object_index = np.where(one_object, obj_lo, -1).astype(np.int64)
        width_ok = (count >= min_points_between) & (width >= min_width_m) & (width <= max_width_m)
        nrm = np.linalg.norm(normals, axis=-1, keepdims=True)
        unit_normals = np.where(nrm > 0, normals / nrm, 0.0)
    fc = force_closure(contacts[:, 0], normals[:, 0], contacts[:, 1], normals[:, 1], mu=mu)
    torque_ratio = _gravity_torque_ratio(contacts, spread, object_index, objects, grip_force_n)
    free = free.ravel()
    valid = free & width_ok & one_object & fc
    if max_torque_ratio is not None:
        valid &= torque_ratio <= max_torque_ratio
    centers = origins[s_of][:, None, :] + shift[..., None] * hf.z_axis[:, None, :]
    t3 = time.perf_counter()
    if timings is not None:
        stages = (("neighbours", t1 - t0), ("collision", t2 - t1),
                  ("closing_and_force_closure", t3 - t2))
        for key, dt in stages:
            timings[key] = timings.get(key, 0.0) + dt
    shape = (S, K, D)
    return _Evaluation(
        centers=centers.reshape(shape + (3,)),
        x_axis=hf.x_axis.reshape(S, K, 3),
        collision_free=free.reshape(shape),
        num_points_between=count.reshape(shape),
        width=np.where(count > 0, width, np.nan).reshape(shape),
        object_index=object_index.reshape(shape),
        contacts=contacts.reshape(shape + (2, 3)),
        contact_normals=unit_normals.reshape(shape + (2, 3)),
        force_closure=fc.reshape(shape),
        torque_ratio=torque_ratio.reshape(shape),
        valid=valid.reshape(shape),
    )


def evaluate_hands(fine: ScenePoints, coarse: ScenePoints, origins, approach, basis_x, base_angle,
                   num_rotations: int, depths, *, mu: float = 0.5, min_width_m: float = 0.005,
                   min_points_between: int = 5, contact_tolerance_m: float = 0.002,
                   table_z: float = TABLE_TOP_Z_M, table_clearance_m: float = 0.002):
    """The candidate tests of `find_grasps_in_meshes` on any point set (e.g. a point
    cloud seen by a camera, where `drake_grasp.policies.gpd` uses them as GPD's geometric
    filters): S axes through `origins` along `approach` (S, 3), `num_rotations` closing
    directions from `base_angle` (S,) measured from `basis_x` (S, 3) toward
    approach x basis_x, at `depths` below the local top.

    Returns:
        Per-hand arrays of shape (S, K, D): ``collision_free``, ``num_points_between``,
        ``width``, ``object_index``, ``force_closure``, ``valid``, the hands'
        ``centers`` (S, K, D, 3) and closing axes ``x_axis`` (S, K, 3).
    """
    origins = np.asarray(origins, dtype=float).reshape(-1, 3)
    if len(origins) == 0 or len(fine) == 0 or len(coarse) == 0:
        raise ValueError("evaluate_hands: expected at least one axis and non-empty point sets")
    return _evaluate(
        _Scene.build(fine, coarse), origins, np.asarray(approach, float),
        np.asarray(basis_x, float), np.asarray(base_angle, float),
        _positive_int("num_rotations", num_rotations), np.atleast_1d(np.asarray(depths, float)),
        mu=_positive("mu", mu, allow_zero=True),
        min_width_m=_positive("min_width_m", min_width_m, allow_zero=True), max_width_m=STROKE_M,
        min_points_between=_positive_int("min_points_between", min_points_between),
        contact_tolerance_m=_positive("contact_tolerance_m", contact_tolerance_m, allow_zero=True),
        table_z=float(table_z), table_clearance_m=float(table_clearance_m), timings=None)


@dataclass(frozen=True)
class GraspCheck:
    """Per-pose outcome of `check_grasp_poses`, every array of length N.

    Attributes:
        collision_free: The hand, fully open, reaches the pose along its approach
            axis without any part touching an object, and stays above the table.
        num_points_between: Object samples in the closing region (the box the pads
            sweep when closing: |x| <= 42.5 mm, |y| <= 11 mm, |z| <= 19 mm in G).
        width: What the pads close to: the extent of those points along x_G [m]
            (NaN when there are none).
        object_index: The one object both pads touch, else -1.
        contacts: (N, 2, 3) centroids of the contact patches (left pad, right pad).
        contact_normals: (N, 2, 3) their mean outward surface normals.
        force_closure: The contacts are in force closure.
        torque_ratio: Gravity's torque about the contact axis over F (r1 + r2), the
            friction coefficient the pads' torsional friction needs to hold the
            object (0 when no `objects` were given; see `_gravity_torque_ratio`).
        valid: All of the above (and torque_ratio <= max_torque_ratio when given):
            a ground-truth grasp.
    """

    collision_free: np.ndarray
    num_points_between: np.ndarray
    width: np.ndarray
    object_index: np.ndarray
    contacts: np.ndarray
    contact_normals: np.ndarray
    force_closure: np.ndarray
    torque_ratio: np.ndarray
    valid: np.ndarray


def check_grasp_poses(
    poses,
    scene: ScenePoints,
    *,
    collision_points: ScenePoints | None = None,
    mu: float = 0.5,
    min_width_m: float = 0.005,
    min_points_between: int = 5,
    contact_tolerance_m: float = 0.002,
    table_z: float = TABLE_TOP_Z_M,
    table_clearance_m: float = 0.002,
    objects: ObjectMasses | None = None,
    grip_force_n: float = 60.0,
    max_torque_ratio: float | None = None,
) -> GraspCheck:
    """Runs every grasp test on explicit grasp-frame poses (e.g. a controller's final
    pose, or hand-made poses in tests). Same tests and defaults as `find_grasps`.

    Args:
        poses: (N, 4, 4) world poses X_WG of the grasp frame.
        scene: Surface samples of the scene (`sample_scene_points`).
        collision_points: Samples for the collision test (default: `scene`).
        mu, min_width_m, min_points_between, contact_tolerance_m, table_z,
            table_clearance_m, objects, grip_force_n, max_torque_ratio: See
            `find_grasps_in_meshes`.
    """
    X = np.asarray(poses, dtype=float)
    if X.shape == (4, 4):
        X = X[None]
    if X.ndim != 3 or X.shape[1:] != (4, 4):
        raise ValueError(
            f"poses: expected an (N, 4, 4) array of transforms, got shape {np.shape(poses)}")
    R = X[:, :3, :3]
    if not (np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-6)
            and np.all(np.linalg.det(R) > 0)):
        raise ValueError("poses: the rotation blocks must be right-handed orthonormal (det +1)")
    N = len(X)
    collision_points = scene if collision_points is None else collision_points
    if N == 0 or len(scene) == 0 or len(collision_points) == 0:
        collision = np.ones(N, dtype=bool)
        if N:
            lowest = _lowest_hand_z(X)
            collision = lowest >= table_z + table_clearance_m
        z = np.zeros(N, dtype=bool)
        return GraspCheck(collision, np.zeros(N, dtype=np.int64), np.full(N, np.nan),
                          np.full(N, -1, dtype=np.int64), np.zeros((N, 2, 3)),
                          np.zeros((N, 2, 3)), z, np.full(N, np.inf), z)
    # Each pose is its own axis (K = 1, angle 0 about x_G) with the centre at the origin.
    ev = _evaluate(
        _Scene.build(scene, collision_points), X[:, :3, 3], R[:, :, 2], R[:, :, 0], np.zeros(N), 1,
        None, mu=_positive("mu", mu, allow_zero=True),
        min_width_m=_positive("min_width_m", min_width_m, allow_zero=True), max_width_m=STROKE_M,
        min_points_between=_positive_int("min_points_between", min_points_between),
        contact_tolerance_m=_positive("contact_tolerance_m", contact_tolerance_m, allow_zero=True),
        table_z=float(table_z), table_clearance_m=float(table_clearance_m), timings=None,
        objects=objects, grip_force_n=_positive("grip_force_n", grip_force_n),
        max_torque_ratio=max_torque_ratio,
    )
    f = lambda a: a[:, 0, 0]  # noqa: E731
    return GraspCheck(f(ev.collision_free), f(ev.num_points_between), f(ev.width),
                      f(ev.object_index), f(ev.contacts), f(ev.contact_normals),
                      f(ev.force_closure), f(ev.torque_ratio), f(ev.valid))


def _lowest_hand_z(X: np.ndarray) -> np.ndarray:
    R = X[:, :3, :3]
    xz, yz, zz = R[:, 2, 0], R[:, 2, 1], R[:, 2, 2]
    tip = zz * FINGERTIP_Z_M - FINGER_OUTER_X_M * np.abs(xz) - PAD_HALF_WIDTH_M * np.abs(yz)
    palm = zz * PALM_FRONT_Z_M - PALM_HALF_X_M * np.abs(xz) - PALM_HALF_Y_M * np.abs(yz)
    return X[:, 2, 3] + np.minimum(tip, palm)



def evaluation_poses(ev, approach: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, tuple]:
    """The grasp-frame poses X_WG (N, 4, 4) of the hands of an evaluation (`evaluate_hands`)
    where `mask` (S, K, D) is true, and their indices (s, k, d)."""
    s, k, d = np.nonzero(mask)
    x_axis = ev.x_axis[s, k]
    z_axis = approach[s]
    poses = np.zeros((len(s), 4, 4))
    poses[:, :3, 0] = x_axis
    poses[:, :3, 1] = np.cross(z_axis, x_axis)
    poses[:, :3, 2] = z_axis
    poses[:, :3, 3] = ev.centers[s, k, d]
    poses[:, 3, 3] = 1.0
    return poses, (s, k, d)
