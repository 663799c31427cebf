"""What the grasp controller remembers and how it writes hand poses.

`ControllerState` is the controller's abstract state (frozen: a Context shares it), with
its `Phase` and the last control decision (`StepRecord`); a hand is [x, y, z, yaw_deg] of
the top-down grasp frame (`hand_to_pose`, `pose_to_hand`). Imports only lower floors and
`systems.state`.
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform, RotationMatrix

from drake_grasp.geometry.hand_model import topdown_rotation
from drake_grasp.systems.state import shared_when_copied


class Phase(enum.Enum):
    START = "start"        # before the first image
    VIEW = "view"          # gpd: to the viewpoint, rest, take the one GPD image
    APPROACH = "approach"  # open-loop move to a one-shot target (gpd, cnn-only, cnn-ctr)
    SERVO = "servo"        # CTR iterations
    DESCEND = "descend"
    CLOSE = "close"
    LIFT = "lift"
    HOLD = "hold"
    DONE = "done"


# The shared grasp motion's phase (`supervisor.MOTION_PHASES`) of each controller phase.
MOTION_PHASE = {Phase.START: "approach", Phase.VIEW: "approach", Phase.APPROACH: "approach",
                 Phase.SERVO: "approach",
                 Phase.DESCEND: "descend", Phase.CLOSE: "close", Phase.LIFT: "lift",
                 Phase.HOLD: "hold", Phase.DONE: "done"}


@dataclass(frozen=True)
class StepRecord:
    """One control decision, for pictures and analysis."""

    iteration: int
    time_s: float
    hand: tuple  # believed hand pose [x, y, z, yaw_deg] when the image was taken
    depth: np.ndarray
    actions: np.ndarray
    distances: np.ndarray
    chosen: np.ndarray
    moved: np.ndarray  # displacement commanded (before the station's kinematic noise)


@shared_when_copied
@dataclass(frozen=True)
class ControllerState:
    """Everything the controller remembers (the Context's abstract state)."""

    phase: Phase = Phase.START
    phase_start_s: float = 0.0
    iteration: int = 0
    hand: tuple = (0.0, 0.0, 0.0, 0.0)         # believed target [x, y, z, yaw_deg]
    segment_from: tuple = (0.0, 0.0, 0.0, 0.0)  # start of the current interpolated move
    # Final grasp [x, y, z, yaw_deg] (yaw of x_G projected onto the table).
    grasp: tuple | None = None
    # gpd: the full believed grasp pose X_WG, 16 floats (a 4x4 matrix row by row); its
    # approach may be tilted. None for the top-down policies.
    grasp_pose: tuple | None = None
    stop_reason: str = ""
    last_step: StepRecord | None = None
    outcome: dict = field(default_factory=dict)
    # When a one-shot policy took the image it decided on [s]: 0 for those deciding at the
    # start; gpd's image comes at the viewpoint. Its control steps count from here.
    decided_s: float = 0.0
    # CTR after its stop rule fired (`controller.converge_iterations`): iterations spent
    # at the stop height, the nearest depth under the grasp axis when it fired [m], and
    # how many iterations in a row the commanded move was below `converge_step_m`.
    converging: int = 0
    stop_near_m: float = 0.0
    calm: int = 0
    # A policy's own memory between control periods, frozen like this state (gpd-track:
    # its `gpd_track.Track`); None for the others.
    memory: object = None


def hand_to_pose(hand) -> RigidTransform:
    x, y, z, yaw = (float(v) for v in hand)
    return RigidTransform(RotationMatrix(topdown_rotation(np.deg2rad(yaw))), [x, y, z])


@functools.lru_cache(maxsize=32)
def hand_pose_memo(hand: tuple) -> RigidTransform:
    """`hand_to_pose` memoized for `_CalcPose`, which runs at every plant step with the
    same few segment end points. The result is shared: read it, never modify it."""
    return hand_to_pose(hand)


@functools.lru_cache(maxsize=32)
def _segment_ends(a: tuple, b: tuple) -> tuple:
    """The end points of a move from hand `a` to hand `b`, as `interpolate_pose` uses them:
    positions, and quaternions on the same hemisphere."""
    X_a, X_b = hand_pose_memo(a), hand_pose_memo(b)
    qa, qb = X_a.rotation().ToQuaternion(), X_b.rotation().ToQuaternion()
    if np.dot(qa.wxyz(), qb.wxyz()) < 0.0:
        qb = Quaternion(-qb.wxyz())
    return X_a.translation(), X_b.translation(), qa, qb


def _segment_pose(a: tuple, b: tuple, s: float) -> RigidTransform:
    pa, pb, qa, qb = _segment_ends(a, b)
    return RigidTransform(RotationMatrix(qa.slerp(s, qb)), (1.0 - s) * pa + s * pb)


_segment_end = functools.lru_cache(maxsize=32)(_segment_pose)


def hand_segment_pose(a: tuple, b: tuple, s: float) -> RigidTransform:
    """`supervisor.interpolate_pose(hand_pose_memo(a), hand_pose_memo(b), s)`, the same
    arithmetic on end points memoized for `_CalcPose` (every plant step); at s = 0 or 1
    (before or after the move) the pose itself is memoized. Shared: never modify it."""
    return _segment_end(a, b, s) if s == 0.0 or s == 1.0 else _segment_pose(a, b, s)


def pose_to_hand(X_WG) -> tuple:
    """[x, y, z, yaw_deg] of a grasp-frame pose (RigidTransform or 4x4), yaw that of the
    closing direction x_G projected onto the table (a tilted grasp's too)."""
    X = np.asarray(getattr(X_WG, "GetAsMatrix4", lambda: X_WG)(), dtype=float)
    return (float(X[0, 3]), float(X[1, 3]), float(X[2, 3]),
            float(np.rad2deg(np.arctan2(X[1, 0], X[0, 0]))))


def rot_z(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose_from_tuple(values) -> RigidTransform:
    return RigidTransform(np.asarray(values, dtype=float).reshape(4, 4))


def pose_tuple(X: np.ndarray) -> tuple:
    return tuple(float(v) for v in np.asarray(X, dtype=float).reshape(16))
