"""The closed-loop controller alone and in small diagrams: convergence, r and z schedule,
the 14 cm stop rule, kinematic noise, the sheet shift."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from drake_grasp.geometry.actions import apply_actions, displacement_norm
from drake_grasp.systems.kinematic_noise import gaussian_noisy_displacement
from drake_grasp.config.scenario import load_scenario
from drake_grasp.world.station import gripper_frame_offsets, topdown_pose
from drake_grasp.policies.controllers import make_controller
from drake_grasp.policies.controller_state import Phase, hand_to_pose
from drake_grasp.policies.evaluator import ActionSampler

GOAL = np.array([0.53, -0.02, 20.0])  # world [x, y, yaw_deg] the stand-in CNN points at


class StandInEvaluator(LeafSystem):
    """Predicts the true distance from each candidate's hand pose to GOAL."""

    def __init__(self):
        super().__init__()
        self.DeclareAbstractInputPort("candidate_actions", AbstractValue.Make(np.zeros((0, 3))))
        self.DeclareAbstractInputPort("X_WG", AbstractValue.Make(RigidTransform()))
        self.DeclareAbstractOutputPort("predicted_distances", lambda: AbstractValue.Make(np.zeros(0)),
                                       self._Calc)

    def _Calc(self, context, output):
        from drake_grasp.geometry.grasp_metric import grasp_distance

        actions = self.get_input_port(0).Eval(context)
        X = self.get_input_port(1).Eval(context)
        R = X.rotation().matrix()
        hand = [X.translation()[0], X.translation()[1], np.rad2deg(np.arctan2(R[1, 0], R[0, 0]))]
        output.set_value(grasp_distance(apply_actions(hand, actions), GOAL))


def _image(value, shape=(64, 64), center=None):
    img = ImageDepth32F(shape[1], shape[0])
    img.mutable_data[:] = value
    if center is not None:
        # Under the grasp axis: the camera is 5 cm beside it, so at 14 cm the axis is
        # seen about 22 px below the image centre.
        img.mutable_data[46:62, 24:40, 0] = center
    return img


def _controller_diagram(scenario, depth_image, policy="ctr", evaluator=None):
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], 0.3 - 0.115, 0.0)
    builder = DiagramBuilder()
    ctrl = builder.AddSystem(make_controller(
        policy, scenario=scenario, X_WG_start=start, X_GC=X_GC))
    c = scenario.controller
    sampler = builder.AddSystem(ActionSampler(num_candidates=c.num_candidates, xy_m=c.sample_xy_m,
                                              theta_deg=c.sample_theta_deg, period_s=c.period_s,
                                              seed=scenario.seed))
    ev = builder.AddSystem(evaluator or StandInEvaluator())
    depth = builder.AddSystem(depth_image if isinstance(depth_image, LeafSystem)
                              else ConstantValueSource(AbstractValue.Make(depth_image)))
    label = builder.AddSystem(ConstantValueSource(AbstractValue.Make(ImageLabel16I(64, 64))))
    grip = builder.AddSystem(ConstantVectorSource(np.zeros(4)))
    builder.Connect(depth.get_output_port(), ctrl.GetInputPort("depth_image"))
    builder.Connect(label.get_output_port(), ctrl.GetInputPort("label_image"))
    builder.Connect(grip.get_output_port(), ctrl.GetInputPort("gripper_state"))
    builder.Connect(sampler.GetOutputPort("candidate_actions"), ctrl.GetInputPort("candidate_actions"))
    builder.Connect(sampler.GetOutputPort("candidate_actions"), ev.GetInputPort("candidate_actions"))
    builder.Connect(ctrl.GetOutputPort("X_WG_desired"), ev.GetInputPort("X_WG"))
    builder.Connect(ev.GetOutputPort("predicted_distances"), ctrl.GetInputPort("predicted_distances"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    return sim, ctrl, ctrl.GetMyContextFromRoot(sim.get_context())


@pytest.fixture
def scenario():
    # The paper's stop rule alone: grasp as soon as it fires (no convergence phase).
    return load_scenario(scenario_name="isolation",
                         scenario_text="{seed: 2, controller: {converge_iterations: 0}}")


def test_controller_converges_to_the_stand_in_minimum(scenario):
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3))
    c = scenario.controller
    sim.AdvanceTo(c.period_s * (c.iterations + 1.5))
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.DESCEND and s.stop_reason == "hand at its lowest height"
    assert s.iteration == c.iterations
    hand = np.array([s.hand[0], s.hand[1], s.hand[3]])
    assert np.linalg.norm(hand[:2] - GOAL[:2]) < 0.003
    assert abs((hand[2] - GOAL[2] + 90) % 180 - 90) < 3.0
    # z schedule: camera from 0.3 m to 0.15 m in equal steps.
    assert s.hand[2] + 0.115 == pytest.approx(c.end_camera_height_m, abs=1e-9)


def test_each_step_moves_the_fraction_r_and_steps_down(scenario):
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3))
    c = scenario.controller
    sim.AdvanceTo(1.5 * c.period_s)
    s1 = ctrl.get_controller_state(ctx)
    rec = s1.last_step
    np.testing.assert_allclose(rec.moved, c.step_ratio * rec.chosen)
    assert rec.chosen.tolist() == rec.actions[np.argmin(rec.distances)].tolist()
    dz = (0.3 - c.end_camera_height_m) / c.iterations
    assert s1.hand[2] == pytest.approx(rec.hand[2] - dz)
    expected = apply_actions([rec.hand[0], rec.hand[1], rec.hand[3]], rec.moved[None])[0]
    assert [s1.hand[0], s1.hand[1], s1.hand[3]] == pytest.approx(list(expected))


def test_robot_profile_moves_half_way_and_steps_down_1_cm_until_the_lowest_height():
    scenario = load_scenario(scenario_name="isolation",
                             scenario_text="{seed: 2, controller: {profile: robot, converge_iterations: 0}}")
    c = scenario.controller
    assert (c.step_ratio, c.z_step_m) == (0.5, 0.01)
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3))
    sim.AdvanceTo(1.5 * c.period_s)
    s1 = ctrl.get_controller_state(ctx)
    rec = s1.last_step
    np.testing.assert_allclose(rec.moved, 0.5 * rec.chosen)  # half way to the best candidate
    assert rec.chosen.tolist() == rec.actions[np.argmin(rec.distances)].tolist()
    assert s1.hand[2] == pytest.approx(rec.hand[2] - 0.01)
    # 1 cm per iteration until the camera is at its lowest height: 0.3 -> 0.15 m in 15.
    sim.AdvanceTo(c.period_s * 17.5)
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.DESCEND and s.stop_reason == "hand at its lowest height"
    assert s.iteration == 15
    assert s.hand[2] + 0.115 == pytest.approx(c.end_camera_height_m, abs=1e-9)
    # r = 0.5 converges faster than the sim profile's 0.2 in 15 iterations.
    assert np.linalg.norm(np.array(s.hand[:2]) - GOAL[:2]) < 0.003


def test_robot_profile_stops_at_14_cm():
    scenario = load_scenario(scenario_name="isolation",
                             scenario_text="{seed: 2, controller: {profile: robot, converge_iterations: 0}}")
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3, center=0.139))
    sim.AdvanceTo(1.5 * scenario.controller.period_s)
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.DESCEND and "within 0.14 m" in s.stop_reason


def test_paper_sim_profile_runs_all_75_iterations_whatever_the_image_shows():
    """Section 5 as written: an object nearer than 14 cm does not stop the descent, and the
    hand grasps where the 75th iteration leaves it, with no convergence."""
    scenario = load_scenario(scenario_name="isolation",
                             scenario_text="{seed: 2, controller: {profile: paper-sim}}")
    c = scenario.controller
    assert (c.step_ratio, c.iterations, c.stop_distance_m, c.converge_iterations) == (
        0.2, 75, 0.0, 0)
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3, center=0.05))
    sim.AdvanceTo(c.period_s * 10.5)
    assert ctrl.get_controller_state(ctx).phase == Phase.SERVO  # "sim" would have stopped
    sim.AdvanceTo(c.period_s * (c.iterations + 1.5))
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.DESCEND and s.stop_reason == "hand at its lowest height"
    assert s.iteration == c.iterations and s.converging == 0
    assert s.hand[2] + 0.115 == pytest.approx(c.end_camera_height_m, abs=1e-9)


@pytest.mark.parametrize("near,stops", [(0.139, True), (0.141, False)])
def test_stop_rule_fires_at_14_cm(scenario, near, stops):
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3, center=near))
    sim.AdvanceTo(1.5 * scenario.controller.period_s)
    s = ctrl.get_controller_state(ctx)
    assert (s.phase == Phase.DESCEND) == stops
    if stops:
        assert "within 0.14 m" in s.stop_reason and s.iteration == 0


class DepthAfter(LeafSystem):
    """One depth image until `t_switch`, another after (a taller object comes under the
    grasp axis)."""

    def __init__(self, before, after, t_switch):
        super().__init__()
        self._images = (before, after)
        self._t = t_switch
        self.DeclareAbstractOutputPort("depth", lambda: AbstractValue.Make(before), self._Calc)

    def _Calc(self, context, output):
        output.set_value(self._images[int(context.get_time() >= self._t)])


class TurnEvaluator(StandInEvaluator):
    """Prefers turning the hand by +theta whatever the image shows (a CNN biased on a
    round object)."""

    def _Calc(self, context, output):
        output.set_value(-np.asarray(self.get_input_port(0).Eval(context))[:, 2])


def _converge_scenario(**controller):
    fields = ", ".join(f"{k}: {v}" for k, v in controller.items())
    return load_scenario(scenario_name="isolation", scenario_text=f"{{seed: 2, controller: {{{fields}}}}}")


def test_converge_servos_at_the_stop_height_until_the_move_is_small():
    scenario = _converge_scenario(converge_iterations=60, converge_step_m=0.004)
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3, center=0.139))
    c = scenario.controller
    sim.AdvanceTo(c.period_s * 62.5)
    s = ctrl.get_controller_state(ctx)
    assert s.phase != Phase.SERVO and "within 0.14 m" in s.stop_reason
    assert "converged after" in s.stop_reason and s.calm == 2
    assert 3 <= s.iteration < 60
    assert s.hand[2] == pytest.approx(0.3 - 0.115)  # no step down after the stop rule fired
    assert np.linalg.norm(np.array(s.hand[:2]) - GOAL[:2]) < 0.01


def test_converge_moves_its_own_fraction_when_given():
    scenario = _converge_scenario(profile="robot", converge_iterations=5, converge_step_m=0.0,
                                  converge_step_ratio=0.2)
    assert scenario.controller.step_ratio == 0.5
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3, center=0.139))
    sim.AdvanceTo(1.5 * scenario.controller.period_s)  # the stop rule fired, one step at 0.2
    rec = ctrl.get_controller_state(ctx).last_step
    np.testing.assert_allclose(rec.moved, 0.2 * rec.chosen)


def test_converge_ends_when_its_iterations_are_spent():
    scenario = _converge_scenario(converge_iterations=5, converge_step_m=0.0)
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3, center=0.139))
    sim.AdvanceTo(scenario.controller.period_s * 8.5)
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.DESCEND
    assert s.stop_reason.endswith("not converged in 5 more iterations") and s.iteration == 5


def test_converge_rises_when_a_taller_surface_comes_under_the_axis():
    scenario = _converge_scenario(converge_iterations=5, converge_step_m=0.0)
    source = DepthAfter(_image(0.3, center=0.139), _image(0.3, center=0.119), 0.25)
    sim, ctrl, ctx = _controller_diagram(scenario, source)
    sim.AdvanceTo(0.15)  # the stop rule fired at 0.139 m, one iteration at that height
    z0 = ctrl.get_controller_state(ctx).hand[2]
    assert z0 == pytest.approx(0.3 - 0.115)
    sim.AdvanceTo(0.35)  # 2 cm nearer: the hand rises 2 cm, once
    s = ctrl.get_controller_state(ctx)
    assert s.hand[2] == pytest.approx(z0 + 0.02)


def test_commanded_yaw_stays_within_its_bound_of_the_start():
    scenario = _converge_scenario(max_yaw_from_start_deg=135)
    sim, ctrl, ctx = _controller_diagram(scenario, _image(0.3), evaluator=TurnEvaluator())
    sim.AdvanceTo(scenario.controller.period_s * 40.5)
    s = ctrl.get_controller_state(ctx)
    assert s.phase == Phase.SERVO and s.iteration == 40
    # 40 steps of about 0.2 x 45 degrees would turn 360 degrees; the bound holds it at 135.
    assert s.hand[3] == pytest.approx(-135.0) or s.hand[3] == pytest.approx(135.0)


def test_gaussian_noise_matches_the_formula():
    rng = np.random.default_rng(0)
    delta = np.array([0.01, -0.004, 5.0])
    draws = np.array([gaussian_noisy_displacement(delta, rng, 0.4) for _ in range(20000)])
    size = displacement_norm(delta)
    np.testing.assert_allclose(draws.mean(0)[:2], delta[:2], atol=2e-4)
    assert draws.mean(0)[2] == pytest.approx(delta[2], abs=0.2)
    np.testing.assert_allclose(draws.std(0), [0.4 * size, 0.4 * size, 0.4 * size / 0.001],
                               rtol=0.03)


def test_offset_model_shifts_the_commanded_pose(scenario):
    """The KinematicNoise system between the policy and the station: the hand really
    goes the constant offset (in the hand frame) from the pose the policy commands."""
    from drake_grasp.systems.kinematic_noise import KinematicNoise

    scenario.noise.kind = "offset"
    scenario.noise.offset_xy_m = [0.02, -0.01]
    scenario.noise.offset_theta_deg = 10.0
    start = topdown_pose([0.5, 0.0], 0.3 - 0.115, 0.0)
    noise = KinematicNoise(noise=scenario.noise, seed=scenario.seed, X_WG_start=start,
                           period_s=scenario.controller.period_s)
    ctx = noise.CreateDefaultContext()
    believed = (0.55, 0.03, 0.1, 30.0)  # 5.8 cm from the start: the full offset applies
    noise.GetInputPort("X_WG_commanded").FixValue(ctx, hand_to_pose(believed))
    noise.GetInputPort("X_WG_goal").FixValue(ctx, hand_to_pose(believed))
    X = noise.GetOutputPort("X_WG_desired").Eval(ctx)
    expected = apply_actions([believed[0], believed[1], believed[3]], np.array([[0.02, -0.01, 10.0]]))[0]
    X_exp = hand_to_pose((expected[0], expected[1], believed[2], expected[2]))
    assert np.allclose(X.GetAsMatrix4(), X_exp.GetAsMatrix4(), atol=1e-9)
    assert np.linalg.norm(X.translation()[:2] - believed[:2]) == pytest.approx(np.hypot(0.02, 0.01))
    # At the start pose (where it observed the scene) the offset has not ramped in yet.
    noise.GetInputPort("X_WG_commanded").FixValue(ctx, start)
    np.testing.assert_allclose(noise.GetOutputPort("X_WG_desired").Eval(ctx).GetAsMatrix4(),
                               start.GetAsMatrix4(), atol=1e-12)


@pytest.mark.parametrize("step,shifted", [(2, False), (3, True)])
def test_shift_after_the_third_iteration_moves_objects_with_the_sheet(library, step, shifted):
    from drake_grasp.world.scene import make_scene
    from drake_grasp.world.station import MakeGraspStation
    from drake_grasp.systems.disturbance import SheetDisturbance

    scenario = load_scenario(scenario_name="clutter_shift", scenario_text=(
        "{seed: 5, policy: scripted, scene: {kind: isolation, object_ids: [tetra_pak_001], pose: lying}}"))
    scene = make_scene(scenario.scene, scenario.seed, library)
    station = MakeGraspStation(scenario, scene, library)
    builder = DiagramBuilder()
    builder.AddSystem(station.diagram)
    sd = station.diagram
    pose = builder.AddSystem(ConstantValueSource(AbstractValue.Make(station.X_WG_start)))
    builder.Connect(pose.get_output_port(), sd.GetInputPort("X_WG_desired"))
    grip = builder.AddSystem(ConstantVectorSource([0.085, 40.0]))
    builder.Connect(grip.get_output_port(), sd.GetInputPort("gripper_command"))
    dist = builder.AddSystem(SheetDisturbance(scenario.disturbance, seed=scenario.seed, period_s=0.1))
    status = builder.AddSystem(ConstantVectorSource([float(step), 1.0, 0.0]))
    builder.Connect(status.get_output_port(), dist.GetInputPort("control_status"))
    builder.Connect(dist.GetOutputPort("sheet_desired_state"), sd.GetInputPort("sheet_desired_state"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    root = sim.get_mutable_context()
    station.set_initial_state(sd.GetMyMutableContextFromRoot(root))
    plant = station.plant
    pc = plant.GetMyContextFromRoot(root)
    before = plant.EvalBodyPoseInWorld(pc, station.object_body(0)).translation().copy()
    sim.AdvanceTo(1.5)
    after = plant.EvalBodyPoseInWorld(pc, station.object_body(0)).translation()
    shift = dist.shift
    moved = np.linalg.norm(after[:2] - before[:2])
    if shifted:
        assert dist.trigger_time(dist.GetMyContextFromRoot(root)) == pytest.approx(0.0)
        # A box (a can would roll) rides on the sheet: it moves by the sheet's displacement at its
        # position (translation plus the yaw about the sheet centre), within 1 cm.
        c = np.array(scene.center_xy_m)
        r = before[:2] - c
        R = np.array([[np.cos(shift[2]), -np.sin(shift[2])], [np.sin(shift[2]), np.cos(shift[2])]])
        expected = c + shift[:2] + R @ r
        assert np.linalg.norm(after[:2] - expected) < 0.01, (after[:2], expected)
        assert moved > 0.02
    else:
        assert moved < 0.002


def test_target_mode_keeps_candidates_on_the_target(scenario):
    """The stand-in prefers GOAL (just left of the target's pixels); the target covers the
    image's right side: every chosen action must put the hand over the target."""
    depth = _image(0.25)
    labels = ImageLabel16I(64, 64)
    labels.mutable_data[:] = 0
    labels.mutable_data[:, 40:, 0] = 7  # the target's pixels
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], 0.3 - 0.115, 0.0)
    builder = DiagramBuilder()
    ctrl = builder.AddSystem(make_controller(
        "ctr", scenario=scenario, X_WG_start=start, X_GC=X_GC, target_label=7))
    c = scenario.controller
    sampler = builder.AddSystem(ActionSampler(num_candidates=c.num_candidates, xy_m=c.sample_xy_m,
                                              theta_deg=c.sample_theta_deg, period_s=c.period_s))
    ev = builder.AddSystem(StandInEvaluator())
    for port, value in (("depth_image", depth), ("label_image", labels)):
        src = builder.AddSystem(ConstantValueSource(AbstractValue.Make(value)))
        builder.Connect(src.get_output_port(), ctrl.GetInputPort(port))
    grip = builder.AddSystem(ConstantVectorSource(np.zeros(4)))
    builder.Connect(grip.get_output_port(), ctrl.GetInputPort("gripper_state"))
    builder.Connect(sampler.GetOutputPort("candidate_actions"), ctrl.GetInputPort("candidate_actions"))
    builder.Connect(sampler.GetOutputPort("candidate_actions"), ev.GetInputPort("candidate_actions"))
    builder.Connect(ctrl.GetOutputPort("X_WG_desired"), ev.GetInputPort("X_WG"))
    builder.Connect(ev.GetOutputPort("predicted_distances"), ctrl.GetInputPort("predicted_distances"))
    sim = Simulator(builder.Build())
    ctx = ctrl.GetMyContextFromRoot(sim.get_context())
    sim.AdvanceTo(1.5 * c.period_s)
    rec = ctrl.get_controller_state(ctx).last_step
    focal = 0.5 * 64 / np.tan(np.deg2rad(scenario.camera.fov_y_deg) / 2)
    u = (rec.chosen[0] - X_GC.translation()[0]) * focal / 0.25 + 31.5
    assert u >= 39.5, u  # on the target's pixels
    # Without target mode the same step heads for GOAL, off the target.
    sim2, ctrl2, ctx2 = _controller_diagram(scenario, depth)
    sim2.AdvanceTo(1.5 * c.period_s)
    u2 = (ctrl2.get_controller_state(ctx2).last_step.chosen[0] - X_GC.translation()[0]) * focal / 0.25 + 31.5
    assert u2 < 39.5, u2


def test_oracle_analysis_scores_every_step_with_the_true_distance(analysis_script):
    """analysis/oracle_ctr.py (CTR with the true distance function, a diagnostic): every
    control decision of the trial went through the oracle, the controller class is put
    back afterwards, and with perfect scores the hand ends on a true grasp."""
    from drake_grasp.policies.controllers import CONTROLLERS
    from drake_grasp.policies.ctr import CTRController

    oracle = analysis_script("oracle_ctr")
    trial = oracle.run_trial(0, 0)  # isolation trial 0: a lying apple
    assert CONTROLLERS["ctr"] is CTRController
    assert trial["num_true_grasps"] > 0
    assert trial["oracle_steps"] == trial["control_steps"] > 0
    assert trial["success"] and trial["final_distance_m"] < 0.01


def test_oracle_analysis_phase_scores_only_the_descent_or_only_the_stop_height(analysis_script):
    """analysis/oracle_ctr.py --oracle-phase: "descent" hands the truth only the decisions
    before the stop rule fired, "stop" only those after; the CNN takes the others."""
    oracle = analysis_script("oracle_ctr")
    descent = oracle.run_trial(0, 0, "descent")
    stop = oracle.run_trial(0, 0, "stop")
    for trial in (descent, stop):
        assert 0 < trial["oracle_steps"] < trial["control_steps"], trial
    with pytest.raises(SystemExit):
        oracle.main(["--out", "unused", "--oracle-phase", "final"])
