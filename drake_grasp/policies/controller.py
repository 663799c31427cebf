"""The grasp controller: the paper's closed-loop CTR and the one-shot baselines, each
ending in the same predefined grasp motion (descend, close, lift, hold). The controller
sees sensors only (depth and label images, gripper state, time); whether its grasp held
is decided outside it, by the `GraspJudge` (systems/judge.py).

Policies (`policy` argument):
    ctr: Algorithm 1 - every control period score the sampled candidates, move a
        fraction r toward the best one in (x, y, theta), step down in z; stop at 14 cm,
        then servo on at that height until converged (`controller.converge_iterations`).
        r and the z steps are the scenario's controller profile
        (`scenario.CONTROLLER_PROFILES`): "sim", r = 0.2 and the camera from 0.3 m to
        0.15 m in 75 equal steps; "robot", r = 0.5 and 1 cm steps until the stop rule.
    cnn-ctr: the CNN's global best action from the first image, then CTR.
    cnn-only: the CNN's global best action from the first image, executed open loop.
    gpd: the paper's GPD baseline: the hand moves to a fixed viewpoint (the start's x, y
        and yaw, the GPD sensor `gpd.view_camera_height_m` above the table), rests
        `gpd.view_settle_s`, takes one image with the GPD sensor (`gpd_depth_image`) and
        asks `detect_fn` (`drake_grasp.policies.gpd.make_detector`) for a 6-DOF grasp (its
        approach may tilt up to `gpd.approach_max_tilt_deg` from straight down); then
        open loop to a pre-grasp `scripted.pregrasp_height_m` back along the approach,
        and the descent along the approach axis.
    gpd-geometric: the hand-tuned geometric detector (`drake_grasp.policies.gpd_geometric`) on the
        wrist camera's first image at the start pose, top-down, open loop.
    init: no motion (the paper's INIT, for the distance experiment).

Kinematic noise acts on every commanded planar displacement the same way: for gpd the
move from the viewpoint to the grasp's (x, y, yaw of x_G on the table) is corrupted, and
the grasp's tilt is kept.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from drake_grasp.geometry.actions import action_between, apply_actions, sample_actions_in_view
from drake_grasp.geometry.camera import PinholeCamera, focal_length_px
from drake_grasp.geometry.hand_model import (
    FINGERTIP_Z_M,
    FINGER_OUTER_X_M,
    PAD_HALF_WIDTH_M,
    STROKE_M,
)
from drake_grasp.policies.controller_state import (MOTION_PHASE, ControllerState,
                                                   Phase, StepRecord, hand_pose_memo,
                                                   hand_to_pose, pose_from_tuple, pose_to_hand,
                                                   pose_tuple, rot_z)
from drake_grasp.policies.decisions import (
    CLOSED_LOOP_POLICIES,
    choose_action,
    displacement_norm,
    grasp_height,
    hand_overlap_m,
    heights_in_hand_box,
    memory_penalty,
    image_points_W,
    widest_section_height,
    min_depth_under_axis,
)
from drake_grasp.config.scenario import Scenario
from drake_grasp.policies.kinematic_noise import executed_hand, executed_pose, noisy_displacement
from drake_grasp.systems.state import freeze
from drake_grasp.systems.supervisor import (
    grasp_motion_next,
    interpolate_pose,
    min_jerk,
    motion_phase_code,
)

class GraspController(LeafSystem):
    """Policy + predefined grasp motion; see the module docstring.

    Input ports:
        depth_image: post-processed wrist depth (ImageDepth32F).
        label_image: the wrist camera's label image (ImageLabel16I), for target mode.
        candidate_actions: (K, 3) from the ActionSampler.
        predicted_distances: (K,) from the DistanceEvaluator.
        gripper_state: [q_left, q_right, v_left, v_right].
        gpd_depth_image: the GPD sensor's depth (ImageDepth32F); evaluated once, at the
            viewpoint, by the gpd policy only (the others never evaluate it, so it costs
            them no rendering).
    Output ports:
        X_WG_desired: desired grasp-frame pose for differential IK.
        gripper_command: [width_m, grip_force_n].
        control_status: [control step, approaching, motion phase]: the CTR iteration (for
            the one-shot policies the number of control periods since the image they
            decided on: the start, or gpd's viewpoint; 0 before it), 1 until
            the gripper starts closing (then 0), and the phase of the shared grasp motion
            (`supervisor.MOTION_PHASES` index), which the GraspJudge reads.
        camera_height: (1,) the wrist camera's height above the table [m] at the pose
            the controller believes the hand holds (the start pose until it starts):
            proprioception, for a distance function that needs it (the height-map FCN's
            `DistanceEvaluator`).
    """

    def __init__(self, *, scenario: Scenario, policy: str, X_WG_start: RigidTransform,
                 X_GC: RigidTransform, score_fn=None, detect_fn=None,
                 target_label: int | None = None, X_GC_gpd: RigidTransform | None = None,
                 score_needs_height: bool = False):
        """Args:
            scenario, policy: the trial's scenario and the policy to run (see the module
                docstring).
            X_WG_start: the grasp frame's start pose (top-down).
            X_GC: the wrist camera in the grasp frame.
            score_fn: ctr, cnn-ctr, cnn-only: score(depth, actions) -> distances
                (score(depth, actions, camera_height_m=h) with `score_needs_height`).
            detect_fn: gpd: detect(depth (H, W) [m], X_WC 4x4) -> X_WG 4x4 or None;
                gpd-geometric: detect(depth, X_WC) -> (x, y, theta_deg, z) or None.
            target_label: the target object's label (target mode), or None.
            X_GC_gpd: the GPD sensor in the grasp frame (gpd: required).
            score_needs_height: cnn-only, cnn-ctr: pass the camera's height to score_fn
                (the height-map FCN; `evaluator.needs_camera_height`).
        """
        super().__init__()
        self._s = scenario
        self._failed = scenario.failure_memory.failed()
        self._policy = policy
        c = scenario.controller
        self._period = c.period_s
        p = X_WG_start.translation()
        R = X_WG_start.rotation().matrix()
        yaw = np.rad2deg(np.arctan2(R[1, 0], R[0, 0]))  # x_G = (cos yaw, sin yaw, 0)
        self._start = (float(p[0]), float(p[1]), float(p[2]), float(yaw))
        self._X_GC = X_GC
        self._cam_dz = -float(X_GC.translation()[2])  # camera above the grasp centre
        self._score = score_fn
        self._score_needs_height = bool(score_needs_height)
        self._detect = detect_fn
        self._target_label = target_label
        start_cam = self._start[2] + self._cam_dz
        # The "robot" profile's fixed z step, or the "sim" profile's schedule: equal steps
        # from the start height to the end height in `iterations`.
        self._dz = (c.z_step_m if c.z_step_m > 0 else
                    max(0.0, (start_cam - c.end_camera_height_m) / c.iterations))
        cam = scenario.camera
        self._focal = focal_length_px(cam.height, cam.fov_y_deg)
        # gpd: the viewpoint, the start's x, y and yaw with the GPD sensor
        # `view_camera_height_m` above the table (top-down: the sensor sits -z_C.z above
        # the grasp centre).
        self._X_GC_gpd = X_GC_gpd
        self._view = None
        if X_GC_gpd is not None:
            self._view = (self._start[0], self._start[1],
                          float(scenario.gpd.view_camera_height_m + X_GC_gpd.translation()[2]),
                          self._start[3])

        self._depth = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F()))
        self._label = self.DeclareAbstractInputPort("label_image", AbstractValue.Make(ImageLabel16I()))
        self._actions = self.DeclareAbstractInputPort(
            "candidate_actions", AbstractValue.Make(np.zeros((0, 3))))
        self._distances = self.DeclareAbstractInputPort(
            "predicted_distances", AbstractValue.Make(np.zeros(0)))
        self._gripper_state = self.DeclareVectorInputPort("gripper_state", 4)
        self._gpd_depth = self.DeclareAbstractInputPort(
            "gpd_depth_image", AbstractValue.Make(ImageDepth32F()))
        self._state = self.DeclareAbstractState(AbstractValue.Make(ControllerState()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._period, 0.0, self._Update)
        self.DeclareAbstractOutputPort(
            "X_WG_desired", lambda: AbstractValue.Make(RigidTransform()), self._CalcPose,
            {self.abstract_state_ticket(self._state), self.time_ticket()})
        self.DeclareVectorOutputPort("gripper_command", 2, self._CalcGripper,
                                     {self.abstract_state_ticket(self._state)})
        self.DeclareVectorOutputPort("control_status", 3, self._CalcStatus,
                                     {self.abstract_state_ticket(self._state), self.time_ticket()})
        self.DeclareVectorOutputPort("camera_height", 1, self._CalcCameraHeight,
                                     {self.abstract_state_ticket(self._state)})

    # -- queries ----------------------------------------------------------------------

    def get_controller_state(self, context) -> ControllerState:
        return context.get_abstract_state(self._state).get_value()

    def is_done(self, context) -> bool:
        return self.get_controller_state(context).phase == Phase.DONE

    def mode_name(self, context) -> str:
        return self.get_controller_state(context).phase.value

    def outcome(self, context) -> dict:
        """The policy's own data once done: iterations and stop_reason, or a
        failure_reason when it attempted no grasp (init, no GPD detection); gpd: its
        detection ("gpd_detection", the selected X_WG as 16 floats, row by row, before
        kinematic noise). Success and the failure class come from the GraspJudge."""
        return dict(self.get_controller_state(context).outcome)

    @property
    def start_hand(self) -> tuple:
        return self._start

    # -- geometry helpers --------------------------------------------------------------

    def _memory_penalty(self, hand, actions: np.ndarray) -> np.ndarray:
        """`policies.memory_penalty` of the run's remembered failed grasps (zeros when
        `failure_memory` is off or empty)."""
        return memory_penalty([hand[0], hand[1], hand[3]], actions, self._failed,
                              self._s.failure_memory.radius_m)

    def _camera_height(self, hand) -> float:
        return float(hand[2]) + self._cam_dz

    def _noisy(self, delta: np.ndarray, rng_key: int) -> np.ndarray:
        return noisy_displacement(self._s.noise, self._s.seed, delta, rng_key)

    def _executed(self, hand) -> tuple:
        return executed_hand(self._s.noise, self._start, hand)

    def _executed_pose(self, X_WG: RigidTransform) -> RigidTransform:
        return executed_pose(self._s.noise, self._start, X_WG)

    def _pregrasp(self, X_WG: RigidTransform) -> RigidTransform:
        """gpd: the pre-grasp, `pregrasp_height_m` back along the approach axis z_G."""
        z_G = X_WG.rotation().matrix()[:, 2]
        return RigidTransform(X_WG.rotation(),
                              X_WG.translation() - self._s.scripted.pregrasp_height_m * z_G)

    def _displaced_grasp(self, X_WG: np.ndarray, view) -> np.ndarray:
        """The detected grasp where the hand will believe it is after the commanded move
        from `view`: the planar displacement to the grasp's (x, y, yaw of x_G on the
        table) gets the kinematic noise (`_noisy`, as any commanded displacement); the
        grasp's height and tilt are kept."""
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
        delta = self._noisy(a, 0)
        moved = apply_actions(here, delta[None])[0]
        out = np.eye(4)
        out[:3, :3] = rot_z(np.deg2rad(moved[2] - yaw_goal)) @ R
        out[:3, 3] = [moved[0], moved[1], p[2]]
        return out

    def _grasp_from_depth(self, depth: np.ndarray, seen_from, hand) -> tuple:
        """The grasp at `hand`'s (x, y, yaw), its height read from a depth image taken
        with the hand at `seen_from`: the fingertips above the support seen under the
        open hand, the pads `grasp_depth_below_top_m` below the top seen between them."""
        return self._grasp_from_points(self._image_points(depth, seen_from), hand)

    def _image_points(self, depth: np.ndarray, seen_from) -> np.ndarray:
        """World points (4, N) of a depth image taken with the hand at `seen_from`."""
        X_WC = (hand_to_pose(seen_from) @ self._X_GC).GetAsMatrix4()
        return image_points_W(depth, self._focal, X_WC, self._s.camera.depth_max_m)

    def _grasp_from_points(self, P_W: np.ndarray, hand) -> tuple:
        """`_grasp_from_depth` from the image's world points (`_image_points`)."""
        X_WG = hand_to_pose(hand).GetAsMatrix4()
        between, x_between = heights_in_hand_box(P_W, X_WG, 0.5 * STROKE_M, PAD_HALF_WIDTH_M,
                                                 return_x=True)
        around = heights_in_hand_box(P_W, X_WG, FINGER_OUTER_X_M, PAD_HALF_WIDTH_M)
        # The object's widest section: only points above the support (the table or sheet
        # seen between the pads is not the object).
        support = float(np.min(around)) if np.size(around) else 0.0
        on_object = between > support + self._s.controller.support_margin_m
        widest = (widest_section_height(between[on_object], x_between[on_object])
                  if self._s.controller.grasp_at_widest_section else None)
        z = grasp_height(between, around, depth_below_top_m=self._s.scripted.grasp_depth_below_top_m,
                         fingertip_below_centre_m=FINGERTIP_Z_M,
                         support_margin_m=self._s.controller.support_margin_m,
                         widest_z=widest)
        return (hand[0], hand[1], min(z, hand[2]), hand[3])

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

    def _target_mask(self, context, actions: np.ndarray, hand) -> np.ndarray | None:
        """Which candidates put the hand centre over the target object's pixels."""
        if self._target_label is None:
            return None
        labels = self._label.Eval(context).data[:, :, 0]
        depth = self._depth.Eval(context).data[:, :, 0]
        target = labels == self._target_label
        if not target.any():
            return None
        h, w = labels.shape
        d = float(np.median(depth[target]))
        c_off = self._X_GC.translation()
        camera = PinholeCamera.centred(w, h, self._focal)
        u, v = (np.round(p).astype(int) for p in camera.project(
            actions[:, 0] - c_off[0], actions[:, 1] - c_off[1], d))
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        mask = np.zeros(len(actions), bool)
        mask[inside] = target[v[inside], u[inside]]
        if not mask.any():
            # Target out of the sampled region: head for the centre of its pixels.
            rows, cols = np.nonzero(target)
            x, y = camera.back_project(cols.mean(), rows.mean(), d)
            goal = np.array([x + c_off[0], y + c_off[1]])
            mask[np.argmin(np.linalg.norm(actions[:, :2] - goal, axis=1))] = True
        return mask

    # -- decisions ----------------------------------------------------------------------

    def _global_best(self, context, hand) -> np.ndarray:
        """cnn-only: the CNN's best action over the whole camera view."""
        cam = self._s.camera
        rng = np.random.default_rng([self._s.seed, 0, 31])
        actions = sample_actions_in_view(
            rng, self._s.controller.global_candidates,
            camera_height_m=self._camera_height(hand), fov_deg=cam.fov_y_deg,
            camera_offset_xy_G=self._X_GC.translation()[:2], margin_m=0.01)
        depth = self._depth.Eval(context).data[:, :, 0]
        height = ({"camera_height_m": self._camera_height(hand)} if self._score_needs_height
                  else {})
        distances = self._score(depth, actions, **height)
        mask = self._target_mask(context, actions, hand)
        if mask is not None:
            distances = np.where(mask, distances, np.inf)
        return choose_action(actions, distances + self._memory_penalty(hand, actions))[0]

    def _ctr_step(self, context, s: ControllerState, t: float) -> ControllerState:
        c = self._s.controller
        hand = s.hand
        depth = np.array(self._depth.Eval(context).data[:, :, 0], copy=True)
        near = min_depth_under_axis(depth, self._focal, self._X_GC.translation()[:2],
                                    c.stop_distance_m, c.stop_window_half_m)
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
        delta = self._noisy(command, s.iteration + 1)
        moved = apply_actions([hand[0], hand[1], hand[3]], delta[None])[0]
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
                              for a in (depth, actions, distances, best, delta)))
        return replace(s, iteration=s.iteration + 1, hand=new_hand, segment_from=hand,
                       phase_start_s=t, last_step=record)

    def _Update(self, context, state):
        s = self.get_controller_state(context)
        t = context.get_time()
        m = self._s.scripted
        elapsed = t - s.phase_start_s
        new = s
        if s.phase == Phase.START:
            new = self._Start(context, s, t)
        elif s.phase == Phase.VIEW:
            if elapsed >= m.approach_time_s + self._s.gpd.view_settle_s:
                new = self._gpd_detect(context, s, t)
        elif s.phase == Phase.APPROACH and elapsed >= m.approach_time_s:
            if self._policy == "cnn-ctr":
                new = replace(s, phase=Phase.SERVO, phase_start_s=t, segment_from=s.hand)
            elif s.grasp_pose is not None:
                new = replace(s, phase=Phase.DESCEND, phase_start_s=t)
            else:
                new = replace(s, phase=Phase.DESCEND, phase_start_s=t, segment_from=s.hand)
        elif s.phase == Phase.SERVO:
            new = self._ctr_step(context, s, t)
        elif s.phase != Phase.DONE:
            speed = float(np.abs(self._gripper_state.Eval(context)[2:]).max())
            nxt = grasp_motion_next(s.phase.value, elapsed, m, speed)
            if nxt is not None:
                new = replace(s, phase=Phase(nxt), phase_start_s=t)
                if nxt == "done":
                    # Keeps what the policy recorded on the way (gpd: its detection).
                    new = replace(new, outcome={**s.outcome, "stop_reason": s.stop_reason,
                                                "iterations": s.iteration})
        if new is not s:
            state.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _Start(self, context, s: ControllerState, t: float) -> ControllerState:
        start = self._start
        base = replace(s, hand=start, segment_from=start, phase_start_s=t)
        if self._policy == "init":
            return replace(base, phase=Phase.DONE, outcome={
                "failure_reason": "init: no grasp attempted", "iterations": 0})
        if self._policy == "ctr":
            return replace(base, phase=Phase.SERVO)
        if self._policy == "gpd":
            if self._view is None:
                raise ValueError("GraspController: policy 'gpd' needs X_GC_gpd (the GPD "
                                 "sensor in the grasp frame: GraspStation.X_GC_gpd)")
            return replace(base, phase=Phase.VIEW, hand=self._view)
        depth = np.array(self._depth.Eval(context).data[:, :, 0], copy=True)
        if self._policy in ("cnn-only", "cnn-ctr"):
            best = self._global_best(context, start)
            delta = self._noisy(best, 0)
            moved = apply_actions([start[0], start[1], start[3]], delta[None])[0]
            hand = (float(moved[0]), float(moved[1]), start[2], float(moved[2]))
            # Its height is read from the start image where the grasp will be.
            grasp = (self._grasp_from_depth(depth, start, hand)
                     if self._policy == "cnn-only" else None)
            # The one-shot move keeps the start height; the final descent (or CTR) follows.
            return replace(base, phase=Phase.APPROACH, hand=hand, grasp=grasp)
        # gpd-geometric
        X_WC = hand_to_pose(start) @ self._X_GC
        detection = self._detect(depth, X_WC.GetAsMatrix4())
        if detection is None:
            return replace(base, phase=Phase.DONE, outcome={
                "failure_reason": "missed: no grasp detected", "iterations": 0})
        x, y, theta, z = detection
        # Move there as one displacement (noisy like any commanded displacement).
        goal = np.array([x, y, theta])
        a = action_between(np.array([start[0], start[1], start[3]]), goal)
        delta = self._noisy(a, 0)
        moved = apply_actions([start[0], start[1], start[3]], delta[None])[0]
        hand = (float(moved[0]), float(moved[1]), start[2], float(moved[2]))
        grasp = (hand[0], hand[1], float(z), hand[3])
        return replace(base, phase=Phase.APPROACH, hand=hand, grasp=grasp)

    def _gpd_detect(self, context, s: ControllerState, t: float) -> ControllerState:
        """gpd at the viewpoint: the one GPD image, the detection, the move's target."""
        depth = np.array(self._gpd_depth.Eval(context).data[:, :, 0], copy=True)
        X_WC = hand_to_pose(s.hand) @ self._X_GC_gpd  # believed: the commanded viewpoint
        detection = self._detect(depth, X_WC.GetAsMatrix4())
        if detection is None:
            return replace(s, phase=Phase.DONE, phase_start_s=t, outcome={
                "failure_reason": "missed: no grasp detected", "iterations": 0})
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
        grasp_pose = self._displaced_grasp(X, s.hand)
        pre = self._pregrasp(RigidTransform(grasp_pose))
        return replace(s, phase=Phase.APPROACH, phase_start_s=t, segment_from=s.hand,
                       hand=pose_to_hand(pre), grasp=pose_to_hand(grasp_pose),
                       grasp_pose=pose_tuple(grasp_pose), decided_s=t,
                       outcome={"gpd_detection": pose_tuple(X)})

    # -- outputs ------------------------------------------------------------------------

    def _CalcPose(self, context, output):
        s = self.get_controller_state(context)
        m = self._s.scripted
        t = context.get_time()
        elapsed = t - s.phase_start_s
        if s.phase in (Phase.START,):
            hand = self._start
            X = hand_pose_memo(self._executed(hand))
        elif s.phase == Phase.VIEW:
            X = interpolate_pose(hand_pose_memo(self._executed(s.segment_from)),
                                 hand_pose_memo(self._executed(s.hand)),
                                 min_jerk(elapsed / m.approach_time_s))
        elif s.grasp_pose is not None:
            X = self._gpd_pose(s, elapsed)
        elif s.phase == Phase.APPROACH:
            X = interpolate_pose(hand_pose_memo(self._executed(s.segment_from)),
                                 hand_pose_memo(self._executed(s.hand)),
                                 min_jerk(elapsed / m.approach_time_s))
        elif s.phase == Phase.SERVO:
            # Move to the new target within one control period.
            X = interpolate_pose(hand_pose_memo(self._executed(s.segment_from)),
                                 hand_pose_memo(self._executed(s.hand)),
                                 min_jerk(elapsed / (0.8 * self._period)))
        elif s.phase == Phase.DESCEND:
            X = interpolate_pose(hand_pose_memo(self._executed(s.segment_from)),
                                 hand_pose_memo(self._executed(s.grasp)),
                                 min_jerk(elapsed / m.descend_time_s))
        elif s.phase == Phase.CLOSE:
            X = hand_pose_memo(self._executed(s.grasp))
        elif s.phase == Phase.LIFT:
            lifted = (s.grasp[0], s.grasp[1], s.grasp[2] + m.lift_height_m, s.grasp[3])
            X = interpolate_pose(hand_pose_memo(self._executed(s.grasp)),
                                 hand_pose_memo(self._executed(lifted)),
                                 min_jerk(elapsed / m.lift_time_s))
        elif s.grasp is not None:
            lifted = (s.grasp[0], s.grasp[1], s.grasp[2] + m.lift_height_m, s.grasp[3])
            X = hand_pose_memo(self._executed(lifted))
        else:
            X = hand_pose_memo(self._executed(s.hand))
        output.set_value(X)

    def _gpd_pose(self, s: ControllerState, elapsed: float) -> RigidTransform:
        """gpd after its detection: to the pre-grasp, along the approach axis to the
        grasp, close there, lift straight up (orientation kept), hold."""
        m = self._s.scripted
        grasp = pose_from_tuple(s.grasp_pose)
        pre = self._pregrasp(grasp)
        lifted = RigidTransform(grasp.rotation(), grasp.translation() + [0.0, 0.0, m.lift_height_m])
        ex = self._executed_pose
        if s.phase == Phase.APPROACH:
            return interpolate_pose(hand_to_pose(self._executed(s.segment_from)), ex(pre),
                                    min_jerk(elapsed / m.approach_time_s))
        if s.phase == Phase.DESCEND:
            return interpolate_pose(ex(pre), ex(grasp), min_jerk(elapsed / m.descend_time_s))
        if s.phase == Phase.CLOSE:
            return ex(grasp)
        if s.phase == Phase.LIFT:
            return interpolate_pose(ex(grasp), ex(lifted), min_jerk(elapsed / m.lift_time_s))
        return ex(lifted)

    def _CalcGripper(self, context, output: BasicVector):
        s = self.get_controller_state(context)
        closed = s.phase in (Phase.CLOSE, Phase.LIFT, Phase.HOLD) or (
            s.phase == Phase.DONE and s.grasp is not None)
        g = self._s.gripper
        output.SetFromVector([0.0 if closed else g.open_width_m, g.grip_force_n])

    def _CalcCameraHeight(self, context, output: BasicVector):
        s = self.get_controller_state(context)
        hand = self._start if s.phase == Phase.START else s.hand
        output.SetAtIndex(0, self._camera_height(hand))

    def _CalcStatus(self, context, output: BasicVector):
        s = self.get_controller_state(context)
        if s.phase in (Phase.START, Phase.VIEW, Phase.SERVO) or self._policy in CLOSED_LOOP_POLICIES:
            step = s.iteration
        else:
            # Control periods since the image the policy decided on (a disturbance "after
            # the 3rd controller iteration" comes after the one-shot decision, as on the
            # paper's robot, where GPD executed as if the pile had not moved).
            step = int(round((context.get_time() - s.decided_s) / self._period))
        approaching = s.phase in (Phase.START, Phase.APPROACH, Phase.SERVO, Phase.DESCEND)
        output.SetFromVector([float(step), 1.0 if approaching else 0.0,
                              motion_phase_code(MOTION_PHASE[s.phase])])
