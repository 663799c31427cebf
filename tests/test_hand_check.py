"""controller.hand_check: while servoing at the stop height, CTR follows the best-scored
candidate whose open hand comes down clear of the surfaces the depth image shows under
it (`policies.hand_overlap_m`)."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from drake_grasp.geometry.hand_model import FINGERTIP_Z_M
from drake_grasp.policies.decisions import hand_overlap_m, image_points_W
from drake_grasp.config.scenario import load_scenario
from drake_grasp.world.station import gripper_frame_offsets, topdown_pose
from drake_grasp.policies.controllers import make_controller
from drake_grasp.policies.controller_state import Phase, hand_to_pose

CAM_Z = 0.3


def _points(xyz):
    p = np.asarray(xyz, float).T
    return np.vstack([p, np.ones(p.shape[1])])


def test_hand_overlap_uses_the_ground_truths_hand_parts_outside_the_closing_strip():
    X_WG = hand_to_pose((0.0, 0.0, 0.03, 0.0)).GetAsMatrix4()  # grasp centre 3 cm up
    strip = [[0.0, 0.0, 0.2], [0.04, 0.01, 0.2]]  # the object between the pads: ignored
    outside = [[0.07, 0.0, 0.2], [0.0, 0.045, 0.2]]  # beyond the palm and the housing
    assert hand_overlap_m(_points(strip + outside), X_WG) == -np.inf
    finger = [[-0.05, 0.005, 0.045]]  # under the left finger: its tip is at 0.011
    assert hand_overlap_m(_points(strip + finger), X_WG) == pytest.approx(0.045 - 0.011)
    palm = [[0.0, 0.013, 0.06], [0.062, 0.0, 0.06]]  # under the palm's front, at 0.055
    assert hand_overlap_m(_points(strip + palm), X_WG) == pytest.approx(0.005)
    housing = [[0.0, 0.03, 0.07]]  # under the housing's front, at 0.061
    assert hand_overlap_m(_points(outside + housing), X_WG) == pytest.approx(0.009)
    # The margin widens the outlines: a point 1 mm beside the palm (beyond the housing)
    # counts with a 3 mm margin.
    beside = [[-0.05, 0.016, 0.02]]
    assert hand_overlap_m(_points(beside), X_WG) == -np.inf
    assert hand_overlap_m(_points(beside), X_WG, margin_m=0.003) == pytest.approx(0.02 - 0.055)
    # The outlines follow the grasp's yaw: turned 90 degrees, the fingers lie along y.
    X_WG = hand_to_pose((0.0, 0.0, 0.03, 90.0)).GetAsMatrix4()
    assert hand_overlap_m(_points(finger), X_WG) == -np.inf
    assert hand_overlap_m(_points([[0.005, -0.05, 0.045]]), X_WG) == pytest.approx(0.034)


def _depth_with_block(X_WC, f, lo, hi, top):
    """Depth image (64x64) of a table at z = 0 and a block of height `top` over the
    world rectangle lo..hi (x, y), seen by a downward camera at X_WC."""
    v, u = np.mgrid[0:64, 0:64]
    rays = np.stack([(u - 31.5) / f, (v - 31.5) / f, np.ones_like(u, float)], axis=-1)
    R, p = X_WC[:3, :3], X_WC[:3, 3]
    d_top = p[2] - top  # the camera looks straight down: depth = height difference
    w = (rays * d_top) @ R.T + p
    inside = (w[..., 0] >= lo[0]) & (w[..., 0] <= hi[0]) & (w[..., 1] >= lo[1]) & (w[..., 1] <= hi[1])
    return np.where(inside, d_top, p[2]).astype(np.float32)


def test_image_points_put_the_block_where_it_was_drawn():
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], CAM_Z + X_GC.translation()[2], 0.0)
    X_WC = (start @ X_GC).GetAsMatrix4()
    f = 0.5 * 64 / np.tan(np.deg2rad(55.0) / 2.0)
    depth = _depth_with_block(X_WC, f, (0.45, -0.01), (0.47, 0.01), 0.05)
    P = image_points_W(depth, f, X_WC)
    top = P[:, P[2] > 0.025]
    assert top.shape[1] > 10
    assert np.all((top[0] > 0.449) & (top[0] < 0.471) & (np.abs(top[1]) < 0.011))
    assert np.allclose(P[2, P[2] <= 0.025], 0.0, atol=1e-6)


def ctr_first_step(scenario, depth_fn=None):
    """CTR's first step from a top-down start over (0.5, 0), the camera CAM_Z above the
    table, between two candidates: staying put (predicted 0.01) and 4 cm along y_G
    (0.02). `depth_fn(X_WC, f)` draws the image (default: the bare table). Returns the
    controller's state after 1.5 periods, the controller, the image and the start pose."""
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], CAM_Z + X_GC.translation()[2], 0.0)
    ctrl = make_controller("ctr", scenario=scenario, X_WG_start=start, X_GC=X_GC,
                           score_fn=None)
    X_WC = (start @ X_GC).GetAsMatrix4()
    f = 0.5 * 64 / np.tan(np.deg2rad(scenario.camera.fov_y_deg) / 2.0)
    depth = (depth_fn(X_WC, f) if depth_fn is not None
             else np.full((64, 64), CAM_Z, np.float32))
    img = ImageDepth32F(64, 64)
    img.mutable_data[:, :, 0] = depth
    sim = Simulator(ctrl)
    ctx = sim.get_mutable_context()
    ctrl.GetInputPort("depth_image").FixValue(ctx, img)
    ctrl.GetInputPort("label_image").FixValue(ctx, ImageLabel16I(64, 64))
    ctrl.GetInputPort("candidate_actions").FixValue(ctx, np.array([[0.0, 0.0, 0.0],
                                                                   [0.0, 0.04, 0.0]]))
    ctrl.GetInputPort("predicted_distances").FixValue(ctx, np.array([0.01, 0.02]))
    ctrl.GetInputPort("gripper_state").FixValue(ctx, np.zeros(4))
    sim.AdvanceTo(1.5 * scenario.controller.period_s)
    return ctrl.get_controller_state(ctx), ctrl, depth, start


def _run(hand_check: bool, clear_candidate: bool = True):
    """CTR at its first iteration with the stop rule firing at once (stop_distance_m
    beyond the table), staying put with a 5 cm block under the left finger's footprint,
    the other candidate clear of it unless `clear_candidate` is False (then the block is
    long enough to lie under both)."""
    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 2, controller: {stop_distance_m: 0.4, step_ratio: 0.5, "
        f"hand_check: {str(hand_check).lower()}}}}}"))
    y_lo = -0.05 if not clear_candidate else -0.01
    # At yaw 0, x_G is world x (the left finger lies on -x_G) and y_G is world -y.
    s, ctrl, depth, start = ctr_first_step(scenario, lambda X_WC, f: _depth_with_block(
        X_WC, f, (0.5 - 0.056, y_lo), (0.5 - 0.046, 0.01), 0.05))
    assert s.phase == Phase.SERVO and s.converging == 2
    return s, ctrl, depth, start


def test_hand_check_follows_the_best_candidate_whose_fingers_clear():
    s, _, _, start = _run(hand_check=False)
    assert np.allclose(s.last_step.chosen, [0.0, 0.0, 0.0])
    s, ctrl, depth, _ = _run(hand_check=True)
    assert np.allclose(s.last_step.chosen, [0.0, 0.04, 0.0])
    # Moved half way (step_ratio 0.5) along y_G.
    y_G = start.rotation().matrix()[:, 1]
    moved = np.array(s.hand[:2]) - start.translation()[:2]
    assert moved @ y_G[:2] == pytest.approx(0.02, abs=1e-9)
    # The check itself: staying put puts the left fingertip under the block's top.
    hand = ctrl.start_hand
    P = ctrl._image_points(depth, hand)
    grasp = ctrl._grasp_from_points(P, hand)
    assert grasp[2] - FINGERTIP_Z_M < 0.05 - 0.005
    assert not ctrl._hand_clear(P, grasp)


def test_hand_check_keeps_the_best_candidate_when_none_clears():
    s, _, _, _ = _run(hand_check=True, clear_candidate=False)
    assert np.allclose(s.last_step.chosen, [0.0, 0.0, 0.0])


@pytest.mark.parametrize("text", ["{controller: {hand_clearance_m: 0.2}}",
                                  "{controller: {hand_margin_m: -0.001}}"])
def test_hand_check_settings_are_range_checked(text):
    with pytest.raises(ValueError, match="hand_"):
        load_scenario(scenario_name="isolation", scenario_text=text)
