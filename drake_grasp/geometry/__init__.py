"""Pure numpy geometry of the hand, the wrist camera and grasps: planar actions
a = (x, y, theta) (`actions`), the pinhole camera model (`camera`), depth-image noise
(`sensing`) and the analytic ground truth of grasps: the ground-truth search (`grasps`)
on the 2F-85 model (`hand_model`), a scene's surface samples (`scene_samples`, searched
with `point_grid`), the hand and contact tests (`hand_checks`, `contact_physics`),
GPD-style candidates (`grasp_candidates`), the label metric (`grasp_metric`) and the
scripted top-down grasp (`topdown`).

Floor 3: imports `core` and `objects` only; no Drake systems, no torch.
"""
