"""gpd-track (`policies.gpd_track`): GPD's grasp followed in the wrist camera. In physics,
its estimate of a shifted sheet's motion is the sheet's own, and the grasp holds."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw

from drake_grasp.config.scenario import load_scenario
from drake_grasp.policies.gpd_track import pose_gap_m, step_toward


def test_step_toward_caps_the_move_and_arrives_within_the_caps():
    a = RigidTransform([0.5, 0.0, 0.6])
    b = RigidTransform(RollPitchYaw(0.0, 0.0, np.deg2rad(20.0)), [0.5, 0.1, 0.5])
    step = step_toward(a, b, step_m=0.025, step_yaw_deg=8.0)
    assert np.linalg.norm(step.translation() - a.translation()) <= 0.025 + 1e-9
    assert pose_gap_m(a, step) < pose_gap_m(a, b)
    near = RigidTransform(RollPitchYaw(0.0, 0.0, np.deg2rad(2.0)), [0.5, 0.005, 0.6])
    assert step_toward(a, near, step_m=0.025, step_yaw_deg=8.0) is near
    # 1 mm per degree
    assert pose_gap_m(a, near) == pytest.approx(0.005 + 0.002)


def test_the_tracked_motion_is_the_sheets_and_the_grasp_holds(library):
    from drake_grasp.evaluation.episode import simulate_episode

    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 5, policy: gpd-track, disturbance: {kind: shift},"
        " scene: {object_ids: [tetra_pak_000], pose: lying}}"))
    run = simulate_episode(scenario, library=library)
    r = run.result
    shift = r.disturbance
    assert shift["kind"] == "shift" and shift["time_s"] is not None, shift
    # Where the sheet took the detected grasp's anchor (it turns about its centre).
    X_det = np.asarray(r.details["gpd_detection"]["X_WG"]).reshape(4, 4)
    a, c = X_det[:2, 3], np.asarray(run.scene.center_xy_m)
    yaw = np.deg2rad(shift["shift_yaw_deg"])
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    expected = R @ (a - c) + c + np.asarray(shift["shift_xy_m"]) - a
    dx, dy, dyaw = r.details["tracked_motion"]
    assert np.hypot(dx - expected[0], dy - expected[1]) < 0.01, (r.details["tracked_motion"], expected)
    assert abs(dyaw - shift["shift_yaw_deg"]) < 5.0
    assert r.success, r.failure_reason
