"""The table and the floor: a pile settles where the episode that uses it will hold it.

A clutter-shift run once ended in three simulation errors in a row: a hammer had come to
rest 0.80 m ahead of the robot on the sheet's edgeless half-space collision (used where
the pile was settled), but the episode, which moves the sheet and so keeps its 0.6 m box,
had no table under it (the top ended at 0.7 m); the hammer fell, spun up in free fall and
the state went non-finite after 6.8 s."""

import dataclasses
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from drake_grasp.objects import load_library
from drake_grasp.config.scenario import load_scenario
from drake_grasp.world.scene import ObjectPlacement, SceneSpec, build_scene_world, settle_world
from drake_grasp.world.table import TABLE_TOP_X_M, TABLE_TOP_Y_M

MODELS = Path(__file__).resolve().parents[1] / "models"
LYING = [0.7071068, 0.7071068, 0.0, 0.0]  # 90 deg about x: a can on its side


@pytest.fixture(scope="module")
def shift():
    scenario = load_scenario(scenario_name="clutter_shift")
    return scenario, load_library(None)


def _one(library, x_m: float, y_m: float = 0.0, z_m: float = 0.04) -> SceneSpec:
    object_id = sorted(library.ids("test"))[0]
    return SceneSpec(kind="clutter", seed=0, center_xy_m=[0.5, 0.0],
                     objects=[ObjectPlacement(object_id, [x_m, y_m, z_m], list(LYING))])


def _geometry_names(world) -> list[str]:
    from pydrake.geometry import Role

    inspector = world.scene_graph.model_inspector()
    return [inspector.GetName(g) for g in inspector.GetAllGeometryIds(Role.kProximity)]


def test_table_top_constants_match_the_model():
    link = ET.parse(MODELS / "scene" / "table.urdf").getroot().find("link")
    top = [c for c in link.findall("collision") if c.get("name") == "top_collision"][0]
    x, y, _ = (float(v) for v in top.find("origin").get("xyz").split())
    sx, sy, _ = (float(v) for v in top.find("geometry/box").get("size").split())
    assert TABLE_TOP_X_M == pytest.approx((x - sx / 2, x + sx / 2))
    assert TABLE_TOP_Y_M == pytest.approx((y - sy / 2, y + sy / 2))
    # The table carries the sheet (0.6 m square around x = 0.5) with room to spare.
    assert TABLE_TOP_X_M[0] < 0.2 - 0.3 and TABLE_TOP_X_M[1] > 0.8 + 0.3
    assert TABLE_TOP_Y_M[0] < -0.3 - 0.3 and TABLE_TOP_Y_M[1] > 0.3 + 0.3


def test_a_moving_sheet_is_settled_with_its_box(shift):
    scenario, library = shift
    assert scenario.sheet_moves
    spec = _one(library, 0.5)
    moving = build_scene_world(spec, library, physics=scenario.physics, sheet_moves=True)
    still = build_scene_world(spec, library, physics=scenario.physics, sheet_moves=False)
    assert "sheet_halfspace" not in _geometry_names(moving)
    assert "sheet_halfspace" in _geometry_names(still)
    assert not load_scenario(scenario_name="clutter").sheet_moves


def test_the_table_collision_of_each_physics_profile(shift):
    """Under the half-space sheet, which lies 2 mm above the table top everywhere, the
    table has no collision geometry: kept, it cost a soft-volume / rigid-mesh
    intersection per resting object piece and step (the broad phase bounds convex pieces
    loosely). Where the sheet keeps its box, the `fast` profile makes the table a half
    space at its top and `reference` keeps its box and floor. An object settles on the
    sheet's top at the same height in all three."""
    scenario, library = shift
    reference = load_scenario(scenario_name="clutter_shift", physics_profile="reference")
    spec = _one(library, 0.5)
    worlds = {"box sheet, half-space table": build_scene_world(
                  spec, library, physics=scenario.physics, sheet_moves=True),
              "half-space sheet, no table": build_scene_world(
                  spec, library, physics=scenario.physics, sheet_moves=False),
              "box sheet, box table": build_scene_world(
                  spec, library, physics=reference.physics, sheet_moves=True)}
    names = {k: _geometry_names(w) for k, w in worlds.items()}
    table = {"table::top_collision", "table::floor_collision"}
    assert table <= set(names["box sheet, box table"])
    assert "table_halfspace" in names["box sheet, half-space table"]
    assert not table & set(names["box sheet, half-space table"])
    assert not table & set(names["half-space sheet, no table"])
    assert "table_halfspace" not in names["half-space sheet, no table"]
    assert "table_halfspace" not in names["box sheet, box table"]
    z = [settle_world(w, spec, max_time_s=1.0).objects[0].xyz[2] for w in worlds.values()]
    assert z == pytest.approx([z[0]] * 3, abs=5e-4)


def test_an_object_beyond_the_sheet_rests_on_the_table(shift):
    scenario, library = shift
    spec = _one(library, 0.85)  # 5 cm beyond the sheet's far edge
    world = build_scene_world(spec, library, physics=scenario.physics, sheet_moves=True)
    rest = settle_world(world, spec, max_time_s=1.0)
    assert len(rest.objects) == 1
    assert rest.objects[0].xyz[2] > 0.0 and abs(rest.objects[0].xyz[0] - 0.85) < 0.05


@pytest.mark.parametrize("sheet_moves, profile", [(True, "reference"), (True, "fast"),
                                                   (False, "fast")])
def test_an_object_beyond_the_table_leaves_the_scene(shift, sheet_moves, profile):
    _, library = shift
    physics = load_scenario(scenario_name="clutter_shift", physics_profile=profile).physics
    spec = _one(library, TABLE_TOP_X_M[1] + 0.1)
    world = build_scene_world(spec, library, physics=physics, sheet_moves=sheet_moves)
    rest = settle_world(world, spec, max_time_s=1.0)
    assert rest.objects == []  # fell off the table, or rests beyond its edge on a half space
    body = world.bodies()[0]
    p = world.plant.EvalBodyPoseInWorld(world.plant_context(), body).translation()
    assert np.all(np.isfinite(p))
    if profile == "reference":
        # The floor, 0.75 m below the table top, caught it: no endless fall.
        assert -0.8 < p[2] < -0.6
    else:
        assert p[2] > -0.01  # held up by the half space (the sheet's or the table's)


def test_settled_spec_keeps_the_objects_on_the_table(shift):
    scenario, library = shift
    near = _one(library, 0.5)
    spec = dataclasses.replace(near, objects=near.objects + _one(library, 0.5, y_m=0.9).objects)
    world = build_scene_world(spec, library, physics=scenario.physics, sheet_moves=False)
    rest = settle_world(world, spec, max_time_s=0.5)
    assert len(rest.objects) == 1 and abs(rest.objects[0].xyz[1]) < 0.05
