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
import typing
from dataclasses import dataclass, field

# No `from __future__ import annotations` here: yaml_load_typed reads the field types
# at run time and cannot resolve string annotations.
from pathlib import Path

from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.multibody.plant import MultibodyPlantConfig

from drake_grasp.core.assets import diagrams_dir
from drake_grasp.config.policy_spec import is_policy_spec
from drake_grasp.config.scenario_checks import (
    _CHOICE_REASONS, _CHOICES, _INTEGER_KEYS, _RANGES, _check_number, _check_user_policy, _get,
    _is_real,
)
from drake_grasp.config.sections import (
    CONTROLLER_PROFILES, PHYSICS_PROFILES, POLICIES, ArmConfig, CalibrationConfig,
    ControllerConfig, DisturbanceConfig, FailureMemoryConfig, GpdConfig, GpdTrackConfig,
    GripperConfig, JudgeConfig, NoiseConfig, PhysicsConfig, SceneConfig, ScriptedGraspConfig,
    TimingConfig, WristCameraConfig, _default_plant,
)
from drake_grasp.geometry.sensing import DepthNoiseConfig

DEFAULT_SCENARIO_FILE = "default.scenarios.yaml"


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
    gpd_track: GpdTrackConfig = field(default_factory=GpdTrackConfig)
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


def apply_scenario_text(scenario: Scenario, text: str, *, section: str = "",
                        where: str = "") -> Scenario:
    """`scenario` with the settings of `text`, a YAML mapping of scenario keys (with
    `section`, e.g. "controller", of that section's keys), checked and validated as
    `load_scenario`'s override text is (a ``profile`` key applies that profile first).
    Blank text changes nothing. `where` names the text in messages (default: the text).

    Raises:
        ValueError: not a YAML mapping, an unknown key, a value of the wrong type or out of
            range; the message names the text, the dotted key and what was expected.
    """
    if not where:
        shown = text if len(text) <= 80 else text[:77] + "..."
        where = f"scenario patch {shown!r}"
    mapping = _parse_yaml(text, where)
    if mapping is None:
        return scenario
    if not isinstance(mapping, dict):
        what = f"{section} settings" if section else "scenario settings"
        example = "'{stop_distance_m: 0.2}'" if section == "controller" else \
            "'{controller: {stop_distance_m: 0.2}}'"
        raise ValueError(f"{where}: expected a mapping of {what}, e.g. {example}, "
                         f"got {_describe(mapping)}")
    override = {section: mapping} if section else mapping
    out = _apply_override(scenario, override, json.dumps(override), where)  # JSON is YAML
    try:
        out.validate()
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    return out


def apply_controller_text(scenario: Scenario, text: str) -> Scenario:
    """`scenario` with the controller settings of `text`, a YAML mapping of
    `ControllerConfig` fields (e.g. ``{stop_distance_m: 0.2}``): `apply_scenario_text` of
    the controller section, named ``--ctr-text`` in messages. Blank text changes nothing.

    Raises:
        ValueError: not a YAML mapping, an unknown key, a value of the wrong type or out of
            range; the message names the text, the dotted key and what was expected.
    """
    shown = text if len(text) <= 80 else text[:77] + "..."
    return apply_scenario_text(scenario, text, section="controller",
                               where=f"--ctr-text {shown!r}")


def dump_scenario(scenario: Scenario) -> str:
    """The resolved scenario as YAML (loadable with `load_scenario`'s schema)."""
    return yaml_dump_typed(scenario)


def replace(scenario: Scenario, **changes) -> Scenario:
    """A copy of `scenario` with top-level fields replaced."""
    return dataclasses.replace(scenario, **changes)
