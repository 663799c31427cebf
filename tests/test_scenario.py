"""Scenario files: named scenarios load, unknown keys are errors naming the key."""

import pytest

from drake_grasp.scenario import Scenario, dump_scenario, list_scenarios, load_scenario


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
