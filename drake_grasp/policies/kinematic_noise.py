"""The kinematic noise models (the paper's "kinematic noise"): what the hand really does
for what the policy commands. The policy keeps believing its command.

gaussian: every commanded planar displacement is corrupted (`noisy_displacement`, seeded
by the trial and the step, so the same trial draws the same noise); offset: the hand
really goes a constant offset away from every believed pose, ramped in over the first
`offset_ramp_m` of the move (`executed_hand`, `executed_pose` for a tilted grasp).
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from drake_grasp.geometry.actions import apply_actions
from drake_grasp.policies.controller_state import pose_to_hand, rot_z
from drake_grasp.policies.decisions import gaussian_noisy_displacement, offset_fraction


def noisy_displacement(noise, seed: int, delta: np.ndarray, rng_key: int) -> np.ndarray:
    """The displacement the hand makes for the commanded `delta` (gaussian noise; others
    leave it as commanded)."""
    if noise.kind != "gaussian" or not np.any(delta):
        return delta
    rng = np.random.default_rng([seed, rng_key, 29])
    return gaussian_noisy_displacement(delta, rng, noise.gaussian_scale)


def executed_hand(noise, start, hand) -> tuple:
    """Where the hand really goes for a believed pose (the constant-offset model)."""
    if noise.kind != "offset":
        return tuple(hand)
    moved = float(np.hypot(hand[0] - start[0], hand[1] - start[1]))
    f = offset_fraction(moved, noise.offset_ramp_m)
    dx, dy = noise.offset_xy_m
    out = apply_actions([hand[0], hand[1], hand[3]],
                        np.array([[f * dx, f * dy, f * noise.offset_theta_deg]]))[0]
    return (float(out[0]), float(out[1]), float(hand[2]), float(out[2]))


def executed_pose(noise, start, X_WG: RigidTransform) -> RigidTransform:
    """`executed_hand` for a full (possibly tilted) grasp-frame pose: the offset moves
    its (x, y) and turns it about the world vertical through its origin."""
    if noise.kind != "offset":
        return X_WG
    hand = pose_to_hand(X_WG)
    x, y, _, yaw = executed_hand(noise, start, hand)
    R = rot_z(np.deg2rad(yaw - hand[3])) @ X_WG.rotation().matrix()
    return RigidTransform(RotationMatrix(R), [x, y, hand[2]])
