"""Each LeafSystem alone: FixValue on the inputs, Eval on the outputs."""

import numpy as np
import pytest
from pydrake.math import RigidTransform

from drake_grasp.geometry.hand_model import (
    STROKE_M,
    topdown_rotation,
)
from drake_grasp.geometry.topdown import (
    plan_topdown_grasp,
    points_between_pads,
)
from drake_grasp.config.sections import GripperConfig, ScriptedGraspConfig
from drake_grasp.systems.gripper import GripperController, gripper_pd_target
from drake_grasp.systems.supervisor import Mode, ScriptedGraspSupervisor, interpolate_pose, min_jerk


@pytest.mark.parametrize("force_mode", ["constant", "limit"])
def test_gripper_target_caps_the_pad_force(force_mode):
    kp = 2000.0
    # Open fingers, far from the commanded closed width: the target is only 2F/kp away.
    q_d = gripper_pd_target(0.0, 0.03, kp, grip_force_n=10.0, force_mode=force_mode)
    assert kp * (0.03 - q_d) == pytest.approx(2 * 10.0)


def test_gripper_target_in_limit_mode_is_the_goal_near_it():
    # Close to the goal the cap is inactive and the target is the goal.
    assert gripper_pd_target(0.05, 0.0251, 2000.0, 100.0, "limit") == pytest.approx(0.025)


def test_gripper_controller_ramps_at_the_closing_speed():
    sys = GripperController(kp=2000.0, closing_speed_m_s=0.1, initial_width_m=0.085, time_step=0.01)
    ctx = sys.CreateDefaultContext()
    sys.GetInputPort("gripper_command").FixValue(ctx, [0.0, 200.0])
    sys.GetInputPort("gripper_state").FixValue(ctx, [0.0425, 0.0425, 0.0, 0.0])
    update = sys.EvalUniquePeriodicDiscreteUpdate(ctx)
    assert update.get_vector().GetAtIndex(0) == pytest.approx(0.085 - 0.1 * 0.01)
    q_d, v_d = sys.GetOutputPort("desired_state").Eval(ctx)
    assert q_d == pytest.approx(0.0425)
    assert v_d == pytest.approx(-0.05)  # half the width rate, per finger


def test_topdown_plan_grasps_a_box_across_its_narrow_side():
    # A 5 cm x 12 cm x 4 cm box lying on the table, long side along y.
    g = np.stack(np.meshgrid(np.linspace(-0.025, 0.025, 11), np.linspace(-0.06, 0.06, 25),
                             np.linspace(0, 0.04, 9)), -1).reshape(-1, 3)
    g += [0.5, 0.1, 0.0]
    plan = plan_topdown_grasp(g)
    closing = topdown_rotation(plan.yaw)[:, 0]
    assert abs(closing[0]) == pytest.approx(1.0, abs=1e-3)  # closes along x, the 5 cm side
    assert plan.width == pytest.approx(0.05, abs=1e-3)
    assert plan.position[:2] == pytest.approx([0.5, 0.1], abs=1e-3)
    assert plan.position[2] == pytest.approx(max(0.04 - 0.025, 0.02))  # min grasp height


def test_topdown_plan_rejects_wide_objects():
    # 12 cm square: the only slices that fit the stroke cross its corners, over 4 cm from
    # its centre.
    g = np.random.default_rng(0).uniform([-0.06, -0.06, 0], [0.06, 0.06, 0.05], size=(500, 3))
    with pytest.raises(ValueError, match="wide"):
        plan_topdown_grasp(g)
    assert plan_topdown_grasp(g, max_com_offset_m=0.1).width <= STROKE_M - 0.01


def test_topdown_plan_fits_a_flat_hammer_slice_by_slice():
    # A hammer lying flat: an 87 mm x 30 mm head at y = 0.10 and a 25 mm wide handle along
    # y, 2 cm thick. No direction fits the whole object into the 75 mm stroke, but the
    # slice under the fingers across the handle does: the plan closes across the handle
    # (along x), as near the centre of mass as a slice clear of the head allows.
    rng = np.random.default_rng(0)
    head = rng.uniform([-0.0435, 0.085, 0.0], [0.0435, 0.115, 0.02], size=(800, 3))
    handle = rng.uniform([-0.0125, -0.15, 0.0], [0.0125, 0.085, 0.02], size=(2000, 3))
    g = np.concatenate([head, handle]) + [0.5, 0.0, 0.0]
    com = np.array([0.5, 0.08, 0.01])  # on the handle, 5 mm from the head
    plan = plan_topdown_grasp(g, min_height=0.025, com_W=com)
    closing = topdown_rotation(plan.yaw)[:, 0]
    assert abs(closing[0]) == pytest.approx(1.0, abs=0.05)  # across the handle
    assert plan.width == pytest.approx(0.025, abs=0.003)
    assert plan.position[0] == pytest.approx(0.5, abs=0.003)
    # The fingers' slice (pad half width + 5 mm margin) stays clear of the head's edge.
    assert plan.position[1] <= 0.085 - 0.016 + 1e-9
    assert plan.position[1] == pytest.approx(0.085 - 0.016, abs=0.005)  # nearest the COM
    assert plan.position[2] == pytest.approx(0.025)


def test_points_between_pads():
    P = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.0]])
    assert points_between_pads(P, width=0.03) == 1


def test_min_jerk_and_interpolation():
    assert min_jerk(0.0) == 0.0 and min_jerk(1.0) == 1.0 and min_jerk(0.5) == pytest.approx(0.5)
    a = RigidTransform([0, 0, 0])
    b = RigidTransform([1, 2, 3])
    assert interpolate_pose(a, b, 0.25).translation() == pytest.approx([0.25, 0.5, 0.75])


def _supervisor():
    # A 4 cm cube at (0.5, 0, 0.02) is body 1.
    pts = np.random.default_rng(1).uniform(-0.02, 0.02, size=(400, 3))
    X_WG_start = RigidTransform([0.5, 0.0, 0.2])
    sup = ScriptedGraspSupervisor(
        object_body_index=1, object_points_O=pts, X_WG_start=X_WG_start,
        motion=ScriptedGraspConfig(), gripper=GripperConfig())
    return sup


def test_supervisor_plans_from_the_true_pose_and_walks_its_modes():
    sup = _supervisor()
    ctx = sup.CreateDefaultContext()
    poses = [RigidTransform(), RigidTransform([0.5, 0.0, 0.02]), RigidTransform([0.5, 0, 0.3])]
    sup.GetInputPort("body_poses").FixValue(ctx, poses)
    sup.GetInputPort("gripper_state").FixValue(ctx, np.zeros(4))
    state = ctx.get_mutable_state()
    sup.ExecuteInitializationEvents(ctx)
    s = sup.get_supervisor_state(ctx)
    assert s.mode == Mode.APPROACH
    # 2.5 cm under the cube's 4 cm top would be 1.5 cm; the scripted grasp keeps its
    # centre >= 2.5 cm up (min_grasp_height_m: the fingertips 4 mm above the sheet's top).
    assert s.X_WG_grasp.translation() == pytest.approx([0.5, 0.0, 0.025], abs=2e-3)
    assert sup.GetOutputPort("gripper_command").Eval(ctx)[0] == pytest.approx(0.085)
    # Start of the approach: the desired pose is the start pose.
    assert sup.GetOutputPort("X_WG_desired").Eval(ctx).translation() == pytest.approx([0.5, 0, 0.2])
    # The judge reads the motion phase from control_status: approaching, phase 0.
    assert list(sup.GetOutputPort("control_status").Eval(ctx)) == [0.0, 1.0, 0.0]
    del state


def test_distance_evaluator_alone_matches_the_direct_form():
    import torch
    from pydrake.systems.sensors import ImageDepth32F

    from drake_grasp.cnn.net_config import NetworkConfig
    from drake_grasp.cnn.network import DistanceCNN
    from drake_grasp.policies.evaluator import DistanceEvaluator

    model = DistanceCNN(NetworkConfig(theta_unit="deg"), generator=torch.Generator().manual_seed(4))
    system = DistanceEvaluator(model)
    ctx = system.CreateDefaultContext()
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.2, 0.3, (64, 64)).astype(np.float32)
    image = ImageDepth32F(64, 64)
    image.mutable_data[:, :, 0] = depth
    actions = np.column_stack([rng.uniform(-0.04, 0.04, (16, 2)), rng.uniform(-45, 45, 16)])
    system.GetInputPort("depth_image").FixValue(ctx, image)
    system.GetInputPort("candidate_actions").FixValue(ctx, actions)
    got = system.GetOutputPort("predicted_distances").Eval(ctx)
    with torch.no_grad():
        direct = model.forward_direct(model.preprocess(np.repeat(depth[None], 16, 0)),
                                      torch.as_tensor(actions, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(got, direct, rtol=1e-4, atol=1e-6)


def test_action_sampler_alone_is_deterministic_per_seed_and_step():
    from drake_grasp.policies.evaluator import ActionSampler

    system = ActionSampler(num_candidates=32, xy_m=0.04, theta_deg=45.0, period_s=0.1, seed=5)
    ctx = system.CreateDefaultContext()
    port = system.GetOutputPort("candidate_actions")
    first = np.array(port.Eval(ctx))
    assert first.shape == (32, 3)
    assert np.abs(first[:, :2]).max() <= 0.04 and np.abs(first[:, 2]).max() <= 45.0
    ctx.SetTime(0.1)
    second = np.array(port.Eval(ctx))
    assert not np.array_equal(first, second)  # a fresh draw every control step
    other = system.CreateDefaultContext()
    other.SetTime(0.1)
    np.testing.assert_array_equal(port.Eval(other), second)  # same (seed, step), same draw
    system.set_seed(other, 6)
    assert not np.array_equal(port.Eval(other), second)


def _tilted_grasp(xyz, yaw_deg: float, tilt_deg: float) -> np.ndarray:
    """A grasp pose X_WG: top-down at `yaw_deg`, then tilted about its y_G axis."""
    a = np.deg2rad(tilt_deg)
    R_tilt = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    X = np.eye(4)
    X[:3, :3] = topdown_rotation(np.deg2rad(yaw_deg)) @ R_tilt
    X[:3, 3] = xyz
    return X


def _fix_gpd_inputs(ctrl, ctx) -> None:
    """Every input of a gpd controller fixed: blank wrist images, no candidates, the GPD
    image a flat 0.6 m."""
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    ctrl.GetInputPort("depth_image").FixValue(ctx, ImageDepth32F(64, 64))
    ctrl.GetInputPort("label_image").FixValue(ctx, ImageLabel16I(64, 64))
    ctrl.GetInputPort("candidate_actions").FixValue(ctx, np.zeros((0, 3)))
    ctrl.GetInputPort("predicted_distances").FixValue(ctx, np.zeros(0))
    ctrl.GetInputPort("gripper_state").FixValue(ctx, np.zeros(4))
    gpd_image = ImageDepth32F(640, 480)
    gpd_image.mutable_data[:] = 0.6
    ctrl.GetInputPort("gpd_depth_image").FixValue(ctx, gpd_image)


def _gpd_controller(detect_fn, scenario_text: str = "{policy: gpd}"):
    """A gpd GraspController alone in a Simulator, every input fixed (the GPD image a
    flat 0.6 m)."""
    from pydrake.systems.analysis import Simulator

    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.station import gpd_camera_offset, gripper_frame_offsets, topdown_pose
    from drake_grasp.policies.controllers import make_controller

    scenario = load_scenario(scenario_name="isolation", scenario_text=scenario_text)
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], 0.3 + X_GC.translation()[2], np.deg2rad(10.0))
    ctrl = make_controller("gpd", scenario=scenario, X_WG_start=start, X_GC=X_GC,
                           X_GC_gpd=gpd_camera_offset(), detect_fn=detect_fn)
    ctx = ctrl.CreateDefaultContext()
    _fix_gpd_inputs(ctrl, ctx)
    sim = Simulator(ctrl, ctx)
    sim.Initialize()
    return scenario, ctrl, sim, start


def test_gpd_controller_views_detects_once_and_executes_the_tilted_grasp():
    from drake_grasp.world.station import gpd_camera_offset
    from drake_grasp.policies.controller_state import Phase

    grasp = _tilted_grasp([0.52, 0.03, 0.04], 30.0, 20.0)
    calls = []

    def detect(depth, X_WC):
        calls.append((np.array(depth, copy=True), np.array(X_WC)))
        return grasp

    scenario, ctrl, sim, start = _gpd_controller(detect)
    ctx = sim.get_context()
    m = scenario.scripted
    pose = ctrl.GetOutputPort("X_WG_desired")
    phases = []

    def run_to(t):
        sim.AdvanceTo(t)
        phases.append(ctrl.get_controller_state(ctx).phase)

    run_to(0.05)
    assert phases[-1] == Phase.VIEW
    view_time = m.approach_time_s + scenario.gpd.view_settle_s
    run_to(view_time - 0.05)  # at the viewpoint, resting, no image taken yet
    assert phases[-1] == Phase.VIEW and not calls
    # No control step before the image: a disturbance "after the 3rd iteration" must
    # come after GPD's decision, not while it looks.
    status = ctrl.GetOutputPort("control_status")
    assert status.Eval(ctx)[0] == 0.0
    X_view = pose.Eval(ctx)
    X_WC_view = X_view @ gpd_camera_offset()
    assert X_view.translation()[:2] == pytest.approx(start.translation()[:2], abs=1e-9)
    assert X_WC_view.translation()[2] == pytest.approx(scenario.gpd.view_camera_height_m, abs=1e-9)
    np.testing.assert_allclose(X_view.rotation().matrix(), start.rotation().matrix(), atol=1e-9)
    run_to(view_time + 0.05)
    assert phases[-1] == Phase.APPROACH
    assert len(calls) == 1
    depth, X_WC = calls[0]
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    np.testing.assert_allclose(X_WC, X_WC_view.GetAsMatrix4(), atol=1e-12)
    t_image = ctrl.get_controller_state(ctx).decided_s
    assert t_image == pytest.approx(view_time, abs=scenario.controller.period_s)
    run_to(t_image + 0.32)  # control steps count from the image
    assert status.Eval(ctx)[0] == 3.0
    run_to(view_time + m.approach_time_s + 0.05)
    assert phases[-1] == Phase.DESCEND
    # The pre-grasp: the grasp moved back along its approach axis z_G.
    X_pre = grasp.copy()
    X_pre[:3, 3] -= m.pregrasp_height_m * grasp[:3, 2]
    s = ctrl.get_controller_state(ctx)
    np.testing.assert_allclose(np.reshape(s.grasp_pose, (4, 4)), grasp, atol=1e-12)
    run_to(view_time + m.approach_time_s + m.descend_time_s + 0.05)
    assert phases[-1] == Phase.CLOSE
    np.testing.assert_allclose(pose.Eval(ctx).GetAsMatrix4(), grasp, atol=1e-9)
    assert ctrl.GetOutputPort("gripper_command").Eval(ctx)[0] == 0.0
    run_to(20.0)
    assert phases[-1] == Phase.DONE and len(calls) == 1
    lifted = grasp.copy()
    lifted[2, 3] += m.lift_height_m
    np.testing.assert_allclose(pose.Eval(ctx).GetAsMatrix4(), lifted, atol=1e-9)
    # Reported as (x, y, z, yaw of x_G on the table).
    x_G = grasp[:3, 0]
    assert s.grasp == pytest.approx((0.52, 0.03, 0.04, np.rad2deg(np.arctan2(x_G[1], x_G[0]))))
    assert s.grasp[3] == pytest.approx(30.0)


def test_gpd_controller_without_a_detection_stays_at_the_viewpoint():
    from drake_grasp.policies.controller_state import Phase

    scenario, ctrl, sim, _ = _gpd_controller(lambda depth, X_WC: None)
    sim.AdvanceTo(3.0)
    ctx = sim.get_context()
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.DONE
    assert ctrl.outcome(ctx)["failure_reason"] == "missed: no grasp detected"
    X = ctrl.GetOutputPort("X_WG_desired").Eval(ctx)
    assert X.translation()[2] == pytest.approx(scenario.gpd.view_camera_height_m - 0.105, abs=1e-9)
    assert ctrl.GetOutputPort("gripper_command").Eval(ctx)[0] == scenario.gripper.open_width_m


def _gpd_with_noise(detect_fn, scenario_text: str):
    """The gpd controller (every input fixed as in `_gpd_controller`) feeding the
    KinematicNoise system, as the episode Diagram wires them."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.systems.kinematic_noise import KinematicNoise
    from drake_grasp.world.station import gpd_camera_offset, gripper_frame_offsets, topdown_pose
    from drake_grasp.policies.controllers import make_controller

    scenario = load_scenario(scenario_name="isolation", scenario_text=scenario_text)
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], 0.3 + X_GC.translation()[2], np.deg2rad(10.0))
    builder = DiagramBuilder()
    ctrl = builder.AddSystem(make_controller(
        "gpd", scenario=scenario, X_WG_start=start, X_GC=X_GC, X_GC_gpd=gpd_camera_offset(),
        detect_fn=detect_fn))
    noise = builder.AddSystem(KinematicNoise(noise=scenario.noise, seed=scenario.seed,
                                             X_WG_start=start, period_s=scenario.controller.period_s))
    builder.Connect(ctrl.GetOutputPort("X_WG_desired"), noise.GetInputPort("X_WG_commanded"))
    builder.Connect(ctrl.GetOutputPort("X_WG_goal"), noise.GetInputPort("X_WG_goal"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    _fix_gpd_inputs(ctrl, ctrl.GetMyMutableContextFromRoot(sim.get_mutable_context()))
    sim.Initialize()
    executed = lambda: noise.GetOutputPort("X_WG_desired").Eval(  # noqa: E731
        noise.GetMyContextFromRoot(sim.get_context())).GetAsMatrix4()
    return ctrl, sim, executed


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gpd_kinematic_noise_moves_the_grasp_in_the_plane_and_keeps_its_tilt(seed):
    """The commanded planar move gets the noise (the KinematicNoise system); the tilt and
    the height are kept, and the policy keeps believing the grasp it commanded. The
    detection's x_G points away from the view's (yaw 10 + 160 deg): the hand takes the
    same grasp turned half a turn about its approach, a 20 degree wrist turn."""
    from drake_grasp.policies.controller_state import Phase

    grasp = _tilted_grasp([0.45, -0.04, 0.05], 170.0, 25.0)
    ctrl, sim, executed = _gpd_with_noise(
        lambda depth, X_WC: grasp, f"{{policy: gpd, seed: {seed}, noise: {{kind: gaussian}}}}")
    sim.AdvanceTo(4.55)
    s = ctrl.get_controller_state(ctrl.GetMyContextFromRoot(sim.get_context()))
    assert s.phase == Phase.CLOSE
    believed = np.reshape(s.grasp_pose, (4, 4))
    np.testing.assert_allclose(believed, grasp @ np.diag([-1.0, -1.0, 1.0, 1.0]), atol=1e-12)
    X = executed()
    assert not np.allclose(X[:2, 3], grasp[:2, 3], atol=1e-4)  # moved by the noise
    assert X[2, 3] == pytest.approx(0.05)
    assert X[:3, 2] @ [0, 0, -1] == pytest.approx(np.cos(np.deg2rad(25.0)))  # tilt kept
    assert X[:3, :3] @ X[:3, :3].T == pytest.approx(np.eye(3))
    # The approach's horizontal part turned with the noisy yaw only; x_G flipped.
    assert X[:3, 0] @ grasp[:3, 0] < 0
    yaw = np.rad2deg(np.arctan2(X[1, 0], X[0, 0]))
    turn = (yaw - 10.0 + 90.0) % 180.0 - 90.0
    assert abs(turn) < 60.0


def test_gpd_without_noise_takes_the_detection_turned_half_a_turn_when_nearer():
    grasp = _tilted_grasp([0.45, -0.04, 0.05], 170.0, 25.0)
    _, ctrl, sim, _ = _gpd_controller(lambda depth, X_WC: grasp)
    sim.AdvanceTo(2.05)
    X = np.reshape(ctrl.get_controller_state(sim.get_context()).grasp_pose, (4, 4))
    np.testing.assert_allclose(X, grasp @ np.diag([-1.0, -1.0, 1.0, 1.0]), atol=1e-12)


def test_gpd_offset_noise_shifts_the_executed_grasp_and_keeps_its_tilt():
    """The constant-offset model: the hand really goes 2 cm along the grasp's x_G (on
    the table) from where the policy believes; the orientation is the believed one."""
    from drake_grasp.policies.controller_state import Phase

    grasp = _tilted_grasp([0.52, 0.03, 0.04], 30.0, 20.0)
    ctrl, sim, executed = _gpd_with_noise(
        lambda depth, X_WC: grasp, "{policy: gpd, noise: {kind: offset, offset_xy_m: [0.02, 0.0]}}")
    sim.AdvanceTo(4.55)
    ctx = ctrl.GetMyContextFromRoot(sim.get_context())
    assert ctrl.get_controller_state(ctx).phase == Phase.CLOSE
    np.testing.assert_allclose(ctrl.GetOutputPort("X_WG_desired").Eval(ctx).GetAsMatrix4(),
                               grasp, atol=1e-9)  # the policy commands what it believes
    X = executed()
    x_G = grasp[:2, 0] / np.linalg.norm(grasp[:2, 0])
    assert X[:2, 3] == pytest.approx(grasp[:2, 3] + 0.02 * x_G, abs=1e-9)
    assert X[2, 3] == pytest.approx(grasp[2, 3])
    np.testing.assert_allclose(X[:3, :3], grasp[:3, :3], atol=1e-9)


def test_depth_postprocessor_streams_draw_their_own_noise_from_one_seed():
    """The GPD sensor's post-processor (stream 1) never repeats the wrist camera's noise
    (stream 0, the draws it always had) for the same trial seed."""
    from pydrake.systems.sensors import ImageDepth32F

    from drake_grasp.geometry.sensing import DepthNoiseConfig, frame_rng, postprocess_depth
    from drake_grasp.systems.depth import DepthPostProcessor

    config = DepthNoiseConfig(enabled=True)
    image = ImageDepth32F(32, 24)
    image.mutable_data[:] = 0.6
    out = []
    for stream in (0, 1):
        system = DepthPostProcessor(config, width=32, height=24, far_value_m=3.5,
                                    frame_period_s=0.1, seed=7, stream=stream)
        ctx = system.CreateDefaultContext()
        system.GetInputPort("depth_image_32f").FixValue(ctx, image)
        out.append(np.array(system.GetOutputPort("depth_image").Eval(ctx).data))
    assert not np.array_equal(out[0], out[1])
    expected = postprocess_depth(np.array(image.data), frame_rng(7, 0), config, 3.5)
    np.testing.assert_array_equal(out[0], expected)
    with pytest.raises(ValueError, match="stream"):
        DepthPostProcessor(config, width=32, height=24, far_value_m=3.5, frame_period_s=0.1,
                           stream=-1)


def test_gpd_controller_names_a_detection_that_is_not_a_pose():
    bad = np.diag([1.0, 1.0, -1.0, 1.0])  # a reflection
    bad[:3, 3] = [0.5, 0.0, 0.05]
    _, _, sim, _ = _gpd_controller(lambda depth, X_WC: bad)
    with pytest.raises(Exception, match="not a rotation matrix"):
        sim.AdvanceTo(2.05)


def test_state_values_are_shared_not_copied_and_stay_immutable():
    import copy
    from dataclasses import dataclass, replace

    from drake_grasp.policies.controller_state import ControllerState
    from drake_grasp.systems.judge import JudgeHistory
    from drake_grasp.systems.state import freeze, shared_when_copied

    s = ControllerState(iteration=3)
    assert copy.deepcopy(s) is s and copy.copy(s) is s
    assert copy.deepcopy(JudgeHistory()) is not None
    # An update makes a new value; the old one is unchanged (what sharing relies on).
    t = replace(s, iteration=4)
    assert (s.iteration, t.iteration) == (3, 4)
    a = freeze(np.zeros(3))
    with pytest.raises(ValueError):
        a[0] = 1.0

    @dataclass
    class Mutable:
        x: int = 0

    with pytest.raises(TypeError, match="frozen dataclass"):
        shared_when_copied(Mutable)


def test_context_clone_keeps_its_own_controller_state():
    # A cloned Context shares the state value; setting a new value in one (what every
    # update does) leaves the other as it was.
    from pydrake.common.value import AbstractValue
    from pydrake.systems.framework import LeafSystem

    from drake_grasp.policies.controller_state import ControllerState

    class Holder(LeafSystem):
        def __init__(self):
            super().__init__()
            self.idx = self.DeclareAbstractState(AbstractValue.Make(ControllerState()))

    sys = Holder()
    ctx = sys.CreateDefaultContext()
    clone = ctx.Clone()
    ctx.get_mutable_abstract_state(int(sys.idx)).set_value(ControllerState(iteration=7))
    assert clone.get_abstract_state(int(sys.idx)).get_value().iteration == 0
    assert ctx.get_abstract_state(int(sys.idx)).get_value().iteration == 7


def test_gripper_target_in_constant_force_mode():
    from drake_grasp.systems.gripper import FORCE_RISE_GAIN

    kp, force = 2000.0, 60.0
    # Blocked at 15 mm while the ramp went on to 0: full force (2F in all, F per pad).
    q_d = gripper_pd_target(0.0, 0.015, kp, force, "constant")
    assert kp * (0.015 - q_d) == pytest.approx(2 * force)
    # "limit" presses with kp (q - q_goal) only: 30 N in all, 15 N per pad.
    q_d = gripper_pd_target(0.0, 0.015, kp, force, "limit")
    assert kp * (0.015 - q_d) == pytest.approx(30.0)
    # Just after contact the squeeze rises with the ramp's lead, FORCE_RISE_GAIN times
    # as steeply as the "limit" spring.
    lead = 0.001
    q_d = gripper_pd_target(2 * (0.015 - lead), 0.015, kp, force, "constant")
    assert kp * (0.015 - q_d) == pytest.approx(kp * FORCE_RISE_GAIN * lead)
    # Opening (the finger behind a wider ramp) is not pushed: the target is the ramp.
    assert gripper_pd_target(0.08, 0.02, kp, force, "constant") == pytest.approx(0.04)
    with pytest.raises(ValueError, match="force_mode"):
        GripperController(kp=kp, closing_speed_m_s=0.1, initial_width_m=0.085, time_step=0.005,
                          force_mode="hard")


@pytest.mark.parametrize("time_step", [0.002, 0.005])
def test_free_closing_fingers_follow_the_ramp(time_step):
    """Closing on nothing, the constant-force mode does not slam the fingers: they follow
    the ramp (the datasheet closing speed) within half a millimetre, i.e. under 5 N of
    extra squeeze per pad."""
    from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource

    from drake_grasp.core.assets import make_parser
    from drake_grasp.evaluation.lab import GRIPPER_URI

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(
        time_step=time_step, discrete_contact_approximation="lagged"), builder)
    (gripper,) = make_parser(plant).AddModels(url=GRIPPER_URI)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("robotiq_base", gripper))
    plant.Finalize()
    kp = plant.GetJointActuatorByName("left_finger_actuator", gripper).get_controller_gains().p
    grip = builder.AddSystem(GripperController(kp=kp, closing_speed_m_s=0.1, initial_width_m=0.085,
                                               time_step=time_step))
    command = builder.AddSystem(ConstantVectorSource([0.0, 60.0]))
    builder.Connect(command.get_output_port(), grip.GetInputPort("gripper_command"))
    builder.Connect(plant.get_state_output_port(gripper), grip.GetInputPort("gripper_state"))
    builder.Connect(grip.GetOutputPort("desired_state"), plant.get_desired_state_input_port(gripper))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyContextFromRoot(context)
    grip_context = grip.GetMyContextFromRoot(context)
    plant.SetPositions(plant.GetMyMutableContextFromRoot(context), gripper, [0.0425, 0.0425])
    lags = []
    t = 0.0
    while t < 0.8:  # 85 mm at 0.1 m/s: fully closed at 0.85 s
        t += time_step
        simulator.AdvanceTo(t)
        q = float(plant.GetPositions(plant_context, gripper)[0])
        ramp = float(grip_context.get_discrete_state(0).GetAtIndex(0))
        lags.append(abs(q - 0.5 * ramp))
    assert float(plant.GetPositions(plant_context, gripper)[0]) < 0.005  # it did close
    assert max(lags) < 0.0005, max(lags)
