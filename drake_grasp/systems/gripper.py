"""Force-controlled, rate-limited position control of the 2F-85 through the plant's PD."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from drake_grasp.config.sections import GRIP_FORCE_MODES

# "constant": how many times the ramp's lead past a blocked finger its PD target is set
# beyond it. At the default closing speed (0.1 m/s, 0.05 m/s per finger) and kp 2000 N/m
# the squeeze rises at about 1000 N/s, reaching 60 N per pad about 0.12 s after contact.
# An instant step to full force instead squeezed curved objects (an apple, mug walls)
# out of 4 of 423 label-check grasps that hold with this rise.
FORCE_RISE_GAIN = 10.0


def gripper_pd_target(
    width_ramp: float, q_measured: float, kp: float, grip_force_n: float,
    force_mode: str = "constant",
) -> float:
    """PD target of the actuated finger.

    The coupler constraint splits the actuator force u over the two pads, so each pad
    presses with u/2, and the plant's PD gives u = kp (q_d - q) at rest.

    - "limit": the target is kept within 2F/kp of the measured position, which caps the
      squeeze at F per pad. A finger blocked by an object then presses with
      kp (q - width/2) / 2 per pad, e.g. 15 N on a 3 cm handle at kp = 2000 N/m: F is
      an upper bound, not the force applied.
    - "constant" (the 2F-85's force control): when the ramp is past the finger (it
      closes on something), the target lies `FORCE_RISE_GAIN` times the ramp's lead
      beyond the finger, up to 2F/kp: the squeeze rises as the ramp goes on and then
      holds at F per pad, whatever the object's width. A finger closing on nothing
      follows its ramp within a fraction of a millimetre, so it is barely pushed.
    """
    q_goal = 0.5 * width_ramp
    reach = 2.0 * grip_force_n / kp
    if force_mode == "constant" and q_measured > q_goal:
        return float(q_measured - min(reach, FORCE_RISE_GAIN * (q_measured - q_goal)))
    # min/max on Python floats, not np.clip: this runs at every plant step.
    return float(q_measured + max(-reach, min(q_goal - q_measured, reach)))


class GripperController(LeafSystem):
    """Turns a (width, grip force) command into the finger PD's desired state.

    The commanded opening is rate limited (discrete state, the datasheet closing speed);
    a finger blocked by an object presses with the commanded grip force per pad
    (`force_mode` "constant") or with at most that force ("limit"; see
    `gripper_pd_target`).

    Input ports:
        gripper_command: [width_m, grip_force_n].
        gripper_state: the gripper model instance's state [q_left, q_right, v_left, v_right].
    Output ports:
        desired_state: [q_d, v_d] for the actuated (left) finger joint.
    State:
        discrete [width_ramp_m]: the rate-limited commanded opening.
    """

    def __init__(self, *, kp: float, closing_speed_m_s: float, initial_width_m: float,
                 time_step: float, num_gripper_positions: int = 2,
                 force_mode: str = "constant"):
        super().__init__()
        if kp <= 0:
            raise ValueError(f"kp: expected > 0, got {kp}")
        if force_mode not in GRIP_FORCE_MODES:
            raise ValueError(f"force_mode: expected one of {GRIP_FORCE_MODES}, got {force_mode!r}")
        self._force_mode = force_mode
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
        q_d = gripper_pd_target(ramp, q, self._kp, force, self._force_mode)
        # Feed the ramp's velocity forward so the fingers move smoothly, but not while
        # the force cap is active (the damping term would add to the squeeze).
        moving = abs(width_cmd - ramp) > 1e-6
        capped = abs(q_d - 0.5 * ramp) > 1e-9
        v_d = (0.5 * self._speed if width_cmd > ramp else -0.5 * self._speed) \
            if moving and not capped else 0.0
        output.SetAtIndex(0, q_d)
        output.SetAtIndex(1, v_d)
