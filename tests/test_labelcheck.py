"""Label check: summary arithmetic, resume, a refused different run, and the gravity-torque
test of the ground truth."""

import dataclasses
import json

import numpy as np
import pytest


def _record(index, checks):
    from drake_grasp.evaluation.labelcheck import FORMAT

    return {"format": FORMAT, "scene_index": index, "seed": index, "replaced_attempts": [],
            "scene": {}, "num_accepted": 5, "num_rejected": 1, "checks": checks, "wall_s": 1.0}


def _check(kind, category, held, failure=""):
    return {"kind": kind, "category": category, "held": held, "failure": failure}


def test_summary_counts_precision_per_category_and_leaves_out_simulation_errors():
    from drake_grasp.evaluation.labelcheck import summarize

    records = [
        _record(0, [_check("accepted", "can", True), _check("accepted", "can", False, "missed"),
                    _check("rejected", "can", True)]),
        _record(1, [_check("accepted", "mug", True),
                    _check("accepted", "mug", False, "dropped-by-shake"),
                    _check("accepted", "mug", False, "simulation-error"),
                    _check("rejected", "mug", False, "missed")]),
    ]
    s = summarize(records)
    assert (s["checked"], s["held"]) == (4, 2)
    assert s["precision"] == pytest.approx(0.5)
    assert s["precision_lift_hold"] == pytest.approx(0.75)  # the shake failure held the lift
    assert (s["rejected_checked"], s["rejected_held"]) == (2, 1)
    assert s["simulation_errors"] == 1
    assert s["per_category"]["can"]["checked"] == 2 and s["per_category"]["mug"]["held"] == 1
    assert s["failures"]["missed"] == 1 and s["failures"]["dropped-by-shake"] == 1
    lo, hi = s["precision_ci95"]
    assert 0.0 < lo < 0.5 < hi < 1.0


def test_gravity_torque_ratio_of_an_off_centre_grasp():
    """A 1 kg box grasped 5 cm beside its centre of mass: the worst load about the contact
    axis is gravity plus the lab's downward shake acceleration on a 5 cm lever; over
    F (r1 + r2) that is the friction the pads need. A centred grasp only needs what the
    sideways shake asks of the ~5 mm between the contact patches' centroid (the face
    from the box's top at 42 mm down to the pads' ends at 11 mm, centroid ~27 mm
    high) and the centre of mass (22 mm high)."""
    import trimesh

    from drake_grasp.geometry.contact_physics import (
        GRAVITY_M_S2,
        SHAKE_ACCELERATION_M_S2,
    )
    from drake_grasp.geometry.hand_checks import check_grasp_poses
    from drake_grasp.geometry.hand_model import topdown_rotation
    from drake_grasp.geometry.scene_samples import (
        ObjectMasses,
        sample_scene_points,
    )

    box = trimesh.creation.box((0.04, 0.20, 0.04))
    box.apply_translation([0.5, 0.0, 0.022])
    rng = np.random.default_rng(0)
    pts = sample_scene_points([box], rng, spacing_m=0.002)
    objects = ObjectMasses(np.array([1.0]), np.array([[0.5, 0.0, 0.022]]))
    poses = []
    for offset in (0.0, 0.05):
        X = np.eye(4)
        X[:3, :3] = topdown_rotation(0.0)  # closing along world x, across the 4 cm side
        X[:3, 3] = [0.5, offset, 0.03]
        poses.append(X)
    check = check_grasp_poses(np.array(poses), pts, objects=objects, grip_force_n=10.0)
    assert check.force_closure.all()
    # Each patch is the face under the pad: 22 mm across (the pad's width) by 31 mm along
    # the approach (the box's top at z = 42 mm down to the pad's end at 11 mm); the RMS
    # radius of a uniform rectangle of half sides a, b is sqrt((a^2 + b^2) / 3).
    lever = 10.0 * 2 * np.sqrt((0.011**2 + 0.0155**2) / 3.0)
    centred, offset = check.torque_ratio
    assert centred == pytest.approx(SHAKE_ACCELERATION_M_S2 * 0.005 / lever, rel=0.3)
    assert offset == pytest.approx((GRAVITY_M_S2 + SHAKE_ACCELERATION_M_S2) * 0.05 / lever,
                                   rel=0.1)
    limited = check_grasp_poses(np.array(poses), pts, objects=objects, grip_force_n=10.0,
                                max_torque_ratio=1.0)
    assert limited.valid.tolist() == [True, False]


@pytest.mark.slow
def test_label_check_runs_resumes_and_refuses_another_run(tmp_path, library):
    from drake_grasp.evaluation.labelcheck import LabelCheckConfig, run_label_check
    from drake_grasp.config.scenario import Scenario

    out = tmp_path / "lc"
    config = LabelCheckConfig(grasps_per_scene=1, rejected_per_scene=0)
    summary = run_label_check(num_scenes=1, seed=3, out=out, scenario=Scenario(),
                              library=library, config=config, show_progress=False)
    assert summary["scenes"] == 1 and summary["checked"] == 1
    assert summary["held"] in (0, 1) and summary["precision"] in (0.0, 1.0)
    # The run ends packed: its scene files moved into one table.
    from drake_grasp.evaluation.labelcheck import read_records

    assert not (out / "scenes").exists()
    record = out / "scenes.parquet"
    check = read_records(out)[0]["checks"][0]
    assert check["kind"] == "accepted" and check["details"]["grip_force_n"] == 60.0
    assert (out / "report.md").read_text().startswith("# Label check")
    stamp = record.stat().st_mtime_ns
    again = run_label_check(num_scenes=1, seed=3, out=out, scenario=Scenario(),
                            library=library, config=config, show_progress=False)
    assert record.stat().st_mtime_ns == stamp  # resumed: nothing re-run
    assert again["checked"] == 1
    with pytest.raises(ValueError, match="seed: 3 in the folder, 4 now"):
        run_label_check(num_scenes=1, seed=4, out=out, scenario=Scenario(), library=library,
                        config=config, show_progress=False)


def test_displaced_pose_has_the_asked_metric_distance():
    from drake_grasp.geometry.grasp_metric import grasp_distance
    from drake_grasp.geometry.hand_model import topdown_rotation
    from drake_grasp.evaluation.tolerance import displaced_pose, random_offset

    X = np.eye(4)
    X[:3, :3] = topdown_rotation(np.deg2rad(30.0))
    X[:3, 3] = [0.5, 0.1, 0.04]
    rng = np.random.default_rng(0)
    for d in (0.0, 0.005, 0.02):
        offset = random_offset(rng, d)
        Y = displaced_pose(X, offset)
        assert Y[2, 3] == pytest.approx(0.04)  # same height
        yaw = lambda M: np.rad2deg(np.arctan2(M[1, 0], M[0, 0]))  # noqa: E731
        a = np.array([X[0, 3], X[1, 3], yaw(X)])
        b = np.array([Y[0, 3], Y[1, 3], yaw(Y)])
        assert float(grasp_distance(a, b)) == pytest.approx(d, abs=1e-9)


@pytest.mark.slow
def test_grasp_tolerance_runs_and_an_undisplaced_grasp_holds(tmp_path, library):
    """The 0 mm offset repeats the verified grasp: the lab is deterministic, so it holds."""
    from drake_grasp.config.scenario import Scenario
    from drake_grasp.evaluation.tolerance import run_grasp_tolerance

    summary = run_grasp_tolerance(num_scenes=1, seed=1, out=tmp_path / "tol", scenario=Scenario(),
                                  library=library, offsets_mm=[0.0, 40.0], show_progress=False)
    assert summary["scenes_with_verified_grasp"] == 1
    assert summary["by_offset_mm"]["0"] == {"n": 1, "held": 1, "success": 1.0,
                                            "ci95": pytest.approx([0.2065, 1.0], abs=1e-4)}
    assert summary["by_offset_mm"]["40"]["n"] == 1
    assert (tmp_path / "tol" / "tolerance.png").stat().st_size > 1000


def test_label_load_case_script_finds_the_static_grasps_the_shake_rejects(analysis_script):
    """analysis/label_load_case.py on isolation trial 25 (a lying hammer): no grasp
    survives the torque test with the shake among its load cases, the static load case
    alone admits some, and one of them is executed in the lab."""
    module = analysis_script("label_load_case")
    scene = module.run_scene(25, 0, 1)
    assert scene["object"] == "hammer_000"
    assert scene["grasps_with_shake"] == 0 < scene["grasps_static"] == scene["admitted_by_static"]
    assert len(scene["checks"]) == 1
    check = scene["checks"][0]
    assert check["lift_hold"] == (check["held"] or check["failure"] == "dropped-by-shake")


def test_label_check_samples_scenes_as_the_dataset_does(monkeypatch, library):
    """label-check draws each scene through `dataset.sample_dataset_scene`, the sampler of
    `generate` (same object count per scene, same seeds)."""
    import drake_grasp.learning.dataset as dataset_module
    from drake_grasp.learning.dataset import sample_dataset_scene, scene_object_count
    from drake_grasp.evaluation.labelcheck import LabelCheckConfig, check_scene
    from drake_grasp.config.scenario import load_scenario

    scenario = load_scenario(scenario_name="isolation")
    specs = [sample_dataset_scene(scenario, split="train", seed=4, scene_index=7, attempt=a,
                                  library=library) for a in range(3)]
    assert {len(s.objects) for s in specs} == {scene_object_count(4, 7, 1, 5)}
    assert len({s.seed for s in specs}) == 3  # each attempt its own seed

    class Sampled(Exception):
        pass

    def sampler(*args, **kwargs):
        raise Sampled(kwargs)

    monkeypatch.setattr(dataset_module, "sample_dataset_scene", sampler)
    with pytest.raises(Sampled) as info:
        check_scene(7, seed=4, scenario=scenario, library=library, config=LabelCheckConfig())
    kwargs = info.value.args[0]
    assert (kwargs["seed"], kwargs["scene_index"], kwargs["attempt"]) == (4, 7, 0)


def test_label_check_labels_with_its_torque_limit(monkeypatch, library):
    """`LabelCheckConfig.max_torque_ratio` (`label-check --max-torque-ratio`) is the limit
    the scene's grasps are labelled with, as `generate --max-torque-ratio` labels them."""
    import dataclasses

    import drake_grasp.geometry.grasps as grasps_module
    import drake_grasp.world.scene as scene_module
    from drake_grasp.evaluation.labelcheck import LabelCheckConfig, check_scene
    from drake_grasp.config.scenario import load_scenario

    class Labelled(Exception):
        pass

    def find_grasps(*args, **kwargs):
        raise Labelled(kwargs)

    monkeypatch.setattr(scene_module, "settle_scene",
                        lambda spec, *a, **k: dataclasses.replace(spec, settled=True))
    monkeypatch.setattr(grasps_module, "find_grasps", find_grasps)
    scenario = load_scenario(scenario_name="isolation")
    for ratio in (0.12, 0.5):
        with pytest.raises(Labelled) as info:
            check_scene(3, seed=4, scenario=scenario, library=library,
                        config=LabelCheckConfig(max_torque_ratio=ratio))
        assert info.value.args[0]["max_torque_ratio"] == ratio
    with pytest.raises(ValueError, match="max_torque_ratio"):
        LabelCheckConfig(max_torque_ratio=0.0).validate()


@pytest.mark.parametrize("command", ["label-check", "generate"])
@pytest.mark.parametrize("value", ["0", "-1", "inf", "abc"])
def test_a_bad_max_torque_ratio_is_refused_before_anything_runs(command, value, tmp_path, capsys):
    from drake_grasp.cli.main import main

    out = tmp_path / "out"
    args = {"label-check": ["label-check", "--scenes", "1", "--seed", "0"],
            "generate": ["generate", "--scenes", "1", "--split", "train"]}[command]
    with pytest.raises(SystemExit) as info:
        main(args + ["--out", str(out), "--max-torque-ratio", value])
    assert info.value.code == 2
    assert "--max-torque-ratio" in capsys.readouterr().err
    assert not out.exists()


def _generate_config(monkeypatch, tmp_path, argv):
    """The `DatasetConfig` that `drake-grasp generate ... ARGV` hands to the generator
    (which is replaced, so nothing is generated)."""
    import drake_grasp.learning.dataset_generate as generate_module
    from drake_grasp.cli.main import main

    seen = {}

    def generate_dataset(**kwargs):
        seen.update(kwargs)
        raise SystemExit(0)

    monkeypatch.setattr(generate_module, "generate_dataset", generate_dataset)
    with pytest.raises(SystemExit):
        main(["generate", "--scenes", "1", "--split", "train", "--out", str(tmp_path)] + argv)
    return seen["config"]


def test_generate_labels_with_the_torque_limit_given(monkeypatch, tmp_path):
    for argv, ratio in (([], 0.12), (["--max-torque-ratio", "0.5"], 0.5)):
        assert _generate_config(monkeypatch, tmp_path, argv).max_torque_ratio == ratio


def test_generate_searches_grasps_with_the_sample_count_given(monkeypatch, tmp_path, capsys):
    """`generate --grasp-samples N` reaches the ground-truth search of every scene; a bad
    N is refused before anything runs; the default keeps the identity (config hash) that
    datasets made before the flag existed have."""
    from drake_grasp.cli.main import main
    from drake_grasp.learning.dataset import DatasetConfig, _config_dict
    from drake_grasp.config.scenario import load_scenario

    for argv, samples in (([], 400), (["--grasp-samples", "2000"], 2000)):
        assert _generate_config(monkeypatch, tmp_path, argv).grasp_samples == samples
    for bad in ("0", "-5", "many"):
        with pytest.raises(SystemExit) as info:
            main(["generate", "--scenes", "1", "--split", "train", "--out",
                  str(tmp_path / "bad"), "--grasp-samples", bad])
        assert info.value.code == 2
        assert "--grasp-samples" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    scenario = load_scenario(scenario_name="random")
    assert "grasp_samples" not in _config_dict(scenario, DatasetConfig(), "train", 0)["dataset"]
    assert _config_dict(scenario, DatasetConfig(grasp_samples=2000), "train", 0)[
        "dataset"]["grasp_samples"] == 2000
    with pytest.raises(ValueError, match="grasp_samples"):
        DatasetConfig(grasp_samples=0).validate()


def test_the_scene_search_uses_the_configured_sample_count(monkeypatch, library):
    import drake_grasp.geometry.grasps as grasps_module
    import drake_grasp.world.scene as scene_module
    from drake_grasp.learning.dataset import DatasetConfig, generate_scene
    from drake_grasp.config.scenario import load_scenario

    class Searched(Exception):
        pass

    def find_grasps(*args, **kwargs):
        raise Searched(kwargs)

    monkeypatch.setattr(grasps_module, "find_grasps", find_grasps)
    monkeypatch.setattr(scene_module, "settle_world",
                        lambda world, spec, **k: dataclasses.replace(spec, settled=True))
    scenario = load_scenario(scenario_name="random")
    with pytest.raises(Searched) as info:
        generate_scene(0, seed=0, split="train", scenario=scenario,
                       config=DatasetConfig(grasp_samples=1234), library=library)
    assert info.value.args[0]["num_samples"] == 1234
