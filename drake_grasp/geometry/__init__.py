"""Pure numpy geometry of the hand, the wrist camera and grasps: planar actions
a = (x, y, theta) (`actions`), the pinhole camera model (`camera`), depth-image noise
(`sensing`) and the analytic ground truth of grasps (`grasps`).

Floor 3: imports `core` and `objects` only; no Drake systems, no torch.
"""
