"""One grasp episode: build the diagram, simulate, judge -> EpisodeResult, files on disk."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from drake_grasp import __version__
from drake_grasp.objects import ObjectLibrary, load_library, visual_mesh
from drake_grasp.policies.plugins import is_policy_spec
from drake_grasp.evaluation.records import classify_failure
from drake_grasp.config.scenario import Scenario, dump_scenario
from drake_grasp.world.scene import SceneSpec, scenario_scene

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


def _object_surface_points(library: ObjectLibrary, object_id: str, count: int = 1500) -> np.ndarray:
    import trimesh

    mesh = visual_mesh(library.get(object_id), process=True)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    return np.vstack([np.asarray(points), np.asarray(mesh.vertices)])


def plan_scripted_grasp(scene: SceneSpec, library: ObjectLibrary,
                        seed: int) -> tuple[int, np.ndarray, np.ndarray | None]:
    """The scripted grasp, planned from the objects' true poses: among the scene's
    ground-truth grasps (`grasps.find_grasps`, whose physical tests were calibrated in
    the grasp lab) of the object nearest the workspace centre that has any, the one whose
    centre is nearest that object's centre of mass (horizontally). Returns (object index,
    its surface points in the object frame, X_WG as a 4x4), with X_WG None when no object
    has a ground-truth grasp (the supervisor then plans with `plan_topdown_grasp`)."""
    from drake_grasp.geometry.grasps import ObjectMasses, find_grasps

    grasps = find_grasps(scene, library, np.random.default_rng([int(seed), 67]))
    center = np.asarray(scene.center_xy_m, dtype=float)
    order = np.argsort([np.linalg.norm(np.asarray(o.xyz[:2]) - center) for o in scene.objects])
    masses = ObjectMasses.of_scene(scene, library)
    for i in (int(k) for k in order):
        mine = np.flatnonzero(grasps.object_index == i)
        if len(mine) == 0:
            continue
        off = np.linalg.norm(grasps.poses[mine, :2, 3] - masses.com_W[i, :2], axis=1)
        best = int(mine[np.argmin(off)])
        return i, _object_surface_points(library, scene.objects[i].object_id), grasps.poses[best]
    i, P_O = choose_scripted_target(scene, library)
    return i, P_O, None


def choose_scripted_target(scene: SceneSpec, library: ObjectLibrary) -> tuple[int, np.ndarray]:
    """The object the scripted grasp goes for: the one nearest the workspace centre that
    a top-down grasp fits (else simply the nearest). Returns (index, surface points in
    the object frame)."""
    from drake_grasp.geometry.grasps import plan_topdown_grasp

    center = np.asarray(scene.center_xy_m, dtype=float)
    order = np.argsort([np.linalg.norm(np.asarray(o.xyz[:2]) - center) for o in scene.objects])
    candidates = []
    for i in order:
        placement = scene.objects[int(i)]
        P_O = _object_surface_points(library, placement.object_id)
        X = placement.pose()
        try:
            plan_topdown_grasp(P_O @ X.rotation().matrix().T + X.translation())
        except ValueError:
            candidates.append((int(i), P_O))
            continue
        return int(i), P_O
    return candidates[0]


def _pose_dict(X) -> dict:
    q = X.rotation().ToQuaternion()
    return {"xyz": [float(v) for v in X.translation()],
            "quat_wxyz": [float(q.w()), float(q.x()), float(q.y()), float(q.z())],
            "rpy": [float(v) for v in X.rotation().ToRollPitchYaw().vector()]}


@dataclass
class EpisodeDiagram:
    """The episode Diagram and handles into it."""

    diagram: object
    station: object
    # What the runner asks for the phase (`is_done`, `mode_name`, `outcome`): the
    # ScriptedGraspSupervisor, the GraspController, or for a user policy the harness's
    # GraspMotionMonitor watching it.
    policy: object
    target: int | None  # scene index of the scripted/target object
    judge: object = None  # GraspJudge
    visualizer: object = None
    disturbance: object = None
    sampler: object = None
    decision_timer: object = None  # DecisionTimer of the policy's computations
    user_policy: object = None  # a user policy's system (`drake_grasp.policies.plugins`), else None
    # The input ports a user policy declared (what it sees); None for built-in policies.
    user_policy_inputs: list | None = None


class DecisionTimer:
    """Wall time of a policy's decisions: wraps the functions its systems call (the CNN's
    scoring, a detector), outside any system's state, so that it never changes what is
    simulated. ``seconds`` over ``calls``: one CTR control step's scoring, or one
    detection (cloud, candidates, images, classifier and selection for gpd). Rendering
    is not included."""

    def __init__(self):
        self.seconds = 0.0
        self.calls = 0

    def wrap(self, fn):
        if fn is None:
            return None

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - t0
                self.calls += 1

        return timed


def _geometric_detector(scenario: Scenario):
    """gpd-geometric: detect(depth, X_WC) -> (x, y, theta_deg, z) of the best grasp of the
    hand-tuned geometric score on the wrist image, or None."""
    from drake_grasp.policies import gpd_geometric as gpd

    def detect(depth, X_WC):
        rng = np.random.default_rng([scenario.seed, 53])
        best = gpd.best_grasp(depth, fov_y_deg=scenario.camera.fov_y_deg, X_WC=X_WC, rng=rng)
        if best is None:
            return None
        return (float(best.xy_theta[0]), float(best.xy_theta[1]), float(best.xy_theta[2]),
                float(best.z))

    return detect


def _detector(scenario: Scenario, detect_fn):
    """The controller's detect_fn: the injected one, else gpd's learned detector
    (`drake_grasp.policies.gpd.make_detector`) or gpd-geometric's; None for other policies."""
    if detect_fn is not None or scenario.policy not in ("gpd", "gpd-geometric"):
        return detect_fn
    if scenario.policy == "gpd-geometric":
        return _geometric_detector(scenario)
    from drake_grasp.policies import gpd

    return gpd.make_detector(scenario)


def build_episode_diagram(scenario: Scenario, scene: SceneSpec, library: ObjectLibrary,
                          *, meshcat=None, model=None, detect_fn=None) -> EpisodeDiagram:
    """Station + policy + sheet command + grasp judge (+ Meshcat), as one Diagram.

    `scripted` uses the ScriptedGraspSupervisor (which plans from the object's true pose:
    it alone of the policies reads `body_poses`); every other policy the GraspController,
    with the ActionSampler and the DistanceEvaluator (CNN) where it needs them and the
    SheetDisturbance moving the sheet. The GraspJudge watches the station's contact
    results and body poses and reads the policy's `control_status`.

    A user policy (`policy: MODULE:FACTORY`, `drake_grasp.policies.plugins`) is built by its
    factory, named "user_policy", connected by port name to the sensors it declares, and
    watched by the harness's GraspMotionMonitor ("motion_monitor"), which gives the judge
    the motion phase.

    `detect_fn` replaces the gpd / gpd-geometric policy's detector (same signature as
    the controller's `detect_fn`), e.g. a stand-in in tests.
    """
    from pydrake.math import RigidTransform
    from pydrake.systems.framework import DiagramBuilder

    from drake_grasp.world.station import MakeGraspStation

    if not scene.objects:
        raise ValueError("scene has no objects on the table (all fell off while settling?)")
    station = MakeGraspStation(scenario, scene, library)
    builder = DiagramBuilder()
    builder.AddNamedSystem("station", station.diagram)
    sd = station.diagram
    out = EpisodeDiagram(diagram=None, station=station, policy=None, target=None)
    if scenario.policy == "scripted":
        from drake_grasp.systems.supervisor import ScriptedGraspSupervisor

        target, points_O, X_WG_plan = plan_scripted_grasp(scene, library, scenario.seed)
        policy = builder.AddNamedSystem("supervisor", ScriptedGraspSupervisor(
            object_body_index=station.object_body(target).index(),
            object_points_O=points_O, X_WG_start=station.X_WG_start,
            motion=scenario.scripted, gripper=scenario.gripper,
            X_WG_planned=None if X_WG_plan is None else RigidTransform(X_WG_plan),
            object_com_O=library.get(scene.objects[target].object_id).read_meta()["com_m"]))
        _hold_sheet(builder, sd)
        builder.Connect(sd.GetOutputPort("body_poses"), policy.GetInputPort("body_poses"))
        out.target = target
    elif is_policy_spec(scenario.policy):
        policy = _add_user_policy(builder, scenario, station, out)
    else:
        out.target, policy = _add_controller(builder, scenario, scene, library, station, model,
                                             out, detect_fn)
    if out.user_policy is None:
        builder.Connect(sd.GetOutputPort("gripper_state"), policy.GetInputPort("gripper_state"))
        builder.Connect(policy.GetOutputPort("X_WG_desired"), sd.GetInputPort("X_WG_desired"))
        builder.Connect(policy.GetOutputPort("gripper_command"),
                        sd.GetInputPort("gripper_command"))
    out.policy = policy
    out.judge = _add_judge(builder, scenario, scene, library, station, policy)
    if meshcat is not None:
        from pydrake.geometry import MeshcatVisualizer, MeshcatVisualizerParams

        params = MeshcatVisualizerParams()
        params.publish_period = 1.0 / 25.0
        out.visualizer = MeshcatVisualizer.AddToBuilder(
            builder, sd.GetOutputPort("query_object"), meshcat, params)
    out.diagram = builder.Build()
    out.diagram.set_name("grasp_episode")
    return out


def _add_judge(builder, scenario, scene, library, station, policy):
    """The GraspJudge, the one system with privileged ports (contacts, body poses)."""
    from drake_grasp.systems.judge import PAD_BODIES, GraspJudge, geometry_bodies

    plant = station.plant
    gripper = {int(i): plant.get_body(i).name() for i in plant.GetBodyIndices(station.gripper)}
    pads = [int(plant.GetBodyByName(name, station.gripper).index()) for name in PAD_BODIES]
    judge = builder.AddNamedSystem("judge", GraspJudge(
        config=scenario.judge,
        object_bodies=[station.object_body(i).index() for i in range(len(scene.objects))],
        object_ids=scene.object_ids(),
        object_points=[_object_surface_points(library, o.object_id, 600) for o in scene.objects],
        gripper_bodies=gripper, pad_bodies=pads, grasp_body=station.gripper_body().index(),
        X_BG=station.X_BG, geometry_bodies=geometry_bodies(plant)))
    sd = station.diagram
    builder.Connect(sd.GetOutputPort("contact_results"), judge.GetInputPort("contact_results"))
    builder.Connect(sd.GetOutputPort("body_poses"), judge.GetInputPort("body_poses"))
    builder.Connect(policy.GetOutputPort("control_status"), judge.GetInputPort("control_status"))
    return judge


def _hold_sheet(builder, station_diagram) -> None:
    """Holds the sheet still with a constant source ("sheet_hold"): a Python system here
    would be evaluated at every plant step."""
    from pydrake.systems.primitives import ConstantVectorSource

    hold = builder.AddNamedSystem("sheet_hold", ConstantVectorSource(np.zeros(6)))
    builder.Connect(hold.get_output_port(), station_diagram.GetInputPort("sheet_desired_state"))


def _drive_sheet(builder, scenario, station_diagram, control_status_port, period_s):
    """The sheet's desired state: held still ("sheet_hold"), or moved by the
    SheetDisturbance ("sheet_disturbance") that reads `control_status_port`. Returns the
    disturbance system or None."""
    from drake_grasp.systems.disturbance import SheetDisturbance

    if scenario.disturbance.kind == "none":
        _hold_sheet(builder, station_diagram)
        return None
    disturbance = builder.AddNamedSystem("sheet_disturbance", SheetDisturbance(
        scenario.disturbance, seed=scenario.seed, period_s=period_s))
    builder.Connect(control_status_port, disturbance.GetInputPort("control_status"))
    builder.Connect(disturbance.GetOutputPort("sheet_desired_state"),
                    station_diagram.GetInputPort("sheet_desired_state"))
    return disturbance


def _sensor(builder, scenario, station_diagram, name: str):
    """The output port a policy reads image `name` from: the station's own, or, when
    `scenario.timing` adds latency or dropped frames, a FrameBuffer ("NAME_frames",
    one per image stream, taking one frame per control period) in front of it."""
    if not scenario.timing.active():
        return station_diagram.GetOutputPort(name)
    buffer_name = f"{name}_frames"
    if builder.HasSubsystemNamed(buffer_name):
        return builder.GetSubsystemByName(buffer_name).GetOutputPort("image")
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    from drake_grasp.systems.frames import FrameBuffer

    t = scenario.timing
    model = ImageLabel16I() if name == "label_image" else ImageDepth32F()
    frames = builder.AddNamedSystem(buffer_name, FrameBuffer(
        model, period_s=scenario.controller.period_s, latency_s=t.latency_s,
        dropped_frame_prob=t.dropped_frame_prob, seed=scenario.seed))
    builder.Connect(station_diagram.GetOutputPort(name), frames.GetInputPort("image"))
    return frames.GetOutputPort("image")


def _add_user_policy(builder, scenario, station, out):
    """A user policy (`drake_grasp.policies.plugins`): its system ("user_policy") connected by port
    name to the sensors it declares, its commands to the station, and the harness's
    GraspMotionMonitor ("motion_monitor") deriving the motion phase from them. Returns the
    monitor (what the runner and the judge read)."""
    from pydrake.common.value import AbstractValue
    from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource

    from drake_grasp.policies.plugins import make_policy_system
    from drake_grasp.systems.monitor import GraspMotionMonitor

    sd = station.diagram
    user = builder.AddNamedSystem("user_policy", make_policy_system(scenario.policy, scenario))
    monitor = builder.AddNamedSystem("motion_monitor", GraspMotionMonitor(scenario=scenario))
    inputs = [user.get_input_port(i).get_name() for i in range(user.num_input_ports())]
    constants = {"X_WG_start": station.X_WG_start, "X_GC": station.X_GC}
    for name in inputs:
        if name in ("depth_image", "gpd_depth_image"):
            builder.Connect(_sensor(builder, scenario, sd, name), user.GetInputPort(name))
        elif name == "gripper_state":
            builder.Connect(sd.GetOutputPort(name), user.GetInputPort(name))
        elif name == "motion_status":
            builder.Connect(monitor.GetOutputPort("motion_status"), user.GetInputPort(name))
        else:  # X_WG_start, X_GC (check_policy_system allows nothing else)
            source = builder.AddNamedSystem(f"user_policy_{name}", ConstantValueSource(
                AbstractValue.Make(constants[name])))
            builder.Connect(source.get_output_port(), user.GetInputPort(name))
    builder.Connect(user.GetOutputPort("X_WG_desired"), sd.GetInputPort("X_WG_desired"))
    builder.Connect(user.GetOutputPort("gripper_command"), sd.GetInputPort("gripper_command"))
    builder.Connect(user.GetOutputPort("gripper_command"), monitor.GetInputPort("gripper_command"))
    builder.Connect(sd.GetOutputPort("gripper_state"), monitor.GetInputPort("gripper_state"))
    if user.HasOutputPort("descending"):
        builder.Connect(user.GetOutputPort("descending"), monitor.GetInputPort("descending"))
    else:  # no announcement: the whole approach is judged as the descent
        always = builder.AddNamedSystem("user_policy_descending", ConstantVectorSource([1.0]))
        builder.Connect(always.get_output_port(), monitor.GetInputPort("descending"))
    out.disturbance = _drive_sheet(builder, scenario, sd, monitor.GetOutputPort("control_status"),
                                   scenario.controller.period_s)
    out.user_policy = user
    out.user_policy_inputs = sorted(inputs)
    return monitor


def target_object(scenario, scene, station) -> tuple[int | None, int | None]:
    """Target mode (`scenario.target`): (the target's scene index, its label in the
    camera's label image); (None, None) without a target.

    Raises:
        ValueError: the target is not in the scene (names the objects that are).
    """
    if not scenario.target:
        return None, None
    ids = scene.object_ids()
    if scenario.target not in ids:
        raise ValueError(f"target: {scenario.target!r} is not in the scene; objects: {ids}")
    target = ids.index(scenario.target)
    # MultibodyPlant labels each body's geometry with its body index.
    return target, int(station.object_body(target).index())


@contextlib.contextmanager
def controller_class(cls):
    """Episodes built inside the block run `cls`, a `GraspController` subclass, as the
    built-in policy's controller (`add_policy_systems` looks the class up each time it
    builds). For diagnostics that replace or log one decision of the controller
    (`analysis/oracle_ctr.py`: the true distances; `analysis/clutter_predicted_distance.py`:
    the predictions logged); not for policies (`Scenario.policy: MODULE:FACTORY` is)."""
    import drake_grasp.policies.controller as module

    original = module.GraspController
    module.GraspController = cls
    try:
        yield cls
    finally:
        module.GraspController = original


def policy_image_ports(builder, scenario, station_diagram) -> dict:
    """The image ports the built-in policy reads, as `add_policy_systems` takes them
    (`depth`, `label`, `gpd_depth`): through the timing's frame buffers (`_sensor`) where
    the policy reads them. Only target mode reads the label image and only gpd the GPD
    sensor (once): a frame buffer, which renders every period, is put in front of them
    only then. Outside target mode `label` is None: the label image, ground truth of which
    pixel shows which object, is then connected to no policy-side system."""
    sd = station_diagram
    return {
        "depth": _sensor(builder, scenario, sd, "depth_image"),
        "label": _sensor(builder, scenario, sd, "label_image") if scenario.target else None,
        "gpd_depth": (_sensor(builder, scenario, sd, "gpd_depth_image")
                      if scenario.policy == "gpd" else sd.GetOutputPort("gpd_depth_image")),
    }


def add_policy_systems(builder, scenario, *, model, X_WG_start, X_GC, X_GC_gpd, target_label,
                       detect_fn, depth, label, gpd_depth):
    """The built-in policy's systems: "controller" (GraspController), "action_sampler" and
    "distance_evaluator" (the CNN; "no_evaluator" for policies without it), connected to
    the image output ports given (`depth`, `label` - None outside target mode -,
    `gpd_depth`). The in-process episode
    and the controller side of `drake_grasp.evaluation.bridge` both build the policy here.

    Returns (controller, its DecisionTimer, the sampler)."""
    from pydrake.common.value import AbstractValue
    from pydrake.systems.primitives import ConstantValueSource

    from drake_grasp.policies.controller import GraspController
    from drake_grasp.policies.evaluator import (ActionSampler, DistanceEvaluator, check_views,
                                               needs_camera_height, score_candidates)

    c = scenario.controller
    needs_cnn = scenario.policy in ("ctr", "cnn-only", "cnn-ctr")
    if needs_cnn:
        check_views(model, c.view_average, mirror=c.mirror_average)
    needs_height = needs_cnn and needs_camera_height(model)
    timer = DecisionTimer()
    score_fn = (timer.wrap(lambda d, actions, **kw: score_candidates(
        model, d, actions, mirror=c.mirror_average, views=c.view_average, **kw))
        if needs_cnn else None)
    controller = builder.AddNamedSystem("controller", GraspController(
        scenario=scenario, policy=scenario.policy, X_WG_start=X_WG_start, X_GC=X_GC,
        X_GC_gpd=X_GC_gpd, score_fn=score_fn, score_needs_height=needs_height,
        detect_fn=timer.wrap(_detector(scenario, detect_fn)), target_label=target_label))
    builder.Connect(depth, controller.GetInputPort("depth_image"))
    if label is not None:  # target mode only: the label image is ground truth
        builder.Connect(label, controller.GetInputPort("label_image"))
    builder.Connect(gpd_depth, controller.GetInputPort("gpd_depth_image"))
    sampler = builder.AddNamedSystem("action_sampler", ActionSampler(
        num_candidates=c.num_candidates, xy_m=c.sample_xy_m, theta_deg=c.sample_theta_deg,
        period_s=c.period_s, seed=scenario.seed))
    builder.Connect(sampler.GetOutputPort("candidate_actions"),
                    controller.GetInputPort("candidate_actions"))
    if needs_cnn:
        evaluator = builder.AddNamedSystem("distance_evaluator",
                                           DistanceEvaluator(model, score_fn=score_fn))
        builder.Connect(depth, evaluator.GetInputPort("depth_image"))
        builder.Connect(sampler.GetOutputPort("candidate_actions"),
                        evaluator.GetInputPort("candidate_actions"))
        if needs_height:
            builder.Connect(controller.GetOutputPort("camera_height"),
                            evaluator.GetInputPort("camera_height"))
        distances = evaluator.GetOutputPort("predicted_distances")
    else:
        none = builder.AddNamedSystem("no_evaluator", ConstantValueSource(
            AbstractValue.Make(np.zeros(0))))
        distances = none.get_output_port()
    builder.Connect(distances, controller.GetInputPort("predicted_distances"))
    return controller, timer, sampler


def _add_controller(builder, scenario, scene, library, station, model, out, detect_fn=None):
    from drake_grasp.policies.evaluator import load_cnn

    c = scenario.controller
    sd = station.diagram
    needs_cnn = scenario.policy in ("ctr", "cnn-only", "cnn-ctr")
    if needs_cnn and model is None:
        model = load_cnn(c.weights, threads=c.torch_threads)
    target, target_label = target_object(scenario, scene, station)
    controller, timer, sampler = add_policy_systems(
        builder, scenario, model=model, X_WG_start=station.X_WG_start, X_GC=station.X_GC,
        X_GC_gpd=station.X_GC_gpd, target_label=target_label, detect_fn=detect_fn,
        **policy_image_ports(builder, scenario, sd))
    out.decision_timer = timer
    out.disturbance = _drive_sheet(builder, scenario, sd, controller.GetOutputPort("control_status"),
                                   c.period_s)
    out.sampler = sampler
    return target, controller


def _hand_xy_yaw(X_WG) -> np.ndarray:
    """[x, y, yaw_deg] of a grasp-frame pose (`grasps.planar_grasp_xy_yaw`)."""
    from drake_grasp.geometry.grasps import planar_grasp_xy_yaw

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
    from drake_grasp.geometry.grasps import distance_to_nearest_grasp, find_grasps

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
    frames, steps = [], []
    distance = None
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
        if detection is None and scenario.policy == "gpd":
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
    replay = None
    if ed.visualizer is not None:
        ed.visualizer.StopRecording()
        ed.visualizer.PublishRecording()
        replay = meshcat.StaticHtml()
    # The policy's own data (iterations, stop reason; why it gave up, if it did) and the
    # judge's verdict (success, failure class and reason, what was lifted).
    outcome = policy.outcome(policy_context)
    verdict = ed.judge.GetOutputPort("judgement").Eval(ed.judge.GetMyContextFromRoot(root))
    failure_reason = verdict.reason
    if not verdict.attempted and verdict.decided and outcome.get("failure_reason"):
        failure_reason = outcome["failure_reason"]  # e.g. "init: no grasp attempted"
    X_WG = plant.CalcRelativeTransform(plant_context, plant.world_frame(),
                                       plant.GetFrameByName("grasp_frame", station.gripper))
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
    target_id = scene.objects[ed.target].object_id if ed.target is not None else None
    result = EpisodeResult(
        success=bool(verdict.success),
        failure_reason=failure_reason,
        policy=scenario.policy,
        scenario=scenario_name,
        seed=int(scenario.seed),
        sim_time_s=float(root.get_time()),
        wall_time_s=time.perf_counter() - wall_start,
        object_ids=scene.object_ids(),
        target_object_id=target_id,
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
