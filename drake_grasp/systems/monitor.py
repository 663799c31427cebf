"""The harness's view of a user policy's grasp motion: which phase it is in, for the judge.

A built-in policy reports the phase of the shared grasp motion itself (its
`control_status`). A user policy (`drake_grasp.policies.plugins`) does not: the
`GraspMotionMonitor` derives the phase from what the policy commands and from the
gripper's measured state, with the rules the built-in policies follow, so the judge
judges both the same way and a policy cannot shorten its own hold.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem

from drake_grasp.config.policy_spec import CLOSE_WIDTH_M
from drake_grasp.config.scenario import Scenario
from drake_grasp.systems.state import shared_when_copied
from drake_grasp.systems.supervisor import grasp_motion_next, motion_phase_code


@shared_when_copied
@dataclass(frozen=True)
class MonitorState:
    """What the monitor has seen (the Context's abstract state)."""

    phase: str = "approach"
    phase_start_s: float = 0.0
    close_start_s: float | None = None


class GraspMotionMonitor(LeafSystem):
    """Derives the phase of a user policy's grasp motion (`MOTION_PHASES`).

    Rules, checked every `period_s` (the judge's sampling period):
        approach -> descend: the policy's `descending` input is > 0.5 (a latch).
        approach or descend -> close: the commanded width is <= `CLOSE_WIDTH_M`.
        close -> lift -> hold -> done: `grasp_motion_next`, as for the built-in policies
            (the closing ends when the fingers have stopped, after 0.3 s, or after
            `scripted.close_time_s`; the lift lasts `lift_time_s`, the hold `hold_time_s`).

    Input ports:
        gripper_command: the policy's [width_m, grip_force_n].
        gripper_state: [q_left, q_right, v_left, v_right] of the fingers.
        descending: the policy's [descending] (a constant 1 when it declares none).
    Output ports:
        control_status: [control step, approaching, motion phase], as a built-in policy's
            (read by the GraspJudge and the SheetDisturbance); the control step is the
            number of `controller.period_s` periods since t = 0, approaching is 1 until
            the closing starts.
        motion_status: [motion phase, phase start time [s], control step], for the policy.
    """

    def __init__(self, *, scenario: Scenario, period_s: float | None = None):
        super().__init__()
        self._motion = scenario.scripted
        self._control_period = float(scenario.controller.period_s)
        period = float(scenario.judge.period_s if period_s is None else period_s)
        self._command = self.DeclareVectorInputPort("gripper_command", 2)
        self._gripper = self.DeclareVectorInputPort("gripper_state", 4)
        self._descending = self.DeclareVectorInputPort("descending", 1)
        self._state = self.DeclareAbstractState(AbstractValue.Make(MonitorState()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, 0.0, self._Update)
        deps = {self.abstract_state_ticket(self._state), self.time_ticket()}
        self.DeclareVectorOutputPort("control_status", 3, self._CalcControlStatus, deps)
        self.DeclareVectorOutputPort("motion_status", 3, self._CalcMotionStatus, deps)

    # -- queries for the episode runner ---------------------------------------------

    def get_monitor_state(self, context) -> MonitorState:
        return context.get_abstract_state(self._state).get_value()

    def is_done(self, context) -> bool:
        return self.get_monitor_state(context).phase == "done"

    def mode_name(self, context) -> str:
        return self.get_monitor_state(context).phase

    def outcome(self, context) -> dict:
        s = self.get_monitor_state(context)
        if s.close_start_s is None:
            return {"stop_reason": "the user policy has not closed the gripper"}
        return {"stop_reason": f"the user policy closed the gripper at t = {s.close_start_s:.2f} s"}

    # -- the update ---------------------------------------------------------------------

    def _Update(self, context, state):
        s = self.get_monitor_state(context)
        t = context.get_time()
        new = s
        if s.phase in ("approach", "descend"):
            if float(self._command.Eval(context)[0]) <= CLOSE_WIDTH_M:
                new = MonitorState(phase="close", phase_start_s=t, close_start_s=t)
            elif s.phase == "approach" and float(self._descending.Eval(context)[0]) > 0.5:
                new = replace(s, phase="descend", phase_start_s=t)
        elif s.phase != "done":
            speed = float(np.abs(self._gripper.Eval(context)[2:]).max())
            nxt = grasp_motion_next(s.phase, t - s.phase_start_s, self._motion, speed)
            if nxt is not None:
                new = replace(s, phase=nxt, phase_start_s=t)
        if new is not s:
            state.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _step(self, context) -> float:
        return float(np.floor(context.get_time() / self._control_period + 1e-9))

    def _CalcControlStatus(self, context, output: BasicVector):
        s = self.get_monitor_state(context)
        approaching = 1.0 if s.phase in ("approach", "descend") else 0.0
        output.SetFromVector([self._step(context), approaching, motion_phase_code(s.phase)])

    def _CalcMotionStatus(self, context, output: BasicVector):
        s = self.get_monitor_state(context)
        output.SetFromVector([motion_phase_code(s.phase), s.phase_start_s, self._step(context)])


__all__ = ["GraspMotionMonitor", "MonitorState"]
