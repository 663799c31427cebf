"""The typed sections of a scenario: one dataclass per part of the station (camera, GPD
view, gripper, arm, scene, scripted grasp, controller, noise, timing, calibration, failure
memory, disturbance, judge, physics), their defaults, the named controller and physics
profiles and the allowed kinds. `scenario.Scenario` holds one of each.
"""

# No `from __future__ import annotations` here: yaml_load_typed reads the field types
# at run time and cannot resolve string annotations.
from dataclasses import dataclass, field

import numpy as np
from pydrake.multibody.plant import MultibodyPlantConfig

from drake_grasp.geometry.sensing import DepthNoiseConfig

SCENE_KINDS = ("isolation", "random", "clutter", "packed")
POLICIES = ("scripted", "ctr", "gpd", "gpd-track", "gpd-geometric", "cnn-only", "cnn-ctr",
            "init")
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


@dataclass
class GpdTrackConfig:
    """gpd-track: GPD's grasp from its viewpoint, followed in the wrist camera on the way
    down (`drake_grasp.policies.gpd_track`). Every control period the wrist image is
    registered against the GPD image around the grasp (`policies.scene_tracking`), the
    grasp moved with the scene, and the hand moved toward its pre-grasp."""

    # Half side of the square around the grasp matched in each wrist image [m].
    template_half_m: float = 0.07
    # Largest translation searched per axis, and turn searched either side of none
    # [m, deg], on a grid of `yaw_step_deg`.
    search_m: float = 0.10
    yaw_range_deg: float = 40.0
    yaw_step_deg: float = 3.0
    # Height-map cell of the fine search [m] (the coarse search's is twice that).
    cell_m: float = 0.003
    # A registration whose new view shares fewer of its cells with the GPD image, or
    # whose heights differ from it by more than `max_rms_m` (root mean square, the mean
    # difference taken out), is not used: the grasp keeps its last estimate.
    min_overlap: float = 0.5
    max_rms_m: float = 0.02
    # Largest move of the hand per control period [m, deg].
    step_max_m: float = 0.025
    step_max_yaw_deg: float = 8.0
    # The hand descends to the grasp once it is at the pre-grasp and the estimate has
    # moved less than `settled_m` (the paper's metric, 1 mm per degree) for
    # `settled_iterations` control periods in a row, or after `max_iterations`.
    settled_m: float = 0.003
    settled_iterations: int = 3
    max_iterations: int = 60


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
    # Clutter (and packed scenes: the number standing side by side): number of objects
    # poured into a pile, and how: "column" drops them from a
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
# paper-sim: Section 5 as written, nothing added: the 75 iterations always run to 0.15 m
#   (no stop rule: stop_distance_m 0) and the hand grasps where the last one leaves it (no
#   convergence: converge_iterations 0). "sim" keeps this project's stop rule and
#   convergence at the stop height; Figure 5's CTR arms ran with "sim".
CONTROLLER_PROFILES: dict[str, dict[str, float]] = {
    "sim": {"step_ratio": 0.2, "iterations": 75, "z_step_m": 0.0,
            "end_camera_height_m": 0.15, "stop_distance_m": 0.14, "converge_iterations": 20},
    "robot": {"step_ratio": 0.5, "iterations": 50, "z_step_m": 0.01,
              "end_camera_height_m": 0.15, "stop_distance_m": 0.14, "converge_iterations": 20},
    "paper-sim": {"step_ratio": 0.2, "iterations": 75, "z_step_m": 0.0,
                  "end_camera_height_m": 0.15, "stop_distance_m": 0.0, "converge_iterations": 0},
}


@dataclass
class ControllerConfig:
    """The paper's closed-loop controller (Algorithm 1) and the learned evaluator.

    `profile` names one of the paper's settings (`CONTROLLER_PROFILES`): "sim" (the
    default; camera from 0.3 m to 0.15 m above the table in 75 equal z steps, each
    iteration moving a fraction r = 0.2 of the way to the best candidate, with the stop
    rule and convergence below), "robot" (r = 0.5, 1 cm z steps until an object is within
    14 cm of the sensor or the hand is at its lowest height) or "paper-sim" ("sim" as the
    paper's Section 5 writes it: all 75 iterations, no stop rule, no convergence). A
    profile given in a scenario file or `--scenario-text` sets `step_ratio`, `iterations`,
    `z_step_m`, `end_camera_height_m`, `stop_distance_m` and `converge_iterations`,
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
    # being `arm.start_camera_height_m` (raised over objects the
    # survey image shows standing taller: `world.station.survey_top_z`).
    z_step_m: float = 0.0
    # Camera height above the table at the last iteration [m]: the hand's lowest height.
    end_camera_height_m: float = 0.15
    # Stop when the depth image shows an object this close to the sensor [m]; 0: no stop rule.
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
    # with the mirrored action (`mirror.mirror_actions`: the wrist camera, the gripper
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
