"""`drake-grasp bench --only` takes groups and every key that bench prints."""

import functools
import json

import pytest

from drake_grasp.cli import bench
from drake_grasp.cli.main import main


def test_every_printed_key_names_its_group():
    for group, keys in bench.PRINTED_KEYS.items():
        assert group in bench.BENCHMARKS
        for key in keys:
            # A key that is also its group's name runs the whole group.
            expected = None if key == group else [key]
            assert bench.resolve_only([key]) == {group: expected}
    assert set(bench.PRINTED_KEYS) == set(bench.BENCHMARKS)


def test_a_key_runs_its_group_once_and_prints_only_that_key(monkeypatch, capsys):
    # The real CNN benchmark, one timing round instead of eight.
    monkeypatch.setitem(bench.BENCHMARKS, "cnn", functools.partial(bench.bench_cnn, rounds=1))
    assert main(["bench", "--only", "cnn_infer_ms_128,train_samples_per_s"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"cnn_infer_ms_128", "train_samples_per_s", "machine", "date"}
    assert out["cnn_infer_ms_128"] > 0 and out["train_samples_per_s"] > 0


def test_a_group_name_prints_the_whole_group(capsys, tmp_path):
    path = tmp_path / "b.json"
    assert main(["bench", "--only", "controller_step_ms", "--out", str(path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["controller_step_ms"] > 0 and out["controller_step_fcn_ms"] > 0
    assert json.loads(path.read_text()) == out


def test_a_group_that_prints_an_undeclared_key_is_an_error(monkeypatch):
    monkeypatch.setitem(bench.BENCHMARKS, "depth_frame_ms", lambda: {"depth_frame_ms": 1.0,
                                                                      "surprise": 2})
    with pytest.raises(RuntimeError, match="surprise"):
        bench.run_benchmarks(only=["depth_frame_ms"])


def test_an_unknown_key_is_named(capsys):
    assert main(["bench", "--only", "cnn_infer_ms_129"]) == 2
    err = capsys.readouterr().err
    assert "cnn_infer_ms_129" in err and "cnn_infer_ms_128" in err


def test_rss_slope_is_the_least_squares_growth_after_the_warmup():
    from drake_grasp.cli.bench_scaling import rss_slope_mb

    rss = [900.0] * 3 + [400.0 + 2.5 * k for k in range(20)]
    assert rss_slope_mb(rss, warmup=3) == pytest.approx(2.5)
    with pytest.raises(ValueError, match="expected more than 4 samples, got 4"):
        rss_slope_mb(rss[:4], warmup=3)


@pytest.mark.slow
def test_a_worker_series_runs_forked_trials_and_reads_its_memory():
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from drake_grasp.cli.bench_scaling import worker_series

    # In a fresh worker, as the bench runs it (this process may have rendered, and then
    # does not fork its trials).
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
        out = pool.submit(worker_series, 2, 3, True).result()
    assert len(out["rss_mb"]) == len(out["wall_s"]) == len(out["outcomes"]) == 2
    assert all(r > 50 for r in out["rss_mb"]) and out["child_max_rss_mb"] > out["rss_mb"][0]
    assert all(isinstance(o[0], bool) and o[2] > 0 for o in out["outcomes"])


@pytest.mark.slow
def test_the_overhead_fraction_is_a_share_of_the_trial():
    from drake_grasp.cli.bench_scaling import bench_trial_overhead

    out = bench_trial_overhead(seeds=(0,))
    detail = out["trial_overhead_fraction_detail"]
    assert 0.0 < out["trial_overhead_fraction"] < 1.0
    assert 0.0 < out["trial_overhead_fraction_profiled"] < 1.0
    assert 0.0 < detail["advance_cpp_s_per_trial"] < detail["advance_s_per_trial"]
    assert detail["advance_s_per_trial"] < detail["wall_s_per_trial"]
    assert 0.0 < detail["python_in_advance_s_per_trial"] < detail["advance_s_per_trial"]
    assert 0.0 < detail["advance_cpp_s_per_trial_profiled"] < detail["wall_s_per_trial_profiled"]
    assert detail["python_s_per_trial_profiled"]["cnn"] > 0.0


def test_the_callback_clock_times_the_python_systems_inside_the_advance_and_restores_them():
    from pydrake.systems.analysis import Simulator, Simulator_
    from pydrake.systems.framework import DiagramBuilder

    from drake_grasp.cli.bench_scaling import CallbackClock
    from drake_grasp.systems.gripper import GripperController

    original = (GripperController._UpdateRamp, Simulator_[float].AdvanceTo)
    with CallbackClock() as clock:
        builder = DiagramBuilder()
        gripper = builder.AddSystem(GripperController(
            kp=2000.0, closing_speed_m_s=0.1, initial_width_m=0.085, time_step=0.001))
        builder.ExportInput(gripper.get_input_port(0))
        builder.ExportInput(gripper.get_input_port(1))
        diagram = builder.Build()
        simulator = Simulator(diagram)
        context = simulator.get_mutable_context()
        diagram.get_input_port(0).FixValue(context, [0.0, 20.0])
        diagram.get_input_port(1).FixValue(context, [0.04, 0.04, 0.0, 0.0])
        gripper.GetOutputPort("desired_state").Eval(
            gripper.GetMyContextFromRoot(context))  # outside the advance: not counted
        assert clock.callbacks_s == 0.0
        simulator.AdvanceTo(0.2)  # 200 ramp updates
    assert 0.0 < clock.callbacks_s < clock.advance_s
    assert (GripperController._UpdateRamp, Simulator_[float].AdvanceTo) == original
