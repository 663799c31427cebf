"""Grasp execution from the depth image alone: the grasp height keeps the fingertips
above the support seen under the hand, the 14 cm stop rule looks under the grasp axis
(the wrist camera sits 5 cm beside it), and cnn-only reads its grasp height from the
start image where its grasp will be."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from drake_grasp.geometry.hand_model import FINGERTIP_Z_M
from drake_grasp.policies.decisions import grasp_axis_pixel, grasp_height
from drake_grasp.config.scenario import load_scenario
from drake_grasp.world.station import gripper_frame_offsets, topdown_pose
from drake_grasp.policies.controllers import make_controller
from drake_grasp.policies.controller_state import Phase

START_CAMERA_HEIGHT_M = 0.3


def _depth_image(value):
    img = ImageDepth32F(64, 64)
    img.mutable_data[:, :, 0] = value
    return img


def _controller(scenario, depth, policy="ctr", score_fn=None):
    """The controller alone, its inputs fixed: a zero candidate action scored 0."""
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], START_CAMERA_HEIGHT_M + X_GC.translation()[2], 0.0)
    ctrl = make_controller(policy, scenario=scenario, X_WG_start=start, X_GC=X_GC,
                           score_fn=score_fn)
    sim = Simulator(ctrl)
    ctx = sim.get_mutable_context()
    ctrl.GetInputPort("depth_image").FixValue(ctx, _depth_image(depth))
    ctrl.GetInputPort("label_image").FixValue(ctx, ImageLabel16I(64, 64))
    ctrl.GetInputPort("candidate_actions").FixValue(ctx, np.zeros((1, 3)))
    ctrl.GetInputPort("predicted_distances").FixValue(ctx, np.zeros(1))
    ctrl.GetInputPort("gripper_state").FixValue(ctx, np.zeros(4))
    return sim, ctrl, ctx


def test_grasp_height_keeps_the_fingertips_above_the_sheet_seen_in_the_image():
    # One CTR step takes the camera from 0.3 m to 0.15 m, over a bare sheet whose top
    # (2 mm) the image shows at 0.148 m: the grasp must keep the fingertips above it.
    scenario = load_scenario(scenario_name="isolation",
                             scenario_text="{seed: 2, controller: {iterations: 1}}")
    sim, ctrl, ctx = _controller(scenario, 0.148)
    sim.AdvanceTo(2.5 * scenario.controller.period_s)
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.DESCEND and s.stop_reason == "hand at its lowest height"
    fingertips = s.grasp[2] - FINGERTIP_Z_M
    assert fingertips >= 0.002 + scenario.controller.support_margin_m - 1e-6


def test_grasp_height_rule():
    kw = dict(depth_below_top_m=0.025, fingertip_below_centre_m=0.019, support_margin_m=0.004)
    # A 12 cm can on the 2 mm sheet: the pads 2.5 cm below its top.
    assert grasp_height([0.12], [0.002, 0.12], **kw) == pytest.approx(0.095)
    # A 1 cm flat object: the fingertips 4 mm above the sheet.
    assert grasp_height([0.012], [0.002, 0.012], **kw) == pytest.approx(0.025)
    # Nothing readable: the table top is the support.
    assert grasp_height([], [], **kw) == pytest.approx(0.023)


def test_grasp_height_goes_down_to_the_widest_section_seen_between_the_pads():
    """A lying 4.5 cm-radius cylinder seen from above (axis along y_G, 2 mm sheet): its
    widest section along the closing direction is at the axis, 47 mm up, below the
    default 2.5 cm under its 92 mm top; the pads go there. A box's walls are not seen
    from above, so its widest section reads as its top and the default depth stays."""
    from drake_grasp.policies.decisions import widest_section_height

    kw = dict(depth_below_top_m=0.025, fingertip_below_centre_m=0.019, support_margin_m=0.004)
    R, sheet = 0.045, 0.002
    x = np.linspace(-R, R, 61)  # pixels ~1.5 mm apart across the closing direction
    z = sheet + R + np.sqrt(R * R - x * x)
    widest = widest_section_height(z, x)
    assert sheet + R <= widest <= sheet + R + 0.006
    z_grasp = grasp_height(z, np.concatenate([z, [sheet]]), widest_z=widest, **kw)
    assert z_grasp == pytest.approx(widest)
    assert z_grasp < z.max() - 0.025 - 0.01  # 1 cm deeper than the top rule alone
    # A 6 cm wide, 8 cm tall box: only its top is seen.
    xb = np.linspace(-0.03, 0.03, 41)
    zb = np.full_like(xb, sheet + 0.08)
    assert widest_section_height(zb, xb) == pytest.approx(sheet + 0.08)
    assert grasp_height(zb, np.concatenate([zb, [sheet]]), widest_z=widest_section_height(zb, xb),
                        **kw) == pytest.approx(sheet + 0.08 - 0.025)


def test_widest_section_is_not_read_off_a_standing_objects_side_wall():
    """A flashlight standing 18.6 cm tall on the 2 mm sheet, 3.6 cm wide: seen from the
    wrist camera (5 cm beside the grasp axis) its top disk and the side wall facing the
    camera. The wall's lower points are not a widest section (the palm would come down
    on the top): no widest section, the pads go 2.5 cm under the top. A lying cylinder
    of the same width keeps its widest section."""
    from drake_grasp.policies.decisions import widest_section_height

    kw = dict(depth_below_top_m=0.025, fingertip_below_centre_m=0.019, support_margin_m=0.004)
    R, sheet, top = 0.018, 0.002, 0.186
    x_top = np.linspace(-R, R, 25)
    phi = np.linspace(np.deg2rad(200), np.deg2rad(340), 15)  # the wall facing the camera
    x_wall, z_wall = np.meshgrid(R * np.cos(phi), np.linspace(sheet + 0.01, top, 20))
    x = np.concatenate([x_top, x_wall.ravel()])
    z = np.concatenate([np.full_like(x_top, top), z_wall.ravel()])
    assert widest_section_height(z, x) is None
    assert grasp_height(z, np.concatenate([z, [sheet]]), widest_z=None,
                        **kw) == pytest.approx(top - 0.025)
    # Lying, the same 3.6 cm across: the widest section is at its axis.
    z_lying = sheet + R + np.sqrt(R * R - x_top * x_top)
    assert sheet + R <= widest_section_height(z_lying, x_top) <= sheet + R + 0.006


@pytest.mark.parametrize("where,stops", [("axis", True), ("centre", False)])
def test_stop_rule_looks_under_the_grasp_axis(where, stops):
    # An object 13.9 cm from the sensor: under the grasp axis it lies ~22 px off the
    # image centre (the camera is 5 cm beside the axis); at the image centre it is
    # 5 cm beside the grasp and must not stop the approach.
    scenario = load_scenario(scenario_name="isolation", scenario_text="{seed: 2, controller: {converge_iterations: 0}}")
    _, _, X_GC = gripper_frame_offsets()
    depth = np.full((64, 64), 0.3)
    if where == "axis":
        u, v = grasp_axis_pixel(depth.shape, 61.47, X_GC.translation()[:2], 0.139)
        assert abs(v - 31.5) > 20
        r, c = int(round(v)), int(round(u))
        depth[r - 2:r + 3, c - 2:c + 3] = 0.139
    else:
        depth[29:35, 29:35] = 0.139
    sim, ctrl, ctx = _controller(scenario, depth)
    sim.AdvanceTo(1.5 * scenario.controller.period_s)
    s = ctrl.get_controller_state(ctx)
    assert (s.phase == Phase.DESCEND) == stops
    if stops:
        assert "within 0.14 m" in s.stop_reason and s.iteration == 0


def test_cnn_only_reads_its_grasp_height_where_its_grasp_will_be():
    # Start: camera 0.3 m over a bare table, a 4 cm box 10 cm tall 8 cm along x_G from
    # the start grasp axis; the stand-in CNN sends the hand there.
    scenario = load_scenario(scenario_name="isolation", scenario_text="{seed: 2}")
    _, _, X_GC = gripper_frame_offsets()
    cam_xy = X_GC.translation()[:2]
    f = 0.5 * 64 / np.tan(np.deg2rad(scenario.camera.fov_y_deg) / 2.0)
    depth = np.full((64, 64), START_CAMERA_HEIGHT_M)
    d_top = START_CAMERA_HEIGHT_M - 0.10
    v, u = np.mgrid[0:64, 0:64]
    x = (u - 31.5) * d_top / f + cam_xy[0]  # in the start grasp frame, at the box top
    y = (v - 31.5) * d_top / f + cam_xy[1]
    depth[(np.abs(x - 0.08) <= 0.02) & (np.abs(y) <= 0.02)] = d_top

    def score(_depth, actions):
        return np.linalg.norm(actions[:, :2] - [0.08, 0.0], axis=1)

    sim, ctrl, ctx = _controller(scenario, depth, policy="cnn-only", score_fn=score)
    sim.AdvanceTo(0.5 * scenario.controller.period_s)
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.APPROACH
    assert s.grasp[0] == pytest.approx(0.58, abs=0.01)
    assert s.grasp[2] == pytest.approx(0.10 - scenario.scripted.grasp_depth_below_top_m, abs=1e-3)


@pytest.mark.parametrize("text", ["{controller: {stop_window_half_m: 0}}",
                                  "{controller: {support_margin_m: -0.001}}"])
def test_execution_settings_are_range_checked(text):
    with pytest.raises(ValueError):
        load_scenario(scenario_name="isolation", scenario_text=text)


@pytest.mark.parametrize("at_widest", [False, True])
def test_controller_grasp_height_follows_grasp_at_widest_section(at_widest):
    """The controller reads its grasp height from the image's world points: over a lying
    4 cm-radius cylinder (axis along y_G) on the 2 mm sheet the pads go 2.5 cm under
    its top, or down to its widest section with `controller.grasp_at_widest_section`."""
    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        f"{{seed: 2, controller: {{grasp_at_widest_section: {str(at_widest).lower()}}}}}"))
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], START_CAMERA_HEIGHT_M + X_GC.translation()[2], 0.0)
    ctrl = make_controller("ctr", scenario=scenario, X_WG_start=start, X_GC=X_GC)
    R, sheet = 0.04, 0.002
    x = np.linspace(-R, R, 61)
    xs, ys = np.meshgrid(x, np.linspace(-0.01, 0.01, 5))
    zs = sheet + R + np.sqrt(R * R - xs * xs)
    bare = np.linspace(0.05, 0.06, 5)  # the sheet beside the cylinder, under the fingers
    pts = np.concatenate([np.stack([0.5 + xs.ravel(), ys.ravel(), zs.ravel()]),
                          np.stack([0.5 + np.concatenate([bare, -bare]), np.zeros(10),
                                    np.full(10, sheet)])], axis=1)
    P_W = np.vstack([pts, np.ones(pts.shape[1])])
    hand = (0.5, 0.0, 0.3, 0.0)
    z = ctrl._grasp_from_points(P_W, hand)[2]
    top = sheet + 2 * R
    if at_widest:
        assert sheet + R <= z <= sheet + R + 0.006
    else:
        assert z == pytest.approx(top - scenario.scripted.grasp_depth_below_top_m)
