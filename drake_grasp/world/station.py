"""The grasping station: UR5 + Robotiq 2F-85 + two wrist depth cameras + table, sheet, objects.

`MakeGraspStation(scenario, scene, library)` returns a `GraspStation` whose `diagram`
is a Drake Diagram with named subsystems and exported ports:

Input ports:
    X_WG_desired: desired pose of the grasp frame G (RigidTransform) -> differential IK.
    gripper_command: [width_m, grip_force_n].
    sheet_desired_state: [x, y, yaw, vx, vy, wz] of the sheet under the objects.
Output ports:
    depth_image: post-processed wrist depth image (ImageDepth32F, metres).
    depth_image_raw: the renderer's depth image before noise and filling.
    label_image: the wrist camera's label image (ImageLabel16I).
    gpd_depth_image: the GPD sensor's depth image (ImageDepth32F, metres,
        `scenario.gpd`: 640x480 by default), post-processed with `scenario.gpd.noise`.
        With the default `fill_max_iterations` 0 no hole is filled: pixels with no
        reading (below the near clip, or beyond the far clip) come out as
        `gpd.depth_max_m`, like far ones.
    gpd_depth_image_raw: the GPD sensor's depth before noise and filling (0 below the
        near clip, +inf beyond the far clip).
    body_poses: every body's pose in the world (std::vector<RigidTransform>).
    gripper_state: [q_left, q_right, v_left, v_right]; the opening is q_left + q_right.
    arm_state: UR5 joint positions and velocities.
    plant_state: the full plant state.

Inside: MultibodyPlant + SceneGraph (hydroelastic with fallback, SAP-family solver),
the UR5 held by its in-plant PD plus gravity feed-forward, a
DifferentialInverseKinematicsIntegrator on a control plant (arm + lumped gripper), the
force-controlled gripper controller, the wrist RGB-D sensor (VTK) and its depth
post-processor, and the GPD baseline's sensor (`gpd_camera`, on the `gpd_camera_mount`
frame) with its own post-processor. Cameras render only when their outputs are
evaluated: nothing renders the 640x480 GPD image unless a policy asks for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydrake.common.eigen_geometry import AngleAxis
from pydrake.geometry import (
    ClippingRange,
    DepthRange,
    DepthRenderCamera,
    MakeRenderEngineVtk,
    RenderCameraCore,
    RenderEngineVtkParams,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import (
    DifferentialInverseKinematicsIntegrator,
    DifferentialInverseKinematicsParameters,
    InverseKinematics,
)
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlant
from pydrake.multibody.tree import SpatialInertia
from pydrake.solvers import Solve
from pydrake.systems.controllers import InverseDynamics
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import StateInterpolatorWithDiscreteDerivative
from pydrake.systems.sensors import CameraInfo, RgbdSensor

from drake_grasp.core.assets import make_parser
from drake_grasp.geometry.hand_model import topdown_rotation
from drake_grasp.core.native import load_llvm_users_first
from drake_grasp.objects import ObjectLibrary
from drake_grasp.config.physics import apply_hydroelastic_margin, sheet_collision, table_collision
from drake_grasp.config.scenario import Scenario
from drake_grasp.world.scene import (
    OBJECT_BODY_NAME,
    SceneSpec,
    add_scene_objects,
    set_object_poses,
)
from drake_grasp.world.table import add_table_and_sheet
from drake_grasp.systems.depth import DepthPostProcessor
from drake_grasp.systems.gripper import GripperController

UR5_URI = "package://drake_grasp/ur5/ur5.urdf"
GRIPPER_URI = "package://drake_grasp/robotiq_2f85/robotiq_2f85.urdf"
RENDERER_NAME = "vtk"
GPD_CAMERA_FRAME = "gpd_camera_mount"
# The GPD sensor's noise comes from its own random stream (`sensing.frame_rng`'s
# `stream`), so it never repeats the wrist camera's noise of the same trial.
GPD_NOISE_STREAM = 1
# Frame rate of the GPD sensor (Structure IO: 30 Hz); selects its noise frame.
GPD_CAMERA_FPS = 30.0
# Fingertips reach this far past the grasp frame along the approach axis
# (models/robotiq_2f85/README.md), and the start keeps this much air below them.
FINGERTIP_BELOW_GRASP_M = 0.025
START_CLEARANCE_M = 0.03
# Each finger joint's position with the hand open (85 mm between the pads).
OPEN_FINGER_Q_M = 0.0425
# Before an episode the wrist camera looks at the scene from this height above the table
# (`survey_top_z`); the start is raised over whatever it sees standing taller than the
# paper's start clears. The open fingertips are then 0.43 m above the table, above every
# object a scene can hold (`tests/test_station.py` checks the library against it).
SURVEY_CAMERA_HEIGHT_M = 0.6
# A UR5 configuration with the tool pointing down over the workspace, elbow up; the
# start pose is solved by IK from here.
Q_HOME = np.array([-0.245, -1.6894, 1.6738, -1.5552, -1.5708, -0.245 + np.pi / 2])


@dataclass
class GraspStation:
    """A built station: the Diagram plus handles tests and runners need."""

    diagram: object
    plant: MultibodyPlant
    scene_graph: object
    arm: object
    gripper: object
    sheet: object
    object_instances: list
    scene: SceneSpec
    q_start: np.ndarray
    X_WG_start: RigidTransform
    X_BG: RigidTransform  # grasp frame in the gripper base body
    X_GC: RigidTransform  # camera in the grasp frame
    X_GC_gpd: RigidTransform  # the GPD sensor in the grasp frame
    # Where both cameras really sit in the frame the policies believe (X_GC, X_GC_gpd):
    # identity unless `scenario.calibration` sets a mount error (`camera_mount_error`).
    X_CC_actual: RigidTransform = field(default_factory=RigidTransform)
    # Helper plants must outlive the diagram (InverseDynamics does not keep them).
    _keep_alive: list = field(default_factory=list)

    def object_body(self, i: int):
        return self.plant.GetBodyByName(OBJECT_BODY_NAME, self.object_instances[i])

    def gripper_body(self):
        return self.plant.GetFrameByName("grasp_frame", self.gripper).body()

    def set_initial_state(self, station_context) -> None:
        """Arm at the start configuration, gripper open, objects at their scene poses.

        Args:
            station_context (Context): this station diagram's Context (use
                `diagram.GetMyMutableContextFromRoot(root)` when it is nested).
        """
        def sub(name):
            system = self.diagram.GetSubsystemByName(name)
            return system, self.diagram.GetMutableSubsystemContext(system, station_context)

        plant, plant_context = sub("plant")
        plant.SetPositions(plant_context, self.arm, self.q_start)
        plant.SetVelocities(plant_context, self.arm, np.zeros(6))
        nq = plant.num_positions(self.gripper)
        plant.SetPositions(plant_context, self.gripper, np.full(nq, OPEN_FINGER_Q_M))
        set_object_poses(plant, plant_context, self.scene, self.object_instances)
        if self.diagram.HasSubsystemNamed("diff_ik"):  # absent with arm_position_command
            ik, ik_context = sub("diff_ik")
            ik.SetPositions(ik_context, self.q_start)
        interp, interp_context = sub("arm_desired_state")
        interp.set_initial_position(interp_context, self.q_start)
        grip, grip_context = sub("gripper_controller")
        grip.set_width(grip_context, 0.085)


def _add_robot(plant: MultibodyPlant):
    parser = make_parser(plant)
    (arm,) = parser.AddModels(url=UR5_URI)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("base_link", arm))
    (gripper,) = parser.AddModels(url=GRIPPER_URI)
    plant.WeldFrames(plant.GetFrameByName("tool0", arm),
                     plant.GetFrameByName("robotiq_base", gripper))
    return arm, gripper


def _gripper_offsets(plant: MultibodyPlant, gripper) -> tuple[RigidTransform, RigidTransform, RigidTransform]:
    """X_BG (grasp frame in the gripper's base body), X_TG (in tool0), X_GC (camera in G)."""
    context = plant.CreateDefaultContext()
    base = plant.GetFrameByName("robotiq_base", gripper)
    G = plant.GetFrameByName("grasp_frame", gripper)
    C = plant.GetFrameByName("camera_mount", gripper)
    X_BG = G.CalcPose(context, G.body().body_frame())
    X_TG = G.CalcPose(context, base)
    X_GC = C.CalcPose(context, G)
    return X_BG, X_TG, X_GC


def gripper_frame_offsets() -> tuple[RigidTransform, RigidTransform, RigidTransform]:
    """(X_BG, X_TG, X_GC) read from the gripper model alone (no robot, no scene)."""
    plant = MultibodyPlant(0.0)
    (gripper,) = make_parser(plant).AddModels(url=GRIPPER_URI)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("robotiq_base", gripper))
    plant.Finalize()
    return _gripper_offsets(plant, gripper)


def _frame_in_grasp_frame(plant: MultibodyPlant, gripper, name: str) -> RigidTransform:
    context = plant.CreateDefaultContext()
    return plant.GetFrameByName(name, gripper).CalcPose(
        context, plant.GetFrameByName("grasp_frame", gripper))


def gpd_camera_offset() -> RigidTransform:
    """X_GC_gpd: the GPD sensor (`gpd_camera_mount`) in the grasp frame, read from the
    gripper model alone."""
    plant = MultibodyPlant(0.0)
    (gripper,) = make_parser(plant).AddModels(url=GRIPPER_URI)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("robotiq_base", gripper))
    plant.Finalize()
    return _frame_in_grasp_frame(plant, gripper, GPD_CAMERA_FRAME)


def arm_control_plant(plant: MultibodyPlant, arm, gripper) -> MultibodyPlant:
    """The arm's control plant (`make_control_plant`) for a finalized plant holding the
    UR5 and the 2F-85 (`_add_robot`): the gripper's bodies lumped onto tool0."""
    _, X_TG, _ = _gripper_offsets(plant, gripper)
    M_T = plant.CalcSpatialInertia(plant.CreateDefaultContext(),
                                   plant.GetFrameByName("tool0", arm),
                                   plant.GetBodyIndices(gripper))
    return make_control_plant(M_T, X_TG)


# Random stream of the camera-mount error's direction (`default_rng([seed, 83])`).
MOUNT_ERROR_STREAM = 83


def camera_mount_error(calibration, seed: int) -> RigidTransform:
    """X_CC': where the camera really sits (C') in the frame the policy believes (C),
    for a `scenario.CalibrationConfig`: a translation of `camera_translation_error_m`
    along, and a rotation of `camera_rotation_error_deg` about, two directions drawn
    uniformly on the sphere from the trial's seed. Identity when both are 0."""
    rng = np.random.default_rng([int(seed), MOUNT_ERROR_STREAM])
    u = rng.normal(size=3)
    w = rng.normal(size=3)
    u /= np.linalg.norm(u)
    w /= np.linalg.norm(w)
    R = RotationMatrix(AngleAxis(np.deg2rad(calibration.camera_rotation_error_deg), w))
    return RigidTransform(R, calibration.camera_translation_error_m * u)


def make_depth_camera(cam, renderer_name: str = RENDERER_NAME) -> DepthRenderCamera:
    """A depth camera model from a `WristCameraConfig` or a `GpdConfig` (anything with
    width, height, fov_y_deg, depth_min_m and depth_max_m)."""
    core = RenderCameraCore(
        renderer_name,
        CameraInfo(width=cam.width, height=cam.height, fov_y=np.deg2rad(cam.fov_y_deg)),
        ClippingRange(0.5 * cam.depth_min_m, 2.0 * cam.depth_max_m), RigidTransform())
    return DepthRenderCamera(core, DepthRange(cam.depth_min_m, cam.depth_max_m))


def make_control_plant(gripper_spatial_inertia_T: SpatialInertia, X_TG: RigidTransform):
    """UR5 with the gripper lumped into one rigid body on tool0, plus the grasp frame.

    Used by differential IK (6 positions only) and gravity compensation.
    """
    from pydrake.multibody.tree import FixedOffsetFrame

    plant = MultibodyPlant(0.0)
    parser = make_parser(plant)
    (arm,) = parser.AddModels(url=UR5_URI)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("base_link", arm))
    tool0 = plant.GetFrameByName("tool0", arm)
    lumped = plant.AddRigidBody("gripper_lumped", arm, gripper_spatial_inertia_T)
    plant.WeldFrames(tool0, lumped.body_frame())
    plant.AddFrame(FixedOffsetFrame("grasp_frame", tool0, X_TG))
    plant.Finalize()
    return plant


def make_arm_diff_ik(scenario: Scenario, control_plant: MultibodyPlant):
    """The arm's DifferentialInverseKinematicsIntegrator: drives the control plant's
    `grasp_frame` to `X_AE_desired` (world frame) every `arm.ik_time_step_s`, within the
    joint position limits, `arm.joint_velocity_fraction` of the velocity limits and the
    TCP speed limits, centred on `Q_HOME`; no measured-state feedback. The station's
    `diff_ik`, and a controller process's (`drake_grasp.evaluation.bridge`)."""
    ik_params = DifferentialInverseKinematicsParameters(6, 6)
    ik_params.set_nominal_joint_position(Q_HOME)
    ik_params.set_joint_centering_gain(0.05 * np.eye(6))
    lower = control_plant.GetPositionLowerLimits()
    upper = control_plant.GetPositionUpperLimits()
    ik_params.set_joint_position_limits((lower, upper))
    v_max = scenario.arm.joint_velocity_fraction * control_plant.GetVelocityUpperLimits()
    ik_params.set_joint_velocity_limits((-v_max, v_max))
    v_tcp = scenario.arm.max_tcp_speed_m_s
    ik_params.set_end_effector_translational_velocity_limits([-v_tcp] * 3, [v_tcp] * 3)
    ik_params.set_end_effector_angular_speed_limit(scenario.arm.max_tcp_angular_speed_rad_s)
    return DifferentialInverseKinematicsIntegrator(
        control_plant, control_plant.world_frame(), control_plant.GetFrameByName("grasp_frame"),
        scenario.arm.ik_time_step_s, ik_params)


def topdown_pose(xy, height: float, yaw: float = 0.0) -> RigidTransform:
    """Grasp-frame pose at (x, y, height) approaching straight down."""
    return RigidTransform(RotationMatrix(topdown_rotation(yaw)), [xy[0], xy[1], height])


def solve_start_configuration(control_plant: MultibodyPlant, X_WG: RigidTransform,
                              q_guess: np.ndarray = Q_HOME, *, tries: int = 8) -> np.ndarray:
    """Joint angles that put the grasp frame at X_WG (within 0.1 mm, 1 mrad).

    The solver is local: from `q_guess` alone it failed for a reachable pose 7 mm above
    the usual start, and converged for others to far-off branches (an elbow at 4.5 rad).
    So it starts from `q_guess` and from `tries - 1` perturbations of it (up to 0.2 rad per
    joint, fixed seed) and returns the converged solution nearest `q_guess`.

    Raises:
        RuntimeError: no start converged.
    """
    ik = InverseKinematics(control_plant)
    G = control_plant.GetFrameByName("grasp_frame")
    p = X_WG.translation()
    ik.AddPositionConstraint(G, [0, 0, 0], control_plant.world_frame(), p - 1e-4, p + 1e-4)
    ik.AddOrientationConstraint(G, RotationMatrix(), control_plant.world_frame(),
                                X_WG.rotation(), 1e-3)
    prog = ik.get_mutable_prog()
    prog.AddQuadraticErrorCost(np.eye(6), q_guess, ik.q())
    rng = np.random.default_rng(0)
    best = None
    for k in range(max(1, int(tries))):
        start = q_guess if k == 0 else q_guess + rng.uniform(-0.2, 0.2, size=len(q_guess))
        prog.SetInitialGuess(ik.q(), start)
        result = Solve(prog)
        if result.is_success():
            q = result.GetSolution(ik.q())
            if best is None or np.linalg.norm(q - q_guess) < np.linalg.norm(best - q_guess):
                best = q
    if best is not None:
        return best
    raise RuntimeError(f"no UR5 configuration reaches the start pose {p} (IK failed from "
                       f"{max(1, int(tries))} starts)")


def survey_top_z(diagram, plant, arm, gripper, objects, scene: SceneSpec, control_plant,
                 X_GC: RigidTransform, *, depth_max_m: float) -> float:
    """The scene's top as the wrist camera sees it from the survey pose [m above the table].

    The arm is put at the survey pose (the camera `SURVEY_CAMERA_HEIGHT_M` above the scene
    centre, looking straight down, fingers open), the objects at their scene poses, and the
    station's `depth_image` (post-processed, frame 0) is read: the top is the survey height
    less the nearest valid reading (0 when nothing but the table is seen). The camera's
    height is the one the robot believes (its mount model), as a robot would compute it.
    """
    X_WG = topdown_pose(scene.center_xy_m, SURVEY_CAMERA_HEIGHT_M + X_GC.translation()[2])
    q = solve_start_configuration(control_plant, X_WG)
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    plant.SetPositions(plant_context, arm, q)
    plant.SetPositions(plant_context, gripper, np.full(plant.num_positions(gripper), OPEN_FINGER_Q_M))
    set_object_poses(plant, plant_context, scene, objects)
    depth = np.asarray(diagram.GetOutputPort("depth_image").Eval(context).data[:, :, 0])
    valid = np.isfinite(depth) & (depth > 0.0) & (depth < depth_max_m)
    if not valid.any():
        return 0.0
    return max(0.0, SURVEY_CAMERA_HEIGHT_M - float(depth[valid].min()))


def start_camera_height(scenario: Scenario, top_z: float, X_GC: RigidTransform) -> float:
    """The wrist camera's start height [m]: `arm.start_camera_height_m`, raised so the open
    fingertips keep `START_CLEARANCE_M` above a scene whose top is `top_z`."""
    clearance = -X_GC.translation()[2] + FINGERTIP_BELOW_GRASP_M + START_CLEARANCE_M
    if top_z + clearance > SURVEY_CAMERA_HEIGHT_M:
        raise ValueError(
            f"scene: the survey image sees an object {top_z:.3f} m above the table; the open "
            f"fingertips need {clearance:.3f} m above it, more than the survey height "
            f"{SURVEY_CAMERA_HEIGHT_M} m allows (world/station.py SURVEY_CAMERA_HEIGHT_M)")
    return max(scenario.arm.start_camera_height_m, top_z + clearance)


def _add_cameras(builder, plant, scene_graph, gripper, scenario: Scenario):
    """The wrist depth camera and the GPD baseline's sensor, each with its depth
    post-processing, and their exported images. Returns X_CC_actual, the calibration
    error of the camera mount."""
    # --- wrist camera ----------------------------------------------------------------
    cam = scenario.camera
    # Before the first render: Mesa's LLVM must not shadow triton's (drake_grasp.core.native).
    load_llvm_users_first()
    scene_graph.AddRenderer(RENDERER_NAME, MakeRenderEngineVtk(RenderEngineVtkParams()))
    camera_frame = plant.GetFrameByName("camera_mount", gripper)
    # The camera where it really is: the model's mount, off by the calibration error.
    X_CC_actual = camera_mount_error(scenario.calibration, scenario.seed)
    X_PC = camera_frame.GetFixedPoseInBodyFrame()
    gpd_frame = plant.GetFrameByName(GPD_CAMERA_FRAME, gripper)
    X_PC_gpd = gpd_frame.GetFixedPoseInBodyFrame()
    if scenario.calibration.active():
        X_PC = X_PC @ X_CC_actual
        X_PC_gpd = X_PC_gpd @ X_CC_actual
    depth_camera = make_depth_camera(cam)
    sensor = builder.AddNamedSystem("wrist_camera", RgbdSensor(
        plant.GetBodyFrameIdOrThrow(camera_frame.body().index()), X_PC, depth_camera))
    builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
    post = builder.AddNamedSystem("depth_postprocessor", DepthPostProcessor(
        scenario.depth_noise, width=cam.width, height=cam.height,
        far_value_m=cam.depth_max_m, frame_period_s=1.0 / cam.fps, seed=scenario.seed))
    builder.Connect(sensor.depth_image_32F_output_port(), post.GetInputPort("depth_image_32f"))
    builder.ExportOutput(post.GetOutputPort("depth_image"), "depth_image")
    builder.ExportOutput(sensor.depth_image_32F_output_port(), "depth_image_raw")
    builder.ExportOutput(sensor.label_image_output_port(), "label_image")

    # --- the GPD baseline's sensor (a Structure IO in the paper) ------------------------
    g = scenario.gpd
    gpd_sensor = builder.AddNamedSystem("gpd_camera", RgbdSensor(
        plant.GetBodyFrameIdOrThrow(gpd_frame.body().index()),
        X_PC_gpd, make_depth_camera(g)))
    builder.Connect(scene_graph.get_query_output_port(), gpd_sensor.query_object_input_port())
    gpd_post = builder.AddNamedSystem("gpd_depth_postprocessor", DepthPostProcessor(
        g.noise, width=g.width, height=g.height, far_value_m=g.depth_max_m,
        frame_period_s=1.0 / GPD_CAMERA_FPS, seed=scenario.seed, stream=GPD_NOISE_STREAM))
    builder.Connect(gpd_sensor.depth_image_32F_output_port(),
                    gpd_post.GetInputPort("depth_image_32f"))
    builder.ExportOutput(gpd_post.GetOutputPort("depth_image"), "gpd_depth_image")
    builder.ExportOutput(gpd_sensor.depth_image_32F_output_port(), "gpd_depth_image_raw")
    return X_CC_actual


def MakeGraspStation(scenario: Scenario, scene: SceneSpec, library: ObjectLibrary, *,
                     arm_input: str = "X_WG_desired") -> GraspStation:
    """Builds the station Diagram for a (settled) scene. See the module docstring.

    Args:
        scenario: plant, camera, GPD sensor, noise, gripper and arm settings.
        scene: the objects and where they rest (`make_scene`).
        library: the object library the scene's ids come from.
        arm_input: "X_WG_desired" (the station's own differential IK takes a grasp-frame
            pose) or "arm_position_command" (no `diff_ik`: the input port
            `arm_position_command` takes the 6 UR5 joint positions, as a robot driver
            does; the controller process of `drake_grasp.evaluation.bridge` runs the IK).

    Returns:
        A `GraspStation`: `diagram` (inputs `X_WG_desired`, `gripper_command`,
        `sheet_desired_state`; outputs `depth_image`, `gripper_state`, `arm_state`, ...:
        see `drake_grasp.api`) with the plant, the start pose and the camera offsets.
        Add `diagram` to a `DiagramBuilder`, then call `set_initial_state` on its Context.
    """
    if arm_input not in ("X_WG_desired", "arm_position_command"):
        raise ValueError(f"arm_input: expected 'X_WG_desired' or 'arm_position_command', "
                         f"got {arm_input!r}")
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(scenario.plant, builder)
    plant.set_name("plant")
    scene_graph.set_name("scene_graph")
    arm, gripper = _add_robot(plant)
    _, sheet = add_table_and_sheet(plant, scene_graph, scene.center_xy_m,
                                   sheet_collision=sheet_collision(
                                       scenario.physics,
                                       sheet_moves=scenario.sheet_moves),
                                   table_collision=table_collision(scenario.physics))
    objects = add_scene_objects(plant, scene, library)
    plant.Finalize()
    apply_hydroelastic_margin(plant, scene_graph, scenario.physics.hydroelastic_margin_m,
                              [gripper])

    X_BG, X_TG, X_GC = _gripper_offsets(plant, gripper)
    control_plant = arm_control_plant(plant, arm, gripper)

    # --- arm: differential IK -> desired state for the in-plant PD + gravity FF -----
    interp = builder.AddNamedSystem("arm_desired_state", StateInterpolatorWithDiscreteDerivative(
        6, scenario.arm.ik_time_step_s, suppress_initial_transient=True))
    if arm_input == "X_WG_desired":
        diff_ik = builder.AddNamedSystem("diff_ik", make_arm_diff_ik(scenario, control_plant))
        builder.Connect(diff_ik.GetOutputPort("joint_positions"), interp.get_input_port())
        builder.ExportInput(diff_ik.GetInputPort("X_AE_desired"), "X_WG_desired")
    else:  # the joint positions come from outside (a controller process, drake_grasp.evaluation.bridge)
        builder.ExportInput(interp.get_input_port(), "arm_position_command")
    builder.Connect(interp.get_output_port(), plant.get_desired_state_input_port(arm))
    gravity = builder.AddNamedSystem("gravity_compensation", InverseDynamics(
        control_plant, InverseDynamics.InverseDynamicsMode.kGravityCompensation))
    builder.Connect(plant.get_state_output_port(arm), gravity.get_input_port_estimated_state())
    builder.Connect(gravity.get_output_port_generalized_force(),
                    plant.get_actuation_input_port(arm))

    # --- gripper -------------------------------------------------------------------
    finger = plant.GetJointActuatorByName("left_finger_actuator", gripper)
    kp = finger.get_controller_gains().p
    grip = builder.AddNamedSystem("gripper_controller", GripperController(
        kp=kp, closing_speed_m_s=scenario.gripper.closing_speed_m_s,
        initial_width_m=scenario.gripper.open_width_m, time_step=plant.time_step(),
        force_mode=scenario.gripper.force_mode))
    builder.Connect(plant.get_state_output_port(gripper), grip.GetInputPort("gripper_state"))
    builder.Connect(grip.GetOutputPort("desired_state"), plant.get_desired_state_input_port(gripper))
    builder.ExportInput(grip.GetInputPort("gripper_command"), "gripper_command")

    # --- sheet -----------------------------------------------------------------------
    builder.ExportInput(plant.get_desired_state_input_port(sheet), "sheet_desired_state")

    X_CC_actual = _add_cameras(builder, plant, scene_graph, gripper, scenario)

    # --- measurements ----------------------------------------------------------------
    builder.ExportOutput(plant.get_body_poses_output_port(), "body_poses")
    builder.ExportOutput(plant.get_state_output_port(gripper), "gripper_state")
    builder.ExportOutput(plant.get_state_output_port(arm), "arm_state")
    builder.ExportOutput(plant.get_state_output_port(), "plant_state")
    builder.ExportOutput(scene_graph.get_query_output_port(), "query_object")
    builder.ExportOutput(plant.get_contact_results_output_port(), "contact_results")

    diagram = builder.Build()
    diagram.set_name("grasp_station")

    # The paper starts the camera 0.3 m above the table; a standing object taller than
    # the open fingers' reach at that height raises the start so nothing touches. How
    # tall the scene is comes from the wrist camera's survey image, not the true scene.
    top_z = survey_top_z(diagram, plant, arm, gripper, objects, scene, control_plant, X_GC,
                         depth_max_m=scenario.camera.depth_max_m)
    start_camera = start_camera_height(scenario, top_z, X_GC)
    X_WG_start = topdown_pose(scene.center_xy_m, start_camera + X_GC.translation()[2])
    q_start = solve_start_configuration(control_plant, X_WG_start)
    return GraspStation(
        diagram=diagram, plant=plant, scene_graph=scene_graph, arm=arm, gripper=gripper,
        sheet=sheet, object_instances=objects, scene=scene, q_start=q_start,
        X_WG_start=X_WG_start, X_BG=X_BG, X_GC=X_GC,
        X_GC_gpd=_frame_in_grasp_frame(plant, gripper, GPD_CAMERA_FRAME),
        X_CC_actual=X_CC_actual, _keep_alive=[control_plant],
    )
