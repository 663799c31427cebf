"""The KinematicNoise system: the arm's execution error between a policy's command and
the station. The gaussian model's moves, their ramp and their draws; its place in the
episode Diagram."""

from __future__ import annotations

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from drake_grasp.config.scenario import load_scenario
from drake_grasp.config.sections import NoiseConfig
from drake_grasp.geometry.actions import action_between, apply_actions
from drake_grasp.policies.controller_state import hand_to_pose
from drake_grasp.systems.kinematic_noise import (
    NOISE_STREAM,
    KinematicNoise,
    MoveError,
    gaussian_noisy_displacement,
    move_error,
    next_move,
    planar,
)

START = (0.5, 0.0, 0.3, 10.0)


def _by_hand(seed: int, goals, scale: float = 0.4) -> np.ndarray:
    """Where the hand really ends after the believed moves through `goals`, computed
    move by move: each commanded displacement noised and applied where the hand was."""
    believed = np.array([START[0], START[1], START[3]])
    real = believed.copy()
    for k, goal in enumerate(goals, start=1):
        delta = action_between(believed, goal)
        rng = np.random.default_rng([seed, k, NOISE_STREAM])
        real = apply_actions(real, gaussian_noisy_displacement(delta, rng, scale)[None])[0]
        believed = np.asarray(goal, float)
    return real


def test_each_move_is_noised_where_the_hand_really_was():
    goals = [np.array([0.52, 0.01, 25.0]), np.array([0.55, -0.02, 5.0])]
    start = (START[0], START[1], START[3])
    state = MoveError(start, start)
    for goal in goals:
        state = next_move(state, goal, scale=0.4, seed=7)
    assert state.moves == 2
    real = np.asarray(state.goal) + np.asarray(state.error_goal)
    expected = _by_hand(7, goals)
    np.testing.assert_allclose(real[:2], expected[:2], atol=1e-12)
    assert (real[2] - expected[2] + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=1e-9)
    # The errors add up: the second move starts from the first one's error.
    assert state.error_start != (0.0, 0.0, 0.0)


def test_a_large_turn_error_keeps_the_hand_frame_of_the_next_move():
    """A draw that turns the hand more than 90 degrees off: the next move still goes
    where the real hand's frame points (the error is not folded by half a turn)."""
    start = (START[0], START[1], START[3])
    goals = [np.array([0.40, 0.10, 80.0]), np.array([0.45, 0.12, 85.0])]
    for seed in range(40):
        state = MoveError(start, start)
        for goal in goals:
            state = next_move(state, goal, scale=1.0, seed=seed)
        real = np.asarray(state.goal) + np.asarray(state.error_goal)
        np.testing.assert_allclose(real[:2], _by_hand(seed, goals, scale=1.0)[:2], atol=1e-12)


def test_the_error_ramps_in_along_the_move_and_a_pure_height_change_draws_nothing():
    start = (START[0], START[1], START[3])
    state = next_move(MoveError(start, start), (0.54, 0.0, 10.0), scale=0.4, seed=3)
    e1 = np.asarray(state.error_goal)
    assert np.any(e1 != 0.0)
    np.testing.assert_allclose(move_error(state, start), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(move_error(state, (0.52, 0.0, 10.0)), 0.5 * e1, atol=1e-12)
    np.testing.assert_allclose(move_error(state, (0.54, 0.0, 10.0)), e1)
    # The same planar goal (only the height changes): no new move, no new draw.
    assert next_move(state, (0.54, 0.0, 10.0), scale=0.4, seed=3) is state


def test_same_seed_same_noise_and_other_seeds_differ():
    start = (START[0], START[1], START[3])
    a = next_move(MoveError(start, start), (0.55, 0.02, 0.0), scale=0.4, seed=11)
    b = next_move(MoveError(start, start), (0.55, 0.02, 0.0), scale=0.4, seed=11)
    c = next_move(MoveError(start, start), (0.55, 0.02, 0.0), scale=0.4, seed=12)
    assert a == b and a.error_goal != c.error_goal


def test_the_system_reads_a_new_goal_after_the_policys_update_and_displaces_the_command():
    noise = KinematicNoise(noise=NoiseConfig(kind="gaussian"), seed=5,
                           X_WG_start=hand_to_pose(START), period_s=0.2)
    sim = Simulator(noise)
    ctx = sim.get_mutable_context()
    goal = (0.53, 0.02, 0.25, 20.0)
    noise.GetInputPort("X_WG_goal").FixValue(ctx, hand_to_pose(goal))
    noise.GetInputPort("X_WG_commanded").FixValue(ctx, hand_to_pose(START))
    sim.Initialize()
    sim.AdvanceTo(0.1)
    state = noise.get_move_error(ctx)
    assert state.moves == 1
    # At the move's start the hand is still where it was; at its goal, off by the error.
    np.testing.assert_allclose(noise.GetOutputPort("X_WG_desired").Eval(ctx).GetAsMatrix4(),
                               hand_to_pose(START).GetAsMatrix4(), atol=1e-12)
    noise.GetInputPort("X_WG_commanded").FixValue(ctx, hand_to_pose(goal))
    X = noise.GetOutputPort("X_WG_desired").Eval(ctx)
    real = planar(X)
    expected = _by_hand(5, [np.array([goal[0], goal[1], goal[3]])])
    np.testing.assert_allclose(real[:2], expected[:2], atol=1e-12)
    assert X.translation()[2] == pytest.approx(goal[2])  # the height is not noised


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="noise.kind"):
        KinematicNoise(noise=NoiseConfig(kind="none"), seed=0, X_WG_start=hand_to_pose(START),
                       period_s=0.2)
    with pytest.raises(ValueError, match="offset_s"):
        KinematicNoise(noise=NoiseConfig(kind="gaussian"), seed=0,
                       X_WG_start=hand_to_pose(START), period_s=0.2, offset_s=0.3)


@pytest.mark.parametrize("kind", ["none", "gaussian", "offset"])
def test_the_episode_puts_the_noise_between_the_controller_and_the_station(kind, library):
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.world.scene import make_scene

    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        f"{{seed: 0, policy: ctr, noise: {{kind: {kind}}}, "
        "scene: {object_ids: [can_000], pose: lying}}"))
    scene = make_scene(scenario.scene, scenario.seed, library, physics=scenario.physics)
    diagram = build_episode_diagram(scenario, scene, library).diagram
    feeds = {(dst.get_name(), dst.get_input_port(i).get_name()):
             (src.get_name(), src.get_output_port(j).get_name())
             for (dst, i), (src, j) in diagram.connection_map().items()}
    if kind == "none":
        assert not diagram.HasSubsystemNamed("kinematic_noise")
        assert feeds[("station", "X_WG_desired")] == ("controller", "X_WG_desired")
    else:
        assert feeds[("station", "X_WG_desired")] == ("kinematic_noise", "X_WG_desired")
        assert feeds[("kinematic_noise", "X_WG_commanded")] == ("controller", "X_WG_desired")
        assert feeds[("kinematic_noise", "X_WG_goal")] == ("controller", "X_WG_goal")
