"""analysis/results/cnn-onpolicy-finetune/choose_gate.py: the plan's choice and gate on
fabricated score files."""

import json

import pytest

SCRIPT = "results/cnn-onpolicy-finetune/choose_gate"


def write_score(path, regret_median_mm, spearman, decisions=100):
    block = {"none": {"decisions": decisions, "spearman_mean": spearman,
                      "regret_mean_mm": regret_median_mm + 5,
                      "regret_median_mm": regret_median_mm, "top1_within_1cm": 0.4}}
    path.write_text(json.dumps({"decisions": decisions, "all": block,
                                "by_outcome": {"failed": block}}))


def test_choose_takes_the_lowest_median_regret_then_the_higher_spearman(analysis_script, tmp_path):
    S = analysis_script(SCRIPT)
    write_score(tmp_path / "default.json", 18.0, 0.43)
    write_score(tmp_path / "a-epoch1.json", 17.0, 0.44)
    write_score(tmp_path / "b-epoch2.json", 16.0, 0.45)
    write_score(tmp_path / "c-epoch3.json", 16.0, 0.47)
    out = S.choose(tmp_path)
    assert out["chosen"] == "c-epoch3" and set(out["candidates"]) == {"a-epoch1", "b-epoch2",
                                                                      "c-epoch3"}
    assert out["default"]["regret_median_mm"] == 18.0
    with pytest.raises(FileNotFoundError, match="no <run>-epoch<E>.json"):
        S.choose(tmp_path / "nothing")


@pytest.mark.parametrize("regret,spearman,passed", [
    (17.0, 0.45, True),    # 1.0 mm and 0.02 exactly
    (17.1, 0.50, False),   # regret not low enough
    (10.0, 0.449, False),  # Spearman not high enough
])
def test_gate(analysis_script, tmp_path, regret, spearman, passed):
    S = analysis_script(SCRIPT)
    write_score(tmp_path / "d.json", 18.0, 0.43)
    write_score(tmp_path / "c.json", regret, spearman)
    assert S.gate(tmp_path / "d.json", tmp_path / "c.json")["passed"] is passed
    write_score(tmp_path / "other.json", regret, spearman, decisions=99)
    with pytest.raises(ValueError, match="99 decisions.*not the same states"):
        S.gate(tmp_path / "d.json", tmp_path / "other.json")


def test_heldout_l1_is_the_training_loss_over_the_labelled_view(analysis_script, tmp_path):
    """heldout_l1.py: the mean absolute error over every labelled in-view node of a
    label folder, computed by hand from the net's grids for one fabricated attempt."""
    import numpy as np
    import torch

    H = analysis_script("results/cnn-onpolicy-finetune/heldout_l1")
    from drake_grasp.learning.dense_labels import GRID_CONFIG, label_grids
    from drake_grasp.cnn.network import DistanceCNN
    from drake_grasp.cnn.weights_io import save_weights

    rng = np.random.default_rng(2)
    hand = np.column_stack([rng.uniform(-0.05, 0.05, (3, 2)), [0.2, 0.1, 0.05], [0, 30, -60]])
    grasps = rng.uniform([-0.1, -0.1, -90], [0.1, 0.1, 90], (4, 3))
    depth = rng.uniform(0.2, 0.3, (3, 64, 64)).astype(np.float16)
    grid = label_grids(hand, grasps, GRID_CONFIG)
    folder = tmp_path / "grid"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps(GRID_CONFIG.to_dict()))
    np.savez(folder / "shard-a.npz", depth=depth, grid=grid, hand_z=hand[:, 2].astype(np.float32))
    net = DistanceCNN(GRID_CONFIG, generator=torch.Generator().manual_seed(0))
    save_weights(net, tmp_path / "w.safetensors", metadata={})
    with torch.no_grad():
        pred = net.eval().image_features(net.preprocess(depth.astype(np.float32))).numpy()
    labelled = np.isfinite(grid.astype(float))
    want = np.abs(pred - grid.astype(np.float32))[labelled].mean()
    assert H.heldout_l1(str(folder), str(tmp_path / "w.safetensors"), batch=2) == pytest.approx(
        float(want), rel=1e-5)
