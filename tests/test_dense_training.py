"""Dense labels for the grid head: exact against the dataset's label function, only in
the view; the grid net trains on them."""

import json

import numpy as np
import pytest
import torch

from drake_grasp.geometry.actions import apply_actions
from drake_grasp.learning.dataset import SceneSamples
from drake_grasp.learning.dataset_shards import shard_name, write_shard
from drake_grasp.learning.dense_labels import (GRID_CONFIG, build_labels, grid_node_actions,
                                               load_labels, nearest_grasp_tree, tree_distances,
                                               view_masks)
from drake_grasp.learning.dense_training import augment_batch, train
from drake_grasp.cnn.views import AUGMENTATIONS, optical_axis_px, turn_grids, turn_images
from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
from drake_grasp.world.station import gripper_frame_offsets

CAMERA_Z = float(gripper_frame_offsets()[2].translation()[2])


def test_tree_distances_are_the_label_function():
    rng = np.random.default_rng(0)
    grasps = np.column_stack([rng.uniform(0.4, 0.6, 50), rng.uniform(-0.1, 0.1, 50),
                              rng.uniform(-180, 180, 50)])
    poses = np.column_stack([rng.uniform(0.3, 0.7, 2000), rng.uniform(-0.2, 0.2, 2000),
                             rng.uniform(-400, 400, 2000)])
    poses[:20, 2] = grasps[:20, 2] + 180.0 * rng.integers(-2, 3, 20)  # across the wrap
    expected = distance_to_nearest_grasp(poses, grasps)
    got = tree_distances(nearest_grasp_tree(grasps), poses)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


def _shard(folder, *, seed=0, scenes=2, images=6):
    """Flat depth, hands at random heights over a few random grasps per scene."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    samples = []
    for s in range(scenes):
        g = np.column_stack([rng.uniform(0.45, 0.55, 5), rng.uniform(-0.05, 0.05, 5),
                             rng.uniform(-90, 90, 5)])
        height = rng.uniform(0.15, 0.30, images)
        hand = np.column_stack([rng.uniform(0.45, 0.55, images), rng.uniform(-0.05, 0.05, images),
                                height + CAMERA_Z, rng.uniform(-180, 180, images)])
        depth = np.repeat(height[:, None, None], 64, axis=1).repeat(64, axis=2).astype(np.float32)
        depth[:, 20:30, 30:40] -= 0.05
        offsets = rng.uniform(-0.05, 0.05, (images, 10, 3))
        offsets[..., 2] = rng.uniform(-90, 90, (images, 10))
        labels = distance_to_nearest_grasp(apply_actions(hand[:, [0, 1, 3]], offsets).reshape(-1, 3),
                                           g).reshape(images, 10)
        samples.append(SceneSamples(s, "{}", depth, hand, offsets.astype(np.float32),
                                    labels.astype(np.float32), np.zeros((5, 4, 4)),
                                    np.full(5, 0.03, np.float32), g))
    write_shard(folder / shard_name(0), samples, attrs={"config_hash": "synthetic", "split": "x"})
    return samples


def test_dense_labels_are_exact_in_the_view_and_nan_beyond(tmp_path):
    samples = _shard(tmp_path / "data")
    assert build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False) == 12
    data = load_labels(tmp_path / "grid")
    assert data["grid"].shape == (12, 18, 33, 33) and data["grid"].dtype == np.float16
    nodes = grid_node_actions(GRID_CONFIG)
    for i in (0, 7):
        s = samples[i // 6]
        hand = s.hand_pose[i % 6]
        expected = distance_to_nearest_grasp(apply_actions(hand[[0, 1, 3]], nodes),
                                             s.grasp_xy_theta).reshape(18, 33, 33)
        mx = view_masks([hand[2]], GRID_CONFIG, CAMERA_Z)[0]
        inside = mx[None, :, None] & mx[None, None, :] & np.ones((18, 1, 1), bool)
        got = data["grid"][i].astype(np.float64)
        assert inside.sum() > 0 and (~inside).sum() > 0
        np.testing.assert_allclose(got[inside], expected[inside], rtol=2e-3, atol=1e-4)
        assert np.isnan(got[~inside]).all()
    # Re-running skips the finished shard.
    assert build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False) == 0


def test_build_labels_refuses_a_folder_without_shards(tmp_path):
    with pytest.raises(ValueError, match="no shard"):
        build_labels(tmp_path, tmp_path / "out", workers=1, progress=False)


def test_the_grid_net_learns_dense_labels(tmp_path):
    _shard(tmp_path / "data", scenes=2, images=8)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    with torch.random.fork_rng():
        metrics = train(tmp_path / "grid", tmp_path / "run", test_data=None, init=None,
                        epochs=10, batch=8, lr=2e-3, lr_decay=1.0, threads=2, progress=False)
    first, last = metrics["epochs"][0]["train_l1_m"], metrics["epochs"][-1]["train_l1_m"]
    assert last < 0.5 * first, (first, last)
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["epochs"][-1]["train_l1_m"] == last
    assert (tmp_path / "run" / "epoch10.safetensors").is_file()


def test_a_grid_net_with_another_trunk_trains_saves_and_scores(tmp_path, capsys):
    """`trunk` (`train-grid --trunk C1,C2,H`): the widths reach the saved net, which
    loads and scores candidates as the controller does; a run of another trunk is
    another run, and init weights of another trunk are refused."""
    import numpy as np

    from drake_grasp.cli.main import main
    from drake_grasp.cnn.weights_io import load_weights
    from drake_grasp.policies.evaluator import score_candidates

    _shard(tmp_path / "data", scenes=2, images=4)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    kw = dict(test_data=None, init=None, epochs=1, batch=4, lr=1e-3, threads=1, progress=False)
    metrics = train(tmp_path / "grid", tmp_path / "wide", trunk=(8, 12, 40), **kw)
    assert np.isfinite(metrics["epochs"][0]["train_l1_m"])
    net, _ = load_weights(tmp_path / "wide" / "epoch1.safetensors")
    cfg = net.config
    assert (cfg.conv1_channels, cfg.conv2_channels, cfg.ip1, cfg.action_fusion) == (8, 12, 40, "grid")
    rng = np.random.default_rng(0)
    actions = np.column_stack([rng.uniform(-0.04, 0.04, 16), rng.uniform(-0.04, 0.04, 16),
                               rng.uniform(-0.8, 0.8, 16)])
    scores = score_candidates(net.float(), rng.uniform(0.2, 0.3, (64, 64)), actions)
    assert scores.shape == (16,) and np.isfinite(scores).all()
    with pytest.raises(ValueError, match="another training run.*config"):
        train(tmp_path / "grid", tmp_path / "wide", trunk=(8, 12, 41), **kw)
    with pytest.raises(ValueError, match=r"trunk \(conv1, conv2, ip1\) is \(8, 12, 40\)"):
        train(tmp_path / "grid", tmp_path / "other", **{**kw, "init": str(
            tmp_path / "wide" / "epoch1.safetensors")})
    with pytest.raises(SystemExit):
        main(["train-grid", "--labels", str(tmp_path / "grid"), "--out", str(tmp_path / "x"),
              "--trunk", "8,12"])
    assert "three integers" in capsys.readouterr().err


def test_a_killed_run_resumes_to_the_uninterrupted_weights(tmp_path):
    _shard(tmp_path / "data", scenes=2, images=6)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    kw = dict(test_data=None, init=None, epochs=2, batch=4, lr=1e-3, threads=1, progress=False)
    train(tmp_path / "grid", tmp_path / "whole", **kw)
    # Killed after 2 of the 3 batches of epoch 1, then after 1 batch of epoch 2.
    train(tmp_path / "grid", tmp_path / "broken", _stop_after_batches=2, **kw)
    train(tmp_path / "grid", tmp_path / "broken", _stop_after_batches=2, **kw)
    metrics = train(tmp_path / "grid", tmp_path / "broken", **kw)
    assert [r["epoch"] for r in metrics["epochs"]] == [1, 2]
    _assert_same_weights(tmp_path / "whole" / "epoch2.safetensors",
                         tmp_path / "broken" / "epoch2.safetensors")
    with pytest.raises(ValueError, match="another training run.*lr"):
        train(tmp_path / "grid", tmp_path / "broken", **{**kw, "lr": 2e-3})


def test_training_runs_in_full_float32_and_restores_the_flags(tmp_path, monkeypatch):
    """TF32 convolutions (PyTorch's default for cuDNN) would change a run's arithmetic
    when it resumes on a GPU (measured: analysis/results/device-train-check/); the
    trainer turns them off for its duration only."""
    import drake_grasp.learning.dense_training as dt
    from drake_grasp.learning.common import full_float32

    flags = lambda: (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)
    saved = flags()
    try:
        torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = True
        _check_full_float32(tmp_path, monkeypatch, dt, full_float32, flags)
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def _check_full_float32(tmp_path, monkeypatch, dt, full_float32, flags):
    with pytest.raises(RuntimeError, match="inside"):
        with full_float32():
            assert flags() == (False, False)
            raise RuntimeError("inside")
    assert flags() == (True, True)

    seen = []
    real_view_masks = dt.view_masks
    monkeypatch.setattr(dt, "view_masks", lambda *a, **k: (seen.append(flags()),
                                                           real_view_masks(*a, **k))[1])
    _shard(tmp_path / "data", scenes=1, images=4)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    train(tmp_path / "grid", tmp_path / "run", test_data=None, init=None, epochs=1, batch=4,
          threads=1, progress=False)
    assert seen and all(f == (False, False) for f in seen)
    assert flags() == (True, True)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_a_run_started_on_the_cpu_resumes_on_the_gpu(tmp_path):
    """`device`: the checkpoint moves between devices; the GPU's float32 arithmetic
    differs from the CPU's in the last bits, so the weights agree to a tolerance (with
    TF32 convolutions they did not: 1.1e-4 apart on an H200; 1.7e-6 in full float32)."""
    from drake_grasp.cnn.weights_io import load_weights

    _shard(tmp_path / "data", scenes=2, images=6)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    kw = dict(test_data=None, init=None, epochs=2, batch=4, lr=1e-3, threads=1, progress=False)
    train(tmp_path / "grid", tmp_path / "cpu", device="cpu", **kw)
    train(tmp_path / "grid", tmp_path / "mixed", device="cpu", _stop_after_batches=4, **kw)
    train(tmp_path / "grid", tmp_path / "mixed", device="cuda", **kw)
    a, _ = load_weights(tmp_path / "cpu" / "epoch2.safetensors")
    b, _ = load_weights(tmp_path / "mixed" / "epoch2.safetensors")
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5, msg=name)


def test_cli_refuses_a_folder_that_holds_no_labels(tmp_path, capsys):
    from drake_grasp.cli.main import main

    assert main(["train-grid", "--labels", str(tmp_path), "--out", str(tmp_path / "run")]) == 2
    assert "not a dense-labels folder" in capsys.readouterr().err


def test_a_moved_label_folder_resumes_its_run(tmp_path):
    _shard(tmp_path / "data", scenes=1, images=4)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    kw = dict(test_data=None, init=None, epochs=2, batch=4, lr=1e-3, threads=1, progress=False)
    train(tmp_path / "grid", tmp_path / "run", _stop_after_batches=1, **kw)
    (tmp_path / "grid").rename(tmp_path / "moved")
    metrics = train(tmp_path / "moved", tmp_path / "run", **kw)
    assert [r["epoch"] for r in metrics["epochs"]] == [1, 2]


def _labels_and_a_grid_net(tmp_path):
    """Dense labels of a small dataset in tmp_path/grid, and a random grid net to start
    from (its weights file, returned)."""
    from drake_grasp.cnn.network import DistanceCNN
    from drake_grasp.cnn.weights_io import save_weights

    _shard(tmp_path / "data", scenes=2, images=6)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    init = tmp_path / "init.safetensors"
    save_weights(DistanceCNN(GRID_CONFIG, generator=torch.Generator().manual_seed(1)), init,
                 metadata={})
    return init


def test_batch_norm_folds_into_a_plain_grid_net_and_starts_as_the_identity(tmp_path):
    """`train(batch_norm=True)` (`train-grid --batch-norm`): the BatchNorms fold into
    Conv1, Conv2 and IP1 exactly (the folded plain net equals the module in eval mode);
    from trained weights they start as the identity (the folded net at step 0 is the
    init net); a killed run resumes to the unbroken one's weights; it is another run."""
    from drake_grasp.cli.main import main
    from drake_grasp.learning.dense_training import BatchNormTrunk
    from drake_grasp.cnn.network import DistanceCNN
    from drake_grasp.cnn.weights_io import load_weights

    gen = torch.Generator().manual_seed(3)
    net = DistanceCNN(GRID_CONFIG, generator=gen).double()
    bn = BatchNormTrunk(net)
    images = net.preprocess(np.random.default_rng(0).uniform(0.15, 0.35, (6, 64, 64)))
    bn.train()
    for _ in range(3):  # running statistics away from their defaults
        bn.image_features(images + 0.3 * torch.randn(images.shape, generator=gen,
                                                     dtype=images.dtype))
    with torch.no_grad():
        for b in (bn.bn1, bn.bn2, bn.bn3):
            b.weight.uniform_(-2.0, 2.0, generator=gen)  # negative scales fold too
            b.bias.uniform_(-0.5, 0.5, generator=gen)
    bn.eval()
    folded = bn.folded()
    assert type(folded) is DistanceCNN and folded.config == net.config
    with torch.no_grad():
        want, got = bn.image_features(images), folded.image_features(images)
    assert torch.allclose(want, got, rtol=0, atol=1e-12), float((want - got).abs().max())
    assert not torch.equal(want, net.image_features(images))  # the BatchNorms did something

    # From trained weights: the identity at the start.
    bn2 = BatchNormTrunk(net)
    bn2.start_as_identity(images)
    with torch.no_grad():
        assert torch.allclose(bn2.folded().image_features(images), net.image_features(images),
                              rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="grid net expected"):
        BatchNormTrunk(DistanceCNN())

    # Training end to end: resumes bit for bit; the epoch file is a plain grid net.
    init = _labels_and_a_grid_net(tmp_path)
    kw = dict(test_data=None, init=str(init), epochs=2, batch=4, lr=1e-3, threads=1,
              progress=False, batch_norm=True)
    train(tmp_path / "grid", tmp_path / "whole", **kw)
    train(tmp_path / "grid", tmp_path / "broken", _stop_after_batches=2, **kw)
    train(tmp_path / "grid", tmp_path / "broken", _stop_after_batches=2, **kw)
    train(tmp_path / "grid", tmp_path / "broken", **kw)
    a, _ = load_weights(tmp_path / "whole" / "epoch2.safetensors")
    b, _ = load_weights(tmp_path / "broken" / "epoch2.safetensors")
    assert a.config == GRID_CONFIG
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(x, y), name
    with pytest.raises(ValueError, match="another training run.*batch_norm"):
        train(tmp_path / "grid", tmp_path / "whole", **{**kw, "batch_norm": False})
    assert main(["train-grid", "--labels", str(tmp_path / "grid"), "--out",
                 str(tmp_path / "cli"), "--epochs", "1", "--batch", "4", "--threads", "1",
                 "--batch-norm"]) == 0
    run = json.loads((tmp_path / "cli" / "metrics.json").read_text())
    assert run["identity"]["batch_norm"] is True


def test_a_run_on_relabelled_data_of_the_same_shapes_is_another_run(tmp_path):
    """The run's identity holds the labels' bytes, not only their names and sizes."""
    _shard(tmp_path / "data", scenes=1, images=4)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    kw = dict(test_data=None, init=None, epochs=2, batch=4, lr=1e-3, threads=1, progress=False)
    train(tmp_path / "grid", tmp_path / "run", _stop_after_batches=1, **kw)
    part = next((tmp_path / "grid").glob("shard-*.npz"))
    with np.load(part) as z:
        data = dict(z)
    data["grid"] = np.where(np.isfinite(data["grid"]), data["grid"] + np.float16(0.01), data["grid"])
    size = part.stat().st_size
    np.savez(part, **data)
    assert part.stat().st_size == size
    with pytest.raises(ValueError, match="another training run.*labels"):
        train(tmp_path / "grid", tmp_path / "run", **kw)


def test_load_labels_fills_folders_and_shards_in_order_and_names_a_misshapen_part(tmp_path):
    rng = np.random.default_rng(0)
    parts = {}
    for folder, shard, n in (("a", 0, 3), ("a", 1, 2), ("b", 0, 4)):
        (tmp_path / folder).mkdir(exist_ok=True)
        part = {"depth": rng.random((n, 64, 64)).astype(np.float16),
                "grid": rng.random((n, 18, 33, 33)).astype(np.float16),
                "hand_z": rng.random(n).astype(np.float32)}
        np.savez(tmp_path / folder / f"shard-{shard:05d}.npz", **part)
        parts[folder, shard] = part
    data = load_labels([tmp_path / "a", tmp_path / "b"])
    for k in ("depth", "grid", "hand_z"):
        expected = np.concatenate([parts["a", 0][k], parts["a", 1][k], parts["b", 0][k]])
        assert data[k].dtype == expected.dtype
        np.testing.assert_array_equal(data[k], expected)
    bad = dict(parts["b", 0], grid=parts["b", 0]["grid"][:, :9])
    np.savez(tmp_path / "b" / "shard-00001.npz", **bad)
    with pytest.raises(ValueError, match=r"shard-00001.npz: 'grid' has shape \(4, 9, 33, 33\)"):
        load_labels([tmp_path / "a", tmp_path / "b"])


def test_checkpoint_weights_reads_a_grid_run_mid_epoch_and_at_its_end(tmp_path, capsys):
    """`drake-grasp checkpoint-weights` on a `train-grid` run (no train_config.json): a
    BatchNorm run's checkpoint comes out folded, equal to the epoch file at an epoch's
    end; within an epoch it says how far the run got."""
    from drake_grasp.cli.main import main
    from drake_grasp.learning.dense_training import export_checkpoint_weights
    from drake_grasp.cnn.weights_io import load_weights

    init = _labels_and_a_grid_net(tmp_path)
    kw = dict(test_data=None, init=str(init), epochs=1, batch=4, lr=1e-3, threads=1,
              progress=False, batch_norm=True)
    train(tmp_path / "grid", tmp_path / "run", **kw)
    assert main(["checkpoint-weights", str(tmp_path / "run"), "--out",
                 str(tmp_path / "end.safetensors")]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == {
        "out": str(tmp_path / "end.safetensors"), "checkpoint_epoch": 1,
        "checkpoint_next_batch": 0, "iterations": 3}
    a, _ = load_weights(tmp_path / "run" / "epoch1.safetensors")
    b, meta = load_weights(tmp_path / "end.safetensors")
    assert b.config == GRID_CONFIG and meta["identity"]["batch_norm"] is True
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(x, y), name

    # Killed after 2 of epoch 1's 3 batches: the weights of those 2 batches.
    train(tmp_path / "grid", tmp_path / "killed", _stop_after_batches=2, **kw)
    m = export_checkpoint_weights(tmp_path / "killed", tmp_path / "mid.safetensors")
    assert (m["checkpoint_epoch"], m["checkpoint_next_batch"], m["iterations"]) == (0, 2, 2)
    mid, _ = load_weights(tmp_path / "mid.safetensors")
    start, _ = load_weights(init)
    assert not torch.equal(mid.state_dict()["conv1.weight"], start.state_dict()["conv1.weight"])
    assert not torch.equal(mid.state_dict()["conv1.weight"], a.state_dict()["conv1.weight"])

    (tmp_path / "other").mkdir()
    torch.save({"epoch": 0}, tmp_path / "other" / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"other/checkpoint.pt: not a `train-grid` checkpoint"):
        export_checkpoint_weights(tmp_path / "other", tmp_path / "x.safetensors")
    with pytest.raises(FileNotFoundError, match="nothing/checkpoint.pt: not found"):
        export_checkpoint_weights(tmp_path / "nothing", tmp_path / "x.safetensors")


def _assert_same_weights(path_a, path_b):
    from drake_grasp.cnn.weights_io import load_weights

    a, _ = load_weights(path_a)
    b, _ = load_weights(path_b)
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        assert torch.equal(x, y), name


def _label_folders(tmp_path, n=3, images=6):
    """`n` dense-label folders of one part each (2 scenes of `images` images)."""
    folders = []
    for i in range(n):
        _shard(tmp_path / f"data{i}", seed=i, scenes=2, images=images)
        build_labels(tmp_path / f"data{i}", tmp_path / f"grid{i}", workers=1, progress=False)
        folders.append(tmp_path / f"grid{i}")
    return folders


def test_streamed_epochs_take_every_image_once_and_hold_at_most_two_groups(tmp_path):
    """`LabelStore(stream_shards=G)`: an epoch's order is a permutation of all images,
    each group of G parts contiguous in it; what a batch takes equals the in-memory
    labels at those indices; while the batches go through the epoch no more than the
    parts of two groups are held."""
    from drake_grasp.learning.dense_labels import LabelStore

    folders = _label_folders(tmp_path, n=5, images=3)  # 5 parts of 6 images
    whole = load_labels(folders)
    store = LabelStore(folders, stream_shards=2)
    assert store.n_images == len(whole["hand_z"]) == 30
    for epoch in (0, 1):
        order = store.epoch_order(7, epoch)
        assert sorted(order) == list(range(30))
        part_of = np.searchsorted(store.offsets, order, side="right") - 1
        group = store._group_of[part_of]
        assert (np.diff(group) >= 0).all()  # the groups in turn
        assert np.bincount(group).tolist() == [12, 12, 6]  # 2 + 2 + 1 parts
        most = 0
        for start in range(0, 30, 4):
            idx = np.sort(order[start:start + 4])
            store.release_before(idx)
            got = store.take(idx)
            for k in ("depth", "grid", "hand_z"):
                np.testing.assert_array_equal(got[k], whole[k][idx])
            most = max(most, len(store._held))
        assert most <= 4
    some = np.array([0, 7, 29])  # what a BatchNorm start reads: the depth alone
    np.testing.assert_array_equal(store.take(some, keys=("depth",))["depth"], whole["depth"][some])
    assert not np.array_equal(store.epoch_order(7, 0), store.epoch_order(7, 1))
    np.testing.assert_array_equal(store.epoch_order(7, 0), LabelStore(folders, 2).epoch_order(7, 0))
    with pytest.raises(ValueError, match="stream_shards: expected a positive"):
        LabelStore(folders, stream_shards=0)


def test_a_killed_streamed_run_resumes_to_the_uninterrupted_weights(tmp_path, capsys):
    """`train-grid --stream-shards G`: a streamed run killed mid-epoch resumes to the
    unbroken run's weights; its identity names the grouping, so an in-memory run's folder
    refuses it; a misshapen part is named when its group is reached."""
    from drake_grasp.cli.main import main

    folders = _label_folders(tmp_path, n=3, images=4)  # 3 parts of 8 images
    kw = dict(test_data=None, init=None, epochs=2, batch=5, lr=1e-3, threads=1,
              progress=False, stream_shards=2)
    m = train(folders, tmp_path / "whole", **kw)
    assert m["identity"]["stream_shards"] == 2 and m["identity"]["images"] == 24
    train(folders, tmp_path / "broken", _stop_after_batches=3, **kw)
    train(folders, tmp_path / "broken", _stop_after_batches=3, **kw)
    metrics = train(folders, tmp_path / "broken", **kw)
    assert [r["epoch"] for r in metrics["epochs"]] == [1, 2]
    assert [r["images"] for r in metrics["epochs"]] == [24, 24]
    _assert_same_weights(tmp_path / "whole" / "epoch2.safetensors",
                         tmp_path / "broken" / "epoch2.safetensors")
    with pytest.raises(ValueError, match="another training run.*stream_shards"):
        train(folders, tmp_path / "whole", **{**kw, "stream_shards": None})
    assert main(["train-grid", "--labels", ",".join(map(str, folders)), "--out",
                 str(tmp_path / "cli"), "--epochs", "1", "--batch", "5", "--threads", "1",
                 "--stream-shards", "1", "--device", "cpu"]) == 0
    saved = json.loads((tmp_path / "cli" / "metrics.json").read_text())
    assert saved["identity"]["stream_shards"] == 1
    part = tmp_path / "grid2" / "shard-00000.npz"
    with np.load(part) as z:
        bad = {k: z[k] for k in z.files}
    bad["grid"] = bad["grid"][:, :9]
    np.savez(part, **bad)
    with pytest.raises(ValueError, match=r"grid2/shard-00000.npz: 'grid' has shape \(8, 9,"):
        train(folders, tmp_path / "bad", **kw)


def test_device_train_check_dry_run_on_the_cpu(tmp_path, analysis_script):
    """analysis/device_train_check.py with the CPU in the GPU's place: its resume check
    runs the product's trainer twice and compares (on one device, bit for bit); with
    Drake present the camera height it would stand in is checked against the gripper
    model, and a wrong one is refused."""
    script = analysis_script("device_train_check")
    _shard(tmp_path / "data", scenes=1, images=5)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    out = tmp_path / "check.json"
    assert script.main(["--labels", str(tmp_path / "grid"), "--out", str(out), "--device", "cpu",
                        "--cpu-threads", "1", "--skip", "throughput,step"]) == 0
    got = json.loads(out.read_text())
    assert got["drake_stand_in"] is False and got["camera_z_G_m"] == CAMERA_Z
    assert got["label_images"] == 5
    for key in ("resume_test_size", "resume_all_images"):
        assert got[key]["within_rtol_1e-4_atol_1e-5"] is True
        assert got[key]["max_abs_diff"] == 0.0
    with pytest.raises(ValueError, match="--camera-z -0.1: the gripper model gives"):
        script.main(["--labels", str(tmp_path / "grid"), "--out", str(out), "--device", "cpu",
                     "--camera-z", "-0.1", "--skip", "resume,throughput,step"])
    assert script.main(["--labels", str(tmp_path / "data"), "--out", str(out)]) == 2


# ----------------------------------------------------------------------------
# Symmetries of the wrist camera (`train-grid --augment`).

X_GC_XY = gripper_frame_offsets()[2].translation()[:2]


def _camera_centre(hand):
    from drake_grasp.geometry.actions import hand_axes

    ex, ey = hand_axes(hand[3])
    return hand[:2] + X_GC_XY[0] * ex + X_GC_XY[1] * ey


def _hand_turned_about_the_camera(hand, dyaw_deg):
    """The hand turned by `dyaw_deg` about the camera's (vertical) axis: same camera
    centre and height, yaw + dyaw."""
    from drake_grasp.geometry.actions import hand_axes

    centre = _camera_centre(hand)
    yaw = hand[3] + dyaw_deg
    ex, ey = hand_axes(yaw)
    return np.array([*(centre - X_GC_XY[0] * ex - X_GC_XY[1] * ey), hand[2], yaw])


def _grid_at(hand, grasps):
    """The label of every grid node (T, N, N) for this hand over these grasps."""
    nodes = grid_node_actions(GRID_CONFIG)
    moved = apply_actions(hand[[0, 1, 3]], nodes)
    return tree_distances(nearest_grasp_tree(grasps), moved).reshape(GRID_CONFIG.grid_shape())


# np.rot90's k on (rows, columns) for the hand turned by +90 degrees per step about the
# camera's axis (measured on rendered images: the test below).
K_PER_QUARTER_TURN_OF_THE_HAND = 3


def test_turned_label_grids_are_the_labels_of_the_turned_hand_and_the_mirrored_scene():
    """`turn_grids` is exact: the labels seen from the hand turned by 90, 180 or 270
    degrees about the camera's axis, and the labels of the scene reflected in the camera's
    y-z plane, are the original grid under the symmetry `turn_images` applies to the
    image."""
    from drake_grasp.geometry.actions import hand_axes

    rng = np.random.default_rng(3)
    hand = np.array([0.52, 0.03, 0.25, 37.0])
    grasps = np.column_stack([rng.uniform(0.42, 0.62, 12), rng.uniform(-0.07, 0.13, 12),
                              rng.uniform(-180, 180, 12)])
    grid = _grid_at(hand, grasps)
    assert np.ptp(grid) > 0.05
    for j in (1, 2, 3):
        k = (K_PER_QUARTER_TURN_OF_THE_HAND * j) % 4
        turned = _grid_at(_hand_turned_about_the_camera(hand, 90.0 * j), grasps)
        np.testing.assert_allclose(turn_grids(grid, k, False), turned, rtol=0, atol=1e-9)
        assert np.abs(turn_grids(grid, (k + 2) % 4, False) - turned).max() > 0.01
    # The scene reflected in the camera's y-z plane (normal x_G through the camera).
    ex, _ = hand_axes(hand[3])
    rel = grasps[:, :2] - _camera_centre(hand)
    mirrored_xy = grasps[:, :2] - 2.0 * (rel @ ex)[:, None] * ex
    d = np.column_stack([np.cos(np.deg2rad(grasps[:, 2])), np.sin(np.deg2rad(grasps[:, 2]))])
    d = d - 2.0 * (d @ ex)[:, None] * ex
    mirrored = np.column_stack([mirrored_xy, np.rad2deg(np.arctan2(d[:, 1], d[:, 0]))])
    flipped = _grid_at(hand, mirrored)
    np.testing.assert_allclose(turn_grids(grid, 0, True), flipped, rtol=0, atol=1e-9)
    for k in (1, 2, 3):  # a flip, then turns of the hand
        j = (k * K_PER_QUARTER_TURN_OF_THE_HAND) % 4
        np.testing.assert_allclose(
            turn_grids(grid, k, True),
            _grid_at(_hand_turned_about_the_camera(hand, 90.0 * j), mirrored), rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="theta bins"):
        turn_grids(np.zeros((3, 5, 5)), 1, False)


def test_a_hand_turned_about_the_camera_axis_renders_the_turned_image(library):
    """`turn_images` matches Drake's renderer: the depth image from the hand turned by
    90, 180 or 270 degrees about the camera's axis is the first image turned about pixel
    (31, 31), pixel for pixel but the last row and column (no partner in the image);
    turned about the image's centre (31.5, 31.5), which `CameraInfo` documents as its
    principal point, it is a pixel off."""
    pytest.importorskip("pydrake")
    from drake_grasp.learning.dataset import SceneRenderer
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.scene import build_scene_world, make_scene

    scenario = load_scenario(scenario_name="isolation",
                             scenario_text="{scene: {object_ids: [tetra_pak_000], pose: lying}}")
    settled = make_scene(scenario.scene, 0, library)
    world = build_scene_world(settled, library, renderer_name="vtk")
    renderer = SceneRenderer(world, scenario.camera)
    hand = np.array([0.51, 0.02, 0.185, 20.0])
    image = renderer.render(hand)
    assert np.ptp(image[np.isfinite(image)]) > 0.02  # the object is in view
    for j in (1, 2, 3):
        k = (K_PER_QUARTER_TURN_OF_THE_HAND * j) % 4
        seen = renderer.render(_hand_turned_about_the_camera(hand, 90.0 * j))
        np.testing.assert_allclose(turn_images(image, k, False)[:63, :63], seen[:63, :63],
                                   rtol=0, atol=1e-6)
        off = np.abs(np.rot90(image, k) - seen)[:63, :63]
        assert (off > 1e-3).sum() > 20
    # GPD's 640 x 480 camera (docs/guide/station.md, *Depth sensing*): turned 180 degrees, its image is
    # symmetric about pixel (319, 239), half a pixel from CameraInfo's (319.5, 239.5).
    gpd = SceneRenderer(world, scenario.gpd)
    high = np.array([0.51, 0.02, 0.68 + CAMERA_Z, 20.0])
    a, b = gpd.render(high), gpd.render(_hand_turned_about_the_camera(high, 180.0))
    assert a.shape == (480, 640)
    assert (optical_axis_px(480), optical_axis_px(640)) == (239, 319)
    np.testing.assert_allclose(a[:479, :639][::-1, ::-1], b[:479, :639], rtol=0, atol=1e-6)
    assert (np.abs(a[::-1, ::-1] - b) > 1e-3).sum() > 100


def test_augmented_batches_turn_each_image_with_its_labels():
    rng = np.random.default_rng(0)
    data = {"depth": rng.uniform(0.2, 0.3, (40, 64, 64)).astype(np.float16),
            "grid": rng.uniform(0.0, 0.2, (40, *GRID_CONFIG.grid_shape())).astype(np.float16),
            "hand_z": rng.uniform(0.3, 0.4, 40).astype(np.float32)}
    assert augment_batch(data, "none", np.random.default_rng(1)) is data
    for name in ("mirror", "d4"):
        out = augment_batch(data, name, np.random.default_rng(1))
        pick = np.random.default_rng(1).integers(0, len(AUGMENTATIONS[name]), 40)
        assert len(set(pick)) == len(AUGMENTATIONS[name])
        for i, j in enumerate(pick):
            k, flip = AUGMENTATIONS[name][j]
            np.testing.assert_array_equal(out["depth"][i], turn_images(data["depth"][i], k, flip))
            np.testing.assert_array_equal(out["grid"][i], turn_grids(data["grid"][i], k, flip))
        np.testing.assert_array_equal(out["hand_z"], data["hand_z"])
        assert out["depth"].dtype == np.float16 and out["grid"].dtype == np.float16
    # turn_images: a quarter turn four times, or a flip twice, is the identity on the
    # 63 x 63 core about the optical axis
    img = data["depth"][0]
    four = img
    for _ in range(4):
        four = turn_images(four, 1, False)
    np.testing.assert_array_equal(four[:63, :63], img[:63, :63])
    np.testing.assert_array_equal(turn_images(turn_images(img, 0, True), 0, True)[:63, :63],
                                  img[:63, :63])
    with pytest.raises(ValueError, match="square images"):
        turn_images(np.zeros((64, 32)), 1, False)
    with pytest.raises(ValueError, match="even image sizes, got 63"):
        turn_images(np.zeros((63, 63)), 1, False)


def test_an_augmented_run_resumes_to_the_uninterrupted_weights(tmp_path):
    """`train(augment="d4")`: the draws are seeded by (seed, epoch, batch), so a killed run
    resumes to the unbroken run's weights; the augmentation is part of the run's identity,
    and it changes what is learnt."""
    from drake_grasp.cli.main import main

    _shard(tmp_path / "data", scenes=2, images=6)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    kw = dict(test_data=None, init=None, epochs=2, batch=4, lr=1e-3, threads=1, progress=False,
              augment="d4")
    m = train(tmp_path / "grid", tmp_path / "whole", **kw)
    assert m["identity"]["augment"] == "d4"
    train(tmp_path / "grid", tmp_path / "broken", _stop_after_batches=2, **kw)
    train(tmp_path / "grid", tmp_path / "broken", _stop_after_batches=2, **kw)
    train(tmp_path / "grid", tmp_path / "broken", **kw)
    _assert_same_weights(tmp_path / "whole" / "epoch2.safetensors",
                         tmp_path / "broken" / "epoch2.safetensors")
    plain = train(tmp_path / "grid", tmp_path / "plain", **{**kw, "augment": "none"})
    assert "augment" not in plain["identity"]
    assert plain["epochs"][-1]["train_l1_m"] != m["epochs"][-1]["train_l1_m"]
    with pytest.raises(ValueError, match="another training run.*augment"):
        train(tmp_path / "grid", tmp_path / "whole", **{**kw, "augment": "mirror"})
    with pytest.raises(ValueError, match="augment: expected one of"):
        train(tmp_path / "grid", tmp_path / "x", **{**kw, "augment": "rot"})
    assert main(["train-grid", "--labels", str(tmp_path / "grid"), "--out", str(tmp_path / "cli"),
                 "--epochs", "1", "--batch", "4", "--threads", "1", "--device", "cpu",
                 "--augment", "mirror"]) == 0
    saved = json.loads((tmp_path / "cli" / "metrics.json").read_text())
    assert saved["identity"]["augment"] == "mirror"


def test_rank_pairs_are_nearby_distinct_nodes_of_the_grid():
    from drake_grasp.learning.dense_rank import RANK_REACH_CELLS, rank_pairs

    shape = GRID_CONFIG.grid_shape()
    t_bins, n, _ = shape
    first, second = rank_pairs(shape, 7, 5000, np.random.default_rng(3))
    assert first.shape == second.shape == (7, 5000)
    assert first.min() >= 0 and first.max() < t_bins * n * n
    on = second >= 0
    assert 0.5 < on.mean() < 1.0  # anchors at the grid's edge lose some partners
    a = np.stack(np.unravel_index(first[on], shape))
    b = np.stack(np.unravel_index(second[on], shape))
    dt = np.abs(a[0] - b[0])
    dt = np.minimum(dt, t_bins - dt)  # theta wraps over 180 degrees
    assert dt.max() == RANK_REACH_CELLS
    assert np.abs(a[1:] - b[1:]).max() == RANK_REACH_CELLS
    assert (first[on] != second[on]).all()
    assert (np.mod(a[0] + (b[0] - a[0]), t_bins) == b[0]).all()
    assert ((a[0] == 0) & (b[0] == t_bins - 1)).any()  # pairs across the wrap exist
    again = rank_pairs(shape, 7, 5000, np.random.default_rng(3))
    np.testing.assert_array_equal(again[0], first)
    np.testing.assert_array_equal(again[1], second)


def test_pairwise_rank_loss_is_the_logistic_loss_of_the_counted_pairs():
    from drake_grasp.learning.dense_rank import pairwise_rank_loss

    rng = np.random.default_rng(0)
    shape = (2, 3, 3, 3)
    target = torch.from_numpy(rng.uniform(0, 0.1, shape))
    pred = torch.from_numpy(rng.uniform(0, 0.1, shape))
    mask = torch.from_numpy(rng.uniform(size=shape) > 0.2)
    first = rng.integers(0, 27, (2, 40))
    second = rng.integers(0, 27, (2, 40))
    second[:, :5] = -1
    target.reshape(2, -1)[0, second[0, 10]] = target.reshape(2, -1)[0, first[0, 10]] + 0.001
    got = pairwise_rank_loss(pred, target, mask, first, second, scale_m=0.01, margin_m=0.002)
    terms = []
    p, t, m = pred.reshape(2, -1).numpy(), target.reshape(2, -1).numpy(), mask.reshape(2, -1).numpy()
    for b in range(2):
        for i, j in zip(first[b], second[b]):
            if j < 0 or not (m[b, i] and m[b, j]) or abs(t[b, j] - t[b, i]) <= 0.002:
                continue
            z = np.sign(t[b, j] - t[b, i]) * (p[b, j] - p[b, i]) / 0.01
            terms.append(np.log1p(np.exp(-z)))
    assert 20 < len(terms) < 80
    np.testing.assert_allclose(float(got), np.mean(terms), rtol=1e-10)
    # predictions in the labels' order cost less than the reverse; no pair counts -> 0
    ordered = pairwise_rank_loss(target, target, mask, first, second, scale_m=0.01, margin_m=0.0)
    reverse = pairwise_rank_loss(-target, target, mask, first, second, scale_m=0.01, margin_m=0.0)
    assert float(ordered) < np.log(2.0) < float(reverse)
    none = pairwise_rank_loss(pred, target, torch.zeros_like(mask), first, second,
                              scale_m=0.01, margin_m=0.0)
    assert float(none) == 0.0


def test_a_rank_loss_run_resumes_and_is_its_own_run(tmp_path):
    """`train(rank_weight=...)`: the pairs are drawn from (seed, epoch, batch), so a killed
    run resumes to the unbroken run's weights; the rank settings are part of the run's
    identity (absent without them) and change what is learnt."""
    from drake_grasp.cli.main import main

    _shard(tmp_path / "data", scenes=2, images=6)
    build_labels(tmp_path / "data", tmp_path / "grid", workers=1, progress=False)
    kw = dict(test_data=None, init=None, epochs=2, batch=4, lr=1e-3, threads=1, progress=False,
              rank_weight=0.05)
    m = train(tmp_path / "grid", tmp_path / "whole", **kw)
    assert m["identity"]["rank"]["weight"] == 0.05
    assert all(row["train_rank_loss"] > 0 for row in m["epochs"])
    train(tmp_path / "grid", tmp_path / "broken", _stop_after_batches=2, **kw)
    train(tmp_path / "grid", tmp_path / "broken", **kw)
    _assert_same_weights(tmp_path / "whole" / "epoch2.safetensors",
                         tmp_path / "broken" / "epoch2.safetensors")
    broken = json.loads((tmp_path / "broken" / "metrics.json").read_text())
    assert broken["epochs"] == m["epochs"]
    plain = train(tmp_path / "grid", tmp_path / "plain", **{**kw, "rank_weight": 0.0})
    assert "rank" not in plain["identity"] and "train_rank_loss" not in plain["epochs"][0]
    assert plain["epochs"][-1]["train_l1_m"] != m["epochs"][-1]["train_l1_m"]
    with pytest.raises(ValueError, match="another training run.*rank"):
        train(tmp_path / "grid", tmp_path / "whole", **{**kw, "rank_weight": 0.1})
    with pytest.raises(ValueError, match="rank_weight: expected a finite number >= 0"):
        train(tmp_path / "grid", tmp_path / "x", **{**kw, "rank_weight": -1.0})
    with pytest.raises(ValueError, match="rank_scale_m > 0"):
        train(tmp_path / "grid", tmp_path / "x", **{**kw, "rank_scale_m": 0.0})
    assert main(["train-grid", "--labels", str(tmp_path / "grid"), "--out", str(tmp_path / "cli"),
                 "--epochs", "1", "--batch", "4", "--threads", "1", "--device", "cpu",
                 "--rank-weight", "0.02", "--rank-scale-m", "0.005"]) == 0
    saved = json.loads((tmp_path / "cli" / "metrics.json").read_text())
    assert saved["identity"]["rank"] == {"weight": 0.02, "pairs_per_image": 1024,
                                         "scale_m": 0.005, "margin_m": 0.002, "reach_cells": 4}
    with pytest.raises(SystemExit):
        main(["train-grid", "--labels", str(tmp_path / "grid"), "--out", str(tmp_path / "y"),
              "--rank-weight", "-0.1"])
