"""Checks of the shipped robot and scene models (models/*/).

Fast (a few seconds): every file parses through `package://drake_grasp/...` without
a Drake warning, the names other code relies on exist, the gripper geometry obeys
width == 2 q, and a plant holding everything simulates with the in-plant PD
controllers (UR5 holds its pose, the gripper closes and opens to commanded widths).
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from drake_grasp.core.assets import make_parser

UR5_URL = "package://drake_grasp/ur5/ur5.urdf"
GRIPPER_URL = "package://drake_grasp/robotiq_2f85/robotiq_2f85.urdf"
TABLE_URL = "package://drake_grasp/scene/table.urdf"
SHEET_URL = "package://drake_grasp/scene/sheet.urdf"
ALL_URLS = [UR5_URL, GRIPPER_URL, TABLE_URL, SHEET_URL]

UR5_JOINTS = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
]
# Grasp frame 0.45 m in front of the base, 0.30 m above the table, z pointing down.
UR5_HOME = np.array([-0.245, -1.6894, 1.6738, -1.5552, -1.5708, -0.245])

TIME_STEP = 0.002


class _DrakeLogCapture(logging.Handler):
    """pydrake forwards Drake's C++ (spdlog) messages to Python's `drake` logger."""

    def __init__(self):
        super().__init__(level=logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


@pytest.fixture
def drake_warnings():
    handler = _DrakeLogCapture()
    logger = logging.getLogger("drake")
    logger.addHandler(handler)
    try:
        yield handler.messages
    finally:
        logger.removeHandler(handler)


def _build(*, with_renderer: bool = False):
    from pydrake.geometry import CollisionFilterDeclaration, GeometrySet
    from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(
            time_step=TIME_STEP,
            discrete_contact_approximation="lagged",
            contact_model="hydroelastic_with_fallback",
        ),
        builder,
    )
    if with_renderer:
        from pydrake.geometry import MakeRenderEngineVtk, RenderEngineVtkParams

        scene_graph.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
    parser = make_parser(plant)
    (ur5,) = parser.AddModels(url=UR5_URL)
    (gripper,) = parser.AddModels(url=GRIPPER_URL)
    (table,) = parser.AddModels(url=TABLE_URL)
    (sheet,) = parser.AddModels(url=SHEET_URL)
    world = plant.world_frame()
    plant.WeldFrames(world, plant.GetFrameByName("base_link", ur5))
    plant.WeldFrames(
        plant.GetFrameByName("tool0", ur5), plant.GetFrameByName("robotiq_base", gripper)
    )
    plant.WeldFrames(world, plant.GetFrameByName("table", table))
    plant.WeldFrames(world, plant.GetFrameByName("sheet_origin", sheet))
    plant.Finalize()
    # The sheet's joints fix its height; it must not touch the table (README).
    scene_graph.collision_filter_manager().Apply(
        CollisionFilterDeclaration().ExcludeBetween(
            GeometrySet(plant.GetCollisionGeometriesForBody(plant.GetBodyByName("table", table))),
            GeometrySet(plant.GetCollisionGeometriesForBody(plant.GetBodyByName("sheet", sheet))),
        )
    )
    return builder, plant, scene_graph, dict(ur5=ur5, gripper=gripper, table=table, sheet=sheet)


@pytest.mark.parametrize("url", ALL_URLS)
def test_model_parses_strictly_without_warnings(url, drake_warnings):
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlantSceneGraph(builder, TIME_STEP)  # so geometry is parsed too
    parser = make_parser(plant)
    parser.SetStrictParsing()  # would turn any warning into an exception
    models = parser.AddModels(url=url)
    assert len(models) == 1
    plant.Finalize()
    assert drake_warnings == []


def test_names_frames_and_actuators(drake_warnings):
    _, plant, _, m = _build()
    assert drake_warnings == []
    ur5, gripper, sheet = m["ur5"], m["gripper"], m["sheet"]
    assert plant.GetModelInstanceName(ur5) == "ur5"
    assert plant.GetModelInstanceName(gripper) == "robotiq_2f85"
    assert plant.GetModelInstanceName(m["table"]) == "table"
    assert plant.GetModelInstanceName(sheet) == "sheet"
    for link in ["base_link", "shoulder_link", "upper_arm_link", "forearm_link",
                 "wrist_1_link", "wrist_2_link", "wrist_3_link"]:
        plant.GetBodyByName(link, ur5)
    plant.GetFrameByName("tool0", ur5)
    for frame in ["grasp_frame", "camera_mount", "left_pad_surface", "right_pad_surface"]:
        plant.GetFrameByName(frame, gripper)
    plant.GetBodyByName("robotiq_base", gripper)
    plant.GetBodyByName("table", m["table"])
    plant.GetBodyByName("sheet", sheet)

    # UR5 joints: order of positions == order of actuators == UR5_JOINTS.
    ur5_actuators = [plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices(ur5)]
    assert [a.joint().name() for a in ur5_actuators] == UR5_JOINTS
    assert [a.name() for a in ur5_actuators] == [
        j.replace("_joint", "_actuator") for j in UR5_JOINTS
    ]
    for j, name in enumerate(UR5_JOINTS):
        assert plant.GetJointByName(name, ur5).position_start() == j
    assert all(a.has_controller() for a in ur5_actuators)
    assert [a.effort_limit() for a in ur5_actuators] == [150, 150, 150, 28, 28, 28]

    (g_act,) = [plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices(gripper)]
    assert g_act.name() == "left_finger_actuator"
    assert g_act.joint().name() == "left_finger_joint"
    assert g_act.has_controller() and g_act.effort_limit() == 470
    right = plant.GetJointByName("right_finger_joint", gripper)
    assert right.position_lower_limits()[0] == 0 and right.position_upper_limits()[0] == 0.0425
    assert plant.num_constraints() == 1  # the <mimic> coupler

    sheet_acts = [plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices(sheet)]
    assert [a.name() for a in sheet_acts] == ["sheet_x", "sheet_y", "sheet_yaw"]
    assert all(a.has_controller() for a in sheet_acts)

    # Sheet: (sheet_x, sheet_y, sheet_yaw) = 0 puts its centre at (0.5, 0) on the table.
    context = plant.CreateDefaultContext()
    sheet_body = plant.GetBodyByName("sheet", sheet)
    assert np.allclose(sheet_body.EvalPoseInWorld(context).translation(), [0.5, 0, 0])
    plant.SetPositions(context, sheet, [0.1, -0.05, 0.3])
    X_WS = sheet_body.EvalPoseInWorld(context)
    assert np.allclose(X_WS.translation(), [0.6, -0.05, 0])
    assert np.allclose(X_WS.rotation().ToRollPitchYaw().vector(), [0, 0, 0.3])


def test_grasp_and_camera_frames_and_width_equals_2q():
    from pydrake.geometry import Box

    builder, plant, scene_graph, m = _build()
    gripper = m["gripper"]
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    plant.SetPositions(plant_context, m["ur5"], UR5_HOME)

    base = plant.GetFrameByName("robotiq_base", gripper)
    X_BG = plant.GetFrameByName("grasp_frame", gripper).CalcPose(plant_context, base)
    assert np.allclose(X_BG.translation(), [0, 0, 0.135])
    assert np.allclose(X_BG.rotation().matrix(), np.eye(3))
    X_BC = plant.GetFrameByName("camera_mount", gripper).CalcPose(plant_context, base)
    assert np.allclose(X_BC.translation(), [0, -0.05, 0.02])
    assert np.allclose(X_BC.rotation().matrix(), np.eye(3))

    # Home: grasp frame 0.45 m in front, 0.30 m above the table, z pointing down.
    X_WG = plant.GetFrameByName("grasp_frame", gripper).CalcPoseInWorld(plant_context)
    assert np.allclose(X_WG.translation(), [0.45, 0.0, 0.30], atol=1e-3)
    assert X_WG.rotation().matrix()[:, 2] @ [0, 0, -1] > 0.9999

    # width == 2 q, from the pad collision boxes' inner faces.
    q = 0.03
    plant.SetPositions(plant_context, gripper, [q, q])
    query = scene_graph.get_query_output_port().Eval(scene_graph.GetMyContextFromRoot(context))
    inspector = query.inspector()
    X_WB = base.CalcPoseInWorld(plant_context)
    inner_x = {}
    for side, sign in [("left", +1), ("right", -1)]:
        body = plant.GetBodyByName(f"{side}_finger", gripper)
        (pad,) = [g for g in plant.GetCollisionGeometriesForBody(body)
                  if inspector.GetName(g).endswith(f"{side}_pad_collision")]
        box = inspector.GetShape(pad)
        assert isinstance(box, Box)
        assert np.allclose([box.width(), box.depth(), box.height()], [0.006, 0.022, 0.038])
        X_BP = X_WB.inverse() @ query.GetPoseInWorld(pad)
        assert np.allclose(X_BP.rotation().matrix(), np.eye(3))
        # Inner face: towards the grasp centre (+x for the left pad, -x for the right).
        inner_x[side] = X_BP.translation()[0] + sign * box.width() / 2
        assert abs(X_BP.translation()[2] - 0.135) < 1e-9  # pads centred on grasp_frame
    assert abs((inner_x["right"] - inner_x["left"]) - 2 * q) < 0.5e-3
    assert abs(inner_x["right"] + inner_x["left"]) < 1e-9  # symmetric about grasp_frame
    p_left = plant.GetFrameByName("left_pad_surface", gripper).CalcPose(plant_context, base)
    p_right = plant.GetFrameByName("right_pad_surface", gripper).CalcPose(plant_context, base)
    assert np.isclose(p_left.translation()[0], inner_x["left"])
    assert np.isclose(p_right.translation()[0], inner_x["right"])


def test_closed_loop_pd_hold_close_and_open():
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.primitives import ConstantVectorSource

    builder, plant, _, m = _build()
    ur5, gripper, sheet = m["ur5"], m["gripper"], m["sheet"]
    n_ur5 = len(UR5_JOINTS)
    ur5_target = builder.AddSystem(ConstantVectorSource(np.r_[UR5_HOME, np.zeros(n_ur5)]))
    gripper_target = builder.AddSystem(ConstantVectorSource(np.array([0.01, 0.0])))
    sheet_target = builder.AddSystem(ConstantVectorSource(np.zeros(6)))
    builder.Connect(ur5_target.get_output_port(), plant.get_desired_state_input_port(ur5))
    builder.Connect(gripper_target.get_output_port(), plant.get_desired_state_input_port(gripper))
    builder.Connect(sheet_target.get_output_port(), plant.get_desired_state_input_port(sheet))
    diagram = builder.Build()

    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyContextFromRoot(context)
    plant.SetPositions(plant_context, ur5, UR5_HOME)
    plant.SetPositions(plant_context, gripper, [0.0425, 0.0425])

    def width() -> float:
        q_left, q_right = plant.GetPositions(plant_context, gripper)
        assert abs(q_left - q_right) < 1e-3  # the coupler constraint holds
        return q_left + q_right

    simulator.AdvanceTo(1.0)
    assert np.max(np.abs(plant.GetPositions(plant_context, ur5) - UR5_HOME)) < 0.05
    assert abs(width() - 0.02) < 1e-3
    assert np.max(np.abs(plant.GetPositions(plant_context, sheet))) < 1e-3

    gripper_target.get_mutable_source_value(
        gripper_target.GetMyMutableContextFromRoot(context)
    ).SetFromVector([0.0425, 0.0])
    simulator.AdvanceTo(2.0)
    assert abs(width() - 0.085) < 1e-3
    assert np.max(np.abs(plant.GetPositions(plant_context, ur5) - UR5_HOME)) < 0.05


def test_gripper_is_invisible_to_the_vtk_camera():
    """The gripper's visuals accept only `no_such_renderer`: a wrist camera on
    `camera_mount` (renderer "vtk") sees past the fingers to the sheet on the table."""
    from pydrake.geometry import (ClippingRange, ColorRenderCamera, DepthRange,
                                  DepthRenderCamera, RenderCameraCore)
    from pydrake.math import RigidTransform
    from pydrake.systems.sensors import CameraInfo, RgbdSensor

    try:
        builder, plant, scene_graph, m = _build(with_renderer=True)
    except Exception as e:  # pragma: no cover - only where VTK cannot render
        pytest.skip(f"no VTK renderer here: {e}")
    gripper = m["gripper"]
    base_body = plant.GetBodyByName("robotiq_base", gripper)
    core = RenderCameraCore("vtk", CameraInfo(64, 48, np.pi / 2),
                            ClippingRange(0.005, 3.0), RigidTransform())
    sensor = builder.AddSystem(RgbdSensor(
        plant.GetBodyFrameIdOrThrow(base_body.index()),
        plant.GetFrameByName("camera_mount", gripper).GetFixedPoseInBodyFrame(),
        ColorRenderCamera(core), DepthRenderCamera(core, DepthRange(0.005, 2.9))))
    builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    plant.SetPositions(plant_context, m["ur5"], UR5_HOME)
    plant.SetPositions(plant_context, gripper, [0.02, 0.02])
    depth = sensor.depth_image_32F_output_port().Eval(
        sensor.GetMyContextFromRoot(context)).data.squeeze()
    seen = depth[np.isfinite(depth)]
    assert seen.size > 0
    # Camera 0.30 + 0.135 - 0.02 m above the table; the sheet top is 2 mm up.
    assert seen.min() > 0.40
