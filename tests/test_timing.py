"""Timing and calibration of the loop: the FrameBuffer (latency, dropped frames), the
camera-mount error, their scenario keys and sweep experiments, one episode with all."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.sensors import ImageDepth32F

from drake_grasp.evaluation.experiments import condition_scenario, get_experiment
from drake_grasp.config.scenario import load_scenario
from drake_grasp.config.sections import CalibrationConfig
from drake_grasp.systems.frames import FrameBuffer, frame_dropped


class _ClockImage(LeafSystem):
    """A 2x3 depth image filled with the current time."""

    def __init__(self):
        super().__init__()
        self.DeclareAbstractOutputPort("image", lambda: AbstractValue.Make(ImageDepth32F(3, 2)),
                                       self._Calc)

    def _Calc(self, context, output):
        image = ImageDepth32F(3, 2)
        image.mutable_data[:] = context.get_time()
        output.set_value(image)


class _Probe(LeafSystem):
    """Reads its input at its periodic unrestricted update, as the GraspController does
    (so it sees the pre-update values of systems updated at the same instant)."""

    def __init__(self, period_s):
        super().__init__()
        self._in = self.DeclareAbstractInputPort("image", AbstractValue.Make(ImageDepth32F()))
        self._log = self.DeclareAbstractState(AbstractValue.Make(()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, 0.0, self._Update)

    def _Update(self, context, state):
        log = context.get_abstract_state(int(self._log)).get_value()
        value = float(self._in.Eval(context).data[0, 0, 0])
        state.get_mutable_abstract_state(int(self._log)).set_value(
            log + ((context.get_time(), value),))

    def log(self, context):
        return context.get_abstract_state(int(self._log)).get_value()


def _run(period, latency, prob, seed=0, until=1.05):
    builder = DiagramBuilder()
    clock = builder.AddSystem(_ClockImage())
    frames = builder.AddSystem(FrameBuffer(ImageDepth32F(), period_s=period, latency_s=latency,
                                           dropped_frame_prob=prob, seed=seed))
    probe = builder.AddSystem(_Probe(period))
    builder.Connect(clock.get_output_port(), frames.GetInputPort("image"))
    builder.Connect(frames.GetOutputPort("image"), probe.GetInputPort("image"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.Initialize()
    simulator.AdvanceTo(until)
    return probe.log(probe.GetMyContextFromRoot(simulator.get_context()))


@pytest.mark.parametrize("latency", [0.0, 0.05, 0.15, 0.2, 0.3])
def test_policy_sees_the_frame_taken_latency_earlier(latency):
    log = _run(0.1, latency, 0.0)
    assert len(log) >= 10
    for t, seen in log:
        expected = max(0.0, t - latency)  # before the start: the start image
        assert seen == pytest.approx(expected, abs=1e-6), (t, seen)


def test_dropped_frames_hold_the_last_frame_that_arrived():
    period, latency, prob, seed = 0.1, 0.05, 0.4, 3
    log = _run(period, latency, prob, seed=seed, until=3.05)
    # Capture j at 0.05 + 0.1 j is frame j + 1 (frame 0: the start image, never lost).
    arrived = [0.0] + [0.05 + 0.1 * j for j in range(40) if not frame_dropped(seed, j + 1, prob)]
    dropped = 0
    for t, seen in log:
        expected = max([c for c in arrived if c <= t - latency + 1e-9], default=0.0)
        assert seen == pytest.approx(expected, abs=1e-6), (t, seen)
        dropped += seen < t - latency - 1e-6
    # About 40% of ~30 ticks see a stale frame: the drops really happen.
    assert 5 <= dropped <= 25
    assert log == _run(period, latency, prob, seed=seed, until=3.05)  # same seed, same drops
    assert log != _run(period, latency, prob, seed=seed + 1, until=3.05)


def test_frame_buffer_rejects_bad_settings():
    with pytest.raises(ValueError, match="dropped_frame_prob"):
        FrameBuffer(ImageDepth32F(), period_s=0.1, latency_s=0.0, dropped_frame_prob=1.0, seed=0)
    with pytest.raises(ValueError, match="period_s"):
        FrameBuffer(ImageDepth32F(), period_s=0.0, latency_s=0.0, dropped_frame_prob=0.0, seed=0)


@pytest.mark.parametrize("key,value", [("timing.latency_s", -0.1), ("timing.latency_s", 5.0),
                                       ("timing.dropped_frame_prob", 1.0),
                                       ("calibration.camera_translation_error_m", 0.2),
                                       ("calibration.camera_rotation_error_deg", -1.0)])
def test_bad_timing_and_calibration_values_are_named(key, value):
    section, name = key.split(".")
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        load_scenario(scenario_name="isolation", scenario_text=f"{{{section}: {{{name}: {value}}}}}")


def test_camera_mount_error_moves_the_cameras_not_the_belief(library):
    from drake_grasp.world.scene import make_scene
    from drake_grasp.world.station import MakeGraspStation, camera_mount_error

    text = "{seed: 5, scene: {object_ids: [can_000], pose: lying}}"
    nominal_scenario = load_scenario(scenario_name="isolation", scenario_text=text)
    scene = make_scene(nominal_scenario.scene, 5, library)
    off_scenario = load_scenario(scenario_name="isolation", scenario_text=text[:-1] + (
        ", calibration: {camera_translation_error_m: 0.01, camera_rotation_error_deg: 2.0}}"))
    nominal = MakeGraspStation(nominal_scenario, scene, library)
    off = MakeGraspStation(off_scenario, scene, library)
    X_err = camera_mount_error(off_scenario.calibration, 5)
    assert np.linalg.norm(X_err.translation()) == pytest.approx(0.01)
    assert np.rad2deg(X_err.rotation().ToAngleAxis().angle()) == pytest.approx(2.0)
    assert off.X_CC_actual.IsExactlyEqualTo(X_err)
    assert nominal.X_CC_actual.IsExactlyIdentity()
    # What the policy is told (X_GC) is the nominal mount in both.
    assert off.X_GC.IsExactlyEqualTo(nominal.X_GC)
    for name in ("wrist_camera", "gpd_camera"):
        X_nominal = nominal.diagram.GetSubsystemByName(name).default_X_PB()
        X_off = off.diagram.GetSubsystemByName(name).default_X_PB()
        assert X_off.IsNearlyEqualTo(X_nominal @ X_err, 1e-12)
        assert not X_off.IsNearlyEqualTo(X_nominal, 1e-3)
    # A different seed draws a different direction.
    other = camera_mount_error(CalibrationConfig(0.01, 2.0), 6)
    assert not other.IsNearlyEqualTo(X_err, 1e-3)
    assert camera_mount_error(CalibrationConfig(), 6).IsNearlyEqualTo(RigidTransform(), 0.0)


@pytest.mark.parametrize("name,key", [("sweep-latency", "timing.latency_s"),
                                      ("sweep-control-period", "controller.period_s"),
                                      ("sweep-dropped-frames", "timing.dropped_frame_prob"),
                                      ("sweep-camera-translation",
                                       "calibration.camera_translation_error_m"),
                                      ("sweep-camera-rotation",
                                       "calibration.camera_rotation_error_deg")])
def test_sweeps_set_what_they_name(name, key):
    experiment = get_experiment(name)
    policies = {c.policy for c in experiment.conditions}
    assert policies == {"ctr", "gpd"}
    seen = set()
    for condition in experiment.conditions:
        value = float(condition.name.split("=")[1])
        s = condition_scenario(experiment, condition)
        section, field = key.split(".")
        assert getattr(getattr(s, section), field) == pytest.approx(value), condition.name
        assert s.controller.profile == "robot"
        seen.add(value)
    assert len(seen) >= 4


def test_latency_drops_and_mount_error_reach_the_episode(library):
    """One short CTR episode with all three: the frame buffer sits in front of the
    controller and the evaluator, the mount error is recorded, and the same seed gives
    the same trial."""
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.world.scene import make_scene

    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 2, policy: ctr, max_sim_time_s: 1.2, controller: {profile: robot},"
        " scene: {object_ids: [can_000], pose: lying},"
        " timing: {latency_s: 0.15, dropped_frame_prob: 0.3},"
        " calibration: {camera_translation_error_m: 0.005, camera_rotation_error_deg: 1.0}}"))
    ed = build_episode_diagram(scenario, make_scene(scenario.scene, 2, library), library)
    assert ed.diagram.HasSubsystemNamed("depth_image_frames")
    assert not ed.diagram.HasSubsystemNamed("gpd_depth_image_frames")  # ctr never reads it
    a = simulate_episode(scenario, library=library, record_depth=False)
    b = simulate_episode(scenario, library=library, record_depth=False)
    assert a.result.control_steps >= 5
    assert np.array_equal(a.final_plant_state, b.final_plant_state)
    error = a.result.details["camera_mount_error"]
    assert np.linalg.norm(error["xyz"]) == pytest.approx(0.005)


def test_interleaved_sweeps_cover_every_test_object_in_their_first_trials(library):
    from drake_grasp.evaluation.experiments import trial_scenario

    experiment = get_experiment("sweep-latency")
    condition = experiment.conditions[0]
    first = [trial_scenario(experiment, condition, i, base_seed=0, library=library).scene
             for i in range(10)]
    assert len({tuple(s.object_ids) for s in first}) == 10
    assert {s.pose for s in first} == {"lying"}
    later = trial_scenario(experiment, condition, 30, base_seed=0, library=library).scene
    assert later.pose == "upright"
    # The blocked order of the Table 1 isolation experiment is unchanged: 4 per object.
    iso = get_experiment("isolation")
    blocked = [trial_scenario(iso, iso.conditions[0], i, base_seed=0, library=library).scene
               for i in range(4)]
    assert len({tuple(s.object_ids) for s in blocked}) == 1
    assert [s.pose for s in blocked] == ["lying"] * 3 + ["upright"]


def test_latency_sweep_runs_through_evaluate_and_plots(tmp_path):
    """The path a user takes: `evaluate --experiment sweep-latency` (two CTR points, one
    trial each) -> records carrying the latency, a report with the sweep picture."""
    from drake_grasp.cli.main import main
    from drake_grasp.evaluation.records import load_records

    out = tmp_path / "sweep"
    main(["evaluate", "--experiment", "sweep-latency", "--trials", "1", "--workers", "1",
          "--seed", "0", "--out", str(out), "--conditions", "ctr/latency_s=0,ctr/latency_s=0.3"])
    records = {r.condition: r for r in load_records(out)}
    assert set(records) == {"ctr/latency_s=0", "ctr/latency_s=0.3"}
    assert "latency_s: 0.3" in records["ctr/latency_s=0.3"].scenario_yaml
    for r in records.values():
        assert r.failure_class != "simulation-error", r.failure_reason
    assert (out / "sweep_latency_s.png").stat().st_size > 1000
    assert "sweep over latency_s" in (out / "report.md").read_text()
