"""drake_grasp's public Python API: what a script, a notebook or a test imports.

Everything here is re-exported from the module that owns it; other names of the package
may change between versions, these are kept. The README's how-tos run them
(`tests/test_api.py` executes each), and `tests/test_api.py` builds this page with pdoc.

The usual path, lowest level first:

1. `load_scenario` -> a typed `Scenario` (every tunable: scene, plant, camera, noise,
   gripper, arm, controller, judge, seed); `dump_scenario` writes it back as YAML.
2. `load_library` -> the object library; `make_scene` samples and settles a scene
   (`SceneSpec`) with physics.
3. `MakeGraspStation(scenario, scene, library)` -> a `GraspStation` whose `diagram` goes
   into your own `DiagramBuilder`. Its input ports: `X_WG_desired` (the grasp frame's
   desired pose, RigidTransform, to the differential IK), `gripper_command`
   ([width_m, grip_force_n]), `sheet_desired_state` (the sheet under the objects; hold it
   with zeros). Output ports: `depth_image` (the wrist camera's 64x64 post-processed
   depth, ImageDepth32F), `depth_image_raw`, `gpd_depth_image`, `gripper_state`,
   `arm_state`, `plant_state`, `body_poses`, `contact_results`, `label_image`,
   `query_object` (the last four are the judge's and visualizers': a policy must not
   read them). `GraspStation.set_initial_state(context)` puts the arm, the gripper and
   the objects at the start.
4. `build_episode_diagram` -> an `EpisodeDiagram`: station + policy + judge (+ Meshcat);
   `simulate_episode` runs one episode to its end (`EpisodeRun`, with its
   `EpisodeResult`); `run_episode` also writes the episode's folder.
5. `evaluate` runs one of the paper's `EXPERIMENTS` (Monte Carlo, resumable) and writes
   its report.
6. Your own policy: `make_policy_system("module:factory", scenario)` builds and checks it
   against the port contract of `drake_grasp.policies.plugins`; pass the same string as
   `Scenario.policy` or as an `evaluate` condition.
7. The distance CNN: `load_cnn` (the shipped weights by default) -> `DistanceCNN`;
   `score_candidates(model, depth, actions)` scores candidate moves on one image. The
   height-map FCN (`load_cnn(".../models/fcn-heightmap/weights.safetensors")` ->
   `FcnDistanceModel`) also needs the camera's height: `score_candidates(model, depth,
   actions, camera_height_m=h)`.
"""

from __future__ import annotations

from drake_grasp.evaluation.episode import EpisodeResult, EpisodeRun, run_episode, simulate_episode
from drake_grasp.evaluation.episode_diagram import EpisodeDiagram, build_episode_diagram
from drake_grasp.evaluation.experiments import EXPERIMENTS, Condition, Experiment
from drake_grasp.cnn.fcn import FcnDistanceModel
from drake_grasp.evaluation.montecarlo import evaluate
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.objects import ObjectLibrary, load_library
from drake_grasp.policies.plugins import make_policy_system
from drake_grasp.config.scenario import Scenario, dump_scenario, load_scenario
from drake_grasp.world.scene import SceneSpec, make_scene, scenario_scene
from drake_grasp.world.station import GraspStation, MakeGraspStation
from drake_grasp.policies.evaluator import load_cnn, score_candidates

__all__ = [
    "load_scenario", "dump_scenario", "Scenario",
    "load_library", "ObjectLibrary", "make_scene", "scenario_scene", "SceneSpec",
    "MakeGraspStation", "GraspStation",
    "build_episode_diagram", "EpisodeDiagram", "simulate_episode", "run_episode",
    "EpisodeRun", "EpisodeResult",
    "evaluate", "EXPERIMENTS", "Experiment", "Condition",
    "make_policy_system",
    "load_cnn", "score_candidates", "DistanceCNN", "FcnDistanceModel",
]
