"""Scenario files: named scenarios load, unknown keys are errors naming the key."""

import pytest

from drake_grasp.config.scenario import Scenario, dump_scenario, list_scenarios, load_scenario


def test_every_named_scenario_loads_and_validates():
    names = list_scenarios()
    assert {"isolation", "random", "clutter"} <= set(names)
    for name in names:
        scenario = load_scenario(scenario_name=name)
        assert isinstance(scenario, Scenario)
        assert scenario.scene.kind in ("isolation", "random", "clutter")
        assert scenario.plant.discrete_contact_approximation in ("lagged", "sap")


def test_misspelled_key_names_the_key(tmp_path):
    path = tmp_path / "bad.scenarios.yaml"
    path.write_text("mine:\n  scene:\n    kind: isolation\n    clutter_objcts: 3\n")
    with pytest.raises(ValueError, match="clutter_objcts"):
        load_scenario(scenario_name="mine", scenario_file=path)


def test_misspelled_key_in_override_names_the_key():
    with pytest.raises(ValueError, match="grip_forse_n"):
        load_scenario(scenario_name="isolation", scenario_text="{gripper: {grip_forse_n: 3}}")


def test_bad_value_names_the_key():
    with pytest.raises(ValueError, match="scene.kind"):
        load_scenario(scenario_name="isolation", scenario_text="{scene: {kind: pile}}")


def test_unknown_scenario_lists_the_available_ones():
    with pytest.raises(ValueError, match="isolation"):
        load_scenario(scenario_name="no_such_scenario")


def test_override_and_round_trip(tmp_path):
    s = load_scenario(scenario_name="clutter", scenario_text="{seed: 7, gripper: {grip_force_n: 5.0}}")
    assert s.seed == 7 and s.gripper.grip_force_n == 5.0
    assert s.scene.kind == "clutter"  # the named scenario's keys survive the override
    path = tmp_path / "resolved.scenarios.yaml"
    path.write_text("resolved:\n" + "".join("  " + line + "\n" for line in dump_scenario(s).splitlines()))
    again = load_scenario(scenario_name="resolved", scenario_file=path)
    assert dump_scenario(again) == dump_scenario(s)  # (Drake configs have no __eq__)


def test_controller_profiles_resolve_to_the_papers_numbers(tmp_path):
    from drake_grasp.config.sections import CONTROLLER_PROFILES, ControllerConfig

    # The defaults are the "sim" profile: r = 0.2, 75 iterations, camera 0.3 -> 0.15 m.
    sim = load_scenario(scenario_name="isolation").controller
    assert sim.profile == "sim"
    for key, value in CONTROLLER_PROFILES["sim"].items():
        assert getattr(sim, key) == value == getattr(ControllerConfig(), key), key
    assert (sim.step_ratio, sim.iterations, sim.z_step_m, sim.end_camera_height_m) == (0.2, 75, 0.0, 0.15)
    # "robot": r = 0.5, 1 cm z steps, stop at 14 cm.
    robot = load_scenario(scenario_name="isolation",
                          scenario_text="{controller: {profile: robot}}").controller
    assert (robot.profile, robot.step_ratio, robot.z_step_m, robot.stop_distance_m) == (
        "robot", 0.5, 0.01, 0.14)
    # "paper-sim": Section 5 as written, no stop rule and no convergence; "sim" after it
    # has both again.
    paper = load_scenario(scenario_name="isolation",
                          scenario_text="{controller: {profile: paper-sim}}").controller
    assert (paper.step_ratio, paper.iterations, paper.stop_distance_m,
            paper.converge_iterations) == (0.2, 75, 0.0, 0)
    again = load_scenario(scenario_name="isolation", controller_profile="paper-sim",
                          scenario_text="{controller: {profile: sim}}").controller
    assert (again.stop_distance_m, again.converge_iterations) == (0.14, 20)
    # Keys given beside the profile win; keys given elsewhere are overridden by it.
    mixed = load_scenario(scenario_name="isolation",
                          scenario_text="{controller: {profile: robot, step_ratio: 0.3}}").controller
    assert (mixed.step_ratio, mixed.z_step_m) == (0.3, 0.01)
    path = tmp_path / "mine.scenarios.yaml"
    path.write_text("mine:\n  controller:\n    profile: robot\n    iterations: 20\n")
    s = load_scenario(scenario_name="mine", scenario_file=path)
    assert (s.controller.profile, s.controller.iterations, s.controller.step_ratio) == ("robot", 20, 0.5)
    back = load_scenario(scenario_name="mine", scenario_file=path,
                         scenario_text="{controller: {profile: sim}}").controller
    assert (back.profile, back.iterations, back.step_ratio, back.z_step_m) == ("sim", 75, 0.2, 0.0)
    # The keyword applies a profile before the text override (how experiments choose).
    kw = load_scenario(scenario_name="isolation", controller_profile="robot",
                       scenario_text="{controller: {iterations: 30}}").controller
    assert (kw.profile, kw.step_ratio, kw.iterations) == ("robot", 0.5, 30)
    # The resolved scenario carries the numbers: it reloads to the same settings.
    resolved = tmp_path / "resolved.scenarios.yaml"
    dump = dump_scenario(load_scenario(scenario_name="isolation",
                                       scenario_text="{controller: {profile: robot, step_ratio: 0.3}}"))
    resolved.write_text("r:\n" + "".join("  " + line + "\n" for line in dump.splitlines()))
    assert dump_scenario(load_scenario(scenario_name="r", scenario_file=resolved)) == dump


@pytest.mark.parametrize("text", ["{controller: {profile: robt}}", "{controller: {profile: real}}"])
def test_unknown_controller_profile_names_the_key_and_the_profiles(text):
    with pytest.raises(ValueError, match=r"controller\.profile: got '(robt|real)'.*expected one of "
                                         r"\('sim', 'robot', 'paper-sim'\)"):
        load_scenario(scenario_name="isolation", scenario_text=text)
    with pytest.raises(ValueError, match=r"controller\.profile"):
        load_scenario(scenario_name="isolation", controller_profile="robt")
    s = load_scenario(scenario_name="isolation")
    s.controller.profile = "robt"
    with pytest.raises(ValueError, match=r"controller\.profile: got 'robt'"):
        s.validate()


def test_table1_experiments_run_the_robot_profile_and_isolation_also_the_sim_one():
    from drake_grasp.evaluation.experiments import EXPERIMENTS, condition_scenario

    for name in ("isolation", "clutter", "clutter-shift"):
        e = EXPERIMENTS[name]
        profiles = {c.name: condition_scenario(e, c).controller for c in e.conditions}
        assert profiles["ctr"].profile == "robot" and profiles["ctr"].step_ratio == 0.5
        assert profiles["ctr"].z_step_m == 0.01
    iso = EXPERIMENTS["isolation"]
    assert [c.name for c in iso.conditions] == ["ctr", "ctr-sim", "gpd", "scripted"]
    ctr_sim = condition_scenario(iso, iso.conditions[1])
    assert (ctr_sim.policy, ctr_sim.controller.profile, ctr_sim.controller.step_ratio,
            ctr_sim.controller.iterations) == ("ctr", "sim", 0.2, 75)
    # The paper's simulation experiments keep the sim settings.
    for c in EXPERIMENTS["sim-distance"].conditions:
        assert condition_scenario(EXPERIMENTS["sim-distance"], c).controller.profile == "sim"
