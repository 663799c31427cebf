"""failure_memory (off by default; not in the paper): in a clutter run, each attempt's
policy is given the hand poses where the run's earlier attempts closed and held nothing;
CTR adds a penalty to candidates leading near them, GPD takes its best detection away
from them."""

import dataclasses

import numpy as np
import pytest

import drake_grasp.evaluation.run_folder as run_folder
import drake_grasp.evaluation.trial_plan as trial_plan
import drake_grasp.evaluation.trial_worker as trial_worker
from drake_grasp.policies.gpd_ranking import Detections
from drake_grasp.evaluation.montecarlo import evaluate
from drake_grasp.evaluation.experiments import option_patches
from drake_grasp.policies.decisions import memory_penalty
from drake_grasp.evaluation.records import load_records
from drake_grasp.config.scenario import load_scenario
from drake_grasp.policies.controller_state import Phase, hand_to_pose
from test_hand_check import ctr_first_step
from test_montecarlo import _pile, _scripted_simulate


def test_penalty_is_how_far_inside_the_radius_a_candidate_leads():
    hand = [0.5, 0.0, 90.0]  # yaw 90: the hand's x axis is world y
    failed = np.array([[0.5, 0.01, 90.0], [0.3, 0.3, 0.0]])
    actions = np.array([[0.01, 0.0, 0.0],     # onto the first failed grasp
                        [0.0, 0.0, 0.0],      # 1 cm from it
                        [0.01, 0.0, 180.0],   # onto it, turned half a turn: the same grasp
                        [0.01, 0.0, 20.0],    # onto it, 20 degrees off: 2 cm in the metric
                        [0.05, 0.0, 0.0]])    # 4 cm from it
    p = memory_penalty(hand, actions, failed, 0.02)
    assert p == pytest.approx([0.02, 0.01, 0.02, 0.0, 0.0], abs=1e-12)
    assert np.all(memory_penalty(hand, actions, failed, 0.0) == 0)
    assert np.all(memory_penalty(hand, actions, np.zeros((0, 3)), 0.02) == 0)


def test_gpd_takes_its_best_detection_away_from_the_remembered_grasps():
    poses = np.stack([hand_to_pose((0.5, 0.0, 0.05, 30.0)).GetAsMatrix4(),
                      hand_to_pose((0.5, 0.005, 0.05, 30.0)).GetAsMatrix4(),
                      hand_to_pose((0.45, 0.0, 0.05, 0.0)).GetAsMatrix4()])
    det = Detections(poses, np.array([0.9, 0.8, 0.7]), 3, 100)
    assert np.array_equal(det.best(), poses[0])
    failed = np.array([[0.5, 0.0, 30.0]])
    assert np.array_equal(det.best(failed, 0.02), poses[2])
    assert np.array_equal(det.best(failed, 0.0), poses[0])  # off
    everywhere = np.array([[0.5, 0.0, 30.0], [0.45, 0.0, 0.0]])
    assert np.array_equal(det.best(everywhere, 0.02), poses[0])  # none clear: the best
    assert Detections(np.zeros((0, 4, 4)), np.zeros(0), 0, 0).best(failed, 0.02) is None


def _ctr_choice(failed_xy_yaw):
    """CTR's first choice between staying put (scored best) and 4 cm along y_G."""
    text = "{seed: 2, failure_memory: {radius_m: 0.02, failed_xy_yaw: %s}}" % failed_xy_yaw
    s, ctrl, _, _ = ctr_first_step(load_scenario(scenario_name="clutter", scenario_text=text))
    assert s.phase == Phase.SERVO and s.iteration == 1
    # The step records the CNN's distances, not the penalized scores.
    assert np.array_equal(s.last_step.distances, [0.01, 0.02])
    return s.last_step.chosen, ctrl.start_hand


def test_ctr_leaves_a_candidate_that_leads_onto_a_remembered_grasp():
    chosen, hand = _ctr_choice("[]")
    assert np.allclose(chosen, [0.0, 0.0, 0.0])
    # A failed grasp where the hand stands: staying put scores 0.01 + 0.02, the other 0.02.
    chosen, _ = _ctr_choice(f"[{hand[0]}, {hand[1]}, {hand[3]}]")
    assert np.allclose(chosen, [0.0, 0.04, 0.0])


def test_the_protocol_passes_each_attempt_the_runs_failed_closings(tmp_path, monkeypatch):
    import drake_grasp.world.scene as scene_module

    # attempt 0 closes and fails, 1 detects nothing (never closes), 2 raises, 3 grasps,
    # 4-6 close and fail: the run ends after three failed grasps in a row.
    outcomes = ["fail", "no closing", "raise", "ok", "fail", "fail", "fail"]
    seen = []
    simulate = _scripted_simulate(
        outcomes, seen, seen=lambda scenario, scene: list(scenario.failure_memory.failed_xy_yaw),
        details=lambda k, what: {"hand_at_close_xy_yaw": [0.5, 0.01 * k, 10.0 * k],
                                 "gripper_closed": what != "no closing"})

    from drake_grasp.evaluation import hermetic

    monkeypatch.setattr(hermetic, "available", lambda: False)  # `seen` is this process's
    monkeypatch.setattr(scene_module, "make_scene", lambda *a, **k: _pile())
    monkeypatch.setattr(scene_module, "settle_scene",
                        lambda spec, *a, **k: dataclasses.replace(spec, settled=True))
    monkeypatch.setattr(trial_worker, "_simulate", simulate)
    evaluate(experiment="clutter", out=tmp_path / "c", trials=1, workers=1, seed=0,
             progress=False, conditions=["ctr"], patches=option_patches(failure_memory_m=0.02), report=False)
    first = [0.5, 0.0, 0.0]
    fifth = [0.5, 0.04, 40.0]
    assert seen == [[], first, first, first, first, first + fifth,
                    first + fifth + [0.5, 0.05, 50.0]]
    records = load_records(tmp_path / "c")
    assert records[1].extra["hand_at_close_xy_yaw"] is None  # it never closed
    assert "0.5, 0.04, 40.0, 0.5, 0.05, 50.0]" in records[6].scenario_yaml
    # Off (the default): nothing is passed.
    seen.clear()
    evaluate(experiment="clutter", out=tmp_path / "off", trials=1, workers=1, seed=0,
             progress=False, conditions=["ctr"], report=False)
    assert seen == [[]] * 7


def test_failure_memory_settings_are_checked(tmp_path):
    with pytest.raises(ValueError, match="failure_memory.radius_m"):
        load_scenario(scenario_name="clutter", scenario_text="{failure_memory: {radius_m: 0.5}}")
    with pytest.raises(ValueError, match="failure_memory.failed_xy_yaw: expected a flat list"):
        load_scenario(scenario_name="clutter",
                      scenario_text="{failure_memory: {failed_xy_yaw: [0.5, 0.0]}}")
    with pytest.raises(ValueError, match=r"--failure-memory: expected a radius in \(0, 0.1\] m"):
        evaluate(experiment="clutter", out=tmp_path / "r", trials=1, patches=option_patches(failure_memory_m=0.5),
                 progress=False)
    assert not (tmp_path / "r").exists()


def test_the_options_reach_their_conditions_and_the_runs_identity():
    """--failure-memory reaches every condition, --no-gpd-fallback the gpd conditions
    only (the fallback is the scenario's default); both change the identity of what they
    reach."""
    from drake_grasp.evaluation.experiments import EXPERIMENTS, trial_scenario
    from drake_grasp.config.sections import GpdConfig

    assert GpdConfig().fallback_best is True
    base = {c["name"]: c for c in run_folder.run_identity(EXPERIMENTS["clutter"], seed=0)["conditions"]}
    assert base["gpd"]["scenario"]["gpd"]["fallback_best"] is True
    # Asking for the default changes nothing.
    on = dataclasses.replace(EXPERIMENTS["clutter"], patches=option_patches(gpd_fallback=True))
    assert run_folder.run_identity(on, seed=0)["conditions"] == run_folder.run_identity(
        EXPERIMENTS["clutter"], seed=0)["conditions"]
    exp = dataclasses.replace(EXPERIMENTS["clutter"], patches=option_patches(failure_memory_m=0.02, gpd_fallback=False))
    ident = {c["name"]: c for c in run_folder.run_identity(exp, seed=0)["conditions"]}
    assert ident["ctr"]["config_hash"] != base["ctr"]["config_hash"]
    assert ident["gpd"]["config_hash"] != base["gpd"]["config_hash"]
    assert ident["gpd"]["scenario"]["gpd"]["fallback_best"] is False
    assert ident["ctr"]["scenario"]["gpd"]["fallback_best"] is True  # untouched: not a gpd condition
    for task in trial_plan.plan_tasks(exp, trials=1, seed=0, conditions=["ctr", "gpd"]):
        run_exp = trial_plan.task_experiment(task)
        s = trial_scenario(run_exp, trial_plan.task_condition(task, run_exp), task.index, base_seed=0)
        assert s.failure_memory.radius_m == 0.02
        assert s.gpd.fallback_best == (task.condition != "gpd")


def test_the_cli_fallback_flag_is_three_way():
    """evaluate's --gpd-fallback / --no-gpd-fallback set the option; neither keeps the
    scenario's (None, the fallback on)."""
    from drake_grasp.cli.main import build_parser

    parse = lambda *a: build_parser().parse_args(["evaluate", "--experiment", "clutter", "--out", "r", *a])
    assert parse().gpd_fallback is None
    assert parse("--gpd-fallback").gpd_fallback is True
    assert parse("--no-gpd-fallback").gpd_fallback is False
