"""Ground-truth grasps of a scene, as the paper labels its training data ("Generating
training data"): `find_grasps` / `find_grasps_in_meshes` sample GPD-style hand candidates
(`grasp_candidates`, ten Pas & Platt, ISRR 2015), keep the collision-free ones with object
surface between the fingers, and test the contacts for force closure (Nguyen 1986) and
the torque about the contact axis (`hand_checks`, `contact_physics`). This module owns
that search over a scene's meshes and its result, the `GraspSet`, whose planar grasps
the paper's label (`grasp_metric.distance_to_nearest_grasp`) measures against.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from drake_grasp.geometry.contact_physics import FORCE_CLOSURE_MU, MAX_TORQUE_RATIO
from drake_grasp.geometry.grasp_candidates import DEFAULT_DEPTHS_M, sample_grasp_candidates
from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
from drake_grasp.geometry.hand_checks import _evaluate, _Evaluation, evaluation_poses
from drake_grasp.geometry.hand_model import STROKE_M, TABLE_TOP_Z_M
from drake_grasp.geometry.point_grid import _Scene
from drake_grasp.geometry.scene_samples import (
    ObjectMasses,
    _check_meshes,
    _check_rng,
    _positive,
    _positive_int,
    sample_scene_points,
    scene_meshes,
)


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
    mu, min_width_m, contact_tolerance_m, min_points_between = _checked_thresholds(
        mu, min_width_m, contact_tolerance_m, min_points_between)
    sampled = _sample_search(
        meshes, rng, timings, point_spacing_m=point_spacing_m,
        collision_spacing_m=collision_spacing_m, num_samples=num_samples,
        num_rotations=num_rotations, depths=depths, approach_max_tilt_deg=approach_max_tilt_deg)
    if sampled is None:
        return (GraspSet.empty(), GraspSet.empty()) if return_rejected else GraspSet.empty()
    scene, cands = sampled
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
    return accepted, _grasp_set(ev, cands.approach, _rejected_mask(ev, min_points_between))


def _checked_thresholds(mu, min_width_m, contact_tolerance_m, min_points_between):
    """The search's test thresholds, checked in this order (a bad one is named)."""
    return (_positive("mu", mu, allow_zero=True),
            _positive("min_width_m", min_width_m, allow_zero=True),
            _positive("contact_tolerance_m", contact_tolerance_m, allow_zero=True),
            _positive_int("min_points_between", min_points_between))


def _sample_search(meshes, rng: np.random.Generator, timings: dict | None, *,
                   point_spacing_m: float, collision_spacing_m: float, num_samples: int,
                   num_rotations: int, depths, approach_max_tilt_deg: float):
    """The search's random draws from one stream, in this order: the fine surface samples,
    the coarse collision samples and the candidates; then the neighbour grids. Adds the
    seconds taken to timings["sampling"].

    Returns:
        (`_Scene`, `GraspCandidates`), or None when there are no candidates or samples.
    """
    t0 = time.perf_counter()
    fine = sample_scene_points(meshes, rng, spacing_m=point_spacing_m)
    coarse = sample_scene_points(meshes, rng, spacing_m=collision_spacing_m)
    cands = sample_grasp_candidates(
        meshes, rng, num_samples=num_samples, num_rotations=num_rotations, depths=depths,
        approach_max_tilt_deg=approach_max_tilt_deg)
    if len(cands.origins) == 0 or len(fine) == 0 or len(coarse) == 0:
        return None
    scene = _Scene.build(fine, coarse)
    t1 = time.perf_counter()
    if timings is not None:
        timings["sampling"] = timings.get("sampling", 0.0) + (t1 - t0)
    return scene, cands


def _rejected_mask(ev: _Evaluation, min_points_between: int) -> np.ndarray:
    """Candidates the analytic test turns down although the open hand reaches them
    and both pads would close on one object: the width or force-closure test said no."""
    return (ev.collision_free & (ev.num_points_between >= min_points_between)
            & (ev.object_index >= 0) & ~ev.valid)



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
