"""Kinematic noise (the paper's Figure 5 condition) as its own system between a policy's
command and the station: the hand goes where the policy commands, displaced in the
table's plane by an execution error the policy never sees. The policy keeps believing
its command; only what it sees in its wrist images tells it otherwise.

Models (`config.sections.NoiseConfig`, `scenario.noise.kind`):
    gaussian: the paper's model, per commanded planar move (x, y, theta):
        delta_noisy = delta + scale * w * |delta|, w ~ N(0, I), with |delta| in the
        paper's metric (0.001 m per degree). A move is the policy's commanded move to a
        new goal (the policy's `X_WG_goal` port); its error adds to the error of the
        moves before it and is ramped in along the move.
    offset: a constant (x, y, theta) error in the hand frame between the believed and
        the executed pose, ramped in over the first `offset_ramp_m` the hand moves from
        its start pose (where it observed the scene: calibrated there).

Floor: systems (imports geometry and config only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import LeafSystem

from drake_grasp.geometry.actions import action_between, apply_actions, displacement_norm
from drake_grasp.geometry.grasp_metric import ANGLE_WEIGHT_M_PER_DEG as METRES_PER_DEGREE

# The random stream of the gaussian model: numpy Generator([seed, move, NOISE_STREAM]).
NOISE_STREAM = 29


def gaussian_noisy_displacement(delta, rng: np.random.Generator, scale: float = 0.4) -> np.ndarray:
    """The paper's kinematic noise: delta + scale * w * |delta|, w ~ N(0, I) per dimension
    (theta's noise in degrees, through the 0.001 m/deg weighting)."""
    d = np.asarray(delta, dtype=float)
    w = rng.standard_normal(3)
    size = float(displacement_norm(d))
    noise = scale * w * size
    noise[2] /= METRES_PER_DEGREE
    return d + noise


def offset_fraction(moved_m: float, ramp_m: float) -> float:
    """How much of the constant offset applies after the hand moved `moved_m` from where
    it observed the scene (0 at the observation pose, 1 after `ramp_m`)."""
    if ramp_m <= 0:
        return 1.0
    return float(min(1.0, max(0.0, moved_m / ramp_m)))


def planar(X_WG: RigidTransform) -> np.ndarray:
    """[x, y, yaw_deg] of a grasp-frame pose, yaw that of x_G projected onto the table."""
    R, p = X_WG.rotation().matrix(), X_WG.translation()
    return np.array([p[0], p[1], np.rad2deg(np.arctan2(R[1, 0], R[0, 0]))])


def wrap_turn(yaw_deg: float) -> float:
    """An angle in [-180, 180) degrees. (Not a half turn: the hand turned half a turn is
    the same grasp, but its next move goes the other way.)"""
    return float((yaw_deg + 180.0) % 360.0 - 180.0)


def displaced(X_WG: RigidTransform, error) -> RigidTransform:
    """`X_WG` moved by a planar error [dx, dy, dyaw_deg] (world frame): translated in the
    table's plane and turned about the world vertical through its origin (a tilted
    pose keeps its tilt)."""
    dx, dy, dyaw = (float(v) for v in error)
    if dx == 0.0 and dy == 0.0 and dyaw == 0.0:
        return X_WG
    R = RotationMatrix.MakeZRotation(np.deg2rad(dyaw)) @ X_WG.rotation()
    return RigidTransform(R, X_WG.translation() + np.array([dx, dy, 0.0]))


def offset_error(noise, start_xy_yaw, pose_xy_yaw) -> np.ndarray:
    """The offset model's world-frame error [dx, dy, dyaw_deg] at a believed planar pose."""
    moved = float(np.hypot(pose_xy_yaw[0] - start_xy_yaw[0], pose_xy_yaw[1] - start_xy_yaw[1]))
    f = offset_fraction(moved, noise.offset_ramp_m)
    dx, dy = noise.offset_xy_m
    out = apply_actions(pose_xy_yaw, np.array([[f * dx, f * dy, f * noise.offset_theta_deg]]))[0]
    return np.array([out[0] - pose_xy_yaw[0], out[1] - pose_xy_yaw[1], out[2] - pose_xy_yaw[2]])


@dataclass(frozen=True)
class MoveError:
    """The gaussian model's state: the move under way (its believed start and goal, as
    [x, y, yaw_deg]), the execution error at each end (world frame [dx, dy, dyaw_deg]),
    and how many moves were commanded."""

    start: tuple
    goal: tuple
    error_start: tuple = (0.0, 0.0, 0.0)
    error_goal: tuple = (0.0, 0.0, 0.0)
    moves: int = 0


def next_move(state: MoveError, goal, *, scale: float, seed: int) -> MoveError:
    """The state after the policy commanded a move to `goal` ([x, y, yaw_deg]) from the
    goal of its previous move: the move's displacement gets the gaussian noise, applied
    where the hand really was."""
    start = np.asarray(state.goal, float)
    goal = np.asarray(goal, float)
    delta = action_between(start, goal)
    if not np.any(delta):
        return state
    moves = state.moves + 1
    rng = np.random.default_rng([seed, moves, NOISE_STREAM])
    real_start = start + np.asarray(state.error_goal, float)
    real = apply_actions(real_start, gaussian_noisy_displacement(delta, rng, scale)[None])[0]
    error = (float(real[0] - goal[0]), float(real[1] - goal[1]),
             wrap_turn(real[2] - goal[2]))
    return MoveError(start=tuple(start), goal=tuple(goal), error_start=state.error_goal,
                     error_goal=error, moves=moves)


def move_error(state: MoveError, pose_xy_yaw) -> np.ndarray:
    """The error at a believed planar pose on the move under way: ramped from the error at
    its start to the error at its goal with the share of the move made (the paper's
    metric; past the goal, or for a move without a planar part, the goal's error)."""
    start, goal = np.asarray(state.start, float), np.asarray(state.goal, float)
    e0, e1 = np.asarray(state.error_start, float), np.asarray(state.error_goal, float)
    total = float(displacement_norm(action_between(start, goal)))
    if total <= 0.0:
        return e1
    made = float(displacement_norm(action_between(start, np.asarray(pose_xy_yaw, float))))
    s = min(1.0, made / total)
    return e0 + s * (e1 - e0)


class KinematicNoise(LeafSystem):
    """The arm's execution error between a policy's command and the station.

    Input ports:
        X_WG_commanded: the policy's commanded grasp-frame pose (RigidTransform).
        X_WG_goal: (gaussian model) the believed pose the policy's current move ends at
            (RigidTransform); a new goal is a new commanded move.
    Output ports:
        X_WG_desired: the pose the station's differential IK is asked for: the command
            displaced by the execution error (`displaced`).

    The gaussian model keeps its `MoveError` in abstract state, updated every control
    period `offset_s` after the policy's own update, when the policy's new goal is out
    and before the hand has moved toward it. The offset model is a function of the
    command alone.
    """

    def __init__(self, *, noise, seed: int, X_WG_start: RigidTransform, period_s: float,
                 offset_s: float = 1e-3):
        """Args:
            noise: `scenario.noise` (kind "gaussian" or "offset").
            seed: the trial's seed (the gaussian model's draws).
            X_WG_start: the hand's start pose (the offset model's ramp starts there).
            period_s: the policy's control period.
            offset_s: how long after the policy's update the gaussian model reads a new
                goal [s]; under the station's time step.
        """
        super().__init__()
        if noise.kind not in ("gaussian", "offset"):
            raise ValueError(f"noise.kind: got {noise.kind!r}; the KinematicNoise system "
                             "models 'gaussian' or 'offset' (leave it out for 'none')")
        if not 0.0 < offset_s < period_s:
            raise ValueError(f"offset_s: got {offset_s}; expected 0 < offset_s < period_s "
                             f"({period_s})")
        self._noise = noise
        self._seed = int(seed)
        self._start = planar(X_WG_start)
        self._command = self.DeclareAbstractInputPort(
            "X_WG_commanded", AbstractValue.Make(RigidTransform()))
        self._goal = self.DeclareAbstractInputPort("X_WG_goal", AbstractValue.Make(RigidTransform()))
        start = tuple(float(v) for v in self._start)
        self._state = self.DeclareAbstractState(AbstractValue.Make(MoveError(start, start)))
        if noise.kind == "gaussian":
            self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, offset_s, self._Update)
        self.DeclareAbstractOutputPort(
            "X_WG_desired", lambda: AbstractValue.Make(RigidTransform()), self._CalcPose,
            {self.abstract_state_ticket(self._state), self._command.ticket()})

    def get_move_error(self, context) -> MoveError:
        return context.get_abstract_state(self._state).get_value()

    def _Update(self, context, state):
        s = self.get_move_error(context)
        goal = planar(self._goal.Eval(context))
        if np.allclose(goal, s.goal, rtol=0.0, atol=1e-12):
            return
        new = next_move(s, goal, scale=self._noise.gaussian_scale, seed=self._seed)
        if new is s:  # no planar move (a pure height change): keep the error, new start
            new = MoveError(start=tuple(goal), goal=tuple(goal), error_start=s.error_goal,
                            error_goal=s.error_goal, moves=s.moves)
        state.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _CalcPose(self, context, output):
        X = self._command.Eval(context)
        here = planar(X)
        if self._noise.kind == "offset":
            error = offset_error(self._noise, self._start, here)
        else:
            error = move_error(self.get_move_error(context), here)
        output.set_value(displaced(X, error))


def connect_with_noise(builder, scenario, policy, arm_input, *, X_WG_start: RigidTransform):
    """Connects `policy`'s `X_WG_desired` to `arm_input` (the station's or the IK's pose
    input), through a `KinematicNoise` system named "kinematic_noise" when
    `scenario.noise.kind` is not "none". Returns that system, or None."""
    if scenario.noise.kind == "none":
        builder.Connect(policy.GetOutputPort("X_WG_desired"), arm_input)
        return None
    noise = builder.AddNamedSystem("kinematic_noise", KinematicNoise(
        noise=scenario.noise, seed=scenario.seed, X_WG_start=X_WG_start,
        period_s=scenario.controller.period_s))
    builder.Connect(policy.GetOutputPort("X_WG_desired"), noise.GetInputPort("X_WG_commanded"))
    builder.Connect(policy.GetOutputPort("X_WG_goal"), noise.GetInputPort("X_WG_goal"))
    builder.Connect(noise.GetOutputPort("X_WG_desired"), arm_input)
    return noise
