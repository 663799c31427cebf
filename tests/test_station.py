"""The station Diagram: named subsystems and ports, arm tracking, gripper width, camera."""

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource
from pydrake.common.value import AbstractValue

from drake_grasp.config.scenario import load_scenario
from drake_grasp.world.scene import SceneSpec, make_scene
from drake_grasp.world.station import MakeGraspStation


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(scenario_name="isolation", scenario_text="{seed: 1}")


@pytest.fixture(scope="module")
def scene(scenario, library):
    return make_scene(scenario.scene, scenario.seed, library)


def _closed_loop(station, X_WG_desired, gripper_command):
    builder = DiagramBuilder()
    builder.AddNamedSystem("station", station.diagram)
    sd = station.diagram
    pose = builder.AddSystem(ConstantValueSource(AbstractValue.Make(X_WG_desired)))
    builder.Connect(pose.get_output_port(), sd.GetInputPort("X_WG_desired"))
    grip = builder.AddSystem(ConstantVectorSource(np.asarray(gripper_command, float)))
    builder.Connect(grip.get_output_port(), sd.GetInputPort("gripper_command"))
    sheet = builder.AddSystem(ConstantVectorSource(np.zeros(6)))
    builder.Connect(sheet.get_output_port(), sd.GetInputPort("sheet_desired_state"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    station.set_initial_state(sd.GetMyMutableContextFromRoot(simulator.get_mutable_context()))
    return diagram, simulator


def test_station_names_its_subsystems_and_ports(scenario, scene, library):
    station = MakeGraspStation(scenario, scene, library)
    d = station.diagram
    for name in ("plant", "scene_graph", "diff_ik", "arm_desired_state", "gravity_compensation",
                 "gripper_controller", "wrist_camera", "depth_postprocessor", "gpd_camera",
                 "gpd_depth_postprocessor"):
        assert d.HasSubsystemNamed(name), name
    for port in ("X_WG_desired", "gripper_command", "sheet_desired_state"):
        assert d.HasInputPort(port), port
    for port in ("depth_image", "depth_image_raw", "label_image", "body_poses",
                 "gripper_state", "arm_state", "plant_state", "gpd_depth_image",
                 "gpd_depth_image_raw"):
        assert d.HasOutputPort(port), port


def test_arm_tracks_a_commanded_pose_and_gripper_closes_to_width(scenario, library):
    empty = SceneSpec(kind="isolation", seed=0, center_xy_m=[0.5, 0.0], objects=[], settled=True)
    station = MakeGraspStation(scenario, empty, library)
    X_goal = RigidTransform(station.X_WG_start.rotation(),
                            station.X_WG_start.translation() + [0.05, -0.04, -0.06])
    diagram, simulator = _closed_loop(station, X_goal, [0.03, 40.0])
    simulator.AdvanceTo(2.5)
    plant = station.plant
    ctx = plant.GetMyContextFromRoot(simulator.get_context())
    X_WG = plant.CalcRelativeTransform(ctx, plant.world_frame(),
                                       plant.GetFrameByName("grasp_frame", station.gripper))
    err = np.linalg.norm(X_WG.translation() - X_goal.translation())
    assert err < 0.002, f"tracking error {err * 1000:.2f} mm"
    angle = (X_WG.rotation().inverse() @ X_goal.rotation()).ToAngleAxis().angle()
    assert angle < 0.01
    q = plant.GetPositions(ctx, station.gripper)
    assert q[0] + q[1] == pytest.approx(0.03, abs=0.001)


def test_wrist_camera_sees_the_object(scenario, scene, library):
    station = MakeGraspStation(scenario, scene, library)
    ctx = station.diagram.CreateDefaultContext()
    station.set_initial_state(ctx)
    raw = station.diagram.GetOutputPort("depth_image_raw").Eval(ctx).data[:, :, 0]
    depth = station.diagram.GetOutputPort("depth_image").Eval(ctx).data[:, :, 0]
    assert depth.shape == (scenario.camera.height, scenario.camera.width)
    assert np.all(np.isfinite(depth))
    # The table is 0.3 m below the camera; the object is nearer.
    assert np.median(depth) == pytest.approx(scenario.arm.start_camera_height_m, abs=0.01)
    assert depth.min() < scenario.arm.start_camera_height_m - 0.02
    assert np.isfinite(raw).any()


def test_gpd_viewpoint_sees_the_top_of_an_upright_hammer(library):
    """The GPD sensor reads nothing nearer than `gpd.depth_min_m`, so the viewpoint must be
    high enough for the tallest test object standing upright: the cloud the detector
    builds of an upright hammer_000 (0.283 m tall) reaches to within 5 mm of its top."""
    from drake_grasp.policies import gpd
    from drake_grasp.learning.gpd_training import experiment_view
    from drake_grasp.geometry.scene_samples import scene_meshes

    # The isolation experiment's trial 26: "lying" turned this hammer onto its end.
    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        "{scene: {object_ids: [hammer_000], pose: lying}}"))
    settled, X_WC, depth = experiment_view(scenario, 1364363495, library)
    top = max(float(np.asarray(m.vertices)[:, 2].max()) for m in scene_meshes(settled, library))
    assert top > 0.27  # standing on its end
    g = scenario.gpd
    cloud = gpd.cloud_from_depth(depth, fov_y_deg=g.fov_y_deg, X_WC=X_WC,
                                 depth_min_m=g.depth_min_m, depth_max_m=g.depth_max_m,
                                 center_xy=tuple(scenario.scene.center_xy_m))
    assert cloud.points[:, 2].max() > top - 0.005


def test_gpd_camera_sees_the_table_from_the_viewpoint(scenario, scene, library):
    """The GPD sensor (640x480) on its mount, the hand at the gpd policy's viewpoint: the
    table fills most of the view at the viewpoint's height; the object is nearer."""
    from drake_grasp.world.station import gpd_camera_offset, solve_start_configuration, topdown_pose

    station = MakeGraspStation(scenario, scene, library)
    X_GC_gpd = station.X_GC_gpd
    assert X_GC_gpd.translation() == pytest.approx([0.0, 0.06, -0.105], abs=1e-9)
    np.testing.assert_allclose(X_GC_gpd.GetAsMatrix4(), gpd_camera_offset().GetAsMatrix4(),
                               atol=1e-12)
    g = scenario.gpd
    X_view = topdown_pose(station.X_WG_start.translation()[:2],
                          g.view_camera_height_m + X_GC_gpd.translation()[2])
    q_view = solve_start_configuration(station._keep_alive[0], X_view, station.q_start)
    ctx = station.diagram.CreateDefaultContext()
    station.set_initial_state(ctx)
    plant = station.plant
    plant.SetPositions(plant.GetMyMutableContextFromRoot(ctx), station.arm, q_view)
    depth = station.diagram.GetOutputPort("gpd_depth_image").Eval(ctx).data[:, :, 0]
    raw = station.diagram.GetOutputPort("gpd_depth_image_raw").Eval(ctx).data[:, :, 0]
    assert depth.shape == (g.height, g.width) == (480, 640)
    # The table top (z = 0) and the 2 mm sheet on it, 0.6 m below the sensor.
    assert np.median(depth) == pytest.approx(g.view_camera_height_m, abs=0.01)
    assert depth.min() < g.view_camera_height_m - 0.02
    # No hole filling by default: pixels beyond the table (+inf raw) read the far value.
    assert np.all(np.isfinite(depth))
    np.testing.assert_array_equal(depth[np.isposinf(raw)], np.float32(g.depth_max_m))


def test_start_configuration_solves_at_every_start_height_on_one_branch():
    """The local IK solver failed at 0.19196 m and jumped to a far branch (elbow at 4.5
    rad) at 0.19 m from Q_HOME alone; with its restarts every height from 0.15 to 0.40 m
    solves, and neighbouring heights give neighbouring joint angles."""
    from pydrake.multibody.plant import MultibodyPlant

    from drake_grasp.world.station import (Q_HOME, _add_robot, gripper_frame_offsets,
                                      make_control_plant, solve_start_configuration,
                                      topdown_pose)

    plant = MultibodyPlant(0.0)
    arm, gripper = _add_robot(plant)
    plant.Finalize()
    M_T = plant.CalcSpatialInertia(plant.CreateDefaultContext(), plant.GetFrameByName("tool0", arm),
                                   plant.GetBodyIndices(gripper))
    control_plant = make_control_plant(M_T, gripper_frame_offsets()[1])
    heights = [0.15, 0.185, 0.19, 0.19195959, 0.195, 0.25, 0.30, 0.40]
    qs = [solve_start_configuration(control_plant, topdown_pose([0.5, 0.0], z)) for z in heights]
    for z, q in zip(heights, qs):
        X = control_plant.CalcRelativeTransform(_context(control_plant, q),
                                                control_plant.world_frame(),
                                                control_plant.GetFrameByName("grasp_frame"))
        assert np.allclose(X.translation(), [0.5, 0.0, z], atol=2e-4), z
    steps = [np.max(np.abs(b - a)) for a, b in zip(qs, qs[1:])]
    assert max(steps) < 0.6, steps          # one branch: no jumps between nearby heights
    assert all(np.linalg.norm(q - Q_HOME) < 3.5 for q in qs)


def _context(plant, q):
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, q)
    return context


def test_the_start_clears_what_the_survey_image_sees_not_the_true_scene(library, monkeypatch):
    """The start height comes from the wrist camera's survey image, not the true scene:
    with `scene_top_z` made to fail, an upright bottle (0.197 m) still raises the start so
    the open fingertips keep START_CLEARANCE_M above the top the image shows (within 1 mm
    of the true top), and a lying one leaves the paper's 0.3 m."""
    import drake_grasp.world.scene as scene_module
    from drake_grasp.world.scene import scenario_scene, scene_top_z
    from drake_grasp.world.station import (FINGERTIP_BELOW_GRASP_M, START_CLEARANCE_M,
                                           gripper_frame_offsets)

    X_GC = gripper_frame_offsets()[2]
    clearance = -X_GC.translation()[2] + FINGERTIP_BELOW_GRASP_M + START_CLEARANCE_M
    cases = []
    for pose in ("upright", "lying"):
        scenario = load_scenario(scenario_name="isolation", scenario_text=(
            f"{{scene: {{object_ids: [bottle_000], pose: {pose}}}}}"))
        scene = scenario_scene(scenario, library)
        cases.append((scenario, scene, scene_top_z(scene, library)))

    def no_truth(*args, **kwargs):
        raise AssertionError("the station read the scene's true top")

    monkeypatch.setattr(scene_module, "scene_top_z", no_truth)
    (upright, up_scene, up_top), (lying, lying_scene, lying_top) = cases
    assert up_top > 0.19 and lying_top < 0.1
    station = MakeGraspStation(upright, up_scene, library)
    camera_z = station.X_WG_start.translation()[2] - X_GC.translation()[2]
    assert camera_z == pytest.approx(up_top + clearance, abs=1e-3)
    station = MakeGraspStation(lying, lying_scene, library)
    assert station.X_WG_start.translation()[2] - X_GC.translation()[2] == pytest.approx(
        lying.arm.start_camera_height_m, abs=1e-9)


def test_every_library_object_fits_under_the_survey_pose(library):
    """No object of the built-in library, in any orientation, reaches the open fingertips
    at the survey pose (its bounding-box diagonal bounds its height on the table)."""
    from drake_grasp.world.scene import _object_vertices
    from drake_grasp.world.station import (FINGERTIP_BELOW_GRASP_M, START_CLEARANCE_M,
                                           SURVEY_CAMERA_HEIGHT_M, gripper_frame_offsets)

    X_GC = gripper_frame_offsets()[2]
    clearance = -X_GC.translation()[2] + FINGERTIP_BELOW_GRASP_M + START_CLEARANCE_M
    tallest = max(float(np.linalg.norm(np.ptp(_object_vertices(library, i), axis=0)))
                  for i in library.ids())
    assert 0.3 < tallest < SURVEY_CAMERA_HEIGHT_M - clearance
