"""The shipped CNN's files describe the same training run: the weights' metadata, the
model card's `metrics.json` and `train_config.json` (so a weights file shipped without its
metrics, or metrics copied from another run, is caught)."""

import json
from pathlib import Path

import pytest

from drake_grasp.core.assets import models_dir
from drake_grasp.cnn.weights_io import load_weights

CNN = models_dir() / "cnn"


@pytest.fixture(scope="module")
def shipped():
    _, meta = load_weights(CNN / "weights.safetensors")
    metrics = json.loads((CNN / "metrics.json").read_text())
    config = json.loads((CNN / "train_config.json").read_text())
    return meta, metrics, config


def test_weights_metrics_and_config_are_one_run(shipped):
    meta, metrics, config = shipped
    assert meta["train_manifest_sha256"] == config["train_manifest_sha256"]
    assert meta["test_manifest_sha256"] == config["test_manifest_sha256"]
    assert meta["num_train_labels"] == metrics["num_train_labels"]
    assert meta["config"] == config["network"]


def test_weights_are_the_last_epoch_in_the_metrics(shipped):
    meta, metrics, config = shipped
    epochs = metrics["epochs"]
    # A finished run's weights carry `epochs`, a checkpoint's `checkpoint_epoch`.
    epoch = meta.get("checkpoint_epoch", meta.get("epochs"))
    assert epoch == len(epochs) == epochs[-1]["epoch"]
    assert meta.get("checkpoint_next_batch", 0) == 0, "weights from the middle of an epoch"
    assert meta["test_l1_m"] == pytest.approx(epochs[-1]["test_l1_m"], abs=0)
    assert metrics["test_l1_m"] == pytest.approx(epochs[-1]["test_l1_m"], abs=0)
    stopped = config["train"].get("stopped_after_epoch", config["train"]["epochs"])
    assert stopped == epoch


GRID = models_dir() / "cnn-grid"
GRID_BN = models_dir() / "cnn-grid-bn"
GRID_BN12 = models_dir() / "cnn-grid-bn12"
GRID_BN12_EP5 = models_dir() / "cnn-grid-bn12-ep5"
GRID_BN12500 = models_dir() / "cnn-grid-bn12500"
GRID_BN12500_EP3 = models_dir() / "cnn-grid-bn12500-ep3"
GRID_BN12500_EP3_FP16 = models_dir() / "cnn-grid-bn12500-ep3-fp16"


@pytest.mark.parametrize("folder", [GRID, GRID_BN, GRID_BN12, GRID_BN12_EP5, GRID_BN12500,
                                    GRID_BN12500_EP3],
                         ids=["cnn-grid", "cnn-grid-bn", "cnn-grid-bn12", "cnn-grid-bn12-ep5",
                              "cnn-grid-bn12500", "cnn-grid-bn12500-ep3"])
def test_the_grid_weights_are_the_last_epoch_of_their_run(folder):
    model, meta = load_weights(folder / "weights.safetensors")
    metrics = json.loads((folder / "metrics.json").read_text())
    assert model.config.action_fusion == "grid"
    assert meta["identity"] == metrics["identity"]
    assert meta["identity"]["config"] == meta["config"]
    assert meta["epoch"] == len(metrics["epochs"]) == metrics["epochs"][-1]["epoch"]


def test_the_episodes_default_cnn_is_the_batchnorm_grid_head_and_the_others_stay_shipped():
    from drake_grasp.evaluation.run_folder import weights_path
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.policies.evaluator import (BN12_WEIGHTS, BN12500_WEIGHTS, BN_WEIGHTS,
                                               DEFAULT_WEIGHTS, EP3_FLOAT32_WEIGHTS,
                                               EP5_WEIGHTS, GRID_WEIGHTS, PAPER_WEIGHTS,
                                               load_cnn)

    assert models_dir() / DEFAULT_WEIGHTS == GRID_BN12500_EP3_FP16 / "weights.safetensors"
    assert models_dir() / EP3_FLOAT32_WEIGHTS == GRID_BN12500_EP3 / "weights.safetensors"
    assert models_dir() / BN12500_WEIGHTS == GRID_BN12500 / "weights.safetensors"
    assert models_dir() / EP5_WEIGHTS == GRID_BN12_EP5 / "weights.safetensors"
    assert models_dir() / BN12_WEIGHTS == GRID_BN12 / "weights.safetensors"
    assert models_dir() / BN_WEIGHTS == GRID_BN / "weights.safetensors"
    assert models_dir() / GRID_WEIGHTS == GRID / "weights.safetensors"
    assert load_cnn("").config.action_fusion == "grid"
    assert load_cnn(str(models_dir() / BN12500_WEIGHTS)).config.action_fusion == "grid"
    assert load_cnn(str(models_dir() / EP5_WEIGHTS)).config.action_fusion == "grid"
    assert load_cnn(str(models_dir() / BN12_WEIGHTS)).config.action_fusion == "grid"
    assert load_cnn(str(models_dir() / BN_WEIGHTS)).config.action_fusion == "grid"
    assert load_cnn(str(models_dir() / GRID_WEIGHTS)).config.action_fusion == "grid"
    assert load_cnn(str(models_dir() / PAPER_WEIGHTS)).config.action_fusion == "tiled"
    ctr = load_scenario(scenario_text="{policy: ctr}")
    assert weights_path(ctr) == str(GRID_BN12500_EP3_FP16 / "weights.safetensors")


def test_the_default_is_the_float32_net_rounded_to_float16():
    """The shipped default is `cnn-grid-bn12500-ep3` stored in float16: the same training
    metadata, every weight within float16's rounding of its source."""
    import torch

    half, half_meta = load_weights(GRID_BN12500_EP3_FP16 / "weights.safetensors")
    full, full_meta = load_weights(GRID_BN12500_EP3 / "weights.safetensors")
    assert half_meta["identity"] == full_meta["identity"]
    assert half_meta["epoch"] == full_meta["epoch"]
    for (name, a), (_, b) in zip(half.state_dict().items(), full.state_dict().items()):
        assert a.dtype == torch.float32, name
        assert torch.allclose(a, b, rtol=1e-3, atol=1e-4), name

def test_a_record_of_an_earlier_default_replays_with_the_weights_it_ran(tmp_path):
    """A trial recorded with `controller.weights: ""` ran the default of its day; its
    run.json holds that file's sha256. `recorded_weights` names the shipped file with that
    sha256 when it is not today's default, keeps today's default, keeps explicit weights,
    and refuses a sha256 no shipped file has, naming it."""
    import dataclasses

    from drake_grasp.evaluation.replay import recorded_weights
    from drake_grasp.core.provenance import file_sha256
    from drake_grasp.config.scenario import load_scenario

    ctr = load_scenario(scenario_text="{policy: ctr}")
    assert ctr.controller.weights == ""

    def run_info(path):
        return {"conditions": [{"name": "gpd", "weights_sha256": None},
                               {"name": "ctr", "weights_sha256": file_sha256(path)}]}

    for earlier in (GRID / "weights.safetensors", GRID_BN / "weights.safetensors",
                    GRID_BN12 / "weights.safetensors", GRID_BN12_EP5 / "weights.safetensors",
                    GRID_BN12500 / "weights.safetensors",
                    GRID_BN12500_EP3 / "weights.safetensors"):
        got = recorded_weights(ctr, run_info(earlier), "ctr")
        assert got.controller.weights == str(earlier)
    grid = GRID / "weights.safetensors"
    assert recorded_weights(ctr, run_info(GRID_BN12500_EP3_FP16 / "weights.safetensors"),
                            "ctr") is ctr
    explicit = dataclasses.replace(ctr, controller=dataclasses.replace(
        ctr.controller, weights=str(GRID_BN12 / "weights.safetensors")))
    assert recorded_weights(explicit, run_info(grid), "ctr") is explicit
    assert recorded_weights(ctr, {"conditions": []}, "ctr") is ctr  # no sha256 recorded
    other = tmp_path / "other.safetensors"
    other.write_bytes(b"not shipped")
    with pytest.raises(ValueError, match=f"run.json: condition 'ctr' .*{file_sha256(other)}"):
        recorded_weights(ctr, run_info(other), "ctr")


def test_a_record_whose_named_weights_are_not_here_replays_with_the_shipped_file(tmp_path):
    """A record that named its weights with a path of another machine (`--weights
    /elsewhere/models/...`) replays with the shipped file of the recorded sha256; members
    of an ensemble that exist are kept; a missing file no shipped file matches is refused
    with its path and sha256 named."""
    import dataclasses

    from drake_grasp.evaluation.replay import recorded_weights
    from drake_grasp.core.provenance import file_sha256
    from drake_grasp.config.scenario import load_scenario

    ctr = load_scenario(scenario_text="{policy: ctr}")
    fcn = models_dir() / "fcn-heightmap" / "weights.safetensors"
    grid = GRID / "weights.safetensors"

    def named(weights, *files):
        scenario = dataclasses.replace(ctr, controller=dataclasses.replace(
            ctr.controller, weights=weights))
        info = {"conditions": [{"name": "ctr",
                                "weights_sha256": ",".join(file_sha256(f) for f in files)}]}
        return recorded_weights(scenario, info, "ctr")

    gone = str(tmp_path / "elsewhere" / "weights.safetensors")
    assert named(gone, fcn).controller.weights == str(fcn)
    assert named(f"{grid},{gone}", grid, fcn).controller.weights == f"{grid},{fcn}"
    here = named(str(grid), grid)
    assert here.controller.weights == str(grid)
    other = tmp_path / "other.safetensors"
    other.write_bytes(b"not shipped")
    with pytest.raises(ValueError, match=f"ran {gone} .*{file_sha256(other)}.*does not exist"):
        named(gone, other)


def test_a_recorded_pile_names_the_weights_its_attempt_ran(tmp_path):
    """`recorded_pile` reads the run.json beside the record's `trials/` folder: an attempt
    recorded with the default of its day (`weights: ""`) replays with that day's file,
    whatever today's default is."""
    from drake_grasp.evaluation.records import record_at, write_record
    from drake_grasp.evaluation.replay import recorded_pile
    from drake_grasp.core.provenance import file_sha256

    src = (Path(__file__).resolve().parents[1] / "analysis" / "results" / "paper-bn12"
           / "clutter" / "trials" / "clutter__ctr__0000__attempt01.json")
    record = write_record(tmp_path, record_at(src))  # the file, or its row once packed
    _, scenario, _ = recorded_pile(record)  # no run.json: the scenario as recorded
    assert scenario.controller.weights == ""
    info = json.loads((src.parents[1] / "run.json").read_text())
    for c in info["conditions"]:
        if c["name"] == "ctr":
            c["weights_sha256"] = file_sha256(GRID / "weights.safetensors")
    (tmp_path / "run.json").write_text(json.dumps(info))
    _, scenario, scene = recorded_pile(record)
    assert scenario.controller.weights == str(GRID / "weights.safetensors")
    assert scene.objects
