"""The grasp controller's shared part: the ports every built-in policy has, the
predefined grasp motion each one ends in (descend, close, lift, hold), and the geometry
they share (a grasp's height read from a depth image, target mode's candidate mask).
The controller sees sensors only (depth and label images, gripper state, time); whether
its grasp held is decided outside it, by the `GraspJudge` (systems/judge.py).

One class per policy, each a `GraspController` subclass (`make_controller` in
`controllers` builds the one a policy name asks for):
    ctr (`ctr.CTRController`): the paper's Algorithm 1.
    cnn-only, cnn-ctr (`cnn_first_look`): the CNN's global best action from the first
        image, executed open loop, or followed by CTR.
    gpd, gpd-geometric (`detector_controllers`): one detection, then open loop.
    init (`controllers.InitController`): no motion (the paper's INIT).

A subclass says what it does at the start (`_begin`), in its own phases (`_policy_phase`:
CTR's servo iterations, GPD's viewpoint) and when its one-shot approach ends
(`_approach_done`); the motion after that is this class's. The controller commands
the poses it believes in; kinematic noise is the `systems.kinematic_noise.KinematicNoise`
system between its `X_WG_desired` and the station, which reads the goal of each
commanded move from `X_WG_goal`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from drake_grasp.geometry.camera import PinholeCamera, focal_length_px
from drake_grasp.geometry.hand_model import (
    FINGERTIP_Z_M,
    FINGER_OUTER_X_M,
    PAD_HALF_WIDTH_M,
    STROKE_M,
)
from drake_grasp.policies.controller_state import (MOTION_PHASE, ControllerState,
                                                   Phase, hand_pose_memo, hand_segment_pose,
                                                   hand_to_pose)
from drake_grasp.policies.decisions import (
    grasp_height,
    heights_in_hand_box,
    memory_penalty,
    image_points_W,
    widest_section_height,
)
from drake_grasp.config.scenario import Scenario
from drake_grasp.systems.supervisor import (
    grasp_motion_next,
    min_jerk,
    motion_phase_code,
)


class GraspController(LeafSystem):
    """A built-in policy plus the predefined grasp motion (a subclass per policy; see the
    module docstring).

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
        X_WG_desired: desired grasp-frame pose for differential IK (the pose the
            controller believes it commands).
        X_WG_goal: the believed pose the current commanded move ends at (the
            `KinematicNoise` system draws a move's error when it changes).
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

    policy = ""  # the policy name (`Scenario.policy`) the subclass runs
    closed_loop = False  # whether its control steps are iterations (`_CalcStatus`)
    EXTRAS: tuple = ()  # the keyword arguments its __init__ takes beyond the base's

    def __init__(self, *, scenario: Scenario, X_WG_start: RigidTransform,
                 X_GC: RigidTransform, target_label: int | None = None):
        """Args:
            scenario: the trial's scenario.
            X_WG_start: the grasp frame's start pose (top-down).
            X_GC: the wrist camera in the grasp frame.
            target_label: the target object's label (target mode), or None.
        """
        super().__init__()
        self._s = scenario
        self._failed = scenario.failure_memory.failed()
        c = scenario.controller
        self._period = c.period_s
        p = X_WG_start.translation()
        R = X_WG_start.rotation().matrix()
        yaw = np.rad2deg(np.arctan2(R[1, 0], R[0, 0]))  # x_G = (cos yaw, sin yaw, 0)
        self._start = (float(p[0]), float(p[1]), float(p[2]), float(yaw))
        self._X_GC = X_GC
        self._cam_dz = -float(X_GC.translation()[2])  # camera above the grasp centre
        self._target_label = target_label
        cam = scenario.camera
        self._focal = focal_length_px(cam.height, cam.fov_y_deg)
        self._declare_ports()

    def _declare_ports(self) -> None:
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
        self.DeclareAbstractOutputPort(
            "X_WG_goal", lambda: AbstractValue.Make(RigidTransform()), self._CalcGoal,
            {self.abstract_state_ticket(self._state)})
        self.DeclareVectorOutputPort("gripper_command", 2, self._CalcGripper,
                                     {self.abstract_state_ticket(self._state)})
        self.DeclareVectorOutputPort("control_status", 3, self._CalcStatus,
                                     {self.abstract_state_ticket(self._state), self.time_ticket()})
        self.DeclareVectorOutputPort("camera_height", 1, self._CalcCameraHeight,
                                     {self.abstract_state_ticket(self._state)})

    # -- what a policy decides (its subclass) ---------------------------------------------

    def _begin(self, context, base: ControllerState, t: float) -> ControllerState:
        """The state after the first update: `base` is the start (hand at the start pose,
        the phase's clock at `t`); the subclass sets its first phase."""
        raise NotImplementedError(f"{type(self).__name__}: a GraspController subclass "
                                  "defines _begin")

    def _policy_phase(self, context, s: ControllerState, t: float,
                      elapsed: float) -> ControllerState:
        """An update in a phase only some policies have (SERVO, VIEW)."""
        raise NotImplementedError(f"{type(self).__name__}: no phase {s.phase.value!r}")

    def _approach_done(self, s: ControllerState, t: float) -> ControllerState:
        """The one-shot approach has ended: the final descent to `s.grasp` from here."""
        return replace(s, phase=Phase.DESCEND, phase_start_s=t, segment_from=s.hand)

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
        the kinematic noise the station adds). Success and the failure class come from the GraspJudge."""
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

    # -- the shared motion ---------------------------------------------------------------

    def _Update(self, context, state):
        s = self.get_controller_state(context)
        t = context.get_time()
        m = self._s.scripted
        elapsed = t - s.phase_start_s
        new = s
        if s.phase == Phase.START:
            start = self._start
            new = self._begin(context, replace(s, hand=start, segment_from=start,
                                               phase_start_s=t), t)
        elif s.phase in (Phase.VIEW, Phase.SERVO):
            new = self._policy_phase(context, s, t, elapsed)
        elif s.phase == Phase.APPROACH and elapsed >= m.approach_time_s:
            new = self._approach_done(s, t)
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

    # -- outputs ------------------------------------------------------------------------

    def _CalcPose(self, context, output):
        s = self.get_controller_state(context)
        output.set_value(self._pose(s, context.get_time() - s.phase_start_s))

    def _CalcGoal(self, context, output):
        output.set_value(self._goal(self.get_controller_state(context)))

    def _goal(self, s: ControllerState) -> RigidTransform:
        """The believed pose the move under way in state `s` ends at: the grasp once the
        policy has one and is past its own phases, else the hand's target."""
        if s.grasp is not None and s.phase not in (Phase.START, Phase.VIEW, Phase.SERVO,
                                                   Phase.APPROACH):
            return hand_pose_memo(tuple(s.grasp))
        return hand_pose_memo(tuple(self._start if s.phase == Phase.START else s.hand))

    def _pose(self, s: ControllerState, elapsed: float) -> RigidTransform:
        """The commanded grasp-frame pose in state `s`, `elapsed` into its phase."""
        m = self._s.scripted
        if s.phase == Phase.START:
            return hand_pose_memo(tuple(self._start))
        if s.phase in (Phase.VIEW, Phase.APPROACH):
            return hand_segment_pose(tuple(s.segment_from), tuple(s.hand),
                                     min_jerk(elapsed / m.approach_time_s))
        if s.phase == Phase.SERVO:
            # Move to the new target within one control period.
            return hand_segment_pose(tuple(s.segment_from), tuple(s.hand),
                                     min_jerk(elapsed / (0.8 * self._period)))
        if s.phase == Phase.DESCEND:
            return hand_segment_pose(tuple(s.segment_from), tuple(s.grasp),
                                     min_jerk(elapsed / m.descend_time_s))
        if s.phase == Phase.CLOSE:
            return hand_pose_memo(tuple(s.grasp))
        if s.phase == Phase.LIFT:
            lifted = (s.grasp[0], s.grasp[1], s.grasp[2] + m.lift_height_m, s.grasp[3])
            return hand_segment_pose(tuple(s.grasp), tuple(lifted),
                                     min_jerk(elapsed / m.lift_time_s))
        if s.grasp is not None:
            lifted = (s.grasp[0], s.grasp[1], s.grasp[2] + m.lift_height_m, s.grasp[3])
            return hand_pose_memo(tuple(lifted))
        return hand_pose_memo(tuple(s.hand))

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
        if s.phase in (Phase.START, Phase.VIEW, Phase.SERVO) or self.closed_loop:
            step = s.iteration
        else:
            # Control periods since the image the policy decided on (a disturbance "after
            # the 3rd controller iteration" comes after the one-shot decision, as on the
            # paper's robot, where GPD executed as if the pile had not moved).
            step = int(round((context.get_time() - s.decided_s) / self._period))
        approaching = s.phase in (Phase.START, Phase.APPROACH, Phase.SERVO, Phase.DESCEND)
        output.SetFromVector([float(step), 1.0 if approaching else 0.0,
                              motion_phase_code(MOTION_PHASE[s.phase])])
