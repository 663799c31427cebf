"""Dataset generation: paper-format shards, determinism, resume after a kill, corruption."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from drake_grasp.dataset import DatasetConfig, DepthGraspDataset, generate_dataset
from drake_grasp.scenario import load_scenario

TINY = dict(images_per_scene=3, offsets_per_image=5, scenes_per_shard=1)


def _generate(out, num_scenes=3, seed=5, **kw):
    scenario = load_scenario(scenario_name="random", scenario_text=f"{{seed: {seed}}}")
    return generate_dataset(out=out, num_scenes=num_scenes, split="train", seed=seed,
                            scenario=scenario, config=DatasetConfig(**TINY), workers=1,
                            progress=False, **kw)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, library):
    out = tmp_path_factory.mktemp("ref")
    manifest = _generate(out)
    return out, manifest


def test_shards_hold_the_paper_format(reference):
    out, manifest = reference
    assert manifest["num_scenes"] + manifest["num_scenes_skipped"] == 3
    assert manifest["num_images"] == 3 * manifest["num_scenes"]
    assert manifest["num_labels"] == 5 * manifest["num_images"]
    ds = DepthGraspDataset(out)
    assert len(ds) == manifest["num_images"] > 0
    item = ds[0]
    assert item["depth"].shape == (64, 64) and np.isfinite(item["depth"]).all()
    assert item["offsets"].shape == (5, 3) and item["labels"].shape == (5,)
    assert (item["labels"] >= 0).all() and np.isfinite(item["labels"]).all()
    rec = ds.image_record(0)
    assert len(rec["grasp_xy_theta"]) > 0 and rec["scene_spec"]["settled"]
    with h5py.File(out / "shard-00000.h5") as f:
        assert f["depth"].compression == "gzip" and f["depth"].chunks is not None


def test_generation_is_deterministic(reference, tmp_path):
    out, manifest = reference
    again = _generate(tmp_path / "again")
    assert again["num_labels"] == manifest["num_labels"]
    a, b = DepthGraspDataset(out), DepthGraspDataset(tmp_path / "again")
    for i in range(len(a)):
        np.testing.assert_array_equal(a[i]["labels"], b[i]["labels"])
        np.testing.assert_array_equal(a[i]["depth"], b[i]["depth"])


def test_killed_run_resumes_to_the_same_counts(reference, tmp_path):
    _, manifest = reference
    out = tmp_path / "killed"
    code = (
        "from drake_grasp.dataset import DatasetConfig, generate_dataset\n"
        "from drake_grasp.scenario import load_scenario\n"
        f"generate_dataset(out={str(out)!r}, num_scenes=3, split='train', seed=5,\n"
        "  scenario=load_scenario(scenario_name='random', scenario_text='{seed: 5}'),\n"
        f"  config=DatasetConfig(**{TINY!r}), workers=1, progress=False)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    deadline = time.time() + 120
    while not (out / "shard-00000.h5").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    finished = sorted(p.name for p in out.glob("shard-*.h5"))
    assert "shard-00000.h5" in finished and len(finished) < 3, finished  # killed mid-run
    resumed = _generate(out)
    for key in ("num_scenes", "num_images", "num_labels", "num_scenes_skipped"):
        assert resumed[key] == manifest[key], key
    assert not list(out.glob("*.tmp"))


def test_corrupt_shard_is_reported_by_name(reference, tmp_path):
    out, _ = reference
    copy = tmp_path / "copy"
    copy.mkdir()
    for p in out.iterdir():
        copy.joinpath(p.name).write_bytes(p.read_bytes())
    shard = copy / "shard-00001.h5"
    shard.write_bytes(shard.read_bytes()[:300])
    with pytest.raises(ValueError, match="shard-00001.h5"):
        _generate(copy)


def test_other_config_in_the_same_folder_is_refused(reference):
    out, _ = reference
    with pytest.raises(ValueError, match="different configuration"):
        _generate(out, seed=6)


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
