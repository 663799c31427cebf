"""ONNX export of the distance CNN: equal to torch under onnxruntime, runs without torch.

Tolerances (float32 graphs, different kernels and summation orders): distances within
1e-5 m of torch's fast path; image features within 1e-5 of their largest magnitude;
the depth normalization bit for bit.
"""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
from pydrake.systems.sensors import ImageDepth32F

from drake_grasp.core.assets import models_dir
from drake_grasp.cli.main import main
from drake_grasp.cnn.mirror import MirrorAveragedCNN
from drake_grasp.cnn.net_config import NetworkConfig, normalize_depth
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.cnn.weights_io import save_weights
from drake_grasp.cnn.onnx_export import SHIPPED_WEIGHTS, export_onnx
from drake_grasp.cnn.onnx_runtime import OnnxDistanceModel, head_path, random_check_inputs
from drake_grasp.cnn.onnx_runtime import normalize_depth as normalize_depth_np
from drake_grasp.policies.evaluator import (
    DEFAULT_WEIGHTS,
    PAPER_WEIGHTS,
    DistanceEvaluator,
    load_cnn,
    score_candidates,
)

DISTANCE_TOL_M = 1e-5
FEATURE_REL_TOL = 1e-5


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The shipped paper net exported once through the CLI (default exporter and weights)."""
    path = tmp_path_factory.mktemp("onnx") / "cnn.onnx"
    assert main(["export-onnx", "--out", str(path)]) == 0
    return path


@pytest.fixture(scope="module")
def torch_model():
    return load_cnn(str(models_dir() / PAPER_WEIGHTS))


def test_normalization_is_bit_for_bit_torchs():
    rng = np.random.default_rng(0)
    depth = rng.uniform(-0.1, 1.5, (5, 64, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = np.inf
    depth[rng.random(depth.shape) < 0.05] = 0.0
    for reference in ("fixed", "median"):
        config = NetworkConfig(depth_reference=reference)
        for d in (depth, depth[0], depth[:, None]):
            np.testing.assert_array_equal(normalize_depth_np(d, config.to_dict()),
                                          normalize_depth(d, config).numpy())
    depth[0, 3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        normalize_depth_np(depth, NetworkConfig().to_dict())
    with pytest.raises(ValueError, match=r"expected shape .* got \(64,\)"):
        normalize_depth_np(depth[0, 0], NetworkConfig().to_dict())


def test_onnx_parts_equal_torch_on_random_inputs(exported, torch_model):
    onnx_model = OnnxDistanceModel(exported)
    depth, actions = random_check_inputs(1)
    images = onnx_model.preprocess(depth)
    np.testing.assert_array_equal(images, torch_model.preprocess(depth).numpy())
    features = onnx_model.image_features(images)
    with torch.inference_mode():
        torch_features = torch_model.image_features(torch.from_numpy(images))
        feature_err = np.abs(features - torch_features.numpy()).max()
        assert feature_err <= FEATURE_REL_TOL * np.abs(torch_features.numpy()).max()
        for i in range(len(depth)):
            want = torch_model.score_actions(torch_features[i], torch.from_numpy(actions))
            got = onnx_model.score_actions(features[i], actions)
            assert got.shape == (len(actions),)
            assert np.abs(got - want.numpy()).max() <= DISTANCE_TOL_M
            # What the DistanceEvaluator runs: depth [m] -> distances, both backends.
            err = np.abs(score_candidates(onnx_model, depth[i], actions)
                         - score_candidates(torch_model, depth[i], actions)).max()
            assert err <= DISTANCE_TOL_M
        # The head graph's batch axes: B images x K actions at once.
        batch = np.broadcast_to(actions[:40], (len(depth), 40, 3)).copy()
        want = torch_model.forward_factored(torch.from_numpy(images), torch.from_numpy(batch))
    got = onnx_model._head.run(None, {"features": features, "actions": batch})[0]
    assert np.abs(got - want.numpy()).max() <= DISTANCE_TOL_M
    assert onnx_model.score_actions(features[0], np.zeros((0, 3))).shape == (0,)


def test_the_torchscript_exporter_gives_the_same_numbers(tmp_path, exported, torch_model):
    result = export_onnx(out=tmp_path / "ts.onnx", exporter="torchscript")
    assert result.exporter == "torchscript" and result.probe_max_abs_error_m <= DISTANCE_TOL_M
    depth, actions = random_check_inputs(2, images=1)
    got = OnnxDistanceModel(result.path).score(depth[0], actions)
    assert np.abs(got - score_candidates(torch_model, depth[0], actions)).max() <= DISTANCE_TOL_M
    # export's default is the paper net; the episodes' default, the grid head, is refused
    assert SHIPPED_WEIGHTS == PAPER_WEIGHTS != DEFAULT_WEIGHTS
    with pytest.raises(ValueError, match="tiled"):
        export_onnx(out=tmp_path / "grid.onnx", weights=str(models_dir() / DEFAULT_WEIGHTS))


def test_evaluator_system_with_the_onnx_file_equals_torch(exported, torch_model):
    depth, actions = random_check_inputs(3, images=1)
    image = ImageDepth32F(64, 64)
    image.mutable_data[:, :, 0] = depth[0]
    out = {}
    for name, model in (("torch", torch_model), ("onnx", load_cnn(str(exported)))):
        system = DistanceEvaluator(model)
        ctx = system.CreateDefaultContext()
        system.GetInputPort("depth_image").FixValue(ctx, image)
        system.GetInputPort("candidate_actions").FixValue(ctx, actions.astype(float))
        out[name] = np.asarray(system.GetOutputPort("predicted_distances").Eval(ctx))
    assert isinstance(load_cnn(str(exported)), OnnxDistanceModel)
    assert out["onnx"].shape == (len(actions),)
    assert np.abs(out["onnx"] - out["torch"]).max() <= DISTANCE_TOL_M


def test_mirror_average_is_the_same_on_both_backends(exported, torch_model):
    # controller.mirror_average: the evaluator scores the mean over the image and its
    # mirror image, as MirrorAveragedCNN does, with either backend.
    depth, actions = random_check_inputs(5, images=1)
    mirrored = MirrorAveragedCNN(torch_model)
    with torch.inference_mode():
        want = mirrored.score_actions(mirrored.image_features(mirrored.preprocess(depth[0])),
                                      torch.from_numpy(actions)).numpy()
    image = ImageDepth32F(64, 64)
    image.mutable_data[:, :, 0] = depth[0]
    for model in (torch_model, load_cnn(str(exported))):
        out = {}
        for mirror in (False, True):
            system = DistanceEvaluator(model, mirror=mirror)
            ctx = system.CreateDefaultContext()
            system.GetInputPort("depth_image").FixValue(ctx, image)
            system.GetInputPort("candidate_actions").FixValue(ctx, actions.astype(float))
            out[mirror] = np.asarray(system.GetOutputPort("predicted_distances").Eval(ctx))
        assert np.abs(out[True] - want).max() <= DISTANCE_TOL_M
        assert np.abs(out[True] - out[False]).max() > 1e-4  # the flag changes the scores


def test_onnx_backend_takes_the_scenarios_thread_count(exported):
    for threads in (1, 2):
        model = load_cnn(str(exported), threads=threads)
        for session in (model._image, model._head):
            assert session.get_session_options().intra_op_num_threads == threads


def test_onnx_backend_runs_with_torch_not_importable(exported, torch_model):
    depth, actions = random_check_inputs(4, images=1, k=16)
    want = score_candidates(torch_model, depth[0], actions)
    script = textwrap.dedent("""
        import json, sys
        sys.modules["torch"] = None  # any `import torch` now raises ImportError
        import numpy as np
        from pydrake.systems.sensors import ImageDepth32F
        from drake_grasp.policies.evaluator import DistanceEvaluator, load_cnn
        args = json.loads(sys.argv[1])
        depth = np.array(args["depth"], np.float32)
        system = DistanceEvaluator(load_cnn(args["path"]))
        ctx = system.CreateDefaultContext()
        image = ImageDepth32F(64, 64)
        image.mutable_data[:, :, 0] = depth
        system.GetInputPort("depth_image").FixValue(ctx, image)
        system.GetInputPort("candidate_actions").FixValue(ctx, np.array(args["actions"]))
        got = system.GetOutputPort("predicted_distances").Eval(ctx)
        loaded = [m for m, v in sys.modules.items() if m.split(".")[0] == "torch" and v]
        print(json.dumps({"distances": [float(v) for v in got], "torch": loaded}))
    """)
    arg = json.dumps({"path": str(exported), "depth": np.where(np.isinf(depth[0]), 1e9,
                                                               depth[0]).tolist(),
                      "actions": actions.tolist()})
    proc = subprocess.run([sys.executable, "-c", script, arg], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["torch"] == []
    # +inf travelled as 1e9 through JSON: both clip to the far plane.
    assert np.abs(np.array(result["distances"]) - want).max() <= DISTANCE_TOL_M


def _copy_pair(exported, folder, name="m.onnx"):
    dst = folder / name
    dst.write_bytes(exported.read_bytes())
    head_path(dst).write_bytes(head_path(exported).read_bytes())
    return dst


def test_bad_files_are_named(tmp_path, exported):
    with pytest.raises(FileNotFoundError, match="nope.onnx: no such ONNX model file"):
        load_cnn(str(tmp_path / "nope.onnx"))

    path = _copy_pair(exported, tmp_path, "renamed.onnx")  # a pair renamed together loads
    assert OnnxDistanceModel(path).head_path.name == "renamed.head.onnx"
    head_path(path).unlink()
    with pytest.raises(FileNotFoundError, match=r"renamed\.head\.onnx: no such file"):
        OnnxDistanceModel(path)

    path = _copy_pair(exported, tmp_path)
    path.write_bytes(path.read_bytes()[:5000])
    with pytest.raises(ValueError, match=r"m\.onnx: not a valid ONNX model"):
        OnnxDistanceModel(path)

    path = _copy_pair(exported, tmp_path)
    data = bytearray(head_path(path).read_bytes())
    data[len(data) // 2] ^= 0x01
    head_path(path).write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"m\.head\.onnx: does not match metadata 'head_sha256'"):
        OnnxDistanceModel(path)

    path = _copy_pair(exported, tmp_path)
    with pytest.raises(ValueError, match="metadata 'part' is 'head', expected 'image'"):
        OnnxDistanceModel(head_path(path).rename(tmp_path / "x.onnx"))

    # Weights of the image part changed, metadata intact: the probe check catches it.
    import onnx

    path = _copy_pair(exported, tmp_path)
    model = onnx.load(str(path))
    init = max(model.graph.initializer, key=lambda t: len(onnx.numpy_helper.to_array(t).ravel()))
    array = onnx.numpy_helper.to_array(init).copy()
    array.flat[:50] += 0.5
    init.CopyFrom(onnx.numpy_helper.from_array(array, init.name))
    onnx.save(model, str(path))
    with pytest.raises(ValueError, match=r"m\.onnx: distances on the built-in probe differ"):
        OnnxDistanceModel(path)

    model = onnx.load(str(exported))
    for prop in model.metadata_props:
        if prop.key == "format":
            prop.value = "someone-else/1"
    onnx.save(model, str(tmp_path / "f.onnx"))
    with pytest.raises(ValueError, match="metadata 'format' is 'someone-else/1'"):
        OnnxDistanceModel(tmp_path / "f.onnx")


def test_export_cli_errors(tmp_path, capsys):
    assert main(["export-onnx", "--out", str(tmp_path / "cnn.bin")]) == 2
    assert "cnn.bin: expected a file name ending in '.onnx'" in capsys.readouterr().err
    assert main(["export-onnx", "--out", str(tmp_path / "a.onnx"),
                 "--weights", str(tmp_path / "missing.safetensors")]) == 2
    assert "missing.safetensors: no such weights file" in capsys.readouterr().err
    window = tmp_path / "window.safetensors"
    save_weights(DistanceCNN(NetworkConfig(action_fusion="window")), window, metadata={})
    assert main(["export-onnx", "--out", str(tmp_path / "a.onnx"), "--weights", str(window)]) == 2
    assert "action_fusion 'window'; the ONNX export covers the tiled" in capsys.readouterr().err
    window.unlink()
    fcn = str(models_dir() / "fcn-heightmap" / "weights.safetensors")
    assert main(["export-onnx", "--out", str(tmp_path / "a.onnx"), "--weights", fcn]) == 2
    assert "a height-map FCN (drake_grasp.HeightmapFCN/1); the ONNX export covers the " \
        "distance CNN" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing half-written
