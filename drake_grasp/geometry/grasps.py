"""Grasp geometry for the 2F-85 parallel-jaw gripper (pure numpy / trimesh).

Conventions: the grasp frame G sits at the centre between the two pads; its z axis
is the approach direction and its x axis the closing direction. A top-down grasp has
z_G = -z_W and is described by (x, y, z, yaw) with R_WG = Rz(yaw) Rx(pi).

Contents:
    * `plan_topdown_grasp`, `points_between_pads`: the scripted single-object grasp.
    * Ground-truth grasps of a scene, as the paper labels its training data
      ("Generating training data"): `find_grasps` / `find_grasps_in_meshes` sample
      GPD-style hand candidates (`sample_grasp_candidates`), keep the collision-free
      ones with object surface between the fingers, and test the contacts for force
      closure (`force_closure`); `check_grasp_poses` runs the same tests on given
      poses. Results come as a `GraspSet`.
    * The paper's label ("CNN Model"): `grasp_distance` and
      `distance_to_nearest_grasp`, Euclidean in (x, y, 0.001 m/deg * theta) with
      theta taken modulo 180 degrees.
"""

from __future__ import annotations

import time
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


# ============================================================================
# Ground-truth grasps of a whole scene (the paper's "Generating training data"):
# GPD-style hand candidates (ten Pas & Platt, ISRR 2015) filtered for collisions and
# for object surface between the fingers, then a two-contact force-closure test
# (Nguyen 1986); plus the paper's distance-to-nearest-grasp metric.
#
# Hand model (models/robotiq_2f85/robotiq_2f85.urdf, README.md), in the grasp frame G
# (0.135 m in front of robotiq_base; z_G approach, x_G closing), fingers fully open:
#   pads          |x| in [0.0425, 0.0485], |y| <= 0.011, z in [-0.019, 0.019]
#   finger bodies |x| in [0.0485, 0.0585], |y| <= 0.011, z in [-0.030, 0.019]
#   palm          |x| <= 0.065, |y| <= 0.015,           z in [-0.041, -0.025]
#   housing       cylinder r 0.04,                      z in [-0.121, -0.031]
# The hand reaches a grasp by moving along its approach axis (the controller descends
# straight down), so the collision test uses the volume each part sweeps on the way in:
# every part is extended backwards (along -z_G) without limit. That also covers the
# coupling, the flange and the wrist above the housing.
# ============================================================================

GRASP_FRAME_IN_BASE_M = 0.135
PAD_THICKNESS_M = 0.006
FINGER_BODY_THICKNESS_M = 0.010
# Outer face of a fully open finger (pad + finger body) along x_G.
FINGER_OUTER_X_M = 0.5 * STROKE_M + PAD_THICKNESS_M + FINGER_BODY_THICKNESS_M
# Pads and finger bodies both end at z = 0.154 in robotiq_base: the fingertips.
FINGERTIP_Z_M = PAD_HALF_LENGTH_M
PALM_HALF_X_M = 0.065
PALM_HALF_Y_M = 0.015
PALM_FRONT_Z_M = 0.110 - GRASP_FRAME_IN_BASE_M  # -0.025
HOUSING_RADIUS_M = 0.04
HOUSING_FRONT_Z_M = 0.104 - GRASP_FRAME_IN_BASE_M  # -0.031
# Radius of the hand's outline seen along the approach axis (the palm's corners) and
# of the closing region's outline (the pads' sweep).
HAND_FOOTPRINT_RADIUS_M = float(np.hypot(PALM_HALF_X_M, PALM_HALF_Y_M))
STRIP_RADIUS_M = float(np.hypot(0.5 * STROKE_M, PAD_HALF_WIDTH_M))

# Top of the 2 mm sheet the objects lie on (the table top is z = 0).
TABLE_TOP_Z_M = 0.002
# Paper: "weighting the angular component (by 0.001 meter/degree)".
ANGLE_WEIGHT_M_PER_DEG = 0.001

DEFAULT_DEPTHS_M = (0.0, 0.01, 0.02)


def _check_rng(rng) -> None:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")


def _positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    v = float(value)
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        expected = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name}: expected a finite number {expected}, got {value!r}")
    return v


def _positive_int(name: str, value: int) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
    return int(value)


# ----------------------------------------------------------------------------
# Scene geometry.


def _quat_wxyz_to_matrix(quat_wxyz) -> np.ndarray:
    """Rotation matrix of a (w, x, y, z) quaternion (normalised first)."""
    q = np.asarray(quat_wxyz, dtype=float)
    n = np.linalg.norm(q) if q.shape == (4,) else 0.0
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"quat_wxyz: expected 4 finite numbers, not all zero, got {quat_wxyz!r}")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def scene_meshes(spec, library) -> list:
    """World-frame surface meshes (`visual.obj`) of a scene's objects, in spec order.

    Plain numpy pose conversion (the spec's xyz and quat_wxyz), so no Drake import.

    Args:
        spec: A `drake_grasp.world.scene.SceneSpec`.
        library: The `ObjectLibrary` the spec's object ids come from.

    Returns:
        One `trimesh.Trimesh` per object; index i is `spec.objects[i]`.
    """
    import trimesh

    from drake_grasp.objects import visual_mesh

    meshes = []
    for placement in spec.objects:
        info = library.get(placement.object_id)
        local = visual_mesh(info)
        R = _quat_wxyz_to_matrix(placement.quat_wxyz)
        t = np.asarray(placement.xyz, dtype=float)
        meshes.append(trimesh.Trimesh(np.asarray(local.vertices) @ R.T + t,
                                      np.asarray(local.faces), process=False))
    return meshes


def _check_meshes(meshes) -> list:
    meshes = list(meshes)
    for i, m in enumerate(meshes):
        if not hasattr(m, "faces") or not hasattr(m, "area_faces") or len(m.faces) == 0:
            raise ValueError(f"meshes[{i}]: expected a trimesh.Trimesh with faces, got {m!r}")
    return meshes


def _sample_faces(meshes, count: int, rng: np.random.Generator, face_mask=None):
    """Area-weighted random surface points of several meshes.

    Returns:
        (points (count, 3), outward face normals (count, 3), mesh index (count,)).
    """
    areas = np.concatenate([np.asarray(m.area_faces, dtype=float) for m in meshes])
    normals = np.concatenate([np.asarray(m.face_normals, dtype=float) for m in meshes])
    owner = np.concatenate([np.full(len(m.faces), i) for i, m in enumerate(meshes)])
    tris = np.concatenate([np.asarray(m.triangles, dtype=float) for m in meshes])
    weights = areas if face_mask is None else areas * face_mask(normals)
    total = weights.sum()
    if count == 0 or total <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    cdf = np.cumsum(weights)
    face = np.minimum(np.searchsorted(cdf, rng.random(count) * cdf[-1], side="right"), len(cdf) - 1)
    # Uniform barycentric coordinates (the square-root trick).
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    a, b, c = 1.0 - s, s * (1.0 - r2), s * r2
    T = tris[face]
    points = a[:, None] * T[:, 0] + b[:, None] * T[:, 1] + c[:, None] * T[:, 2]
    return points, normals[face], owner[face].astype(np.int64)


@dataclass(frozen=True)
class ScenePoints:
    """Dense object surface samples of a scene, the geometry every test runs on.

    Attributes:
        points: (P, 3) world positions [m].
        normals: (P, 3) outward unit surface normals.
        object_index: (P,) which mesh / scene object each point lies on.
    """

    points: np.ndarray
    normals: np.ndarray
    object_index: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def sample_scene_points(
    meshes, rng: np.random.Generator, *, spacing_m: float = 0.003
) -> ScenePoints:
    """Area-weighted random surface samples, about one per `spacing_m`^2 of surface.

    Surface samples suffice for the swept-volume collision test: a hand part inside an
    object must have passed through its surface on the way in. The spacing bounds
    the error of the measured widths and of the collision test (the thinnest hand
    part, a 16 mm finger, cannot slip between samples 3 mm apart).

    Args:
        meshes: World-frame `trimesh.Trimesh` objects (outward normals).
        rng: Source of randomness.
        spacing_m: Mean distance between neighbouring samples [m].
    """
    _check_rng(rng)
    meshes = _check_meshes(meshes)
    spacing = _positive("spacing_m", spacing_m)
    if not meshes:
        return ScenePoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    area = sum(float(m.area) for m in meshes)
    count = int(np.ceil(area / spacing**2))
    return ScenePoints(*_sample_faces(meshes, count, rng))


# ----------------------------------------------------------------------------
# Candidates.


@dataclass(frozen=True)
class GraspCandidates:
    """Hand poses to test: approach axes through sampled surface points.

    Candidate (s, k, d) has its approach axis through `origins[s]` along
    `approach[s]`, its closing direction at angle `angles[s, k] = base_angle[s] +
    k * pi / K` about that axis from `basis_x[s]` (x_G = cos(angle) basis_x +
    sin(angle) (approach x basis_x)), and its centre `depths[d]` further along the
    axis than the highest object point between the pads (the local top). The centre
    is found only when the candidates are evaluated against the scene.

    Attributes:
        origins: (S, 3) sampled surface points [m].
        normals: (S, 3) surface normals at the origins.
        object_index: (S,) the mesh each origin lies on.
        approach: (S, 3) unit approach directions z_G.
        basis_x: (S, 3) unit vectors perpendicular to `approach` (x_G at angle 0).
        base_angle: (S,) angle of the first closing direction [rad].
        num_rotations: K, closing directions per axis, evenly spaced over 180 deg.
        depths: (D,) grasp-centre depths below the local top [m].
    """

    origins: np.ndarray
    normals: np.ndarray
    object_index: np.ndarray
    approach: np.ndarray
    basis_x: np.ndarray
    base_angle: np.ndarray
    num_rotations: int
    depths: np.ndarray

    @property
    def angles(self) -> np.ndarray:
        """(S, K) closing-direction angles about the approach axes [rad]."""
        K = self.num_rotations
        return self.base_angle[:, None] + np.pi * np.arange(K)[None, :] / K

    def __len__(self) -> int:
        return len(self.origins) * self.num_rotations * len(self.depths)


def _basis_perpendicular(approach: np.ndarray) -> np.ndarray:
    """Unit vectors perpendicular to each approach direction (world x made orthogonal;
    world y where the approach is nearly along x)."""
    ref = np.tile([1.0, 0.0, 0.0], (len(approach), 1))
    ref[np.abs(approach[:, 0]) > 0.9] = [0.0, 1.0, 0.0]
    e1 = ref - np.sum(ref * approach, axis=1, keepdims=True) * approach
    return e1 / np.linalg.norm(e1, axis=1, keepdims=True)


def sample_grasp_candidates(
    meshes,
    rng: np.random.Generator,
    *,
    num_samples: int = 400,
    num_rotations: int = 8,
    depths=DEFAULT_DEPTHS_M,
    approach_max_tilt_deg: float = 0.0,
) -> GraspCandidates:
    """GPD-style hand candidates from surface samples.

    Surface points are drawn with probability proportional to the area they show
    from above (face area x the normal's z; none on faces turned away), i.e.
    uniformly over the objects' silhouettes (stacked surfaces each count): every
    point of what a camera above sees is equally likely to be under the hand. (Plain
    area weighting wastes samples on
    side walls and undersides, whose axes duplicate those through the tops: it found
    ~30 % fewer grasps at the same cost.)

    Each sampled surface point gets one approach axis through it: straight down
    (-z_W), or tilted from it by an angle drawn uniformly over the spherical cap of
    half angle `approach_max_tilt_deg` (the controller of this project only moves in
    (x, y, theta) and descends vertically, hence the default 0). About each axis,
    `num_rotations` closing directions cover 180 degrees evenly (the same K offsets
    for every axis, so the evaluation rotates points with a K-entry table): the
    first along the surface normal projected onto the plane across the axis (the
    antipodal direction of a curved or sloped side), or a uniformly random one where
    the normal is within ~12 degrees of the axis (flat tops), so that the seeds
    together cover all angles.

    Args:
        meshes: World-frame surface meshes of the scene's objects.
        rng: Source of randomness.
        num_samples: Surface points (approach axes) S. The default 400 (x 8 x 3 =
            9600 hands) takes ~0.1 s per random scene; the distance labels it gives
            exceed those of a 10x denser search by ~4-7 mm on average where the true
            label is under 3 cm (800: ~3-5 mm at twice the time).
        num_rotations: Closing directions per axis K (8: 22.5 degrees apart; 6 or 12
            were worse per unit of time).
        depths: Grasp-centre depths below the local top [m] (several, D). 0 puts the
            pad centres level with the object's top, so the lower half of the 38 mm
            pads touches it; this lets flat objects (a 23 mm hammer) be grasped with
            the fingertips above the table.
        approach_max_tilt_deg: Largest angle between the approach and straight down.

    Raises:
        ValueError: a bad argument (named in the message).
    """
    _check_rng(rng)
    meshes = _check_meshes(meshes)
    S = _positive_int("num_samples", num_samples)
    K = _positive_int("num_rotations", num_rotations)
    depths = np.atleast_1d(np.asarray(depths, dtype=float))
    if depths.ndim != 1 or len(depths) == 0 or not np.all(np.isfinite(depths)):
        raise ValueError(
            f"depths: expected a non-empty 1-D sequence of finite numbers [m], got {depths!r}")
    tilt = float(approach_max_tilt_deg)
    if not 0.0 <= tilt < 90.0:
        raise ValueError(
            f"approach_max_tilt_deg: expected a value in [0, 90), got {approach_max_tilt_deg!r}")
    if not meshes:
        empty3 = np.zeros((0, 3))
        return GraspCandidates(empty3, empty3, np.zeros(0, dtype=np.int64), empty3, empty3,
                               np.zeros(0), K, depths)

    # Weighted by the area seen from above (area x n_z): uniform over the objects'
    # silhouettes, as the hand's camera sees them.
    origins, normals, owner = _sample_faces(
        meshes, S, rng, face_mask=lambda n: np.maximum(n[:, 2], 0.0))
    S = len(origins)
    # Uniform on the cap: cos(tilt) uniform in [cos(max), 1].
    cos_t = 1.0 - rng.random(S) * (1.0 - np.cos(np.deg2rad(tilt)))
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    phi = rng.uniform(0.0, 2.0 * np.pi, S)
    approach = -np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)
    e1 = _basis_perpendicular(approach)
    e2 = np.cross(approach, e1)
    n_along = np.sum(normals * approach, axis=1, keepdims=True)
    n_perp = normals - n_along * approach
    has_dir = np.linalg.norm(n_perp, axis=1) > 0.2
    base = np.where(has_dir,
                    np.arctan2(np.sum(n_perp * e2, axis=1), np.sum(n_perp * e1, axis=1)),
                    rng.uniform(0.0, np.pi, S))
    return GraspCandidates(origins, normals, owner, approach, e1, np.mod(base, np.pi), K, depths)


# ----------------------------------------------------------------------------
# Evaluation against the scene.


def force_closure(p1, n1, p2, n2, mu: float = 0.5) -> np.ndarray:
    """Two-contact force closure with Coulomb friction (Nguyen 1986), vectorised.

    Two point contacts with friction (or soft-finger contacts, whose torsional
    friction does not change the planar condition) are in force closure iff the line
    through them lies inside both friction cones: the angle between p2 - p1 and the
    inward normal -n1 at p1, and between p1 - p2 and -n2 at p2, is at most atan(mu).

    Args:
        p1, n1, p2, n2: (..., 3) contact points and outward surface normals
            (normals need not be unit length); broadcast against each other.
        mu: Friction coefficient (>= 0).

    Returns:
        Boolean array of the broadcast shape (without the last axis). Coincident
        contacts or zero normals give False.
    """
    mu = _positive("mu", mu, allow_zero=True)
    p1, n1, p2, n2 = (np.asarray(a, dtype=float) for a in (p1, n1, p2, n2))
    for name, a in (("p1", p1), ("n1", n1), ("p2", p2), ("n2", n2)):
        if a.ndim == 0 or a.shape[-1] != 3:
            raise ValueError(f"{name}: expected an array of shape (..., 3), got shape {a.shape}")
    line = p2 - p1
    dist = np.linalg.norm(line, axis=-1)
    l1 = np.linalg.norm(n1, axis=-1)
    l2 = np.linalg.norm(n2, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos1 = -np.sum(line * n1, axis=-1) / (dist * l1)
        cos2 = np.sum(line * n2, axis=-1) / (dist * l2)
    # cos(atan(mu)) = 1 / sqrt(1 + mu^2); a hair of slack so that exact cone edges pass.
    cos_cone = 1.0 / np.sqrt(1.0 + mu * mu) - 1e-12
    ok = (cos1 >= cos_cone) & (cos2 >= cos_cone) & (dist > 1e-9) & (l1 > 0) & (l2 > 0)
    return np.asarray(ok & np.isfinite(cos1) & np.isfinite(cos2))


def _group_min(values: np.ndarray, ids: np.ndarray, n: int) -> np.ndarray:
    """Per-group minimum of `values` by `ids` in [0, n); +inf for empty groups."""
    out = np.full(n, np.inf)
    # float64 values: ufunc.at is ~20x slower when it has to cast.
    np.minimum.at(out, ids, np.asarray(values, dtype=np.float64))
    return out


def _group_max(values: np.ndarray, ids: np.ndarray, n: int) -> np.ndarray:
    """Per-group maximum of `values` by `ids` in [0, n); -inf for empty groups."""
    out = np.full(n, -np.inf)
    np.maximum.at(out, ids, np.asarray(values, dtype=np.float64))
    return out


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
class _Grid:
    """Points bucketed into square cells of their xy: a flat, vectorisable neighbour
    index (scipy's ball queries return Python lists, slow to flatten at ~1e6 pairs)."""

    lo: np.ndarray  # (2,) corner of cell (0, 0)
    cell: float
    shape: tuple[int, int]
    order: np.ndarray  # point indices sorted by cell
    starts: np.ndarray  # per cell: first position in `order`
    counts: np.ndarray  # per cell: number of points
    xyz: tuple[np.ndarray, np.ndarray, np.ndarray]  # coordinates in `order`, contiguous

    @classmethod
    def build(cls, points: np.ndarray, cell: float) -> _Grid:
        xy = points[:, :2]
        lo = xy.min(axis=0) if len(xy) else np.zeros(2)
        ij = np.floor((xy - lo) / cell).astype(np.int64)
        shape = tuple(int(v) for v in (ij.max(axis=0) + 1 if len(xy) else (1, 1)))
        flat = ij[:, 0] * shape[1] + ij[:, 1]
        order = np.argsort(flat, kind="stable")
        counts = np.bincount(flat, minlength=shape[0] * shape[1])
        xyz = tuple(np.ascontiguousarray(points[order, j]) for j in range(3))
        return cls(lo, cell, shape, order, np.cumsum(counts) - counts, counts, xyz)

    def candidates(self, centers_xy: np.ndarray, radius: float):
        """(centre, sorted position) pairs of all points in the cells that a disc of
        `radius` around each centre can overlap (a superset). Grouped by centre."""
        # Never more cells than the grid has (a near-horizontal approach reaches far).
        span = int(min(np.ceil(radius / self.cell), max(self.shape)))
        off = np.arange(-span, span + 1)
        di, dj = (a.ravel() for a in np.meshgrid(off, off, indexing="ij"))
        # Cells that a disc centred anywhere in cell (0, 0) can reach.
        gap_i = np.maximum(np.abs(di) - 1, 0) * self.cell
        gap_j = np.maximum(np.abs(dj) - 1, 0) * self.cell
        near = gap_i**2 + gap_j**2 <= radius**2
        di, dj = di[near], dj[near]
        ij0 = np.floor((centers_xy - self.lo) / self.cell).astype(np.int64)
        ci = ij0[:, 0, None] + di[None, :]
        cj = ij0[:, 1, None] + dj[None, :]
        ok = (ci >= 0) & (ci < self.shape[0]) & (cj >= 0) & (cj < self.shape[1])
        center = np.nonzero(ok)[0]
        cells = ci[ok] * self.shape[1] + cj[ok]
        n = self.counts[cells]
        keep = n > 0
        center, cells, n = center[keep], cells[keep], n[keep]
        total = int(n.sum())
        pos = np.repeat(self.starts[cells] - (np.cumsum(n) - n), n)
        pos += np.arange(total)
        return center, n, pos


def _neighbour_pairs(grid: _Grid, origins: np.ndarray, approach: np.ndarray, e1: np.ndarray,
                     e2: np.ndarray, radius_across: float, w_max: float):
    """(axis, point) pairs, grouped by axis, of the points that can lie in a hand
    outline of radius `radius_across` around each approach axis and no more than
    `w_max` beyond the origin along it (points further ahead cannot touch the hand).

    Culling uses distances across world z: for an axis tilted by t from vertical, the
    outline reaches at most r / cos(t) + tan(t) |dz| horizontally from the origin at
    height difference dz.

    Returns:
        axis index, point index, and the point's coordinates relative to its axis:
        u, v across it (along e1, e2) and w along the approach (all (pairs,)).
    """
    if len(origins) == 0 or len(grid.order) == 0:
        empty_i, empty_f = np.zeros(0, dtype=np.int64), np.zeros(0)
        return empty_i, empty_i, empty_f, empty_f, empty_f
    cos_t = np.clip(-approach[:, 2], 1e-6, 1.0)
    z = grid.xyz[2]
    reach_dz = np.maximum(np.abs(z.max() - origins[:, 2]), np.abs(origins[:, 2] - z.min()))
    tan_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None)) / cos_t
    radius = radius_across / cos_t + np.where(tan_t > 1e-9, tan_t * reach_dz, 0.0) + 1e-9
    center, n, pos = grid.candidates(origins[:, :2], float(radius.max()))
    axis = np.repeat(center, n)
    dx = grid.xyz[0][pos] - np.repeat(origins[center, 0], n)
    dy = grid.xyz[1][pos] - np.repeat(origins[center, 1], n)
    dz = grid.xyz[2][pos] - np.repeat(origins[center, 2], n)
    frames = np.concatenate([approach, e1, e2], axis=1)
    if np.all(frames == frames[:1]):
        # All axes parallel with the same basis (the top-down default): scalar
        # coefficients instead of per-pair gathers.
        (ax, ay, az), (ux, uy, uz), (vx, vy, vz) = approach[0], e1[0], e2[0]
    else:
        ax, ay, az = (np.repeat(approach[center, j], n) for j in range(3))
        ux, uy, uz = (np.repeat(e1[center, j], n) for j in range(3))
        vx, vy, vz = (np.repeat(e2[center, j], n) for j in range(3))
    w = dx * ax + dy * ay + dz * az
    keep = np.flatnonzero((dx * dx + dy * dy <= np.repeat(radius[center] ** 2, n)) & (w <= w_max))
    dx, dy, dz, axis, w = dx[keep], dy[keep], dz[keep], axis[keep], w[keep]
    if not np.isscalar(ux):
        ux, uy, uz, vx, vy, vz = (c[keep] for c in (ux, uy, uz, vx, vy, vz))
    u = dx * ux + dy * uy + dz * uz
    v = dx * vx + dy * vy + dz * vz
    return axis, grid.order[pos[keep]], u, v, w


def _in_hand_frame(axis, u, v, base_angle, K, half_width, hands=None):
    """Hand-frame coordinates of the (pair, k) entries with |y_G| <= half_width.

    All K rotations of a pair are tested at once in a dense (pairs, K) block: K is
    small, and this beats generating only the runs of k that can hit (np.repeat
    with variable counts is slower than the extra arithmetic).

    Args:
        axis, u, v: per pair, from `_neighbour_pairs`.
        base_angle: (S,) angle of rotation 0 per axis; rotation k adds k pi / K.
        hands: Optional (S, K) mask: only entries of these hands are kept.

    Returns:
        x, y (entries,), hand ids g = s * K + k and pair indices (entries,).
    """
    cb, sb = np.cos(base_angle)[axis], np.sin(base_angle)[axis]
    # Coordinates at rotation 0 (float32: errors ~1e-8 m, half the memory traffic of
    # this, the largest block); rotation k then only needs a K-entry table.
    u0 = (u * cb + v * sb).astype(np.float32)
    v0 = (v * cb - u * sb).astype(np.float32)
    phase = np.pi * np.arange(K) / K
    c, s = np.cos(phase).astype(np.float32), np.sin(phase).astype(np.float32)
    Y = np.multiply.outer(v0, c)
    Y -= np.multiply.outer(u0, s)
    inside = np.abs(Y, out=Y) <= np.float32(half_width)
    if hands is not None:
        inside &= hands[axis]
    idx = np.flatnonzero(inside)
    pair = idx // K
    k = idx - pair * K
    up, vp, ck, sk = u0[pair], v0[pair], c[k], s[k]
    return up * ck + vp * sk, vp * ck - up * sk, axis[pair] * K + k, pair


@dataclass(frozen=True)
class _Scene:
    """Surface samples of a scene with their neighbour grids: a fine set for the
    closing region and contacts, a coarse one for collisions."""

    fine: ScenePoints
    coarse: ScenePoints
    fine_grid: _Grid
    coarse_grid: _Grid

    @classmethod
    def build(cls, fine: ScenePoints, coarse: ScenePoints) -> _Scene:
        # Cells of a quarter of the query radius: the cells a query disc can reach
        # hold less than twice the points of the disc itself.
        return cls(fine, coarse, _Grid.build(fine.points, STRIP_RADIUS_M / 4.0),
                   _Grid.build(coarse.points, HAND_FOOTPRINT_RADIUS_M / 4.0))


@dataclass(frozen=True)
class ObjectMasses:
    """Mass and world-frame centre of mass of each scene object (index as the meshes)."""

    mass_kg: np.ndarray  # (M,)
    com_W: np.ndarray  # (M, 3)

    @classmethod
    def of_scene(cls, spec, library) -> ObjectMasses:
        """From the objects' model data (`meta.json`: mass and centre of mass)."""
        mass, com = [], []
        for placement in spec.objects:
            meta = library.get(placement.object_id).read_meta()
            R = _quat_wxyz_to_matrix(placement.quat_wxyz)
            mass.append(float(meta["mass_kg"]))
            com.append(R @ np.asarray(meta["com_m"], dtype=float) + np.asarray(placement.xyz))
        return cls(np.asarray(mass, dtype=float).reshape(-1), np.asarray(com).reshape(-1, 3))

    @classmethod
    def of_meshes(cls, meshes, density_kg_m3: float = 500.0) -> ObjectMasses:
        """Uniform density: each (closed) mesh's volume centroid and volume x density."""
        mass = [abs(float(m.volume)) * density_kg_m3 if m.is_volume else 0.0 for m in meshes]
        com = [np.asarray(m.center_mass if m.is_volume else m.centroid, dtype=float)
               for m in meshes]
        return cls(np.asarray(mass, dtype=float), np.asarray(com).reshape(-1, 3))


GRAVITY_M_S2 = 9.81
# The ground truth's physical tests (`find_grasps`' defaults), calibrated against the grasp
# physics lab (`drake-grasp label-check`): 325 executed "true" grasps of 69 dataset scenes
# (seed 1000 with the plain force-closure test at mu 0.5, 145 grasps, 39 failed; seed 2026
# with mu 0.5 and a torque limit of 0.15, 180 grasps, 20 failed). Failures were of two
# kinds: contacts whose normals lean 20-27 degrees from the closing line (a lying can or
# an apple grasped high on its curve: held still, squeezed out by the shake), and loads far
# from the contact line (grasps at the end of long objects or high above the centre of
# mass). Of the 133 grasps with normals within 14 degrees (mu 0.25) and a torque ratio of
# at most 0.12, all held through lift, hold and shake; 14 degrees / 0.15 let 1 of 152 fail.
# Both limits are far below the pads' friction (0.9-1.0): the compliant pads' pressure
# peaks in the middle of a patch, and dynamic loads wedge a curved contact out.
FORCE_CLOSURE_MU = 0.25
MAX_TORQUE_RATIO = 0.12
# Peak acceleration of the grasp lab's translational shake (2 cm one-cycle sine in
# 0.25 s: 0.02 (2 pi / 0.25)^2), the default load case of the torque test.
SHAKE_ACCELERATION_M_S2 = 0.02 * (2.0 * np.pi / 0.25) ** 2


def _gravity_torque_ratio(contacts, spread, object_index, objects: ObjectMasses | None,
                          grip_force_n: float,
                          accel_m_s2: float = SHAKE_ACCELERATION_M_S2) -> np.ndarray:
    """The largest torque about the line through the two contact patches that the
    object's inertia under gravity and the hand's accelerations asks for, divided by
    what the pads' torsional friction can hold per unit friction coefficient.

    A parallel-jaw grasp rotates about the line through its contacts unless the
    patches' torsional friction holds the load acting at the object's centre of mass:
    |((p_com - c1) x m (g - a_hand)) . a| <= mu F (r1 + r2), where a is the unit
    contact axis, F the grip force of a pad and r the patches' spread (the lever arm
    of their friction). The hand's acceleration a_hand is zero (a static hold) or
    `accel_m_s2` along +-x, +-y or +-z of the world (the lab's shake). Returns the
    largest such torque / (F (r1 + r2)), the friction coefficient needed to hold
    (0 without `objects`; inf for a patch without spread).
    """
    n = len(object_index)
    if objects is None or n == 0:
        return np.zeros(n)
    ok = object_index >= 0
    idx = np.where(ok, object_index, 0)
    c1, c2 = contacts[:, 0], contacts[:, 1]
    axis = c2 - c1
    length = np.linalg.norm(axis, axis=1, keepdims=True)
    loads = [np.array([0.0, 0.0, -GRAVITY_M_S2])]
    for j in range(3):
        for sign in (-1.0, 1.0):
            a_hand = np.zeros(3)
            a_hand[j] = sign * float(accel_m_s2)
            loads.append(loads[0] - a_hand)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = axis / length
        lever = np.cross(a, objects.com_W[idx] - c1)  # (r x L) . a = (a x r) . L
        torque = np.max(np.abs(lever @ np.stack(loads, axis=1)), axis=1) * objects.mass_kg[idx]
        ratio = torque / (float(grip_force_n) * spread.sum(axis=1))
    ratio = np.where(ok & np.isfinite(ratio), ratio, np.inf)
    return np.where(ok & (torque == 0), 0.0, ratio)


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

    # --- Collisions (coarse samples) --------------------------------------------
    axis, _, u, v, w_pair = _neighbour_pairs(scene.coarse_grid, origins, approach, basis_x, e2,
                                             HAND_FOOTPRINT_RADIUS_M, w_max)
    t1 = time.perf_counter()
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
    t2 = time.perf_counter()

    # Centre offsets along the axis, (A, D).
    if depths is None:
        shift = np.zeros((A, 1))
    else:
        shift = top[:, None] + depth_arr[None, :]
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

    # --- Closing region (fine samples), collision-free hands only ------------------
    fs = scene.fine
    any_free = free.any(axis=1)
    seeds_free = np.zeros(S, dtype=bool)
    seeds_free[s_of[any_free]] = True
    sel = np.flatnonzero(seeds_free)
    f_axis, f_point, f_u, f_v, f_w = _neighbour_pairs(scene.fine_grid, origins[sel], approach[sel],
                                                      basis_x[sel], e2[sel], STRIP_RADIUS_M, w_max)
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
    count = np.bincount(ids, minlength=n)
    xmin = _group_min(xq, ids, n)
    xmax = _group_max(xq, ids, n)
    with np.errstate(invalid="ignore"):
        width = xmax - xmin
    # Contact patches: what the pads touch first (within the pads' compliance): their
    # centroids and mean normals. Both pads must touch one and the same object.
    pts = ps[q]
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
    centers = origins[s_of][:, None, :] + shift[..., None] * z_axis[:, None, :]
    t3 = time.perf_counter()
    if timings is not None:
        stages = (("neighbours", t1 - t0), ("collision", t2 - t1),
                  ("closing_and_force_closure", t3 - t2))
        for key, dt in stages:
            timings[key] = timings.get(key, 0.0) + dt
    shape = (S, K, D)
    return _Evaluation(
        centers=centers.reshape(shape + (3,)),
        x_axis=x_axis.reshape(S, K, 3),
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


# ----------------------------------------------------------------------------
# Grasp sets.


def _yaw_deg_mod_180(x_axis: np.ndarray) -> np.ndarray:
    return np.mod(np.rad2deg(np.arctan2(x_axis[..., 1], x_axis[..., 0])), 180.0)


@dataclass(frozen=True)
class GraspSet:
    """Ground-truth grasps of one scene.

    Attributes:
        poses: (N, 4, 4) world poses X_WG of the grasp frame (centre between the pads,
            z_G approach, x_G closing).
        widths: (N,) what the pads close to [m].
        xy_theta: (N, 3) the planar grasp (x [m], y [m], theta [deg] in [0, 180)):
            the centre's x, y and the yaw of the closing direction, modulo 180 for
            the parallel jaw's symmetry (for tilted grasps, of its horizontal part).
        object_index: (N,) the grasped object (index into the scene's objects).

    A hand that works at several depths appears once per depth: rows then share
    their `xy_theta` (harmless for nearest-grasp distances).
    """

    poses: np.ndarray
    widths: np.ndarray
    xy_theta: np.ndarray
    object_index: np.ndarray

    KEYS = ("poses", "widths", "xy_theta", "object_index")

    def __post_init__(self) -> None:
        n = len(self.widths)
        shapes = {"poses": (n, 4, 4), "widths": (n,), "xy_theta": (n, 3), "object_index": (n,)}
        for key, shape in shapes.items():
            if np.shape(getattr(self, key)) != shape:
                raise ValueError(
                    f"GraspSet.{key}: expected shape {shape}, got {np.shape(getattr(self, key))}")

    def __len__(self) -> int:
        return len(self.widths)

    @classmethod
    def empty(cls) -> GraspSet:
        return cls(np.zeros((0, 4, 4)), np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))

    def to_dict(self) -> dict[str, np.ndarray]:
        """Plain arrays (float64 / int64), e.g. for an HDF5 group."""
        return {
            "poses": np.asarray(self.poses, dtype=np.float64),
            "widths": np.asarray(self.widths, dtype=np.float64),
            "xy_theta": np.asarray(self.xy_theta, dtype=np.float64),
            "object_index": np.asarray(self.object_index, dtype=np.int64),
        }

    @classmethod
    def from_dict(cls, data) -> GraspSet:
        """Inverse of `to_dict` (accepts any mapping of array-likes, e.g. an h5py group).

        Raises:
            ValueError: a key is missing or the shapes disagree.
        """
        missing = [k for k in cls.KEYS if k not in data]
        if missing:
            raise ValueError(
                f"GraspSet.from_dict: missing keys {missing}; expected {list(cls.KEYS)}")
        return cls(
            poses=np.asarray(data["poses"], dtype=np.float64).reshape(-1, 4, 4),
            widths=np.asarray(data["widths"], dtype=np.float64).reshape(-1),
            xy_theta=np.asarray(data["xy_theta"], dtype=np.float64).reshape(-1, 3),
            object_index=np.asarray(data["object_index"], dtype=np.int64).reshape(-1),
        )

    def distances(self, poses_xy_theta) -> np.ndarray:
        """`distance_to_nearest_grasp` from planar poses to this set."""
        return distance_to_nearest_grasp(poses_xy_theta, self.xy_theta)


def find_grasps_in_meshes(
    meshes,
    rng: np.random.Generator,
    *,
    num_samples: int = 400,
    num_rotations: int = 8,
    depths=DEFAULT_DEPTHS_M,
    approach_max_tilt_deg: float = 0.0,
    mu: float = 0.5,
    point_spacing_m: float = 0.003,
    collision_spacing_m: float = 0.005,
    min_width_m: float = 0.005,
    min_points_between: int = 5,
    contact_tolerance_m: float = 0.002,
    table_z: float = TABLE_TOP_Z_M,
    table_clearance_m: float = 0.002,
    timings: dict | None = None,
    return_rejected: bool = False,
    objects: ObjectMasses | None = None,
    grip_force_n: float = 60.0,
    max_torque_ratio: float | None = None,
) -> GraspSet | tuple[GraspSet, GraspSet]:
    """Ground-truth grasps among world-frame meshes on the table (no Drake needed).

    1. Surface samples of all objects (`sample_scene_points`, `point_spacing_m`).
    2. Candidates (`sample_grasp_candidates`): S axes x K rotations x D depths.
    3. Collision: the fully open hand (fingers, palm, housing) swept in along its
       approach axis touches no object sample (a stricter test than the final pose
       alone: it also rejects hands under overhangs, which a hand descending straight
       down, as this project's controller does, could not reach), and its fingertips
       / palm stay `table_clearance_m` above `table_z` (the sheet's top).
    4. Closing region: at least `min_points_between` object samples between the pads;
       the pads would close to their extent along x_G, which must lie in
       [min_width_m, 85 mm]; both pads touch the same object.
    5. Force closure (`force_closure`, friction `mu`) of the two contact patches (the
       samples within `contact_tolerance_m` of either extreme along x_G: centroid and
       mean normal).

    Args:
        meshes: World-frame `trimesh.Trimesh` surfaces with outward normals.
        rng: Source of randomness (all of it; the same seed gives the same set).
        num_samples, num_rotations, depths, approach_max_tilt_deg: See
            `sample_grasp_candidates`.
        mu: Friction coefficient of the force-closure test. 0.5 (the paper does not
            say; a conservative value for rubber pads on plastic / wood / metal,
            whose Drake pads use mu 0.9 - 1.0).
        point_spacing_m: Spacing of the surface samples for the closing region and
            the contacts [m]: 3 mm resolves widths and contact normals to ~1-2 mm.
        collision_spacing_m: Spacing of the (separate, coarser) samples for the
            collision test [m]: 5 mm still puts ~14 samples in a finger's 16 x 22 mm
            outline, at a third of the cost of the fine set.
        min_width_m: Narrowest graspable width [m] (thinner than this is a sliver).
        min_points_between: Fewest samples between the pads for a grasp.
        contact_tolerance_m: Depth of the pads' contact patch [m] (pad compliance).
        table_z: Height of the surface the objects lie on [m].
        table_clearance_m: How far above it the hand must stay [m].
        timings: Optional dict; seconds per stage are added to it: "sampling"
            (surface samples, candidates, neighbour grids), "neighbours" (the
            collision samples near each axis), "collision", and
            "closing_and_force_closure" (with its own search of the fine samples).
        objects: Mass and centre of mass of each mesh's object (`ObjectMasses`), for
            the gravity-torque test; None: no such test.
        grip_force_n: Normal force of each pad [N] (the station's grip force).
        max_torque_ratio: Largest gravity torque about the contact axis per unit of
            the pads' torsional friction lever, F (r1 + r2) (`GraspCheck.torque_ratio`);
            None: no limit.
        return_rejected: also return the candidates that reach the object collision
            free with both pads on one object but fail the width or force-closure
            test (what `drake-grasp label-check` executes as "rejected").

    Returns:
        The grasps (`GraspSet`); `object_index` indexes `meshes`. With
        `return_rejected`, (grasps, rejected candidates).
    """
    _check_rng(rng)
    meshes = _check_meshes(meshes)
    mu = _positive("mu", mu, allow_zero=True)
    min_width_m = _positive("min_width_m", min_width_m, allow_zero=True)
    contact_tolerance_m = _positive("contact_tolerance_m", contact_tolerance_m, allow_zero=True)
    min_points_between = _positive_int("min_points_between", min_points_between)
    t0 = time.perf_counter()
    fine = sample_scene_points(meshes, rng, spacing_m=point_spacing_m)
    coarse = sample_scene_points(meshes, rng, spacing_m=collision_spacing_m)
    cands = sample_grasp_candidates(
        meshes, rng, num_samples=num_samples, num_rotations=num_rotations, depths=depths,
        approach_max_tilt_deg=approach_max_tilt_deg)
    if len(cands.origins) == 0 or len(fine) == 0 or len(coarse) == 0:
        return (GraspSet.empty(), GraspSet.empty()) if return_rejected else GraspSet.empty()
    scene = _Scene.build(fine, coarse)
    t1 = time.perf_counter()
    if timings is not None:
        timings["sampling"] = timings.get("sampling", 0.0) + (t1 - t0)
    ev = _evaluate(scene, cands.origins, cands.approach, cands.basis_x, cands.base_angle,
                   cands.num_rotations, cands.depths,
                   mu=mu, min_width_m=min_width_m, max_width_m=STROKE_M,
                   min_points_between=min_points_between, contact_tolerance_m=contact_tolerance_m,
                   table_z=float(table_z), table_clearance_m=float(table_clearance_m),
                   timings=timings, objects=objects,
                   grip_force_n=_positive("grip_force_n", grip_force_n),
                   max_torque_ratio=max_torque_ratio)
    accepted = _grasp_set(ev, cands.approach, ev.valid)
    if not return_rejected:
        return accepted
    # Candidates the analytic test turns down although the open hand reaches them
    # and both pads would close on one object: the width or force-closure test said no.
    near = (ev.collision_free & (ev.num_points_between >= min_points_between)
            & (ev.object_index >= 0) & ~ev.valid)
    return accepted, _grasp_set(ev, cands.approach, near)


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


def _grasp_set(ev: _Evaluation, approach: np.ndarray, mask: np.ndarray) -> GraspSet:
    poses, (s, k, d) = evaluation_poses(ev, approach, mask)
    x_axis = poses[:, :3, 0]
    xy_theta = np.column_stack([poses[:, 0, 3], poses[:, 1, 3], _yaw_deg_mod_180(x_axis)])
    widths = np.nan_to_num(ev.width[s, k, d].astype(float), nan=0.0)
    return GraspSet(poses, widths, xy_theta, ev.object_index[s, k, d])


def find_grasps(spec, library, rng: np.random.Generator, **kwargs) -> GraspSet:
    """Ground-truth grasps of a `SceneSpec` (see `find_grasps_in_meshes` for kwargs).

    `object_index` indexes `spec.objects`. The objects' masses and centres of mass
    come from the library (`ObjectMasses.of_scene`) unless `objects` is given, and
    the physical tests apply with `mu=FORCE_CLOSURE_MU` and
    `max_torque_ratio=MAX_TORQUE_RATIO` unless given (values calibrated in the grasp lab).
    """
    if "objects" not in kwargs:
        kwargs["objects"] = ObjectMasses.of_scene(spec, library)
    kwargs.setdefault("max_torque_ratio", MAX_TORQUE_RATIO)
    kwargs.setdefault("mu", FORCE_CLOSURE_MU)
    return find_grasps_in_meshes(scene_meshes(spec, library), rng, **kwargs)


# ----------------------------------------------------------------------------
# The paper's distance metric.


def angle_difference_deg(theta1, theta2) -> np.ndarray:
    """|theta1 - theta2| in degrees modulo 180 (a parallel jaw turned by 180 degrees is
    the same grasp), in [0, 90]."""
    d = np.mod(np.abs(np.asarray(theta1, dtype=float) - np.asarray(theta2, dtype=float)), 180.0)
    return np.minimum(d, 180.0 - d)


def planar_grasp_xy_yaw(X_WG) -> np.ndarray:
    """(..., 3) [x, y, yaw_deg] of grasp-frame poses (..., 4, 4): the grasp centre's (x, y)
    and the yaw of the closing direction x_G projected onto the table (so a tilted grasp,
    e.g. gpd's, is compared with the planar ground truth by where it grasps and how it
    closes)."""
    X = np.asarray(X_WG, dtype=float)
    yaw = np.rad2deg(np.arctan2(X[..., 1, 0], X[..., 0, 0]))
    return np.stack([X[..., 0, 3], X[..., 1, 3], yaw], axis=-1)


def grasp_distance(a, b, *, angle_weight_m_per_deg: float = ANGLE_WEIGHT_M_PER_DEG) -> np.ndarray:
    """Distance between planar grasps (x, y, theta_deg), broadcast over leading axes.

    Euclidean in (x, y, w * theta) with w = 0.001 m/deg and the angle difference
    taken modulo 180 degrees: sqrt(dx^2 + dy^2 + (w dtheta)^2) [m] (paper, "CNN
    Model": "Distance is measured in meters in the (x, y, theta) pose space by
    weighting the angular component (by 0.001 meter/degree)").
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape[-1:] != (3,) or b.shape[-1:] != (3,):
        raise ValueError(f"a, b: expected arrays of shape (..., 3) = (x, y, theta_deg), got "
                         f"{a.shape} and {b.shape}")
    dth = angle_difference_deg(a[..., 2], b[..., 2]) * float(angle_weight_m_per_deg)
    return np.sqrt((a[..., 0] - b[..., 0]) ** 2 + (a[..., 1] - b[..., 1]) ** 2 + dth**2)


def distance_to_nearest_grasp(
    poses_xy_theta,
    grasps_xy_theta,
    *,
    angle_weight_m_per_deg: float = ANGLE_WEIGHT_M_PER_DEG,
    chunk_elements: int = 4_000_000,
) -> np.ndarray:
    """The paper's label: distance from each pose to the nearest grasp [m].

    Args:
        poses_xy_theta: (M, 3) planar poses (x [m], y [m], theta [deg]).
        grasps_xy_theta: (N, 3) ground-truth grasps, e.g. `GraspSet.xy_theta`.
        angle_weight_m_per_deg: Weight of the angle (paper: 0.001 m/deg).
        chunk_elements: Largest M x N block computed at once (memory bound).

    Returns:
        (M,) distances `grasp_distance` to the nearest grasp; +inf for every pose
        when there are no grasps.
    """
    Q = np.asarray(poses_xy_theta, dtype=float)
    G = np.asarray(grasps_xy_theta, dtype=float)
    if Q.ndim != 2 or Q.shape[1] != 3:
        raise ValueError(f"poses_xy_theta: expected an (M, 3) array, got shape {Q.shape}")
    if G.ndim != 2 or G.shape[1] != 3:
        raise ValueError(f"grasps_xy_theta: expected an (N, 3) array, got shape {G.shape}")
    out = np.full(len(Q), np.inf)
    if len(G) == 0 or len(Q) == 0:
        return out
    step = max(1, int(chunk_elements) // len(G))
    for i in range(0, len(Q), step):
        out[i:i + step] = grasp_distance(Q[i:i + step, None, :], G[None, :, :],
                                         angle_weight_m_per_deg=angle_weight_m_per_deg).min(axis=1)
    return out
