"""A depth-centroid visual servo: a template for bringing your own policy.

Run it from this folder (`drake_grasp.policies.plugins` has the port contract):

    drake-grasp demo --policy centroid_policy:make_policy --scenario isolation --seed 3 --out /tmp/centroid
    drake-grasp evaluate --experiment isolation --trials 4 --conditions ctr,centroid_policy:make_policy --out /tmp/byop

Every control period (`scenario.controller.period_s`) it back-projects the wrist depth image
into the world with the pose it believes the hand has (the last one it commanded), takes
what stands more than 1 cm above the table (the 10th percentile of the heights seen) as the
object, moves halfway toward the object's centroid, turns the closing direction across the
object's principal axis and steps down. Once centred, with the camera 0.2 m above the
object's top, it descends until the pads are `scripted.grasp_depth_below_top_m` below the
top (the grasp centre at least `scripted.min_grasp_height_m` above the table), closes, and
lifts when the harness says the closing has ended (`motion_status`). No randomness.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.sensors import ImageDepth32F

from drake_grasp.geometry.camera import PinholeCamera
from drake_grasp.geometry.hand_model import topdown_rotation
from drake_grasp.systems.supervisor import MOTION_PHASES

LIFT = MOTION_PHASES.index("lift")


def hand_pose(hand) -> RigidTransform:
    """Grasp-frame pose of a top-down hand [x, y, z, yaw (of the closing direction x_G)]."""
    x, y, z, yaw = hand
    return RigidTransform(RotationMatrix(topdown_rotation(yaw)), [x, y, z])


def smooth(s: float) -> float:
    """0 -> 1 with zero slope at both ends (s clipped to [0, 1])."""
    s = min(max(s, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


@dataclass(frozen=True)
class ServoState:
    """Everything the servo remembers (the Context's abstract state, never `self`)."""

    phase: str = "start"      # start -> servo -> descend -> close (the harness times the lift)
    phase_start_s: float = 0.0
    hand: tuple = ()          # the hand's believed target [x, y, z, yaw]
    prev: tuple = ()          # where the current move started
    grasp: tuple = ()         # the final grasp [x, y, z, yaw]
    steps: int = 0


class CentroidServo(LeafSystem):
    """The depth-centroid visual servo (see the module docstring).

    Input ports: depth_image, motion_status, X_WG_start, X_GC (`drake_grasp.policies.plugins`).
    Output ports: X_WG_desired, gripper_command, descending.

    Args:
        scenario: the trial's Scenario (camera, gripper, grasp-motion timing, period).
        gain: fraction of the way to the centroid (and the closing direction) per step.
        z_step_m: how far the hand steps down per control period.
        camera_above_top_m: the servo ends with the camera this far above the top.
        object_margin_m: what stands this much above the table is the object.
        max_steps: control periods before it descends on its best estimate.
        max_move_m, max_turn_rad: the largest move and turn per control period.
    """

    def __init__(self, scenario, *, gain=0.5, z_step_m=0.02, camera_above_top_m=0.2,
                 object_margin_m=0.01, max_steps=30, max_move_m=0.03, max_turn_rad=0.1):
        super().__init__()
        self._s = scenario
        self._gain, self._dz, self._above = gain, z_step_m, camera_above_top_m
        self._margin, self._max_steps = object_margin_m, max_steps
        self._max_move, self._max_turn = max_move_m, max_turn_rad
        self._period = scenario.controller.period_s
        self._depth = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F()))
        self._status = self.DeclareVectorInputPort("motion_status", 3)
        self._start = self.DeclareAbstractInputPort("X_WG_start", AbstractValue.Make(RigidTransform()))
        self._X_GC = self.DeclareAbstractInputPort("X_GC", AbstractValue.Make(RigidTransform()))
        self._state = self.DeclareAbstractState(AbstractValue.Make(ServoState()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._period, 0.0, self._Update)
        self.DeclareAbstractOutputPort("X_WG_desired", lambda: AbstractValue.Make(RigidTransform()),
                                       self._CalcPose)
        self.DeclareVectorOutputPort("gripper_command", 2, self._CalcGripper)
        self.DeclareVectorOutputPort("descending", 1, self._CalcDescending)

    def _get(self, context) -> ServoState:
        return context.get_abstract_state(self._state).get_value()

    def _object_points(self, context, hand) -> tuple[np.ndarray, float]:
        """World points of the depth image (seen from `hand`) that stand above the table,
        and the table's height."""
        depth = np.asarray(self._depth.Eval(context).data[:, :, 0], dtype=float)
        camera = PinholeCamera.of_image(depth, self._s.camera.fov_y_deg)
        v, u = np.mgrid[0:camera.height, 0:camera.width]
        ok = (depth > 0) & (depth < self._s.camera.depth_max_m - 1e-3)
        d = depth[ok]
        P_C = np.stack([*camera.back_project(u[ok], v[ok], d), d], axis=1)
        X_WC = hand_pose(hand) @ self._X_GC.Eval(context)
        P = P_C @ X_WC.rotation().matrix().T + X_WC.translation()
        table_z = float(np.percentile(P[:, 2], 10)) if len(P) else 0.0
        return P[P[:, 2] > table_z + self._margin], table_z

    def _servo(self, context, s: ServoState, t: float) -> ServoState:
        x, y, z, yaw = s.hand
        cam_dz = -self._X_GC.Eval(context).translation()[2]  # camera above the grasp centre
        lowest = self._s.controller.end_camera_height_m - cam_dz
        obj, table_z = self._object_points(context, s.hand)
        if len(obj) < 20:  # nothing seen: step down where we are (the harness times out)
            down = (x, y, max(z - self._dz, lowest), yaw)
            return replace(s, prev=s.hand, hand=down, phase_start_s=t, steps=s.steps + 1)
        c = obj[:, :2].mean(axis=0)
        lam, V = np.linalg.eigh(np.cov((obj[:, :2] - c).T))
        major = V[:, 1]  # the principal axis; close across it (the jaw is symmetric: mod pi)
        dyaw = (np.arctan2(major[1], major[0]) + np.pi / 2 - yaw + np.pi / 2) % np.pi - np.pi / 2
        if lam[1] < 1.5 * lam[0]:  # round seen from above: any closing direction will do
            dyaw = 0.0
        top = float(np.percentile(obj[:, 2], 95))
        error = float(np.hypot(c[0] - x, c[1] - y))
        high = z + cam_dz - top > self._above + 1e-3
        if (error < 0.004 and abs(dyaw) < np.deg2rad(5) and not high) or s.steps >= self._max_steps:
            m = self._s.scripted
            gz = max(top - m.grasp_depth_below_top_m, table_z + m.min_grasp_height_m)
            grasp = (float(c[0]), float(c[1]), min(gz, z), float(yaw + dyaw))
            return replace(s, phase="descend", phase_start_s=t, prev=s.hand, grasp=grasp)
        # Small steps: the arm must finish each move within the period (its speed limits
        # are `arm.max_tcp_speed_m_s`, `max_tcp_angular_speed_rad_s`), or the pose we
        # believe we have, and so every point we back-project, would be wrong.
        step = self._gain * (c - [x, y])
        step *= min(1.0, self._max_move / max(float(np.linalg.norm(step)), 1e-9))
        turn = float(np.clip(self._gain * dyaw, -self._max_turn, self._max_turn))
        nz = max(z - self._dz, top + self._above - cam_dz, lowest)
        hand = (x + step[0], y + step[1], min(nz, z), yaw + turn)
        return replace(s, prev=s.hand, hand=tuple(float(v) for v in hand), phase_start_s=t,
                       steps=s.steps + 1)

    def _Update(self, context, state):
        s = self._get(context)
        t = context.get_time()
        if s.phase == "start":
            X = self._start.Eval(context)
            R = X.rotation().matrix()
            hand = (*(float(v) for v in X.translation()), float(np.arctan2(R[1, 0], R[0, 0])))
            s = ServoState(phase="servo", phase_start_s=t, hand=hand, prev=hand)
        if s.phase == "servo":
            s = self._servo(context, s, t)
        elif s.phase == "descend" and t - s.phase_start_s >= self._s.scripted.descend_time_s + 0.2:
            s = replace(s, phase="close", phase_start_s=t)
        state.get_mutable_abstract_state(int(self._state)).set_value(s)

    def _CalcPose(self, context, output):
        s, t = self._get(context), context.get_time()
        if s.phase == "start":
            output.set_value(self._start.Eval(context))
            return
        a = np.array(s.prev)
        if s.phase == "servo":
            b, k = np.array(s.hand), smooth((t - s.phase_start_s) / (0.8 * self._period))
        elif s.phase == "descend":
            b, k = np.array(s.grasp), smooth((t - s.phase_start_s) / self._s.scripted.descend_time_s)
        else:  # closed: hold the grasp, and lift once the harness says the closing has ended
            phase, since, _ = self._status.Eval(context)
            m = self._s.scripted
            up = 0.0 if phase < LIFT else m.lift_height_m * (
                smooth((t - since) / m.lift_time_s) if phase == LIFT else 1.0)
            a = b = np.array(s.grasp) + [0.0, 0.0, up, 0.0]
            k = 1.0
        output.set_value(hand_pose(a + k * (b - a)))

    def _CalcGripper(self, context, output: BasicVector):
        g = self._s.gripper
        closed = self._get(context).phase == "close"
        output.SetFromVector([0.0 if closed else g.open_width_m, g.grip_force_n])

    def _CalcDescending(self, context, output: BasicVector):
        output.SetFromVector([1.0 if self._get(context).phase in ("descend", "close") else 0.0])


def make_policy(scenario) -> CentroidServo:
    """The factory: `--policy centroid_policy:make_policy`."""
    return CentroidServo(scenario)
