"""One grasp episode: build the diagram, simulate, judge -> EpisodeResult, files on disk."""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from drake_grasp import __version__
from drake_grasp.objects import ObjectLibrary, load_library
from drake_grasp.scenario import Scenario, dump_scenario
from drake_grasp.scene import SceneSpec, make_scene


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
    code_version: str = __version__
    details: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)


@dataclass
class EpisodeRun:
    """An EpisodeResult plus what was recorded on the way (not written to JSON)."""

    result: EpisodeResult
    depth_frames: list = field(default_factory=list)  # (time, mode, HxW array)
    final_plant_state: np.ndarray | None = None
    replay_html: str | None = None
    scene: SceneSpec | None = None


def _object_surface_points(library: ObjectLibrary, object_id: str, count: int = 1500) -> np.ndarray:
    import trimesh

    info = library.get(object_id)
    mesh = trimesh.load(str(Path(info.directory) / "visual.obj"), force="mesh")
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    return np.vstack([np.asarray(points), np.asarray(mesh.vertices)])


def choose_scripted_target(scene: SceneSpec, library: ObjectLibrary) -> tuple[int, np.ndarray]:
    """The object the scripted grasp goes for: the one nearest the workspace centre that
    a top-down grasp fits (else simply the nearest). Returns (index, surface points in
    the object frame)."""
    from drake_grasp.grasps import plan_topdown_grasp

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


def build_episode_diagram(scenario: Scenario, scene: SceneSpec, library: ObjectLibrary,
                          *, meshcat=None):
    """Station + policy (scripted supervisor) + sheet hold, as one Diagram.

    Returns:
        (diagram, station, supervisor, target index, meshcat visualizer or None)
    """
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import ConstantVectorSource

    from drake_grasp.station import MakeGraspStation
    from drake_grasp.systems.supervisor import ScriptedGraspSupervisor

    if not scene.objects:
        raise ValueError("scene has no objects on the table (all fell off while settling?)")
    station = MakeGraspStation(scenario, scene, library)
    builder = DiagramBuilder()
    builder.AddNamedSystem("station", station.diagram)
    target, points_O = choose_scripted_target(scene, library)
    supervisor = builder.AddNamedSystem("supervisor", ScriptedGraspSupervisor(
        object_body_index=station.object_body(target).index(),
        object_points_O=points_O,
        gripper_body_index=station.gripper_body().index(),
        X_BG=station.X_BG, X_WG_start=station.X_WG_start,
        motion=scenario.scripted, gripper=scenario.gripper, judge=scenario.judge))
    sd = station.diagram
    builder.Connect(sd.GetOutputPort("body_poses"), supervisor.GetInputPort("body_poses"))
    builder.Connect(sd.GetOutputPort("gripper_state"), supervisor.GetInputPort("gripper_state"))
    builder.Connect(supervisor.GetOutputPort("X_WG_desired"), sd.GetInputPort("X_WG_desired"))
    builder.Connect(supervisor.GetOutputPort("gripper_command"), sd.GetInputPort("gripper_command"))
    sheet = builder.AddNamedSystem("sheet_hold", ConstantVectorSource(np.zeros(6)))
    builder.Connect(sheet.get_output_port(), sd.GetInputPort("sheet_desired_state"))
    visualizer = None
    if meshcat is not None:
        from pydrake.geometry import MeshcatVisualizer, MeshcatVisualizerParams

        params = MeshcatVisualizerParams()
        params.publish_period = 1.0 / 25.0
        visualizer = MeshcatVisualizer.AddToBuilder(
            builder, sd.GetOutputPort("query_object"), meshcat, params)
    diagram = builder.Build()
    diagram.set_name("grasp_episode")
    return diagram, station, supervisor, target, visualizer


def simulate_episode(scenario: Scenario, *, scenario_name: str = "", library=None,
                     scene: SceneSpec | None = None, record_depth: bool = True,
                     visualize: bool | None = None) -> EpisodeRun:
    """Samples and settles the scene, builds the diagram and runs the episode to its end."""
    from pydrake.systems.analysis import Simulator

    wall_start = time.perf_counter()
    library = library if library is not None else load_library(scenario.objects_dir or None)
    if scene is None:
        scene = make_scene(scenario.scene, scenario.seed, library, scenario.plant)
    visualize = scenario.visualize if visualize is None else visualize
    meshcat = None
    if visualize:
        from pydrake.geometry import StartMeshcat

        meshcat = StartMeshcat()
    diagram, station, supervisor, target, visualizer = build_episode_diagram(
        scenario, scene, library, meshcat=meshcat)
    simulator = Simulator(diagram)
    root = simulator.get_mutable_context()
    station.set_initial_state(station.diagram.GetMyMutableContextFromRoot(root))
    if visualizer is not None:
        visualizer.StartRecording()
    simulator.Initialize()
    station_context = station.diagram.GetMyContextFromRoot(root)
    sup_context = supervisor.GetMyContextFromRoot(root)
    depth_port = station.diagram.GetOutputPort("depth_image")
    frames = []
    dt = 1.0 / scenario.camera.fps
    t = 0.0
    loop_start = time.perf_counter()
    while True:
        if record_depth:
            img = depth_port.Eval(station_context)
            frames.append((t, supervisor.get_supervisor_state(sup_context).mode.value,
                           np.array(img.data[:, :, 0], copy=True)))
        if supervisor.is_done(sup_context) or t >= scenario.max_sim_time_s:
            break
        t = min(t + dt, scenario.max_sim_time_s)
        simulator.AdvanceTo(t)
    loop_wall_s = time.perf_counter() - loop_start
    replay = None
    if visualizer is not None:
        visualizer.StopRecording()
        visualizer.PublishRecording()
        replay = meshcat.StaticHtml()
    state = supervisor.get_supervisor_state(sup_context)
    outcome = dict(state.outcome)
    if not outcome:
        outcome = {"success": False, "failure_reason": f"timeout in mode {state.mode.value}"}
    plant = station.plant
    plant_context = plant.GetMyContextFromRoot(root)
    X_WG = plant.CalcRelativeTransform(plant_context, plant.world_frame(),
                                       plant.GetFrameByName("grasp_frame", station.gripper))
    result = EpisodeResult(
        success=bool(outcome["success"]),
        failure_reason=outcome.get("failure_reason"),
        policy=scenario.policy,
        scenario=scenario_name,
        seed=int(scenario.seed),
        sim_time_s=float(root.get_time()),
        wall_time_s=time.perf_counter() - wall_start,
        object_ids=scene.object_ids(),
        target_object_id=scene.objects[target].object_id,
        final_X_WG=_pose_dict(X_WG),
        object_lowest_point_m=outcome.get("object_lowest_point_m"),
        details={"held_after_close": outcome.get("held_after_close"),
                 "final_mode": state.mode.value,
                 "simulation_wall_time_s": loop_wall_s,
                 "num_depth_frames": len(frames)},
    )
    return EpisodeRun(result=result, depth_frames=frames,
                      final_plant_state=np.array(plant.GetPositionsAndVelocities(plant_context)),
                      replay_html=replay, scene=scene)


def save_depth_contact_sheet(frames, path: Path, *, max_frames: int = 24, title: str = "") -> None:
    """A grid of wrist depth images over the episode (time and mode under each)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not frames:
        raise ValueError("no depth frames to draw")
    idx = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).astype(int))
    cols = min(6, len(idx))
    rows = int(np.ceil(len(idx) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.0 * cols, 2.2 * rows + 0.4), squeeze=False)
    all_depth = np.concatenate([frames[i][2].ravel() for i in idx])
    vmin, vmax = np.percentile(all_depth, 1), np.percentile(all_depth, 99)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, i in zip(axes.ravel(), idx):
        t, mode, depth = frames[i]
        ax.imshow(depth, cmap="viridis_r", vmin=vmin, vmax=vmax)
        ax.set_title(f"t={t:.1f}s {mode}", fontsize=8)
    fig.suptitle(title or "wrist depth images (near = yellow)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def run_episode(scenario: Scenario, *, out_dir: str | Path, scenario_name: str = "",
                library=None, replay: bool = True) -> EpisodeResult:
    """Runs one episode and writes `episode.json`, `scenario.yaml`, `scene.json`,
    `depth.png` and (with `replay`) `replay.html` into `out_dir`.

    Files are written to a staging folder beside `out_dir` and moved in only when the
    episode finished, so a failure leaves nothing half-written in `out_dir`.
    """
    out_dir = Path(out_dir)
    staging = out_dir.parent / f".{out_dir.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    try:
        run = simulate_episode(scenario, scenario_name=scenario_name, library=library,
                               visualize=replay)
        (staging / "scenario.yaml").write_text(dump_scenario(scenario))
        run.scene.save(staging / "scene.json")
        save_depth_contact_sheet(run.depth_frames, staging / "depth.png",
                                 title=f"{scenario_name} seed {scenario.seed}: "
                                       f"{'success' if run.result.success else 'failure'}")
        if run.replay_html is not None:
            (staging / "replay.html").write_text(run.replay_html)
        (staging / "episode.json").write_text(run.result.to_json())
        out_dir.mkdir(parents=True, exist_ok=True)
        for f in staging.iterdir():
            os.replace(f, out_dir / f.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return run.result
