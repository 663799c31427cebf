"""Training data and training of GPD's grasp classifier (`drake_grasp.policies.gpd`).

Data (`generate`): seeded scenes like the experiments' (isolation, 1-5 objects at random,
poured piles), settled by physics; the GPD sensor's view from the viewpoint above the
scene (jittered in position, height and yaw, and with the sensor's noise model on for a
share of the scenes); GPD's candidates on that cloud (`gpd.sample_hands`); each labelled
by this project's ground truth (`grasps.check_grasp_poses` on the true object surfaces
with the dataset's friction and gravity-and-shake torque limits: the labels whose
precision `drake-grasp label-check` measured in physics); a class-balanced subset of
them kept with its grasp images. One `.npz` shard per `scenes_per_shard` scenes, written
under a temporary name and renamed when complete, so a killed run resumes where it
stopped. Splits use disjoint object instances ("train" / "test").

Training (`train`): Adam on the class-weighted binary cross-entropy, a checkpoint after
every epoch (a killed run resumes from it), then precision and recall on the held-out
instances, the weights as safetensors and `metrics.json`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drake_grasp.policies import gpd
from drake_grasp.core.provenance import file_sha256

SHARD_FORMAT = "drake_grasp.gpd_data/1"


@dataclass
class GpdDataConfig:
    """How GPD's training candidates are sampled and labelled."""

    # Scene kinds, drawn in turn (scene i gets kinds[i % len]).
    scene_kinds: tuple = ("isolation", "random", "clutter")
    # Candidates kept per scene: every positive up to a quarter of them, negatives fill
    # up (among all candidates a scene has about 4% positives; more negatives than
    # positives teach the classifier the confident false positives that top-1 selection
    # would otherwise pick).
    candidates_per_scene: int = 600
    max_positive_fraction: float = 0.25
    # Viewpoint jitter about the experiments' viewpoint (scene centre, gpd height, yaw 0).
    view_xy_jitter_m: float = 0.03
    view_height_jitter_m: float = 0.05
    # Share of scenes whose image gets the sensor's noise model (gpd.noise, enabled).
    noisy_fraction: float = 0.25
    scenes_per_shard: int = 5
    # Ground truth: the dataset's friction and torque limit (dataset.DatasetConfig).
    friction_coefficient: float = 0.25
    max_torque_ratio: float = 0.12
    settle_time_step_s: float = 0.005
    settle_max_time_s: float = 2.0
    settle_speed_tol_m_s: float = 0.01
    # Independent surface samplings the ground truth runs on (see `generate_scene`), and
    # whether candidates they disagree on are left out of the data.
    label_samplings: int = 2
    drop_ambiguous: bool = True
    # Object categories every scene holds one instance of (drawn uniformly among their
    # instances of the split; the scene's other objects drawn as usual): more data of the
    # categories the classifier gets wrong. Empty: objects drawn as the experiments do.
    focus_categories: tuple = ()


def focus_object_ids(library, categories, split: str, seed: int, slots: int = 1) -> list[str]:
    """The object ids a scene with focus `categories` draws from, in order: every instance
    of the split but one in random order, with one instance of those categories put at a
    random place among the first `slots` (`scene.sample_scene` takes the first as many as
    the scene holds, and a poured pile stacks them in that order, so a pile's focus object
    is not always at its bottom). Seeded by `seed`.

    Raises:
        ValueError: a category without instances in the split, named with the known ones.
    """
    rng = np.random.default_rng([int(seed), 63])
    per_category = {c: library.ids(split=split, category=c) for c in categories}
    missing = [c for c, ids in per_category.items() if not ids]
    if missing or not per_category:
        raise ValueError(f"focus categories {list(categories)}: no {split!r} instances of "
                         f"{missing or list(categories)} (categories: {library.categories()})")
    focus = sorted(i for ids in per_category.values() for i in ids)
    chosen = focus[int(rng.integers(len(focus)))]
    others = [i for i in library.ids(split=split) if i != chosen]
    ids = [others[int(k)] for k in rng.permutation(len(others))]
    ids.insert(int(rng.integers(max(1, int(slots)))), chosen)
    return ids


def _render_view(world, camera, X_WC: np.ndarray) -> np.ndarray:
    from pydrake.math import RigidTransform

    sg = world.scene_graph
    ctx = sg.GetMyContextFromRoot(world.simulator.get_context())
    image = sg.get_query_output_port().Eval(ctx).RenderDepthImage(
        camera, sg.world_frame_id(), RigidTransform(X_WC))
    return np.array(image.data[:, :, 0], copy=True)


def view_pose(center_xy, camera_height_m: float, yaw_rad: float = 0.0) -> np.ndarray:
    """X_WC of a camera `camera_height_m` above the table over `center_xy`, looking down
    (Drake's camera frame: +z the optical axis)."""
    from drake_grasp.geometry.hand_model import topdown_rotation

    X = np.eye(4)
    X[:3, :3] = topdown_rotation(yaw_rad)
    X[:3, 3] = [center_xy[0], center_xy[1], camera_height_m]
    return X


def ground_truth_passes(settled, library, poses, rng: np.random.Generator,
                        config: GpdDataConfig, *, samplings: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The labelling check of GPD candidates: on how many of `samplings` independent
    surface samplings of the true objects each pose passes the ground truth
    (`grasps.check_grasp_poses` with `config`'s friction and torque limits), and the
    one object both its pads touch (index into the scene's objects; -1: none, or two
    different objects) from the first sampling that finds one. No pose: nothing is drawn
    from `rng`."""
    from drake_grasp.geometry.hand_checks import check_grasp_poses
    from drake_grasp.geometry.scene_samples import ObjectMasses, sample_scene_points, scene_meshes

    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    passes = np.zeros(len(poses), dtype=np.int64)
    obj = np.full(len(poses), -1, dtype=np.int64)
    if len(poses) == 0:
        return passes, obj
    meshes = scene_meshes(settled, library)
    masses = ObjectMasses.of_scene(settled, library)
    for _ in range(samplings):
        fine = sample_scene_points(meshes, rng, spacing_m=0.003)
        coarse = sample_scene_points(meshes, rng, spacing_m=0.005)
        check = check_grasp_poses(poses, fine, collision_points=coarse,
                                  mu=config.friction_coefficient, objects=masses,
                                  max_torque_ratio=config.max_torque_ratio)
        passes += check.valid
        obj = np.where(obj < 0, check.object_index, obj)
    return passes, obj


def experiment_view(scenario, seed: int, library, *, split: str = "test"):
    """A scene of `scenario`'s kind (object `split`), settled as the episodes settle it,
    and the GPD sensor's image from the experiments' viewpoint (over the scene centre,
    `gpd.view_camera_height_m`, yaw 0): (settled spec, X_WC, depth)."""
    from drake_grasp.world.scene import build_scene_world, sample_scene, settle_world
    from drake_grasp.world.station import make_depth_camera

    spec = sample_scene(dataclasses.replace(scenario.scene, split=split), seed, library)
    world = build_scene_world(spec, library, renderer_name="vtk", physics=scenario.physics)
    settled = settle_world(world, spec)
    X_WC = view_pose(settled.center_xy_m, scenario.gpd.view_camera_height_m)
    return settled, X_WC, _render_view(world, make_depth_camera(scenario.gpd), X_WC)


def generate_scene(index: int, *, seed: int, split: str, scenario, config: GpdDataConfig,
                   library) -> dict:
    """One scene's labelled candidates (see the module docstring)."""
    import copy

    from drake_grasp.learning.dataset import scene_seed
    from drake_grasp.world.scene import build_scene_world, sample_scene, settle_world
    from drake_grasp.geometry.sensing import apply_depth_noise
    from drake_grasp.world.station import make_depth_camera

    kind = config.scene_kinds[index % len(config.scene_kinds)]
    for attempt in range(20):
        s_seed = scene_seed(seed, index, attempt)
        ids = []
        if config.focus_categories:
            slots = scenario.scene.clutter_objects if kind == "clutter" else 1
            ids = focus_object_ids(library, config.focus_categories, split, s_seed, slots)
        scene_cfg = dataclasses.replace(scenario.scene, kind=kind, split=split, object_ids=ids)
        spec = sample_scene(scene_cfg, s_seed, library)
        plant_config = copy.deepcopy(scenario.plant)
        plant_config.time_step = config.settle_time_step_s
        world = build_scene_world(spec, library, plant_config=plant_config, renderer_name="vtk",
                                  physics=scenario.physics)
        settled = settle_world(world, spec, speed_tol_m_s=config.settle_speed_tol_m_s,
                               max_time_s=config.settle_max_time_s)
        if settled.settled and settled.objects:
            break
    else:
        raise ValueError(f"scene {index}: no seed of 20 settled (split {split!r}, kind {kind!r})")
    rng = np.random.default_rng([s_seed, 61])
    g = scenario.gpd
    cx, cy = settled.center_xy_m
    j = config.view_xy_jitter_m
    height = g.view_camera_height_m + rng.uniform(-1.0, 1.0) * config.view_height_jitter_m
    X_WC = view_pose([cx + rng.uniform(-j, j), cy + rng.uniform(-j, j)], height,
                     rng.uniform(-np.pi, np.pi))
    depth = _render_view(world, make_depth_camera(g), X_WC)
    noisy = bool(rng.random() < config.noisy_fraction)
    if noisy:
        depth = apply_depth_noise(depth, rng, dataclasses.replace(g.noise, enabled=True))
    cloud = gpd.cloud_from_depth(depth, fov_y_deg=g.fov_y_deg, X_WC=X_WC,
                                 depth_min_m=g.depth_min_m, depth_max_m=g.depth_max_m,
                                 center_xy=(cx, cy))
    hands = gpd.sample_hands(cloud, rng, gpd.HandSearch(approach_max_tilt_deg=g.approach_max_tilt_deg))
    # The ground truth on `label_samplings` independent surface samplings: a candidate
    # near a threshold (width, friction cone, torque) can pass on one and fail on another;
    # it is a positive only when it passes on all, a negative only when it fails on all,
    # and otherwise left out (`drop_ambiguous`) or counted negative.
    passes, obj = ground_truth_passes(settled, library, hands.poses, rng, config,
                                      samplings=config.label_samplings)
    valid = passes == config.label_samplings
    ambiguous = (passes > 0) & ~valid
    usable = ~ambiguous if config.drop_ambiguous else np.ones(len(hands), dtype=bool)
    valid_all = valid
    valid = valid & usable
    pos, neg = np.flatnonzero(valid), np.flatnonzero(~valid & usable)
    n = config.candidates_per_scene
    pos = rng.permutation(pos)[: int(n * config.max_positive_fraction)]
    neg = rng.permutation(neg)[: n - len(pos)]
    keep = np.sort(np.concatenate([pos, neg]))
    images = gpd.grasp_images(cloud, hands.poses[keep])
    ids = settled.object_ids()
    # The object each candidate's pads touch (ground truth), "" where none.
    touched = [ids[i] if 0 <= i < len(ids) else "" for i in obj[keep]]
    categories = [library.get(i).category if i else "" for i in touched]
    return dict(
        images=np.round(images * 255.0).astype(np.uint8),
        labels=valid[keep].astype(np.uint8),
        poses=hands.poses[keep].astype(np.float32),
        category=np.array(categories, dtype="U32"),
        scene=np.full(len(keep), index, np.int32),
        stats=dict(scene=index, kind=kind, seed=int(s_seed), noisy=noisy,
                   cloud_points=len(cloud), candidates=len(hands), positives=int(valid_all.sum()),
                   ambiguous=int(ambiguous.sum()),
                   objects=len(ids), object_ids=list(ids)),
    )


def _shard_path(out: Path, k: int) -> Path:
    return out / f"gpd-shard-{k:05d}.npz"


def _write_shard(path: Path, scenes: list[dict], meta: dict) -> None:
    cat = lambda key: np.concatenate([s[key] for s in scenes])  # noqa: E731
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        np.savez_compressed(f, images=cat("images"), labels=cat("labels"), poses=cat("poses"),
                            category=cat("category"), scene=cat("scene"),
                            meta=np.array(json.dumps({**meta, "scenes": [s["stats"] for s in scenes]})))
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path)


def _shard_task(k: int, out: str, seed: int, split: str, scenario_yaml: str, config: dict,
                num_scenes: int, objects_dir: str | None, meta: dict) -> dict:
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import Scenario

    scenario = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    cfg = GpdDataConfig(**{**config, "scene_kinds": tuple(config["scene_kinds"])})
    library = load_library(objects_dir)
    first = k * cfg.scenes_per_shard
    stop = min(num_scenes, first + cfg.scenes_per_shard)
    t0 = time.perf_counter()
    scenes = [generate_scene(i, seed=seed, split=split, scenario=scenario, config=cfg,
                             library=library) for i in range(first, stop)]
    _write_shard(_shard_path(Path(out), k), scenes, meta)
    return dict(shard=k, seconds=time.perf_counter() - t0,
                candidates=int(sum(len(s["labels"]) for s in scenes)))


def generate(*, out: str | Path, num_scenes: int, split: str, seed: int, scenario,
             config: GpdDataConfig | None = None, workers: int = 1,
             objects_dir: str | None = None, progress: bool = True) -> dict:
    """Generates (or resumes) `num_scenes` scenes of labelled GPD candidates in `out`.

    Raises:
        ValueError: a bad split or count, or a folder made with another configuration.
    """
    from tqdm import tqdm

    from drake_grasp.learning.dataset_generate import check_generate_args
    from drake_grasp.learning.folder_lock import GenerateLock
    from drake_grasp.core.provenance import code_version
    from drake_grasp.config.scenario import dump_scenario

    config = config or GpdDataConfig()
    check_generate_args(split=split, num_scenes=num_scenes)
    if config.focus_categories:  # refused before any folder is made
        from drake_grasp.objects import load_library

        focus_object_ids(load_library(objects_dir), config.focus_categories, split, seed)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario_yaml = dump_scenario(scenario)
    ident = dict(split=split, seed=int(seed), num_scenes=int(num_scenes),
                 config=dataclasses.asdict(config), gpd=dataclasses.asdict(scenario.gpd),
                 objects_dir=str(objects_dir or ""), format=SHARD_FORMAT)
    ident["config"]["scene_kinds"] = list(config.scene_kinds)
    # Folders made before focus categories existed keep their identity.
    if config.focus_categories:
        ident["config"]["focus_categories"] = list(config.focus_categories)
    else:
        del ident["config"]["focus_categories"]
    manifest_path = out / "manifest.json"
    with GenerateLock(out):
        if manifest_path.exists():
            old = json.loads(manifest_path.read_text())
            diff = [k for k in ident if old.get("identity", {}).get(k) != ident[k]]
            if diff:
                raise ValueError(f"{out}: holds GPD data made with different settings "
                                 f"(differs in {diff}); use another --out")
        else:
            tmp = manifest_path.with_name("manifest.json.tmp")
            tmp.write_text(json.dumps({"identity": ident, "complete": False}, indent=1))
            tmp.replace(manifest_path)
        for stale in out.glob("*.npz.tmp-*"):
            stale.unlink()
        num_shards = -(-num_scenes // config.scenes_per_shard)
        todo = [k for k in range(num_shards) if not _shard_path(out, k).exists()]
        meta = dict(split=split, code_version=code_version(), format=SHARD_FORMAT)
        args = dict(out=str(out), seed=int(seed), split=split, scenario_yaml=scenario_yaml,
                    config=ident["config"], num_scenes=int(num_scenes),
                    objects_dir=str(objects_dir) if objects_dir else None, meta=meta)
        bar = tqdm(total=num_shards, initial=num_shards - len(todo), unit="shard",
                   desc="gpd-generate", disable=not progress, dynamic_ncols=True)
        if workers <= 1:
            for k in todo:
                _shard_task(k, **args)
                bar.update()
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
                for fut in as_completed([pool.submit(_shard_task, k, **args) for k in todo]):
                    fut.result()
                    bar.update()
        bar.close()
        data = load_data(out, require_complete=False)
        summary = dict(identity=ident, complete=True, num_scenes=num_scenes,
                       candidates=int(len(data["labels"])), positives=int(data["labels"].sum()),
                       scene_stats=data["scene_stats"])
        tmp = manifest_path.with_name("manifest.json.tmp")
        tmp.write_text(json.dumps(summary, indent=1))
        tmp.replace(manifest_path)
        return summary


def load_data(folder: str | Path, *, require_complete: bool = True) -> dict:
    """All shards of a folder: images uint8 (N, 15, S, S), labels, poses, category, scene.

    Raises:
        ValueError: no shards, an incomplete folder (generation still to finish), or a
            shard of another format.
    """
    folder = Path(folder)
    manifest = folder / "manifest.json"
    if require_complete and (not manifest.exists()
                             or not json.loads(manifest.read_text()).get("complete")):
        raise ValueError(f"{folder}: not a complete GPD data folder (no complete manifest.json; "
                         "run or resume `drake-grasp gpd-generate` there)")
    shards = sorted(folder.glob("gpd-shard-*.npz"))
    if not shards:
        raise ValueError(f"{folder}: holds no gpd-shard-*.npz files")
    parts: dict = {k: [] for k in ("images", "labels", "poses", "category", "scene")}
    stats = []
    for path in shards:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            if meta.get("format") != SHARD_FORMAT:
                raise ValueError(f"{path}: format {meta.get('format')!r}, expected {SHARD_FORMAT!r}")
            for k in parts:
                parts[k].append(z[k])
            stats.extend(meta["scenes"])
    out = {k: np.concatenate(v) for k, v in parts.items()}
    out["scene_stats"] = stats
    return out


def load_data_folders(folders) -> dict:
    """`load_data` of one folder, or of several (a list, or one string with commas:
    "data/a,data/b"), concatenated in the order given."""
    if isinstance(folders, (str, Path)):
        folders = str(folders).split(",")
    names = [str(f) for f in folders if str(f)]
    if not names:
        raise ValueError(f"data folders: none given ({folders!r})")
    sets = [load_data(f) for f in names]
    out = {k: np.concatenate([s[k] for s in sets]) for k in sets[0] if k != "scene_stats"}
    out["scene_stats"] = [row for s in sets for row in s["scene_stats"]]
    return out


# ----------------------------------------------------------------------------
# Training.


@dataclass
class GpdTrainConfig:
    epochs: int = 12
    batch_size: int = 256
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    threads: int = 2


def precision_recall(prob: np.ndarray, labels: np.ndarray, threshold: float = 0.5) -> dict:
    pred = prob >= threshold
    tp = int(np.sum(pred & (labels == 1)))
    fp = int(np.sum(pred & (labels == 0)))
    fn = int(np.sum(~pred & (labels == 1)))
    return dict(threshold=threshold, precision=tp / max(tp + fp, 1), recall=tp / max(tp + fn, 1),
                accuracy=float(np.mean(pred == (labels == 1))), tp=tp, fp=fp, fn=fn,
                num=int(len(labels)), positives=int(labels.sum()))


def held_out_metrics(prob: np.ndarray, labels: np.ndarray, category: np.ndarray,
                     thresholds=(0.5, 0.7, 0.9)) -> dict:
    """Precision and recall at each threshold, over all candidates and per object category
    (the category of the one object both pads touch, by the ground truth's surface
    sampling; `NO_SINGLE_OBJECT` where the pads touch none, or two different objects).

    Returns:
        {"held_out": {"0.5": precision_recall, ...},
         "by_category": {category: {"0.5": precision_recall, ...}}}
    """
    from drake_grasp.objects.categories import NO_SINGLE_OBJECT

    prob, labels = np.asarray(prob), np.asarray(labels)
    category = np.asarray(category)
    if not len(prob) == len(labels) == len(category):
        raise ValueError(f"held_out_metrics: {len(prob)} probabilities, {len(labels)} labels, "
                         f"{len(category)} categories (expected one of each per candidate)")
    names = np.where(category == "", NO_SINGLE_OBJECT, category)
    return dict(
        held_out={f"{t:.1f}": precision_recall(prob, labels, t) for t in thresholds},
        by_category={str(c): {f"{t:.1f}": precision_recall(prob[names == c], labels[names == c], t)
                              for t in thresholds}
                     for c in sorted(set(names.tolist()))})


def evaluate_classifier(*, weights: str | Path = "", data, threads: int = 2) -> dict:
    """`held_out_metrics` of a classifier (`gpd.load_classifier(weights)`; "" is the shipped
    one) on gpd-generate folders (`load_data_folders`), with the weights' sha256."""
    import torch

    torch.set_num_threads(max(1, int(threads)))
    model = gpd.load_classifier(weights)
    path = Path(weights) if weights else gpd.default_weights_path()
    test_set = load_data_folders(data)
    out = held_out_metrics(_predict(model, test_set["images"]), test_set["labels"],
                           test_set["category"])
    return dict(weights=str(weights) or "shipped", weights_sha256=file_sha256(path),
                data=str(data), candidates=int(len(test_set["labels"])),
                positives=int(test_set["labels"].sum()),
                scenes=len(test_set["scene_stats"]), **out)


def _predict(model, images: np.ndarray, batch: int = 1024) -> np.ndarray:
    import torch

    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            x = torch.from_numpy(images[i:i + batch].astype(np.float32) / 255.0)
            out.append(torch.sigmoid(model(x)).numpy())
    return np.concatenate(out) if out else np.zeros(0)


def train(*, data: str | Path, test_data: str | Path, out: str | Path,
          config: GpdTrainConfig | None = None, progress: bool = True) -> dict:
    """Trains the classifier; resumes from `out/checkpoint.pt`; returns the metrics."""
    import torch
    from tqdm import tqdm

    config = config or GpdTrainConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(max(1, config.threads))
    train_set, test_set = load_data_folders(data), load_data(test_data)
    X, y = train_set["images"], train_set["labels"].astype(np.float32)
    gen = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    model = gpd.GraspClassifier(X.shape[-1])
    opt = torch.optim.Adam(model.parameters(), lr=config.learning_rate,
                           weight_decay=config.weight_decay)
    pos_weight = torch.tensor(float((1 - y).sum() / max(y.sum(), 1)))
    loss_fn = torch.nn.BCEWithLogitsLoss(pos_weight=pos_weight)
    ckpt = out / "checkpoint.pt"
    history: list[dict] = []
    start = 0
    if ckpt.exists():
        state = torch.load(ckpt, weights_only=True)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        history = json.loads(state["history"])
        start = int(state["epoch"])
    t_start = time.perf_counter()
    for epoch in range(start, config.epochs):
        model.train()
        perm = torch.randperm(len(X), generator=gen).numpy()
        total, count = 0.0, 0
        t0 = time.perf_counter()
        bar = tqdm(range(0, len(X), config.batch_size), desc=f"gpd-train epoch {epoch + 1}",
                   disable=not progress, dynamic_ncols=True, leave=False)
        for i in bar:
            idx = np.sort(perm[i:i + config.batch_size])
            xb = torch.from_numpy(X[idx].astype(np.float32) / 255.0)
            loss = loss_fn(model(xb), torch.from_numpy(y[idx]))
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
            count += len(idx)
        p_test = _predict(model, test_set["images"])
        pr = precision_recall(p_test, test_set["labels"])
        history.append(dict(epoch=epoch + 1, train_loss=total / count, seconds=time.perf_counter() - t0,
                            test=pr))
        tmp = ckpt.with_name("checkpoint.pt.tmp")
        torch.save(dict(model=model.state_dict(), optimizer=opt.state_dict(),
                        generator=gen.get_state(), history=json.dumps(history), epoch=epoch + 1), tmp)
        tmp.replace(ckpt)
        if progress:
            print(f"epoch {epoch + 1}: train loss {total / count:.4f}, held-out precision "
                  f"{pr['precision']:.3f} recall {pr['recall']:.3f}", flush=True)
    p_test = _predict(model, test_set["images"])
    held = held_out_metrics(p_test, test_set["labels"], test_set["category"])
    metrics = dict(
        train=dict(folder=str(data), candidates=int(len(y)), positives=int(y.sum()),
                   scenes=len(train_set["scene_stats"])),
        test=dict(folder=str(test_data), candidates=int(len(test_set["labels"])),
                  positives=int(test_set["labels"].sum()), scenes=len(test_set["scene_stats"])),
        config=dataclasses.asdict(config), history=history, held_out=held["held_out"],
        held_out_by_category=held["by_category"],
        seconds_this_run=time.perf_counter() - t_start)
    gpd.save_classifier(model, out / "weights.safetensors",
                        metadata={"train_candidates": len(y), "epochs": config.epochs})
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=1))
    tmp.replace(out / "metrics.json")
    return metrics
