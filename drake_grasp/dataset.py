"""The simulated training set (the paper's section "Generating training data").

Per scene (a `random` scene of 1-5 objects from one split, settled by physics): the
ground-truth grasps (`grasps.find_grasps`), then K wrist depth images from hand poses
drawn at random in (x, y, z, theta) above the objects, each rendered by Drake's VTK
renderer and post-processed by the same `sensing.postprocess_depth` the Diagram uses,
and M offsets per image drawn uniformly within the camera's view, each labelled with its
distance to the nearest true grasp (`grasps.distance_to_nearest_grasp`).

On disk (this module owns the format):

    DIR/manifest.json           counts, resolved config, code version, shard list
    DIR/shard-00000.h5          scenes [0, S), one file per task of S scenes
    DIR/shard-00001.h5          ...

Each shard is written to `shard-XXXXX.h5.tmp` and renamed when complete, so a killed run
leaves no half-written shard; re-running the same command skips finished shards.
Shard layout (HDF5, chunked + gzip):

    depth        (I, H, W) float32   post-processed depth [m]
    hand_pose    (I, 4)    float64   [x, y, z, yaw_deg] of the grasp frame G (camera rigid on G)
    offsets      (I, M, 3) float32   actions [dx, dy, dtheta_deg] in the hand frame
    labels       (I, M)    float32   distance to the nearest true grasp [m]
    image_scene  (I,)      int64     global scene index of each image
    scene_index  (S,)      int64     global scene indices in this shard
    scene_spec   (S,)      str       SceneSpec JSON (re-render any sample from it)
    grasp_scene  (G,)      int64     global scene index of each grasp
    grasp_pose   (G, 4, 4) float64   world grasp-frame poses
    grasp_width  (G,)      float32
    grasp_xy_theta (G, 3)  float64   [x, y, theta_deg mod 180]
    attrs: split, config_hash, code_version, num_scenes, num_images, num_labels, skipped
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from drake_grasp import __version__

FORMAT_VERSION = 1
MANIFEST = "manifest.json"


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
    # Settling for data generation: tolerance and time cap.
    settle_speed_tol_m_s: float = 0.01
    settle_max_time_s: float = 1.5
    # Settling only has to bring objects to rest, not resolve a grasp: a coarser step
    # than the episodes' 2 ms is enough and makes generation faster.
    settle_time_step_s: float = 0.005
    # Friction coefficient of the force-closure test.
    friction_coefficient: float = 0.5

    def validate(self) -> None:
        for name in ("images_per_scene", "offsets_per_image", "scenes_per_shard"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if not 0 < self.camera_height_min_m <= self.camera_height_max_m:
            raise ValueError("camera_height_min_m/max_m: expected 0 < min <= max")


def _config_dict(scenario, config: DatasetConfig, split: str, seed: int) -> dict:
    from drake_grasp.scenario import dump_scenario

    return {"format_version": FORMAT_VERSION, "split": split, "seed": int(seed),
            "dataset": dataclasses.asdict(config), "scenario": dump_scenario(scenario)}


def config_hash(cfg: dict) -> str:
    return hashlib.sha256(json.dumps(cfg, sort_keys=True).encode()).hexdigest()[:16]


def scene_seed(seed: int, scene_index: int) -> int:
    """The seed of scene `scene_index` of a dataset generated with `seed`."""
    return int(np.random.default_rng([int(seed), int(scene_index), 31]).integers(2**31 - 1))


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


class SceneRenderer:
    """Renders the wrist depth image of a settled scene world from any hand pose."""

    def __init__(self, world, camera_config, renderer_name: str = "vtk"):
        from drake_grasp.station import gripper_frame_offsets, make_depth_camera

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
        from drake_grasp.station import topdown_pose

        x, y, z, yaw = (float(v) for v in hand_pose)
        X_WC = topdown_pose([x, y], z, np.deg2rad(yaw)) @ self._X_GC
        query = self._world.scene_graph.get_query_output_port().Eval(self._sg_context)
        image = query.RenderDepthImage(self._camera, self._frame, X_WC)
        return np.array(image.data[:, :, 0], copy=True)


def generate_scene(scene_index: int, *, seed: int, split: str, scenario, config: DatasetConfig,
                   library) -> SceneSamples | None:
    """Settles one random scene, finds its grasps, renders K images and labels M offsets.

    Returns None when the scene has no ground-truth grasp (nothing to learn from).
    """
    from drake_grasp.actions import apply_actions, sample_actions_in_view
    from drake_grasp.grasps import distance_to_nearest_grasp, find_grasps
    from drake_grasp.scene import build_scene_world, sample_scene, settle_world
    from drake_grasp.sensing import frame_rng, postprocess_depth

    timings: dict = {}
    clock = time.perf_counter()

    def lap(name):
        nonlocal clock
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock
        clock = now

    s_seed = scene_seed(seed, scene_index)
    scene_cfg = dataclasses.replace(scenario.scene, kind="random", split=split, object_ids=[])
    spec = sample_scene(scene_cfg, s_seed, library)
    plant_config = copy.deepcopy(scenario.plant)  # a Drake config: no dataclasses.replace
    plant_config.time_step = config.settle_time_step_s
    world = build_scene_world(spec, library, plant_config=plant_config, renderer_name="vtk")
    lap("build")
    settled = settle_world(world, spec, speed_tol_m_s=config.settle_speed_tol_m_s,
                           max_time_s=config.settle_max_time_s)
    lap("settle")
    rng = np.random.default_rng([s_seed, 1])
    grasps = find_grasps(settled, library, rng, mu=config.friction_coefficient)
    lap("grasps")
    if len(grasps.xy_theta) == 0:
        return None
    renderer = SceneRenderer(world, scenario.camera)
    K, M = config.images_per_scene, config.offsets_per_image
    cx, cy = settled.center_xy_m
    h = config.hand_xy_half_extent_m
    cam_height = rng.uniform(config.camera_height_min_m, config.camera_height_max_m, K)
    X_GC = renderer.X_GC.translation()
    hand = np.stack([rng.uniform(cx - h, cx + h, K), rng.uniform(cy - h, cy + h, K),
                     cam_height + X_GC[2], rng.uniform(-180.0, 180.0, K)], axis=1)
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
        grasp_xy_theta=np.asarray(grasps.xy_theta, float), timings=timings)


# ----------------------------------------------------------------------------
# Shards.


def shard_name(shard_index: int) -> str:
    return f"shard-{shard_index:05d}.h5"


def write_shard(path: Path, samples: list[SceneSamples], *, attrs: dict) -> None:
    """Writes a shard atomically: `path.tmp`, then renamed to `path`."""
    import h5py

    tmp = path.with_name(path.name + ".tmp")
    kept = [s for s in samples if s is not None]
    with h5py.File(tmp, "w") as f:
        def put(name, arrays, dtype, shape_tail):
            data = np.concatenate(arrays) if arrays else np.zeros((0, *shape_tail), dtype)
            chunks = (min(64, max(1, len(data))), *shape_tail) if len(data) else None
            f.create_dataset(name, data=data.astype(dtype), chunks=chunks,
                             compression="gzip" if len(data) else None, compression_opts=4 if len(data) else None)

        hw = kept[0].depth.shape[1:] if kept else (0, 0)
        m = kept[0].offsets.shape[1] if kept else 0
        put("depth", [s.depth for s in kept], np.float32, hw)
        put("hand_pose", [s.hand_pose for s in kept], np.float64, (4,))
        put("offsets", [s.offsets for s in kept], np.float32, (m, 3))
        put("labels", [s.labels for s in kept], np.float32, (m,))
        put("image_scene", [np.full(len(s.depth), s.scene_index) for s in kept], np.int64, ())
        put("grasp_scene", [np.full(len(s.grasp_width), s.scene_index) for s in kept], np.int64, ())
        put("grasp_pose", [s.grasp_pose for s in kept], np.float64, (4, 4))
        put("grasp_width", [s.grasp_width for s in kept], np.float32, ())
        put("grasp_xy_theta", [s.grasp_xy_theta for s in kept], np.float64, (3,))
        f.create_dataset("scene_index", data=np.array([s.scene_index for s in kept], np.int64))
        f.create_dataset("scene_spec", data=[s.spec_json for s in kept],
                         dtype=h5py.string_dtype())
        num_images = int(sum(len(s.depth) for s in kept))
        f.attrs.update(attrs)
        f.attrs["num_scenes"] = len(kept)
        f.attrs["num_images"] = num_images
        f.attrs["num_labels"] = int(sum(s.labels.size for s in kept))
        f.attrs["skipped"] = len(samples) - len(kept)
    os.replace(tmp, path)


def read_shard_counts(path: Path) -> dict:
    """Counts and attrs of a finished shard; a corrupt file is reported by name."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            counts = {k: int(f.attrs[k]) for k in ("num_scenes", "num_images", "num_labels", "skipped")}
            counts["config_hash"] = str(f.attrs["config_hash"])
            if f["depth"].shape[0] != counts["num_images"]:
                raise ValueError("depth rows do not match num_images")
            return counts
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"corrupt dataset shard {path}: {e}; delete it and re-run to regenerate it") from None


def _shard_task(shard_index: int, out: str, seed: int, split: str, scenario_yaml: str,
                config: dict, objects_dir: str | None, attrs: dict) -> dict:
    """One worker task: generate the shard's scenes and write the shard."""
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.objects import load_library
    from drake_grasp.scenario import Scenario

    scenario = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    cfg = DatasetConfig(**config)
    library = load_library(objects_dir)
    path = Path(out) / shard_name(shard_index)
    first = shard_index * cfg.scenes_per_shard
    t0 = time.perf_counter()
    samples = [generate_scene(i, seed=seed, split=split, scenario=scenario, config=cfg,
                              library=library)
               for i in range(first, first + cfg.scenes_per_shard)]
    t_write = time.perf_counter()
    write_shard(path, samples, attrs=attrs)
    counts = read_shard_counts(path)
    counts["seconds"] = time.perf_counter() - t0
    timings: dict = {"write": time.perf_counter() - t_write}
    for s in samples:
        for k, v in (s.timings if s is not None else {}).items():
            timings[k] = timings.get(k, 0.0) + v
    counts["timings"] = timings
    return counts


# ----------------------------------------------------------------------------
# The whole dataset.


def write_manifest(out: Path, cfg: dict) -> dict:
    """Rebuilds `manifest.json` from the finished shards (so counts are never doubled)."""
    shards = sorted(out.glob("shard-*.h5"))
    totals = {"num_scenes": 0, "num_images": 0, "num_labels": 0, "num_scenes_skipped": 0}
    listing = []
    for path in shards:
        c = read_shard_counts(path)
        totals["num_scenes"] += c["num_scenes"]
        totals["num_images"] += c["num_images"]
        totals["num_labels"] += c["num_labels"]
        totals["num_scenes_skipped"] += c["skipped"]
        listing.append({"file": path.name, "num_scenes": c["num_scenes"],
                        "num_images": c["num_images"], "num_labels": c["num_labels"]})
    manifest = {**totals, "num_shards": len(shards), "shards": listing,
                "config_hash": config_hash(cfg), "config": cfg, "code_version": __version__}
    tmp = out / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, out / MANIFEST)
    return manifest


def generate_dataset(*, out: str | Path, num_scenes: int, split: str, seed: int,
                     scenario, config: DatasetConfig | None = None, workers: int = 1,
                     scheduler: str | None = None, objects_dir: str | None = None,
                     progress: bool = True) -> dict:
    """Generates (or resumes) a dataset of `num_scenes` scenes; returns the manifest.

    Args:
        out: output folder; finished shards there are kept and skipped.
        num_scenes: number of scenes (rounded up to whole shards).
        split: "train" or "test": which object instances the scenes use.
        seed: dataset seed; scene i uses `scene_seed(seed, i)`.
        scenario: the `Scenario` whose camera, depth noise, plant and scene settings apply.
        workers: local worker processes (ignored with `scheduler`).
        scheduler: address of a Dask distributed scheduler; None -> local processes.
        objects_dir: object library folder; None -> built-in objects.
    """
    from drake_grasp.scenario import dump_scenario

    config = config or DatasetConfig()
    config.validate()
    if split not in ("train", "test"):
        raise ValueError(f"--split: expected train or test, got {split!r}")
    if num_scenes < 1:
        raise ValueError(f"--scenes: expected >= 1, got {num_scenes}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = _config_dict(scenario, config, split, seed)
    chash = config_hash(cfg)
    old = out / MANIFEST
    if old.exists():
        previous = json.loads(old.read_text())
        if previous.get("config_hash") != chash:
            diff = [k for k in cfg if previous.get("config", {}).get(k) != cfg[k]]
            raise ValueError(f"{out}: holds a dataset made with a different configuration "
                             f"(differs in {diff}); use another --out")
    for stale in out.glob("shard-*.h5.tmp"):
        stale.unlink()  # left by a killed run; regenerated below
    num_shards = -(-num_scenes // config.scenes_per_shard)
    todo = []
    for i in range(num_shards):
        path = out / shard_name(i)
        if path.exists():
            if read_shard_counts(path)["config_hash"] != chash:
                raise ValueError(f"{path}: made with a different configuration")
            continue
        todo.append(i)
    attrs = {"split": split, "config_hash": chash, "code_version": __version__,
             "format_version": FORMAT_VERSION}
    args = dict(out=str(out), seed=int(seed), split=split, scenario_yaml=dump_scenario(scenario),
                config=dataclasses.asdict(config),
                objects_dir=str(objects_dir) if objects_dir else None, attrs=attrs)
    timings = _run_tasks(todo, args, workers=workers, scheduler=scheduler, progress=progress,
                         total=num_shards, done=num_shards - len(todo))
    manifest = write_manifest(out, cfg)
    # Summed worker seconds per stage of this run (returned, not written).
    manifest["run_timings_s"] = timings
    return manifest


def _run_tasks(todo: list[int], args: dict, *, workers: int, scheduler: str | None,
               progress: bool, total: int, done: int) -> dict:
    """Runs the shard tasks; returns the summed per-stage worker seconds."""
    from tqdm import tqdm

    bar = tqdm(total=total, initial=done, unit="shard", disable=not progress,
               desc="generate", dynamic_ncols=True)
    labels = 0
    t0 = time.perf_counter()
    timings: dict = {}

    def tick(counts):
        nonlocal labels
        labels += counts["num_labels"]
        for k, v in counts.get("timings", {}).items():
            timings[k] = timings.get(k, 0.0) + v
        bar.update(1)
        bar.set_postfix(labels_per_s=f"{labels / (time.perf_counter() - t0):.0f}")

    try:
        if not todo:
            return timings
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
    return timings


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
