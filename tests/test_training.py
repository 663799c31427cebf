"""Training: the model learns a tiny synthetic task; checkpoints resume; metrics written."""

import json

import numpy as np
import pytest
import torch

from drake_grasp.dataset import SceneSamples, write_manifest, write_shard, shard_name
from drake_grasp.training import TrainConfig, train


def _synthetic(out, *, seed, scenes=4, images=24, m=10):
    """Depth images of a table with one box; the label is the distance from the offset to
    the box centre (a learnable stand-in for the distance to the nearest grasp)."""
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True)
    cfg = {"synthetic": True}
    samples = []
    for s in range(scenes):
        depth = np.full((images, 64, 64), 0.3, np.float32)
        offsets = rng.uniform(-0.08, 0.08, (images, m, 3)).astype(np.float32)
        offsets[..., 2] = rng.uniform(-90, 90, (images, m))
        labels = np.empty((images, m), np.float32)
        for k in range(images):
            r, c = rng.integers(12, 52, 2)
            depth[k, r - 6:r + 6, c - 6:c + 6] = 0.25
            centre = np.array([(c - 31.5) * 0.004, (r - 31.5) * 0.004])
            labels[k] = np.linalg.norm(offsets[k, :, :2] - centre, axis=1)
        samples.append(SceneSamples(s, "{}", depth, np.zeros((images, 4)), offsets, labels,
                                    np.zeros((0, 4, 4)), np.zeros(0, np.float32), np.zeros((0, 3))))
    write_shard(out / shard_name(0), samples, attrs={"config_hash": "synthetic", "split": "x"})
    write_manifest(out, cfg)
    return out


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    _synthetic(root / "train", seed=0, scenes=2)
    _synthetic(root / "test", seed=1, scenes=1)
    return root


def _config(epochs):
    return TrainConfig(epochs=epochs, batch_instances=80, learning_rate=0.02, seed=3, threads=2)


def test_training_reduces_the_l1_loss(data, tmp_path):
    with torch.random.fork_rng():
        metrics = train(data=data, out=tmp_path / "run", config=_config(12), progress=False)
    first, last = metrics["epochs"][0], metrics["epochs"][-1]
    assert last["train_l1_m"] < 0.6 * first["train_l1_m"], (first, last)
    assert metrics["test_l1_m"] == last["test_l1_m"]
    out = tmp_path / "run"
    assert json.loads((out / "metrics.json").read_text())["test_l1_m"] == metrics["test_l1_m"]
    assert (out / "learning_curves.png").stat().st_size > 1000
    assert (out / "weights.safetensors").is_file()


def test_resume_continues_from_the_saved_epoch(data, tmp_path):
    out = tmp_path / "run"
    straight = train(data=data, out=tmp_path / "straight", config=_config(4), progress=False)
    train(data=data, out=out, config=_config(2), progress=False)
    ckpt = torch.load(out / "checkpoint.pt", weights_only=True)
    assert ckpt["epoch"] == 2
    resumed = train(data=data, out=out, config=_config(4), progress=False)
    assert [e["epoch"] for e in resumed["epochs"]] == [1, 2, 3, 4]
    # Same seed, same batches: resuming gives the run an uninterrupted one gives.
    assert resumed["test_l1_m"] == pytest.approx(straight["test_l1_m"], rel=1e-5)


def test_other_data_in_the_same_out_is_refused(data, tmp_path):
    out = tmp_path / "run"
    train(data=data, out=out, config=_config(1), progress=False)
    other = _config(1)
    other.learning_rate = 0.5
    with pytest.raises(ValueError, match="another configuration"):
        train(data=data, out=out, config=other, progress=False)


def test_a_single_dataset_needs_a_test_set(data, tmp_path):
    with pytest.raises(ValueError, match="--test-data"):
        train(data=data / "train", out=tmp_path / "o", config=_config(1), progress=False)
