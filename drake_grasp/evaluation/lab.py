"""A grasp physics lab: does this grasp pose hold one object when a 2F-85 executes it?

A small, fast Diagram (no arm, no camera): the station's Robotiq 2F-85 model with its
compliant hydroelastic pads and the same force-controlled `GripperController`, mounted on a
floating base, grasping ONE object that rests on the station's table and sheet
(`table.add_table_and_sheet`, `scene.add_scene_objects`; the object is settled first).

Base actuation: the gripper base rides on six joints (prismatic x, y, z in the world,
then revolute z, y, x - the roll-pitch-yaw order, so R_WB = RollPitchYaw(r, p, y)),
on six 10 g bodies (the last welded to the gripper base, so all six
actuators belong to one `lab_base` model instance), with PD gains inside the plant and a desired-state input fed
by a `TrajectorySource` (plus a constant gravity feed-forward on the z joint). SAP
treats in-plant PD implicitly, so stiff gains stay stable at the station's 2 ms step
with no Python system on the step path; a free body pushed by a spatial PD force would
be explicit in the force (stiffness limited by the step) and need a Python force
system evaluated every step. Grasps near pitch = +-90 deg (gimbal lock) are outside
the lab's reach; top-down and moderately tilted grasps are far from it.

Sequence (times in `LabConfig`): start `approach_m` back along the approach axis z_G,
descend to the grasp pose, close with the scenario's grip force, lift `lift_m` straight
up, hold, then shake (`LabConfig.shake_axes`): for each world axis a one-cycle sine
displacement of amplitude `shake_translation_m` (2 cm) over `shake_translation_period_s`
(0.25 s; peak acceleration A (2 pi / T)^2 = 12.6 m/s^2, about 1.3 g), then a one-cycle
sine rotation of `shake_rotation_rad` (0.25 rad) over `shake_rotation_period_s` (0.4 s;
62 rad/s^2 peak) of the yaw and then the pitch joint (and the roll joint if listed, as
in every check before 2026-12-07) - short accelerations along and about each axis in
the spirit of published grasp-verification shake tests.

The Diagram is built once per scene and reused by its checks (`lab_diagram.GraspLab`,
`check_grasps`, `scene_labs`), each check in a fresh Context.

Judge (contact-based, at the end of each phase and of each shake segment, the check
ending at the first failure): the object must touch both pads
(the plant's contact results) and, after the lift, have risen at least
`scenario.judge.min_lift_m` above its resting height. Failure classes: `missed` (not
touching both pads after closing), `slipped-during-lift`, `slipped-during-hold`,
`dropped-by-shake`, `simulation-error` (the simulator threw).
"""

from __future__ import annotations

import time

import numpy as np

from drake_grasp.config.scenario import Scenario
from drake_grasp.evaluation.lab_diagram import (
    FAILURES,
    GRIPPER_URI,
    SHAKE_AXES,
    GraspCheckResult,
    GraspLab,
    LabConfig,
)
from drake_grasp.objects import ObjectLibrary
from drake_grasp.world.scene import ObjectPlacement, SceneSpec, settle_scene


def isolated_scene(object_id: str, library: ObjectLibrary, *, lying: bool = True,
                   yaw: float = 0.0, rotation=None, center_xy_m=(0.5, 0.0)) -> SceneSpec:
    """One object dropped at the centre of the sheet and settled.

    Args:
        lying: tip the object's z axis (e.g. a can's axis) over onto the table.
        yaw: rotation about the world z axis [rad].
        rotation: a 3x3 R_WO to drop the object with (overrides `lying` and `yaw`).
    """
    from pydrake.math import RollPitchYaw, RotationMatrix

    R = (RotationMatrix(np.asarray(rotation, dtype=float)) if rotation is not None
         else RollPitchYaw(np.pi / 2 if lying else 0.0, 0.0, yaw).ToRotationMatrix())
    from drake_grasp.objects import visual_mesh

    V = np.asarray(visual_mesh(library.get(object_id)).vertices, dtype=float) @ R.matrix().T
    center = 0.5 * (V.min(axis=0) + V.max(axis=0))
    xyz = [float(center_xy_m[0] - center[0]), float(center_xy_m[1] - center[1]),
           float(0.005 - V[:, 2].min())]
    q = R.ToQuaternion()
    spec = SceneSpec(kind="isolated", seed=0, center_xy_m=list(center_xy_m), objects=[
        ObjectPlacement(object_id, xyz, [float(q.w()), float(q.x()), float(q.y()), float(q.z())])])
    return settle_scene(spec, library)


def check_grasp(object_id: str | None, X_WG, *, scene: SceneSpec | None = None,
                scenario: Scenario | None = None, library: ObjectLibrary,
                lab: LabConfig | None = None, grip_force_n: float | None = None,
                object_index: int = 0, neighbours: bool = False) -> GraspCheckResult:
    """Executes the grasp X_WG (grasp frame: z_G approach, x_G closing) on one object, in
    a Diagram built for this check alone (`GraspLab`; `check_grasps` builds one per scene).

    Args:
        object_id: the object (on `isolated_scene(object_id)` when `scene` is None).
        X_WG: the grasp pose, a RigidTransform or a 4x4 matrix (as in `GraspSet.poses`).
        scene: a settled scene; `scene.objects[object_index]` is the object to grasp.
        scenario: plant config, grip force, closing speed, open width, judge thresholds.
        grip_force_n: overrides `scenario.gripper.grip_force_n`.
        neighbours: load every object of `scene` (as settled) instead of the one to
            grasp alone; the judge still looks at `scene.objects[object_index]`.
    """
    if scene is None:
        if object_id is None:
            raise ValueError("check_grasp: give object_id or scene")
        scene = isolated_scene(object_id, library)
        object_index = 0
    if not 0 <= int(object_index) < len(scene.objects):
        raise ValueError(f"object_index: got {object_index}, the scene has "
                         f"{len(scene.objects)} objects")
    labs = scene_labs(scene, scenario=scenario, library=library, lab=lab, neighbours=neighbours)
    return labs(object_index).check(X_WG, object_index=object_index, grip_force_n=grip_force_n)


def scene_labs(scene: SceneSpec, *, scenario: Scenario | None = None, library: ObjectLibrary,
               lab: LabConfig | None = None, neighbours: bool = False):
    """A function object_index -> the `GraspLab` that grasps that object of `scene`: one
    Diagram for the whole scene with `neighbours` (every object loaded), else one per
    object grasped (it alone loaded); each built on first use and then reused."""
    built: dict[int | None, GraspLab] = {}

    def lab_for(object_index: int) -> GraspLab:
        key = None if neighbours else int(object_index)
        if key not in built:
            built[key] = GraspLab(scene, scenario=scenario, library=library, lab=lab,
                                  loaded=None if neighbours else [key])
        return built[key]

    return lab_for


def check_grasps(object_id: str | None, poses, *, scene: SceneSpec | None = None,
                 scenario: Scenario | None = None, library: ObjectLibrary,
                 lab: LabConfig | None = None, object_indices=None, neighbours: bool = False,
                 reuse: bool = True, progress=None) -> list[GraspCheckResult]:
    """`check_grasp` for each pose (e.g. `GraspSet.poses`); the scene is settled once and
    its lab Diagram built once (`scene_labs`), each check in a fresh Context.

    Args:
        object_indices: the object of each pose in `scene` (e.g. `GraspSet.object_index`).
        neighbours: as in `check_grasp`.
        reuse: False builds a Diagram for every check (as before 2026-12-07; the same
            verdicts and trajectories, only slower - kept for measuring).
        progress: called with each result (e.g. a tqdm bar's update).
    """
    if scene is None:
        scene = isolated_scene(object_id, library)
    labs = scene_labs(scene, scenario=scenario, library=library, lab=lab, neighbours=neighbours)
    results = []
    for i, X in enumerate(poses):
        index = 0 if object_indices is None else int(object_indices[i])
        if reuse:
            results.append(labs(index).check(X, object_index=index))
        else:
            results.append(check_grasp(None, X, scene=scene, scenario=scenario, library=library,
                                       lab=lab, object_index=index, neighbours=neighbours))
        if progress is not None:
            progress(results[-1])
    return results


def run_grasp_checks(*, object_ids: list[str], num_grasps: int, seed: int, out,
                     scenario: Scenario | None = None, library: ObjectLibrary,
                     lab: LabConfig | None = None, show_progress: bool = True) -> dict:
    """Checks `num_grasps` sampled ground-truth grasps (`grasps.find_grasps`) per object.

    Each object is dropped with a random rotation (from `seed`) onto an empty sheet and
    settled; its grasps are drawn without replacement from the ground-truth set. Writes
    `out/summary.json` (checked, held, hold_rate, failures, per object with each grasp's
    result) through a temporary name, and returns the summary.
    """
    import json
    import os
    from pathlib import Path

    from tqdm import tqdm

    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.world.scene import _random_rotation

    if num_grasps < 1:
        raise ValueError(f"num_grasps: expected >= 1, got {num_grasps}")
    for object_id in object_ids:
        library.get(object_id)  # an unknown id fails before any work
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    per_object = {}
    bar = tqdm(total=num_grasps * len(object_ids), desc="grasp-check", unit="grasp",
               disable=not show_progress)
    t0 = time.perf_counter()
    for object_id in object_ids:
        scene = isolated_scene(object_id, library, rotation=_random_rotation(rng))
        grasps = find_grasps(scene, library, rng)
        chosen = (rng.choice(len(grasps), size=min(num_grasps, len(grasps)), replace=False)
                  if len(grasps) else np.zeros(0, dtype=int))
        results = check_grasps(None, grasps.poses[chosen], scene=scene, scenario=scenario,
                               library=library, lab=lab, object_indices=grasps.object_index[chosen],
                               progress=lambda _: bar.update(1))
        bar.update(num_grasps - len(chosen))
        held = sum(r.held for r in results)
        per_object[object_id] = {
            "ground_truth_grasps": len(grasps), "checked": len(results), "held": held,
            "hold_rate": held / len(results) if results else None,
            "grasps": [{"held": r.held, "failure": r.failure, "width_m": float(grasps.widths[i]),
                        **r.details} for i, r in zip(chosen, results)],
        }
    bar.close()
    checked = sum(o["checked"] for o in per_object.values())
    held = sum(o["held"] for o in per_object.values())
    failures = {name: sum(g["failure"] == name for o in per_object.values() for g in o["grasps"])
                for name in FAILURES}
    summary = {"seed": int(seed), "grasps_per_object": int(num_grasps), "checked": checked,
               "held": held, "hold_rate": held / checked if checked else None,
               "failures": failures, "wall_s": round(time.perf_counter() - t0, 3),
               "objects": per_object}
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=1))
    os.replace(tmp, out / "summary.json")
    return summary


__all__ = ["FAILURES", "GRIPPER_URI", "SHAKE_AXES", "GraspCheckResult", "GraspLab", "LabConfig",
           "check_grasp", "check_grasps", "isolated_scene", "run_grasp_checks", "scene_labs"]
