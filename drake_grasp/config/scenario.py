"""Typed configuration of a grasp episode, loaded from `diagrams/*.scenarios.yaml`.

Every tunable of the station lives in one of these dataclasses. Files are read with
Drake's `yaml_load_typed`, so an unknown (e.g. misspelled) key is an error, and the
resolved scenario is written beside every output with `yaml_dump_typed`.
"""


import copy
import dataclasses
import difflib
import json
import math
import numbers
import typing
from dataclasses import dataclass, field

# No `from __future__ import annotations` here: yaml_load_typed reads the field types
# at run time and cannot resolve string annotations.
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.multibody.plant import MultibodyPlantConfig

from drake_grasp.core.assets import diagrams_dir
from drake_grasp.config.policy_spec import is_policy_spec, parse_policy_spec
from drake_grasp.geometry.sensing import DepthNoiseConfig

DEFAULT_SCENARIO_FILE = "default.scenarios.yaml"
SCENE_KINDS = ("isolation", "random", "clutter")
POLICIES = ("scripted", "ctr", "gpd", "gpd-geometric", "cnn-only", "cnn-ctr", "init")
NOISE_KINDS = ("none", "gaussian", "offset")
DISTURBANCE_KINDS = ("none", "shift", "moving")


def _default_plant() -> MultibodyPlantConfig:
    # SAP-family solver (lagged): needed for in-plant PD gains and the gripper's
    # mimic coupler constraint; hydroelastic pads/objects decide grasp success.
    return MultibodyPlantConfig(
        time_step=PHYSICS_PROFILES[DEFAULT_PHYSICS_PROFILE]["plant.time_step"],
        contact_model="hydroelastic_with_fallback",
        discrete_contact_approximation="lagged",
    )


@dataclass
class WristCameraConfig:
    """The wrist depth camera (the paper: 64x64 depth; Intel SR300 on the robot)."""

    width: int = 64
    height: int = 64
    # SR300 depth field of view is about 55 deg vertical (Intel datasheet).
    fov_y_deg: float = 55.0
    # Depth range [m]: readings below `depth_min_m` come back invalid (0), beyond
    # `depth_max_m` come back "far". 5 cm lets the 14 cm stop rule be seen.
    depth_min_m: float = 0.05
    depth_max_m: float = 1.5
    # Frame rate of recorded pictures in demos [Hz].
    fps: float = 10.0


def _structure_noise() -> DepthNoiseConfig:
    # Off by default, like the wrist camera's (both policies see noiseless renders unless
    # a scenario turns noise on); when on, the Kinect-v1 axial model of Nguyen et al.
    # (the Structure IO is a PrimeSense-type structured-light sensor of the same kind).
    # No hole filling: GPD works on the point cloud and drops invalid pixels.
    return DepthNoiseConfig(enabled=False, fill_max_iterations=0)


@dataclass
class GpdConfig:
    """The GPD baseline: its depth sensor, viewpoint and learned grasp classifier.

    The paper runs GPD on a point cloud from a Structure IO on the wrist (640x480 depth,
    about 58 x 45 degrees field of view, working range from about 0.4 m), taken once with
    the hand moved to a fixed pose above the table, pointing down (Viereck et al. 2017,
    Section 6). `drake_grasp.policies.gpd` is the pipeline.
    """

    # Structure IO depth stream (Occipital datasheet: VGA 640x480, 58 deg H x 45 deg V).
    width: int = 640
    height: int = 480
    fov_y_deg: float = 45.0
    depth_min_m: float = 0.4
    depth_max_m: float = 3.5
    noise: DepthNoiseConfig = field(default_factory=_structure_noise)
    # The viewpoint: this camera this high above the table over the scene centre [m].
    # Nearer than `depth_min_m` the sensor reads nothing, so it is blind above
    # 0.68 - 0.4 = 0.28 m: an upright hammer_000 (0.283 m) shows all but its top 3 mm (at
    # 0.6 m it lost the top 8 cm, and GPD planned grasps on the cut). 0.68 m is about as
    # high as the UR5 takes this camera over the scene centre: at 0.70 m the arm's
    # differential IK stalls on the way. The view spans about 0.75 x 0.56 m of table.
    view_camera_height_m: float = 0.68
    # Time the hand rests at the viewpoint before the image is taken [s].
    view_settle_s: float = 0.5
    # Largest angle between a grasp's approach and straight down [deg].
    approach_max_tilt_deg: float = 30.0
    # Classifier weights; "" = the shipped models/gpd/weights.safetensors.
    weights: str = ""
    # True: when no candidate reaches the classifier's threshold, take the best-ranked
    # one anyway (`gpd_ranking.Selection.fallback`) instead of reporting no detection. On by
    # default: without it GPD closed on nothing in 8 of its 10 failures in clutter and
    # grasped 89.7% there, the paper's GPD 94.8% (README, *Remembering failed grasps;
    # GPD's fallback*); false is the strict-threshold GPD of the earlier records.
    fallback_best: bool = True


# `GripperConfig.force_mode`'s values (`systems.gripper.gripper_pd_target`).
GRIP_FORCE_MODES = ("constant", "limit")


@dataclass
class GripperConfig:
    """Robotiq 2F-85 command defaults (datasheet: 20-235 N, 20-150 mm/s)."""

    # Normal force each pad presses on the object [N].
    grip_force_n: float = 60.0
    # "constant": a finger blocked by the object presses with `grip_force_n` (the
    # 2F-85's force control); "limit": `grip_force_n` only caps the squeeze, which is
    # then kp (q - width/2) / 2 per pad, well below it on narrow objects (what every
    # result before this field existed ran with). `systems.gripper.gripper_pd_target`.
    force_mode: str = "constant"
    # Rate at which the commanded opening changes [m/s].
    closing_speed_m_s: float = 0.1
    # Opening commanded while approaching [m] (85 mm stroke).
    open_width_m: float = 0.085


@dataclass
class ArmConfig:
    """UR5 start configuration and differential-IK limits."""

    # Height of the wrist camera above the table at the start [m] (the paper: 0.3 m).
    start_camera_height_m: float = 0.3
    # Rate of the differential IK integrator [s].
    ik_time_step_s: float = 0.005
    # Tool speed limits for differential IK.
    max_tcp_speed_m_s: float = 0.5
    max_tcp_angular_speed_rad_s: float = 2.0
    # Fraction of UR5 joint velocity limits (pi rad/s) the IK may use.
    joint_velocity_fraction: float = 0.5


@dataclass
class SceneConfig:
    """What is on the table; see `drake_grasp.world.scene`."""

    kind: str = "isolation"
    # Object library split to draw from ("train", "test" or "" for all).
    split: str = "test"
    # Fixed object ids; empty -> drawn from the library with the seed.
    object_ids: list[str] = field(default_factory=list)
    # Isolation: "lying", "upright" or "any" (3:1 lying:upright as in the paper).
    pose: str = "any"
    # Random scenes: number of objects drawn uniformly in [min, max].
    num_objects_min: int = 1
    num_objects_max: int = 5
    # Clutter: number of objects poured into a pile, and how: "column" drops them from a
    # column (each above the last), "sequential" releases them one at a time just above
    # the pile (`scene.pour_scene`).
    clutter_objects: int = 5
    pour: str = "column"
    # Centre of the workspace on the table [m] and half size of the placement square.
    center_xy_m: list[float] = field(default_factory=lambda: [0.5, 0.0])
    region_half_extent_m: float = 0.08
    # Settling: simulate until every object is at rest by this speed, at most this long.
    settle_speed_tol_m_s: float = 0.005
    settle_max_time_s: float = 4.0
    # How rest is judged (`scene.settle_world`): "speed" (every object slower than the
    # tolerance at one instant) or "verified" (rotation damped while settling, rest judged
    # by displacement over 0.2 s and checked without the damping). The clutter scenarios
    # use "verified": with "speed" 9 of 10 sampled 10-object piles were still moving
    # when settling stopped (`analysis/clutter_pour.py settle`).
    settle: str = "speed"


@dataclass
class ScriptedGraspConfig:
    """Timing and geometry of the predefined grasp motion."""

    approach_time_s: float = 1.5
    pregrasp_height_m: float = 0.08
    descend_time_s: float = 1.0
    # Maximum time the fingers are given to close [s].
    close_time_s: float = 1.0
    lift_height_m: float = 0.15
    lift_time_s: float = 1.5
    hold_time_s: float = 1.0
    # Pads reach this far below the object's top [m] (capped by the table clearance).
    grasp_depth_below_top_m: float = 0.025
    # The scripted grasp (planned on the object model) keeps its centre at least this far
    # above the table [m]: 25 mm puts the fingertips (19 mm below the centre) 4 mm above
    # the sheet's top (2 mm), the margin the depth-image grasps keep
    # (`controller.support_margin_m`); 20 mm had them 1 mm below it.
    min_grasp_height_m: float = 0.025


# The paper's two settings of the closed-loop controller (Viereck, ten Pas, Saenko, Platt,
# CoRL 2017), as named profiles of `ControllerConfig` (`controller.profile`):
#
# sim, Section 5 (simulation, Figure 5): "The initial camera position is set to 0.3 m
#   above the table. At each iteration the camera height is reduced by a constant step
#   until height 0.15 m is reached. We run the controller for a total of 75 iterations,
#   using r=0.2 as the step ratio to a target pose". (z steps of (start - end) / 75.)
# robot, Section 6 (the UR5, Table 1): "we run the controller with a step ratio of r=0.5
#   and a z step size of 1cm. [...] The controller runs until the depth data indicates
#   that an object is within 14 cm distance from the sensor or the robot hand is too
#   close to the table." Here "too close to the table" is the camera at 0.15 m (the open
#   fingertips then 1 cm above the table), and the iteration budget is only a safety cap:
#   from any start height below 0.65 m the 1 cm steps reach the table first.
CONTROLLER_PROFILES: dict[str, dict[str, float]] = {
    "sim": {"step_ratio": 0.2, "iterations": 75, "z_step_m": 0.0,
            "end_camera_height_m": 0.15, "stop_distance_m": 0.14},
    "robot": {"step_ratio": 0.5, "iterations": 50, "z_step_m": 0.01,
              "end_camera_height_m": 0.15, "stop_distance_m": 0.14},
}


@dataclass
class ControllerConfig:
    """The paper's closed-loop controller (Algorithm 1) and the learned evaluator.

    `profile` names one of the paper's two settings (`CONTROLLER_PROFILES`): "sim" (the
    default; camera from 0.3 m to 0.15 m above the table in 75 equal z steps, each
    iteration moving a fraction r = 0.2 of the way to the best candidate) or "robot"
    (r = 0.5, 1 cm z steps until an object is within 14 cm of the sensor or the hand is
    at its lowest height). A profile given in a scenario file or `--scenario-text` sets
    `step_ratio`, `iterations`, `z_step_m`, `end_camera_height_m` and `stop_distance_m`,
    except those given beside it in the same `controller:` mapping.
    """

    # One of CONTROLLER_PROFILES; the settings below are the "sim" profile's.
    profile: str = "sim"
    # Control period [s] (the robot's loop ran at about 5 Hz).
    period_s: float = 0.1
    # Iteration budget (the "sim" profile's stop rule; a safety cap for "robot").
    iterations: int = 75
    step_ratio: float = 0.2
    # Camera step down per iteration [m]; 0: (start - end) / iterations, the start height
    # being `arm.start_camera_height_m` (possibly raised over standing objects).
    z_step_m: float = 0.0
    # Camera height above the table at the last iteration [m]: the hand's lowest height.
    end_camera_height_m: float = 0.15
    # Stop when the depth image shows an object this close to the sensor [m].
    stop_distance_m: float = 0.14
    # ... looking at a square window around the grasp axis as the image shows it at
    # `stop_distance_m` (the camera is beside the axis): half side [m] at that distance
    # (0.02 m: about 9 px of the 64 px image, the pads' closing strip).
    stop_window_half_m: float = 0.02
    # Once the stop rule fires (an object within `stop_distance_m`, or the hand at its
    # lowest height), keep servoing in (x, y, theta) at that height for up to this many
    # iterations before the grasp, as the paper's Algorithm 1 repeats "until the
    # controller converges" (0: grasp at once, the paper's robot runs). The hand rises
    # when a taller surface comes under the grasp axis, never descends.
    converge_iterations: int = 20
    # ... ending once the commanded move (the paper's metric, 0.001 m/deg, after r) has
    # stayed below this for two iterations in a row [m].
    converge_step_m: float = 0.002
    # The fraction r of the way to the best candidate while converging; 0: `step_ratio`.
    converge_step_ratio: float = 0.0
    # The commanded yaw stays within this of the start's [deg]. A parallel gripper is
    # symmetric under 180 degrees, so every grasp has a yaw within 90 degrees of the start;
    # without the bound, a CNN that prefers some rotation on a round object (whose image
    # does not change as the hand turns) turns the wrist on and on into its joint limit,
    # where differential IK sticks and the hand no longer follows. 0: no bound.
    max_yaw_from_start_deg: float = 135.0
    # The grasp height read from the depth image keeps the fingertips this far above the
    # lowest surface seen under the open hand (the table or sheet top) [m].
    support_margin_m: float = 0.004
    # The pads go lower than `scripted.grasp_depth_below_top_m` under the top, to the
    # object's widest section seen between them (`policies.widest_section_height`),
    # where that lies deeper; clutter without it grasped 6.3 points less
    # (analysis/results/widest-section/). A "widest section" deeper below the top than
    # the object is wide is a standing object's side wall seen by the camera, and is not
    # used (analysis/results/standing-objects/).
    grasp_at_widest_section: bool = True
    # While servoing at the stop height (`converge_iterations`), follow the best-scored
    # candidate whose grasp - its height read from the depth image as the descent reads
    # it - brings no part of the open hand (fingers, palm, housing: the ground truth's
    # collision model, outlines widened by `hand_margin_m`) down on a surface the image
    # shows under it, outside the closing strip: a surface may rise at most
    # `hand_clearance_m` above the part over it. When no candidate clears, the
    # best-scored one, as without the check. Not in the paper (its CNN alone chooses);
    # off by default.
    hand_check: bool = False
    hand_clearance_m: float = 0.005
    hand_margin_m: float = 0.0
    # Candidate actions per step, sampled uniformly in [-xy, xy]^2 x [-theta, theta]
    # around the current pose (the paper constrains sampling near the origin).
    num_candidates: int = 128
    sample_xy_m: float = 0.04
    sample_theta_deg: float = 45.0
    # CNN weights; "" = the shipped default (`systems.evaluator.DEFAULT_WEIGHTS`, where the
    # earlier shipped nets are listed too);
    # an X.onnx file from `drake-grasp export-onnx` runs the CNN with onnxruntime instead
    # of torch;
    # "A,B,..." scores each candidate with the mean of those nets (`CnnEnsemble`).
    weights: str = ""
    # Open-loop policies (cnn-only) search this many actions over the whole view.
    global_candidates: int = 2048
    # CPU threads for the CNN (1 suits one simulation per core).
    torch_threads: int = 1
    # Score each candidate as the mean of the CNN on the image and on its mirror image
    # with the mirrored action (`network.mirror_actions`: the wrist camera, the gripper
    # and physics share that symmetry); twice the CNN's cost.
    mirror_average: bool = False
    # Grid-head nets: "mirror" or "d4" scores the candidates on the distance grid averaged
    # over the image's symmetric views about the optical axis (the mirror image; also its
    # quarter turns), each view's grid turned back (`dense_training.view_averaged_grids`;
    # README, *The camera's symmetries*); 2 or 8 passes of the CNN's trunk. "none": the
    # image as shown. Not together with mirror_average.
    view_average: str = "none"


@dataclass
class NoiseConfig:
    """Kinematic noise on commanded hand displacements.

    gaussian: the paper's model, per commanded displacement
        delta_noisy = delta + scale * w * |delta|, w ~ N(0, I) in (x, y, theta),
        with |delta| in the paper's metric (0.001 m per degree).
    offset: a fixed (x, y, theta) error between where the policy believes the hand goes
        and where it goes, reached once the hand has moved `offset_ramp_m` from where
        it looked first (calibrated at the observation pose, off at the grasp).
    """

    kind: str = "none"
    gaussian_scale: float = 0.4
    offset_xy_m: list[float] = field(default_factory=lambda: [0.02, 0.0])
    offset_theta_deg: float = 0.0
    offset_ramp_m: float = 0.01


@dataclass
class TimingConfig:
    """When the policy's images are taken, as a real control loop would see them (beyond
    the paper, whose robot loop ran at about 5 Hz; the loop's rate itself is
    `controller.period_s`). A frame is taken every control period; the policy deciding at
    time t sees the frame taken at t - `latency_s` (`systems.frames.FrameBuffer`). The
    hand pose the controller believes for that image is the one it last commanded, so an
    image taken while the hand still moves misleads it, as it would on a robot.
    """

    # Sensor-to-action latency [s]: capture, transfer and computation together.
    latency_s: float = 0.0
    # Probability that a frame is lost; the policy then gets the last frame that arrived
    # (without knowing it is stale). Drawn per frame from the trial's seed.
    dropped_frame_prob: float = 0.0

    def active(self) -> bool:
        return self.latency_s > 0.0 or self.dropped_frame_prob > 0.0


@dataclass
class CalibrationConfig:
    """Camera-mount extrinsic error: the wrist camera (and the GPD sensor) sits off the
    pose the policy believes (the gripper model's `camera_mount`) by a translation of
    `camera_translation_error_m` along, and a rotation of `camera_rotation_error_deg`
    about, a direction drawn per trial from its seed (uniform on the sphere, both in the
    camera frame; `station.camera_mount_error`). The policy keeps the nominal X_GC.
    """

    camera_translation_error_m: float = 0.0
    camera_rotation_error_deg: float = 0.0

    def active(self) -> bool:
        return self.camera_translation_error_m > 0.0 or self.camera_rotation_error_deg > 0.0


@dataclass
class FailureMemoryConfig:
    """A clutter run's memory of the policy's own failed grasps (not in the paper; off
    by default). With `radius_m` > 0, `ctr` adds to each candidate's predicted distance
    how far inside `radius_m` of the nearest remembered grasp the candidate's pose lies
    (the grasp metric: x, y and 0.001 m/deg of yaw, modulo 180 degrees), and `gpd` takes
    its best detection farther than `radius_m` from all of them (its best one when none
    is). The experiment protocol fills `failed_xy_yaw` (x, y [m], yaw [deg], flat) with
    the hand's pose at each earlier failed closing of the run: what the robot knows of
    its own arm and of an empty gripper after a lift.
    """

    radius_m: float = 0.0
    failed_xy_yaw: list[float] = field(default_factory=list)

    def failed(self) -> np.ndarray:
        """The remembered grasps, (N, 3) = (x, y, yaw_deg); none while off."""
        if self.radius_m <= 0.0:
            return np.zeros((0, 3))
        return np.asarray(self.failed_xy_yaw, float).reshape(-1, 3)


@dataclass
class DisturbanceConfig:
    """Moving the sheet under the objects during a grasp.

    shift: after `after_iterations` controller iterations the sheet moves by a random
        planar displacement (uniform translation up to `shift_max_m` in a random
        direction, yaw uniform in +-`shift_max_yaw_deg`) within `shift_duration_s`,
        as the paper's experimenter did with a sheet of paper.
    moving: the sheet moves at a constant planar velocity during the approach.
    """

    kind: str = "none"
    after_iterations: int = 3
    shift_min_m: float = 0.03
    shift_max_m: float = 0.08
    shift_max_yaw_deg: float = 30.0
    shift_duration_s: float = 0.5
    velocity_m_s: list[float] = field(default_factory=lambda: [0.0, 0.01])


@dataclass
class JudgeConfig:
    """What counts as a successful grasp, and how failures are told apart
    (`drake_grasp.systems.judge.GraspJudge`)."""

    # The object's lowest point must be this high above the table after the hold [m].
    min_lift_m: float = 0.05
    # Read by the earlier geometric judge (a fully closed gripper holds nothing); the
    # contact judge needs no width (an object touching both pads keeps them apart).
    # Kept so that scenario files written before it still load.
    min_holding_width_m: float = 0.002
    # The judge samples the contacts this often [s] (a Python system evaluated at every
    # plant step would cost real-time factor).
    period_s: float = 0.01
    # "pushed-away": the object the grasp went for moved more than this horizontally
    # before the closing pads touched it [m].
    max_push_m: float = 0.02
    # Surface points of the ground-truth search behind each trial's `final_distance_m`
    # (the paper's distance to the nearest grasp). 400 is the dataset's labels' search; a
    # sparser search finds fewer of the true grasps, so its nearest one is farther away
    # (README *How exact the labels are*). `evaluate --distance-samples` sets it.
    distance_grasp_samples: int = 400


# Named contact-simulation settings (`physics.profile`). "reference" is what every result
# before the fast profile was measured with; "fast" is the default. Each lever's speed-up
# and the fidelity checks behind the choice: README, "Physics profiles".
PHYSICS_PROFILES: dict[str, dict] = {
    "reference": {"plant.time_step": 0.002, "plant.discrete_contact_approximation": "lagged",
                  "hydroelastic_margin_m": 0.0,
                  "sheet_collision": "box", "table_collision": "box",
                  "settle_time_step_s": 0.0},
    "fast": {"plant.time_step": 0.005, "plant.discrete_contact_approximation": "lagged",
             "hydroelastic_margin_m": 1e-4,
             "sheet_collision": "auto", "table_collision": "halfspace",
             "settle_time_step_s": 0.005},
    # "fast" at a 10 ms plant step with the "similar" contact approximation (lagged at
    # 10 ms lost more true grasps in the grasp lab); scenes still settle at 5 ms.
    "fast10": {"plant.time_step": 0.01, "plant.discrete_contact_approximation": "similar",
               "hydroelastic_margin_m": 1e-4, "sheet_collision": "auto",
               "table_collision": "halfspace", "settle_time_step_s": 0.005},
}
DEFAULT_PHYSICS_PROFILE = "fast"


@dataclass
class PhysicsConfig:
    """Contact-simulation settings beyond Drake's `MultibodyPlantConfig` (`plant`).

    `profile` names a set of them (`PHYSICS_PROFILES`: "fast", the default, "fast10" or
    "reference"). A profile given in a scenario file or `--scenario-text` sets
    `plant.time_step`, `plant.discrete_contact_approximation` and the fields below,
    except those given beside it (in the same `physics:` mapping, or a `plant:` key in
    the same text).
    """

    # One of PHYSICS_PROFILES; the defaults below are the default profile's.
    profile: str = DEFAULT_PHYSICS_PROFILE
    # Drake's `hydroelastic_margin` on the gripper's compliant pads and fingers [m] (0:
    # none): keeps flat-on-flat contact stable at larger time steps (the objects' convex
    # pieces cannot take one: `physics.apply_hydroelastic_margin`).
    hydroelastic_margin_m: float = PHYSICS_PROFILES[DEFAULT_PHYSICS_PROFILE]["hydroelastic_margin_m"]
    # The sheet's collision geometry: "box" (its 2 mm box), "halfspace" (a rigid half
    # space at its top surface, anchored to the world: cheaper to intersect with
    # compliant geometry; the box stays as its visual) or "auto" (the half space where
    # the sheet stays still, the box where a disturbance moves it).
    sheet_collision: str = PHYSICS_PROFILES[DEFAULT_PHYSICS_PROFILE]["sheet_collision"]
    # The table's collision geometry where the sheet keeps its box: "box" (the table top
    # and the floor below it) or "halfspace" (a rigid half space at the table top,
    # anchored to the world; nothing falls off the table then). Under a half-space sheet
    # the table has none (the sheet's half space lies above it everywhere).
    table_collision: str = PHYSICS_PROFILES[DEFAULT_PHYSICS_PROFILE]["table_collision"]
    # Time step of scene settling [s]; 0: `plant.time_step`.
    settle_time_step_s: float = PHYSICS_PROFILES[DEFAULT_PHYSICS_PROFILE]["settle_time_step_s"]


@dataclass
class Scenario:
    """One grasp episode: the scene, the station, the policy and the seed."""

    seed: int = 0
    policy: str = "scripted"
    scene: SceneConfig = field(default_factory=SceneConfig)
    plant: MultibodyPlantConfig = field(default_factory=_default_plant)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    camera: WristCameraConfig = field(default_factory=WristCameraConfig)
    gpd: GpdConfig = field(default_factory=GpdConfig)
    depth_noise: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    gripper: GripperConfig = field(default_factory=GripperConfig)
    arm: ArmConfig = field(default_factory=ArmConfig)
    scripted: ScriptedGraspConfig = field(default_factory=ScriptedGraspConfig)
    judge: JudgeConfig = field(default_factory=JudgeConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)
    timing: TimingConfig = field(default_factory=TimingConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    failure_memory: FailureMemoryConfig = field(default_factory=FailureMemoryConfig)
    # Target-object mode: grasp this object id (restricts candidates to its pixels).
    target: str = ""
    # Object library folder made by `drake-grasp objects import`; "" = built-in.
    objects_dir: str = ""
    # Simulated-time budget of one episode [s].
    max_sim_time_s: float = 15.0
    # Record a Meshcat replay.
    visualize: bool = False

    @property
    def sheet_moves(self) -> bool:
        """Whether the episode moves the sheet (any disturbance): the sheet then keeps its
        box collision (`physics.sheet_collision`), in the station and where the scene is
        settled (`scene.make_scene`)."""
        return self.disturbance.kind != "none"

    def validate(self) -> None:
        """Checks every field: its type and its allowed range.

        Raises:
            ValueError: naming the first bad key (dotted, e.g. `gripper.grip_force_n`),
                its value and the allowed values.
        """
        if is_policy_spec(self.policy):
            _check_user_policy(self)
        elif self.policy not in POLICIES:
            raise ValueError(f"policy: got {self.policy!r}, expected one of {POLICIES} or "
                             "MODULE:FACTORY (a user policy, e.g. 'centroid_policy:make_policy'; "
                             "see drake_grasp.policies.plugins)")
        for key, value in (("scene.kind", self.scene.kind),
                           ("noise.kind", self.noise.kind),
                           ("disturbance.kind", self.disturbance.kind),
                           ("scene.pose", self.scene.pose), ("scene.split", self.scene.split),
                           ("scene.pour", self.scene.pour),
                           ("scene.settle", self.scene.settle),
                           ("plant.contact_model", self.plant.contact_model),
                           ("plant.discrete_contact_approximation",
                            self.plant.discrete_contact_approximation),
                           ("plant.contact_surface_representation",
                            self.plant.contact_surface_representation),
                           ("controller.profile", self.controller.profile),
                           ("physics.sheet_collision", self.physics.sheet_collision),
                           ("physics.table_collision", self.physics.table_collision),
                           ("physics.profile", self.physics.profile),
                           ("gripper.force_mode", self.gripper.force_mode),
                           ("controller.view_average", self.controller.view_average)):
            allowed = _CHOICES[key]
            if value not in allowed:
                why = _CHOICE_REASONS.get(key, "")
                raise ValueError(f"{key}: got {value!r}, expected one of {allowed}{why}")
        for key, (low, high, low_open, high_open, unit) in _RANGES.items():
            _check_number(key, _get(self, key), low, high, low_open, high_open, unit,
                          integer=key in _INTEGER_KEYS)
        for key in ("target", "objects_dir", "gpd.weights"):
            if not isinstance(_get(self, key), str):
                raise ValueError(f"{key}: expected a string, got {_get(self, key)!r}")
        for key in ("visualize", "gpd.fallback_best"):
            if not isinstance(_get(self, key), bool):
                raise ValueError(f"{key}: expected true or false, got {_get(self, key)!r}")
        if self.controller.mirror_average and self.controller.view_average != "none":
            raise ValueError(f"controller.view_average: got {self.controller.view_average!r} "
                             "with controller.mirror_average true; expected one of them "
                             "(view_average: mirror is the mirror image about the optical axis)")
        ids = self.scene.object_ids
        if not isinstance(ids, list) or not all(isinstance(i, str) and i for i in ids):
            raise ValueError(f"scene.object_ids: expected a list of object ids (strings), got {ids!r}")
        for key in ("scene.center_xy_m", "noise.offset_xy_m", "disturbance.velocity_m_s"):
            value = _get(self, key)
            if (not isinstance(value, list) or len(value) != 2
                    or not all(_is_real(v) and math.isfinite(v) for v in value)):
                raise ValueError(f"{key}: expected [x, y] (two finite numbers), got {value!r}")
        failed = self.failure_memory.failed_xy_yaw
        if (not isinstance(failed, list) or len(failed) % 3
                or not all(_is_real(v) and math.isfinite(v) for v in failed)):
            raise ValueError("failure_memory.failed_xy_yaw: expected a flat list of finite "
                             f"numbers, 3 per grasp (x, y, yaw_deg), got {failed!r}")
        c = self.controller
        if not c.end_camera_height_m <= self.arm.start_camera_height_m:
            raise ValueError(
                f"controller.end_camera_height_m: got {c.end_camera_height_m}, expected 0 < end <= "
                f"arm.start_camera_height_m ({self.arm.start_camera_height_m})")
        if not self.scene.num_objects_min <= self.scene.num_objects_max:
            raise ValueError(
                "scene.num_objects_min/num_objects_max: expected 1 <= min <= max, got "
                f"{self.scene.num_objects_min}, {self.scene.num_objects_max}"
            )
        if not self.camera.depth_min_m < self.camera.depth_max_m:
            raise ValueError(
                f"camera.depth_min_m/depth_max_m: expected 0 < min < max, got "
                f"{self.camera.depth_min_m}, {self.camera.depth_max_m}")
        d = self.disturbance
        from drake_grasp.config.physics import sheet_collision

        sheet_collision(self.physics, sheet_moves=self.sheet_moves)  # raises for 'halfspace'
        if not d.shift_min_m <= d.shift_max_m:
            raise ValueError(f"disturbance.shift_min_m/shift_max_m: expected min <= max, got "
                             f"{d.shift_min_m}, {d.shift_max_m}")
        try:
            self.depth_noise.validate()
        except ValueError as e:
            raise ValueError(f"depth_noise: {e}") from None
        if not self.gpd.depth_min_m < self.gpd.depth_max_m:
            raise ValueError(
                f"gpd.depth_min_m/depth_max_m: expected 0 < min < max, got "
                f"{self.gpd.depth_min_m}, {self.gpd.depth_max_m}")
        try:
            self.gpd.noise.validate()
        except ValueError as e:
            raise ValueError(f"gpd.noise: {e}") from None


def _check_user_policy(scenario: "Scenario") -> None:
    """A user policy (`policy: MODULE:FACTORY`): the spec's form, and no setting that only
    the built-in controller applies (`drake_grasp.policies.plugins`)."""
    parse_policy_spec(scenario.policy)  # raises, naming the spec
    if scenario.noise.kind != "none":
        raise ValueError(f"noise.kind: got {scenario.noise.kind!r} with the user policy "
                         f"{scenario.policy!r}; expected 'none' (the kinematic noise models act "
                         "inside the built-in controller, a user policy gets none)")
    if scenario.target:
        raise ValueError(f"target: got {scenario.target!r} with the user policy "
                         f"{scenario.policy!r}; expected '' (target-object mode uses the label "
                         "image, which a user policy does not see)")


# --------------------------------------------------------------------------- profiles

def controller_profile(name: str) -> dict:
    """The settings of a named controller profile (`CONTROLLER_PROFILES`).

    Raises:
        ValueError: an unknown name; the message names `controller.profile` and the
            profiles there are.
    """
    if name not in CONTROLLER_PROFILES:
        close = difflib.get_close_matches(str(name), list(CONTROLLER_PROFILES), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"controller.profile: got {name!r}{hint}, expected one of "
                         f"{tuple(CONTROLLER_PROFILES)}")
    return dict(CONTROLLER_PROFILES[name])


def apply_controller_profile(controller: ControllerConfig, name: str, *,
                             keep=()) -> ControllerConfig:
    """A copy of `controller` with the named profile's settings, except the keys in
    `keep` (those given explicitly beside the profile), and `profile` set to `name`.
    The one place a profile turns into numbers."""
    values = {k: v for k, v in controller_profile(name).items() if k not in set(keep)}
    return dataclasses.replace(controller, profile=name, **values)


def apply_physics_profile(scenario: "Scenario", name: str, *, keep=()) -> "Scenario":
    """A copy of `scenario` with the named `PHYSICS_PROFILES` settings (`plant.time_step`,
    `plant.discrete_contact_approximation` and the `physics` fields), except the keys in
    `keep` (given explicitly beside the profile: "plant.<field>" or a `physics` field
    name), and `physics.profile` set.

    Raises:
        ValueError: an unknown name, naming `physics.profile` and the profiles there are.
    """
    if name not in PHYSICS_PROFILES:
        close = difflib.get_close_matches(str(name), list(PHYSICS_PROFILES), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"physics.profile: got {name!r}{hint}, expected one of "
                         f"{tuple(PHYSICS_PROFILES)}")
    values = {k: v for k, v in PHYSICS_PROFILES[name].items() if k not in set(keep)}
    plant = copy.deepcopy(scenario.plant)  # a Drake config: no dataclasses.replace
    for key in [k for k in values if k.startswith("plant.")]:
        setattr(plant, key[len("plant."):], values.pop(key))
    physics = dataclasses.replace(scenario.physics, profile=name, **values)
    return dataclasses.replace(scenario, plant=plant, physics=physics)


def _apply_profile_given(raw, scenario: "Scenario", where: str) -> "Scenario":
    """Applies `controller.profile` and `physics.profile` where the raw YAML mapping gives
    them: a profile sets its settings, except the ones given beside it (the same
    `controller:` / `physics:` mapping; for physics also any `plant:` key)."""
    if not isinstance(raw, dict):
        return scenario
    c = raw.get("controller")
    if isinstance(c, dict) and "profile" in c:
        try:
            controller = apply_controller_profile(scenario.controller, c["profile"],
                                                  keep=set(c) - {"profile"})
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        scenario = dataclasses.replace(scenario, controller=controller)
    ph = raw.get("physics")
    if isinstance(ph, dict) and "profile" in ph:
        keep = set(ph) - {"profile"}
        plant = raw.get("plant")
        if isinstance(plant, dict):
            keep.update(f"plant.{k}" for k in plant)
        try:
            scenario = apply_physics_profile(scenario, ph["profile"], keep=keep)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
    return scenario


# --------------------------------------------------------------------------- validation
# Allowed values of every tunable, checked by `Scenario.validate` (the message names the
# dotted key, the value and this range).

_INF = math.inf
# key: (low, high, low_open, high_open, unit). An infinite bound means "any finite value".
_RANGES: dict[str, tuple[float, float, bool, bool, str]] = {
    # The depth post-processor keeps the seed in a double parameter: exact below 2**53.
    "seed": (0, 2**53, False, True, ""),
    "max_sim_time_s": (0, _INF, True, True, "s"),
    "camera.width": (1, 4096, False, False, "px"),
    "camera.height": (1, 4096, False, False, "px"),
    "camera.fov_y_deg": (0, 180, True, True, "deg"),
    "camera.depth_min_m": (0, _INF, True, True, "m"),
    "camera.depth_max_m": (0, _INF, True, True, "m"),
    "camera.fps": (0, _INF, True, True, "Hz"),
    "gpd.width": (1, 4096, False, False, "px"),
    "gpd.height": (1, 4096, False, False, "px"),
    "gpd.fov_y_deg": (0, 180, True, True, "deg"),
    "gpd.depth_min_m": (0, _INF, True, True, "m"),
    "gpd.depth_max_m": (0, _INF, True, True, "m"),
    "gpd.view_camera_height_m": (0, _INF, True, True, "m"),
    "gpd.view_settle_s": (0, _INF, False, True, "s"),
    "gpd.approach_max_tilt_deg": (0, 60, False, False, "deg"),
    # Robotiq 2F-85 datasheet: 20-235 N; lower forces are allowed for slip studies.
    "gripper.grip_force_n": (0, 235, True, False, "N"),
    "gripper.closing_speed_m_s": (0, _INF, True, True, "m/s"),
    "gripper.open_width_m": (0, 0.085, True, False, "m"),  # 85 mm stroke
    "arm.start_camera_height_m": (0, _INF, True, True, "m"),
    "arm.ik_time_step_s": (0, _INF, True, True, "s"),
    "arm.max_tcp_speed_m_s": (0, _INF, True, True, "m/s"),
    "arm.max_tcp_angular_speed_rad_s": (0, _INF, True, True, "rad/s"),
    "arm.joint_velocity_fraction": (0, 1, True, False, ""),
    # Object counts are capped so a typo (1000 for 10) does not hang scene settling.
    "scene.num_objects_min": (1, 100, False, False, ""),
    "scene.num_objects_max": (1, 100, False, False, ""),
    "scene.clutter_objects": (1, 100, False, False, ""),
    "scene.region_half_extent_m": (0, _INF, True, True, "m"),
    "scene.settle_speed_tol_m_s": (0, _INF, True, True, "m/s"),
    "scene.settle_max_time_s": (0, _INF, True, True, "s"),
    "scripted.approach_time_s": (0, _INF, True, True, "s"),
    "scripted.pregrasp_height_m": (0, _INF, False, True, "m"),
    "scripted.descend_time_s": (0, _INF, True, True, "s"),
    "scripted.close_time_s": (0, _INF, True, True, "s"),
    "scripted.lift_height_m": (0, _INF, True, True, "m"),
    "scripted.lift_time_s": (0, _INF, True, True, "s"),
    "scripted.hold_time_s": (0, _INF, False, True, "s"),
    "scripted.grasp_depth_below_top_m": (0, _INF, False, True, "m"),
    "scripted.min_grasp_height_m": (0, _INF, False, True, "m"),
    "judge.min_lift_m": (0, _INF, False, True, "m"),
    "judge.min_holding_width_m": (0, 0.085, False, False, "m"),
    # At most the controller's usual period: a slower judge could miss a motion phase.
    "judge.period_s": (0, 0.1, True, False, "s"),
    "judge.max_push_m": (0, _INF, True, True, "m"),
    "controller.period_s": (0, _INF, True, True, "s"),
    "controller.iterations": (1, 10_000, False, False, ""),
    "controller.step_ratio": (0, 1, True, False, ""),
    "controller.z_step_m": (0, 0.1, False, False, "m"),
    "controller.end_camera_height_m": (0, _INF, True, True, "m"),
    "controller.stop_distance_m": (0, _INF, False, True, "m"),
    "controller.stop_window_half_m": (0, 0.1, True, False, "m"),
    "controller.converge_iterations": (0, 10_000, False, False, ""),
    "controller.converge_step_m": (0, _INF, False, True, "m"),
    "controller.converge_step_ratio": (0, 1, False, False, ""),
    "controller.max_yaw_from_start_deg": (0, 360, False, False, "deg"),
    "controller.support_margin_m": (0, 0.05, False, False, "m"),
    "controller.hand_clearance_m": (-0.05, 0.05, False, False, "m"),
    "failure_memory.radius_m": (0.0, 0.1, False, False, "m"),
    "controller.hand_margin_m": (0, 0.05, False, False, "m"),
    "controller.num_candidates": (1, 1_000_000, False, False, ""),
    "controller.sample_xy_m": (0, _INF, False, True, "m"),
    "controller.sample_theta_deg": (0, 180, False, False, "deg"),
    "controller.global_candidates": (1, 1_000_000, False, False, ""),
    "controller.torch_threads": (0, 1024, False, False, ""),  # 0: one thread
    "noise.gaussian_scale": (0, _INF, False, True, ""),
    "noise.offset_theta_deg": (-_INF, _INF, True, True, "deg"),
    "noise.offset_ramp_m": (0, _INF, False, True, "m"),
    "disturbance.after_iterations": (0, _INF, False, True, ""),
    "disturbance.shift_min_m": (0, _INF, False, True, "m"),
    "disturbance.shift_max_m": (0, _INF, False, True, "m"),
    "disturbance.shift_max_yaw_deg": (0, 180, False, False, "deg"),
    "disturbance.shift_duration_s": (0, _INF, True, True, "s"),
    # The station is a discrete (SAP-family) plant: a zero time step is a continuous plant.
    "plant.time_step": (0, _INF, True, True, "s"),
    "plant.penetration_allowance": (0, _INF, True, True, "m"),
    "plant.stiction_tolerance": (0, _INF, True, True, "m/s"),
    "plant.sap_near_rigid_threshold": (0, _INF, False, True, ""),
    "physics.hydroelastic_margin_m": (0, 0.01, False, False, "m"),
    "physics.settle_time_step_s": (0, 0.05, False, False, "s"),
    "timing.latency_s": (0, 2.0, False, False, "s"),
    # 1 would mean no frame ever arrives after the first.
    "timing.dropped_frame_prob": (0, 1, False, True, ""),
    "calibration.camera_translation_error_m": (0, 0.05, False, False, "m"),
    "calibration.camera_rotation_error_deg": (0, 30, False, False, "deg"),
}
_INTEGER_KEYS = {"seed", "camera.width", "camera.height", "scene.num_objects_min",
                 "scene.num_objects_max", "scene.clutter_objects", "controller.iterations",
                 "controller.num_candidates", "controller.global_candidates",
                 "controller.torch_threads", "disturbance.after_iterations"}
_CHOICES: dict[str, tuple[str, ...]] = {
    "scene.kind": SCENE_KINDS,
    "noise.kind": NOISE_KINDS,
    "disturbance.kind": DISTURBANCE_KINDS,
    "scene.pose": ("lying", "upright", "any"),
    "scene.split": ("train", "test", ""),
    "scene.pour": ("column", "sequential"),
    "scene.settle": ("speed", "verified"),
    "plant.contact_model": ("hydroelastic_with_fallback", "hydroelastic", "point"),
    "plant.discrete_contact_approximation": ("lagged", "sap", "similar"),
    "plant.contact_surface_representation": ("polygon", "triangle"),
    "controller.profile": tuple(CONTROLLER_PROFILES),
    "physics.sheet_collision": ("box", "halfspace", "auto"),
    "physics.table_collision": ("box", "halfspace"),
    "physics.profile": tuple(PHYSICS_PROFILES),
    "gripper.force_mode": GRIP_FORCE_MODES,
    "controller.view_average": ("none", "mirror", "d4"),
}
_CHOICE_REASONS = {
    "plant.discrete_contact_approximation":
        " (the arm's in-plant PD gains and the gripper's coupler constraint need a "
        "SAP-family solver; TAMSI ignores both)",
}


def _get(scenario: "Scenario", key: str):
    value = scenario
    for part in key.split("."):
        value = getattr(value, part)
    return value


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _bound_text(value) -> str:
    if value == 2**53:
        return "2**53"
    if float(value).is_integer() and abs(value) < 1e7:
        return str(int(value))
    return f"{value:g}"


def _range_text(low, high, low_open, high_open, unit, integer) -> str:
    unit = f" {unit}" if unit else ""
    kind = "an integer" if integer else "a finite number"
    if math.isinf(low) and math.isinf(high):
        return f"a finite number{unit}"
    if math.isinf(high):
        return f"{kind} {'>' if low_open else '>='} {_bound_text(low)}{unit}"
    return (f"{kind} in {'(' if low_open else '['}{_bound_text(low)}, {_bound_text(high)}"
            f"{')' if high_open else ']'}{unit}")


def _check_number(key, value, low, high, low_open, high_open, unit, *, integer) -> None:
    expected = _range_text(low, high, low_open, high_open, unit, integer)
    ok = isinstance(value, numbers.Integral) if integer else _is_real(value)
    ok = ok and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (low < value if low_open else low <= value) and (
            math.isinf(high) or (value < high if high_open else value <= high))
    if not ok:
        raise ValueError(f"{key}: got {value!r}, expected {expected}")


def scenario_file_path(scenario_file: "str | Path | None") -> Path:
    """The scenarios file: the given path, or the shipped `default.scenarios.yaml`."""
    if scenario_file is None or str(scenario_file) == "":
        return diagrams_dir() / DEFAULT_SCENARIO_FILE
    return Path(scenario_file)


def _describe(value) -> str:
    text = repr(value)
    if len(text) > 60:
        text = text[:57] + "..."
    return f"{text} ({type(value).__name__})"


def _parse_yaml(text: str, where: str):
    """YAML text -> plain data (dicts, lists, scalars), parsed as Drake's loader does."""
    from pydrake.common.yaml import yaml_load_data

    try:
        # private=True: keep "_" keys here; the callers drop them where Drake does.
        return yaml_load_data(text, private=True)
    except Exception as e:  # yaml.YAMLError and its kin, with line and column
        detail = " ".join(str(e).split())
        raise ValueError(f"{where}: not valid YAML ({type(e).__name__}: {detail})") from None


def _read_scenarios_file(path: Path) -> dict:
    """The parsed scenarios file: scenario name -> raw YAML data."""
    if not path.is_file():
        what = " (that is a folder)" if path.is_dir() else ""
        raise FileNotFoundError(f"scenario file not found: {path}{what}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a UTF-8 text file ({e})") from None
    except OSError as e:
        raise ValueError(f"{path}: cannot read the scenario file ({e.strerror})") from None
    data = _parse_yaml(text, str(path))
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of scenario names to scenarios, "
                         f"got {_describe(data)}")
    for name in data:
        if not isinstance(name, str):
            raise ValueError(f"{path}: scenario names must be strings, got {_describe(name)}")
    return data


def _schema_fields(schema) -> "dict[str, object] | None":
    """Field name -> type of a dataclass or of a Drake config struct; None for others."""
    if dataclasses.is_dataclass(schema):
        return typing.get_type_hints(schema)
    fields = getattr(schema, "__fields__", None)  # pydrake's bound config structs
    if isinstance(fields, tuple):
        return {f.name: f.type for f in fields}
    return None


_TYPE_WORDS = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def _scalar_ok(value, schema) -> bool:
    """Whether Drake's yaml_load_typed converts `value` into `schema` without loss.

    Mirrors pydrake.common.yaml's primitive conversions: exact type; int -> float;
    float -> int without a fractional part; number parsing of strings; "true"/"false".
    """
    kind = type(value)
    try:
        if kind is schema:
            return True
        if kind is int and schema is float:
            float(value)
            return True
        if kind is float and schema is int:
            return value.is_integer()
        if kind is str and schema in (int, float):
            schema(value)
            return True
        if kind is str and schema is bool:
            return value in ("true", "false")
    except (ValueError, OverflowError, TypeError):
        return False
    return False


def _check_yaml(value, schema, where: str, key: str) -> None:
    """Checks raw YAML data against the schema before Drake reads it.

    Drake's loader reports some mistakes without the key (a failed int() of "abc"),
    some with an AssertionError, and turns a string given for a list into a list of
    characters; this names the dotted key, the value and what was expected.
    """
    fields = _schema_fields(schema)
    label = key or "the scenario"
    if fields is not None:
        if not isinstance(value, dict):
            raise ValueError(f"{where}: {label}: expected a mapping with keys "
                             f"{sorted(fields)}, got {_describe(value)}")
        for name, item in value.items():
            if not isinstance(name, str):
                raise ValueError(f"{where}: {label}: keys must be strings, got {_describe(name)}")
            full = f"{key}.{name}" if key else name
            if name not in fields:
                close = difflib.get_close_matches(name, list(fields), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                if ":" in name:
                    hint += " (YAML needs a space after ':', e.g. '{seed: 3}')"
                raise ValueError(f"{where}: unknown key {full!r}{hint}; {label} has the keys "
                                 f"{sorted(fields)}")
            _check_yaml(item, fields[name], where, full)
        return
    if typing.get_origin(schema) is list:
        (item_schema,) = typing.get_args(schema) or (typing.Any,)
        if not isinstance(value, list):
            raise ValueError(f"{where}: {label}: expected a list, got {_describe(value)}")
        for i, item in enumerate(value):
            _check_yaml(item, item_schema, where, f"{key}[{i}]")
        return
    if schema in _TYPE_WORDS and not _scalar_ok(value, schema):
        raise ValueError(f"{where}: {label}: expected {_TYPE_WORDS[schema]}, "
                         f"got {_describe(value)}")


def _load_typed(where: str, **kwargs) -> Scenario:
    try:
        return yaml_load_typed(schema=Scenario, **kwargs)
    except Exception as e:  # not expected after _check_yaml; keep the location anyway
        raise ValueError(f"{where}: {type(e).__name__}: {e}") from None


def list_scenarios(scenario_file: str | Path | None = None) -> list[str]:
    """Names of the scenarios in a scenarios file (keys not starting with '_').

    Raises:
        FileNotFoundError: the file is missing.
        ValueError: it is not UTF-8 YAML holding a mapping (the message names the file).
    """
    data = _read_scenarios_file(scenario_file_path(scenario_file))
    return [k for k in data if not k.startswith("_")]


def load_scenario(
    *,
    scenario_name: str = "isolation",
    scenario_file: str | Path | None = None,
    scenario_text: str = "",
    controller_profile: str = "",
    physics_profile: str = "",
) -> Scenario:
    """Loads a named scenario, then applies an inline YAML override.

    Args:
        scenario_name: key in the scenarios file.
        scenario_file: a `*.scenarios.yaml`; None -> the shipped default file.
        scenario_text: YAML text whose keys override the named scenario's.
        controller_profile: a `CONTROLLER_PROFILES` name applied to the named scenario
            before `scenario_text` ("" keeps the scenario's); how experiments choose
            the paper's sim or robot controller settings.
        physics_profile: a `PHYSICS_PROFILES` name applied to the named scenario before
            `scenario_text` ("" keeps the scenario's).

    Raises:
        FileNotFoundError: the file is missing.
        ValueError: not valid YAML, unknown scenario name, unknown key, a value of the
            wrong type or out of range; the message names the file and scenario (or the
            override text), the dotted key, the value and what was expected.
    """
    path = scenario_file_path(scenario_file)
    data = _read_scenarios_file(path)
    names = [k for k in data if not k.startswith("_")]
    if scenario_name not in names:
        close = difflib.get_close_matches(str(scenario_name), names, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"{path}: no scenario named {scenario_name!r}{hint}; available: {names}")
    where = f"{path}: scenario {scenario_name!r}"
    _check_yaml(data[scenario_name], Scenario, where, "")
    scenario = _load_typed(where, filename=str(path), child_name=scenario_name,
                           defaults=Scenario())
    scenario = _apply_profile_given(data[scenario_name], scenario, where)
    if controller_profile:
        try:
            scenario = dataclasses.replace(scenario, controller=apply_controller_profile(
                scenario.controller, controller_profile))
        except ValueError as e:
            raise ValueError(f"controller_profile: {e}") from None
    if physics_profile:
        try:
            scenario = apply_physics_profile(scenario, physics_profile)
        except ValueError as e:
            raise ValueError(f"physics_profile: {e}") from None
    named = scenario
    shown = scenario_text if len(scenario_text) <= 80 else scenario_text[:77] + "..."
    text_where = f"--scenario-text {shown!r}"
    if scenario_text:
        override = _parse_yaml(scenario_text, text_where)
        if isinstance(override, dict):  # Drake drops top-level "_" keys (YAML anchors)
            override = {k: v for k, v in override.items()
                        if not (isinstance(k, str) and k.startswith("_"))}
        if override is not None:  # blank or comment-only text overrides nothing
            scenario = _apply_override(scenario, override, scenario_text, text_where)
    try:
        scenario.validate()
    except ValueError as e:
        blame = where
        if scenario is not named:
            try:
                named.validate()
                blame = text_where  # the named scenario alone is fine: the override broke it
            except ValueError:
                pass
        raise ValueError(f"{blame}: {e}") from None
    return scenario


def _apply_override(scenario: Scenario, override, text: str, where: str) -> Scenario:
    """`scenario` with the parsed override mapping `override` (the YAML `text`) applied:
    its keys checked against the schema, loaded over `scenario`, and the profiles it names
    applied (the caller validates)."""
    _check_yaml(override, Scenario, where, "")
    scenario = _load_typed(where, data=text, defaults=scenario)
    return _apply_profile_given(override, scenario, where)


def apply_controller_text(scenario: Scenario, text: str) -> Scenario:
    """`scenario` with the controller settings of `text`, a YAML mapping of
    `ControllerConfig` fields (e.g. ``{stop_distance_m: 0.2}``), checked and validated as
    `load_scenario`'s override text is (a ``profile`` key applies that controller profile
    first). Blank text changes nothing.

    Raises:
        ValueError: not a YAML mapping, an unknown key, a value of the wrong type or out of
            range; the message names the text, the dotted key and what was expected.
    """
    shown = text if len(text) <= 80 else text[:77] + "..."
    where = f"--ctr-text {shown!r}"
    mapping = _parse_yaml(text, where)
    if mapping is None:
        return scenario
    if not isinstance(mapping, dict):
        raise ValueError(f"{where}: expected a mapping of controller settings, e.g. "
                         f"'{{stop_distance_m: 0.2}}', got {_describe(mapping)}")
    override = {"controller": mapping}
    out = _apply_override(scenario, override, json.dumps(override), where)  # JSON is YAML
    try:
        out.validate()
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    return out


def dump_scenario(scenario: Scenario) -> str:
    """The resolved scenario as YAML (loadable with `load_scenario`'s schema)."""
    return yaml_dump_typed(scenario)


def replace(scenario: Scenario, **changes) -> Scenario:
    """A copy of `scenario` with top-level fields replaced."""
    return dataclasses.replace(scenario, **changes)
