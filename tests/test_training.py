"""Training: the model learns a tiny synthetic task; checkpoints resume; metrics written."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from drake_grasp.learning.dataset import SceneSamples
from drake_grasp.learning.dataset_generate import write_manifest
from drake_grasp.learning.dataset_shards import write_shard, shard_name
from drake_grasp.learning.training import TrainConfig, train


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


def _config(epochs, recipe="paper", **kw):
    """The paper's SGD (or `recipe`) on the tiny synthetic task; no ranking metrics (the
    synthetic scenes have no grasps)."""
    return TrainConfig.from_recipe(recipe, epochs=epochs, batch_instances=80,
                                   learning_rate=kw.pop("learning_rate", 0.02), seed=3,
                                   threads=2, ranking_images=0, **kw)


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


def _cli_args(data):
    """`drake-grasp train` on the synthetic task: Adam at 0.001, 6 epochs (no --out)."""
    return ["train", "--data", str(data / "train"), "--test-data", str(data / "test"),
            "--recipe", "fast", "--lr", "0.001", "--batch", "80", "--epochs", "6",
            "--seed", "3", "--threads", "2", "--ranking-images", "0"]


def test_init_weights_start_from_a_trained_net(data, tmp_path):
    """--init-weights: the run starts from the given net (at a learning rate too small to
    move it, its test L1 is the given net's, far below a fresh net's), its identity holds
    the tensors' sha256, and a missing file is refused before the folder is made."""
    with torch.random.fork_rng():
        trained = train(data=data, out=tmp_path / "a", config=_config(12), progress=False)
        still = dict(learning_rate=1e-12)
        warm = train(data=data, out=tmp_path / "b", progress=False, config=_config(
            1, init_weights=str(tmp_path / "a" / "weights.safetensors"), **still))
        cold = train(data=data, out=tmp_path / "c", config=_config(1, **still), progress=False)
    assert warm["test_l1_m"] == pytest.approx(trained["test_l1_m"], rel=1e-4)
    assert cold["test_l1_m"] > 1.5 * warm["test_l1_m"]
    from drake_grasp.cnn.weights_io import load_weights, tensors_sha256

    net, _ = load_weights(tmp_path / "a" / "weights.safetensors")
    config = json.loads((tmp_path / "b" / "train_config.json").read_text())
    assert config["init_weights_sha256"] == tensors_sha256(net.state_dict())
    assert "init_weights_sha256" not in json.loads((tmp_path / "c" / "train_config.json").read_text())
    with pytest.raises(ValueError, match="init_weights .*nope.safetensors: no such file"):
        train(data=data, out=tmp_path / "d", progress=False,
              config=_config(1, init_weights=str(tmp_path / "nope.safetensors")))
    assert not (tmp_path / "d").exists()


def test_the_window_fusion_trains_from_the_cli(data, tmp_path, capsys):
    """`train --action-fusion window` learns the synthetic task (whose labels are
    distances in the image plane, which the window reads where the candidate is) and
    writes a window net; the default run's identity and weights stay tiled."""
    from drake_grasp.cli.main import main
    from drake_grasp.cnn.weights_io import load_weights

    args = _cli_args(data)
    with torch.random.fork_rng():
        assert main(args + ["--out", str(tmp_path / "w"), "--action-fusion", "window"]) == 0
    capsys.readouterr()
    metrics = json.loads((tmp_path / "w" / "metrics.json").read_text())
    first, last = metrics["epochs"][0], metrics["epochs"][-1]
    assert last["train_l1_m"] < 0.6 * first["train_l1_m"], (first, last)
    net, _ = load_weights(tmp_path / "w" / "weights.safetensors")
    assert net.config.action_fusion == "window" and net.config.theta_unit == "deg"
    resolved = json.loads((tmp_path / "w" / "train_config.json").read_text())
    assert resolved["network"]["action_fusion"] == "window"
    assert main(args + ["--out", str(tmp_path / "x"), "--context-side", "0.3"]) == 2
    assert "--context-side: needs --action-fusion window" in capsys.readouterr().err
    assert main(args + ["--out", str(tmp_path / "x"), "--action-fusion", "window",
                        "--context-side", "-1"]) == 2
    assert "context_side_m: expected a finite number >= 0" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_the_log_l1_loss_weights_errors_near_a_grasp_more():
    """log-l1 is |log(p + c) - log(t + c)|; a 1 cm error 1 cm from a grasp costs about
    (0.2 + c) / (0.01 + c) times what it costs 20 cm away, while L1 costs both the same."""
    from drake_grasp.learning.training import training_loss

    log = TrainConfig(loss="log-l1", loss_offset_m=0.01)
    pred, true = torch.tensor([0.02, 0.21]), torch.tensor([0.01, 0.20])
    near = training_loss(pred[:1], true[:1], log)
    far = training_loss(pred[1:], true[1:], log)
    assert float(near) == pytest.approx(np.log(0.03 / 0.02), rel=1e-5)
    assert float(near / far) == pytest.approx(np.log(1.5) / np.log(0.22 / 0.21), rel=1e-4)
    assert float(near / far) > 8
    l1 = TrainConfig()
    assert float(training_loss(pred, true, l1)) == pytest.approx(0.01, rel=1e-5)
    for bad, match in ((dict(loss="l2"), "loss: expected one of"),
                       (dict(loss="log-l1", loss_offset_m=0.0), "loss_offset_m: expected > 0")):
        with pytest.raises(ValueError, match=match):
            TrainConfig(**bad).validate()


def test_the_log_l1_loss_trains_from_the_cli_and_l1_runs_keep_their_identity(
        data, tmp_path, capsys):
    """`train --loss log-l1` learns the synthetic task (its running figure is the L1 in
    metres) and records the loss in the run's identity; an L1 run's identity has no loss
    fields, as runs made before the option; bad flags are refused before a folder is made."""
    from drake_grasp.cli.main import main

    args = _cli_args(data)
    with torch.random.fork_rng():
        assert main(args + ["--out", str(tmp_path / "log"), "--loss", "log-l1"]) == 0
    capsys.readouterr()
    metrics = json.loads((tmp_path / "log" / "metrics.json").read_text())
    first, last = metrics["epochs"][0], metrics["epochs"][-1]
    assert last["train_l1_m"] < 0.6 * first["train_l1_m"], (first, last)
    resolved = json.loads((tmp_path / "log" / "train_config.json").read_text())["train"]
    assert resolved["loss"] == "log-l1" and resolved["loss_offset_m"] == 0.01
    assert "loss" not in TrainConfig().identity_dict()
    assert "loss_offset_m" not in TrainConfig(loss_offset_m=0.05).identity_dict()
    assert main(args + ["--out", str(tmp_path / "x"), "--loss-offset", "0.02"]) == 2
    assert "--loss-offset: needs --loss log-l1" in capsys.readouterr().err
    assert main(args + ["--out", str(tmp_path / "x"), "--loss", "log-l1",
                        "--loss-offset", "-1"]) == 2
    assert "loss_offset_m: expected > 0" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


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


def test_the_fast_recipe_reduces_the_l1_loss(data, tmp_path):
    config = _config(6, recipe="fast", learning_rate=0.001)
    assert config.optimizer == "adam" and config.lr_decay_per_epoch < 1
    metrics = train(data=data, out=tmp_path / "run", config=config, progress=False)
    first, last = metrics["epochs"][0], metrics["epochs"][-1]
    assert last["train_l1_m"] < 0.6 * first["train_l1_m"], (first, last)
    rates = [e["learning_rate"] for e in metrics["epochs"]]
    assert rates == pytest.approx([0.001 * 0.8 ** k for k in range(6)])


def test_a_run_killed_within_an_epoch_resumes_to_the_uninterrupted_weights(
        data, tmp_path, monkeypatch):
    """Checkpoints within epochs (here before every batch): a run stopped right after
    the 3rd one of epoch 2, resumes mid-epoch and ends with the weights, bit for bit,
    of a run that was never stopped."""
    from safetensors.torch import load_file

    from drake_grasp.learning import training

    config = _config(3, recipe="fast", learning_rate=0.001, checkpoint_minutes=0.0)
    train(data=data, out=tmp_path / "straight", config=config, progress=False)

    save = training._save_checkpoint
    calls = []

    def save_then_stop(*args, **kw):
        save(*args, **kw)
        if kw.get("in_epoch") is not None:
            calls.append(kw["in_epoch"])
            if len(calls) == 8:  # 5 mid-epoch saves in epoch 1 (6 batches), 3 in epoch 2
                raise KeyboardInterrupt

    monkeypatch.setattr(training, "_save_checkpoint", save_then_stop)
    with pytest.raises(KeyboardInterrupt):
        train(data=data, out=tmp_path / "killed", config=config, progress=False)
    monkeypatch.setattr(training, "_save_checkpoint", save)
    assert calls[-1]["epoch"] == 2 and calls[-1]["next_batch"] == 3
    ckpt = torch.load(tmp_path / "killed" / "checkpoint.pt", weights_only=True)
    assert ckpt["epoch"] == 1
    # The unfinished run's checkpoint as weights: the checkpoint's tensors, and where
    # the run stood (6 batches per epoch: 6 + 3 done).
    meta = training.export_checkpoint_weights(tmp_path / "killed", tmp_path / "mid.safetensors")
    assert (meta["checkpoint_epoch"], meta["checkpoint_next_batch"], meta["iterations"]) == \
        (1, 3, 9)
    mid = load_file(tmp_path / "mid.safetensors")
    assert mid.keys() == ckpt["model"].keys()
    assert all(torch.equal(mid[k], ckpt["model"][k]) for k in mid)
    resumed = train(data=data, out=tmp_path / "killed", config=config, progress=False)
    assert [e["epoch"] for e in resumed["epochs"]] == [1, 2, 3]
    a = load_file(tmp_path / "straight" / "weights.safetensors")
    b = load_file(tmp_path / "killed" / "weights.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # A finished run's checkpoint is its final weights.
    training.export_checkpoint_weights(tmp_path / "straight", tmp_path / "end.safetensors")
    end = load_file(tmp_path / "end.safetensors")
    assert all(torch.equal(end[k], a[k]) for k in a)
    with pytest.raises(FileNotFoundError, match="checkpoint.pt: not found"):
        training.export_checkpoint_weights(tmp_path / "nothing", tmp_path / "x.safetensors")


def test_unknown_recipe_is_refused():
    with pytest.raises(ValueError, match="recipe: expected one of"):
        TrainConfig.from_recipe("papr")


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


# ----------------------------------------------------------------------------
# Resuming on another device, and memory.


def test_resume_with_another_device_setting_and_thread_count_continues_the_run(data, tmp_path):
    """device, threads and max_memory_gb say where a run computes, not what: a run
    started with device="cpu", 1 thread, resumes with device="auto", 2 threads and
    another memory bound, and ends where an uninterrupted run does."""
    straight = train(data=data, out=tmp_path / "straight", config=_config(3), progress=False)
    first = dataclasses.replace(_config(1), device="cpu", threads=1, max_memory_gb=8.0)
    train(data=data, out=tmp_path / "run", config=first, progress=False)
    later = dataclasses.replace(_config(3), device="auto", threads=2, max_memory_gb=0.5)
    resumed = train(data=data, out=tmp_path / "run", config=later, progress=False)
    assert [e["epoch"] for e in resumed["epochs"]] == [1, 2, 3]
    assert resumed["test_l1_m"] == pytest.approx(straight["test_l1_m"], rel=1e-4)
    torch.set_num_threads(2)


def test_a_checkpoint_whose_tensors_are_tagged_cuda_resumes_on_cpu(data, tmp_path, monkeypatch):
    """A checkpoint written on a GPU: its tensors are re-saved tagged "cuda:0" (as
    torch.save records CUDA tensors), then training resumes from it on the CPU."""
    import torch.serialization

    out = tmp_path / "run"
    train(data=data, out=out, config=_config(1), progress=False)
    ckpt = torch.load(out / "checkpoint.pt", weights_only=True)
    with monkeypatch.context() as m:
        m.setattr(torch.serialization, "location_tag", lambda storage: "cuda:0")
        torch.save(ckpt, out / "checkpoint.pt")
    if not torch.cuda.is_available():  # the file really claims CUDA tensors
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(out / "checkpoint.pt", weights_only=True)
    resumed = train(data=data, out=out, config=_config(2), progress=False)
    assert [e["epoch"] for e in resumed["epochs"]] == [1, 2]
    assert resumed["epochs"][1]["device"] == "cpu"


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    """640 train images in 10 HDF5 chunks of 64 and 64 test images: about 5.9 MB as the
    loader caches them (float16 depth, float32 offsets and labels)."""
    root = tmp_path_factory.mktemp("big")
    _synthetic(root / "train", seed=0, scenes=10, images=64)
    _synthetic(root / "test", seed=1, scenes=1, images=64)
    return root


BUDGET_GB = 0.0025  # 2.5 MB: room for two chunks and a batch, not for the data


def test_training_streams_a_dataset_larger_than_max_memory_gb(big, tmp_path):
    config = dataclasses.replace(_config(1), max_memory_gb=BUDGET_GB)
    metrics = train(data=big, out=tmp_path / "run", config=config, progress=False)
    loader = metrics["loader"]
    assert loader["dataset_bytes"] > BUDGET_GB * 1e9  # the data does not fit...
    assert loader["chunk_loads"] > 2 * 11  # ...so its 11 chunks were evicted and read again
    assert loader["cache_peak_bytes"] + loader["batch_reserve_bytes"] <= BUDGET_GB * 1e9
    assert metrics["num_train_images"] == 640 and len(metrics["epochs"]) == 1


def test_loader_memory_measured_with_tracemalloc_stays_under_max_memory_gb(big):
    """Bytes allocated by numpy and h5py (tracemalloc) while the loader serves one
    shuffled training epoch and a test pass, batch by batch as training does."""
    import tracemalloc

    from drake_grasp.learning.common import open_training_sets

    train_set, test_set, cache = open_training_sets(big / "train", big / "test",
                                                    max_memory_gb=BUDGET_GB, batch_instances=80)
    per_batch = 8
    order = torch.randperm(len(train_set), generator=torch.Generator().manual_seed(0)).numpy()
    checked = []
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        for start in range(0, len(order), per_batch):
            batch = train_set.gather(np.sort(order[start:start + per_batch]))
            if start % (8 * per_batch) == 0:
                checked.append((start, batch[2][:, 0].copy()))  # a few labels, to compare
            del batch
        for start in range(0, len(test_set), per_batch):
            batch = test_set.gather(np.arange(start, min(start + per_batch, len(test_set))))
            del batch
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    data_bytes = (len(train_set) + len(test_set)) * train_set.bytes_per_image
    assert data_bytes > 2 * BUDGET_GB * 1e9  # holding the sets would take twice the bound
    assert cache.loads > 11  # its 11 chunks were evicted and read again
    print(f"loader peak {peak} bytes (tracemalloc), bound {BUDGET_GB * 1e9:.0f}, "
          f"data {data_bytes}, chunk loads {cache.loads}")
    assert 1e6 < peak <= BUDGET_GB * 1e9, peak  # at least one chunk, at most the bound
    # The same batches as a loader that holds everything: the bound changes speed only.
    roomy, _, roomy_cache = open_training_sets(big / "train", big / "test", max_memory_gb=1.0,
                                               batch_instances=80)
    for start, labels in checked:
        np.testing.assert_array_equal(
            roomy.gather(np.sort(order[start:start + per_batch]))[2][:, 0], labels)
    assert roomy_cache.loads <= 10  # each train chunk read once


def test_max_memory_gb_too_small_for_one_batch_is_refused(big, tmp_path, capsys):
    from drake_grasp.cli.main import main

    rc = main(["train", "--data", str(big), "--out", str(tmp_path / "o"), "--epochs", "1",
               "--batch", "80", "--max-memory-gb", "0.0005"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--max-memory-gb 0.0005: too small for even one batch: 8 images" in err
    assert not (tmp_path / "o" / "checkpoint.pt").exists()


def test_a_moved_dataset_still_resumes(data, tmp_path):
    import shutil

    moved = tmp_path / "moved"
    shutil.copytree(data, moved)
    out = tmp_path / "run"
    train(data=data, out=out, config=_config(1), progress=False)
    resumed = train(data=moved, out=out, config=_config(2), progress=False)
    assert [e["epoch"] for e in resumed["epochs"]] == [1, 2]


_HOLD_TRAIN_LOCK = """
import sys
from drake_grasp.learning.training import TrainLock
TrainLock(sys.argv[1]).acquire()
print("ready", flush=True)
sys.stdin.read()
"""


def test_a_second_training_run_on_a_folder_in_use_is_refused(data, tmp_path):
    import os
    import socket
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "busy"
    out.mkdir()
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen([sys.executable, "-c", _HOLD_TRAIN_LOCK, str(out)], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        with pytest.raises(ValueError, match=rf"another training run is using this folder "
                                             rf"\(pid {proc.pid} on host "
                                             rf"{socket.gethostname()}, started "):
            train(data=data, out=out, config=_config(1), progress=False)
        assert sorted(p.name for p in out.iterdir()) == ["train.lock"]
    finally:
        proc.kill()
        proc.wait()
    # Its owner is gone: the next run takes the folder.
    metrics = train(data=data, out=out, config=_config(1), progress=False)
    assert len(metrics["epochs"]) == 1 and not (out / "train.lock").exists()
