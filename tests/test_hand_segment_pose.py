"""The controller's memoized pose along a move equals `interpolate_pose`, bit for bit."""

import numpy as np
import pytest

from drake_grasp.policies.controller_state import hand_pose_memo, hand_segment_pose
from drake_grasp.systems.supervisor import interpolate_pose


@pytest.mark.parametrize("a, b", [
    ((0.5, 0.0, 0.3, 10.0), (0.52, -0.01, 0.29, 35.0)),
    ((0.5, 0.0, 0.3, 170.0), (0.5, 0.02, 0.25, -170.0)),  # across +-180: the hemisphere flip
    ((0.4, 0.1, 0.2, -90.0), (0.4, 0.1, 0.35, -90.0)),    # a lift: rotation unchanged
])
def test_hand_segment_pose_is_interpolate_pose_bit_for_bit(a, b):
    for s in (0.0, 1e-9, 0.25, 0.5, 0.9999, 1.0):
        want = interpolate_pose(hand_pose_memo(a), hand_pose_memo(b), s).GetAsMatrix4()
        for _ in range(2):  # the first call fills the memo, the second reads it
            got = hand_segment_pose(a, b, s).GetAsMatrix4()
            assert np.array_equal(got, want), (a, b, s)
