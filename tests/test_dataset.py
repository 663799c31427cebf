"""Dataset generation: paper-format shards, determinism, resume after a kill, corruption,
exactly N scenes, one generator per folder, durable writes."""

import copy
import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from drake_grasp.learning import dataset as dataset_module
from drake_grasp.learning.dataset import DatasetConfig, SceneSamples, scene_seed
from drake_grasp.learning.dataset_generate import generate_dataset
from drake_grasp.learning.dataset_shards import DepthGraspDataset
from drake_grasp.config.scenario import load_scenario

TINY = dict(images_per_scene=3, offsets_per_image=5, scenes_per_shard=2)
ROOT = Path(__file__).resolve().parents[1]


def _generate(out, num_scenes=3, seed=5, config=None, **kw):
    scenario = load_scenario(scenario_name="random", scenario_text=f"{{seed: {seed}}}")
    return generate_dataset(out=out, num_scenes=num_scenes, split="train", seed=seed,
                            scenario=scenario, config=config or DatasetConfig(**TINY),
                            workers=1, progress=False, **kw)


def _stored_scenes(out) -> dict:
    """{scene index: (kept attempt or None, scene spec)} over every shard of a folder."""
    scenes = {}
    for path in sorted(Path(out).glob("shard-*.h5")):
        with h5py.File(path) as f:
            attempts = f["scene_attempt"][:] if "scene_attempt" in f else [None] * len(f["scene_index"])
            for i, a, spec in zip(f["scene_index"][:], attempts, f["scene_spec"][:]):
                scenes[int(i)] = (None if a is None else int(a),
                                  json.loads(spec.decode() if isinstance(spec, bytes) else spec))
    return scenes


@pytest.fixture(scope="module")
def reference(tmp_path_factory, library):
    out = tmp_path_factory.mktemp("ref")
    manifest = _generate(out)
    return out, manifest


def test_shards_hold_the_paper_format(reference):
    out, manifest = reference
    # 3 scenes at 2 per shard: exactly 3 scenes, the last shard holds the one left over.
    assert manifest["num_scenes"] == 3
    assert [s["num_scenes"] for s in manifest["shards"]] == [2, 1]
    assert sorted(_stored_scenes(out)) == [0, 1, 2]
    assert manifest["num_scene_attempts"] == 3 + manifest["num_scenes_replaced"]
    assert manifest["num_scenes_replaced"] == (manifest["num_scenes_unsettled_resampled"]
                                               + manifest["num_scenes_no_grasp_resampled"])
    assert manifest["num_images"] == 3 * manifest["num_scenes"]
    assert manifest["num_labels"] == 5 * manifest["num_images"]
    assert manifest["code_version"].startswith(manifest["code_version"].split("+")[0])
    ds = DepthGraspDataset(out)
    assert len(ds) == manifest["num_images"] > 0
    item = ds[0]
    assert item["depth"].shape == (64, 64) and np.isfinite(item["depth"]).all()
    assert item["offsets"].shape == (5, 3) and item["labels"].shape == (5,)
    assert (item["labels"] >= 0).all() and np.isfinite(item["labels"]).all()
    rec = ds.image_record(0)
    assert len(rec["grasp_xy_theta"]) > 0 and rec["scene_spec"]["settled"]
    for i, (attempt, spec) in _stored_scenes(out).items():
        assert spec["settled"] is True
        assert spec["seed"] == scene_seed(5, i, attempt)
    with h5py.File(out / "shard-00000.h5") as f:
        assert f["depth"].compression == "gzip" and f["depth"].chunks is not None
        assert f["depth"].dtype == np.float16 and f.attrs["format_version"] == 3
    assert item["depth"].dtype == np.float32  # readers convert
    assert not (out / "generate.lock").exists()


def test_generation_is_deterministic(reference, tmp_path):
    out, manifest = reference
    again = _generate(tmp_path / "again")
    assert again["num_labels"] == manifest["num_labels"]
    a, b = DepthGraspDataset(out), DepthGraspDataset(tmp_path / "again")
    for i in range(len(a)):
        np.testing.assert_array_equal(a[i]["labels"], b[i]["labels"])
        np.testing.assert_array_equal(a[i]["depth"], b[i]["depth"])


def test_near_grasp_images_look_near_a_true_grasp_and_leave_the_others_unchanged(
        reference, tmp_path):
    """`near_grasp_fraction`: the last images of each scene are posed near one of its
    true grasps (within the configured range, so their zero-offset label is at most
    the range's reach); the scenes, the other images and their labels are those of the
    plain dataset; the plain config's identity (and so its folders' hash) is unchanged."""
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp

    out, _ = reference
    cfg = DatasetConfig(**TINY, near_grasp_fraction=0.34)  # 1 of 3 images per scene
    assert "near_grasp_fraction" not in DatasetConfig(**TINY).identity()
    assert cfg.identity()["near_grasp_fraction"] == 0.34
    _generate(tmp_path / "near", config=cfg)
    plain, near = DepthGraspDataset(out), DepthGraspDataset(tmp_path / "near")
    assert len(plain) == len(near) == 9
    reach = np.hypot(0.04, 0.04) + 0.001 * 45.0  # metric: m + 0.001 m/deg
    for i in range(len(near)):
        a, b = plain.image_record(i), near.image_record(i)
        assert a["scene_spec"] == b["scene_spec"]
        if i % 3 < 2:  # the random poses: the plain dataset's images and labels
            np.testing.assert_array_equal(plain[i]["depth"], near[i]["depth"])
            np.testing.assert_array_equal(plain[i]["labels"], near[i]["labels"])
        else:
            pose = np.asarray(b["hand_pose"])[[0, 1, 3]]
            d = distance_to_nearest_grasp(pose[None], np.asarray(b["grasp_xy_theta"]))[0]
            assert d <= reach and not np.array_equal(plain[i]["depth"], near[i]["depth"])
    with pytest.raises(ValueError, match="near_grasp_fraction: expected 0 <= f <= 1, got 1.5"):
        DatasetConfig(near_grasp_fraction=1.5).validate()


def test_clutter_scene_kind_pours_the_scenarios_pile(tmp_path):
    """`scene_kind="clutter"`: each dataset scene is the scenario's pile of
    scene.clutter_objects objects stacked in a column (poured when settled), drawn from
    the scene's own seed; the kind enters the config's identity (the random default
    leaves it unchanged); an unknown kind is refused by name."""
    from drake_grasp.learning.dataset import sample_dataset_scene
    from drake_grasp.objects import load_library

    library = load_library(None)
    scenario = load_scenario(scenario_name="random",
                             scenario_text="{scene: {clutter_objects: 3, region_half_extent_m: 0.02}}")
    spec = sample_dataset_scene(scenario, split="train", seed=5, scene_index=1, attempt=0,
                                library=library, kind="clutter")
    assert spec.kind == "clutter" and len(spec.objects) == 3
    assert spec.seed == scene_seed(5, 1, 0)
    z = [o.xyz[2] for o in spec.objects]  # each object above the one before: a column
    assert z[2] > z[1] > z[0] and max(np.ptp([o.xyz[0] for o in spec.objects]),
                                      np.ptp([o.xyz[1] for o in spec.objects])) <= 0.1
    random_spec = sample_dataset_scene(scenario, split="train", seed=5, scene_index=1,
                                       attempt=0, library=library)
    assert random_spec.kind == "random"
    assert "scene_kind" not in DatasetConfig(**TINY).identity()
    cfg = DatasetConfig(**TINY, scene_kind="clutter")
    assert cfg.identity()["scene_kind"] == "clutter"
    generate_dataset(out=tmp_path / "pile", num_scenes=1, split="train", seed=5,
                     scenario=scenario, config=cfg, workers=1, progress=False)
    (attempt, stored), = _stored_scenes(tmp_path / "pile").values()
    assert stored["kind"] == "clutter" and stored["settled"]
    assert 1 <= len(stored["objects"]) <= 3  # objects that fell off the table are dropped
    with pytest.raises(ValueError, match="scene_kind: expected one of random, clutter, got 'pile'"):
        DatasetConfig(scene_kind="pile").validate()
    with pytest.raises(ValueError, match="settle_max_time_s: expected > 0, got 0.0"):
        DatasetConfig(settle_max_time_s=0.0).validate()
    from drake_grasp.cli.main import build_parser

    args = build_parser().parse_args(["generate", "--scenes", "1", "--split", "train", "--out",
                                      "x", "--scene-kind", "clutter", "--settle-max-time", "6"])
    assert (args.scene_kind, args.settle_max_time) == ("clutter", 6.0)


def test_near_grasp_poses_stay_within_their_range():
    rng = np.random.default_rng(0)
    grasps = np.array([[0.5, 0.0, 10.0], [0.4, 0.1, 170.0]])
    poses = dataset_module.near_grasp_poses(rng, grasps, 2000, z=np.full(2000, 0.1),
                                            xy_m=0.02, theta_deg=30.0)
    assert poses.shape == (2000, 4) and (poses[:, 2] == 0.1).all()
    assert ((poses[:, 3] >= -180) & (poses[:, 3] < 180)).all()
    # Each pose is within range of some grasp, in (x, y) and in theta modulo 180.
    dxy = np.abs(poses[:, None, :2] - grasps[None, :, :2]).max(-1)
    dth = np.abs((poses[:, None, 3] - grasps[None, :, 2] + 90.0) % 180.0 - 90.0)
    assert ((dxy <= 0.02) & (dth <= 30.0)).any(1).all()
    # Both grasps and both ways round are drawn.
    assert len(np.unique(np.round(poses[:, 3] // 90))) == 4


def test_killed_run_resumes_to_the_same_counts(reference, tmp_path, capfd):
    _, manifest = reference
    out = tmp_path / "killed"
    code = (
        "from drake_grasp.learning.dataset import DatasetConfig\n"
        "from drake_grasp.learning.dataset_generate import generate_dataset\n"
        "from drake_grasp.config.scenario import load_scenario\n"
        f"generate_dataset(out={str(out)!r}, num_scenes=3, split='train', seed=5,\n"
        "  scenario=load_scenario(scenario_name='random', scenario_text='{seed: 5}'),\n"
        f"  config=DatasetConfig(**{TINY!r}), workers=1, progress=False)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    deadline = time.time() + 120
    while not (out / "shard-00000.h5").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = sorted(p.name for p in out.glob("shard-*.h5"))
    assert finished == ["shard-00000.h5"], finished  # killed mid-run
    assert json.loads((out / "generate.lock").read_text())["pid"] == proc.pid
    capfd.readouterr()
    resumed = _generate(out)
    assert f"taking over the stale lock {out / 'generate.lock'} of pid {proc.pid}" in capfd.readouterr().err
    for key in ("num_scenes", "num_images", "num_labels", "num_scene_attempts",
                "num_scenes_unsettled_resampled", "num_scenes_no_grasp_resampled"):
        assert resumed[key] == manifest[key], key
    assert not list(out.glob("*.tmp")) and not (out / "generate.lock").exists()


def test_corrupt_shard_is_reported_by_name(reference, tmp_path):
    out, _ = reference
    copy_dir = tmp_path / "copy"
    copy_dir.mkdir()
    for p in out.iterdir():
        copy_dir.joinpath(p.name).write_bytes(p.read_bytes())
    shard = copy_dir / "shard-00001.h5"
    shard.write_bytes(shard.read_bytes()[:300])
    with pytest.raises(ValueError, match="shard-00001.h5"):
        _generate(copy_dir)


def test_other_config_in_the_same_folder_is_refused(reference):
    out, _ = reference
    with pytest.raises(ValueError, match="different configuration"):
        _generate(out, seed=6)


def test_settling_that_hits_the_time_cap_is_not_labelled_settled(library):
    """Two scenes of the dataset's seed sequence under the dataset's settling (5 ms steps,
    verified rest, 3 s cap, 0.01 m/s): scene_seed(0, 4) is still moving at the cap,
    scene_seed(0, 0) comes to rest (analysis/results/settle-check)."""
    from drake_grasp.world.scene import build_scene_world, sample_scene, settle_world

    scenario = load_scenario(scenario_name="random")
    cfg = DatasetConfig()
    scene_cfg = dataclasses.replace(scenario.scene, kind="random", split="train", object_ids=[])
    plant_config = copy.deepcopy(scenario.plant)
    plant_config.time_step = cfg.settle_time_step_s
    settled = {}
    for i in (0, 4):
        spec = sample_scene(scene_cfg, scene_seed(0, i), library)
        world = build_scene_world(spec, library, plant_config=plant_config,
                                  physics=scenario.physics)
        settled[i] = settle_world(world, spec, speed_tol_m_s=cfg.settle_speed_tol_m_s,
                                  max_time_s=cfg.settle_max_time_s, verified=True).settled
    assert settled == {0: True, 4: False}


def test_object_counts_are_uniform_and_kept_by_replacements():
    from drake_grasp.learning.dataset import scene_object_count

    counts = [scene_object_count(0, i, 1, 5) for i in range(5000)]
    assert counts == [scene_object_count(0, i, 1, 5) for i in range(5000)]
    shares = np.bincount(counts, minlength=6)[1:] / len(counts)
    assert np.all(np.abs(shares - 0.2) < 0.02), shares
    assert {scene_object_count(0, i, 3, 3) for i in range(20)} == {3}
    with pytest.raises(ValueError, match="num_objects_min/max"):
        scene_object_count(0, 0, 0, 5)


def test_unsettled_and_graspless_scenes_are_replaced_by_the_next_seed_of_their_scene(
        reference, tmp_path, monkeypatch):
    """The seed the reference kept for scene 0 is forced to end unsettled, and the one
    it kept for scene 2 to have no grasp: each is replaced by a later seed of its own
    sequence, counted in the manifest, and scene 1 is the reference's scene 1."""
    import drake_grasp.geometry.grasps
    import drake_grasp.world.scene

    ref_out, ref = reference
    ref_scenes = _stored_scenes(ref_out)
    unsettled_seed, graspless_seed = ref_scenes[0][1]["seed"], ref_scenes[2][1]["seed"]
    real_settle, real_find = drake_grasp.world.scene.settle_world, drake_grasp.geometry.grasps.find_grasps

    def settle(world, spec, **kw):
        result = real_settle(world, spec, **kw)
        if spec.seed == unsettled_seed:
            result.settled = False  # as if an object were still rolling at the cap
        return result

    def find(spec, library, rng, **kw):
        if spec.seed == graspless_seed:
            return SimpleNamespace(xy_theta=np.zeros((0, 3)), poses=np.zeros((0, 4, 4)),
                                   widths=np.zeros(0))
        return real_find(spec, library, rng, **kw)

    monkeypatch.setattr(drake_grasp.world.scene, "settle_world", settle)
    monkeypatch.setattr(drake_grasp.geometry.grasps, "find_grasps", find)
    manifest = _generate(tmp_path / "replaced")
    assert manifest["num_scenes"] == 3
    assert manifest["num_scenes_unsettled_resampled"] >= 1
    assert manifest["num_scenes_no_grasp_resampled"] >= 1
    assert manifest["num_scene_attempts"] == 3 + manifest["num_scenes_replaced"]
    assert manifest["num_scenes_replaced"] >= ref["num_scenes_replaced"] + 2
    assert (manifest["num_scenes_unsettled_resampled"]
            >= ref["num_scenes_unsettled_resampled"] + 1)
    assert (manifest["num_scenes_no_grasp_resampled"]
            >= ref["num_scenes_no_grasp_resampled"] + 1)
    scenes = _stored_scenes(tmp_path / "replaced")
    assert sorted(scenes) == [0, 1, 2]
    for i, (attempt, spec) in scenes.items():
        assert spec["settled"] is True and spec["seed"] == scene_seed(5, i, attempt)
    assert scenes[0][0] > ref_scenes[0][0] and scenes[0][1]["seed"] != unsettled_seed
    # A replacement draws new objects, as many as the scene it replaces.
    assert len(scenes[0][1]["objects"]) == len(ref_scenes[0][1]["objects"])
    assert scenes[2][0] > ref_scenes[2][0] and scenes[2][1]["seed"] != graspless_seed
    assert scenes[1] == ref_scenes[1]


# ----------------------------------------------------------------------------
# Bookkeeping, with a stand-in for the (physics) scene generator.


def _fake_scene(scene_index, *, seed, config, attempt=0, **_):
    """A tiny labelled scene whose numbers depend on its seed only."""
    s_seed = scene_seed(seed, scene_index, attempt) if attempt else scene_seed(seed, scene_index)
    rng = np.random.default_rng(s_seed)
    k, m = config.images_per_scene, config.offsets_per_image
    spec = {"kind": "random", "seed": s_seed, "center_xy_m": [0.5, 0.0], "objects": [],
            "settled": True}
    samples = SceneSamples(scene_index, json.dumps(spec), rng.random((k, 8, 8), np.float32),
                           np.zeros((k, 4)), rng.random((k, m, 3), np.float32),
                           rng.random((k, m), np.float32), np.zeros((1, 4, 4)),
                           np.ones(1, np.float32), np.zeros((1, 3)))
    samples.attempt = attempt
    return samples


@pytest.fixture
def fake_scenes(monkeypatch):
    monkeypatch.setattr(dataset_module, "generate_scene", _fake_scene)


def test_scenes_gives_exactly_n_when_n_is_not_a_multiple_of_the_shard_size(tmp_path, fake_scenes):
    out = tmp_path / "five"
    manifest = _generate(out, num_scenes=5)  # scenes_per_shard=2
    assert manifest["num_scenes"] == 5 and manifest["num_images"] == 15
    assert [s["num_scenes"] for s in manifest["shards"]] == [2, 2, 1]
    assert sorted(_stored_scenes(out)) == [0, 1, 2, 3, 4]
    # A larger N extends the folder: the short last shard is rewritten with more scenes.
    grown = _generate(out, num_scenes=6)
    assert grown["num_scenes"] == 6 and [s["num_scenes"] for s in grown["shards"]] == [2, 2, 2]
    # A smaller N would not give exactly N scenes from this folder: refused.
    with pytest.raises(ValueError, match=r"holds scenes 4\.\.5 but --scenes 5"):
        _generate(out, num_scenes=5)
    with pytest.raises(ValueError, match=r"shard-00002.h5 beyond the 2 shard\(s\) of --scenes 4"):
        _generate(out, num_scenes=4)


_HOLD_LOCK = """
import sys
from pathlib import Path
from drake_grasp.learning.folder_lock import GenerateLock
lock = GenerateLock(sys.argv[1]).acquire()
Path(sys.argv[1], f"shard-00000.h5.{lock.token}.{sys.argv[2]}.tmp").write_bytes(b"in progress")
print("ready", flush=True)
sys.stdin.read()
"""


def test_a_second_generator_on_a_folder_in_use_is_refused_and_deletes_nothing(
        tmp_path, fake_scenes, capfd):
    out = tmp_path / "busy"
    out.mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(out), "worker-7"], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        theirs = sorted(out.glob("*.tmp"))
        assert len(theirs) == 1
        host = socket.gethostname()
        with pytest.raises(ValueError, match=rf"another dataset generator is using this folder "
                                             rf"\(pid {proc.pid} on host {host}, started "):
            _generate(out)
        assert sorted(out.glob("*.tmp")) == theirs  # its in-progress file is untouched
        assert not list(out.glob("shard-*.h5")) and not (out / "manifest.json").exists()
    finally:
        proc.kill()
        proc.wait()
    # Its owner is gone: the next generator takes the lock over and removes its files.
    capfd.readouterr()
    manifest = _generate(out)
    err = capfd.readouterr().err
    assert f"taking over the stale lock {out / 'generate.lock'} of pid {proc.pid}" in err
    assert "removing its 1 temporary file(s)" in err
    assert manifest["num_scenes"] == 3 and not list(out.glob("*.tmp"))


def test_a_lock_of_another_host_is_refused(tmp_path, fake_scenes):
    out = tmp_path / "nfs"
    out.mkdir()
    owner = {"pid": 4242, "host": "render-node-9", "started_at": "2025-01-02T03:04:05+00:00",
             "token": "abc"}
    (out / "generate.lock").write_text(json.dumps(owner))
    (out / "shard-00000.h5.abc.render-node-9-4242.tmp").write_bytes(b"in progress")
    with pytest.raises(ValueError, match=r"pid 4242 on host render-node-9, started "
                                         r"2025-01-02T03:04:05\+00:00.*if it does not, delete"):
        _generate(out)
    assert (out / "shard-00000.h5.abc.render-node-9-4242.tmp").exists()


def test_shards_and_manifest_are_fsynced_before_rename(tmp_path, fake_scenes, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst, **kw):
        events.append(("replace", str(src), str(dst)))
        return real_replace(src, dst, **kw)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    out = tmp_path / "durable"
    _generate(out, num_scenes=3)
    for final in ("shard-00000.h5", "shard-00001.h5", "manifest.json"):
        (k, (_, src, dst)), = [(k, e) for k, e in enumerate(events)
                               if e[0] == "replace" and e[2] == str(out / final)]
        assert ("fsync", src) in events[:k], final  # the complete file reached the disk
        assert ("fsync", str(out)) in events[k + 1:], final  # then the rename did


def test_same_dataset_on_a_dask_local_cluster(reference, tmp_path):
    from dask.distributed import LocalCluster

    out, manifest = reference
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        dask_manifest = _generate(tmp_path / "dask", scheduler=cluster.scheduler_address)
    assert dask_manifest["num_labels"] == manifest["num_labels"]
    a, b = DepthGraspDataset(out), DepthGraspDataset(tmp_path / "dask")
    for i in range(len(a)):
        np.testing.assert_array_equal(a[i]["labels"], b[i]["labels"])


def test_the_ranking_metrics_true_distances_are_the_datasets_own_labels(reference):
    """cnn_metrics labels new candidates with the shard's grasps and the dataset's label
    function: on the stored offsets that gives the stored labels back."""
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp

    out, manifest = reference
    data = DepthGraspDataset(out)
    assert len(data) == manifest["num_images"] == 9
    for i in range(len(data)):
        rec = data.image_record(i)
        hand = np.asarray(rec["hand_pose"], float)[[0, 1, 3]]
        moved = apply_actions(hand[None], rec["offsets"][None].astype(float))[0]
        np.testing.assert_allclose(distance_to_nearest_grasp(moved, rec["grasp_xy_theta"]),
                                   rec["labels"], rtol=1e-6, atol=1e-6)


def test_ranking_metrics_on_a_generated_set(reference):
    import torch

    from drake_grasp.learning.cnn_metrics import ranking_metrics
    from drake_grasp.cnn.net_config import NetworkConfig
    from drake_grasp.cnn.network import DistanceCNN

    model = DistanceCNN(NetworkConfig(theta_unit="deg"), generator=torch.Generator().manual_seed(0))
    out, _ = reference
    a = ranking_metrics(model, out, images=6, candidates=32, seed=4)
    assert a == ranking_metrics(model, out, images=6, candidates=32, seed=4)  # seeded
    assert a["images"] == 6 and a["candidates"] == 32
    assert -1 <= a["spearman_mean"] <= 1 and a["regret_mean_m"] >= 0
    assert 0 <= a["top1_within_1cm"] <= 1 and a["l1_m"] > 0
    with pytest.raises(ValueError, match="candidates: expected >= 2"):
        ranking_metrics(model, out, candidates=1)


def test_cnn_eval_script_scores_weights_on_a_generated_set(reference, tmp_path, analysis_script):
    """analysis/cnn_eval.py: the shipped weights' test L1 over every label (as `train`
    computes it) and the ranking metrics, written to JSON."""
    import torch

    from drake_grasp.learning.cnn_metrics import ranking_metrics
    from drake_grasp.cnn.weights_io import load_weights
    from drake_grasp.learning.training import evaluate_l1
    from drake_grasp.learning.common import ChunkCache, ShardSet

    out, _ = reference
    script = analysis_script("cnn_eval")
    weights = ROOT / "models" / "cnn" / "weights.safetensors"
    result = script.main(["--weights", str(weights), "--test-data", str(out),
                          "--ranking-images", "4", "--out", str(tmp_path / "eval.json")])
    model, _ = load_weights(weights)
    expected = evaluate_l1(model, ShardSet(out, ChunkCache(int(1e9))), device=torch.device("cpu"))
    assert result["test_l1_m"] == pytest.approx(expected, rel=1e-6) and expected > 0
    assert result["ranking"] == ranking_metrics(model, out, images=4, seed=0)
    assert json.loads((tmp_path / "eval.json").read_text())["num_test_images"] == len(
        DepthGraspDataset(out))


def test_cnn_eval_script_scores_several_weights_as_their_mean(reference, tmp_path, analysis_script):
    """analysis/cnn_eval.py --weights A,B: every distance is the mean of the two nets' (as
    `controller.weights: A,B` scores in an episode); an empty item is refused."""
    import torch

    from drake_grasp.cnn.weights_io import load_weights
    from drake_grasp.learning.common import ChunkCache, ShardSet

    out, _ = reference
    script = analysis_script("cnn_eval")
    a = ROOT / "models" / "cnn-grid-bn12500-ep3" / "weights.safetensors"
    b = ROOT / "models" / "cnn-grid-bn" / "weights.safetensors"
    result = script.main(["--weights", f"{a},{b}", "--test-data", str(out),
                          "--ranking-images", "3", "--out", str(tmp_path / "eval.json")])
    nets = [load_weights(w)[0].eval() for w in (a, b)]
    data = ShardSet(out, ChunkCache(int(1e9)))
    depth, offsets, labels = data.gather(np.arange(len(data)))
    with torch.no_grad():
        preds = [n.forward_factored(n.preprocess(depth), torch.as_tensor(offsets, dtype=n.dtype))
                 .double().numpy() for n in nets]
    errors = [np.abs(p - labels).mean() for p in preds]
    expected = np.abs(0.5 * (preds[0] + preds[1]) - labels).mean()
    assert result["test_l1_m"] == pytest.approx(expected, rel=1e-5)
    assert errors[0] != pytest.approx(errors[1], rel=1e-3)  # two different nets
    assert result["ranking"]["images"] == 3
    # the episode's ensemble (`load_cnn("A,B")`, `score_candidates`) scores alike
    from drake_grasp.policies.evaluator import load_cnn, score_candidates

    mean = script.MeanCNN(nets)
    actions = np.array([[0.0, 0.0, 0.0], [0.02, -0.01, 30.0], [-0.03, 0.01, -60.0]], np.float32)
    with torch.inference_mode():
        ours = mean.score_actions(mean.image_features(mean.preprocess(depth[:1])), actions)
    episode = score_candidates(load_cnn(f"{a},{b}"), depth[0], actions)
    np.testing.assert_allclose(ours.double().numpy(), episode, atol=1e-6)
    from dataclasses import replace

    from drake_grasp.cnn.network import DistanceCNN

    other = DistanceCNN(replace(nets[0].config, depth_offset_m=0.4))
    with pytest.raises(ValueError, match="member 1 has depth_offset_m = 0.4"):
        script.MeanCNN([nets[0], other])
    with pytest.raises(SystemExit, match="empty item"):
        script.main(["--weights", f"{a},", "--test-data", str(out), "--out", str(tmp_path / "x.json")])
    assert not (tmp_path / "x.json").exists()


def test_cnn_eval_views_average_the_grid_over_the_turned_views(reference, tmp_path, analysis_script):
    """analysis/cnn_eval.py --views d4: a grid net's grid is the mean over the 8 turned
    views, each turned back; "none" is the net itself; paper nets and --mirror with
    --views are refused."""
    import torch

    from drake_grasp.cnn.views import AUGMENTATIONS, turn_grids, turn_images
    from drake_grasp.cnn.weights_io import load_weights
    from drake_grasp.learning.common import ChunkCache, ShardSet

    out, _ = reference
    script = analysis_script("cnn_eval")
    weights = ROOT / "models" / "cnn-grid-bn12500-ep3" / "weights.safetensors"
    net = load_weights(weights)[0].eval()
    assert script.view_averaged(net, "none") is net
    averaged = script.view_averaged(net, "d4")
    depth = ShardSet(out, ChunkCache(int(1e9))).gather(np.arange(2))[0]
    images = net.preprocess(depth)
    with torch.inference_mode():
        got = averaged.image_features(images).numpy()
        plain = net.image_features(images).numpy()
        views = []
        for k, flip in AUGMENTATIONS["d4"]:
            g = net.image_features(torch.from_numpy(turn_images(images.numpy(), k, flip))).numpy()
            # the inverse of (k, flip): flip back after turning back
            back = turn_grids(g, (-k) % 4, False)
            views.append(turn_grids(back, 0, True) if flip else back)
    np.testing.assert_allclose(got, np.mean(views, axis=0), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(net.image_features(images).detach().numpy(), plain)
    assert np.abs(got - plain).max() > 1e-4  # the views differ
    result = script.main(["--weights", str(weights), "--test-data", str(out), "--views", "d4",
                          "--ranking-images", "2", "--out", str(tmp_path / "eval.json")])
    assert result["views"] == "d4" and result["test_l1_m"] > 0
    paper = ROOT / "models" / "cnn" / "weights.safetensors"
    with pytest.raises(SystemExit, match="needs grid-head nets"):
        script.main(["--weights", str(paper), "--test-data", str(out), "--views", "mirror",
                     "--out", str(tmp_path / "x.json")])
    with pytest.raises(SystemExit, match="choose one"):
        script.main(["--weights", str(weights), "--test-data", str(out), "--views", "d4",
                     "--mirror", "--out", str(tmp_path / "x.json")])
    assert not (tmp_path / "x.json").exists()


def test_spearman_matches_scipy_and_is_nan_without_an_order():
    from scipy.stats import spearmanr

    from drake_grasp.learning.cnn_metrics import spearman

    rng = np.random.default_rng(0)
    a, b = rng.random((5, 20)), rng.random((5, 20))
    b[0] = a[0] * 3 + 1  # same order: 1
    b[1, :10] = b[1, 10:]  # ties
    rho = spearman(a, b)
    assert rho[0] == pytest.approx(1.0)
    for k in range(5):
        assert rho[k] == pytest.approx(spearmanr(a[k], b[k]).statistic)
    assert np.isnan(spearman(np.ones((1, 4)), a[:1, :4]))[0]
