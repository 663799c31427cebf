"""The sequential pour (`scene.pour_scene`): objects released one at a time just above the
pile instead of dropped from a column."""

import pytest

from drake_grasp.objects import load_library
from drake_grasp.config.scenario import load_scenario
import dataclasses

import numpy as np

from drake_grasp.objects import visual_mesh
from drake_grasp.world.scene import make_scene, release_above, sample_scene, scene_top_z


@pytest.fixture(scope="module")
def clutter():
    scenario = load_scenario(scenario_name="clutter", scenario_text=(
        "{scene: {clutter_objects: 3, region_half_extent_m: 0.04, pour: sequential}}"))
    return scenario, load_library(None)


def test_sequential_pour_keeps_every_object_on_the_table(clutter):
    scenario, library = clutter
    column = sample_scene(scenario.scene, 0, library)
    pile = make_scene(scenario.scene, 0, library, scenario.plant, physics=scenario.physics)
    assert [o.object_id for o in pile.objects] == [o.object_id for o in column.objects]
    # Three objects poured onto each other stay a low pile near the centre.
    assert scene_top_z(pile, library) < 0.25
    for o in pile.objects:
        assert abs(o.xyz[0] - 0.5) < 0.3 and abs(o.xyz[1]) < 0.3 and o.xyz[2] > -0.01


def test_pour_is_checked():
    with pytest.raises(ValueError, match="scene.pour"):
        load_scenario(scenario_name="clutter", scenario_text="{scene: {pour: bucket}}")


def test_each_object_is_released_just_above_the_pile(clutter):
    scenario, library = clutter
    column = sample_scene(scenario.scene, 0, library)  # the column: each above the last
    first, second, third = column.objects
    pile = dataclasses.replace(column, objects=[first, second])
    released = release_above(pile, third, library, 0.02)
    V = np.asarray(visual_mesh(library.get(third.object_id)).vertices)
    lowest = released.xyz[2] + (V @ released.pose().rotation().matrix().T)[:, 2].min()
    assert lowest == pytest.approx(scene_top_z(pile, library) + 0.02, abs=1e-9)
    assert released.xyz[:2] == third.xyz[:2] and released.quat_wxyz == third.quat_wxyz
