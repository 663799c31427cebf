"""The simulated training set (the paper's section "Generating training data").

Per scene (a `random` scene of 1-5 objects from one split, the count uniform over the
scenes, settled by physics until verified at rest: `scene.settle_world`): the
ground-truth grasps (`grasps.find_grasps`), then K wrist depth images from hand poses
drawn at random in (x, y, z, theta) above the objects, each rendered by Drake's VTK
renderer and post-processed by the same `sensing.postprocess_depth` the Diagram uses,
and M offsets per image drawn uniformly within the camera's view, each labelled with its
distance to the nearest true grasp (`grasps.distance_to_nearest_grasp`).

On disk (this module owns the format):

    DIR/manifest.json           counts, resolved config, code version, shard list
    DIR/shard-00000.h5          scenes [0, S), one file per task of S scenes
    DIR/shard-00001.h5          ...; the last shard holds the rest (may be smaller)
    DIR/generate.lock           while a generator runs: its pid, host and start time

Exactly N scenes. `--scenes N` gives N labelled scenes, numbered 0..N-1. Scene i has a
reserved sequence of seeds `scene_seed(seed, i, attempt)`, attempt = 0, 1, 2, ...; an
attempt whose settling hit the time cap with objects still moving ("unsettled"), or
whose settled scene has no ground-truth grasp ("no grasp"), is replaced by the next
attempt of the same scene, so the dataset never silently holds fewer scenes and every
scene depends only on (seed, i), not on other scenes or on the shard size. The replaced
attempts are counted in the shards and the manifest; after `max_attempts_per_scene`
failed attempts generation stops with an error naming the scene.

One generator per folder. `generate_dataset` holds `generate.lock` (an exclusive `flock`
plus the owner's pid, host and start time in the file) for the whole run; a second
generator on the same folder is refused with an error naming the owner. A lock left by
a killed run (its pid no longer running on this host) is taken over with a message.
Workers write each shard to a temporary name private to the run and the worker process
(`shard-XXXXX.h5.<run>.<host>-<pid>.tmp`), fsync it and rename it when complete (then
fsync the folder), so a killed run leaves no half-written shard and no run ever deletes
a temporary file that another run is writing: a run removes only its own temporary
files, and those of a stale lock's run it takes over. Re-running the same command skips
finished shards.

Shard layout (HDF5, chunked + gzip):

    depth        (I, H, W) float16   post-processed depth [m] (float32 in format 2)
    hand_pose    (I, 4)    float64   [x, y, z, yaw_deg] of the grasp frame G (camera rigid on G)
    offsets      (I, M, 3) float32   actions [dx, dy, dtheta_deg] in the hand frame
    labels       (I, M)    float32   distance to the nearest true grasp [m]
    image_scene  (I,)      int64     global scene index of each image
    scene_index  (S,)      int64     global scene indices in this shard
    scene_attempt (S,)     int64     which attempt of the scene's seed sequence was kept
    scene_spec   (S,)      str       SceneSpec JSON (re-render any sample from it)
    grasp_scene  (G,)      int64     global scene index of each grasp
    grasp_pose   (G, 4, 4) float64   world grasp-frame poses
    grasp_width  (G,)      float32
    grasp_xy_theta (G, 3)  float64   [x, y, theta_deg mod 180]
    attrs: split, config_hash, code_version, format_version, num_scenes, num_images,
           num_labels, skipped, scene_first, scene_stop, num_attempts,
           num_replaced_no_grasp, num_replaced_unsettled
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import hashlib
import json
import os
import socket
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from drake_grasp.core.provenance import code_version

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
LOCK = "generate.lock"


# `DatasetConfig` fields added after datasets were made, with the value those datasets used
# (`DatasetConfig.identity` leaves them out at that value).
_LATER_FIELD_DEFAULTS = {"grasp_samples": 400, "near_grasp_fraction": 0.0,
                         "near_grasp_xy_m": 0.04, "near_grasp_theta_deg": 45.0,
                         "scene_kind": "random"}
SCENE_KINDS = ("random", "clutter")


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
                         library, kind: str = "random"):
    """The (unsettled) scene of attempt `attempt` of dataset scene `scene_index`, drawn
    with `scene_seed(seed, scene_index, attempt)` from the `split`'s objects: for `kind`
    `random`, a random scene of the scenario's scene config with `scene_object_count`
    objects; for `clutter`, the scenario's pile of scene.clutter_objects objects (poured
    when settled). `generate` and `label-check` both sample through it."""
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
    return sample_scene(cfg, scene_seed(seed, scene_index, attempt), library)


def shard_scene_range(shard_index: int, *, num_scenes: int, scenes_per_shard: int) -> range:
    """Scene indices of shard `shard_index`: [k S, min((k + 1) S, N))."""
    first = shard_index * scenes_per_shard
    return range(first, min(first + scenes_per_shard, num_scenes))


# ----------------------------------------------------------------------------
# Durable files.


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    """Makes a rename in `path` durable, where the OS allows fsync on a folder."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return  # e.g. Windows: folders cannot be opened
    try:
        os.fsync(fd)
    except OSError:
        pass  # some filesystems refuse fsync on a folder
    finally:
        os.close(fd)


def replace_durably(tmp: Path, path: Path) -> None:
    """fsync `tmp`, rename it to `path`, fsync the folder: after a crash `path` is either
    the old file or the complete new one."""
    _fsync_file(tmp)
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _process_tag() -> str:
    return f"{socket.gethostname()}-{os.getpid()}".replace("/", "_").replace(".", "_")


# ----------------------------------------------------------------------------
# One generator per folder.


class FolderInUseError(ValueError):
    """Another dataset generator holds the folder's lock (names the owner)."""


def _proc_start_ticks(pid: int) -> int | None:
    """Start time of a process in clock ticks since boot (Linux), to tell a reused pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    try:
        return int(stat.rsplit(")", 1)[1].split()[19])
    except (IndexError, ValueError):
        return None


def _pid_running(pid: int, start_ticks: int | None) -> bool:
    """Whether process `pid` (started at `start_ticks`, if known) runs on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # runs, as another user
    except OSError:
        return False
    if start_ticks is not None:
        now = _proc_start_ticks(pid)
        if now is not None and now != start_ticks:
            return False  # the pid was reused by another process
    return True


def _describe_owner(owner: dict) -> str:
    return (f"pid {owner.get('pid')} on host {owner.get('host')}, started "
            f"{owner.get('started_at')}")


class GenerateLock:
    """The lock file of a dataset folder: one generator at a time (subclasses set `FILE`
    and `WHAT` to lock other kinds of run folders the same way).

    The file holds the owner's pid, host, start time and a run token (JSON) and is
    `flock`ed for the owner's lifetime, so the kernel releases it when the owner dies.
    Acquiring: a held flock -> `FolderInUseError` naming the owner; a file left by a
    process that no longer runs on this host -> taken over (`stale_owner` says whose);
    a file naming a process on another host -> refused (this host cannot tell whether it
    still runs; the message says to delete the file if it does not).
    """

    FILE = LOCK
    WHAT = "dataset generator"

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.path = self.folder / self.FILE
        self.token = uuid.uuid4().hex[:12]
        self.stale_owner: dict | None = None
        self._fd: int | None = None

    def _owner_record(self) -> dict:
        return {"pid": os.getpid(), "host": socket.gethostname(),
                "started_at": datetime.datetime.now(datetime.timezone.utc).isoformat(
                    timespec="seconds"),
                "start_ticks": _proc_start_ticks(os.getpid()), "token": self.token,
                "argv": list(sys.argv)}

    def _refuse(self, owner: dict, extra: str = "") -> FolderInUseError:
        return FolderInUseError(
            f"{self.folder}: another {self.WHAT} is using this folder "
            f"({_describe_owner(owner)}; lock file {self.path}); wait for it to finish or "
            f"use another --out{extra}")

    def acquire(self) -> GenerateLock:
        import fcntl

        for _ in range(20):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                owner = self._read(fd)
                os.close(fd)
                raise self._refuse(owner) from None
            # An owner finishing right now unlinks the file it locked: retry on the new one.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            previous = self._read(fd)
            if previous:
                if previous.get("host") != socket.gethostname():
                    os.close(fd)
                    raise self._refuse(previous, extra=(
                        f". This host ({socket.gethostname()}) cannot tell whether that "
                        f"process still runs; if it does not, delete {self.path} and re-run"))
                if _pid_running(int(previous.get("pid", -1)), previous.get("start_ticks")):
                    os.close(fd)
                    raise self._refuse(previous)
                self.stale_owner = previous
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(self._owner_record()) + "\n").encode(), 0)
            os.fsync(fd)
            self._fd = fd
            return self
        raise FolderInUseError(f"{self.folder}: could not take {self.path} (it kept changing)")

    @staticmethod
    def _read(fd: int) -> dict:
        data = b""
        while chunk := os.pread(fd, 65536, len(data)):
            data += chunk
        if not data.strip():
            return {}
        try:
            owner = json.loads(data)
        except ValueError:
            return {"pid": "?", "host": "?", "started_at": "? (unreadable lock file)"}
        return owner if isinstance(owner, dict) else {}

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            os.unlink(self.path)  # while still locked: nobody can take a file being removed
        except FileNotFoundError:
            pass
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> GenerateLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _temp_files(out: Path, token: str) -> list[Path]:
    """Temporary files of the run with this token (shards and manifest)."""
    return sorted(out.glob(f"*.{token}.*tmp"))


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
                                attempt=attempt, library=library, kind=config.scene_kind)
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


# ----------------------------------------------------------------------------
# Shards.


def shard_name(shard_index: int) -> str:
    return f"shard-{shard_index:05d}.h5"


def write_shard(path: Path, samples: list[SceneSamples], *, attrs: dict,
                tmp_tag: str | None = None) -> None:
    """Writes a shard atomically and durably: a temporary name private to this process
    (`path.<tmp_tag>.<host>-<pid>.tmp`), fsync, rename to `path`, fsync the folder.

    `samples` entries that are None are counted in the `skipped` attr (older callers).
    """
    import h5py

    path = Path(path)
    tmp = path.with_name(f"{path.name}.{tmp_tag or 'write'}.{_process_tag()}.tmp")
    kept = [s for s in samples if s is not None]
    try:
        with h5py.File(tmp, "w") as f:
            def put(name, arrays, dtype, shape_tail):
                data = np.concatenate(arrays) if arrays else np.zeros((0, *shape_tail), dtype)
                chunks = (min(64, max(1, len(data))), *shape_tail) if len(data) else None
                f.create_dataset(name, data=data.astype(dtype), chunks=chunks,
                                 compression="gzip" if len(data) else None,
                                 compression_opts=4 if len(data) else None)

            hw = kept[0].depth.shape[1:] if kept else (0, 0)
            m = kept[0].offsets.shape[1] if kept else 0
            put("depth", [s.depth for s in kept], DEPTH_DTYPE, hw)
            put("hand_pose", [s.hand_pose for s in kept], np.float64, (4,))
            put("offsets", [s.offsets for s in kept], np.float32, (m, 3))
            put("labels", [s.labels for s in kept], np.float32, (m,))
            put("image_scene", [np.full(len(s.depth), s.scene_index) for s in kept], np.int64, ())
            put("grasp_scene", [np.full(len(s.grasp_width), s.scene_index) for s in kept],
                np.int64, ())
            put("grasp_pose", [s.grasp_pose for s in kept], np.float64, (4, 4))
            put("grasp_width", [s.grasp_width for s in kept], np.float32, ())
            put("grasp_xy_theta", [s.grasp_xy_theta for s in kept], np.float64, (3,))
            f.create_dataset("scene_index", data=np.array([s.scene_index for s in kept], np.int64))
            f.create_dataset("scene_attempt", data=np.array([s.attempt for s in kept], np.int64))
            f.create_dataset("scene_spec", data=[s.spec_json for s in kept],
                             dtype=h5py.string_dtype())
            num_images = int(sum(len(s.depth) for s in kept))
            f.attrs.update(attrs)
            f.attrs["num_scenes"] = len(kept)
            f.attrs["num_images"] = num_images
            f.attrs["num_labels"] = int(sum(s.labels.size for s in kept))
            f.attrs["skipped"] = len(samples) - len(kept)
        replace_durably(tmp, path)
    except OSError as e:
        message = f"cannot write dataset shard {path}: {e.strerror or e}"  # e.g. a full disk
        raise (OSError(e.errno, message) if e.errno else OSError(message)) from e
    finally:
        if tmp.exists():
            tmp.unlink()  # a failed write leaves nothing behind


_COUNT_ATTRS = ("num_scenes", "num_images", "num_labels", "skipped")
# Written since format 2; 0/absent in shards written without them.
_OPTIONAL_ATTRS = ("scene_first", "scene_stop", "num_attempts", "num_replaced_no_grasp",
                   "num_replaced_unsettled")


def read_shard_counts(path: Path) -> dict:
    """Counts and attrs of a finished shard; a corrupt file is reported by name."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            counts = {k: int(f.attrs[k]) for k in _COUNT_ATTRS}
            for k in _OPTIONAL_ATTRS:
                counts[k] = int(f.attrs[k]) if k in f.attrs else None
            counts["config_hash"] = str(f.attrs["config_hash"])
            if f["depth"].shape[0] != counts["num_images"]:
                raise ValueError("depth rows do not match num_images")
            return counts
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"corrupt dataset shard {path}: {e}; delete it and re-run to regenerate it") from None


# Whether this process has run a shard task yet: its first one pays the imports and the
# first meshes' loading (a long run's rate leaves it out: `bench`'s labels_per_s_sustained).
_TASKS_RUN_HERE = 0


def _shard_task(shard_index: int, out: str, seed: int, split: str, scenario_yaml: str,
                config: dict, objects_dir: str | None, attrs: dict, num_scenes: int,
                tmp_tag: str) -> dict:
    """One worker task: generate the shard's scenes and write the shard."""
    global _TASKS_RUN_HERE
    first_here = _TASKS_RUN_HERE == 0
    _TASKS_RUN_HERE += 1
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import Scenario

    scenario = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    cfg = DatasetConfig(**config)
    library = load_library(objects_dir)
    path = Path(out) / shard_name(shard_index)
    scenes = shard_scene_range(shard_index, num_scenes=num_scenes,
                               scenes_per_shard=cfg.scenes_per_shard)
    t0 = time.perf_counter()
    samples, rejected = [], []
    for i in scenes:
        kept, replaced = fill_scene(i, seed=seed, split=split, scenario=scenario, config=cfg,
                                    library=library)
        samples.append(kept)
        rejected.extend(replaced)
    t_write = time.perf_counter()
    shard_attrs = {**attrs, "scene_first": scenes.start, "scene_stop": scenes.stop,
                   "num_attempts": len(samples) + len(rejected),
                   "num_replaced_no_grasp": sum(r.reason == "no_grasp" for r in rejected),
                   "num_replaced_unsettled": sum(r.reason == "unsettled" for r in rejected)}
    write_shard(path, samples, attrs=shard_attrs, tmp_tag=tmp_tag)
    counts = read_shard_counts(path)
    counts["seconds"] = time.perf_counter() - t0
    counts["first_in_process"] = first_here
    timings: dict = {"write": time.perf_counter() - t_write}
    for s in [*samples, *rejected]:
        for k, v in s.timings.items():
            timings[k] = timings.get(k, 0.0) + v
    counts["timings"] = timings
    return counts


# ----------------------------------------------------------------------------
# The whole dataset.


def write_manifest(out: Path, cfg: dict, *, tmp_tag: str | None = None) -> dict:
    """Rebuilds `manifest.json` from the finished shards (so counts are never doubled).

    Keys: num_scenes (labelled scenes), num_images, num_labels, num_shards, shards,
    num_scene_attempts (seeds tried), num_scenes_replaced (attempts not used, the sum
    of num_scenes_unsettled_resampled and num_scenes_no_grasp_resampled), config_hash,
    config, code_version, format_version.
    """
    out = Path(out)
    shards = sorted(out.glob("shard-*.h5"))
    totals = {"num_scenes": 0, "num_images": 0, "num_labels": 0, "num_scene_attempts": 0,
              "num_scenes_replaced": 0, "num_scenes_unsettled_resampled": 0,
              "num_scenes_no_grasp_resampled": 0}
    listing = []
    for path in shards:
        c = read_shard_counts(path)
        unsettled = c["num_replaced_unsettled"] or 0
        # Shards written without the split count their unused scenes in `skipped`.
        no_grasp = c["num_replaced_no_grasp"] if c["num_replaced_no_grasp"] is not None \
            else c["skipped"]
        totals["num_scenes"] += c["num_scenes"]
        totals["num_images"] += c["num_images"]
        totals["num_labels"] += c["num_labels"]
        totals["num_scenes_unsettled_resampled"] += unsettled
        totals["num_scenes_no_grasp_resampled"] += no_grasp
        totals["num_scenes_replaced"] += unsettled + no_grasp
        totals["num_scene_attempts"] += (c["num_attempts"] if c["num_attempts"] is not None
                                         else c["num_scenes"] + c["skipped"])
        entry = {"file": path.name, "num_scenes": c["num_scenes"],
                 "num_images": c["num_images"], "num_labels": c["num_labels"]}
        if c["scene_first"] is not None:
            entry.update(scene_first=c["scene_first"], scene_stop=c["scene_stop"])
        listing.append(entry)
    manifest = {**totals, "num_shards": len(shards), "shards": listing,
                "config_hash": config_hash(cfg), "config": cfg, "code_version": code_version(),
                "format_version": cfg.get("format_version", FORMAT_VERSION)}
    tmp = out / f"{MANIFEST}.{tmp_tag or 'write'}.{_process_tag()}.tmp"
    try:
        with open(tmp, "w") as f:
            f.write(json.dumps(manifest, indent=1))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out / MANIFEST)
        _fsync_dir(out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return manifest


def _check_existing_shards(out: Path, *, chash: str, num_scenes: int, scenes_per_shard: int,
                           num_shards: int) -> list[int]:
    """Shard indices still to write; refuses a folder holding more scenes than asked."""
    todo = []
    for i in range(num_shards):
        path = out / shard_name(i)
        if not path.exists():
            todo.append(i)
            continue
        c = read_shard_counts(path)
        if c["config_hash"] != chash:
            raise ValueError(f"{path}: made with a different configuration")
        if c["scene_first"] is None:
            raise ValueError(f"{path}: written without its scene range (an older format); "
                             "use another --out")
        want = shard_scene_range(i, num_scenes=num_scenes, scenes_per_shard=scenes_per_shard)
        have = range(c["scene_first"], c["scene_stop"])
        if have == want:
            continue
        if have.start == want.start and have.stop < want.stop:
            todo.append(i)  # the last shard of a smaller run: rewritten with more scenes
            continue
        raise ValueError(
            f"{path}: holds scenes {have.start}..{have.stop - 1} but --scenes {num_scenes} "
            f"puts scenes {want.start}..{want.stop - 1} in it; this folder holds a larger "
            f"dataset: use --scenes >= {have.stop} or another --out")
    beyond = sorted(p.name for p in out.glob("shard-*.h5")
                    if p.name not in {shard_name(i) for i in range(num_shards)})
    if beyond:
        raise ValueError(
            f"{out}: holds {', '.join(beyond)} beyond the {num_shards} shard(s) of --scenes "
            f"{num_scenes}; this folder holds a larger dataset: use a larger --scenes or "
            "another --out")
    return todo


def check_generate_args(*, split: str, num_scenes: int) -> None:
    """The split and scene count of a generator (this dataset's and GPD's).

    Raises:
        ValueError: naming the flag and what was expected.
    """
    if split not in ("train", "test"):
        raise ValueError(f"--split: expected train or test, got {split!r}")
    if num_scenes < 1:
        raise ValueError(f"--scenes: expected >= 1, got {num_scenes}")


def generate_dataset(*, out: str | Path, num_scenes: int, split: str, seed: int,
                     scenario, config: DatasetConfig | None = None, workers: int = 1,
                     scheduler: str | None = None, objects_dir: str | None = None,
                     progress: bool = True) -> dict:
    """Generates (or resumes) a dataset of exactly `num_scenes` scenes; returns the manifest.

    Args:
        out: output folder; finished shards there are kept and skipped.
        num_scenes: number of labelled scenes (the last shard may hold fewer than
            `scenes_per_shard`). A scene that does not settle or has no true grasp is
            replaced by the next seed of its own sequence (`scene_seed`).
        split: "train" or "test": which object instances the scenes use.
        seed: dataset seed; scene i uses `scene_seed(seed, i, attempt)`.
        scenario: the `Scenario` whose camera, depth noise, plant and scene settings apply.
        workers: local worker processes (ignored with `scheduler`).
        scheduler: address of a Dask distributed scheduler; None -> local processes.
        objects_dir: object library folder; None -> built-in objects.

    Raises:
        FolderInUseError: another generator holds `out` (the message names it).
        ValueError: a folder made with another configuration, or holding more scenes.
    """
    from drake_grasp.config.scenario import dump_scenario

    config = config or DatasetConfig()
    config.validate()
    check_generate_args(split=split, num_scenes=num_scenes)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = _config_dict(scenario, config, split, seed)
    chash = config_hash(cfg)
    with GenerateLock(out) as lock:
        if lock.stale_owner is not None:
            stale_token = str(lock.stale_owner.get("token", ""))
            leftovers = _temp_files(out, stale_token) if stale_token else []
            print(f"drake-grasp generate: taking over the stale lock {lock.path} of "
                  f"{_describe_owner(lock.stale_owner)}, which no longer runs; removing its "
                  f"{len(leftovers)} temporary file(s)", file=sys.stderr)
            for path in leftovers:
                path.unlink(missing_ok=True)
        try:
            return _generate_locked(out, cfg=cfg, chash=chash, num_scenes=num_scenes,
                                    split=split, seed=seed, scenario_yaml=dump_scenario(scenario),
                                    config=config, workers=workers, scheduler=scheduler,
                                    objects_dir=objects_dir, progress=progress,
                                    token=lock.token)
        finally:
            for path in _temp_files(out, lock.token):
                path.unlink(missing_ok=True)  # this run's own, from a failed worker


def _generate_locked(out: Path, *, cfg: dict, chash: str, num_scenes: int, split: str,
                     seed: int, scenario_yaml: str, config: DatasetConfig, workers: int,
                     scheduler: str | None, objects_dir, progress: bool, token: str) -> dict:
    old = out / MANIFEST
    if old.exists():
        previous = json.loads(old.read_text())
        if previous.get("config_hash") != chash:
            diff = [k for k in cfg if previous.get("config", {}).get(k) != cfg[k]]
            raise ValueError(f"{out}: holds a dataset made with a different configuration "
                             f"(differs in {diff}); use another --out")
    num_shards = -(-num_scenes // config.scenes_per_shard)
    todo = _check_existing_shards(out, chash=chash, num_scenes=num_scenes,
                                  scenes_per_shard=config.scenes_per_shard,
                                  num_shards=num_shards)
    attrs = {"split": split, "config_hash": chash, "code_version": code_version(),
             "format_version": FORMAT_VERSION}
    args = dict(out=str(out), seed=int(seed), split=split, scenario_yaml=scenario_yaml,
                config=dataclasses.asdict(config),
                objects_dir=str(objects_dir) if objects_dir else None, attrs=attrs,
                num_scenes=int(num_scenes), tmp_tag=token)
    timings, steady = _run_tasks(todo, args, workers=workers, scheduler=scheduler,
                                 progress=progress, total=num_shards,
                                 done=num_shards - len(todo))
    manifest = write_manifest(out, cfg, tmp_tag=token)
    if manifest["num_scenes"] != num_scenes:  # a bookkeeping error, never expected
        raise RuntimeError(f"{out}: holds {manifest['num_scenes']} scenes, expected {num_scenes}")
    # Summed worker seconds per stage of this run's shard tasks, and the labels and seconds
    # of the tasks that were not their process's first (returned, not written).
    manifest["run_timings_s"] = timings
    manifest["run_steady_labels"], manifest["run_steady_seconds"] = steady
    return manifest


def _run_tasks(todo: list[int], args: dict, *, workers: int, scheduler: str | None,
               progress: bool, total: int, done: int) -> tuple[dict, tuple[int, float]]:
    """Runs the shard tasks; returns the summed per-stage worker seconds, and the labels
    and summed seconds of the tasks that were not the first of their process."""
    from tqdm import tqdm

    bar = tqdm(total=total, initial=done, unit="shard", disable=not progress,
               desc="generate", dynamic_ncols=True)
    labels, steady_labels, steady_seconds = 0, 0, 0.0
    t0 = time.perf_counter()
    timings: dict = {}

    def tick(counts):
        nonlocal labels, steady_labels, steady_seconds
        labels += counts["num_labels"]
        if not counts["first_in_process"]:
            steady_labels += counts["num_labels"]
            steady_seconds += counts["seconds"]
        for k, v in counts.get("timings", {}).items():
            timings[k] = timings.get(k, 0.0) + v
        bar.update(1)
        bar.set_postfix(labels_per_s=f"{labels / (time.perf_counter() - t0):.0f}")

    try:
        if not todo:
            return timings, (steady_labels, steady_seconds)
        if scheduler:
            from dask.distributed import Client, as_completed

            with Client(scheduler) as client:
                futures = [client.submit(_shard_task, i, **args, pure=False) for i in todo]
                for fut in as_completed(futures):
                    tick(fut.result())
        elif workers <= 1:
            for i in todo:
                tick(_shard_task(i, **args))
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            ctx = mp.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                futures = [pool.submit(_shard_task, i, **args) for i in todo]
                for fut in as_completed(futures):
                    tick(fut.result())
    finally:
        bar.close()
    return timings, (steady_labels, steady_seconds)


# ----------------------------------------------------------------------------
# Reading.


def load_manifest(data_dir: str | Path) -> dict:
    path = Path(data_dir) / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no manifest; is {data_dir} a dataset folder?")
    return json.loads(path.read_text())


class DepthGraspDataset(Dataset):
    """A torch-style Dataset over shards, read lazily: item i is one depth image with its
    M labelled offsets: {"depth": (H, W), "offsets": (M, 3), "labels": (M,)} (float32).

    Shards are opened on first use in each process (safe with DataLoader workers).
    """

    def __init__(self, data_dir: str | Path):
        self.root = Path(data_dir)
        self.manifest = load_manifest(self.root)
        self._files = [self.root / s["file"] for s in self.manifest["shards"]]
        for path in self._files:
            if not path.is_file():
                raise FileNotFoundError(f"{path}: listed in the manifest but missing")
        counts = np.array([s["num_images"] for s in self.manifest["shards"]], dtype=np.int64)
        self._starts = np.concatenate([[0], np.cumsum(counts)])
        self._handles: dict = {}

    def __len__(self) -> int:
        return int(self._starts[-1])

    def _file(self, k: int):
        import h5py

        h = self._handles.get(k)
        if h is None:
            try:
                h = h5py.File(self._files[k], "r")
            except OSError as e:
                raise ValueError(f"corrupt dataset shard {self._files[k]}: {e}") from None
            self._handles[k] = h
        return h

    def locate(self, index: int) -> tuple[int, int]:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} images")
        k = int(np.searchsorted(self._starts, index, side="right") - 1)
        return k, int(index - self._starts[k])

    def __getitem__(self, index: int) -> dict:
        k, row = self.locate(int(index))
        f = self._file(k)
        try:
            return {"depth": np.asarray(f["depth"][row], np.float32),
                    "offsets": np.asarray(f["offsets"][row], np.float32),
                    "labels": np.asarray(f["labels"][row], np.float32)}
        except (OSError, KeyError) as e:
            raise ValueError(f"corrupt dataset shard {self._files[k]}: {e}") from None

    def image_record(self, index: int) -> dict:
        """The image with its hand pose, scene spec and the scene's grasps (for pictures)."""
        k, row = self.locate(int(index))
        f = self._file(k)
        scene = int(f["image_scene"][row])
        s_row = int(np.nonzero(f["scene_index"][:] == scene)[0][0])
        g = f["grasp_scene"][:] == scene
        spec = f["scene_spec"][s_row]
        return {**self[index], "hand_pose": f["hand_pose"][row], "scene_index": scene,
                "scene_spec": json.loads(spec.decode() if isinstance(spec, bytes) else spec),
                "grasp_pose": f["grasp_pose"][g], "grasp_width": f["grasp_width"][g],
                "grasp_xy_theta": f["grasp_xy_theta"][g]}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_handles"] = {}
        return state
