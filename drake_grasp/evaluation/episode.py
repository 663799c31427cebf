"""One grasp episode: build the diagram (`episode_diagram`), simulate, judge ->
EpisodeResult, files on disk."""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from drake_grasp import __version__
from drake_grasp.objects import load_library
from drake_grasp.policies.decisions import GPD_POLICIES, TRACK_RECORD_KEYS
from drake_grasp.policies.plugins import is_policy_spec
from drake_grasp.evaluation.records import classify_failure
from drake_grasp.config.scenario import Scenario, dump_scenario
from drake_grasp.world.scene import SceneSpec, scenario_scene
from drake_grasp.evaluation.episode_diagram import EpisodeDiagram, build_episode_diagram

logger = logging.getLogger(__name__)

# What `run_episode` writes; a folder holding only these (or nothing) may be replaced.
EPISODE_FILES = ("episode.json", "scenario.yaml", "scene.json", "depth.png",
                 "controller_steps.png", "replay.html")


@dataclass
class EpisodeResult:
    """What one episode did. Written as `episode.json`."""

    success: bool
    failure_reason: str | None
    policy: str
    scenario: str
    seed: int
    sim_time_s: float
    wall_time_s: float
    object_ids: list[str]
    target_object_id: str | None
    final_X_WG: dict
    object_lowest_point_m: float | None = None
    # The paper's metric at the moment the fingers start closing [m].
    final_distance_m: float | None = None
    control_steps: int = 0
    disturbance: dict = field(default_factory=dict)
    noise: str = "none"
    code_version: str = __version__
    details: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)


@dataclass
class EpisodeRun:
    """An EpisodeResult plus what was recorded on the way (not written to JSON)."""

    result: EpisodeResult
    depth_frames: list = field(default_factory=list)  # (time, mode, HxW array)
    steps: list = field(default_factory=list)  # controller StepRecords
    final_plant_state: np.ndarray | None = None
    replay_html: str | None = None
    scene: SceneSpec | None = None
    # The objects where they are at the end (not settled).
    final_scene: SceneSpec | None = None


def _pose_dict(X) -> dict:
    q = X.rotation().ToQuaternion()
    return {"xyz": [float(v) for v in X.translation()],
            "quat_wxyz": [float(q.w()), float(q.x()), float(q.y()), float(q.z())],
            "rpy": [float(v) for v in X.rotation().ToRollPitchYaw().vector()]}


def _hand_xy_yaw(X_WG) -> np.ndarray:
    """[x, y, yaw_deg] of a grasp-frame pose (`grasps.planar_grasp_xy_yaw`)."""
    from drake_grasp.geometry.grasp_metric import planar_grasp_xy_yaw

    return planar_grasp_xy_yaw(X_WG.GetAsMatrix4())


def _scene_now(plant, plant_context, station, scene: SceneSpec) -> SceneSpec:
    """The scene with every object where it is now."""
    from drake_grasp.world.scene import ObjectPlacement

    placements = []
    for i, o in enumerate(scene.objects):
        X = plant.EvalBodyPoseInWorld(plant_context, station.object_body(i))
        q = X.rotation().ToQuaternion()
        placements.append(ObjectPlacement(o.object_id, [float(v) for v in X.translation()],
                                          [float(q.w()), float(q.x()), float(q.y()), float(q.z())]))
    return SceneSpec(kind=scene.kind, seed=scene.seed, center_xy_m=list(scene.center_xy_m),
                     objects=placements, settled=False)


def final_distance(plant, plant_context, station, scene: SceneSpec, library, seed: int, *,
                   num_samples: int = 400) -> dict:
    """The paper's metric for the hand's current pose: its (x, y, theta) distance to the
    nearest ground-truth grasp of the scene as it is now (objects where they are), the
    ground truth searched from `num_samples` surface points (`judge.distance_grasp_samples`;
    400 as in the dataset's labels)."""
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.geometry.grasps import find_grasps

    now = _scene_now(plant, plant_context, station, scene)
    grasps = find_grasps(now, library, np.random.default_rng([seed, 61]),
                         num_samples=int(num_samples))
    X_WG = plant.CalcRelativeTransform(plant_context, plant.world_frame(),
                                       plant.GetFrameByName("grasp_frame", station.gripper))
    hand = _hand_xy_yaw(X_WG)
    d = float(distance_to_nearest_grasp(hand[None], grasps.xy_theta)[0])
    return {"final_distance_m": d if np.isfinite(d) else None, "hand_xy_yaw": hand.tolist(),
            "num_true_grasps": int(len(grasps.xy_theta))}


def detection_check(now: SceneSpec, library, seed: int, X_WG) -> dict:
    """The judge's look at a one-shot detection (gpd), taken as it is decided (`now`: the
    scene then): whether the selected grasp pose X_WG passes the ground truth of GPD's
    training labels (`gpd_training.ground_truth_passes`: collision, closing region, force
    closure and the torque limit) on 2 independent surface samplings, and the one object
    both its pads touch (None: none, or two different objects). Evaluation only: the
    policy never sees it."""
    from drake_grasp.learning.gpd_training import GpdDataConfig, ground_truth_passes

    X = np.asarray(X_WG, dtype=float).reshape(1, 4, 4)
    passes, obj = ground_truth_passes(now, library, X, np.random.default_rng([seed, 62]),
                                      GpdDataConfig(), samplings=2)
    object_id = now.objects[int(obj[0])].object_id if obj[0] >= 0 else None
    return {"X_WG": [float(v) for v in X.reshape(16)],
            "ground_truth_passes": int(passes[0]), "samplings": 2,
            "object_id": object_id,
            "object_category": library.get(object_id).category if object_id else None,
            "tilt_deg": float(np.degrees(np.arccos(np.clip(-X[0, 2, 2], -1.0, 1.0))))}


def simulate_episode(scenario: Scenario, *, scenario_name: str = "", library=None,
                     scene: SceneSpec | None = None, record_depth: bool = True,
                     visualize: bool | None = None, model=None, detect_fn=None) -> EpisodeRun:
    """Samples and settles the scene, builds the diagram and runs the episode to its end.

    `detect_fn`: see `build_episode_diagram`."""
    wall_start = time.perf_counter()
    if is_policy_spec(scenario.policy):
        from drake_grasp.policies.plugins import load_policy_factory

        load_policy_factory(scenario.policy)  # a bad spec fails before the scene is settled
    library = library if library is not None else load_library(scenario.objects_dir or None)
    if scene is None:
        scene = scenario_scene(scenario, library)
    visualize = scenario.visualize if visualize is None else visualize
    meshcat = None
    if visualize:
        from pydrake.geometry import StartMeshcat

        meshcat = StartMeshcat()
    threads = None
    # The ONNX backend (controller.weights *.onnx) needs no torch; it runs on 1 thread.
    from drake_grasp.policies.evaluator import needs_torch

    if (scenario.policy in ("ctr", "cnn-only", "cnn-ctr")
            and needs_torch(scenario.controller.weights)):
        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(max(1, scenario.controller.torch_threads))
    try:
        ed = build_episode_diagram(scenario, scene, library, meshcat=meshcat, model=model,
                                   detect_fn=detect_fn)
        return _run(ed, scenario, scenario_name, scene, library, meshcat, record_depth,
                    wall_start)
    finally:
        if threads is not None:
            import torch

            torch.set_num_threads(threads)


def _replay_html(ed: EpisodeDiagram, meshcat) -> str | None:
    """The Meshcat recording as a standalone page (None without a visualizer)."""
    if ed.visualizer is None:
        return None
    ed.visualizer.StopRecording()
    ed.visualizer.PublishRecording()
    return meshcat.StaticHtml()


def _failure_reason(verdict, outcome: dict):
    """The judge's reason, or the policy's own where it attempted no grasp."""
    failure_reason = verdict.reason
    if not verdict.attempted and verdict.decided and outcome.get("failure_reason"):
        failure_reason = outcome["failure_reason"]  # e.g. "init: no grasp attempted"
    return failure_reason


def _disturbance_record(ed: EpisodeDiagram, scenario, root) -> dict:
    """What the sheet's disturbance did (its kind; a shift's size and time)."""
    disturbance = {"kind": "none"}
    if ed.disturbance is not None and scenario.disturbance.kind != "none":
        dctx = ed.disturbance.GetMyContextFromRoot(root)
        disturbance = {"kind": scenario.disturbance.kind}
        if scenario.disturbance.kind == "shift":
            trigger = ed.disturbance.trigger_time(dctx)
            disturbance.update({
                "shift_xy_m": ed.disturbance.shift[:2].tolist(),
                "shift_yaw_deg": float(np.rad2deg(ed.disturbance.shift[2])),
                "time_s": None if np.isnan(trigger) else trigger})
        else:
            disturbance["velocity_m_s"] = list(scenario.disturbance.velocity_m_s)
    return disturbance


def _run(ed: EpisodeDiagram, scenario, scenario_name, scene, library, meshcat, record_depth,
         wall_start) -> EpisodeRun:
    from pydrake.systems.analysis import Simulator

    station, policy = ed.station, ed.policy
    simulator = Simulator(ed.diagram)
    root = simulator.get_mutable_context()
    station.set_initial_state(station.diagram.GetMyMutableContextFromRoot(root))
    if ed.visualizer is not None:
        ed.visualizer.StartRecording()
    simulator.Initialize()
    station_context = station.diagram.GetMyContextFromRoot(root)
    policy_context = policy.GetMyContextFromRoot(root)
    plant = station.plant
    plant_context = plant.GetMyContextFromRoot(root)
    depth_port = station.diagram.GetOutputPort("depth_image")
    frames, steps, distance = [], [], None
    closed = False  # whether the policy closed the gripper
    detection = None  # gpd: the judge's check of its detection (`detection_check`)
    dt = 1.0 / scenario.camera.fps
    t = 0.0
    loop_start = time.perf_counter()
    while True:
        mode = policy.mode_name(policy_context)
        if record_depth:
            img = depth_port.Eval(station_context)
            frames.append((t, mode, np.array(img.data[:, :, 0], copy=True)))
        if hasattr(policy, "get_controller_state"):
            last = policy.get_controller_state(policy_context).last_step
            if last is not None and (not steps or steps[-1].iteration != last.iteration):
                steps.append(last)
        # The paper's metric is taken where the hand stands when the fingers start to
        # close (INIT: where it started).
        closed = closed or mode == "close"
        if distance is None and (mode == "close" or (mode == "done" and scenario.policy == "init")):
            distance = final_distance(plant, plant_context, station, scene, library, scenario.seed,
                                      num_samples=scenario.judge.distance_grasp_samples)
        if detection is None and scenario.policy in GPD_POLICIES:
            X_det = policy.get_controller_state(policy_context).outcome.get("gpd_detection")
            if X_det is not None:
                detection = detection_check(_scene_now(plant, plant_context, station, scene),
                                            library, scenario.seed, X_det)
        if policy.is_done(policy_context) or t >= scenario.max_sim_time_s:
            break
        t = min(t + dt, scenario.max_sim_time_s)
        simulator.AdvanceTo(t)
    loop_wall_s = time.perf_counter() - loop_start
    if distance is None:
        distance = final_distance(plant, plant_context, station, scene, library, scenario.seed,
                                  num_samples=scenario.judge.distance_grasp_samples)
    replay = _replay_html(ed, meshcat)
    # The policy's own data (iterations, stop reason; why it gave up, if it did) and the
    # judge's verdict (success, failure class and reason, what was lifted).
    outcome = policy.outcome(policy_context)
    verdict = ed.judge.GetOutputPort("judgement").Eval(ed.judge.GetMyContextFromRoot(root))
    failure_reason = _failure_reason(verdict, outcome)
    X_WG = plant.CalcRelativeTransform(plant_context, plant.world_frame(),
                                       plant.GetFrameByName("grasp_frame", station.gripper))
    disturbance = _disturbance_record(ed, scenario, root)
    result = EpisodeResult(
        success=bool(verdict.success),
        failure_reason=failure_reason,
        policy=scenario.policy,
        scenario=scenario_name,
        seed=int(scenario.seed),
        sim_time_s=float(root.get_time()),
        wall_time_s=time.perf_counter() - wall_start,
        object_ids=scene.object_ids(),
        target_object_id=None if ed.target is None else scene.objects[ed.target].object_id,
        final_X_WG=_pose_dict(X_WG),
        object_lowest_point_m=verdict.object_lowest_point_m,
        final_distance_m=distance["final_distance_m"],
        control_steps=int(outcome.get("iterations", len(steps)) or 0),
        disturbance=disturbance,
        noise=scenario.noise.kind,
        details={"failure_class": classify_failure(verdict.success, failure_reason),
                 "held_after_close": verdict.held_after_close,
                 "grasped_object_id": verdict.grasped_object_id,
                 "stop_reason": outcome.get("stop_reason"),
                 "final_mode": policy.mode_name(policy_context),
                 "hand_at_close_xy_yaw": distance["hand_xy_yaw"],
                 "gripper_closed": closed,
                 "num_true_grasps": distance["num_true_grasps"],
                 "simulation_wall_time_s": loop_wall_s,
                 "num_depth_frames": len(frames),
                 "decision_time_s": (ed.decision_timer.seconds
                                     if ed.decision_timer is not None else None),
                 "decisions": ed.decision_timer.calls if ed.decision_timer is not None else 0,
                 **({"policy_inputs": ed.user_policy_inputs}
                    if ed.user_policy_inputs is not None else {}),
                 **({"gpd_detection": detection} if detection is not None else {}),
                 **{key: outcome[key] for key in TRACK_RECORD_KEYS if key in outcome},
                 **({"camera_mount_error": _pose_dict(station.X_CC_actual)}
                    if scenario.calibration.active() else {}),
                 "judge": verdict.details},
    )
    return EpisodeRun(result=result, depth_frames=frames, steps=steps,
                      final_plant_state=np.array(plant.GetPositionsAndVelocities(plant_context)),
                      replay_html=replay, scene=scene,
                      final_scene=_scene_now(plant, plant_context, station, scene))


def run_episode(scenario: Scenario, *, out_dir: str | Path, scenario_name: str = "",
                library=None, replay: bool = True, scene: SceneSpec | None = None,
                detect_fn=None) -> EpisodeResult:
    """Runs one episode and writes `episode.json`, `scenario.yaml`, `scene.json`,
    `depth.png`, `controller_steps.png` (closed-loop policies) and (with `replay`)
    `replay.html` into `out_dir`.

    `detect_fn` replaces the gpd / gpd-geometric detector (see `build_episode_diagram`).

    Files are written to a staging folder beside `out_dir`; only when the episode has
    finished does the staging folder take the place of `out_dir`. A failure leaves
    `out_dir` as it was, and a folder that held an earlier episode holds exactly the new
    one afterwards (no file of the earlier episode stays behind); the replacement is
    logged on the "drake_grasp.evaluation.episode" logger, naming the files that went away.

    Raises:
        ValueError: `out_dir` exists and holds anything other than an episode's files
            (it is never emptied then); checked before the episode runs.
    """
    out_dir = Path(out_dir)
    earlier = _episode_folder_contents(out_dir)
    staging = out_dir.parent / f".{out_dir.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    try:
        run = simulate_episode(scenario, scenario_name=scenario_name, library=library,
                               visualize=replay, scene=scene, detect_fn=detect_fn)
        (staging / "scenario.yaml").write_text(dump_scenario(scenario))
        run.scene.save(staging / "scene.json")
        verdict = "success" if run.result.success else "failure"
        from drake_grasp.evaluation.pictures import save_controller_steps, save_depth_contact_sheet

        save_depth_contact_sheet(run.depth_frames, staging / "depth.png",
                                 title=f"{scenario_name} {scenario.policy} seed {scenario.seed}: {verdict}")
        if run.steps:
            from drake_grasp.world.station import gripper_frame_offsets

            save_controller_steps(
                run.steps, staging / "controller_steps.png", fov_y_deg=scenario.camera.fov_y_deg,
                X_GC_xyz=gripper_frame_offsets()[2].translation(),
                title=f"{scenario_name} {scenario.policy} seed {scenario.seed}: {verdict}; "
                      "red = gripper now, green = best candidate")
        if run.replay_html is not None:
            (staging / "replay.html").write_text(run.replay_html)
        (staging / "episode.json").write_text(run.result.to_json())
        _swap_in(staging, out_dir, earlier)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return run.result


def _episode_folder_contents(out_dir: Path) -> list[str] | None:
    """Names in `out_dir` when it is an earlier episode's folder; None when it does not
    exist. Refuses a folder holding anything else, so a mistyped --out never empties a
    folder of the user's."""
    if not out_dir.exists():
        return None
    if not out_dir.is_dir():
        raise ValueError(f"--out {out_dir}: exists and is not a folder")
    names = sorted(p.name for p in out_dir.iterdir())
    foreign = [n for n in names if n not in EPISODE_FILES]
    if foreign:
        raise ValueError(f"--out {out_dir}: holds files that are not an episode's "
                         f"({', '.join(foreign[:5])}{', ...' if len(foreign) > 5 else ''}); "
                         f"expected a new folder, an empty one, or an earlier episode's "
                         f"(only {', '.join(EPISODE_FILES)})")
    return names


def _swap_in(staging: Path, out_dir: Path, earlier: list[str] | None) -> None:
    """Puts the complete `staging` folder where `out_dir` is: two renames, so a reader
    sees the old episode or the new one, and the old one is deleted only afterwards."""
    if earlier is None or not out_dir.exists():
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        os.replace(staging, out_dir)
        return
    # The folder may have changed since it was checked (another run): check again.
    earlier = _episode_folder_contents(out_dir)
    old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}"
    if old.exists():
        shutil.rmtree(old)
    os.replace(out_dir, old)
    os.replace(staging, out_dir)
    shutil.rmtree(old, ignore_errors=True)
    new = {p.name for p in out_dir.iterdir()}
    gone = [n for n in earlier or [] if n not in new]
    logger.info("%s: replaced the earlier episode in this folder%s", out_dir,
                f" (removed {', '.join(gone)}, which this episode does not write)" if gone else "")
