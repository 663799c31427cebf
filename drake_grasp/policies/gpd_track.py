"""gpd-track: GPD's grasp from its one look, followed in the wrist camera on the way down.

GPD's detection from its viewpoint is right most of the time in a still pile, but it is
executed open loop: a pile that moves, or a hand that is not where the controller
believes (kinematic noise), makes it miss. This policy keeps GPD's look and grasp and
closes the loop the way CTR does, with the wrist camera, every control period:

1. at the viewpoint, the GPD image and its detection, as `gpd` (`GPDController`); the
   GPD image's height map around the grasp becomes the reference
   (`scene_tracking.SceneReference`);
2. every control period, the wrist image's points (at the pose the controller believes)
   are registered against the reference: the scene's planar motion since the GPD image
   (`SceneReference.register`); the grasp is moved with it (`scene_tracking.moved_pose`)
   and the hand moves toward its pre-grasp, at most `gpd_track.step_max_m` and
   `step_max_yaw_deg` per period;
3. once the hand is at the pre-grasp and the estimate has stayed within
   `gpd_track.settled_m` for `settled_iterations` periods (or after `max_iterations`,
   when the estimate is frozen), GPD's own ending: along the approach to the grasp,
   close, lift.

Sensors only: the GPD sensor's image, the wrist camera's, and the poses the controller
believes it commanded. Settings: `scenario.gpd_track` (`config.sections.GpdTrackConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pydrake.math import RigidTransform

from drake_grasp.geometry.camera import focal_length_px
from drake_grasp.geometry.grasp_metric import ANGLE_WEIGHT_M_PER_DEG
from drake_grasp.policies.controller_state import (ControllerState, Phase, hand_to_pose,
                                                   pose_from_tuple, pose_to_hand, pose_tuple)
from drake_grasp.policies.decisions import image_points_W
from drake_grasp.policies.detector_controllers import GPDController
from drake_grasp.policies.scene_tracking import Motion, SceneReference, moved_pose
from drake_grasp.systems.supervisor import interpolate_pose, min_jerk


@dataclass(frozen=True)
class Track:
    """What gpd-track remembers between control periods (in `ControllerState.memory`)."""

    reference: SceneReference
    detection: tuple  # the detected grasp as the hand takes it (X_WG, 16 floats)
    motion: Motion  # the scene's planar motion since the GPD image, last estimate
    pose_from: tuple  # the commanded move under way (X_WG, 16 floats each)
    pose_to: tuple
    settled: int = 0  # periods in a row at the pre-grasp with a steady estimate
    frozen: bool = False  # past `max_iterations`: the estimate no longer changes
    registrations: int = 0  # wrist images registered (not rejected)


def motion_change_m(a: Motion, b: Motion) -> float:
    """How far two estimates differ, in the paper's metric (1 mm per degree)."""
    return float(np.hypot(a.xy_m[0] - b.xy_m[0], a.xy_m[1] - b.xy_m[1])
                 + ANGLE_WEIGHT_M_PER_DEG * abs(a.yaw_deg - b.yaw_deg))


def pose_gap_m(X_a: RigidTransform, X_b: RigidTransform) -> float:
    """How far two poses are apart: the distance between their origins plus their
    relative turn in the paper's metric (1 mm per degree)."""
    turn = abs((X_a.rotation().inverse() @ X_b.rotation()).ToAngleAxis().angle())
    return float(np.linalg.norm(X_a.translation() - X_b.translation())
                 + ANGLE_WEIGHT_M_PER_DEG * np.rad2deg(turn))


def step_toward(X_from: RigidTransform, X_to: RigidTransform, *, step_m: float,
                step_yaw_deg: float) -> RigidTransform:
    """The pose a capped step from `X_from` toward `X_to` reaches (all the way when it is
    within the caps)."""
    dist = float(np.linalg.norm(X_to.translation() - X_from.translation()))
    turn = float(np.rad2deg(abs((X_from.rotation().inverse() @ X_to.rotation())
                                .ToAngleAxis().angle())))
    f = min(1.0, step_m / dist if dist > 0 else 1.0, step_yaw_deg / turn if turn > 0 else 1.0)
    return X_to if f >= 1.0 else interpolate_pose(X_from, X_to, f)


class GPDTrackController(GPDController):
    """gpd-track: GPD's detection, followed in the wrist camera (module docstring)."""

    policy = "gpd-track"
    closed_loop = True

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        g = self._s.gpd
        self._gpd_focal = focal_length_px(g.height, g.fov_y_deg)

    def _gpd_detect(self, context, s: ControllerState, t: float) -> ControllerState:
        detected = super()._gpd_detect(context, s, t)
        if detected.phase == Phase.DONE:
            return detected
        c = self._s.gpd_track
        depth = np.array(self._gpd_depth.Eval(context).data[:, :, 0], copy=True)
        X_WC = (hand_to_pose(s.hand) @ self._X_GC_gpd).GetAsMatrix4()
        P_W = image_points_W(depth, self._gpd_focal, X_WC, self._s.gpd.depth_max_m)
        grasp = np.asarray(detected.grasp_pose, float).reshape(4, 4)
        reference = SceneReference(P_W, grasp[:2, 3], template_half_m=c.template_half_m,
                                   search_m=c.search_m, cell_m=c.cell_m)
        view = pose_tuple(hand_to_pose(s.hand).GetAsMatrix4())
        track = Track(reference=reference, detection=detected.grasp_pose, motion=Motion(),
                      pose_from=view, pose_to=view)
        return self._next_move(replace(detected, phase=Phase.SERVO, iteration=0,
                                       segment_from=s.hand, hand=s.hand, memory=track), t)

    def _policy_phase(self, context, s: ControllerState, t: float,
                      elapsed: float) -> ControllerState:
        if s.phase != Phase.SERVO:
            return super()._policy_phase(context, s, t, elapsed)
        return self._next_move(self._observe(context, s), t)

    def _observe(self, context, s: ControllerState) -> ControllerState:
        """The wrist image registered against the GPD image: the new estimate."""
        track, c = s.memory, self._s.gpd_track
        if track.frozen:
            return s
        X_WC = (pose_from_tuple(track.pose_to) @ self._X_GC).GetAsMatrix4()
        depth = self._depth.Eval(context).data[:, :, 0]
        P_W = image_points_W(depth, self._focal, X_WC, self._s.camera.depth_max_m)
        motion = track.reference.register(P_W, prior=track.motion, yaw_range_deg=c.yaw_range_deg,
                                          yaw_step_deg=c.yaw_step_deg,
                                          min_overlap=c.min_overlap)
        if motion is None or motion.rms_m > c.max_rms_m:
            return s
        steady = motion_change_m(motion, track.motion) < c.settled_m
        return replace(s, memory=replace(track, motion=motion,
                                         settled=track.settled + 1 if steady else 0,
                                         registrations=track.registrations + 1))

    def _next_move(self, s: ControllerState, t: float) -> ControllerState:
        """The grasp where the estimate puts it; the next capped move toward its pre-grasp,
        or the descent when the hand is there and the estimate has settled."""
        track, c = s.memory, self._s.gpd_track
        grasp = moved_pose(np.asarray(track.detection).reshape(4, 4), track.reference.anchor,
                           track.motion)
        pre = self._pregrasp(RigidTransform(grasp))
        here = pose_from_tuple(track.pose_to)
        at_pre = pose_gap_m(here, pre) < c.settled_m
        frozen = track.frozen or s.iteration >= c.max_iterations
        s = replace(s, grasp_pose=pose_tuple(grasp), grasp=pose_to_hand(grasp))
        if at_pre and (track.settled >= c.settled_iterations or frozen):
            outcome = {**s.outcome, "tracked_motion": [track.motion.xy_m[0], track.motion.xy_m[1],
                                                       track.motion.yaw_deg],
                       "tracked_rms_m": track.motion.rms_m,
                       "registrations": track.registrations}
            return replace(s, phase=Phase.DESCEND, phase_start_s=t, outcome=outcome,
                           stop_reason="iterations" if frozen else "settled")
        nxt = step_toward(here, pre, step_m=c.step_max_m, step_yaw_deg=c.step_max_yaw_deg)
        memory = replace(track, pose_from=track.pose_to, pose_to=pose_tuple(nxt.GetAsMatrix4()),
                         frozen=frozen)
        return replace(s, phase_start_s=t, iteration=s.iteration + 1, memory=memory,
                       segment_from=s.hand, hand=pose_to_hand(nxt))

    def _goal(self, s: ControllerState) -> RigidTransform:
        """While tracking, every control period's step is a commanded move (as CTR's): it
        ends at the grasp that the step's pre-grasp leads to, so that the descent from the
        last one is no new move (as gpd's pre-grasp and grasp are one)."""
        if s.phase == Phase.SERVO:
            step = pose_from_tuple(s.memory.pose_to)
            z_G = step.rotation().matrix()[:, 2]
            return RigidTransform(step.rotation(),
                                  step.translation() + self._s.scripted.pregrasp_height_m * z_G)
        return super()._goal(s)

    def _pose(self, s: ControllerState, elapsed: float) -> RigidTransform:
        if s.phase == Phase.SERVO:
            # Each move within 0.8 control periods, as CTR's.
            return interpolate_pose(pose_from_tuple(s.memory.pose_from),
                                    pose_from_tuple(s.memory.pose_to),
                                    min_jerk(elapsed / (0.8 * self._period)))
        return super()._pose(s, elapsed)
