"""The paper's experiments as data: which scenario, policies, noise, disturbance, trials.

An `Experiment` is a named set of `Condition`s (the arms compared) run on the same trial
seeds, so trial i of every condition sees the same scene (paired comparison).
`trial_scenario` turns (experiment, condition, trial index, base seed) into the exact
`Scenario` of that trial. The Table 1 experiments run the controller with the paper's
robot settings (`controller_profile="robot"`: r = 0.5, 1 cm z steps, stop at 14 cm);
`isolation` adds `ctr-sim`, the same CTR with the simulation settings (r = 0.2, 75
iterations), so both appear in its report.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from drake_grasp.policies.decisions import CLOSED_LOOP_POLICIES, GPD_POLICIES, SENSOR_POLICIES
from drake_grasp.config.scenario import Scenario, apply_scenario_text, load_scenario


# Policies that run the distance CNN (and so depend on its weights file).
CNN_POLICIES = ("ctr", "cnn-only", "cnn-ctr")
# The groups of conditions a scenario patch names (`ScenarioPatch.group`), by policy:
# every condition, those that run the distance CNN, the closed-loop ones, GPD.
PATCH_GROUPS = {"all": None, "cnn": CNN_POLICIES, "closed-loop": CLOSED_LOOP_POLICIES,
                "gpd": GPD_POLICIES}


@dataclass(frozen=True)
class ScenarioPatch:
    """Settings that a group of an experiment's conditions run with: `text`, a YAML mapping
    of scenario keys (of the `section`'s keys when one is named), applied to the resolved
    scenario of every condition whose policy is in `PATCH_GROUPS[group]`, checked by the
    typed loader (`scenario.apply_scenario_text`). `source` names it in messages (the
    command-line option it came from). The one way an experiment's settings change:
    `evaluate`'s options (--weights, --converge, --ctr-text, ...) are patches."""

    group: str
    text: str
    section: str = ""
    source: str = ""

    def __post_init__(self):
        if self.group not in PATCH_GROUPS:
            raise ValueError(f"scenario patch group: expected one of {list(PATCH_GROUPS)}, "
                             f"got {self.group!r}")

    def applies_to(self, policy: str) -> bool:
        policies = PATCH_GROUPS[self.group]
        return policies is None or policy in policies

    def apply(self, scenario: Scenario) -> Scenario:
        return apply_scenario_text(scenario, self.text, section=self.section,
                                   where=self.source)


@dataclass(frozen=True)
class Condition:
    """One arm of an experiment."""

    name: str
    policy: str
    noise: str = "none"          # none | gaussian | offset
    noise_scale: float = 0.4     # the Gaussian model's factor
    offset_m: float = 0.0        # constant-offset size (along the closing direction)
    depth_noise: float = 0.0     # 0 = clean depth; k = k x the default sensor noise model
    disturbance: str = "none"    # none | shift | moving
    # A controller profile (scenario.CONTROLLER_PROFILES: sim | robot | paper-sim); "" = the
    # experiment's `controller_profile`.
    controller_profile: str = ""
    # The loop's timing and the camera's calibration (scenario.TimingConfig,
    # CalibrationConfig; 0 = the scenario's): control period [s], sensor-to-action
    # latency [s], dropped-frame probability, camera-mount error [m], [deg].
    control_period_s: float = 0.0
    latency_s: float = 0.0
    dropped_frame_prob: float = 0.0
    camera_translation_error_m: float = 0.0
    camera_rotation_error_deg: float = 0.0


@dataclass(frozen=True)
class Experiment:
    """A named experiment: scenario, conditions, default trial count, how trials run."""

    name: str
    scenario: str
    conditions: tuple[Condition, ...]
    trials: int
    description: str
    # "episodes": independent trials; "clutter-runs": each trial is a run of repeated
    # attempts on one pile (grasped objects removed) until 3 consecutive failures.
    kind: str = "episodes"
    # Extra YAML overrides applied to the named scenario.
    scenario_text: str = ""
    # Isolation: trial i grasps test object i // 4, lying for i % 4 < 3, else upright
    # (`object_order` "blocked"); "interleaved": object i % K of the K test objects,
    # lying for (i // K) % 4 < 3, so any K trials cover every object once.
    per_object_poses: bool = False
    object_order: str = "blocked"
    max_consecutive_failures: int = 3
    # Clutter runs: a run also ends when the policy finds no grasp (the clutter-removal
    # protocol's rule; a one-shot detector's "missed: no grasp detected").
    end_on_no_detection: bool = False
    distance_only: bool = False
    paper: dict = field(default_factory=dict)
    # The controller settings its conditions run with (scenario.CONTROLLER_PROFILES):
    # "robot" for the paper's Table 1 robot runs; "" keeps the named scenario's (the
    # shipped scenarios: "sim", as the paper's simulation experiments).
    controller_profile: str = ""
    # The contact-simulation settings (scenario.PHYSICS_PROFILES); "" keeps the named
    # scenario's (the default profile). `evaluate --physics-profile` sets it.
    physics_profile: str = ""
    # Scenario patches applied, in order, to the conditions of their groups after the
    # profiles (`ScenarioPatch`; `option_patches` makes them of `evaluate`'s options).
    patches: tuple[ScenarioPatch, ...] = ()


def _sweep(name: str, values, make) -> tuple[Condition, ...]:
    out = []
    for policy in ("ctr", "gpd"):
        for v in values:
            out.append(make(f"{policy}/{name}={v:g}", policy, v))
    return tuple(out)


def _loop_sweep(name: str, param: str, field_name: str, values, description: str) -> Experiment:
    """A timing or calibration sweep: CTR and GPD at each value of the `Condition` field
    `field_name` (conditions "ctr/PARAM=value"), robot profile, isolation scenes with the
    test objects interleaved (any 10 trials cover every object)."""
    return Experiment(
        name=name, scenario="isolation", trials=40, per_object_poses=True,
        controller_profile="robot", object_order="interleaved", description=description,
        conditions=_sweep(param, values, lambda n, p, v: Condition(n, p, **{field_name: v})))


EXPERIMENTS: dict[str, Experiment] = {
    e.name: e
    for e in (
        Experiment(
            name="sim-distance", scenario="random", trials=400, distance_only=True,
            description="Figure 5 left: final distance to the nearest true grasp, with and "
                        "without the Gaussian kinematic noise (0.4); beyond the paper, "
                        "gpd-track with and without it.",
            conditions=(
                Condition("init", "init"),
                Condition("ctr", "ctr"),
                Condition("ctr_noise", "ctr", noise="gaussian"),
                Condition("gpd", "gpd"),
                Condition("gpd_noise", "gpd", noise="gaussian"),
                Condition("gpd-track", "gpd-track"),
                Condition("gpd-track_noise", "gpd-track", noise="gaussian"),
            ),
        ),
        Experiment(
            name="perception", scenario="random", trials=400, distance_only=True,
            description="Figure 5 right: the CNN's one-shot global best vs the same followed "
                        "by the closed-loop controller.",
            conditions=(Condition("cnn-only", "cnn-only"), Condition("cnn-ctr", "cnn-ctr")),
        ),
        Experiment(
            name="isolation", scenario="isolation", trials=40, per_object_poses=True,
            description="Table 1 row 1: the 10 test objects, each in 4 configurations "
                        "(3 lying, 1 upright); CTR with the robot's controller settings "
                        "(r = 0.5, 1 cm z steps) and, as ctr-sim, with the simulation's "
                        "(r = 0.2, 75 iterations); the scripted grasp planned from the "
                        "object's true pose shows what the station can hold.",
            conditions=(Condition("ctr", "ctr"),
                        Condition("ctr-sim", "ctr", controller_profile="sim"),
                        Condition("gpd", "gpd"),
                        Condition("scripted", "scripted")),
            paper={"ctr": 0.975, "gpd": 0.975}, controller_profile="robot",
        ),
        Experiment(
            name="clutter", scenario="clutter", trials=10, kind="clutter-runs",
            controller_profile="robot",
            scenario_text="{scene: {clutter_objects: 10, region_half_extent_m: 0.06}}",
            description="Table 1 row 2: 10 objects poured onto the table; attempts until 3 "
                        "consecutive failures or nothing left in view; 10 runs.",
            conditions=(Condition("ctr", "ctr"), Condition("gpd", "gpd")),
            paper={"ctr": 0.889, "gpd": 0.948},
        ),
        Experiment(
            name="clutter-shift", scenario="clutter_shift", trials=10, kind="clutter-runs",
            controller_profile="robot",
            scenario_text="{scene: {clutter_objects: 10, region_half_extent_m: 0.06}}",
            description="Table 1 row 3: as clutter, the sheet under the pile shifted after the "
                        "3rd controller iteration of every attempt.",
            conditions=(Condition("ctr", "ctr", disturbance="shift"),
                        Condition("gpd", "gpd", disturbance="shift")),
            paper={"ctr": 0.773, "gpd": 0.225},
        ),
        # The clutter-removal protocol of VGN (Breyer et al., CoRL 2020), GIGA and Edge
        # Grasp Network: 5 objects, a round (a run) ends when the table is clear, no grasp
        # is found or 2 grasps fail in a row; grasp success rate and percent cleared per
        # seed (`report_stats.clutter_runs`), mean +- std over 5 seeds of 100 rounds
        # (`analysis/removal_table.py`).
        Experiment(
            name="removal-pile", scenario="clutter", trials=100, kind="clutter-runs",
            controller_profile="robot", max_consecutive_failures=2, end_on_no_detection=True,
            scenario_text="{scene: {clutter_objects: 5}}",
            description="Clutter removal, pile: 5 objects poured onto the table; a round ends "
                        "when the table is clear, no grasp is found or 2 grasps fail in a row.",
            conditions=(Condition("ctr", "ctr"), Condition("gpd", "gpd"),
                        Condition("gpd-track", "gpd-track")),
        ),
        Experiment(
            name="removal-packed", scenario="clutter", trials=100, kind="clutter-runs",
            controller_profile="robot", max_consecutive_failures=2, end_on_no_detection=True,
            scenario_text="{scene: {kind: packed, clutter_objects: 5, region_half_extent_m: 0.08}}",
            description="Clutter removal, packed: 5 objects standing upright side by side; a "
                        "round ends when the table is clear, no grasp is found or 2 grasps "
                        "fail in a row.",
            conditions=(Condition("ctr", "ctr"), Condition("gpd", "gpd"),
                        Condition("gpd-track", "gpd-track")),
        ),
        Experiment(
            name="smoke", scenario="isolation", trials=3, per_object_poses=True,
            description="A tiny experiment for checking the pipeline: INIT and the scripted "
                        "grasp (no CNN), a few seconds per trial.",
            conditions=(Condition("init", "init"), Condition("scripted", "scripted")),
        ),
        Experiment(
            name="sweep-noise", scenario="isolation", trials=40, per_object_poses=True,
            description="Success vs the Gaussian kinematic noise scale.",
            conditions=_sweep("noise_scale", (0.0, 0.2, 0.4, 0.8), lambda n, p, v: Condition(
                n, p, noise="gaussian" if v > 0 else "none", noise_scale=v)),
        ),
        Experiment(
            name="sweep-depth-noise", scenario="isolation", trials=40, per_object_poses=True,
            description="Success vs depth-sensor noise (multiples of the default model).",
            conditions=_sweep("depth_noise", (0.0, 1.0, 2.0, 4.0), lambda n, p, v: Condition(
                n, p, depth_noise=v)),
        ),
        Experiment(
            name="sweep-offset", scenario="isolation", trials=40, per_object_poses=True,
            description="Success vs a constant kinematic offset (along the closing direction).",
            conditions=_sweep("offset_m", (0.0, 0.01, 0.02, 0.04), lambda n, p, v: Condition(
                n, p, noise="offset" if v > 0 else "none", offset_m=v)),
        ),
        # Timing and calibration (beyond the paper): the Table 1 controller settings
        # (robot profile), isolation scenes, objects interleaved.
        _loop_sweep("sweep-latency", "latency_s", "latency_s", (0.0, 0.1, 0.2, 0.25, 0.3),
                    "Success vs sensor-to-action latency: the policy deciding at t sees the "
                    "image taken at t - latency (control period 0.1 s)."),
        _loop_sweep("sweep-control-period", "period_s", "control_period_s",
                    (0.05, 0.1, 0.2, 0.5),
                    "Success vs the control period (the paper's robot loop: about 0.2 s); "
                    "each CTR step moves as far, within 0.8 periods."),
        _loop_sweep("sweep-dropped-frames", "dropped_frame_prob", "dropped_frame_prob",
                    (0.0, 0.25, 0.5, 0.75),
                    "Success vs the probability that a frame is lost (the policy then gets "
                    "the last frame that arrived, unaware that it is stale)."),
        _loop_sweep("sweep-camera-translation", "camera_translation_m",
                    "camera_translation_error_m", (0.0, 0.005, 0.01, 0.02),
                    "Success vs a camera-mount translation error (a direction drawn per "
                    "trial); the policy believes the nominal mount."),
        _loop_sweep("sweep-camera-rotation", "camera_rotation_deg", "camera_rotation_error_deg",
                    (0.0, 2.0, 5.0, 10.0),
                    "Success vs a camera-mount rotation error (about an axis drawn per "
                    "trial); the policy believes the nominal mount."),
    )
}


# Built-in policies that `evaluate --conditions` may add to an experiment whose own
# conditions do not include them (e.g. `cnn-ctr` in clutter); each runs as
# `plugin_condition` says, as a user policy does.
EXTRA_POLICIES = SENSOR_POLICIES


def plugin_condition(experiment: Experiment, spec: str) -> Condition:
    """The condition a user policy (``MODULE:FACTORY``, `drake_grasp.policies.plugins`), or a
    built-in policy of `EXTRA_POLICIES` the experiment does not list, runs as in
    `experiment`: named `plugins.condition_name(spec)` ("centroid_policy.make_policy"; a
    built-in: its own name), with the experiment's settings that all of its conditions
    share (disturbance, depth noise, controller profile), and no kinematic noise (the
    `KinematicNoise` system reads each commanded move's goal from the built-in
    controller's `X_WG_goal`, which a user policy does not have; a built-in added so runs
    noise-free too). Its trials get the same seeds, so the same scenes, as the others.

    Raises:
        ValueError: a malformed spec, or one whose name clashes with a condition of the
            experiment.
    """
    from drake_grasp.policies.plugins import condition_name

    if spec in EXTRA_POLICIES:
        if any(c.name == spec for c in experiment.conditions):
            raise ValueError(f"--conditions: {spec!r} is already a condition of experiment "
                             f"{experiment.name}; it runs as the experiment defines it")
        name = spec
    else:
        name = condition_name(spec)
    if any(c.name == name for c in experiment.conditions):
        raise ValueError(f"--conditions: user policy {spec!r} would be named {name!r}, which is "
                         f"already a condition of experiment {experiment.name}")
    shared = {}
    for key in ("depth_noise", "disturbance", "controller_profile", "control_period_s",
                "latency_s", "dropped_frame_prob", "camera_translation_error_m",
                "camera_rotation_error_deg"):
        values = {getattr(c, key) for c in experiment.conditions}
        if len(values) == 1:
            shared[key] = values.pop()
    return Condition(name, spec, **shared)


def get_experiment(name: str) -> Experiment:
    if name not in EXPERIMENTS:
        raise ValueError(f"--experiment: unknown {name!r}; known: {sorted(EXPERIMENTS)}")
    return EXPERIMENTS[name]


def trial_seed(base_seed: int, index: int) -> int:
    """Seed of trial `index` (the same for every condition: paired comparisons)."""
    return int(np.random.default_rng([int(base_seed), int(index), 71]).integers(2**31 - 1))


def condition_scenario(experiment: Experiment, condition: Condition, *,
                       objects_dir: str | None = None) -> Scenario:
    """What every trial of `condition` shares: its resolved scenario before the per-trial
    parts are applied.

    The per-trial parts, which `trial_scenario` adds, are the seed (0 here) and, for
    `per_object_poses` experiments, the object and its pose chosen from the trial index
    (here `scene.object_ids` and `scene.pose` are as the named scenario has them). This is
    what `drake_grasp.evaluation.run_folder` hashes into a record's `config_hash` and compares when
    a run is resumed.
    """
    s = load_scenario(scenario_name=experiment.scenario, scenario_text=experiment.scenario_text,
                      controller_profile=condition.controller_profile
                      or experiment.controller_profile,
                      physics_profile=experiment.physics_profile)
    s = dataclasses.replace(s, seed=0, policy=condition.policy)
    for patch in experiment.patches:
        if patch.applies_to(condition.policy):
            s = patch.apply(s)
    if objects_dir:
        s = dataclasses.replace(s, objects_dir=str(objects_dir))
    s.noise = dataclasses.replace(s.noise, kind=condition.noise,
                                  gaussian_scale=condition.noise_scale,
                                  offset_xy_m=[condition.offset_m, 0.0])
    if condition.depth_noise > 0:
        k = condition.depth_noise
        d = s.depth_noise
        s.depth_noise = dataclasses.replace(
            d, enabled=True, sigma_base_m=k * d.sigma_base_m,
            sigma_quadratic_per_m2=k * d.sigma_quadratic_per_m2,
            edge_dropout_prob=min(1.0, k * d.edge_dropout_prob),
            random_dropout_prob=min(1.0, k * d.random_dropout_prob))
    s.disturbance = dataclasses.replace(s.disturbance, kind=condition.disturbance)
    if condition.control_period_s > 0:
        s.controller = dataclasses.replace(s.controller, period_s=condition.control_period_s)
    if condition.latency_s > 0 or condition.dropped_frame_prob > 0:
        s.timing = dataclasses.replace(s.timing, latency_s=condition.latency_s,
                                       dropped_frame_prob=condition.dropped_frame_prob)
    if condition.camera_translation_error_m > 0 or condition.camera_rotation_error_deg > 0:
        s.calibration = dataclasses.replace(
            s.calibration, camera_translation_error_m=condition.camera_translation_error_m,
            camera_rotation_error_deg=condition.camera_rotation_error_deg)
    s.validate()
    return s


def trial_scenario(experiment: Experiment, condition: Condition, index: int, *,
                   base_seed: int, objects_dir: str | None = None, library=None) -> Scenario:
    """The exact scenario of trial `index` of `condition`: `condition_scenario` plus the
    trial's seed and, for `per_object_poses` experiments, its object and pose."""
    s = condition_scenario(experiment, condition, objects_dir=objects_dir)
    s = dataclasses.replace(s, seed=trial_seed(base_seed, index))
    if experiment.per_object_poses:
        if library is None:
            from drake_grasp.objects import load_library

            library = load_library(objects_dir)
        ids = library.ids(split=s.scene.split or None)
        if not ids:
            raise ValueError(f"the object library has no {s.scene.split!r} objects")
        # 10 test objects x (3 lying + 1 upright), round-robin over the library's objects.
        per_category = _one_per_category(ids)
        k = len(per_category)
        if experiment.object_order == "interleaved":
            obj = per_category[index % k]
            pose = "lying" if (index // k) % 4 < 3 else "upright"
        else:
            obj = per_category[(index // 4) % k]
            pose = "lying" if index % 4 < 3 else "upright"
        s.scene = dataclasses.replace(s.scene, object_ids=[obj], pose=pose)
    s.validate()
    return s


def _one_per_category(ids: list[str]) -> list[str]:
    """The first object id of each category (ids are `<category>_<index>`), else all."""
    seen, out = set(), []
    for i in ids:
        cat = i.rsplit("_", 1)[0]
        if cat not in seen:
            seen.add(cat)
            out.append(i)
    return out if len(out) > 1 else list(ids)


def option_patches(*, weights: str = "", gpd_weights: str = "", mirror_average: bool = False,
                   converge_iterations: int = -1, distance_samples: int = 0,
                   hand_check: bool = False, ctr_text: str = "", failure_memory_m: float = 0.0,
                   gpd_fallback: bool | None = None) -> tuple[ScenarioPatch, ...]:
    """The scenario patches of `evaluate`'s options, checked here so that a bad value is
    refused, naming its option, before any folder is made (the defaults make none).

    weights: distance-CNN weights (FILE or FILE,FILE,... for an ensemble) of the CNN
    conditions; gpd_weights: the GPD classifier's of the gpd conditions; mirror_average:
    the CNN conditions score with `controller.mirror_average`; converge_iterations >= 0:
    the closed-loop conditions' `controller.converge_iterations` (-1: unchanged);
    distance_samples > 0: every judge's `distance_grasp_samples`; hand_check: the
    closed-loop conditions' `controller.hand_check`; ctr_text: a YAML mapping of controller
    settings for the closed-loop conditions, applied after those; failure_memory_m in
    (0, 0.1]: every condition's `failure_memory.radius_m`; gpd_fallback: the gpd
    conditions' `gpd.fallback_best` (None: unchanged).

    Raises:
        ValueError: a weights file that does not exist, or a value out of range.
    """
    import json
    from pathlib import Path

    if weights:
        from drake_grasp.policies.evaluator import weights_files

        try:
            files = weights_files(weights)
        except ValueError as e:
            raise ValueError(f"--weights {weights}: {e}") from None
        from drake_grasp.core.assets import missing_weights_message, repository_model

        for f in files:
            if not Path(f).is_file() and repository_model(f) is not None:
                raise ValueError(f"--weights {weights}: {missing_weights_message(f)}")
            if not Path(f).is_file():
                raise ValueError(f"--weights {weights}: {f}: no such file (expected CNN weights: "
                                 "*.safetensors from `drake-grasp train`, or *.onnx; several "
                                 "separated by commas for an ensemble)")
    if gpd_weights and not Path(gpd_weights).is_file():
        raise ValueError(f"--gpd-weights {gpd_weights}: no such file (expected GPD "
                         "classifier weights: *.safetensors from `drake-grasp gpd-train`)")
    if converge_iterations < -1:
        raise ValueError(f"--converge: expected >= 0 iterations, got {converge_iterations}")
    if distance_samples < 0:
        raise ValueError(f"--distance-samples: expected a positive number of surface points, "
                         f"got {distance_samples}")
    if failure_memory_m and not 0.0 < failure_memory_m <= 0.1:
        raise ValueError(f"--failure-memory: expected a radius in (0, 0.1] m, got "
                         f"{failure_memory_m}")

    def patch(group: str, option: str, section: str, **values) -> ScenarioPatch:
        return ScenarioPatch(group, json.dumps(values), section, option)  # JSON is YAML

    out = []
    if weights:
        out.append(patch("cnn", f"--weights {weights}", "controller", weights=str(weights)))
    if mirror_average:
        out.append(patch("cnn", "--mirror-average", "controller", mirror_average=True))
    if converge_iterations >= 0:
        out.append(patch("closed-loop", f"--converge {converge_iterations}", "controller",
                         converge_iterations=int(converge_iterations)))
    if hand_check:
        out.append(patch("closed-loop", "--hand-check", "controller", hand_check=True))
    if ctr_text and ctr_text.strip():
        shown = ctr_text if len(ctr_text) <= 80 else ctr_text[:77] + "..."
        out.append(ScenarioPatch("closed-loop", ctr_text, "controller", f"--ctr-text {shown!r}"))
    if gpd_weights:
        out.append(patch("gpd", f"--gpd-weights {gpd_weights}", "gpd", weights=str(gpd_weights)))
    if gpd_fallback is not None:
        out.append(patch("gpd", "--gpd-fallback", "gpd", fallback_best=bool(gpd_fallback)))
    if distance_samples > 0:
        out.append(patch("all", f"--distance-samples {distance_samples}", "judge",
                         distance_grasp_samples=int(distance_samples)))
    if failure_memory_m:
        out.append(patch("all", f"--failure-memory {failure_memory_m}", "failure_memory",
                         radius_m=float(failure_memory_m)))
    return tuple(out)
