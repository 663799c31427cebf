"""Moving the sheet under the objects: the paper's shift, and a constant drift."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from drake_grasp.config.sections import DisturbanceConfig
from drake_grasp.systems.supervisor import min_jerk


def sample_shift(config: DisturbanceConfig, seed: int) -> np.ndarray:
    """The shift [dx, dy, dyaw_rad] of trial `seed`: a random direction, a distance
    uniform in [min, max], a yaw uniform in +-max_yaw."""
    rng = np.random.default_rng([int(seed), 41])
    angle = rng.uniform(-np.pi, np.pi)
    dist = rng.uniform(config.shift_min_m, config.shift_max_m)
    yaw = np.deg2rad(rng.uniform(-config.shift_max_yaw_deg, config.shift_max_yaw_deg))
    return np.array([dist * np.cos(angle), dist * np.sin(angle), yaw])


class SheetDisturbance(LeafSystem):
    """Desired state of the sheet's (x, y, yaw) joints.

    none: held at zero. shift: once the controller's step reaches `after_iterations`,
    the sheet moves by `sample_shift(config, seed)` along a smooth (min-jerk) path within
    `shift_duration_s`. moving: the sheet drifts at `velocity_m_s` while the controller
    approaches and stops when the gripper starts closing.

    Input ports:
        control_status: [control step, approaching, motion phase] from the policy
            (the motion phase is not used here).
    Output ports:
        sheet_desired_state: [x, y, yaw, vx, vy, wz].
    State:
        discrete [trigger_time_s (NaN until triggered), drift_x, drift_y].
    """

    def __init__(self, config: DisturbanceConfig, *, seed: int, period_s: float):
        super().__init__()
        self._c = config
        self._shift = sample_shift(config, seed)
        self._dt = float(period_s)
        self.DeclareVectorInputPort("control_status", 3)
        self._xd = self.DeclareDiscreteState(np.array([np.nan, 0.0, 0.0]))
        self.DeclarePeriodicDiscreteUpdateEvent(self._dt, 0.0, self._Update)
        self.DeclareVectorOutputPort("sheet_desired_state", 6, self._Calc,
                                     {self.discrete_state_ticket(self._xd), self.time_ticket()})

    @property
    def shift(self) -> np.ndarray:
        return self._shift.copy()

    def trigger_time(self, context) -> float:
        return float(context.get_discrete_state(self._xd).GetAtIndex(0))

    def _Update(self, context, discrete_state):
        x = context.get_discrete_state(self._xd).CopyToVector()
        step, approaching = self.get_input_port(0).Eval(context)[:2]
        if self._c.kind == "shift" and np.isnan(x[0]) and step >= self._c.after_iterations:
            x[0] = context.get_time()
        if self._c.kind == "moving" and approaching > 0.5:
            x[1:] += np.asarray(self._c.velocity_m_s, float) * self._dt
        discrete_state.get_mutable_vector(self._xd).SetFromVector(x)

    def _Calc(self, context, output: BasicVector):
        x = context.get_discrete_state(self._xd).CopyToVector()
        out = np.zeros(6)
        if self._c.kind == "shift" and not np.isnan(x[0]):
            T = self._c.shift_duration_s
            s = (context.get_time() - x[0]) / T
            out[:3] = min_jerk(s) * self._shift
            if 0.0 < s < 1.0:  # d/dt of the min-jerk profile
                out[3:] = (30 * s**2 - 60 * s**3 + 30 * s**4) / T * self._shift
        elif self._c.kind == "moving":
            # The drift is integrated per period in the state; the PD follows it.
            out[:2] = x[1:]
        output.SetFromVector(out)
