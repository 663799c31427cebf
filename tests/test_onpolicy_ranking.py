"""analysis/onpolicy_ranking.py: a recorded clutter attempt replayed with its decisions
kept and labelled; scorers ranked on them."""

import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
RECORD = (ROOT / "analysis" / "results" / "cnn-view-average" / "plain-clutter-seed30" / "trials"
          / "clutter__ctr__0000__attempt04.json")


def _fake_attempt(folder, name, *, success, rng, decisions=4, k=16, reproduced=True,
                  grasps=True):
    true = rng.uniform(0.0, 0.1, (decisions, k))
    meta = {"trial_id": name, "success": success, "reproduced": reproduced,
            "decisions": decisions, "true_grasps": 3,
            "failure_class": "none" if success else "missed"}
    hand = np.column_stack([rng.uniform(-0.1, 0.1, (decisions, 2)),
                            np.linspace(0.2, 0.05, decisions), rng.uniform(-90, 90, decisions)])
    extra = {"grasps": rng.uniform([-0.1, -0.1, -90], [0.1, 0.1, 90], (3, 3))} if grasps else {}
    np.savez(folder / f"{name}.npz", depth=rng.uniform(0.2, 0.3, (decisions, 64, 64)),
             hand=hand, actions=rng.uniform(-0.04, 0.04, (decisions, k, 3)), true=true,
             predicted=true + 0.01, meta=json.dumps(meta), **extra)


def test_score_ranks_each_decision_by_its_true_distances(analysis_script, tmp_path):
    """A scorer that returns the true distances ranks perfectly (Spearman 1, regret 0,
    top-1 1.0); one that returns them negated picks the worst candidate; the splits
    cover every decision; an empty folder is refused by name."""
    O = analysis_script("onpolicy_ranking")
    rng = np.random.default_rng(3)
    _fake_attempt(tmp_path, "a", success=True, rng=rng)
    _fake_attempt(tmp_path, "b", success=False, rng=rng, decisions=3)
    data = O.load_decisions(tmp_path)["data"]
    lookup = {d.tobytes(): t for d, t in zip(data["depth"], data["true"])}
    out = O.score(tmp_path, {"truth": lambda d, a: lookup[d.tobytes()],
                             "worst": lambda d, a: -lookup[d.tobytes()]})
    assert out["decisions"] == 7 and out["attempts"] == 2
    assert out["all"]["truth"]["spearman_mean"] == pytest.approx(1.0)
    assert out["all"]["truth"]["regret_mean_mm"] == 0 and out["all"]["truth"]["top1_within_1cm"] == 1
    worst = data["true"].max(axis=1) - data["true"].min(axis=1)
    assert out["all"]["worst"]["regret_mean_mm"] == pytest.approx(1e3 * worst.mean())
    assert out["by_outcome"]["held"]["truth"]["decisions"] == 4
    assert out["by_outcome"]["failed"]["worst"]["decisions"] == 3
    assert sum(b["truth"]["decisions"] for b in out["by_hand_height"]) == 7
    assert sum(b["truth"]["decisions"] for b in out["by_best_true_distance"]) == 7
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="empty: no \\*.npz"):
        O.load_decisions(tmp_path / "empty")


def test_collect_replays_a_recorded_attempt_and_keeps_its_decisions(analysis_script, tmp_path):
    """One recorded CTR clutter attempt (6 objects in the pile): the replay reproduces the
    recorded outcome and decision count, its candidates carry true distances, the scores of
    the net it ran on the kept images are the distances the controller saw, and a second
    call reads the file instead of simulating again."""
    from drake_grasp.evaluation.records import record_at

    O = analysis_script("onpolicy_ranking")
    rec = record_at(RECORD).to_dict()
    meta = O.collect_attempt(str(RECORD), str(tmp_path))
    assert meta["reproduced"] and meta["success"] == rec["success"]
    assert meta["decisions"] == rec["extra"]["decisions"] and meta["true_grasps"] > 0
    path = tmp_path / "plain-clutter-seed30__clutter__ctr__0000__attempt04.npz"
    with np.load(path) as z:
        assert z["depth"].shape == (meta["decisions"], 64, 64)
        assert np.isfinite(z["true"]).all() and (z["true"] >= 0).all()
        from drake_grasp.geometry.actions import apply_actions
        from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp

        moved = apply_actions(z["hand"][0, [0, 1, 3]][None], z["actions"][0][None])[0]
        np.testing.assert_allclose(distance_to_nearest_grasp(moved, z["grasps"]), z["true"][0])
    from drake_grasp.core.assets import models_dir
    from drake_grasp.policies.evaluator import EP3_FLOAT32_WEIGHTS, load_cnn, score_candidates

    # The net the record ran (the default of its day, the float32 file; today's default is
    # its float16 copy, whose scores differ by up to 0.6 mm).
    net = load_cnn(str(models_dir() / EP3_FLOAT32_WEIGHTS))
    out = O.score(tmp_path, {"none": lambda d, a: score_candidates(net, d, a)})
    assert out["max_abs_recorded_minus_none_m"] < 1e-6
    assert out["reproduced"] == 1
    stamp = path.stat().st_mtime_ns
    assert O.collect_attempt(str(RECORD), str(tmp_path)) == meta
    assert path.stat().st_mtime_ns == stamp
    # Another seed's folder holds the same trial id: its file is its own, and a file that
    # holds another attempt is refused by name.
    other = ROOT / "analysis" / "results" / "cnn-view-average" / "plain-clutter-seed29" / \
        "trials" / RECORD.name
    wrong = tmp_path / f"plain-clutter-seed29__{path.name.split('__', 1)[1]}"
    wrong.write_bytes(path.read_bytes())
    with pytest.raises(ValueError, match="holds .*plain-clutter-seed30 clutter/ctr/0000/attempt04"):
        O.collect_attempt(str(other), str(tmp_path))


def test_labels_label_every_kept_image_as_the_dataset_and_train_grid_reads_them(
        analysis_script, tmp_path):
    """`labels`: one shard per reproduced attempt of the selected results folders, each
    image's grid the dataset's label function at its hand pose against the attempt's
    grasps (NaN beyond the view), in the format train-grid's label store reads; attempts
    not reproduced are left out and counted; a file without grasps and an unknown
    folder name are refused by name; a re-run skips what is written."""
    O = analysis_script("onpolicy_ranking")
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.learning.dense_labels import GRID_CONFIG, LabelStore, grid_node_actions
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp

    rng = np.random.default_rng(5)
    col = tmp_path / "collect"
    col.mkdir()
    _fake_attempt(col, "seed25__clutter__ctr__0000__attempt00", success=True, rng=rng)
    _fake_attempt(col, "seed25__clutter__ctr__0000__attempt01", success=False, rng=rng,
                  decisions=2)
    _fake_attempt(col, "seed25__clutter__ctr__0001__attempt00", success=True, rng=rng,
                  reproduced=False)
    _fake_attempt(col, "seed28__clutter__ctr__0000__attempt00", success=True, rng=rng)
    out = tmp_path / "grid"
    counts = O.build_labels(col, out, exclude=("seed28",))
    assert counts == {"attempts": 3, "labelled_attempts": 2, "images": 6,
                      "left_out": {"not reproduced": 1}}
    shards = sorted(p.name for p in out.glob("shard-*.npz"))
    assert shards == ["shard-seed25__clutter__ctr__0000__attempt00.npz",
                      "shard-seed25__clutter__ctr__0000__attempt01.npz"]
    nodes = grid_node_actions(GRID_CONFIG)
    with np.load(col / "seed25__clutter__ctr__0000__attempt00.npz") as z, \
            np.load(out / shards[0]) as lab:
        assert lab["grid"].shape == (4, *GRID_CONFIG.grid_shape())
        np.testing.assert_array_equal(lab["hand_z"], z["hand"][:, 2].astype(np.float32))
        seen = []
        for i in range(4):  # the hand goes down from 20 to 5 cm
            flat = lab["grid"][i].reshape(-1).astype(float)
            labelled = np.isfinite(flat)
            seen.append(labelled.sum())
            want = distance_to_nearest_grasp(
                apply_actions(z["hand"][i, [0, 1, 3]], nodes[labelled]), z["grasps"])
            np.testing.assert_allclose(flat[labelled], want, atol=2e-4, rtol=1e-3)  # float16
        assert 0 < seen[-1] < seen[0] == len(flat)  # a low hand sees part of the grid
    # A shard write killed midway leaves its temporary file behind: not read as a part.
    (out / "shard-seed25__clutter__ctr__0001__attempt00.tmp.npz").write_bytes(b"partial")
    store = LabelStore([out])
    assert store.n_images == 6
    assert store.take(np.arange(6))["grid"].shape == (6, *GRID_CONFIG.grid_shape())
    stamp = (out / shards[0]).stat().st_mtime_ns
    assert O.build_labels(col, out, only=("seed25",))["labelled_attempts"] == 2
    assert (out / shards[0]).stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="named 'seed99'.*seed25"):
        O.build_labels(col, out, only=("seed99",))
    _fake_attempt(col, "seed30__clutter__ctr__0000__attempt00", success=True, rng=rng,
                  grasps=False)
    with pytest.raises(ValueError, match="seed30__clutter__ctr__0000__attempt00.npz: holds no 'grasps'"):
        O.build_labels(col, tmp_path / "grid2", only=("seed30",))
    assert O.score(col, {"truth": lambda d, a: a[:, 0]}, only=("seed28",))["decisions"] == 4
