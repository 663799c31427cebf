"""The CNN's one look: its best action over the whole first image (`cnn-only`, executed
open loop to a grasp read from that image; `cnn-ctr`, followed by CTR).

The candidates are `controller.global_candidates` actions drawn so the displaced hand
centre stays in the camera's view, scored by the CNN (`score_fn`), masked to the target
in target mode, penalised near remembered failed grasps; the best is commanded as one
displacement at the start height (the `KinematicNoise` system noises it like any
commanded move).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from drake_grasp.geometry.actions import apply_actions, sample_actions_in_view
from drake_grasp.policies.controller import GraspController
from drake_grasp.policies.controller_state import ControllerState, Phase
from drake_grasp.policies.ctr import CTRController
from drake_grasp.policies.decisions import choose_action


class _FirstLook:
    """The CNN's global best action from the first image (mixed into a GraspController)."""

    EXTRAS = ("score_fn", "score_needs_height")

    def __init__(self, *, score_fn, score_needs_height: bool = False, **kwargs):
        """Args:
            score_fn: score(depth, actions) -> distances (score(depth, actions,
                camera_height_m=h) with `score_needs_height`).
            score_needs_height: pass the camera's height to score_fn (the height-map
                FCN; `evaluator.needs_camera_height`).
            others: as `GraspController`.
        """
        super().__init__(**kwargs)
        self._score = score_fn
        self._score_needs_height = bool(score_needs_height)

    def _global_best(self, context, hand) -> np.ndarray:
        """The CNN's best action over the whole camera view from `hand`."""
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

    def _first_move(self, context) -> tuple:
        """The hand after the one-shot move to the global best (start height kept)."""
        start = self._start
        best = self._global_best(context, start)
        moved = apply_actions([start[0], start[1], start[3]], np.asarray(best)[None])[0]
        return (float(moved[0]), float(moved[1]), start[2], float(moved[2]))


class CNNOnlyController(_FirstLook, GraspController):
    """cnn-only: the CNN's global best action from the first image, executed open loop;
    the grasp's height is read from the start image where the grasp will be."""

    policy = "cnn-only"

    def _begin(self, context, base: ControllerState, t: float) -> ControllerState:
        depth = np.array(self._depth.Eval(context).data[:, :, 0], copy=True)
        hand = self._first_move(context)
        grasp = self._grasp_from_depth(depth, self._start, hand)
        # The one-shot move keeps the start height; the final descent follows.
        return replace(base, phase=Phase.APPROACH, hand=hand, grasp=grasp)


class CNNCTRController(_FirstLook, CTRController):
    """cnn-ctr: the CNN's global best action from the first image, then CTR from there."""

    policy = "cnn-ctr"

    def _begin(self, context, base: ControllerState, t: float) -> ControllerState:
        # The one-shot move keeps the start height; CTR follows.
        return replace(base, phase=Phase.APPROACH, hand=self._first_move(context),
                       grasp=None)

    def _approach_done(self, s: ControllerState, t: float) -> ControllerState:
        return replace(s, phase=Phase.SERVO, phase_start_s=t, segment_from=s.hand)
