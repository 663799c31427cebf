"""The paper's closed-loop controller, CTR (Algorithm 1), as one policy class.

Every control period: score the sampled candidates (the DistanceEvaluator's
`predicted_distances` for the ActionSampler's `candidate_actions`), move a fraction r
toward the best one in (x, y, theta), step down in z; at the stop rule (an object within
`controller.stop_distance_m` of the sensor under the grasp axis, the lowest height, or the
iteration budget) descend to the grasp read from the last image, close and lift. r and the
z steps are the scenario's controller profile (`scenario.CONTROLLER_PROFILES`): "sim",
r = 0.2 and the camera from 0.3 m to 0.15 m in 75 equal steps; "robot", r = 0.5 and 1 cm
steps until the stop rule.

Its documented additions, each a `controller` setting: convergence at the stop height
(servo on at that height until the commanded moves are small, `converge_iterations`), the
yaw bound (`max_yaw_from_start_deg`), the grasp at the object's widest section
(`grasp_at_widest_section`), the hand check (`hand_check`: the best candidate whose open
hand comes down clear), failure memory and target mode.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from drake_grasp.geometry.actions import apply_actions, displacement_norm
from drake_grasp.policies.controller import GraspController
from drake_grasp.policies.controller_state import ControllerState, Phase, StepRecord, hand_to_pose
from drake_grasp.policies.decisions import (
    choose_action,
    hand_overlap_m,
    min_depth_under_axis,
)
from drake_grasp.systems.state import freeze


class CTRController(GraspController):
    """CTR: Algorithm 1 plus its documented additions (see the module docstring)."""

    policy = "ctr"
    closed_loop = True

    def __init__(self, **kwargs):
        """Args: as `GraspController`."""
        super().__init__(**kwargs)
        c = self._s.controller
        start_cam = self._start[2] + self._cam_dz
        # The "robot" profile's fixed z step, or the "sim" profile's schedule: equal steps
        # from the start height to the end height in `iterations`.
        self._dz = (c.z_step_m if c.z_step_m > 0 else
                    max(0.0, (start_cam - c.end_camera_height_m) / c.iterations))

    def _begin(self, context, base: ControllerState, t: float) -> ControllerState:
        return replace(base, phase=Phase.SERVO)

    def _policy_phase(self, context, s: ControllerState, t: float,
                      elapsed: float) -> ControllerState:
        if s.phase != Phase.SERVO:
            return super()._policy_phase(context, s, t, elapsed)
        return self._ctr_step(context, s, t)

    def _hand_clear(self, P_W: np.ndarray, grasp) -> bool:
        """Whether the open hand can come straight down to `grasp` (x, y, z, yaw): no
        surface seen under its fingers, palm or housing (outside the closing strip;
        outlines widened by `controller.hand_margin_m`) rises more than
        `controller.hand_clearance_m` above that part's front (`hand_overlap_m`)."""
        c = self._s.controller
        over = hand_overlap_m(P_W, hand_to_pose(grasp).GetAsMatrix4(), margin_m=c.hand_margin_m)
        return over <= c.hand_clearance_m

    def _best_clear(self, depth: np.ndarray, hand, actions: np.ndarray,
                    distances: np.ndarray) -> np.ndarray | None:
        """`controller.hand_check`: the best-scored candidate whose grasp (its height read
        from `depth` as the descent would read it) lets the open hand come down clear of
        the surfaces seen under it (`_hand_clear`); None when none does. Candidates are
        checked best first, up to the first that clears."""
        P_W = self._image_points(depth, hand)
        poses = apply_actions([hand[0], hand[1], hand[3]], actions)
        for i in np.argsort(distances, kind="stable"):
            if not np.isfinite(distances[i]):
                break
            x, y, yaw = poses[i]
            grasp = self._grasp_from_points(P_W, (x, y, hand[2], yaw))
            if self._hand_clear(P_W, grasp):
                return np.asarray(actions[i], dtype=float)
        return None

    def _ctr_step(self, context, s: ControllerState, t: float) -> ControllerState:
        c = self._s.controller
        hand = s.hand
        depth = np.array(self._depth.Eval(context).data[:, :, 0], copy=True)
        near = (min_depth_under_axis(depth, self._focal, self._X_GC.translation()[:2],
                                     c.stop_distance_m, c.stop_window_half_m)
                if c.stop_distance_m > 0 else np.inf)  # 0: no stop rule (paper-sim)
        cam_z = self._camera_height(hand)
        reason = ""
        if s.converging:
            if s.calm >= 2:
                reason = f"{s.stop_reason}; converged after {s.converging - 1} more iterations"
            elif s.converging > c.converge_iterations or s.iteration >= c.iterations:
                reason = (f"{s.stop_reason}; not converged in {s.converging - 1} more "
                          "iterations")
        elif near < c.stop_distance_m:
            reason = f"object within {c.stop_distance_m:.2f} m of the sensor ({near:.3f} m)"
        elif cam_z <= c.end_camera_height_m + 1e-6:
            reason = "hand at its lowest height"
        elif s.iteration >= c.iterations:
            reason = "iteration budget spent"
        if (reason and not s.converging and c.converge_iterations > 0
                and s.iteration < c.iterations):
            # Servo on at this height until converged (Algorithm 1's "until the
            # controller converges").
            s = replace(s, converging=1, stop_near_m=float(near), stop_reason=reason)
            reason = ""
        if reason:
            grasp = self._grasp_from_depth(depth, hand, hand)
            return replace(s, phase=Phase.DESCEND, phase_start_s=t, segment_from=hand,
                           grasp=grasp, stop_reason=reason)
        actions = np.asarray(self._actions.Eval(context), float)
        distances = np.asarray(self._distances.Eval(context), float)
        mask = self._target_mask(context, actions, hand)
        if mask is not None:
            distances = np.where(mask, distances, np.inf)
        scores = distances + self._memory_penalty(hand, actions)
        best, _ = choose_action(actions, scores)
        if s.converging and c.hand_check:
            clear = self._best_clear(depth, hand, actions, scores)
            best = best if clear is None else clear
        ratio = c.converge_step_ratio if s.converging and c.converge_step_ratio > 0 else c.step_ratio
        command = ratio * best
        moved = apply_actions([hand[0], hand[1], hand[3]], command[None])[0]
        if s.converging:
            # Hold the height; rise when a surface under the grasp axis comes nearer than
            # the stop rule allows (or than it was when the rule fired, if nearer then):
            # the descent's invariant, kept while the hand moves sideways.
            keep = min(s.stop_near_m, c.stop_distance_m)
            z = hand[2] + (max(0.0, keep - near) if np.isfinite(near) else 0.0)
            small = float(displacement_norm(command)) < c.converge_step_m
            s = replace(s, converging=s.converging + 1, calm=s.calm + 1 if small else 0)
        else:
            z = max(hand[2] - self._dz, c.end_camera_height_m - self._cam_dz)
        yaw = float(moved[2])
        if c.max_yaw_from_start_deg > 0:
            bound = c.max_yaw_from_start_deg
            yaw = float(np.clip(yaw, self._start[3] - bound, self._start[3] + bound))
        new_hand = (float(moved[0]), float(moved[1]), float(z), yaw)
        record = StepRecord(s.iteration, t, tuple(hand),
                            *(freeze(np.array(a, copy=True))
                              for a in (depth, actions, distances, best, command)))
        return replace(s, iteration=s.iteration + 1, hand=new_hand, segment_from=hand,
                       phase_start_s=t, last_step=record)
