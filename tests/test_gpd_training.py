"""GPD classifier data (resumable shards, ground-truth labels) and training."""

import json

import numpy as np
import pytest

from drake_grasp.policies import gpd

from drake_grasp.learning import gpd_training
from drake_grasp.objects.categories import NO_SINGLE_OBJECT
from drake_grasp.config.scenario import Scenario

TINY = gpd_training.GpdDataConfig(scene_kinds=("isolation",), candidates_per_scene=16,
                                  scenes_per_shard=1, noisy_fraction=0.0)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("gpd_data")
    summary = gpd_training.generate(out=out, num_scenes=2, split="train", seed=3,
                                    scenario=Scenario(), config=TINY, progress=False)
    return out, summary


def test_generate_writes_labelled_candidates(tiny_data):
    out, summary = tiny_data
    assert summary["complete"] and summary["num_scenes"] == 2
    data = gpd_training.load_data(out)
    n = len(data["labels"])
    assert n == summary["candidates"] and 0 < n <= 2 * TINY.candidates_per_scene
    assert data["images"].shape == (n, gpd.CHANNELS, gpd.IMAGE_SIZE, gpd.IMAGE_SIZE)
    assert data["images"].dtype == np.uint8
    assert set(np.unique(data["labels"])) <= {0, 1}
    # Positives are at most a quarter of each scene's kept candidates.
    for s in (0, 1):
        assert data["labels"][data["scene"] == s].sum() <= int(TINY.candidates_per_scene * TINY.max_positive_fraction)
    # Approaches stay in the configured cone.
    tilt = np.degrees(np.arccos(np.clip(-data["poses"][:, 2, 2], -1, 1)))
    assert tilt.max() <= Scenario().gpd.approach_max_tilt_deg + 1e-3
    # A positive's pads touch an object (its category is recorded).
    assert all(c for c in data["category"][data["labels"] == 1])


def test_generate_resumes_a_lost_shard_identically_and_refuses_other_settings(tiny_data):
    out, _ = tiny_data
    shard = out / "gpd-shard-00001.npz"
    before = np.load(shard)["labels"].copy()
    shard.unlink()
    gpd_training.generate(out=out, num_scenes=2, split="train", seed=3, scenario=Scenario(),
                          config=TINY, progress=False)
    np.testing.assert_array_equal(np.load(shard)["labels"], before)
    with pytest.raises(ValueError, match="different settings"):
        gpd_training.generate(out=out, num_scenes=2, split="train", seed=4, scenario=Scenario(),
                              config=TINY, progress=False)


def test_load_data_refuses_incomplete_folders(tmp_path):
    with pytest.raises(ValueError, match="not a complete GPD data folder"):
        gpd_training.load_data(tmp_path)


def test_several_data_folders_are_concatenated_in_order(tiny_data, tmp_path):
    """`gpd-train --data A,B`: the folders' candidates one after the other; a missing
    or incomplete folder among them is named."""
    out, _ = tiny_data
    one = gpd_training.load_data(out)
    both = gpd_training.load_data_folders(f"{out},{out}")
    n = len(one["labels"])
    assert len(both["labels"]) == 2 * n and len(both["scene_stats"]) == 2 * len(one["scene_stats"])
    np.testing.assert_array_equal(both["images"][n:], one["images"])
    assert len(gpd_training.load_data_folders([out])["labels"]) == n
    with pytest.raises(ValueError, match=f"{tmp_path}: not a complete GPD data folder"):
        gpd_training.load_data_folders([out, tmp_path])
    with pytest.raises(ValueError, match="none given"):
        gpd_training.load_data_folders(",")


def test_train_writes_weights_metrics_and_resumes(tiny_data, tmp_path):
    out, _ = tiny_data
    cfg = gpd_training.GpdTrainConfig(epochs=1, batch_size=8, threads=1)
    metrics = gpd_training.train(data=out, test_data=out, out=tmp_path, config=cfg, progress=False)
    assert (tmp_path / "weights.safetensors").exists()
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["held_out"]["0.5"]["num"] == metrics["test"]["candidates"]
    assert sum(c["0.5"]["num"] for c in saved["held_out_by_category"].values()) \
        == metrics["test"]["candidates"]
    assert len(saved["history"]) == 1
    gpd.load_classifier(tmp_path / "weights.safetensors")
    # A second run with more epochs continues from the checkpoint (one more epoch).
    cfg2 = gpd_training.GpdTrainConfig(epochs=2, batch_size=8, threads=1)
    again = gpd_training.train(data=out, test_data=out, out=tmp_path, config=cfg2, progress=False)
    assert [h["epoch"] for h in again["history"]] == [1, 2]


def test_held_out_metrics_split_by_category():
    prob = np.array([0.95, 0.6, 0.2, 0.8, 0.3, 0.99])
    labels = np.array([1, 0, 1, 0, 0, 0])
    category = np.array(["mug", "mug", "mug", "hammer", "hammer", ""])
    m = gpd_training.held_out_metrics(prob, labels, category)
    assert m["held_out"]["0.5"]["tp"] == 1 and m["held_out"]["0.5"]["fp"] == 3
    assert set(m["by_category"]) == {"mug", "hammer", NO_SINGLE_OBJECT}
    mug = m["by_category"]["mug"]
    assert (mug["0.5"]["tp"], mug["0.5"]["fp"], mug["0.5"]["fn"]) == (1, 1, 1)
    assert mug["0.9"]["precision"] == 1.0 and mug["0.9"]["recall"] == 0.5
    assert m["by_category"]["hammer"]["0.5"]["precision"] == 0.0
    assert m["by_category"][NO_SINGLE_OBJECT]["0.5"]["fp"] == 1
    # The per-category counts add up to the overall ones.
    for t in ("0.5", "0.7", "0.9"):
        for k in ("tp", "fp", "fn", "num"):
            assert sum(c[t][k] for c in m["by_category"].values()) == m["held_out"][t][k]
    with pytest.raises(ValueError, match="3 categories"):
        gpd_training.held_out_metrics(prob, labels, category[:3])


def test_gpd_eval_scores_a_classifier_per_category(tiny_data, tmp_path, capsys):
    from drake_grasp.cli.main import main

    out, summary = tiny_data
    assert main(["gpd-eval", "--data", str(out), "--out", str(tmp_path / "eval.json"),
                 "--threads", "1"]) == 0
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["weights"] == "shipped" and len(result["weights_sha256"]) == 64
    assert result["candidates"] == summary["candidates"]
    assert result["held_out"]["0.5"]["num"] == summary["candidates"]
    data = gpd_training.load_data(out)
    assert set(result["by_category"]) == {c or NO_SINGLE_OBJECT for c in data["category"]}
    assert "all" in capsys.readouterr().out


def test_focus_categories_put_one_instance_of_them_in_every_scene(tmp_path):
    from drake_grasp.objects import load_library

    library = load_library()
    for seed in range(6):
        ids = gpd_training.focus_object_ids(library, ("hammer",), "train", seed, slots=5)
        assert sorted(ids) == sorted(library.ids(split="train"))
        assert any(library.get(i).category == "hammer" for i in ids[:5])
    firsts = {gpd_training.focus_object_ids(library, ("hammer", "flashlight"), "test", s)[0]
              for s in range(12)}
    assert {library.get(i).category for i in firsts} == {"hammer", "flashlight"}
    assert gpd_training.focus_object_ids(library, ("hammer",), "test", 3) == \
        gpd_training.focus_object_ids(library, ("hammer",), "test", 3)
    with pytest.raises(ValueError, match="wrench"):
        gpd_training.focus_object_ids(library, ("wrench",), "train", 0)
    with pytest.raises(ValueError, match="wrench"):
        gpd_training.generate(out=tmp_path / "never", num_scenes=1, split="train", seed=0,
                              scenario=Scenario(), config=gpd_training.GpdDataConfig(
                                  focus_categories=("wrench",)), progress=False)
    assert not (tmp_path / "never").exists()
    cfg = gpd_training.GpdDataConfig(scene_kinds=("isolation",), candidates_per_scene=16,
                                     scenes_per_shard=1, noisy_fraction=0.0,
                                     focus_categories=("hammer",))
    gpd_training.generate(out=tmp_path, num_scenes=2, split="train", seed=3,
                          scenario=Scenario(), config=cfg, progress=False)
    data = gpd_training.load_data(tmp_path)
    assert {s["object_ids"][0].split("_")[0] for s in data["scene_stats"]} == {"hammer"}
