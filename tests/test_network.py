"""Tests of the distance CNN: shapes, symmetry, fast path == direct form, weights I/O."""

import copy
import dataclasses
import json
import math
import re

import numpy as np
import pytest
import safetensors
import safetensors.torch
import torch

import drake_grasp
from drake_grasp.cnn.mirror import MirrorAveragedCNN, mirror_actions, mirror_images
from drake_grasp.cnn.net_config import NetworkConfig, action_features, normalize_depth
from drake_grasp.cnn.network import DistanceCNN
from drake_grasp.cnn.weights_io import load_weights, save_weights, tensors_sha256

CFG = NetworkConfig()


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _model(seed: int = 0, dtype: torch.dtype = torch.float64, config=None) -> DistanceCNN:
    return DistanceCNN(config, generator=_gen(seed), dtype=dtype)


def _images(n: int, seed: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return torch.randn(n, 1, CFG.image_size, CFG.image_size, generator=_gen(seed), dtype=dtype)


def _raw_actions(shape: tuple, seed: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Raw (x, y, theta): x, y in +-0.1 m, theta in [-pi, pi) rad."""
    u = torch.rand(*shape, 3, generator=_gen(seed), dtype=dtype)
    scale = torch.tensor([0.2, 0.2, 2 * math.pi], dtype=dtype)
    shift = torch.tensor([0.1, 0.1, math.pi], dtype=dtype)
    return u * scale - shift


def _max_rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()


def _param_grads(model: DistanceCNN, out: torch.Tensor, seed: int) -> dict:
    # A random weighting of the outputs so every gradient path is exercised.
    w = torch.randn(out.shape, generator=_gen(seed), dtype=out.dtype)
    names, params = zip(*model.named_parameters())
    grads = torch.autograd.grad((w * out).sum(), params)
    return dict(zip(names, grads))


# -- config and normalization --------------------------------------------------------


def test_default_config_shapes():
    assert CFG.feature_shape() == (50, 13, 13)
    assert CFG.num_features == 8450
    assert CFG.pool1_size == 30


@pytest.mark.parametrize(
    "field, value",
    [("conv2_channels", 0), ("kernel", 2.5), ("leaky_slope", -0.1), ("depth_reference", "max"),
     ("theta_unit", "grad"), ("depth_clip_far_m", 0.01), ("image_size", 12)],
)
def test_config_rejects_bad_values(field, value):
    with pytest.raises(ValueError, match=field if field != "depth_clip_far_m" else "depth_clip"):
        NetworkConfig(**{field: value})


def test_config_from_dict_requires_every_field():
    d = CFG.to_dict()
    assert NetworkConfig.from_dict(d) == CFG
    del d["ip1"]
    with pytest.raises(ValueError, match="missing.*ip1"):
        NetworkConfig.from_dict(d)
    with pytest.raises(ValueError, match="unknown.*bogus"):
        NetworkConfig.from_dict({**CFG.to_dict(), "bogus": 1})


def test_normalize_depth_fixed():
    depth = np.full((64, 64), 0.3, dtype=np.float32)
    depth[0, 0] = np.inf  # nothing there -> far clip
    depth[0, 1] = 0.0  # invalid pixel -> near clip
    depth[0, 2] = 0.25
    n = normalize_depth(depth)
    assert n.shape == (1, 1, 64, 64) and n.dtype == torch.float32
    assert n[0, 0, 0, 0].item() == pytest.approx((CFG.depth_clip_far_m - 0.3) / 0.1)
    assert n[0, 0, 0, 1].item() == pytest.approx((CFG.depth_clip_near_m - 0.3) / 0.1)
    assert n[0, 0, 0, 2].item() == pytest.approx(-0.5, abs=1e-6)
    assert n[0, 0, 5, 5].item() == pytest.approx(0.0, abs=1e-6)
    assert normalize_depth(np.stack([depth] * 3)).shape == (3, 1, 64, 64)
    assert normalize_depth(torch.as_tensor(depth)[None, None]).shape == (1, 1, 64, 64)


def test_normalize_depth_median_is_height_invariant():
    cfg = NetworkConfig(depth_reference="median")
    rng = np.random.default_rng(0)
    depth = 0.3 + 0.05 * rng.random((2, 64, 64))
    a = normalize_depth(depth, cfg, dtype=torch.float64)
    b = normalize_depth(depth + 0.07, cfg, dtype=torch.float64)
    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_normalize_depth_errors():
    with pytest.raises(ValueError, match="NaN"):
        normalize_depth(np.full((64, 64), np.nan))
    with pytest.raises(ValueError, match="depth: expected shape"):
        normalize_depth(np.zeros((2, 3, 64, 64)))


def test_action_features():
    raw = torch.tensor([[0.05, -0.1, math.pi / 4]], dtype=torch.float64)
    f = action_features(raw, dtype=torch.float64)
    torch.testing.assert_close(f, torch.tensor([[0.5, -1.0, 0.0, 1.0]], dtype=torch.float64))
    deg = NetworkConfig(theta_unit="deg")
    f_deg = action_features([[0.05, -0.1, 45.0]], deg, dtype=torch.float64)
    torch.testing.assert_close(f_deg, f)
    assert torch.equal(action_features(f, dtype=torch.float64), f)  # features pass through
    with pytest.raises(ValueError, match="actions"):
        action_features(torch.zeros(5, 2))


# -- the network -----------------------------------------------------------------------


def test_construction_is_seeded_and_leaves_global_rng_alone():
    with torch.random.fork_rng():
        torch.manual_seed(123)
        before = torch.random.get_rng_state()
        a = _model(seed=7, dtype=torch.float32)
        after = torch.random.get_rng_state()
    assert torch.equal(before, after)
    b = _model(seed=7, dtype=torch.float32)
    c = _model(seed=8, dtype=torch.float32)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k
        assert not torch.equal(sa[k], sc[k]), k


def test_shapes_and_non_negative():
    m = _model(dtype=torch.float32)
    imgs = _images(3, seed=1, dtype=torch.float32)
    acts = _raw_actions((3, 4), seed=2, dtype=torch.float32)
    assert m(imgs, acts[:, 0]).shape == (3,)
    feats = m.image_features(imgs)
    assert feats.shape == (3, 50, 13, 13)
    assert m.score_actions(feats[0], acts[0]).shape == (4,)
    assert m.score_actions(feats[:1], acts[0]).shape == (4,)
    out = m.forward_factored(imgs, acts)
    assert out.shape == (3, 4)
    assert torch.all(out >= 0) and torch.all(torch.isfinite(out))
    # Even a net pushed hard toward negative outputs stays >= 0 (softplus).
    with torch.no_grad():
        m.ip2.bias.fill_(-50.0)
    out = m.forward_factored(imgs, acts)
    assert torch.all(out >= 0) and torch.all(torch.isfinite(out))


def test_input_shape_errors():
    m = _model(dtype=torch.float32)
    with pytest.raises(ValueError, match=r"images: expected shape \(B, 1, 64, 64\)"):
        m(torch.zeros(2, 64, 64), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="actions"):
        m(torch.zeros(2, 1, 64, 64), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="features"):
        m.score_actions(torch.zeros(2, 50, 13, 13), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="actions"):
        m.forward_factored(torch.zeros(2, 1, 64, 64), torch.zeros(2, 3))


@pytest.mark.parametrize("theta_unit, half_turn", [("rad", math.pi), ("deg", 180.0)])
def test_theta_symmetry(theta_unit, half_turn):
    cfg = NetworkConfig(theta_unit=theta_unit)
    m = _model(config=cfg)
    imgs = _images(2, seed=3)
    acts = _raw_actions((2, 5), seed=4)
    if theta_unit == "deg":
        acts[..., 2] = torch.rad2deg(acts[..., 2])
    flipped = acts.clone()
    flipped[..., 2] += half_turn
    out = m.forward_factored(imgs, acts)
    torch.testing.assert_close(m.forward_factored(imgs, flipped), out, rtol=1e-12, atol=0)
    torch.testing.assert_close(m(imgs, flipped[:, 0]), m(imgs, acts[:, 0]), rtol=1e-12, atol=0)
    # ...while a quarter turn is a different grasp.
    quarter = acts.clone()
    quarter[..., 2] += half_turn / 2
    assert not torch.allclose(m.forward_factored(imgs, quarter), out)


def test_raw_and_feature_actions_agree():
    m = _model()
    imgs = _images(2, seed=5)
    acts = _raw_actions((2, 3), seed=6)
    feats = action_features(acts, m.config, dtype=torch.float64)
    torch.testing.assert_close(m.forward_factored(imgs, feats), m.forward_factored(imgs, acts))


# float64 is the real check of the identities. float32 gets looser gradient bounds: the
# two forms round differently, so a max-pool window whose two largest entries are within
# rounding of each other can pick a different argmax and route one gradient entry
# elsewhere (seen at ~3e-3 max-relative on 1 seed in 20); outputs stay within ~4e-6.
_TOLERANCES = [(torch.float64, 1e-9, 1e-8), (torch.float32, 5e-5, 1e-2)]


def _ip1_branches(m: DistanceCNN, feats: torch.Tensor, offsets: torch.Tensor) -> tuple:
    """How many IP1 inputs are on lrelu's identity branch for every candidate, on its
    slope branch for every candidate, and ambiguous (what `InferenceIP1.split` partitions)."""
    x = feats.reshape(1, feats.shape[0], -1) + offsets[:, :, None]
    on, off = (x > 0).all(dim=0), (x <= 0).all(dim=0)
    return int(on.sum()), int(off.sum()), int((~(on | off)).sum())


@pytest.mark.parametrize("spread, expect_split", [(0.05, True), (1.0, True), (50.0, False)])
def test_split_ip1_equals_dense_product(spread, expect_split):
    # float32 under inference_mode: the controller's path. The actions' spread sets how
    # many IP1 inputs are ambiguous; at 50 most are, and the dense product is used.
    m = _model(seed=31, dtype=torch.float32).eval()
    img = _images(1, seed=32, dtype=torch.float32)
    acts = _raw_actions((128,), seed=33, dtype=torch.float32) * spread
    with torch.inference_mode():
        feats = m.image_features(img)[0]
        offsets = m.action_offsets(acts)
        on, off, ambiguous = _ip1_branches(m, feats, offsets)
        if expect_split:
            assert min(on, off, ambiguous) > 0, "the check needs inputs of all three kinds"
        else:
            assert ambiguous > m.head.fast_ip1.SPLIT_MAX_AMBIGUOUS * (on + off + ambiguous)
        assert (m.head.fast_ip1.split(feats, offsets) is not None) == expect_split, (on, off, ambiguous)
        fast = m.score_actions(feats, acts)
        dense = m.head.score_features(feats[None], offsets)
    direct = m.forward_direct(img.expand(128, -1, -1, -1), acts).detach()
    assert _max_rel(fast, dense) <= 5e-5
    assert _max_rel(fast, direct) <= 5e-5


def test_split_ip1_single_candidate_has_no_ambiguous_inputs():
    # One candidate: every input's branch is known, so IP1 is the affine part alone.
    m = _model(seed=34, dtype=torch.float32).eval()
    img = _images(1, seed=35, dtype=torch.float32)
    acts = _raw_actions((1,), seed=36, dtype=torch.float32)
    with torch.inference_mode():
        feats = m.image_features(img)[0]
        assert _ip1_branches(m, feats, m.action_offsets(acts))[2] == 0
        fast = m.score_actions(feats, acts)
    direct = m.forward_direct(img, acts).detach()
    assert _max_rel(fast, direct) <= 5e-5


def test_score_actions_takes_no_candidates():
    m = _model(seed=40, dtype=torch.float32).eval()
    with torch.inference_mode():
        out = m.score_actions(m.image_features(_images(1, seed=41, dtype=torch.float32)),
                              torch.zeros(0, 3))
    assert out.shape == (0,)


def test_split_ip1_cache_follows_weight_updates():
    # The weight layouts are memoized; changing the weights must change the scores.
    m = _model(seed=37, dtype=torch.float32).eval()
    img = _images(1, seed=38, dtype=torch.float32)
    acts = _raw_actions((16,), seed=39, dtype=torch.float32) * 0.1
    with torch.inference_mode():
        before = m.score_actions(m.image_features(img), acts)
    with torch.no_grad():
        m.ip1.weight.mul_(0.5)
    with torch.inference_mode():
        after = m.score_actions(m.image_features(img), acts)
    direct = m.forward_direct(img.expand(16, -1, -1, -1), acts).detach()
    assert _max_rel(after, direct) <= 5e-5
    assert not torch.allclose(before, after)


@pytest.mark.parametrize("dtype, out_rtol, grad_rtol", _TOLERANCES)
def test_control_fast_path_equals_direct(dtype, out_rtol, grad_rtol):
    m = _model(seed=11, dtype=dtype)
    img = _images(1, seed=12, dtype=dtype)
    acts = _raw_actions((16,), seed=13, dtype=dtype)

    direct = m.forward_direct(img.expand(16, -1, -1, -1), acts)
    fast = m.score_actions(m.image_features(img), acts)
    assert _max_rel(fast, direct) <= out_rtol

    g_direct = _param_grads(m, direct, seed=14)
    g_fast = _param_grads(m, fast, seed=14)
    for name, g in g_direct.items():
        assert g.abs().max() > 0, f"{name}: zero gradient makes the comparison vacuous"
        assert _max_rel(g_fast[name], g) <= grad_rtol, name


@pytest.mark.parametrize("dtype, out_rtol, grad_rtol", _TOLERANCES)
def test_training_fast_path_equals_direct(dtype, out_rtol, grad_rtol):
    B, M = 3, 4
    m = _model(seed=21, dtype=dtype)
    imgs = _images(B, seed=22, dtype=dtype)
    acts = _raw_actions((B, M), seed=23, dtype=dtype)

    direct = m.forward_direct(imgs.repeat_interleave(M, dim=0), acts.reshape(B * M, 3))
    direct = direct.reshape(B, M)
    fast = m.forward_factored(imgs, acts)
    assert _max_rel(fast, direct) <= out_rtol

    g_direct = _param_grads(m, direct, seed=24)
    g_fast = _param_grads(m, fast, seed=24)
    for name, g in g_direct.items():
        assert g.abs().max() > 0, f"{name}: zero gradient makes the comparison vacuous"
        assert _max_rel(g_fast[name], g) <= grad_rtol, name


def test_mirror_averaged_cnn_is_mirror_invariant_and_its_forms_agree():
    # The mean of d(I, a) and d(flip(I), mirror(a)): invariant under the mirror itself,
    # the same number from the direct, training and control forms, and not the plain
    # network (a random one is not mirror-symmetric).
    base = _model(seed=51)
    m = MirrorAveragedCNN(base)
    img = _images(1, seed=52)
    acts = _raw_actions((12,), seed=53)
    direct = m.forward(img.expand(12, -1, -1, -1), acts)
    mirrored = m.forward(mirror_images(img).expand(12, -1, -1, -1), mirror_actions(acts))
    assert _max_rel(mirrored, direct) <= 1e-12
    assert _max_rel(m.score_actions(m.image_features(img), acts), direct) <= 1e-10
    assert _max_rel(m.forward_factored(img, acts[None])[0], direct) <= 1e-10
    plain = base.forward(img.expand(12, -1, -1, -1), acts)
    assert _max_rel(plain, direct) > 1e-3
    # Raw actions and features are mirrored alike; mirroring twice is the identity.
    np.testing.assert_allclose(action_features(mirror_actions(acts)),
                               mirror_actions(action_features(acts)), atol=1e-12)
    assert torch.equal(mirror_actions(mirror_actions(acts)), acts)
    a = np.array([[0.01, 0.02, 30.0]])
    np.testing.assert_array_equal(mirror_actions(a), [[-0.01, 0.02, -30.0]])
    assert a[0, 0] == 0.01  # the input is not changed
    np.testing.assert_array_equal(mirror_images(np.arange(6.0).reshape(2, 3)),
                                  [[2, 1, 0], [5, 4, 3]])
    with pytest.raises(ValueError, match="features"):
        m.score_actions(base.image_features(img), acts)
    with pytest.raises(ValueError, match="already"):
        MirrorAveragedCNN(m)


def test_inference_mode_control_path():
    # Without autograd, float32 IP1 runs on cached oneDNN weights: same numbers to
    # float32 rounding, and the cache follows in-place weight updates.
    m = _model(seed=41, dtype=torch.float32)
    img = _images(1, seed=42, dtype=torch.float32)
    acts = _raw_actions((32,), seed=43, dtype=torch.float32)
    for _ in range(2):
        with torch.inference_mode():
            fast = m.score_actions(m.image_features(img), acts)
        direct = m.forward_direct(img.expand(32, -1, -1, -1), acts).detach()
        assert _max_rel(fast, direct) <= 5e-5
        with torch.no_grad():
            m.ip1.weight.mul_(1.5)  # must invalidate the cache for the second round
    clone = copy.deepcopy(m)
    with torch.inference_mode():
        assert torch.equal(clone.score_actions(clone.image_features(img), acts),
                           m.score_actions(m.image_features(img), acts))


# -- weights I/O -------------------------------------------------------------------------


META = {"dataset_manifest_sha256": "ab" * 32, "epoch": 3}


def _saved(tmp_path, dtype=torch.float32, config=None):
    m = _model(seed=31, dtype=dtype, config=config)
    path = tmp_path / "cnn.safetensors"
    save_weights(m, path, metadata=META)
    return m, path


def _rewrite(path, *, metadata=None, tensors=None, recompute_digest=True):
    """Re-saves `path` with some metadata entries / tensors replaced (or removed: None)."""
    with safetensors.safe_open(str(path), framework="pt") as f:
        header = dict(f.metadata())
        stored = {k: f.get_tensor(k) for k in f.keys()}
    for k, v in (metadata or {}).items():
        header[k] = v
    for k, v in (tensors or {}).items():
        if v is None:
            del stored[k]
        else:
            stored[k] = v
    if recompute_digest:
        header["tensors_sha256"] = tensors_sha256(stored)
    safetensors.torch.save_file(stored, str(path), metadata=header)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_save_load_round_trip(tmp_path, dtype):
    m, path = _saved(tmp_path, dtype=dtype, config=NetworkConfig(depth_reference="median"))
    loaded, meta = load_weights(path, expected_config=m.config)
    assert loaded.config == m.config and loaded.dtype == dtype and not loaded.training
    assert meta["dataset_manifest_sha256"] == META["dataset_manifest_sha256"]
    assert meta["epoch"] == 3
    assert meta["code_version"] == drake_grasp.__version__
    assert NetworkConfig.from_dict(meta["config"]) == m.config
    imgs = _images(2, seed=32, dtype=dtype)
    acts = _raw_actions((2, 3), seed=33, dtype=dtype)
    assert torch.equal(loaded.forward_factored(imgs, acts), m.forward_factored(imgs, acts))
    assert not list(tmp_path.glob(".*tmp")), "temporary file left behind"


def test_save_rejects_bad_metadata(tmp_path):
    m = _model(dtype=torch.float32)
    with pytest.raises(ValueError, match="JSON"):
        save_weights(m, tmp_path / "a.safetensors", metadata={"x": object()})
    with pytest.raises(ValueError, match="reserved"):
        save_weights(m, tmp_path / "a.safetensors", metadata={"config": "{}"})
    assert not (tmp_path / "a.safetensors").exists()


def test_load_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.safetensors"):
        load_weights(tmp_path / "nope.safetensors")


def test_load_flipped_bytes(tmp_path):
    _, path = _saved(tmp_path)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2  # inside ip1.weight, the bulk of the file
    data[mid : mid + 8] = bytes(b ^ 0xFF for b in data[mid : mid + 8])
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*tensors_sha256"):
        load_weights(path)


def test_load_truncated(tmp_path):
    _, path = _saved(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*not a valid safetensors"):
        load_weights(path)
    path.write_bytes(b"\x00\x01garbage")
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*not a valid safetensors"):
        load_weights(path)


def test_load_config_changed_in_metadata(tmp_path):
    m, path = _saved(tmp_path)
    cfg = {**m.config.to_dict(), "conv2_channels": 40}
    _rewrite(path, metadata={"config": json.dumps(cfg)})
    with pytest.raises(ValueError, match=re.escape(str(path)) + r".*'conv2\.(weight|bias)'.*shape"):
        load_weights(path)


def test_load_tensor_shape_changed(tmp_path):
    m, path = _saved(tmp_path)
    _rewrite(path, tensors={"ip2.weight": torch.zeros(1, 499)})
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*'ip2.weight'.*shape"):
        load_weights(path)


def test_load_tensor_missing_or_extra(tmp_path):
    _, path = _saved(tmp_path)
    _rewrite(path, tensors={"conv1.bias": None})
    with pytest.raises(ValueError, match="'conv1.bias' missing"):
        load_weights(path)
    _, path = _saved(tmp_path)
    _rewrite(path, tensors={"extra": torch.zeros(2)})
    with pytest.raises(ValueError, match="unexpected tensor 'extra'"):
        load_weights(path)


def test_load_expected_config_mismatch(tmp_path):
    _, path = _saved(tmp_path)
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*'depth_scale_m'"):
        load_weights(path, expected_config=dataclasses.replace(CFG, depth_scale_m=0.2))


def test_load_bad_metadata(tmp_path):
    _, path = _saved(tmp_path)
    _rewrite(path, metadata={"config": "{not json"})
    with pytest.raises(ValueError, match="'config' is not valid JSON"):
        load_weights(path)
    _, path = _saved(tmp_path)
    _rewrite(path, metadata={"format": "something-else"})
    with pytest.raises(ValueError, match="'format'"):
        load_weights(path)
    # A plain safetensors file without our metadata.
    safetensors.torch.save_file({"x": torch.zeros(2)}, str(path))
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*metadata key 'format' missing"):
        load_weights(path)


# -- window fusion ---------------------------------------------------------------------

WIN = NetworkConfig(action_fusion="window")


def test_window_config_and_backward_compatible_dicts():
    """A tiled net's dict has no window fields (files and run identities written before
    the window fusion existed are unchanged); a window net's needs all of them."""
    assert "action_fusion" not in CFG.to_dict()
    assert NetworkConfig.from_dict(CFG.to_dict()).action_fusion == "tiled"
    assert NetworkConfig.from_dict(WIN.to_dict()) == WIN
    d = WIN.to_dict()
    del d["window_side_m"]
    with pytest.raises(ValueError, match="missing.*window_side_m"):
        NetworkConfig.from_dict(d)
    assert WIN.feature_shape() == (51, 26, 26)
    assert WIN.num_features == 50 * 10 * 10
    with pytest.raises(ValueError, match="window_samples"):
        NetworkConfig(action_fusion="window", window_samples=7)
    with pytest.raises(ValueError, match="depth_reference"):
        NetworkConfig(action_fusion="window", depth_reference="median")
    with pytest.raises(ValueError, match="action_fusion"):
        NetworkConfig(action_fusion="concat")
    with pytest.raises(ValueError, match="context_side_m"):
        NetworkConfig(action_fusion="window", context_side_m=-0.1)


@pytest.mark.parametrize("context_side_m", [0.0, 0.3])
def test_window_forms_agree_and_save_load(tmp_path, context_side_m):
    cfg = dataclasses.replace(WIN, context_side_m=context_side_m)
    assert cfg.num_features == (2 if context_side_m else 1) * 5000
    m = _model(config=cfg)
    images = _images(3, seed=1) * 0.3
    actions = _raw_actions((3, 5), seed=2) * torch.tensor([0.8, 0.8, 1.0], dtype=torch.float64)
    factored = m.forward_factored(images, actions)
    direct = torch.stack([m.forward(images, actions[:, j]) for j in range(5)], dim=1)
    control = torch.stack([m.score_actions(m.image_features(images[i:i + 1])[0], actions[i])
                           for i in range(3)])
    assert factored.shape == (3, 5) and (factored > 0).all()
    assert _max_rel(direct, factored) < 1e-12 and _max_rel(control, factored) < 1e-12
    save_weights(m, tmp_path / "w.safetensors", metadata={})
    loaded, meta = load_weights(tmp_path / "w.safetensors")
    assert loaded.config == cfg and meta["config"]["action_fusion"] == "window"
    # context_side_m came after the window: a window net without it has none.
    assert ("context_side_m" in meta["config"]) == bool(context_side_m)
    assert torch.equal(loaded.forward_factored(images, actions), factored)
    with pytest.raises(ValueError, match="window"):
        m.action_offsets(actions)


def test_window_is_placed_where_the_candidate_grasp_is_seen():
    """Translation equivariance, exactly: content moved by 4 pixels (two Conv2 cells) in
    the image, and the candidate moved by the same 4 pixels' worth of metres at the
    image's depth, score the same. And the window's centre is the pixel where the
    candidate's grasp axis is seen (`policies.grasp_axis_pixel`'s geometry)."""
    from drake_grasp.policies.decisions import grasp_axis_pixel

    m = _model(config=WIN)
    rng = np.random.default_rng(0)
    depth = np.full((64, 64), 0.25)
    depth[24:40, 20:44] -= rng.uniform(0.0, 0.06, (16, 24))  # an object, away from borders
    moved = np.roll(depth, 4, axis=1)  # 4 px towards +u, i.e. +x_G
    dx = 4 * 0.25 / WIN.focal_px
    a = torch.tensor([[0.0, -0.05, 30.0], [0.01, -0.04, -60.0]], dtype=torch.float64)
    b = a + torch.tensor([dx, 0.0, 0.0], dtype=torch.float64)
    images = m.preprocess(np.stack([depth, moved]))
    f = m.image_features(images)
    assert torch.allclose(f[:, -1, 0, 0], torch.full((2,), 0.25, dtype=torch.float64))
    d0 = m.score_actions(f[0], a)
    d1 = m.score_actions(f[1], b)
    assert torch.allclose(d0, d1, rtol=1e-9, atol=0), (d0, d1)
    # The grid's centre for the hand's own grasp axis (action 0) at the image's depth.
    feats = action_features(torch.zeros(1, 1, 3), WIN, dtype=torch.float64)
    grid = m.head.window_grid(feats, torch.tensor([0.25], dtype=torch.float64))
    side = WIN.feature_shape()[1]
    u, v = ((grid.mean(dim=(1, 2))[0] + 1) * (side - 1) / 2) * 2 + 6.5  # back to pixels
    u0, v0 = grasp_axis_pixel((64, 64), WIN.focal_px, (WIN.camera_x_G_m, WIN.camera_y_G_m), 0.25)
    assert abs(u.item() - u0) < 1e-9 and abs(v.item() - v0) < 1e-9
    # Turned by 60 degrees, each window row runs along the closing axis, (cos 60, sin 60)
    # in (x_G, y_G), i.e. in (u, v).
    turned = m.head.window_grid(action_features(torch.tensor([[[0.0, 0.0, math.pi / 3]]]), WIN,
                                                dtype=torch.float64),
                                torch.tensor([0.25], dtype=torch.float64))
    du, dv = (turned[0, 0, 1] - turned[0, 0, 0]).tolist()
    assert du > 0 and abs(dv / du - math.sqrt(3)) < 1e-5


# -- the grid head ---------------------------------------------------------------------

GRID = NetworkConfig(action_fusion="grid", theta_unit="deg")


def _node_action(cfg: NetworkConfig, k: int, iy: int, ix: int) -> list[float]:
    half = (cfg.grid_shape()[1] - 1) // 2
    return [cfg.camera_x_G_m + (ix - half) * cfg.grid_step_m,
            cfg.camera_y_G_m + (iy - half) * cfg.grid_step_m,
            -90.0 + k * cfg.grid_theta_step_deg]


def test_grid_config_and_dicts():
    """A grid net's dict names the grid; other nets' dicts do not (older files unchanged)."""
    assert GRID.grid_shape() == (18, 33, 33) and GRID.feature_shape() == (18, 33, 33)
    assert GRID.num_features == CFG.num_features == 8450
    assert NetworkConfig.from_dict(GRID.to_dict()) == GRID
    for cfg in (CFG, WIN):
        assert not any(k.startswith("grid_") for k in cfg.to_dict())
    d = GRID.to_dict()
    del d["grid_step_m"]
    with pytest.raises(ValueError, match="missing.*grid_step_m"):
        NetworkConfig.from_dict(d)
    with pytest.raises(ValueError, match="whole numbers"):
        NetworkConfig(action_fusion="grid", grid_step_m=0.015)
    with pytest.raises(ValueError, match="grid_theta_step_deg"):
        NetworkConfig(action_fusion="grid", grid_theta_step_deg=0.0)


def test_grid_interpolates_its_nodes_periodically_and_its_forms_agree(tmp_path):
    m = _model(config=GRID)
    images = _images(2, seed=3) * 0.3
    grids = m.image_features(images)
    assert grids.shape == (2, 18, 33, 33) and (grids > 0).all()
    nodes = [(0, 0, 0), (3, 7, 20), (17, 32, 32), (9, 16, 16)]
    actions = torch.tensor([_node_action(GRID, *n) for n in nodes], dtype=torch.float64)
    at_nodes = m.score_actions(grids[0], actions)
    expected = torch.stack([grids[0][n] for n in nodes])
    assert _max_rel(at_nodes, expected) < 1e-9
    # A parallel jaw turned by 180 degrees is the same grasp: theta wraps.
    turned = actions + torch.tensor([0.0, 0.0, 180.0], dtype=torch.float64)
    assert _max_rel(m.score_actions(grids[0], turned), expected) < 1e-9
    # Half way between two theta nodes across the wrap (80 and -90 = 90 degrees).
    mid = torch.tensor([_node_action(GRID, 17, 5, 6)], dtype=torch.float64)
    mid[0, 2] += 5.0
    assert torch.allclose(m.score_actions(grids[0], mid)[0],
                          0.5 * (grids[0, 17, 5, 6] + grids[0, 0, 5, 6]))
    # Beyond the grid: clamped to its edge.
    far = torch.tensor([[1.0, -1.0, -90.0]], dtype=torch.float64)
    assert torch.allclose(m.score_actions(grids[0], far)[0], grids[0, 0, 0, 32])
    acts = _raw_actions((2, 6), seed=4) * torch.tensor([1.0, 1.0, 180 / math.pi],
                                                       dtype=torch.float64)
    factored = m.forward_factored(images, acts)
    direct = torch.stack([m.forward(images, acts[:, j]) for j in range(6)], dim=1)
    assert _max_rel(direct, factored) < 1e-12
    save_weights(m, tmp_path / "g.safetensors", metadata={})
    loaded, meta = load_weights(tmp_path / "g.safetensors")
    assert loaded.config == GRID and meta["config"]["grid_step_m"] == GRID.grid_step_m
    assert torch.equal(loaded.forward_factored(images, acts), factored)
    with pytest.raises(ValueError, match="grid"):
        m.action_offsets(acts)


def test_grid_nodes_only_where_the_actions_need_them_equal_the_whole_grid():
    """`score_grid_nodes` (IP2 at the nodes around the actions: the controller's path)
    gives `score_actions` on the whole grid, near the hand, over the whole view, across
    the theta wrap and beyond the grid's edge."""
    m = _model(seed=8, config=GRID)
    images = _images(2, seed=9) * 0.3
    grids = m.image_features(images)
    hidden = m.grid_hidden(images)
    assert hidden.shape == (2, GRID.ip1)
    near = _raw_actions((40,), seed=10) * torch.tensor([0.3, 0.3, 30.0], dtype=torch.float64)
    wide = _raw_actions((300,), seed=11) * torch.tensor([3.0, 3.0, 400.0], dtype=torch.float64)
    edge = torch.tensor([[1.0, -1.0, -90.0], [0.0, 0.0, 179.9], [0.01, 0.0, -180.0]],
                        dtype=torch.float64)
    # More than 1/32 as many actions as nodes: IP2 over the whole grid instead.
    many = _raw_actions((700,), seed=13) * torch.tensor([3.0, 3.0, 400.0], dtype=torch.float64)
    for b in range(2):
        for actions in (near, wide, edge, many):
            assert _max_rel(m.score_grid_nodes(hidden[b], actions),
                            m.score_actions(grids[b], actions)) < 1e-12
    assert m.score_grid_nodes(hidden[:1], near).shape == (40,)
    with pytest.raises(ValueError, match="hidden"):
        m.score_grid_nodes(hidden, near)
    with pytest.raises(ValueError, match="grid head"):
        _model(config=CFG).grid_hidden(images)


def test_the_episode_scores_the_shipped_grid_net_at_its_needed_nodes():
    """The controller's `score_candidates` on the shipped (float32) grid net agrees with
    the whole grid's interpolation to float rounding."""
    import numpy as np

    from drake_grasp.policies.evaluator import load_cnn, score_candidates

    net = load_cnn("")
    assert net.grid
    rng = np.random.default_rng(12)
    depth = (0.25 + 0.1 * rng.random((64, 64))).astype(np.float32)
    actions = np.column_stack([rng.uniform(-0.04, 0.04, 128), rng.uniform(-0.04, 0.04, 128),
                               rng.uniform(-0.8, 0.8, 128)]).astype(np.float32)
    with torch.inference_mode():
        whole = net.score_actions(net.image_features(net.preprocess(depth))[0], actions)
    assert np.allclose(score_candidates(net, depth, actions), whole.numpy(), rtol=0, atol=1e-6)


def test_view_averaged_scores_interpolate_the_grid_averaged_over_the_turned_views():
    """`controller.view_average: d4` / `mirror`: the controller's scores (and the
    DistanceEvaluator's port) are the interpolation, at the candidates, of the mean of the
    8 (2) views' grids, each view's grid turned back by hand; "none" is the image as shown;
    with mirror_average, on a tiled paper net, or on an ONNX file, a clear error."""
    import numpy as np
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.sensors import ImageDepth32F

    from drake_grasp.core.assets import models_dir
    from drake_grasp.cnn.views import AUGMENTATIONS, turn_grids, turn_images
    from drake_grasp.cnn.grid_head import grid_scores
    from drake_grasp.cnn.net_config import action_features
    from drake_grasp.policies.evaluator import DistanceEvaluator, load_cnn, score_candidates

    net = load_cnn("")
    rng = np.random.default_rng(7)
    depth = (0.3 - 0.08 * (rng.random((64, 64)) > 0.8)).astype(np.float32)
    depth[10:30, 20:28] = 0.22  # something the turns move
    actions = np.column_stack([rng.uniform(-0.04, 0.04, 64), rng.uniform(-0.04, 0.04, 64),
                               rng.uniform(-45, 45, 64)]).astype(np.float32)
    feats = action_features(actions, net.config)[None]
    with torch.inference_mode():
        shown = net.preprocess(depth).numpy()
        by_hand = {}
        for views in ("mirror", "d4"):
            grids = []
            for k, flip in AUGMENTATIONS[views]:
                g = net.image_features(torch.from_numpy(turn_images(shown, k, flip))).numpy()
                back = turn_grids(g, (-k) % 4, False)  # turn back, then flip back
                grids.append(turn_grids(back, 0, True) if flip else back)
            by_hand[views] = grid_scores(net.config, torch.from_numpy(np.mean(grids, axis=0)),
                                         feats)[0].numpy()
    plain = score_candidates(net, depth, actions)
    for views in ("mirror", "d4"):
        got = score_candidates(net, depth, actions, views=views)
        np.testing.assert_allclose(got, by_hand[views], rtol=0, atol=1e-6)
        assert np.abs(got - plain).max() > 1e-4  # the views differ
    np.testing.assert_array_equal(score_candidates(net, depth, actions, views="none"), plain)

    builder = DiagramBuilder()
    evaluator = builder.AddSystem(DistanceEvaluator(net, views="d4"))
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    image = ImageDepth32F(64, 64)
    image.mutable_data[:, :, 0] = depth
    sub = evaluator.GetMyContextFromRoot(context)
    evaluator.get_input_port(0).FixValue(sub, image)
    evaluator.get_input_port(1).FixValue(sub, actions.astype(float))
    np.testing.assert_allclose(evaluator.get_output_port(0).Eval(sub), by_hand["d4"],
                               rtol=0, atol=1e-6)

    with pytest.raises(ValueError, match="mirror_average and controller.view_average"):
        score_candidates(net, depth, actions, mirror=True, views="d4")
    paper = load_cnn(str(models_dir() / "cnn" / "weights.safetensors"))
    with pytest.raises(ValueError, match="view_average 'mirror': needs a grid-head torch net"):
        score_candidates(paper, depth, actions, views="mirror")


def test_an_episode_scores_with_the_views_and_refuses_a_net_without_a_grid(library):
    """`controller.view_average: d4` in an episode's diagram: the evaluator's port is the
    8-view score of the image and candidates it gets; with the tiled paper net the
    diagram is refused when it is built (not at the first decision), naming the setting;
    so is the DistanceEvaluator itself, and an ensemble with such a member."""
    import numpy as np

    from drake_grasp.core.assets import models_dir
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.scene import make_scene
    from drake_grasp.policies.evaluator import (CnnEnsemble, DistanceEvaluator, check_views,
                                               load_cnn, score_candidates)

    text = ("{seed: 3, policy: ctr, controller: {profile: robot, view_average: d4%s},"
            " scene: {object_ids: [can_000], pose: lying}}")
    scenario = load_scenario(scenario_name="isolation", scenario_text=text % "")
    ed = build_episode_diagram(scenario, make_scene(scenario.scene, 3, library), library)
    evaluator = ed.diagram.GetSubsystemByName("distance_evaluator")
    context = evaluator.GetMyContextFromRoot(ed.diagram.CreateDefaultContext())
    depth = evaluator.GetInputPort("depth_image").Eval(context).data[:, :, 0]
    actions = evaluator.GetInputPort("candidate_actions").Eval(context)
    got = evaluator.GetOutputPort("predicted_distances").Eval(context)
    net = load_cnn("")
    assert len(got) == len(actions) > 0
    np.testing.assert_allclose(got, score_candidates(net, depth, actions, views="d4"),
                               rtol=0, atol=1e-6)
    assert np.abs(got - score_candidates(net, depth, actions)).max() > 1e-5

    paper = str(models_dir() / "cnn" / "weights.safetensors")
    scenario = load_scenario(scenario_name="isolation",
                             scenario_text=text % (", weights: '%s'" % paper))
    with pytest.raises(ValueError, match="view_average 'd4': needs a grid-head torch net"):
        build_episode_diagram(scenario, make_scene(scenario.scene, 3, library), library)
    with pytest.raises(ValueError, match="needs a grid-head torch net"):
        DistanceEvaluator(load_cnn(paper), views="mirror")
    with pytest.raises(ValueError, match="needs a grid-head torch net"):
        check_views(CnnEnsemble([net, load_cnn(paper)]), "d4")
    check_views(CnnEnsemble([net, net]), "d4")  # grid members only: accepted
    check_views(load_cnn(paper), "none")


def test_view_average_is_checked_by_the_scenario():
    """`controller.view_average`: one of none / mirror / d4, and not together with
    mirror_average; each refused naming the key."""
    from drake_grasp.config.scenario import load_scenario

    assert load_scenario(scenario_text="controller: {view_average: d4}").controller.view_average == "d4"
    with pytest.raises(ValueError, match="controller.view_average: got 'd8', expected one of"):
        load_scenario(scenario_text="controller: {view_average: d8}")
    with pytest.raises(ValueError, match="controller.view_average: got 'mirror' with "
                                         "controller.mirror_average true"):
        load_scenario(scenario_text="controller: {view_average: mirror, mirror_average: true}")


def test_an_ensemble_scores_the_mean_of_its_members():
    """`load_cnn("A,B")`: a `CnnEnsemble` whose distances are the mean of A's and B's (a
    grid head and a tiled net together), with mirror averaging applied to each member."""
    import numpy as np

    from drake_grasp.core.assets import models_dir
    from drake_grasp.policies.evaluator import (CnnEnsemble, load_cnn, needs_torch,
                                               score_candidates)

    grid, paper = (str(models_dir() / d / "weights.safetensors") for d in ("cnn-grid", "cnn"))
    ens = load_cnn(f"{grid},{paper}")
    assert isinstance(ens, CnnEnsemble) and len(ens.members) == 2
    assert ens.members[0].grid and not ens.members[1].grid
    rng = np.random.default_rng(3)
    depth = (0.25 + 0.1 * rng.random((64, 64))).astype(np.float32)
    actions = np.column_stack([rng.uniform(-0.04, 0.04, 16), rng.uniform(-0.04, 0.04, 16),
                               rng.uniform(-45, 45, 16)]).astype(np.float32)
    for mirror in (False, True):
        a = score_candidates(ens.members[0], depth, actions, mirror=mirror)
        b = score_candidates(ens.members[1], depth, actions, mirror=mirror)
        assert np.abs(a - b).max() > 1e-4  # the members differ, so the mean is informative
        got = score_candidates(ens, depth, actions, mirror=mirror)
        assert np.allclose(got, 0.5 * (a + b), rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="empty item"):
        load_cnn(f"{grid},,{paper}")
    with pytest.raises(ValueError, match="itself an ensemble"):
        CnnEnsemble([ens, ens.members[0]])
    with pytest.raises(ValueError, match="at least 2"):
        CnnEnsemble([ens.members[0]])
    assert needs_torch("") and needs_torch(f"x.onnx,{grid}") and not needs_torch("x.onnx,y.onnx")


def test_grid_starts_from_a_tiled_net_at_its_zero_action():
    from drake_grasp.learning.dense_training import init_from_tiled

    tiled = _model(seed=5, config=dataclasses.replace(CFG, theta_unit="deg"))
    grid = _model(seed=6, config=GRID)
    init_from_tiled(grid, tiled)
    images = _images(2, seed=7) * 0.3
    at_zero = tiled.forward(images, torch.zeros(2, 3, dtype=torch.float64))
    grids = grid.image_features(images)
    assert _max_rel(grids, at_zero[:, None, None, None].expand_as(grids)) < 1e-12
