"""Force-limited, rate-limited position control of the 2F-85 through the plant's PD."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem


def gripper_pd_target(
    width_ramp: float, q_measured: float, kp: float, grip_force_n: float
) -> float:
    """PD target of the actuated finger that caps the pad force at `grip_force_n`.

    The coupler constraint splits the actuator force u over the two pads, so each pad
    presses with u/2. With the plant's PD u = kp (q_d - q) at rest, keeping the target
    within 2F/kp of the measured position caps the squeeze at F per pad, however far
    the commanded opening lies behind the object.
    """
    q_goal = 0.5 * width_ramp
    reach = 2.0 * grip_force_n / kp
    # min/max on Python floats, not np.clip: this runs at every plant step.
    return float(q_measured + max(-reach, min(q_goal - q_measured, reach)))


class GripperController(LeafSystem):
    """Turns a (width, grip force) command into the finger PD's desired state.

    The commanded opening is rate limited (discrete state, the datasheet closing speed)
    and the PD target is kept close enough to the measured finger that the steady pad
    force never exceeds the commanded grip force (see `gripper_pd_target`).

    Input ports:
        gripper_command: [width_m, grip_force_n].
        gripper_state: the gripper model instance's state [q_left, q_right, v_left, v_right].
    Output ports:
        desired_state: [q_d, v_d] for the actuated (left) finger joint.
    State:
        discrete [width_ramp_m]: the rate-limited commanded opening.
    """

    def __init__(self, *, kp: float, closing_speed_m_s: float, initial_width_m: float,
                 time_step: float, num_gripper_positions: int = 2):
        super().__init__()
        if kp <= 0:
            raise ValueError(f"kp: expected > 0, got {kp}")
        self._kp = float(kp)
        self._speed = float(closing_speed_m_s)
        self._dt = float(time_step)
        self._nq = int(num_gripper_positions)
        self._command = self.DeclareVectorInputPort("gripper_command", 2)
        self._gripper_state = self.DeclareVectorInputPort("gripper_state", 2 * self._nq)
        self._ramp = self.DeclareDiscreteState(np.array([initial_width_m]))
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._UpdateRamp)
        self.DeclareVectorOutputPort("desired_state", 2, self._CalcDesiredState,
                                     {self.discrete_state_ticket(self._ramp),
                                      self.input_port_ticket(self.get_input_port(0).get_index()),
                                      self.input_port_ticket(self.get_input_port(1).get_index())})

    def set_width(self, context, width_m: float) -> None:
        """Sets the ramped opening (e.g. at the start of an episode)."""
        context.SetDiscreteState(self._ramp, np.array([width_m]))

    # Both callbacks run at every plant step: scalar Python arithmetic, no numpy calls.
    def _UpdateRamp(self, context, discrete_state):
        width_cmd = float(self._command.Eval(context)[0])
        ramp = float(context.get_discrete_state(self._ramp).GetAtIndex(0))
        limit = self._speed * self._dt
        step = max(-limit, min(width_cmd - ramp, limit))
        discrete_state.get_mutable_vector(self._ramp).SetAtIndex(0, ramp + step)

    def _CalcDesiredState(self, context, output: BasicVector):
        width_cmd, force = (float(v) for v in self._command.Eval(context))
        q = float(self._gripper_state.Eval(context)[0])
        ramp = float(context.get_discrete_state(self._ramp).GetAtIndex(0))
        q_d = gripper_pd_target(ramp, q, self._kp, force)
        # Feed the ramp's velocity forward so the fingers move smoothly, but not while
        # the force cap is active (the damping term would add to the squeeze).
        moving = abs(width_cmd - ramp) > 1e-6
        capped = abs(q_d - 0.5 * ramp) > 1e-9
        v_d = (0.5 * self._speed if width_cmd > ramp else -0.5 * self._speed) \
            if moving and not capped else 0.0
        output.SetAtIndex(0, q_d)
        output.SetAtIndex(1, v_d)
