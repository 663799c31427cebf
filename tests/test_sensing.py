"""Tests of the depth noise model, the hole filter and DepthPostProcessor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydrake.systems.sensors import ImageDepth32F

from drake_grasp.geometry.sensing import (
    INVALID_DEPTH,
    DepthNoiseConfig,
    apply_depth_noise,
    fill_invalid_depth,
    frame_rng,
    postprocess_depth,
)
from drake_grasp.systems import DepthPostProcessor

FAR = 2.0


def _gaussian_only(**overrides) -> DepthNoiseConfig:
    fields = dict(enabled=True, edge_dropout_prob=0.0, random_dropout_prob=0.0)
    fields.update(overrides)
    return DepthNoiseConfig(**fields)


# --- fill_invalid_depth ------------------------------------------------------


def test_fill_single_hole_takes_neighbourhood_max():
    depth = np.array(
        [
            [0.5, 0.5, 0.5, 0.5, 0.5],
            [0.5, 0.3, 0.4, 0.2, 0.5],
            [0.5, 0.1, 0.0, 0.7, 0.5],
            [0.5, 0.2, 0.3, 0.6, 0.5],
            [0.5, 0.5, 0.5, 0.5, 0.5],
        ],
        dtype=np.float32,
    )
    out = fill_invalid_depth(depth, max_iterations=10, far_value_m=FAR)
    expected = depth.copy()
    expected[2, 2] = 0.7  # max of the 8 neighbours; the 0.5 border is not adjacent
    np.testing.assert_array_equal(out, expected)
    assert out.dtype == np.float32
    assert depth[2, 2] == 0.0  # input untouched


def test_fill_multi_iteration_grows_from_valid_pixels():
    depth = np.zeros((5, 5), dtype=np.float32)
    depth[0, 0] = 0.4
    depth[4, 4] = 0.9
    out = fill_invalid_depth(depth, max_iterations=10, far_value_m=FAR)
    # Iteration k fills Chebyshev distance k; where both fronts arrive in the
    # same iteration the max wins, and a later front never overwrites.
    cheb_a = np.maximum.outer(np.arange(5), np.arange(5))
    cheb_b = np.maximum.outer(4 - np.arange(5), 4 - np.arange(5))
    expected = np.where(cheb_b <= cheb_a, 0.9, 0.4).astype(np.float32)
    np.testing.assert_array_equal(out, expected)


def test_fill_stops_after_max_iterations_and_uses_far_value():
    depth = np.zeros((1, 6), dtype=np.float32)
    depth[0, 0] = 0.5
    out = fill_invalid_depth(depth, max_iterations=2, far_value_m=FAR)
    np.testing.assert_array_equal(out, [[0.5, 0.5, 0.5, FAR, FAR, FAR]])


def test_fill_all_invalid_becomes_far_value():
    for bad in (0.0, np.nan, -np.inf, -1.0):
        out = fill_invalid_depth(np.full((4, 3), bad, np.float32), 64, FAR)
        np.testing.assert_array_equal(out, np.full((4, 3), FAR, np.float32))


def test_fill_inf_is_far_value_not_filled():
    depth = np.full((3, 3), 0.5, np.float32)
    depth[1, 1] = np.inf
    depth[0, 0] = 0.0  # next to the far pixel: takes far as the max neighbour
    out = fill_invalid_depth(depth, 8, FAR)
    assert out[1, 1] == np.float32(FAR)
    assert out[0, 0] == np.float32(FAR)
    assert np.all(np.isfinite(out))


def test_fill_keeps_drake_channel_shape():
    out = fill_invalid_depth(np.zeros((4, 5, 1), np.float32), 3, FAR)
    assert out.shape == (4, 5, 1)


# --- apply_depth_noise -------------------------------------------------------


@pytest.mark.parametrize("z", [0.3, 0.8, 1.5])
def test_gaussian_noise_std_matches_model(z):
    config = _gaussian_only()
    depth = np.full((200, 200), z, np.float32)
    noisy = apply_depth_noise(depth, frame_rng(7, 0), config)
    assert np.all(noisy > 0.0)
    std = float(np.std(noisy.astype(np.float64) - z))
    expected = config.sigma_at(z)
    assert abs(std - expected) < 0.1 * expected
    if z > 0.4:
        # Nguyen et al. 2012 directly.
        assert expected == pytest.approx(0.0012 + 0.0019 * (z - 0.4) ** 2)


def test_noise_grows_with_depth():
    config = _gaussian_only()
    stds = []
    for z in (0.5, 1.0, 2.0, 3.0):
        noisy = apply_depth_noise(np.full((100, 100), z, np.float32), frame_rng(1, 0), config)
        stds.append(float(np.std(noisy.astype(np.float64) - z)))
    assert all(a < b for a, b in zip(stds, stds[1:]))


def test_edge_dropout_only_near_discontinuities():
    config = DepthNoiseConfig(enabled=True, edge_dropout_prob=1.0, random_dropout_prob=0.0)
    flat = np.full((32, 32), 0.5, np.float32)
    assert np.all(apply_depth_noise(flat, frame_rng(0, 0), config) > 0.0)

    step = flat.copy()
    step[:, 16:] = 0.7  # a 20 cm jump between columns 15 and 16
    noisy = apply_depth_noise(step, frame_rng(0, 0), config)
    dropped = noisy == INVALID_DEPTH
    assert np.all(dropped[:, 15:17])
    assert not np.any(dropped[:, :15]) and not np.any(dropped[:, 17:])


def test_random_dropout_rate():
    config = DepthNoiseConfig(enabled=True, random_dropout_prob=0.1, edge_dropout_prob=0.0)
    noisy = apply_depth_noise(np.full((200, 200), 0.5, np.float32), frame_rng(3, 0), config)
    assert np.mean(noisy == INVALID_DEPTH) == pytest.approx(0.1, abs=0.01)


def test_noise_marks_invalid_and_keeps_far():
    depth = np.full((4, 4), 0.5, np.float32)
    depth[0, 0] = np.nan
    depth[1, 1] = 0.0
    depth[2, 2] = np.inf
    noisy = apply_depth_noise(depth, frame_rng(0, 0), _gaussian_only())
    assert noisy[0, 0] == INVALID_DEPTH and noisy[1, 1] == INVALID_DEPTH
    assert np.isposinf(noisy[2, 2])


def test_disabled_noise_is_a_copy():
    depth = np.random.default_rng(0).uniform(0.2, 1.0, (8, 8)).astype(np.float32)
    out = apply_depth_noise(depth, frame_rng(0, 0), DepthNoiseConfig())
    np.testing.assert_array_equal(out, depth)
    assert out is not depth


def test_same_seed_and_frame_reproduce_and_other_frame_differs():
    config = DepthNoiseConfig(enabled=True)
    depth = np.full((64, 64), 0.5, np.float32)
    depth[20:40, 20:40] = 0.4
    a = postprocess_depth(depth, frame_rng(0, 5), config, FAR)
    b = postprocess_depth(depth, frame_rng(0, 5), config, FAR)
    c = postprocess_depth(depth, frame_rng(0, 6), config, FAR)
    d = postprocess_depth(depth, frame_rng(1, 5), config, FAR)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a, d)


def test_postprocess_output_is_finite_float32_same_shape():
    depth = np.full((64, 64, 1), 0.5, np.float32)
    depth[:5] = 0.0
    depth[-5:] = np.inf
    depth[30, 30] = np.nan
    for config in (DepthNoiseConfig(), DepthNoiseConfig(enabled=True)):
        out = postprocess_depth(depth, frame_rng(2, 0), config, FAR)
        assert out.shape == depth.shape and out.dtype == np.float32
        assert np.all(np.isfinite(out)) and np.all(out > 0.0)


def test_postprocess_enabled_requires_rng():
    with pytest.raises(ValueError, match="rng"):
        postprocess_depth(np.ones((2, 2)), None, DepthNoiseConfig(enabled=True), FAR)


# --- validation ---------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("sigma_base_m", -0.001),
        ("sigma_quadratic_per_m2", float("nan")),
        ("sigma_reference_depth_m", -1.0),
        ("edge_threshold_m", 0.0),
        ("edge_dropout_prob", 1.5),
        ("random_dropout_prob", -0.1),
        ("fill_max_iterations", -1),
        ("fill_max_iterations", 2.5),
        ("enabled", "yes"),
    ],
)
def test_validation_names_field(field, value):
    config = dataclasses.replace(DepthNoiseConfig(), **{field: value})
    with pytest.raises(ValueError, match=field):
        config.validate()


def test_defaults_are_valid():
    DepthNoiseConfig().validate()
    DepthNoiseConfig(enabled=True).validate()


def test_frame_rng_rejects_negative():
    with pytest.raises(ValueError, match="seed"):
        frame_rng(-1, 0)
    with pytest.raises(ValueError, match="frame_index"):
        frame_rng(0, -1)


# --- DepthPostProcessor --------------------------------------------------------


def _make_system(config: DepthNoiseConfig, seed: int = 0):
    system = DepthPostProcessor(
        config, width=6, height=5, far_value_m=FAR, frame_period_s=0.1, seed=seed
    )
    context = system.CreateDefaultContext()
    return system, context


def _fix_input(system, context, depth: np.ndarray) -> None:
    image = ImageDepth32F(depth.shape[1], depth.shape[0])
    image.mutable_data[:, :, 0] = depth
    system.get_input_port().FixValue(context, image)


def _eval(system, context) -> np.ndarray:
    return np.array(system.get_output_port().Eval(context).data[:, :, 0])


def test_system_ports():
    system, _ = _make_system(DepthNoiseConfig())
    assert system.get_input_port().get_name() == "depth_image_32f"
    assert system.get_output_port().get_name() == "depth_image"


def test_system_fills_hole_with_neighbourhood_max():
    system, context = _make_system(DepthNoiseConfig())
    depth = np.full((5, 6), 0.5, np.float32)
    depth[2, 2] = 0.0
    depth[1, 3] = 0.8
    depth[0, 5] = np.inf
    _fix_input(system, context, depth)
    out = _eval(system, context)
    expected = depth.copy()
    expected[2, 2] = 0.8
    expected[0, 5] = FAR
    np.testing.assert_array_equal(out, expected)


def test_system_seed_parameter_controls_noise():
    system, context = _make_system(DepthNoiseConfig(enabled=True), seed=0)
    assert system.get_seed(context) == 0
    depth = np.full((5, 6), 0.5, np.float32)
    _fix_input(system, context, depth)
    context.SetTime(0.3)
    first = _eval(system, context)
    assert not np.array_equal(first, depth)

    system.set_seed(context, 1)
    assert system.get_seed(context) == 1
    other = _eval(system, context)
    assert not np.array_equal(first, other)

    system.set_seed(context, 0)
    np.testing.assert_array_equal(_eval(system, context), first)
    # A fresh context with the same seed and time reproduces it bit for bit, and
    # it is exactly the library pipeline for frame round(0.3 / 0.1) = 3.
    fresh_system, fresh = _make_system(DepthNoiseConfig(enabled=True), seed=0)
    _fix_input(fresh_system, fresh, depth)
    fresh.SetTime(0.3)
    np.testing.assert_array_equal(_eval(fresh_system, fresh), first)
    library = postprocess_depth(depth, frame_rng(0, 3), DepthNoiseConfig(enabled=True), FAR)
    np.testing.assert_array_equal(first, library)

    context.SetTime(0.4)
    assert not np.array_equal(_eval(system, context), first)


def test_system_rejects_bad_arguments():
    with pytest.raises(ValueError, match="edge_dropout_prob"):
        _make_system(DepthNoiseConfig(edge_dropout_prob=2.0))
    with pytest.raises(ValueError, match="frame_period_s"):
        DepthPostProcessor(
            DepthNoiseConfig(), width=4, height=4, far_value_m=FAR, frame_period_s=0.0
        )
    system, context = _make_system(DepthNoiseConfig())
    with pytest.raises(ValueError, match="seed"):
        system.set_seed(context, -1)
