"""The planar registration behind gpd-track (`policies.scene_tracking`): known motions of a
synthetic scene are recovered from a sparse wrist-like view."""

import numpy as np
import pytest

from drake_grasp.policies.scene_tracking import (Motion, SceneReference, compose, height_map,
                                                 moved_pose)

ANCHOR = np.array([0.5, 0.1])


def _heights(rel: np.ndarray) -> np.ndarray:
    """A box, a round blob and a ramp on a table at z = 0 (coordinates about the anchor)."""
    z = np.zeros(len(rel))
    z[(np.abs(rel[:, 0]) < 0.04) & (np.abs(rel[:, 1]) < 0.02)] = 0.05
    z[np.hypot(rel[:, 0] - 0.07, rel[:, 1] + 0.05) < 0.025] = 0.03
    ramp = (rel[:, 0] > -0.1) & (rel[:, 0] < -0.06) & (np.abs(rel[:, 1] - 0.05) < 0.03)
    z[ramp] = 0.02 + 0.3 * (rel[ramp, 0] + 0.1)
    return z


def _view(motion: Motion, *, half: float, centre=(0.0, 0.0), side: int) -> np.ndarray:
    """World points (3, N) on a side x side grid over the scene moved by `motion`."""
    g = np.linspace(-half, half, side)
    X, Y = np.meshgrid(g, g)
    pts = np.stack([X.ravel(), Y.ravel()], 1) + ANCHOR + np.asarray(centre)
    c, s = np.cos(np.deg2rad(motion.yaw_deg)), np.sin(np.deg2rad(motion.yaw_deg))
    R = np.array([[c, -s], [s, c]])
    before = (pts - ANCHOR - np.asarray(motion.xy_m)) @ R + ANCHOR  # the motion undone
    return np.vstack([pts.T, _heights(before - ANCHOR)])


@pytest.fixture(scope="module")
def reference():
    return SceneReference(_view(Motion(), half=0.3, side=400), ANCHOR, template_half_m=0.07,
                          search_m=0.1, cell_m=0.003)


@pytest.mark.parametrize("seed", range(6))
def test_a_moved_scene_is_found_to_within_2_mm_and_3_degrees(reference, seed):
    rng = np.random.default_rng(seed)
    truth = Motion(xy_m=tuple(rng.uniform(-0.08, 0.08, 2)), yaw_deg=rng.uniform(-30, 30))
    # A wrist camera's 64 x 64 view, not centred on the grasp.
    view = _view(truth, half=0.1, centre=0.8 * np.asarray(truth.xy_m), side=64)
    found = reference.register(view, prior=Motion(), yaw_range_deg=40, yaw_step_deg=3)
    assert found is not None
    assert np.hypot(*(np.subtract(found.xy_m, truth.xy_m))) < 0.002, (found, truth)
    assert abs(found.yaw_deg - truth.yaw_deg) < 3.0, (found, truth)
    assert found.rms_m < 0.015


def test_a_still_scene_is_found_still(reference):
    found = reference.register(_view(Motion(), half=0.1, side=64), prior=Motion(),
                               yaw_range_deg=40, yaw_step_deg=3)
    assert np.hypot(*found.xy_m) < 0.002 and abs(found.yaw_deg) < 2.0, found


def test_a_featureless_view_keeps_the_prior():
    # A flat table seen in every cell (a view that misses cells prefers the shifts that
    # overlap most: unseen cells cost).
    g = np.arange(-0.2, 0.2, 0.002)
    X, Y = np.meshgrid(g + ANCHOR[0], g + ANCHOR[1])
    flat = np.vstack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    ref = SceneReference(flat, ANCHOR, template_half_m=0.05, search_m=0.05, cell_m=0.004)
    prior = Motion(xy_m=(0.01, -0.02), yaw_deg=5.0)
    found = ref.register(flat, prior=prior, yaw_range_deg=10, yaw_step_deg=5)
    assert np.allclose(found.xy_m, prior.xy_m, atol=0.005) and abs(found.yaw_deg - 5.0) < 3.0


def test_no_overlap_is_no_estimate(reference):
    far = np.array([[5.0, 5.1], [5.0, 5.1], [0.0, 0.0]])
    assert reference.register(far, prior=Motion(), yaw_range_deg=10, yaw_step_deg=5) is None


def test_moved_pose_moves_the_grasp_with_the_scene():
    X = np.eye(4)
    X[:3, 3] = [0.53, 0.08, 0.04]
    m = Motion(xy_m=(0.02, -0.01), yaw_deg=30.0)
    out = moved_pose(X, ANCHOR, m)
    assert np.allclose(out[:2, 3], m.apply(ANCHOR, X[:2, 3]))
    assert out[2, 3] == pytest.approx(0.04)
    assert np.rad2deg(np.arctan2(out[1, 0], out[0, 0])) == pytest.approx(30.0)
    # A composed motion is the two applied in turn.
    inner = Motion(xy_m=(0.005, 0.0), yaw_deg=-4.0)
    p = np.array([0.47, 0.12])
    assert np.allclose(compose(m, inner, 0.0, 1.0).apply(ANCHOR, p),
                       m.apply(ANCHOR, inner.apply(ANCHOR, p)))


def test_height_map_keeps_the_highest_point_per_cell():
    P = np.array([[0.0005, 0.0009, 0.0035], [0.0005, 0.0005, 0.0005], [0.01, 0.03, 0.02]])
    hm = height_map(P, (0.0, 0.0), 0.004, 0.002)
    assert hm.heights.shape == (4, 4)
    assert hm.heights[2, 2] == pytest.approx(0.03) and hm.known[2, 2]
    assert hm.heights[3, 2] == pytest.approx(0.02)
    assert hm.known.sum() == 2


def test_the_turns_searched_do_not_follow_a_wrong_prior(reference):
    """An estimate that wandered off (whole turns, on an elongated object) does not carry
    the search window with it: turns are searched within the range of none."""
    truth = Motion(xy_m=(0.02, -0.01), yaw_deg=10.0)
    view = _view(truth, half=0.1, side=64)
    found = reference.register(view, prior=Motion(yaw_deg=300.0), yaw_range_deg=40,
                               yaw_step_deg=3)
    assert abs(found.yaw_deg - 10.0) < 3.0 and np.hypot(*np.subtract(found.xy_m, truth.xy_m)) < 0.002
