"""The grasp lab's Diagram, built once per scene and reused by every check in it.

`GraspLab` builds the lab's plant (the 2F-85 on its floating base, the table and sheet,
the scene's objects), the base's trajectory source, the gravity feed-forward and the
gripper controller once; each `GraspLab.check` loads a new base trajectory and gripper
command into the two trajectory sources and simulates in a fresh Context (a new
`Simulator`), so nothing of one check's state reaches the next. The Diagram's systems
keep no state outside the Context (the trajectories are the sources' parameters, set
before each check), which is what makes the reuse exact: a reused Diagram gives the
same trajectory, bit for bit, as one built for the check alone (`tests/test_lab_reuse.py`).
Building took 4-8% of a check (the gripper and object models parsed, the plant finalized);
`evaluation.lab.check_grasp` is a `GraspLab` used once.

The phases, the judge and the failure classes are described in `evaluation.lab`.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import numpy as np

from drake_grasp.config.physics import apply_hydroelastic_margin, sheet_collision, table_collision
from drake_grasp.config.scenario import Scenario
from drake_grasp.objects import ObjectLibrary
from drake_grasp.systems.judge import pad_contacts, pad_squeeze_n
from drake_grasp.world.scene import (
    OBJECT_BODY_NAME,
    SceneSpec,
    add_scene_objects,
    set_object_poses,
)
from drake_grasp.world.table import add_table_and_sheet, connect_sheet_hold

GRIPPER_URI = "package://drake_grasp/robotiq_2f85/robotiq_2f85.urdf"
FAILURES = ("missed", "slipped-during-lift", "slipped-during-hold", "dropped-by-shake",
            "simulation-error")
# The shake's segments: each a one-cycle sine of one base joint (x, y, z: translation;
# yaw, pitch, roll: rotation), in the order `LabConfig.shake_axes` lists them.
SHAKE_AXES = ("x", "y", "z", "yaw", "pitch", "roll")


@dataclass
class LabConfig:
    """Timing and shake amplitudes of one lab check."""

    approach_m: float = 0.10
    descend_s: float = 1.0
    close_s: float = 1.2
    lift_m: float = 0.15
    lift_s: float = 1.0
    hold_s: float = 0.5
    shake_translation_m: float = 0.02
    shake_translation_period_s: float = 0.25
    shake_rotation_rad: float = 0.25
    shake_rotation_period_s: float = 0.4
    # Base PD gains: translation [N/m, N s/m], rotation [N m/rad, N m s/rad].
    kp_translation: float = 2.0e4
    kd_translation: float = 400.0
    kp_rotation: float = 500.0
    kd_rotation: float = 5.0
    # Discrete step of the lab's plant [s]; None keeps the scenario's `plant.time_step`
    # (its physics profile's: 5 ms "fast", 2 ms "reference"). 5 ms gave the same held /
    # not-held verdict as 2 ms on 15 of 15 sampled grasps (can, mug, hammer) at 2.5x less
    # wall time; 10 ms disagreed on 3 of 15.
    time_step_s: float | None = None
    # The closing phase ends early once the grasp has settled: both pads touch the object
    # and, over the last `close_settle_s`, the opening changed by less than 0.1 mm and each
    # pad's squeeze by less than 2% (checked every `close_check_s`). The base then lifts
    # from there on the same schedule; up to that moment the check is the fixed one's.
    # None keeps the fixed `close_s` (the closing time of every check before 2026-11-25).
    close_settle_s: float | None = 0.1
    close_check_s: float = 0.025
    # The shake's segments, in order (names from SHAKE_AXES); the judge looks after each
    # one and the check ends at the first failure. Without roll, the last segment (0.4 s),
    # a check is about 8% shorter, but 2 of the 587 recorded label-check grasps (rejected
    # candidates) that only roll drops would hold (`analysis/results/lab-speed-2026-12-07/`):
    # all six stay, so every verdict is as before.
    shake_axes: tuple = SHAKE_AXES

    def __post_init__(self):
        self.shake_axes = tuple(self.shake_axes)
        unknown = [a for a in self.shake_axes if a not in SHAKE_AXES]
        if unknown or len(set(self.shake_axes)) != len(self.shake_axes):
            raise ValueError(f"LabConfig.shake_axes: expected distinct names from {SHAKE_AXES}, "
                             f"got {list(self.shake_axes)}")


@dataclass
class GraspCheckResult:
    """Outcome of one lab check: `held`, the failure class ("" when held), details."""

    held: bool
    failure: str
    details: dict = field(default_factory=dict)


def _shake_segments(lab: LabConfig) -> list[tuple[str, int, float, float]]:
    """(name, base joint index, amplitude, period) of each shake segment, in order."""
    out = []
    for name in lab.shake_axes:
        i = SHAKE_AXES.index(name)
        out.append((name, i) + ((lab.shake_translation_m, lab.shake_translation_period_s)
                                if i < 3 else (lab.shake_rotation_rad, lab.shake_rotation_period_s)))
    return out


def _base_trajectory(X_WB_grasp, lab: LabConfig, t_close_end: float):
    """Desired [q; v] of the six base joints over the whole check, and the phase ends
    (with `shake_segments`: each shake segment's name and end time)."""
    from pydrake.math import RollPitchYaw
    from pydrake.trajectories import PiecewisePolynomial

    rpy = RollPitchYaw(X_WB_grasp.rotation()).vector()
    p_grasp = X_WB_grasp.translation()
    approach = X_WB_grasp.rotation().matrix()[:, 2]
    p_start = p_grasp - lab.approach_m * approach
    q_grasp = np.concatenate([p_grasp, rpy[::-1]])  # x, y, z, yaw, pitch, roll
    q_start = np.concatenate([p_start, rpy[::-1]])
    q_lift = q_grasp + np.array([0, 0, lab.lift_m, 0, 0, 0])

    t_descend = lab.descend_s
    t_close = t_descend + t_close_end
    t_lift = t_close + lab.lift_s
    t_hold = t_lift + lab.hold_s
    shakes = _shake_segments(lab)
    ends = t_hold + np.cumsum([T for *_, T in shakes])
    t_shake = float(ends[-1]) if shakes else t_hold

    def smooth(u):
        u = np.clip(u, 0.0, 1.0)
        return u * u * (3 - 2 * u)

    def q_of(t):
        """(6, N) joint positions at the N times `t` (vectorized: built twice per check)."""
        t = np.asarray(t, dtype=float)
        q = np.empty((len(t), 6))
        descend = t <= t_descend
        close = ~descend & (t <= t_close)
        lift = ~descend & ~close & (t <= t_lift)
        after = ~(descend | close | lift)
        q[descend] = q_start + smooth(t[descend] / t_descend)[:, None] * (q_grasp - q_start)
        q[close] = q_grasp
        q[lift] = q_grasp + smooth((t[lift] - t_close) / lab.lift_s)[:, None] * (q_lift - q_grasp)
        q[after] = q_lift
        t0 = t_hold
        for _, i, amplitude, period in shakes:
            m = after & (t >= t0) & (t < t0 + period)
            q[m, i] += amplitude * np.sin(2 * np.pi * (t[m] - t0) / period)
            t0 += period
        return q.T

    times = np.arange(0.0, t_shake + 0.1, 0.005)
    Q = q_of(times)
    h = 1e-5
    V = (q_of(times + h) - q_of(times - h)) / (2 * h)
    V[:, times <= h] = 0.0
    traj = PiecewisePolynomial.CubicHermite(times, Q, V)
    phases = {"descend": t_descend, "close": t_close, "lift": t_lift, "hold": t_hold,
              "shake": t_shake,
              "shake_segments": [(name, float(e)) for (name, *_), e in zip(shakes, ends)]}
    return traj, q_start, phases


def _add_floating_base(plant, base_instance, gripper, lab: LabConfig) -> list:
    """Six PD-actuated joints (x, y, z, yaw, pitch, roll) from the world to the gripper's
    base: the floating hand of the lab. Returns the joints, in that order."""
    from pydrake.multibody.tree import (
        PdControllerGains,
        PrismaticJoint,
        RevoluteJoint,
        SpatialInertia,
    )

    link_inertia = SpatialInertia.SolidSphereWithMass(0.01, 0.01)
    parent = plant.world_frame()
    joints = []
    axes = [("x", PrismaticJoint, [1, 0, 0]), ("y", PrismaticJoint, [0, 1, 0]),
            ("z", PrismaticJoint, [0, 0, 1]), ("yaw", RevoluteJoint, [0, 0, 1]),
            ("pitch", RevoluteJoint, [0, 1, 0]), ("roll", RevoluteJoint, [1, 0, 0])]
    for k, (name, kind, axis) in enumerate(axes):
        child = plant.AddRigidBody(f"base_{name}", base_instance, link_inertia).body_frame()
        joint = plant.AddJoint(kind(f"base_{name}", parent, child, axis))
        if kind is PrismaticJoint:
            joint.set_position_limits([-np.inf], [np.inf])
        actuator = plant.AddJointActuator(f"base_{name}", joint)
        kp, kd = ((lab.kp_translation, lab.kd_translation) if k < 3
                  else (lab.kp_rotation, lab.kd_rotation))
        actuator.set_controller_gains(PdControllerGains(p=kp, d=kd))
        joints.append(joint)
        parent = child
    plant.WeldFrames(parent, plant.GetFrameByName("robotiq_base", gripper))
    return joints


def _add_gravity_feedforward(builder, plant, gripper, base_instance) -> None:
    """A constant upward force on the base's z joint that carries the moving mass."""
    from pydrake.systems.primitives import ConstantVectorSource

    moving_mass = sum(plant.get_body(b).default_mass() for b in
                      plant.GetBodyIndices(gripper) + plant.GetBodyIndices(base_instance))
    g = float(np.linalg.norm(plant.gravity_field().gravity_vector()))
    ff = np.zeros(6)
    ff[2] = moving_mass * g
    gravity_ff = builder.AddNamedSystem("gravity_feedforward", ConstantVectorSource(ff))
    builder.Connect(gravity_ff.get_output_port(), plant.get_actuation_input_port(base_instance))


def _gripper_command(open_w: float, phases: dict, force: float):
    """The gripper's command: open until the descent ends, then closed with `force`."""
    from pydrake.trajectories import PiecewisePolynomial

    return PiecewisePolynomial.ZeroOrderHold(
        [0.0, phases["descend"], phases["shake"] + 1.0],
        np.array([[open_w, 0.0, 0.0], [force, force, force]]))


def _add_gripper(builder, plant, gripper, scenario: Scenario, phases: dict, force: float):
    """The gripper controller and its command source (`_gripper_command`); returns the
    source, whose trajectory each check replaces."""
    from pydrake.systems.primitives import TrajectorySource

    from drake_grasp.systems.gripper import GripperController

    finger = plant.GetJointActuatorByName("left_finger_actuator", gripper)
    grip = builder.AddNamedSystem("gripper_controller", GripperController(
        kp=finger.get_controller_gains().p, closing_speed_m_s=scenario.gripper.closing_speed_m_s,
        initial_width_m=scenario.gripper.open_width_m, time_step=plant.time_step(),
        force_mode=scenario.gripper.force_mode))
    command = _gripper_command(scenario.gripper.open_width_m, phases, force)
    command_source = builder.AddNamedSystem("gripper_command", TrajectorySource(command))
    builder.Connect(command_source.get_output_port(), grip.GetInputPort("gripper_command"))
    builder.Connect(plant.get_state_output_port(gripper), grip.GetInputPort("gripper_state"))
    builder.Connect(grip.GetOutputPort("desired_state"), plant.get_desired_state_input_port(gripper))
    return command_source


class GraspLab:
    """The grasp lab's Diagram for one settled scene, built once; `check` executes grasps.

    Args:
        scene: the settled scene.
        scenario: plant config, grip force, closing speed, open width, judge thresholds.
        library: the object library the scene's objects come from.
        lab: the check's timing and shake.
        loaded: indices of `scene.objects` to load (None: all of them). A check grasps
            one of these; the others stay where the scene settled them.
    """

    def __init__(self, scene: SceneSpec, *, scenario: Scenario | None = None,
                 library: ObjectLibrary, lab: LabConfig | None = None, loaded=None):
        self.scenario = scenario if scenario is not None else Scenario()
        self.lab = lab if lab is not None else LabConfig()
        self.loaded = (list(range(len(scene.objects))) if loaded is None
                       else [int(i) for i in loaded])
        bad = [i for i in self.loaded if not 0 <= i < len(scene.objects)]
        if bad or not self.loaded:
            raise ValueError(f"GraspLab: loaded objects {self.loaded} must be indices into the "
                             f"scene's {len(scene.objects)} objects (at least one)")
        self.scene = scene
        self._spec = SceneSpec(kind=scene.kind, seed=scene.seed,
                               center_xy_m=list(scene.center_xy_m),
                               objects=[scene.objects[i] for i in self.loaded],
                               settled=scene.settled)
        self._build(library)

    def _build(self, library: ObjectLibrary) -> None:
        from pydrake.multibody.plant import AddMultibodyPlant
        from pydrake.systems.framework import DiagramBuilder
        from pydrake.systems.primitives import TrajectorySource

        from drake_grasp.core.assets import make_parser

        scenario, lab = self.scenario, self.lab
        builder = DiagramBuilder()
        plant_config = scenario.plant
        if lab.time_step_s is not None:
            plant_config = copy.deepcopy(scenario.plant)
            plant_config.time_step = float(lab.time_step_s)
        plant, scene_graph = AddMultibodyPlant(plant_config, builder)
        plant.set_name("plant")
        (gripper,) = make_parser(plant).AddModels(url=GRIPPER_URI)
        base_instance = plant.AddModelInstance("lab_base")
        self._X_BG = plant.GetFrameByName("grasp_frame", gripper).GetFixedPoseInBodyFrame()
        self._joints = _add_floating_base(plant, base_instance, gripper, lab)
        _, sheet = add_table_and_sheet(plant, scene_graph, self._spec.center_xy_m,
                                       sheet_collision=sheet_collision(scenario.physics,
                                                                       sheet_moves=False),
                                       table_collision=table_collision(scenario.physics))
        self._instances = add_scene_objects(plant, self._spec, library)
        plant.Finalize()
        apply_hydroelastic_margin(plant, scene_graph, scenario.physics.hydroelastic_margin_m,
                                  [gripper])
        connect_sheet_hold(builder, plant, sheet)
        _add_gravity_feedforward(builder, plant, gripper, base_instance)
        # Placeholder trajectories with each check's shape; `check` replaces both.
        from pydrake.math import RigidTransform

        traj, _, phases = _base_trajectory(RigidTransform(), lab, self._close_time())
        self._base_source = builder.AddNamedSystem("base_trajectory", TrajectorySource(traj, 1))
        builder.Connect(self._base_source.get_output_port(),
                        plant.get_desired_state_input_port(base_instance))
        self._command_source = _add_gripper(builder, plant, gripper, scenario, phases,
                                            scenario.gripper.grip_force_n)
        self.diagram = builder.Build()
        self.diagram.set_name("grasp_lab")
        self.plant, self._gripper = plant, gripper

    def _close_time(self) -> float:
        """The fixed closing phase's length: `close_s`, or longer if the fingers need it."""
        g = self.scenario.gripper
        return max(self.lab.close_s, g.open_width_m / g.closing_speed_m_s + 0.3)

    def check(self, X_WG, *, object_index: int = 0,
              grip_force_n: float | None = None) -> GraspCheckResult:
        """Executes the grasp X_WG (grasp frame: z_G approach, x_G closing) on
        `scene.objects[object_index]`, in a fresh Context of the Diagram.

        Args:
            X_WG: the grasp pose, a RigidTransform or a 4x4 matrix (as in `GraspSet.poses`).
            object_index: the object to grasp; it must be one of `loaded`.
            grip_force_n: overrides `scenario.gripper.grip_force_n`.
        """
        from pydrake.math import RigidTransform
        from pydrake.multibody.tree import PrismaticJoint
        from pydrake.systems.analysis import Simulator

        if int(object_index) not in self.loaded:
            raise ValueError(f"object_index: got {object_index}; this lab loaded the scene's "
                             f"objects {self.loaded} (of {len(self.scene.objects)})")
        scenario, lab, plant = self.scenario, self.lab, self.plant
        force = float(scenario.gripper.grip_force_n if grip_force_n is None else grip_force_n)
        X_WG = X_WG if isinstance(X_WG, RigidTransform) else RigidTransform(np.asarray(X_WG))
        t_wall = time.perf_counter()
        X_WB = X_WG @ self._X_BG.inverse()
        traj, q_start, phases = _base_trajectory(X_WB, lab, self._close_time())
        self._base_source.UpdateTrajectory(traj)
        self._command_source.UpdateTrajectory(
            _gripper_command(scenario.gripper.open_width_m, phases, force))

        simulator = Simulator(self.diagram)
        context = simulator.get_mutable_context()
        plant_context = plant.GetMyMutableContextFromRoot(context)
        for joint, q in zip(self._joints, q_start):
            joint.set_translation(plant_context, q) if isinstance(joint, PrismaticJoint) \
                else joint.set_angle(plant_context, q)
        nq = plant.num_positions(self._gripper)
        plant.SetPositions(plant_context, self._gripper,
                           np.full(nq, 0.5 * scenario.gripper.open_width_m))
        set_object_poses(plant, plant_context, self._spec, self._instances)
        target = self.loaded.index(int(object_index))
        body = plant.GetBodyByName(OBJECT_BODY_NAME, self._instances[target])
        placement = self.scene.objects[int(object_index)]
        details = {"object_id": placement.object_id, "grip_force_n": force,
                   "X_WG": np.asarray(X_WG.GetAsMatrix4()).round(6).tolist()}
        failure, phases = _run_checks(simulator, plant, plant_context, self._gripper, body, lab,
                                      scenario, phases, X_WB=X_WB, base_source=self._base_source,
                                      z_rest=float(placement.xyz[2]), details=details)
        details["close_end_s"] = round(phases["close"], 4)
        details["sim_time_s"] = round(context.get_time(), 4)
        details["wall_s"] = round(time.perf_counter() - t_wall, 3)
        return GraspCheckResult(held=failure == "", failure=failure, details=details)


def _judge(plant, plant_context, gripper, body, z_rest: float, phase: str,
           details: dict) -> tuple[int, float]:
    """Records the object's pads, the opening, the squeeze and the rise under `phase`_*
    in `details`; returns (pads touching, rise)."""
    pads = pad_contacts(plant, plant_context, body)
    rise = float(plant.EvalBodyPoseInWorld(plant_context, body).translation()[2]) - z_rest
    details[f"{phase}_pads"] = sorted(pads)
    details[f"{phase}_width_m"] = round(
        2.0 * float(plant.GetPositions(plant_context, gripper)[0]), 5)
    details[f"{phase}_squeeze_n"] = {
        k: round(v, 2) for k, v in sorted(pad_squeeze_n(plant, plant_context, body).items())}
    details[f"{phase}_rise_m"] = round(rise, 5)
    return len(pads), rise


def _run_checks(simulator, plant, plant_context, gripper, body, lab: LabConfig,
                scenario: Scenario, phases: dict, *, X_WB, base_source, z_rest: float,
                details: dict) -> tuple[str, dict]:
    """Simulates close, lift, hold and shake, recording each phase's pads, width, squeeze
    and rise in `details`; stops at the first failed check (in the shake: after the
    first segment that fails, named in `details["shake_failed_after"]`). Returns (failure
    class, "" when held; the phase times, moved earlier when the close settled early)."""
    checks = [("close", "missed", False), ("lift", "slipped-during-lift", True),
              ("hold", "slipped-during-hold", True), ("shake", "dropped-by-shake", True)]
    failure = ""
    try:
        simulator.Initialize()
        for phase, failure_name, need_lift in checks:
            if phase == "close" and lab.close_settle_s is not None:
                settled_at = _close_until_settled(simulator, plant, plant_context, gripper, body,
                                                  lab, phases)
                if settled_at is not None and settled_at < phases["close"] - 1e-9:
                    traj, _, phases = _base_trajectory(X_WB, lab, settled_at - phases["descend"])
                    base_source.UpdateTrajectory(traj)
            ends = ((phases["shake_segments"] or [("shake", phases["shake"])])
                    if phase == "shake" else [(phase, phases[phase])])
            for name, t_end in ends:
                simulator.AdvanceTo(t_end)
                pads, rise = _judge(plant, plant_context, gripper, body, z_rest, phase, details)
                if pads < 2 or (need_lift and rise < scenario.judge.min_lift_m):
                    failure = failure_name
                    if phase == "shake":
                        details["shake_failed_after"] = name
                    break
            if failure:
                break
    except RuntimeError as e:
        failure = "simulation-error"
        details["error"] = str(e)
    return failure, phases


def _close_until_settled(simulator, plant, plant_context, gripper, body, lab: LabConfig,
                         phases: dict) -> float | None:
    """Advances through the closing phase in `lab.close_check_s` steps until the grasp has
    settled (`LabConfig.close_settle_s`); returns that time, or None if it did not settle
    before the fixed phase end `phases["close"]`."""
    window = max(1, round(lab.close_settle_s / lab.close_check_s))
    history = []  # (opening, squeeze per pad) at each check
    t = simulator.get_context().get_time()
    while t + lab.close_check_s < phases["close"] - 1e-9:
        t += lab.close_check_s
        simulator.AdvanceTo(t)
        squeeze = pad_squeeze_n(plant, plant_context, body)
        width = 2.0 * float(plant.GetPositions(plant_context, gripper)[0])
        history.append((width, squeeze) if len(squeeze) >= 2 else None)
        recent = history[-(window + 1):]
        if len(recent) < window + 1 or any(h is None for h in recent):
            continue
        w0, f0 = recent[0]
        calm = all(abs(w - w0) < 1e-4 and f.keys() == f0.keys()
                   and all(abs(f[k] - f0[k]) <= 0.02 * max(f0[k], 1e-6) for k in f0)
                   for w, f in recent[1:])
        if calm:
            return t
    return None


__all__ = ["FAILURES", "GRIPPER_URI", "SHAKE_AXES", "GraspCheckResult", "GraspLab", "LabConfig"]
