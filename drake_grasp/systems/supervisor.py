"""The scripted grasp: approach from above using the object's true pose, close, lift, hold.

The predefined grasp motion (descend, close, lift, hold) is the same one every policy
ends with; here it follows a plan made from the object's true pose, which makes it the
physics check for everything else: if this fails, the contact model is wrong. Whether
the grasp held is not decided here: the `GraspJudge` (systems/judge.py) watches the
contacts and reads the motion's phase from the policy's `control_status` output.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem

from drake_grasp.geometry.topdown import plan_topdown_grasp
from drake_grasp.config.sections import GripperConfig, ScriptedGraspConfig
from drake_grasp.systems.state import shared_when_copied

# The phases of the shared grasp motion, as every policy reports them in the third entry
# of its `control_status` output (the index into this tuple): "approach" covers
# everything before the final descent (CTR's iterations, a one-shot move).
MOTION_PHASES = ("approach", "descend", "close", "lift", "hold", "done")


def motion_phase_code(name: str) -> float:
    """The `control_status` value of a motion phase (its index in `MOTION_PHASES`)."""
    return float(MOTION_PHASES.index(name))


def motion_phase_name(code: float) -> str:
    """The motion phase a `control_status` value stands for."""
    i = int(round(float(code)))
    if not 0 <= i < len(MOTION_PHASES):
        raise ValueError(f"control_status: motion phase {code!r} is not one of 0..{len(MOTION_PHASES) - 1}")
    return MOTION_PHASES[i]


class Mode(enum.Enum):
    APPROACH = "approach"
    DESCEND = "descend"
    CLOSE = "close"
    LIFT = "lift"
    HOLD = "hold"
    DONE = "done"


@shared_when_copied
@dataclass(frozen=True)
class SupervisorState:
    """Everything the supervisor remembers; lives in the Context's abstract state."""

    mode: Mode = Mode.APPROACH
    mode_start_s: float = 0.0
    X_WG_grasp: RigidTransform | None = None
    outcome: dict = field(default_factory=dict)


def grasp_motion_next(mode: str, elapsed: float, motion: ScriptedGraspConfig,
                      finger_speed: float) -> str | None:
    """The predefined grasp motion every policy ends with: the phase that follows `mode`
    ("descend" -> "close" -> "lift" -> "hold" -> "done") once its time is up, or None.
    Closing ends when the fingers have stopped (after 0.3 s) or after `close_time_s`."""
    if mode == "descend" and elapsed >= motion.descend_time_s:
        return "close"
    if mode == "close" and ((elapsed > 0.3 and finger_speed < 1e-3)
                            or elapsed >= motion.close_time_s):
        return "lift"
    if mode == "lift" and elapsed >= motion.lift_time_s:
        return "hold"
    if mode == "hold" and elapsed >= motion.hold_time_s:
        return "done"
    return None


def min_jerk(s: float) -> float:
    """Smooth 0 -> 1 time scaling with zero start/end velocity and acceleration."""
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def interpolate_pose(X_a: RigidTransform, X_b: RigidTransform, s: float) -> RigidTransform:
    """Pose between X_a (s=0) and X_b (s=1): linear position, slerp rotation."""
    p = (1.0 - s) * X_a.translation() + s * X_b.translation()
    qa = X_a.rotation().ToQuaternion()
    qb = X_b.rotation().ToQuaternion()
    if np.dot(qa.wxyz(), qb.wxyz()) < 0.0:
        qb = Quaternion(-qb.wxyz())
    return RigidTransform(RotationMatrix(qa.slerp(s, qb)), p)


class ScriptedGraspSupervisor(LeafSystem):
    """Grasps one object from above, planned from its true pose (an oracle by design):
    a grasp planned outside from the scene's true poses (`X_WG_planned`, e.g. a
    ground-truth grasp), else `plan_topdown_grasp` on the object's points at
    initialization (with `object_com_O`, the object's centre of mass in its frame, for
    objects that fit the stroke only slice by slice).

    Modes (abstract state): approach -> descend -> close -> lift -> hold -> done. The
    `GraspJudge` decides whether the grasp held.

    Input ports:
        body_poses: the plant's body poses (std::vector<RigidTransform>); read once, at
            initialization, to plan the grasp from the object's true pose.
        gripper_state: [q_left, q_right, v_left, v_right] of the 2F-85 fingers.
    Output ports:
        X_WG_desired: desired grasp-frame pose (RigidTransform) for differential IK.
        gripper_command: [width_m, grip_force_n].
        control_status: [control step, approaching, motion phase]: the number of periods
            since the start, 1 until the gripper starts closing (else 0), and the phase of
            the shared grasp motion (`MOTION_PHASES` index).
    """

    def __init__(self, *, object_body_index, object_points_O: np.ndarray,
                 X_WG_start: RigidTransform, motion: ScriptedGraspConfig,
                 gripper: GripperConfig, table_z: float = 0.0, period_s: float = 0.01,
                 X_WG_planned: RigidTransform | None = None,
                 object_com_O: np.ndarray | None = None):
        super().__init__()
        self._com_O = None if object_com_O is None else np.asarray(object_com_O, float).reshape(3)
        self._X_WG_planned = X_WG_planned
        self._object = int(object_body_index)
        self._points_O = np.asarray(object_points_O, dtype=float)
        self._X_WG_start = X_WG_start
        self._motion = motion
        self._gripper = gripper
        self._table_z = float(table_z)
        self._period = float(period_s)
        self._body_poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()]))
        self._gripper_state = self.DeclareVectorInputPort("gripper_state", 4)
        self._state = self.DeclareAbstractState(AbstractValue.Make(SupervisorState()))
        self.DeclareInitializationUnrestrictedUpdateEvent(self._Initialize)
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, 0.0, self._Update)
        self.DeclareAbstractOutputPort(
            "X_WG_desired", lambda: AbstractValue.Make(RigidTransform()), self._CalcPose,
            {self.abstract_state_ticket(self._state), self.time_ticket()})
        self.DeclareVectorOutputPort(
            "gripper_command", 2, self._CalcGripperCommand,
            {self.abstract_state_ticket(self._state)})
        self.DeclareVectorOutputPort(
            "control_status", 3, self._CalcStatus,
            {self.abstract_state_ticket(self._state), self.time_ticket()})

    # -- queries for episode runners --------------------------------------------------

    def get_supervisor_state(self, context) -> SupervisorState:
        return context.get_abstract_state(self._state).get_value()

    def is_done(self, context) -> bool:
        return self.get_supervisor_state(context).mode == Mode.DONE

    def mode_name(self, context) -> str:
        return self.get_supervisor_state(context).mode.value

    def outcome(self, context) -> dict:
        """The supervisor's own data: empty, or {"failure_reason": ...} when it planned no
        grasp (success and failure class come from the GraspJudge)."""
        return dict(self.get_supervisor_state(context).outcome)

    # -- helpers --------------------------------------------------------------------

    def _object_points_W(self, context) -> np.ndarray:
        X_WO = self._body_poses.Eval(context)[self._object]
        return self._points_O @ X_WO.rotation().matrix().T + X_WO.translation()

    def _pregrasp(self, X_WG_grasp: RigidTransform) -> RigidTransform:
        return RigidTransform(X_WG_grasp.rotation(), X_WG_grasp.translation()
                              + [0.0, 0.0, self._motion.pregrasp_height_m])

    def _lifted(self, X_WG_grasp: RigidTransform) -> RigidTransform:
        return RigidTransform(X_WG_grasp.rotation(), X_WG_grasp.translation()
                              + [0.0, 0.0, self._motion.lift_height_m])

    # -- events ---------------------------------------------------------------------

    def _Initialize(self, context, state):
        if self._X_WG_planned is not None:
            new = SupervisorState(mode=Mode.APPROACH, mode_start_s=context.get_time(),
                                  X_WG_grasp=self._X_WG_planned)
            state.get_mutable_abstract_state(int(self._state)).set_value(new)
            return
        try:
            com_W = None
            if self._com_O is not None:
                X_WO = self._body_poses.Eval(context)[self._object]
                com_W = X_WO.rotation().matrix() @ self._com_O + X_WO.translation()
            plan = plan_topdown_grasp(
                self._object_points_W(context), table_z=self._table_z,
                depth_below_top=self._motion.grasp_depth_below_top_m,
                min_height=self._motion.min_grasp_height_m, com_W=com_W)
        except ValueError as e:
            new = SupervisorState(mode=Mode.DONE, outcome={
                "failure_reason": f"no top-down grasp: {e}"})
        else:
            X = RigidTransform(RotationMatrix(plan.rotation()), plan.position)
            new = SupervisorState(mode=Mode.APPROACH, mode_start_s=context.get_time(),
                                  X_WG_grasp=X)
        state.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _Update(self, context, state):
        s = self.get_supervisor_state(context)
        t = context.get_time()
        elapsed = t - s.mode_start_s
        m = self._motion
        new = s
        if s.mode == Mode.APPROACH and elapsed >= m.approach_time_s:
            new = replace(s, mode=Mode.DESCEND, mode_start_s=t)
        elif s.mode != Mode.DONE:
            speed = float(np.abs(self._gripper_state.Eval(context)[2:]).max())
            nxt = grasp_motion_next(s.mode.value, elapsed, m, speed)
            if nxt is not None:
                new = replace(s, mode=Mode(nxt), mode_start_s=t)
        if new is not s:
            state.get_mutable_abstract_state(int(self._state)).set_value(new)

    # -- outputs ----------------------------------------------------------------------

    def _CalcPose(self, context, output):
        s = self.get_supervisor_state(context)
        m = self._motion
        elapsed = context.get_time() - s.mode_start_s
        if s.X_WG_grasp is None:
            X = self._X_WG_start
        elif s.mode == Mode.APPROACH:
            X = interpolate_pose(self._X_WG_start, self._pregrasp(s.X_WG_grasp),
                                 min_jerk(elapsed / m.approach_time_s))
        elif s.mode == Mode.DESCEND:
            X = interpolate_pose(self._pregrasp(s.X_WG_grasp), s.X_WG_grasp,
                                 min_jerk(elapsed / m.descend_time_s))
        elif s.mode == Mode.CLOSE:
            X = s.X_WG_grasp
        elif s.mode == Mode.LIFT:
            X = interpolate_pose(s.X_WG_grasp, self._lifted(s.X_WG_grasp),
                                 min_jerk(elapsed / m.lift_time_s))
        else:
            X = self._lifted(s.X_WG_grasp)
        output.set_value(X)

    def _CalcGripperCommand(self, context, output: BasicVector):
        s = self.get_supervisor_state(context)
        closed = s.mode in (Mode.CLOSE, Mode.LIFT, Mode.HOLD) or (
            s.mode == Mode.DONE and s.X_WG_grasp is not None)
        width = 0.0 if closed else self._gripper.open_width_m
        output.SetFromVector([width, self._gripper.grip_force_n])

    def _CalcStatus(self, context, output: BasicVector):
        s = self.get_supervisor_state(context)
        step = int(round(context.get_time() / self._period))
        approaching = s.mode in (Mode.APPROACH, Mode.DESCEND)
        output.SetFromVector([float(step), 1.0 if approaching else 0.0,
                              motion_phase_code(s.mode.value)])
