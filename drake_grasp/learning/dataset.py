"""The simulated training set (the paper's section "Generating training data"): one scene.

Per scene (a `random` scene of 1-5 objects from one split, the count uniform over the
scenes, oriented as `DatasetConfig.initial_pose` says, settled by physics until verified
at rest: `scene.settle_world`): the
ground-truth grasps (`grasps.find_grasps`), then K wrist depth images from hand poses
drawn at random in (x, y, z, theta) above the objects, each rendered by Drake's VTK
renderer and post-processed by the same `sensing.postprocess_depth` the Diagram uses,
and M offsets per image drawn uniformly within the camera's view, each labelled with its
distance to the nearest true grasp (`grasps.distance_to_nearest_grasp`).

Exactly N scenes. `--scenes N` gives N labelled scenes, numbered 0..N-1. Scene i has a
reserved sequence of seeds `scene_seed(seed, i, attempt)`, attempt = 0, 1, 2, ...; an
attempt whose settling hit the time cap with objects still moving ("unsettled"), or
whose settled scene has no ground-truth grasp ("no grasp"), is replaced by the next
attempt of the same scene, so the dataset never silently holds fewer scenes and every
scene depends only on (seed, i), not on other scenes or on the shard size. The replaced
attempts are counted in the shards and the manifest; after `max_attempts_per_scene`
failed attempts generation stops with an error naming the scene.

This module holds the dataset's settings (`DatasetConfig`), the scenes' seeds and what one
scene contributes. Beside it: `dataset_generate` runs the generation over shards and
workers, `dataset_shards` owns the format on disk and reads it back (`DepthGraspDataset`),
`folder_lock` keeps one generator per folder and makes each file durable.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field

import numpy as np



# 2: exactly N scenes (replaced attempts, last shard smaller), per-run temporary names.
# 3: depth stored as float16 (readers convert to float32; format 2 shards stay readable).
FORMAT_VERSION = 3
# How scenes are drawn and settled, part of the config hash: a folder begun by another
# version is not resumed. 2: object count per scene (`scene_object_count`), verified
# settling (`scene.settle_world(verified=True)`).
SCENE_VERSION = 2
# Depth storage type. float16 rounds a depth in [0.125, 0.25) m to 0.06 mm, in [0.25, 0.5) m
# to 0.12 mm and at the far clip (1.5 m) to 0.49 mm, against the sensor model's 1.2 mm
# noise at 0.4 m; it measured a 0.12 mm worst case over 1,600 images of a 0.15-0.30 m
# camera and 2.7x smaller gzip-compressed depth than float32.
DEPTH_DTYPE = np.float16
MANIFEST = "manifest.json"


# `DatasetConfig` fields added after datasets were made, with the value those datasets used
# (`DatasetConfig.identity` leaves them out at that value).
_LATER_FIELD_DEFAULTS = {"grasp_samples": 400, "near_grasp_fraction": 0.0,
                         "near_grasp_xy_m": 0.04, "near_grasp_theta_deg": 45.0,
                         "scene_kind": "random", "initial_pose": "uniform"}
SCENE_KINDS = ("random", "clutter")
# `DatasetConfig.initial_pose` (as `scene.INITIAL_POSES`, which this module does not import
# at load time).
INITIAL_POSES = ("stable", "uniform")



@dataclass
class DatasetConfig:
    """How the training set is sampled (defaults from the paper)."""

    images_per_scene: int = 40
    offsets_per_image: int = 10
    # Camera height above the table, covering the controller's range (0.3 -> 0.15 m).
    camera_height_min_m: float = 0.15
    camera_height_max_m: float = 0.30
    # Hand positions drawn within this half extent around the scene centre [m].
    hand_xy_half_extent_m: float = 0.08
    # Scenes per shard file (one task of a worker).
    scenes_per_shard: int = 4
    # Settling for data generation (`scene.settle_world(verified=True)`: damped, judged by
    # displacement, checked undamped): tolerance and time cap. A scene still moving at the
    # cap is not used; the next seed of its sequence replaces it.
    settle_speed_tol_m_s: float = 0.01
    settle_max_time_s: float = 3.0
    # Settling only has to bring objects to rest, not resolve a grasp: a coarser step
    # than the episodes' 2 ms is enough and makes generation faster.
    settle_time_step_s: float = 0.005
    # Friction coefficient of the force-closure test and the largest gravity-and-shake
    # torque about the contact axis per unit of the pads' torsional friction lever
    # (`grasps.FORCE_CLOSURE_MU`, `grasps.MAX_TORQUE_RATIO`: calibrated in the grasp lab).
    friction_coefficient: float = 0.25
    max_torque_ratio: float = 0.12
    # Surface points of the ground-truth grasp search (`grasps.find_grasps`' num_samples).
    # 400 labels a scene in ~0.12 s; two such searches differ by 6.6 mm of L1 and read
    # 7.8 mm high under 3 cm against a 10x denser one (README *How exact the labels are*).
    grasp_samples: int = 400
    # The fraction of each scene's images whose hand pose is drawn near a true grasp
    # instead (not in the paper; 0 keeps its random poses): a grasp of the scene at
    # random, its (x, y) moved uniformly within +-near_grasp_xy_m and its theta (either
    # way round: a 180-degree turn is the same grasp) within +-near_grasp_theta_deg, the
    # camera height drawn as for the others. The defaults match the controller's
    # candidate sampling (`controller.sample_xy_m`, `sample_theta_deg`): the views a
    # converging controller sees.
    near_grasp_fraction: float = 0.0
    near_grasp_xy_m: float = 0.04
    near_grasp_theta_deg: float = 45.0
    # The scenes: `random` (the paper's: 1-5 objects of the scenario's
    # num_objects_min..max spread over its region) or `clutter` (the scenario's
    # scene.clutter_objects poured into a pile over its region, as the clutter
    # experiments' piles; not in the paper's training set).
    scene_kind: str = "random"
    # How the objects are oriented before the settle (`scene.sample_scene`): "uniform", a
    # uniformly random rotation, dropped to tumble (every dataset and label check so far;
    # about a third of its scenes are still moving at the time cap and are replaced);
    # "stable", a resting pose of each object on a plane drawn with its probability,
    # random yaw (`objects.stable_poses`): 1.4x the labels/s, a quarter of the replaced
    # scenes, but its label precision is not yet shown equal (docs/guide/data-training.md
    # *Stable initial poses*), so not the default. `generate --initial-pose`.
    initial_pose: str = "uniform"
    # Seeds tried for one scene (unsettled or without a true grasp -> the next one)
    # before generation stops with an error naming the scene.
    max_attempts_per_scene: int = 20

    def grasp_search(self) -> dict:
        """The keywords of `grasps.find_grasps` that make this config's ground truth
        (also what `label-check` labels with)."""
        return {"mu": self.friction_coefficient, "max_torque_ratio": self.max_torque_ratio,
                "num_samples": self.grasp_samples}

    def identity(self) -> dict:
        """The fields as a dict for run identities; fields added after datasets were made
        are left out at their default, so that those datasets keep their identity (and
        resume)."""
        out = dataclasses.asdict(self)
        for name, default in _LATER_FIELD_DEFAULTS.items():
            if out[name] == default:
                del out[name]
        return out

    def validate(self) -> None:
        for name in ("images_per_scene", "offsets_per_image", "scenes_per_shard",
                     "max_attempts_per_scene", "grasp_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if not 0 < self.camera_height_min_m <= self.camera_height_max_m:
            raise ValueError("camera_height_min_m/max_m: expected 0 < min <= max")
        if not 0.0 <= self.near_grasp_fraction <= 1.0:
            raise ValueError(f"near_grasp_fraction: expected 0 <= f <= 1, got {self.near_grasp_fraction}")
        for name in ("near_grasp_xy_m", "near_grasp_theta_deg"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name}: expected >= 0, got {getattr(self, name)}")
        if self.initial_pose not in INITIAL_POSES:
            raise ValueError(f"initial_pose: expected one of {', '.join(INITIAL_POSES)}, "
                             f"got {self.initial_pose!r}")
        if self.scene_kind not in SCENE_KINDS:
            raise ValueError(f"scene_kind: expected one of {', '.join(SCENE_KINDS)}, "
                             f"got {self.scene_kind!r}")
        if not self.settle_max_time_s > 0.0:
            raise ValueError(f"settle_max_time_s: expected > 0, got {self.settle_max_time_s}")


def _config_dict(scenario, config: DatasetConfig, split: str, seed: int) -> dict:
    from drake_grasp.config.scenario import dump_scenario

    return {"format_version": FORMAT_VERSION, "scene_version": SCENE_VERSION,
            "split": split, "seed": int(seed),
            "dataset": config.identity(), "scenario": dump_scenario(scenario)}


def config_hash(cfg: dict) -> str:
    return hashlib.sha256(json.dumps(cfg, sort_keys=True).encode()).hexdigest()[:16]


def scene_seed(seed: int, scene_index: int, attempt: int = 0) -> int:
    """The seed of attempt `attempt` of scene `scene_index` of a dataset made with `seed`.

    Attempt 0 is the scene's first choice; attempts 1, 2, ... are its reserved
    replacements (used when an earlier attempt did not settle or had no true grasp).
    """
    key = [int(seed), int(scene_index), 31] + ([int(attempt)] if attempt else [])
    return int(np.random.default_rng(key).integers(2**31 - 1))


def scene_object_count(seed: int, scene_index: int, low: int, high: int) -> int:
    """How many objects scene `scene_index` holds, uniform in [low, high]: drawn once per
    scene, not per attempt, so that a replaced attempt keeps the count. (Drawn per
    attempt, the counts of the kept scenes lean towards the scenes that settle most
    often, the sparse ones: `analysis/settle_check.py`.)"""
    if not 1 <= low <= high:
        raise ValueError(f"scene.num_objects_min/max: expected 1 <= min <= max, got {low}, {high}")
    return int(np.random.default_rng([int(seed), int(scene_index), 37]).integers(low, high + 1))


def sample_dataset_scene(scenario, *, split: str, seed: int, scene_index: int, attempt: int,
                         library, kind: str = "random", initial_pose: str = "uniform"):
    """The (unsettled) scene of attempt `attempt` of dataset scene `scene_index`, drawn
    with `scene_seed(seed, scene_index, attempt)` from the `split`'s objects: for `kind`
    `random`, a random scene of the scenario's scene config with `scene_object_count`
    objects; for `clutter`, the scenario's pile of scene.clutter_objects objects (poured
    when settled). The objects' orientation: `initial_pose` (`scene.sample_scene`; the
    dataset passes `DatasetConfig.initial_pose`). `generate` and `label-check` both sample
    through it."""
    from drake_grasp.world.scene import sample_scene

    if kind == "clutter":
        cfg = dataclasses.replace(scenario.scene, kind="clutter", split=split, object_ids=[])
    elif kind == "random":
        count = scene_object_count(seed, scene_index, scenario.scene.num_objects_min,
                                   scenario.scene.num_objects_max)
        cfg = dataclasses.replace(scenario.scene, kind="random", split=split, object_ids=[],
                                  num_objects_min=count, num_objects_max=count)
    else:
        raise ValueError(f"scene kind: expected one of {', '.join(SCENE_KINDS)}, got {kind!r}")
    return sample_scene(cfg, scene_seed(seed, scene_index, attempt), library,
                        initial_pose=initial_pose)


def shard_scene_range(shard_index: int, *, num_scenes: int, scenes_per_shard: int) -> range:
    """Scene indices of shard `shard_index`: [k S, min((k + 1) S, N))."""
    first = shard_index * scenes_per_shard
    return range(first, min(first + scenes_per_shard, num_scenes))



# ----------------------------------------------------------------------------
# One scene.


@dataclass
class SceneSamples:
    """Everything one scene contributes to a shard."""

    scene_index: int
    spec_json: str
    depth: np.ndarray
    hand_pose: np.ndarray
    offsets: np.ndarray
    labels: np.ndarray
    grasp_pose: np.ndarray
    grasp_width: np.ndarray
    grasp_xy_theta: np.ndarray
    # Wall time of each stage [s] (for profiling; not stored in shards).
    timings: dict = field(default_factory=dict)
    # Which attempt of the scene's seed sequence this is (`scene_seed`).
    attempt: int = 0


@dataclass
class SceneRejected:
    """An attempt of a scene that is not used: `reason` is "unsettled" (settling hit its
    time cap with objects still moving) or "no_grasp" (no ground-truth grasp)."""

    scene_index: int
    attempt: int
    seed: int
    reason: str
    timings: dict = field(default_factory=dict)


REJECT_REASONS = ("unsettled", "no_grasp")


class SceneRenderer:
    """Renders the wrist depth image of a settled scene world from any hand pose."""

    def __init__(self, world, camera_config, renderer_name: str = "vtk"):
        from drake_grasp.world.station import gripper_frame_offsets, make_depth_camera

        self._world = world
        self._camera = make_depth_camera(camera_config, renderer_name)
        self._X_GC = gripper_frame_offsets()[2]
        sg = world.scene_graph
        self._sg_context = sg.GetMyContextFromRoot(world.simulator.get_context())
        self._frame = sg.world_frame_id()

    @property
    def X_GC(self):
        return self._X_GC

    def render(self, hand_pose: np.ndarray) -> np.ndarray:
        """Raw depth (H, W) from the hand pose [x, y, z, yaw_deg] of the grasp frame."""
        from drake_grasp.world.station import topdown_pose

        x, y, z, yaw = (float(v) for v in hand_pose)
        X_WC = topdown_pose([x, y], z, np.deg2rad(yaw)) @ self._X_GC
        query = self._world.scene_graph.get_query_output_port().Eval(self._sg_context)
        image = query.RenderDepthImage(self._camera, self._frame, X_WC)
        return np.array(image.data[:, :, 0], copy=True)


def generate_scene(scene_index: int, *, seed: int, split: str, scenario, config: DatasetConfig,
                   library, attempt: int = 0) -> SceneSamples | SceneRejected:
    """Settles one random scene, finds its grasps, renders K images and labels M offsets.

    Uses the seed `scene_seed(seed, scene_index, attempt)`. Returns a `SceneRejected`
    when the objects were still moving at the settling time cap, or when the settled
    scene has no ground-truth grasp (nothing to learn from).
    """
    from drake_grasp.geometry.actions import apply_actions, sample_actions_in_view
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.world.scene import build_scene_world, settle_world
    from drake_grasp.geometry.sensing import frame_rng, postprocess_depth

    timings: dict = {}
    clock = time.perf_counter()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock
        clock = now

    s_seed = scene_seed(seed, scene_index, attempt)
    spec = sample_dataset_scene(scenario, split=split, seed=seed, scene_index=scene_index,
                                attempt=attempt, library=library, kind=config.scene_kind,
                                initial_pose=config.initial_pose)
    plant_config = copy.deepcopy(scenario.plant)  # a Drake config: no dataclasses.replace
    plant_config.time_step = config.settle_time_step_s
    # The profile's sheet collision (the half space for `fast`); the step is the config's.
    world = build_scene_world(spec, library, plant_config=plant_config, renderer_name="vtk",
                              physics=scenario.physics)
    lap("build")
    settled = settle_world(world, spec, speed_tol_m_s=config.settle_speed_tol_m_s,
                           max_time_s=config.settle_max_time_s, verified=True)
    lap("settle")
    if not settled.settled:
        return SceneRejected(scene_index, attempt, s_seed, "unsettled", timings)
    rng = np.random.default_rng([s_seed, 1])
    grasps = find_grasps(settled, library, rng, **config.grasp_search())
    lap("grasps")
    if len(grasps.xy_theta) == 0:
        return SceneRejected(scene_index, attempt, s_seed, "no_grasp", timings)
    renderer = SceneRenderer(world, scenario.camera)
    K, M = config.images_per_scene, config.offsets_per_image
    cx, cy = settled.center_xy_m
    h = config.hand_xy_half_extent_m
    cam_height = rng.uniform(config.camera_height_min_m, config.camera_height_max_m, K)
    X_GC = renderer.X_GC.translation()
    hand = np.stack([rng.uniform(cx - h, cx + h, K), rng.uniform(cy - h, cy + h, K),
                     cam_height + X_GC[2], rng.uniform(-180.0, 180.0, K)], axis=1)
    near = int(round(config.near_grasp_fraction * K))
    if near:  # the last `near` images, from a stream of their own (the others unchanged)
        hand[K - near:] = near_grasp_poses(
            np.random.default_rng([s_seed, 2]), grasps.xy_theta, near, z=hand[K - near:, 2],
            xy_m=config.near_grasp_xy_m, theta_deg=config.near_grasp_theta_deg)
    depth = np.empty((K, scenario.camera.height, scenario.camera.width), np.float32)
    offsets = np.empty((K, M, 3))
    for k in range(K):
        raw = renderer.render(hand[k])
        lap("render")
        depth[k] = postprocess_depth(raw, frame_rng(s_seed, k), scenario.depth_noise,
                                     scenario.camera.depth_max_m)
        offsets[k] = sample_actions_in_view(
            rng, M, camera_height_m=cam_height[k], fov_deg=scenario.camera.fov_y_deg,
            camera_offset_xy_G=X_GC[:2])
        lap("postprocess")
    moved = apply_actions(hand[:, [0, 1, 3]], offsets)  # (K, M, 3)
    labels = distance_to_nearest_grasp(moved.reshape(-1, 3), grasps.xy_theta).reshape(K, M)
    lap("labels")
    return SceneSamples(
        scene_index=scene_index, spec_json=json.dumps(settled.to_dict()), depth=depth,
        hand_pose=hand, offsets=offsets.astype(np.float32), labels=labels.astype(np.float32),
        grasp_pose=np.asarray(grasps.poses, float), grasp_width=np.asarray(grasps.widths, np.float32),
        grasp_xy_theta=np.asarray(grasps.xy_theta, float), timings=timings, attempt=attempt)


def near_grasp_poses(rng: np.random.Generator, grasps_xy_theta: np.ndarray, n: int, *,
                     z: np.ndarray, xy_m: float, theta_deg: float) -> np.ndarray:
    """`n` hand poses [x, y, z, yaw_deg] near true grasps: for each a grasp of
    `grasps_xy_theta` (G, 3) at random, (x, y) moved uniformly within +-`xy_m`, yaw the
    grasp's theta or theta + 180 (the same grasp) moved uniformly within +-`theta_deg`
    and wrapped to [-180, 180)."""
    g = np.asarray(grasps_xy_theta, float)[rng.integers(0, len(grasps_xy_theta), n)]
    yaw = g[:, 2] + 180.0 * rng.integers(0, 2, n) + rng.uniform(-theta_deg, theta_deg, n)
    return np.column_stack([g[:, 0] + rng.uniform(-xy_m, xy_m, n),
                            g[:, 1] + rng.uniform(-xy_m, xy_m, n), np.asarray(z, float),
                            (yaw + 180.0) % 360.0 - 180.0])


def fill_scene(scene_index: int, *, seed: int, split: str, scenario, config: DatasetConfig,
               library) -> tuple[SceneSamples, list[SceneRejected]]:
    """Scene `scene_index`: the first attempt of its seed sequence that settles and has a
    true grasp, with the attempts it replaced.

    Raises:
        ValueError: naming the scene and the reasons, after `max_attempts_per_scene`.
    """
    rejected: list[SceneRejected] = []
    for attempt in range(config.max_attempts_per_scene):
        result = generate_scene(scene_index, seed=seed, split=split, scenario=scenario,
                                config=config, library=library, attempt=attempt)
        if isinstance(result, SceneSamples):
            return result, rejected
        rejected.append(result)
    reasons = {r: sum(x.reason == r for x in rejected) for r in REJECT_REASONS}
    raise ValueError(
        f"scene {scene_index}: none of its {config.max_attempts_per_scene} seeds "
        f"(max_attempts_per_scene) gave a usable scene ({reasons['unsettled']} still moving "
        f"after settle_max_time_s={config.settle_max_time_s}, {reasons['no_grasp']} without "
        "a true grasp); check the scenario's objects or raise those settings")
