"""The one-shot detector policies: one grasp detection, then open loop to it.

gpd: the paper's GPD baseline. The hand moves to a fixed viewpoint (the start's x, y and
yaw, the GPD sensor `gpd.view_camera_height_m` above the table), rests
`gpd.view_settle_s`, takes one image with the GPD sensor (`gpd_depth_image`) and asks
`detect_fn` (`drake_grasp.policies.gpd.make_detector`) for a 6-DOF grasp (its approach may
tilt up to `gpd.approach_max_tilt_deg` from straight down); then open loop to a pre-grasp
`scripted.pregrasp_height_m` back along the approach, and the descent along the approach
axis. The policy commands the detected grasp; kinematic noise (the
`systems.kinematic_noise.KinematicNoise` system) corrupts the move from the viewpoint to
the grasp's (x, y, yaw of x_G on the table), and keeps the grasp's tilt.

gpd-geometric: the hand-tuned geometric detector (`drake_grasp.policies.gpd_geometric`) on
the wrist camera's first image at the start pose, top-down, open loop.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from pydrake.math import RigidTransform

from drake_grasp.geometry.actions import action_between, apply_actions
from drake_grasp.policies.controller import GraspController
from drake_grasp.policies.decisions import NO_GRASP_FOUND
from drake_grasp.policies.controller_state import (ControllerState, Phase, hand_to_pose,
                                                   pose_from_tuple, pose_to_hand, pose_tuple,
                                                   rot_z)
from drake_grasp.systems.supervisor import interpolate_pose, min_jerk

# What a one-shot policy records when its detector finds nothing.
NO_DETECTION = {"failure_reason": NO_GRASP_FOUND, "iterations": 0}


class GPDController(GraspController):
    """gpd: view, detect once with the GPD sensor, then open loop (module docstring)."""

    policy = "gpd"
    EXTRAS = ("detect_fn", "X_GC_gpd")

    def __init__(self, *, detect_fn, X_GC_gpd=None, **kwargs):
        """Args:
            detect_fn: detect(depth (H, W) [m], X_WC 4x4) -> X_WG 4x4 or None.
            X_GC_gpd: the GPD sensor in the grasp frame (required).
            others: as `GraspController`.
        """
        super().__init__(**kwargs)
        self._detect = detect_fn
        # The viewpoint: the start's x, y and yaw with the GPD sensor `view_camera_height_m`
        # above the table (top-down: the sensor sits -z_C.z above the grasp centre).
        self._X_GC_gpd = X_GC_gpd
        self._view = None
        if X_GC_gpd is not None:
            self._view = (self._start[0], self._start[1],
                          float(self._s.gpd.view_camera_height_m + X_GC_gpd.translation()[2]),
                          self._start[3])

    def _begin(self, context, base: ControllerState, t: float) -> ControllerState:
        if self._view is None:
            raise ValueError("GraspController: policy 'gpd' needs X_GC_gpd (the GPD "
                             "sensor in the grasp frame: GraspStation.X_GC_gpd)")
        return replace(base, phase=Phase.VIEW, hand=self._view)

    def _policy_phase(self, context, s: ControllerState, t: float,
                      elapsed: float) -> ControllerState:
        if s.phase != Phase.VIEW:
            return super()._policy_phase(context, s, t, elapsed)
        if elapsed >= self._s.scripted.approach_time_s + self._s.gpd.view_settle_s:
            return self._gpd_detect(context, s, t)
        return s

    def _approach_done(self, s: ControllerState, t: float) -> ControllerState:
        return replace(s, phase=Phase.DESCEND, phase_start_s=t)

    def _gpd_detect(self, context, s: ControllerState, t: float) -> ControllerState:
        """gpd at the viewpoint: the one GPD image, the detection, the move's target."""
        depth = np.array(self._gpd_depth.Eval(context).data[:, :, 0], copy=True)
        X_WC = hand_to_pose(s.hand) @ self._X_GC_gpd  # believed: the commanded viewpoint
        detection = self._detect(depth, X_WC.GetAsMatrix4())
        if detection is None:
            return replace(s, phase=Phase.DONE, phase_start_s=t, outcome=dict(NO_DETECTION))
        X = np.array(detection, dtype=float)
        if X.shape != (4, 4) or not np.all(np.isfinite(X)):
            raise ValueError(f"gpd detect_fn: expected a finite 4x4 grasp pose X_WG or None, "
                             f"got shape {X.shape}: {X!r}")
        # The nearest rotation (a float32 or rounded detection is not orthonormal to
        # Drake's tolerance); anything farther than rounding is an error.
        U, _, Vt = np.linalg.svd(X[:3, :3])
        R = U @ Vt
        if np.linalg.det(R) < 0.0 or np.abs(R - X[:3, :3]).max() > 1e-3:
            raise ValueError(f"gpd detect_fn: the grasp pose's rotation is not a rotation "
                             f"matrix: {X[:3, :3]!r}")
        X[:3, :3] = R
        grasp_pose = self._turned_grasp(X, s.hand)
        pre = self._pregrasp(RigidTransform(grasp_pose))
        return replace(s, phase=Phase.APPROACH, phase_start_s=t, segment_from=s.hand,
                       hand=pose_to_hand(pre), grasp=pose_to_hand(grasp_pose),
                       grasp_pose=pose_tuple(grasp_pose), decided_s=t,
                       outcome={"gpd_detection": pose_tuple(X)})

    def _turned_grasp(self, X_WG: np.ndarray, view) -> np.ndarray:
        """The detected grasp as the hand takes it from `view`: turned half a turn about
        its approach when its x_G points away from the view's."""
        X = np.array(X_WG, dtype=float)
        R, p = X[:3, :3], X[:3, 3]
        _, _, _, yaw = pose_to_hand(X)
        here = np.array([view[0], view[1], view[3]])
        a = action_between(here, np.array([p[0], p[1], yaw]))
        # The move turns the wrist at most 90 degrees (the parallel jaw is symmetric); a
        # grasp whose x_G points the other way is the same grasp turned half a turn
        # about its approach.
        yaw_goal = here[2] - a[2]
        if np.cos(np.deg2rad(yaw_goal - yaw)) < 0.0:
            R = R @ np.diag([-1.0, -1.0, 1.0])
        moved = apply_actions(here, a[None])[0]  # the grasp's (x, y, yaw), as moved to
        out = np.eye(4)
        out[:3, :3] = rot_z(np.deg2rad(moved[2] - yaw_goal)) @ R
        out[:3, 3] = [moved[0], moved[1], p[2]]
        return out

    def _pregrasp(self, X_WG: RigidTransform) -> RigidTransform:
        """gpd: the pre-grasp, `pregrasp_height_m` back along the approach axis z_G."""
        z_G = X_WG.rotation().matrix()[:, 2]
        return RigidTransform(X_WG.rotation(),
                              X_WG.translation() - self._s.scripted.pregrasp_height_m * z_G)

    def _pose(self, s: ControllerState, elapsed: float) -> RigidTransform:
        if s.grasp_pose is not None:
            return self._gpd_pose(s, elapsed)
        return super()._pose(s, elapsed)

    def _gpd_pose(self, s: ControllerState, elapsed: float) -> RigidTransform:
        """gpd after its detection: to the pre-grasp, along the approach axis to the
        grasp, close there, lift straight up (orientation kept), hold."""
        m = self._s.scripted
        grasp = pose_from_tuple(s.grasp_pose)
        pre = self._pregrasp(grasp)
        lifted = RigidTransform(grasp.rotation(), grasp.translation() + [0.0, 0.0, m.lift_height_m])
        if s.phase == Phase.APPROACH:
            return interpolate_pose(hand_to_pose(s.segment_from), pre,
                                    min_jerk(elapsed / m.approach_time_s))
        if s.phase == Phase.DESCEND:
            return interpolate_pose(pre, grasp, min_jerk(elapsed / m.descend_time_s))
        if s.phase == Phase.CLOSE:
            return grasp
        if s.phase == Phase.LIFT:
            return interpolate_pose(grasp, lifted, min_jerk(elapsed / m.lift_time_s))
        return lifted

    def _goal(self, s: ControllerState) -> RigidTransform:
        """gpd after its detection: every move ends at the grasp (the pre-grasp is on
        its approach axis)."""
        if s.grasp_pose is not None:
            return pose_from_tuple(s.grasp_pose)
        return super()._goal(s)


class GeometricController(GraspController):
    """gpd-geometric: the geometric detector on the wrist camera's first image."""

    policy = "gpd-geometric"
    EXTRAS = ("detect_fn",)

    def __init__(self, *, detect_fn, **kwargs):
        """Args:
            detect_fn: detect(depth, X_WC) -> (x, y, theta_deg, z) or None.
            others: as `GraspController`.
        """
        super().__init__(**kwargs)
        self._detect = detect_fn

    def _begin(self, context, base: ControllerState, t: float) -> ControllerState:
        start = self._start
        depth = np.array(self._depth.Eval(context).data[:, :, 0], copy=True)
        X_WC = hand_to_pose(start) @ self._X_GC
        detection = self._detect(depth, X_WC.GetAsMatrix4())
        if detection is None:
            return replace(base, phase=Phase.DONE, outcome=dict(NO_DETECTION))
        x, y, theta, z = detection
        # Move there as one displacement.
        goal = np.array([x, y, theta])
        a = action_between(np.array([start[0], start[1], start[3]]), goal)
        moved = apply_actions([start[0], start[1], start[3]], a[None])[0]
        hand = (float(moved[0]), float(moved[1]), start[2], float(moved[2]))
        grasp = (hand[0], hand[1], float(z), hand[3])
        return replace(base, phase=Phase.APPROACH, hand=hand, grasp=grasp)
