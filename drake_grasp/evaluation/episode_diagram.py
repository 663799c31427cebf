"""The episode Diagram: the station plus the policy side (a built-in controller, GPD's
detector, a scripted grasp or a user plugin), the judge, the sheet's hold or drive, wired
for one scenario and scene (`build_episode_diagram` -> `EpisodeDiagram`). Simulating and
judging it is `episode`'s.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass

import numpy as np

from drake_grasp.objects import ObjectLibrary, visual_mesh
from drake_grasp.policies.decisions import GPD_POLICIES
from drake_grasp.policies.plugins import is_policy_spec
from drake_grasp.config.scenario import Scenario
from drake_grasp.world.scene import SceneSpec


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
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.geometry.scene_samples import ObjectMasses

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
    from drake_grasp.geometry.topdown import plan_topdown_grasp

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
    """The controller's detect_fn: the injected one, else GPD's learned detector
    (`drake_grasp.policies.gpd.make_detector`: gpd, gpd-track) or gpd-geometric's; None
    for other policies."""
    if detect_fn is not None or scenario.policy not in (*GPD_POLICIES, "gpd-geometric"):
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

    from drake_grasp.systems.kinematic_noise import connect_with_noise
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
        if scenario.policy == "scripted":
            builder.Connect(policy.GetOutputPort("X_WG_desired"), sd.GetInputPort("X_WG_desired"))
        else:  # the built-in policies, through the kinematic noise when the scenario has it
            connect_with_noise(builder, scenario, policy, sd.GetInputPort("X_WG_desired"),
                               X_WG_start=station.X_WG_start)
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
    """Episodes built inside the block run `cls`, a subclass of a built-in policy's
    controller class (`policies.controllers.CONTROLLERS`), for the policies whose class it
    derives from (`make_controller` looks the class up each time it builds; a subclass of
    `CTRController` runs ctr). For diagnostics that replace or log one decision of the
    controller (`analysis/oracle_ctr.py`: the true distances;
    `analysis/clutter_predicted_distance.py`: the predictions logged); not for policies
    (`Scenario.policy: MODULE:FACTORY` is)."""
    from drake_grasp.policies.controllers import CONTROLLERS

    original = dict(CONTROLLERS)
    replaced = [policy for policy, base in original.items() if issubclass(cls, base)]
    if not replaced:
        raise TypeError(f"controller_class: {cls.__name__} derives from none of the built-in "
                        f"controller classes {sorted(c.__name__ for c in original.values())}")
    # Only the most derived match: a CNNCTRController subclass runs cnn-ctr, not ctr.
    best = [p for p in replaced if not any(
        original[q] is not original[p] and issubclass(original[q], original[p])
        for q in replaced)]
    CONTROLLERS.update({policy: cls for policy in best})
    try:
        yield cls
    finally:
        CONTROLLERS.clear()
        CONTROLLERS.update(original)


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
                      if scenario.policy in GPD_POLICIES else sd.GetOutputPort("gpd_depth_image")),
    }


def add_policy_systems(builder, scenario, *, model, X_WG_start, X_GC, X_GC_gpd, target_label,
                       detect_fn, depth, label, gpd_depth):
    """The built-in policy's systems: "controller" (`make_controller`), "action_sampler" and
    "distance_evaluator" (the CNN; "no_evaluator" for policies without it), connected to
    the image output ports given (`depth`, `label` - None outside target mode -,
    `gpd_depth`). The in-process episode
    and the controller side of `drake_grasp.evaluation.bridge` both build the policy here.

    Returns (controller, its DecisionTimer, the sampler)."""
    from pydrake.common.value import AbstractValue
    from pydrake.systems.primitives import ConstantValueSource

    from drake_grasp.policies.controllers import make_controller
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
    controller = builder.AddNamedSystem("controller", make_controller(
        scenario.policy, scenario=scenario, X_WG_start=X_WG_start, X_GC=X_GC,
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
