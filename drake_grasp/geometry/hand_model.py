"""The 2F-85 parallel-jaw hand as the analytic grasp tests model it (pure numpy).

Owns the hand's dimensions in the grasp frame G (stroke, pads, finger bodies, palm and
housing, from models/robotiq_2f85), the outlines derived from them, the height of the
sheet the objects lie on (what the hand must clear), and `topdown_rotation`, the
orientation of a grasp that approaches straight down. Conventions: G sits at the centre
between the two pads; its z axis is the approach direction and its x axis the closing
direction; a top-down grasp has z_G = -z_W and R_WG = Rz(yaw) Rx(pi).
"""

from __future__ import annotations

import numpy as np

STROKE_M = 0.085
# Pad geometry (models/robotiq_2f85/README.md): half length along the approach axis
# and half width across it.
PAD_HALF_LENGTH_M = 0.019
PAD_HALF_WIDTH_M = 0.011


def topdown_rotation(yaw: float) -> np.ndarray:
    """R_WG of a grasp that approaches straight down with closing direction at `yaw`."""
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    Rx_pi = np.diag([1.0, -1.0, -1.0])
    return Rz @ Rx_pi



# Hand model (models/robotiq_2f85/robotiq_2f85.urdf, README.md), in the grasp frame G
# (0.135 m in front of robotiq_base; z_G approach, x_G closing), fingers fully open:
#   pads          |x| in [0.0425, 0.0485], |y| <= 0.011, z in [-0.019, 0.019]
#   finger bodies |x| in [0.0485, 0.0585], |y| <= 0.011, z in [-0.030, 0.019]
#   palm          |x| <= 0.065, |y| <= 0.015,           z in [-0.041, -0.025]
#   housing       cylinder r 0.04,                      z in [-0.121, -0.031]
# The hand reaches a grasp by moving along its approach axis (the controller descends
# straight down), so the collision test uses the volume each part sweeps on the way in:
# every part is extended backwards (along -z_G) without limit. That also covers the
# coupling, the flange and the wrist above the housing.

GRASP_FRAME_IN_BASE_M = 0.135
PAD_THICKNESS_M = 0.006
FINGER_BODY_THICKNESS_M = 0.010
# Outer face of a fully open finger (pad + finger body) along x_G.
FINGER_OUTER_X_M = 0.5 * STROKE_M + PAD_THICKNESS_M + FINGER_BODY_THICKNESS_M
# Pads and finger bodies both end at z = 0.154 in robotiq_base: the fingertips.
FINGERTIP_Z_M = PAD_HALF_LENGTH_M
PALM_HALF_X_M = 0.065
PALM_HALF_Y_M = 0.015
PALM_FRONT_Z_M = 0.110 - GRASP_FRAME_IN_BASE_M  # -0.025
HOUSING_RADIUS_M = 0.04
HOUSING_FRONT_Z_M = 0.104 - GRASP_FRAME_IN_BASE_M  # -0.031
# Radius of the hand's outline seen along the approach axis (the palm's corners) and
# of the closing region's outline (the pads' sweep).
HAND_FOOTPRINT_RADIUS_M = float(np.hypot(PALM_HALF_X_M, PALM_HALF_Y_M))
STRIP_RADIUS_M = float(np.hypot(0.5 * STROKE_M, PAD_HALF_WIDTH_M))

# Top of the 2 mm sheet the objects lie on (the table top is z = 0).
TABLE_TOP_Z_M = 0.002
