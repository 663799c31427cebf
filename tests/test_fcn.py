"""drake_grasp/cnn/fcn.py: the height-map FCN as a distance function - its weights file, its
scores at the grid's nodes, its grasp map, the shipped file's provenance, and the FCN in
an episode's Diagram, where the controller gives it the camera's height."""

import hashlib
import json
import math

import numpy as np
import pytest
import torch

from drake_grasp.cnn import fcn
from drake_grasp.core.assets import models_dir
from drake_grasp.learning.dense_labels import GRID_CONFIG, grid_node_actions
from drake_grasp.config.scenario import load_scenario
from drake_grasp.policies.evaluator import (FCN_WEIGHTS, load_cnn, needs_camera_height,
                                           score_candidates)

SHIPPED = models_dir() / FCN_WEIGHTS


def _net(seed=0, **kw):
    torch.manual_seed(seed)
    net = fcn.HeightmapFCN(fcn.FcnConfig(width=4, dilations=(1, 2), **kw), GRID_CONFIG)
    with torch.no_grad():  # BatchNorm's running statistics away from the identity too
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    return net.eval()


def _depth(cam_h=0.25, seed=0):
    rng = np.random.default_rng(seed)
    depth = np.full((64, 64), cam_h, np.float32)
    depth[20:40, 10:30] = cam_h - rng.uniform(0.02, 0.06)  # a box
    return depth


def test_weights_round_trip_and_bad_files_are_named(tmp_path):
    net = _net(grasp_head=True, grasp_threshold=0.8)
    path = tmp_path / "fcn.safetensors"
    fcn.save_fcn(net, path, metadata={"note": "test"})
    model, meta = fcn.load_fcn(path)
    assert meta == {"note": "test"} and model.cfg == net.cfg
    depth = _depth()
    a = fcn.FcnDistanceModel(net).grids(depth[None], [0.25])
    assert np.array_equal(model.grids(depth[None], [0.25]), a)
    # load_cnn tells it from a DistanceCNN's file by the format in its metadata.
    assert isinstance(load_cnn(str(path)), fcn.FcnDistanceModel)
    assert not needs_camera_height(load_cnn(""))
    with pytest.raises(ValueError, match=r"cnn-grid-bn12/weights.safetensors: metadata "
                       r"'format' is 'drake_grasp.DistanceCNN/1', expected "
                       r"'drake_grasp.HeightmapFCN/1'"):
        fcn.load_fcn(models_dir() / "cnn-grid-bn12" / "weights.safetensors")
    # A flipped byte in the tensors is caught by the checksum.
    raw = bytearray(path.read_bytes())
    raw[-5] ^= 0xFF
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"bad.safetensors: tensor data does not match"):
        fcn.load_fcn(bad)
    with pytest.raises(FileNotFoundError, match="no such weights file"):
        fcn.load_fcn(tmp_path / "missing.safetensors")
    with pytest.raises(ValueError, match="grasp_threshold > 0 needs grasp_head"):
        fcn.FcnConfig(grasp_threshold=0.5)
    with pytest.raises(ValueError, match=r"grasp_threshold: expected in \[0, 1\)"):
        fcn.FcnConfig(grasp_head=True, grasp_threshold=1.0)


def test_a_candidate_on_a_grid_node_scores_that_node_and_the_height_is_required():
    model = fcn.FcnDistanceModel(_net(seed=1))
    depth = _depth(0.22, seed=1)
    grid = model.grids(depth[None], [0.22])[0]
    nodes = grid_node_actions(GRID_CONFIG)  # (x, y, theta) in the grid's (theta, y, x) order
    rng = np.random.default_rng(0)
    pick = rng.choice(len(nodes), 50, replace=False)
    scores = score_candidates(model, depth, nodes[pick], camera_height_m=0.22)
    assert np.allclose(scores, grid.reshape(-1)[pick], rtol=1e-5, atol=1e-7)
    # Between two nodes along x: the mean of the two.
    mid = (nodes[pick[0]] + np.array([GRID_CONFIG.grid_step_m / 2, 0, 0]))[None]
    t, y, x = np.unravel_index(pick[0], grid.shape)
    if x + 1 < grid.shape[2]:
        assert score_candidates(model, depth, mid, camera_height_m=0.22)[0] == pytest.approx(
            0.5 * (grid[t, y, x] + grid[t, y, x + 1]), rel=1e-5)
    with pytest.raises(ValueError, match="needs camera_height_m"):
        score_candidates(model, depth, nodes[pick])
    with pytest.raises(ValueError, match="camera_height_m: expected finite heights > 0"):
        score_candidates(model, depth, nodes[pick], camera_height_m=float("nan"))
    assert needs_camera_height(model)


def test_the_grasp_threshold_takes_the_nearer_of_the_head_and_the_grasp_map():
    net = _net(seed=2, grasp_head=True, grasp_threshold=0.5)
    t_bins, n, _ = GRID_CONFIG.grid_shape()
    with torch.no_grad():  # distances 5 cm everywhere; grasp logits +20 in theta bin 3 only
        net.head.weight.zero_()
        net.head.bias[:t_bins] = math.log(math.expm1(0.05 / GRID_CONFIG.output_scale_m))
        net.head.bias[t_bins:] = -20.0
        net.head.bias[t_bins + 3] = 20.0
    cam_h = 0.30
    grids = fcn.FcnDistanceModel(net).grids(_depth(cam_h)[None], [cam_h])[0]
    view = fcn.in_view_nodes([cam_h], GRID_CONFIG)[0]
    step = GRID_CONFIG.grid_step_m
    for t in range(t_bins):
        dt = min(abs(t - 3), t_bins - abs(t - 3))  # theta wraps over 180 degrees
        assert np.allclose(grids[t][view], min(0.05, dt * step), atol=1e-6)
    plain = fcn.FcnDistanceModel(_net(seed=2, grasp_head=True))  # threshold 0: the head
    assert plain.cfg.grasp_threshold == 0.0


@pytest.mark.parametrize("shipped,compare_file", [
    (SHIPPED, "compare_grasp_n100000.json"),                     # the pilot, 100,000 images
    (models_dir() / "fcn-heightmap-all" / "weights.safetensors",  # all 7,500 scenes
     "compare_grasp_all.json"),
])
def test_the_shipped_fcns_are_the_committed_nets_with_their_validation_thresholds(
        shipped, compare_file):
    model, meta = fcn.load_fcn(shipped)
    results = shipped.parents[2] / "analysis" / "results" / "heightmap-fcn"
    source = results / meta["source"]
    assert meta["source_sha256"] == hashlib.sha256(source.read_bytes()).hexdigest()
    saved = torch.load(source, weights_only=False)
    assert meta["training"] == saved["identity"]
    for k, v in saved["model"].items():
        assert torch.equal(model.net.state_dict()[k], v), k
    compare = json.loads((results / compare_file).read_text())
    chosen = next(v for k, v in compare.items() if isinstance(v, dict)
                  and "min(grasp map, distance head)" in v)
    assert model.cfg.grasp_threshold == chosen["min(grasp map, distance head)"]["threshold"]


def test_the_evaluator_gets_the_controllers_camera_height_in_the_episode(library):
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.world.scene import make_scene

    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 3, policy: ctr, controller: {profile: robot, weights: '%s'},"
        " scene: {object_ids: [can_000], pose: lying}}" % SHIPPED))
    ed = build_episode_diagram(scenario, make_scene(scenario.scene, 3, library), library)
    evaluator = ed.diagram.GetSubsystemByName("distance_evaluator")
    controller = ed.diagram.GetSubsystemByName("controller")
    context = ed.diagram.CreateDefaultContext()
    height = controller.GetOutputPort("camera_height").Eval(
        controller.GetMyContextFromRoot(context))[0]
    cam_dz = -ed.station.X_GC.translation()[2]
    assert height == pytest.approx(controller.start_hand[2] + cam_dz)
    ev_context = evaluator.GetMyContextFromRoot(context)
    assert evaluator.GetInputPort("camera_height").Eval(ev_context)[0] == height
    depth = evaluator.GetInputPort("depth_image").Eval(ev_context).data[:, :, 0]
    actions = evaluator.GetInputPort("candidate_actions").Eval(ev_context)
    got = evaluator.GetOutputPort("predicted_distances").Eval(ev_context)
    model = load_cnn(str(SHIPPED))
    assert np.array_equal(got, score_candidates(model, depth, actions, camera_height_m=height))
    assert not np.array_equal(
        got, score_candidates(model, depth, actions, camera_height_m=height + 0.05))


def test_ctr_with_the_fcn_grasps_an_isolated_can(library):
    from drake_grasp.evaluation.episode import simulate_episode

    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 1, policy: ctr, controller: {profile: robot, weights: '%s'},"
        " scene: {object_ids: [can_000], pose: lying}}" % SHIPPED))
    r = simulate_episode(scenario, library=library, record_depth=False).result
    assert r.success, r.failure_reason
    assert r.details["grasped_object_id"] == "can_000"
    assert r.control_steps > 5
    assert r.final_distance_m is not None and r.final_distance_m < 0.03


def test_an_ensemble_with_the_fcn_passes_the_height_to_it_and_means_the_scores():
    from drake_grasp.policies.evaluator import DEFAULT_WEIGHTS

    cnn_file = str(models_dir() / DEFAULT_WEIGHTS)
    ensemble = load_cnn(f"{SHIPPED},{cnn_file}")
    assert needs_camera_height(ensemble)
    depth = _depth(0.2)
    actions = np.random.default_rng(3).uniform([-0.04, -0.04, -45], [0.04, 0.04, 45], (16, 3))
    members = [score_candidates(m, depth, actions, camera_height_m=0.2)
               for m in ensemble.members]
    assert np.allclose(score_candidates(ensemble, depth, actions, camera_height_m=0.2),
                       np.mean(members, axis=0))
    with pytest.raises(ValueError, match="needs camera_height_m"):
        score_candidates(ensemble, depth, actions)
    # The mirror average scores the FCN on the mirrored image at the same height.
    mirrored = score_candidates(ensemble.members[0], depth, actions, mirror=True,
                                camera_height_m=0.2)
    assert mirrored.shape == (16,) and np.all(np.isfinite(mirrored))


def test_cnn_only_scores_its_global_candidates_with_the_start_camera_height():
    """cnn-only decides in its first update, before the evaluator runs: it passes the
    score function the camera height of its start pose when told the model needs one."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    from drake_grasp.world.station import gripper_frame_offsets, topdown_pose
    from drake_grasp.policies.controllers import make_controller
    from drake_grasp.policies.controller_state import Phase

    scenario = load_scenario(scenario_name="isolation", scenario_text="{seed: 2}")
    _, _, X_GC = gripper_frame_offsets()
    start = topdown_pose([0.5, 0.0], 0.3 + X_GC.translation()[2], 0.0)
    seen = []

    def score(depth, actions, **kw):
        seen.append(kw)
        return np.linalg.norm(actions[:, :2], axis=1)

    ctrl = make_controller("cnn-only", scenario=scenario, X_WG_start=start, X_GC=X_GC,
                           score_fn=score, score_needs_height=True)
    sim = Simulator(ctrl)
    ctx = sim.get_mutable_context()
    img = ImageDepth32F(64, 64)
    img.mutable_data[:, :, 0] = 0.3
    ctrl.GetInputPort("depth_image").FixValue(ctx, img)
    ctrl.GetInputPort("label_image").FixValue(ctx, ImageLabel16I(64, 64))
    ctrl.GetInputPort("candidate_actions").FixValue(ctx, np.zeros((1, 3)))
    ctrl.GetInputPort("predicted_distances").FixValue(ctx, np.zeros(1))
    ctrl.GetInputPort("gripper_state").FixValue(ctx, np.zeros(4))
    assert ctrl.GetOutputPort("camera_height").Eval(ctx)[0] == pytest.approx(0.3)
    sim.AdvanceTo(0.5 * scenario.controller.period_s)
    assert ctrl.get_controller_state(ctx).phase == Phase.APPROACH
    assert seen == [{"camera_height_m": pytest.approx(0.3)}]
