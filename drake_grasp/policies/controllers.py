"""Which controller class runs which built-in policy, and the one call that builds it.

`CONTROLLERS` maps each policy name the `GraspController` family runs to its class;
`make_controller(policy, ...)` builds one, passing each class only the arguments it
takes (`EXTRAS`). Every built-in policy but `scripted` (the ScriptedGraspSupervisor,
`systems.supervisor`) is here; user policies come from `plugins`.
"""

from __future__ import annotations

from dataclasses import replace

from pydrake.math import RigidTransform

from drake_grasp.config.scenario import Scenario
from drake_grasp.policies.cnn_first_look import CNNCTRController, CNNOnlyController
from drake_grasp.policies.controller import GraspController
from drake_grasp.policies.controller_state import ControllerState, Phase
from drake_grasp.policies.ctr import CTRController
from drake_grasp.policies.detector_controllers import GeometricController, GPDController
from drake_grasp.policies.gpd_track import GPDTrackController


class InitController(GraspController):
    """init: no motion, no grasp (the paper's INIT, for the distance experiment)."""

    policy = "init"

    def _begin(self, context, base: ControllerState, t: float) -> ControllerState:
        return replace(base, phase=Phase.DONE, outcome={
            "failure_reason": "init: no grasp attempted", "iterations": 0})


CONTROLLERS: dict[str, type] = {cls.policy: cls for cls in (
    CTRController, CNNOnlyController, CNNCTRController, GPDController, GPDTrackController,
    GeometricController, InitController)}


def make_controller(policy: str, *, scenario: Scenario, X_WG_start: RigidTransform,
                    X_GC: RigidTransform, target_label: int | None = None, score_fn=None,
                    score_needs_height: bool = False, detect_fn=None,
                    X_GC_gpd: RigidTransform | None = None) -> GraspController:
    """The controller of a built-in policy (`CONTROLLERS[policy]`).

    Args:
        policy: a key of `CONTROLLERS`.
        scenario, X_WG_start, X_GC, target_label: as `GraspController`.
        score_fn, score_needs_height: the CNN's scoring (cnn-only, cnn-ctr).
        detect_fn: the detector (gpd, gpd-track, gpd-geometric).
        X_GC_gpd: the GPD sensor in the grasp frame (gpd, gpd-track).

    Raises:
        ValueError: an unknown policy.
    """
    cls = CONTROLLERS.get(policy)
    if cls is None:
        raise ValueError(f"policy: expected one of {sorted(CONTROLLERS)} for the built-in "
                         f"controller, got {policy!r}")
    offered = {"score_fn": score_fn, "score_needs_height": score_needs_height,
               "detect_fn": detect_fn, "X_GC_gpd": X_GC_gpd}
    return cls(scenario=scenario, X_WG_start=X_WG_start, X_GC=X_GC, target_label=target_label,
               **{name: offered[name] for name in cls.EXTRAS})
