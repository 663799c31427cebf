"""The checks behind `Scenario.validate`: the allowed range of every numeric tunable,
the allowed choices of every string one, the messages that name a bad key, its value and
what it may be, and the rules for a user policy (`policy: MODULE:FACTORY`).
"""

import math
import numbers

from drake_grasp.config.policy_spec import parse_policy_spec
from drake_grasp.config.sections import (
    CONTROLLER_PROFILES, DISTURBANCE_KINDS, GRIP_FORCE_MODES, NOISE_KINDS, PHYSICS_PROFILES,
    SCENE_KINDS,
)


def _check_user_policy(scenario) -> None:
    """A user policy (`policy: MODULE:FACTORY`): the spec's form, and no setting that only
    the built-in controller applies (`drake_grasp.policies.plugins`)."""
    parse_policy_spec(scenario.policy)  # raises, naming the spec
    if scenario.noise.kind != "none":
        raise ValueError(f"noise.kind: got {scenario.noise.kind!r} with the user policy "
                         f"{scenario.policy!r}; expected 'none' (the KinematicNoise system reads "
                         "each commanded move from the built-in controller's X_WG_goal port, "
                         "which a user policy does not have)")
    if scenario.target:
        raise ValueError(f"target: got {scenario.target!r} with the user policy "
                         f"{scenario.policy!r}; expected '' (target-object mode uses the label "
                         "image, which a user policy does not see)")


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
    "gpd_track.template_half_m": (0, 0.5, True, False, "m"),
    "gpd_track.search_m": (0, 0.5, True, False, "m"),
    "gpd_track.yaw_range_deg": (0, 180, False, False, "deg"),
    "gpd_track.yaw_step_deg": (0, 90, True, False, "deg"),
    "gpd_track.cell_m": (0, 0.05, True, False, "m"),
    "gpd_track.min_overlap": (0, 1, False, False, ""),
    "gpd_track.max_rms_m": (0, _INF, True, True, "m"),
    "gpd_track.step_max_m": (0, 0.2, True, False, "m"),
    "gpd_track.step_max_yaw_deg": (0, 90, True, False, "deg"),
    "gpd_track.settled_m": (0, _INF, False, True, "m"),
    "gpd_track.settled_iterations": (1, 1000, False, False, ""),
    "gpd_track.max_iterations": (1, 10000, False, False, ""),
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
                 "controller.torch_threads", "disturbance.after_iterations",
                 "gpd_track.settled_iterations", "gpd_track.max_iterations"}
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


def _get(scenario, key: str):
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
