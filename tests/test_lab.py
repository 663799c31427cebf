"""The grasp physics lab: a centred grasp across a lying can holds; one beside it
misses; a too-weak grip lets it slip."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def can_scene(library):
    from drake_grasp.evaluation.lab import isolated_scene

    return isolated_scene("can_000", library, lying=True)


def test_centred_grasp_across_lying_can_holds(can_scene, library, across_can):
    from drake_grasp.evaluation.lab import check_grasp

    result = check_grasp(None, across_can(can_scene, library), scene=can_scene, library=library)
    assert result.held, result.details
    assert result.failure == ""
    assert result.details["shake_pads"] == ["left_finger", "right_finger"]
    assert result.details["shake_rise_m"] >= 0.05


def test_grasp_beside_the_can_is_missed(can_scene, library, across_can):
    from drake_grasp.evaluation.lab import check_grasp

    X = across_can(can_scene, library, offset_m=0.06)  # 6 cm beyond the can's side
    result = check_grasp(None, X, scene=can_scene, library=library)
    assert not result.held
    assert result.failure == "missed", result.details


def test_weak_grip_does_not_hold(can_scene, library, across_can):
    from drake_grasp.evaluation.lab import FAILURES, check_grasp

    result = check_grasp(None, across_can(can_scene, library), scene=can_scene,
                         library=library, grip_force_n=0.2)
    assert not result.held
    assert result.failure in FAILURES and result.failure != "simulation-error", result.details


def test_check_grasps_takes_grasp_set_poses(can_scene, library, across_can):
    from drake_grasp.evaluation.lab import check_grasps

    X = across_can(can_scene, library).GetAsMatrix4()
    seen = []
    results = check_grasps(None, np.stack([X]), scene=can_scene, library=library,
                           object_indices=[0], progress=seen.append)
    assert len(results) == 1 and results[0].held and seen == results


def test_grasp_check_cli_writes_summary(tmp_path, capsys):
    import json

    from drake_grasp.cli.main import main

    out = tmp_path / "checks"
    assert main(["grasp-check", "--object", "can_000", "--grasps", "2", "--seed", "0",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["checked"] == 2
    assert summary["objects"]["can_000"]["checked"] == 2
    assert 0 <= summary["held"] <= 2
    assert summary["hold_rate"] == summary["held"] / 2
    assert sum(summary["failures"].values()) == 2 - summary["held"]
    printed = json.loads(capsys.readouterr().out)
    assert printed["checked"] == 2


def test_grasp_check_cli_unknown_object_is_a_clean_error(tmp_path, capsys):
    from drake_grasp.cli.main import main

    assert main(["grasp-check", "--object", "no_such_thing", "--grasps", "1",
                 "--out", str(tmp_path)]) == 2
    assert "no_such_thing" in capsys.readouterr().err


@pytest.mark.parametrize("force_mode", ["constant", "limit"])
def test_pads_press_with_the_commanded_grip_force(can_scene, library, across_can, force_mode):
    """The 2F-85's force control: once the fingers stop on the can, each pad presses with
    the commanded grip force ("constant"); "limit" only caps it, and the PD's spring
    then presses with kp (q - q_goal) / 2 per pad, a width-dependent force below it."""
    from drake_grasp.evaluation.lab import check_grasp
    from drake_grasp.config.scenario import Scenario

    scenario = Scenario()
    scenario.gripper.force_mode = force_mode
    result = check_grasp(None, across_can(can_scene, library), scene=can_scene,
                         scenario=scenario, library=library, grip_force_n=60.0)
    assert result.held, result.details
    squeeze = result.details["hold_squeeze_n"]
    assert sorted(squeeze) == ["left_finger", "right_finger"]
    if force_mode == "constant":
        assert squeeze["left_finger"] == pytest.approx(60.0, rel=0.05)
        assert squeeze["right_finger"] == pytest.approx(60.0, rel=0.05)
    else:
        # The commanded width is 0, so q_goal = 0 and q = width / 2.
        kp = 2000.0  # models/robotiq_2f85: left_finger_actuator's controller gain
        expected = 0.5 * kp * 0.5 * result.details["hold_width_m"]
        assert expected < 0.7 * 60.0
        assert squeeze["left_finger"] == pytest.approx(expected, rel=0.1)
        assert squeeze["right_finger"] == pytest.approx(expected, rel=0.1)


def test_closing_ends_once_the_grasp_has_settled(can_scene, library, across_can):
    """The closing phase ends when the pads have stopped on the can and their squeeze has
    levelled off (well before the fixed closing time, 1.2 s after the descent); the
    lift then follows the same schedule, and the pads still press with the grip force."""
    from drake_grasp.evaluation.lab import LabConfig, check_grasp

    X = across_can(can_scene, library)
    fixed = check_grasp(None, X, scene=can_scene, library=library,
                        lab=LabConfig(close_settle_s=None))
    early = check_grasp(None, X, scene=can_scene, library=library)
    assert fixed.held and early.held, (fixed.details, early.details)
    lab = LabConfig()
    assert fixed.details["close_end_s"] == pytest.approx(lab.descend_s + lab.close_s)
    # The can is ~57 mm wide: the fingers travel ~14 mm each at 50 mm/s, then the
    # squeeze rises at ~1000 N/s to 60 N.
    assert lab.descend_s + 0.3 < early.details["close_end_s"] < lab.descend_s + 0.8
    saved = fixed.details["close_end_s"] - early.details["close_end_s"]
    assert early.details["sim_time_s"] == pytest.approx(fixed.details["sim_time_s"] - saved)
    for phase in ("close", "shake"):
        squeeze = early.details[f"{phase}_squeeze_n"]
        assert squeeze["left_finger"] == pytest.approx(60.0, rel=0.05), phase
        assert squeeze["right_finger"] == pytest.approx(60.0, rel=0.05), phase
    assert early.details["close_width_m"] == pytest.approx(fixed.details["close_width_m"],
                                                           abs=5e-4)
