"""Typed configuration of a grasp episode, loaded from `diagrams/*.scenarios.yaml`.

Every tunable of the station lives in one of these dataclasses. Files are read with
Drake's `yaml_load_typed`, so an unknown (e.g. misspelled) key is an error, and the
resolved scenario is written beside every output with `yaml_dump_typed`.
"""


import dataclasses
from dataclasses import dataclass, field

# No `from __future__ import annotations` here: yaml_load_typed reads the field types
# at run time and cannot resolve string annotations.
from pathlib import Path

from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.multibody.plant import MultibodyPlantConfig

from drake_grasp.assets import diagrams_dir
from drake_grasp.sensing import DepthNoiseConfig

DEFAULT_SCENARIO_FILE = "default.scenarios.yaml"
SCENE_KINDS = ("isolation", "random", "clutter")
POLICIES = ("scripted", "ctr", "gpd", "cnn-only", "cnn-ctr", "init")
NOISE_KINDS = ("none", "gaussian", "offset")
DISTURBANCE_KINDS = ("none", "shift", "moving")


def _default_plant() -> MultibodyPlantConfig:
    # SAP-family solver (lagged): needed for in-plant PD gains and the gripper's
    # mimic coupler constraint; hydroelastic pads/objects decide grasp success.
    return MultibodyPlantConfig(
        time_step=0.002,
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


@dataclass
class GripperConfig:
    """Robotiq 2F-85 command defaults (datasheet: 20-235 N, 20-150 mm/s)."""

    # Normal force each pad presses on the object [N].
    grip_force_n: float = 60.0
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
    """What is on the table; see `drake_grasp.scene`."""

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
    # Clutter: number of objects poured into a pile.
    clutter_objects: int = 5
    # Centre of the workspace on the table [m] and half size of the placement square.
    center_xy_m: list[float] = field(default_factory=lambda: [0.5, 0.0])
    region_half_extent_m: float = 0.08
    # Settling: simulate until every object is slower than this, at most this long.
    settle_speed_tol_m_s: float = 0.005
    settle_max_time_s: float = 4.0


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
    # The grasp centre stays at least this far above the table [m].
    min_grasp_height_m: float = 0.02


@dataclass
class ControllerConfig:
    """The paper's closed-loop controller (Algorithm 1) and the learned evaluator.

    Defaults are the paper's simulation: camera from 0.3 m to 0.15 m above the table in
    75 iterations, each moving a fraction r = 0.2 of the way to the best candidate. (The
    robot used r = 0.5 and 1 cm z steps.)
    """

    # Control period [s] (the robot's loop ran at about 5 Hz).
    period_s: float = 0.1
    iterations: int = 75
    step_ratio: float = 0.2
    # Camera height above the table at the last iteration [m]; the start height is
    # `arm.start_camera_height_m`. z steps = (start - end) / iterations.
    end_camera_height_m: float = 0.15
    # Stop when the depth image shows an object this close to the sensor [m].
    stop_distance_m: float = 0.14
    # ... looking at the central part of the image (fraction of its side).
    stop_window_fraction: float = 0.5
    # Candidate actions per step, sampled uniformly in [-xy, xy]^2 x [-theta, theta]
    # around the current pose (the paper constrains sampling near the origin).
    num_candidates: int = 128
    sample_xy_m: float = 0.04
    sample_theta_deg: float = 45.0
    # CNN weights; "" = the shipped models/cnn/weights.safetensors.
    weights: str = ""
    # Open-loop policies (cnn-only) search this many actions over the whole view.
    global_candidates: int = 2048
    # CPU threads for the CNN (1 suits one simulation per core).
    torch_threads: int = 1


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
    """What counts as a successful grasp."""

    # The object's lowest point must be this high above the table after the hold [m].
    min_lift_m: float = 0.05
    # A fully closed gripper holds nothing: the opening must stay above this [m].
    min_holding_width_m: float = 0.002


@dataclass
class Scenario:
    """One grasp episode: the scene, the station, the policy and the seed."""

    seed: int = 0
    policy: str = "scripted"
    scene: SceneConfig = field(default_factory=SceneConfig)
    plant: MultibodyPlantConfig = field(default_factory=_default_plant)
    camera: WristCameraConfig = field(default_factory=WristCameraConfig)
    depth_noise: DepthNoiseConfig = field(default_factory=DepthNoiseConfig)
    gripper: GripperConfig = field(default_factory=GripperConfig)
    arm: ArmConfig = field(default_factory=ArmConfig)
    scripted: ScriptedGraspConfig = field(default_factory=ScriptedGraspConfig)
    judge: JudgeConfig = field(default_factory=JudgeConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)
    # Target-object mode: grasp this object id (restricts candidates to its pixels).
    target: str = ""
    # Object library folder made by `drake-grasp objects import`; "" = built-in.
    objects_dir: str = ""
    # Simulated-time budget of one episode [s].
    max_sim_time_s: float = 15.0
    # Record a Meshcat replay.
    visualize: bool = False

    def validate(self) -> None:
        """Raises ValueError naming the key and the expected values."""
        if self.scene.kind not in SCENE_KINDS:
            raise ValueError(f"scene.kind: got {self.scene.kind!r}, expected one of {SCENE_KINDS}")
        if self.policy not in POLICIES:
            raise ValueError(f"policy: got {self.policy!r}, expected one of {POLICIES}")
        if self.noise.kind not in NOISE_KINDS:
            raise ValueError(f"noise.kind: got {self.noise.kind!r}, expected one of {NOISE_KINDS}")
        if self.disturbance.kind not in DISTURBANCE_KINDS:
            raise ValueError(f"disturbance.kind: got {self.disturbance.kind!r}, "
                             f"expected one of {DISTURBANCE_KINDS}")
        c = self.controller
        if c.iterations < 1 or c.num_candidates < 1 or c.period_s <= 0:
            raise ValueError("controller.iterations/num_candidates/period_s: expected positive values")
        if not 0.0 < c.step_ratio <= 1.0:
            raise ValueError(f"controller.step_ratio: got {c.step_ratio}, expected (0, 1]")
        if not 0.0 < c.end_camera_height_m <= self.arm.start_camera_height_m:
            raise ValueError("controller.end_camera_height_m: expected 0 < end <= "
                             "arm.start_camera_height_m")
        if len(self.noise.offset_xy_m) != 2:
            raise ValueError(f"noise.offset_xy_m: expected [x, y], got {self.noise.offset_xy_m}")
        if self.scene.pose not in ("lying", "upright", "any"):
            raise ValueError(f"scene.pose: got {self.scene.pose!r}, expected lying|upright|any")
        if not 1 <= self.scene.num_objects_min <= self.scene.num_objects_max:
            raise ValueError(
                "scene.num_objects_min/num_objects_max: expected 1 <= min <= max, got "
                f"{self.scene.num_objects_min}, {self.scene.num_objects_max}"
            )
        if len(self.scene.center_xy_m) != 2:
            raise ValueError(f"scene.center_xy_m: expected [x, y], got {self.scene.center_xy_m}")
        if self.seed < 0:
            raise ValueError(f"seed: expected a non-negative integer, got {self.seed}")
        if not 0.0 < self.gripper.grip_force_n <= 235.0:
            raise ValueError(
                f"gripper.grip_force_n: got {self.gripper.grip_force_n}, expected (0, 235] N"
            )
        if not 0.0 < self.gripper.open_width_m <= 0.085:
            raise ValueError(
                f"gripper.open_width_m: got {self.gripper.open_width_m}, expected (0, 0.085] m"
            )
        if self.camera.width <= 0 or self.camera.height <= 0:
            raise ValueError("camera.width/height: expected positive pixel counts")
        if not 0.0 < self.camera.depth_min_m < self.camera.depth_max_m:
            raise ValueError("camera.depth_min_m/depth_max_m: expected 0 < min < max")
        if self.max_sim_time_s <= 0:
            raise ValueError(f"max_sim_time_s: expected > 0, got {self.max_sim_time_s}")
        self.depth_noise.validate()


def scenario_file_path(scenario_file: "str | Path | None") -> Path:
    """The scenarios file: the given path, or the shipped `default.scenarios.yaml`."""
    if scenario_file is None or str(scenario_file) == "":
        return diagrams_dir() / DEFAULT_SCENARIO_FILE
    return Path(scenario_file)


def list_scenarios(scenario_file: str | Path | None = None) -> list[str]:
    """Names of the scenarios in a scenarios file (keys not starting with '_')."""
    import yaml

    path = scenario_file_path(scenario_file)
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of scenario names to scenarios")
    return [k for k in data if not str(k).startswith("_")]


def load_scenario(
    *,
    scenario_name: str = "isolation",
    scenario_file: str | Path | None = None,
    scenario_text: str = "",
) -> Scenario:
    """Loads a named scenario, then applies an inline YAML override.

    Args:
        scenario_name: key in the scenarios file.
        scenario_file: a `*.scenarios.yaml`; None -> the shipped default file.
        scenario_text: YAML text whose keys override the named scenario's.

    Raises:
        FileNotFoundError: the file is missing.
        ValueError: unknown scenario name, unknown key, or an invalid value; the message
            names the file, the scenario and the key.
    """
    path = scenario_file_path(scenario_file)
    if not path.is_file():
        raise FileNotFoundError(f"scenario file not found: {path}")
    names = list_scenarios(path)
    if scenario_name not in names:
        raise ValueError(f"{path}: no scenario named {scenario_name!r}; available: {names}")
    try:
        scenario = yaml_load_typed(
            schema=Scenario, filename=str(path), child_name=scenario_name, defaults=Scenario()
        )
    except RuntimeError as e:
        raise ValueError(f"{path}: scenario {scenario_name!r}: {e}") from None
    if scenario_text:
        try:
            scenario = yaml_load_typed(schema=Scenario, data=scenario_text, defaults=scenario)
        except RuntimeError as e:
            raise ValueError(f"--scenario-text {scenario_text!r}: {e}") from None
    try:
        scenario.validate()
    except ValueError as e:
        raise ValueError(f"{path}: scenario {scenario_name!r}: {e}") from None
    return scenario


def dump_scenario(scenario: Scenario) -> str:
    """The resolved scenario as YAML (loadable with `load_scenario`'s schema)."""
    return yaml_dump_typed(scenario)


def replace(scenario: Scenario, **changes) -> Scenario:
    """A copy of `scenario` with top-level fields replaced."""
    return dataclasses.replace(scenario, **changes)
