"""Physics profiles: what each one sets, how a profile combines with explicit keys, the
half-space sheet, the gripper's hydroelastic margin, and a small fidelity comparison of
the fast profile against the reference one in the grasp lab."""

import re

import pytest

from drake_grasp.config.scenario import load_scenario
from drake_grasp.config.sections import PHYSICS_PROFILES


def test_default_is_the_fast_profile_and_reference_restores_the_old_settings():
    fast = load_scenario(scenario_name="clutter")
    assert fast.physics.profile == "fast"
    assert fast.plant.time_step == PHYSICS_PROFILES["fast"]["plant.time_step"] == 0.005
    ref = load_scenario(scenario_name="clutter", physics_profile="reference")
    assert ref.physics.profile == "reference"
    assert ref.plant.time_step == 0.002
    assert ref.physics.hydroelastic_margin_m == 0.0
    assert ref.physics.sheet_collision == "box"
    assert ref.physics.table_collision == "box"
    assert ref.physics.settle_time_step_s == 0.0
    assert fast.physics.table_collision == "halfspace"


def test_fast10_profile_is_fast_at_a_10_ms_step_with_the_similar_approximation():
    fast = load_scenario(scenario_name="isolation", physics_profile="fast")
    s = load_scenario(scenario_name="isolation", physics_profile="fast10")
    assert s.physics.profile == "fast10"
    assert s.plant.time_step == 0.01
    assert s.plant.discrete_contact_approximation == "similar"
    assert fast.plant.discrete_contact_approximation == "lagged"
    # Everything else is the fast profile's; scenes still settle at 5 ms.
    assert s.physics.settle_time_step_s == 0.005
    assert (s.physics.hydroelastic_margin_m, s.physics.sheet_collision,
            s.physics.table_collision) == (fast.physics.hydroelastic_margin_m,
                                           fast.physics.sheet_collision,
                                           fast.physics.table_collision)
    # Switching back restores the fast profile's approximation.
    back = load_scenario(scenario_name="isolation",
                         scenario_text="{physics: {profile: fast}}", physics_profile="fast10")
    assert (back.plant.time_step, back.plant.discrete_contact_approximation) == (0.005, "lagged")


def test_a_plant_key_given_beside_a_profile_wins():
    s = load_scenario(scenario_name="isolation", scenario_text=(
        "{physics: {profile: fast10}, plant: {discrete_contact_approximation: sap}}"))
    assert s.plant.discrete_contact_approximation == "sap"   # given in the same text
    assert s.plant.time_step == 0.01                          # from the profile


def test_keys_given_beside_a_profile_win():
    s = load_scenario(scenario_name="clutter", scenario_text=(
        "{physics: {profile: reference, sheet_collision: auto}, plant: {time_step: 0.003}}"))
    assert s.physics.profile == "reference"
    assert s.physics.sheet_collision == "auto"        # given beside the profile
    assert s.plant.time_step == 0.003                 # given in the same text
    assert s.physics.hydroelastic_margin_m == 0.0     # from the profile


@pytest.mark.parametrize("text, words", [
    ("{physics: {profile: refrence}}", ["physics.profile", "refrence", "reference"]),
    ("{physics: {sheet_collision: plane}}", ["physics.sheet_collision", "plane"]),
    ("{physics: {table_collision: plane}}", ["physics.table_collision", "plane"]),
    ("{physics: {hydroelastic_margin_m: -1.0}}", ["physics.hydroelastic_margin_m"]),
])
def test_bad_physics_values_name_the_key(text, words):
    with pytest.raises(ValueError) as e:
        load_scenario(scenario_name="isolation", scenario_text=text)
    for w in words:
        assert w in str(e.value)


def test_half_space_sheet_cannot_follow_a_moving_sheet():
    with pytest.raises(ValueError, match="physics.sheet_collision.*moves"):
        load_scenario(scenario_name="clutter_shift",
                      scenario_text="{physics: {sheet_collision: halfspace}}")
    from drake_grasp.config.physics import sheet_collision

    s = load_scenario(scenario_name="clutter_shift")
    assert s.physics.sheet_collision == "auto"
    assert sheet_collision(s.physics, sheet_moves=True) == "box"
    assert sheet_collision(s.physics, sheet_moves=False) == "halfspace"


def _world(physics):
    from pydrake.multibody.plant import AddMultibodyPlant
    from pydrake.systems.framework import DiagramBuilder

    from drake_grasp.config.physics import apply_hydroelastic_margin, sheet_collision
    from drake_grasp.world.table import add_table_and_sheet
    from drake_grasp.world.station import _add_robot

    s = load_scenario(scenario_name="isolation", physics_profile=physics)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(s.plant, builder)
    _, gripper = _add_robot(plant)
    add_table_and_sheet(plant, scene_graph, [0.5, 0.0],
                        sheet_collision=sheet_collision(s.physics, sheet_moves=False))
    plant.Finalize()
    n = apply_hydroelastic_margin(plant, scene_graph, s.physics.hydroelastic_margin_m, [gripper])
    return plant, scene_graph, n


def test_fast_profile_puts_a_half_space_under_the_objects_and_a_margin_on_the_pads():
    from pydrake.geometry import Role

    plant, scene_graph, changed = _world("fast")
    inspector = scene_graph.model_inspector()
    names = {inspector.GetName(g): g for g in inspector.GetAllGeometryIds(Role.kProximity)}
    assert "sheet::sheet_collision" not in names          # the box's proximity role is gone
    hs = [g for n, g in names.items() if n.endswith("sheet_halfspace")]
    assert len(hs) == 1
    assert inspector.GetFrameId(hs[0]) == scene_graph.world_frame_id()
    assert changed == 4                                    # two pads, two finger bodies
    pad = names["robotiq_2f85::left_pad_collision"]
    assert inspector.GetProximityProperties(pad).GetProperty("hydroelastic", "margin") == 1e-4

    plant, scene_graph, changed = _world("reference")
    inspector = scene_graph.model_inspector()
    names = [inspector.GetName(g) for g in inspector.GetAllGeometryIds(Role.kProximity)]
    assert "sheet::sheet_collision" in names and changed == 0
    assert not any(n.endswith("sheet_halfspace") for n in names)


def test_fast_and_reference_profiles_agree_in_the_grasp_lab(library, across_can):
    """The fidelity guard in small: the same grasps (a centred one that holds, one 6 cm
    beside the can that misses) get the same verdict under every profile."""
    from drake_grasp.evaluation.lab import check_grasp, isolated_scene

    scene = isolated_scene("can_000", library, lying=True)
    for offset, held in ((0.0, True), (0.06, False)):
        X = across_can(scene, library, offset_m=offset)
        verdicts = {p: check_grasp(None, X, scene=scene, library=library,
                                   scenario=load_scenario(physics_profile=p)).held
                    for p in ("reference", "fast", "fast10")}
        assert verdicts == {"reference": held, "fast": held, "fast10": held}, (offset, verdicts)


def test_a_record_made_before_physics_profiles_replays_with_the_reference_settings():
    from drake_grasp.evaluation.replay import recorded_scenario
    from drake_grasp.config.scenario import dump_scenario

    fast = load_scenario(scenario_name="isolation")
    now = recorded_scenario(dump_scenario(fast))
    assert now.physics == fast.physics and now.plant.time_step == 0.005
    ref = load_scenario(scenario_name="isolation", physics_profile="reference")
    old_yaml = re.sub(r"^physics:\n(?:  .*\n)+", "", dump_scenario(ref), flags=re.M)
    assert "physics" not in old_yaml
    old = recorded_scenario(old_yaml)
    assert old.physics == ref.physics
    assert old.plant.time_step == 0.002


@pytest.mark.parametrize("scenario_name, key, value_now, value_before", [
    ("clutter_shift", "physics.table_collision", "halfspace", "box"),
    ("isolation", "gripper.force_mode", "constant", "limit"),
])
def test_a_record_made_before_a_key_existed_replays_with_what_it_ran(
        scenario_name, key, value_now, value_before):
    from drake_grasp.evaluation.replay import recorded_scenario
    from drake_grasp.config.scenario import dump_scenario

    section, name = key.split(".")
    now = load_scenario(scenario_name=scenario_name)
    text = dump_scenario(now)
    line = f"  {name}: {value_now}\n"
    assert getattr(getattr(now, section), name) == value_now and line in text
    assert getattr(getattr(recorded_scenario(text), section), name) == value_now
    old = recorded_scenario(text.replace(line, ""))
    assert getattr(getattr(old, section), name) == value_before
    # Nothing else differs from the record.
    setattr(getattr(old, section), name, value_now)
    assert dump_scenario(old) == text


def test_a_gpd_record_made_before_the_fallback_was_a_key_replays_without_it():
    """`gpd.fallback_best` is on by default now; a record whose scenario has no such key
    ran GPD's strict threshold and replays so; one that names it keeps its value."""
    from drake_grasp.evaluation.replay import recorded_scenario
    from drake_grasp.config.scenario import dump_scenario

    now = load_scenario(scenario_name="clutter")
    text = dump_scenario(now)
    line = "  fallback_best: true\n"
    assert now.gpd.fallback_best is True and line in text
    assert recorded_scenario(text).gpd.fallback_best is True
    assert recorded_scenario(text.replace(line, "  fallback_best: false\n")).gpd.fallback_best is False
    old = recorded_scenario(text.replace(line, ""))
    assert old.gpd.fallback_best is False
    old.gpd.fallback_best = True
    assert dump_scenario(old) == text  # nothing else differs from the record


def test_a_record_with_a_retired_key_is_refused_by_name(tmp_path):
    from drake_grasp.evaluation.replay import replay_trial
    from drake_grasp.evaluation.records import TrialRecord, write_record
    from drake_grasp.config.scenario import dump_scenario

    text = dump_scenario(load_scenario(scenario_name="isolation")).replace(
        "controller:\n", "controller:\n  stop_window_fraction: 0.1\n", 1)
    write_record(tmp_path, TrialRecord(
        trial_id="isolation/ctr/0000", experiment="isolation", condition="ctr", policy="ctr",
        noise="none", noise_scale=None, depth_noise=False, offset_m=None, disturbance={},
        scenario_name="isolation", scenario_yaml=text, seed=0, config_hash="x",
        code_version="0.0.9+git.0123456789ab", success=False, failure_class="missed",
        failure_reason="missed", final_distance_m=None, sim_time_s=1.0, wall_time_s=1.0,
        control_steps=0, object_ids=["can_000"], grasped_object_id=None))
    with pytest.raises(ValueError, match=r"isolation/ctr/0000.*0\.0\.9\+git\.0123456789ab"
                                         r".*stop_window_fraction.*Replay it with that version"):
        replay_trial(tmp_path, trial_id="isolation/ctr/0000")


def test_unknown_grip_force_mode_is_refused_by_name():
    with pytest.raises(ValueError, match=r"gripper.force_mode: got 'hard', expected one of"):
        load_scenario(scenario_name="isolation", scenario_text="{gripper: {force_mode: hard}}")
