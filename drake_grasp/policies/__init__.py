"""The policies and the systems on their side of the Diagram: the paper's
closed-loop controller and the other built-in policies, one class each behind the
shared grasp motion of `controller.GraspController` (CTR in `ctr`, cnn-only and cnn-ctr
in `cnn_first_look`, gpd and gpd-geometric in `detector_controllers`, built by name with
`controllers.make_controller`; their state in `controller_state`, their decisions as pure
functions in `decisions`; kinematic noise is `systems.kinematic_noise`, between a policy
and the station), the CNN distance evaluator and action sampler
(`evaluator`), grasp-pose detection (`gpd` with its ranking `gpd_ranking`, `gpd_geometric`
with its stages in `gpd_geometric_*`) and user policies (`plugins`). A policy sees only
sensors: depth images, gripper state, timing.

Floor 8: imports `world`, `systems` and the floors below.
"""
