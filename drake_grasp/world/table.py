"""The table and the sheet on it: their models, their collision variants (boxes or rigid
half spaces, `PhysicsConfig`), the sheet's hold, and where the table top ends.

The plant-building pieces shared by settling (`scene`), the station and the grasp lab, so
all use one implementation.
"""

from __future__ import annotations

import numpy as np

from drake_grasp.core.assets import make_parser

TABLE_URI = "package://drake_grasp/scene/table.urdf"
SHEET_URI = "package://drake_grasp/scene/sheet.urdf"
SHEET_THICKNESS_M = 0.002
# The table top's extent in the world, (x_min, x_max), (y_min, y_max) [m] (table.urdf's
# top box; tests/test_table.py checks the two agree). An object whose centre of mass
# rests beyond it has fallen off, even where the sheet's half-space collision, which
# has no edge, still holds it up.
TABLE_TOP_X_M = (-0.7, 1.3)
TABLE_TOP_Y_M = (-0.7, 0.7)
SHEET_CENTER_IN_MODEL_M = (0.5, 0.0)


def add_table_and_sheet(plant, scene_graph, center_xy_m, *, sheet_collision: str = "box",
                        table_collision: str = "box") -> tuple:
    """Adds the table (top surface at world z=0) and the movable sheet centred at
    `center_xy_m`; its three joints (x, y, yaw) measure the sheet's displacement.

    The sheet's joints fix its height, so sheet-table contact is filtered out.
    `sheet_collision` "halfspace" replaces the sheet's box collision by a rigid half
    space at its top surface (`PhysicsConfig.sheet_collision`); the table then has no
    collision geometry. Otherwise `table_collision` "halfspace" replaces the table's top
    and floor by a rigid half space at the top (`PhysicsConfig.table_collision`). Call
    before Finalize.

    Returns:
        (table_instance, sheet_instance)
    """
    from pydrake.geometry import CollisionFilterDeclaration
    from pydrake.math import RigidTransform

    parser = make_parser(plant)
    (table,) = parser.AddModels(url=TABLE_URI)
    plant.WeldFrames(plant.world_frame(), plant.GetBodyByName("table", table).body_frame())
    (sheet,) = parser.AddModels(url=SHEET_URI)
    # With its joints at zero the sheet centre is SHEET_CENTER_IN_MODEL_M ahead of the
    # model's root (models/scene/sheet.urdf).
    plant.WeldFrames(
        plant.world_frame(), plant.GetBodyByName("sheet_origin", sheet).body_frame(),
        RigidTransform([float(center_xy_m[0]) - SHEET_CENTER_IN_MODEL_M[0],
                        float(center_xy_m[1]) - SHEET_CENTER_IN_MODEL_M[1], 0.0]),
    )
    if sheet_collision not in ("box", "halfspace"):
        raise ValueError(f"sheet_collision: got {sheet_collision!r}, expected 'box' or 'halfspace'")
    if table_collision not in ("box", "halfspace"):
        raise ValueError(f"table_collision: got {table_collision!r}, expected 'box' or 'halfspace'")
    table_body = plant.GetBodyByName("table", table)
    if sheet_collision == "halfspace":
        _sheet_as_half_space(plant, scene_graph, plant.GetBodyByName("sheet", sheet))
        _drop_collision(plant, scene_graph, table_body)
    elif table_collision == "halfspace":
        _table_as_half_space(plant, scene_graph, table_body)
    # The world body holds the half spaces.
    geometries = plant.CollectRegisteredGeometries(
        [plant.world_body(), table_body, plant.GetBodyByName("sheet", sheet)])
    scene_graph.collision_filter_manager().Apply(
        CollisionFilterDeclaration().ExcludeWithin(geometries))
    return table, sheet


class _HalfSpaceWarningFilter:
    """Drops Drake's notice that rigid half spaces do not touch deformable bodies."""

    def filter(self, record) -> bool:
        return "half spaces are not currently supported for deformable" not in record.getMessage()


def _collision_ids(plant, scene_graph, body) -> list:
    """The ids of `body`'s geometries with a proximity role. Found by frame through the
    inspector: ids taken from GetCollisionGeometriesForBody came back corrupted here
    (pydrake 1.51)."""
    from pydrake.geometry import Role

    inspector = scene_graph.model_inspector()
    frame_id = plant.GetBodyFrameIdOrThrow(body.index())
    return [g for g in inspector.GetAllGeometryIds(Role.kProximity)
            if inspector.GetFrameId(g) == frame_id]


def _friction(scene_graph, geometry_id):
    return scene_graph.model_inspector().GetProximityProperties(geometry_id).GetProperty(
        "material", "coulomb_friction")


def _drop_collision(plant, scene_graph, body) -> None:
    """Removes the proximity role of every collision geometry of `body`.

    For the table under a half-space sheet: the half space lies 2 mm above the table top
    everywhere, so nothing can reach the top or the floor below it. The geometries still
    cost time: Drake's broad phase bounds a convex piece's box loosely enough that every
    object piece resting on the sheet was a candidate pair with the table top, and each
    candidate ran a soft-volume / rigid-mesh intersection that found nothing (a quarter
    of the settling simulation's time, per `perf`)."""
    from pydrake.geometry import Role

    for geometry_id in _collision_ids(plant, scene_graph, body):
        scene_graph.RemoveRole(source_id=plant.get_source_id(), geometry_id=geometry_id,
                               role=Role.kProximity)


def _add_world_half_space(plant, z_m: float, name: str, friction) -> None:
    """A rigid hydroelastic half space with its surface at height `z_m`, anchored to the
    world: Drake's broad phase crashed (segmentation fault) with a half space on a
    moving body."""
    import logging

    from pydrake.geometry import AddRigidHydroelasticProperties, HalfSpace, ProximityProperties
    from pydrake.math import RigidTransform

    props = ProximityProperties()
    AddRigidHydroelasticProperties(props)
    props.AddProperty("material", "coulomb_friction", friction)
    # Drake warns (whenever a Context is made) that deformable bodies cannot touch a rigid
    # half space; there are none here. pydrake routes Drake's log through `logging`.
    logger = logging.getLogger("drake")
    if not any(isinstance(f, _HalfSpaceWarningFilter) for f in logger.filters):
        logger.addFilter(_HalfSpaceWarningFilter())
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0.0, 0.0, z_m]),
                                    HalfSpace(), name, props)


def _sheet_as_half_space(plant, scene_graph, sheet_body) -> None:
    """Swaps the sheet's box collision for a rigid half space at its top (z = 2 mm), with
    the box's friction. Anchored to the world (`_add_world_half_space`), so this is only
    for scenes whose sheet stays where it is."""
    (box_id,) = _collision_ids(plant, scene_graph, sheet_body)
    _add_world_half_space(plant, SHEET_THICKNESS_M, "sheet_halfspace",
                          _friction(scene_graph, box_id))
    _drop_collision(plant, scene_graph, sheet_body)


def _table_as_half_space(plant, scene_graph, table_body) -> None:
    """Swaps the table's top and floor collision for a rigid half space at the top
    (z = 0), anchored to the world, with the top's friction: cheaper than the top's box
    for every object piece on the sheet beside it (a soft-volume / rigid-mesh
    intersection per candidate pair). It has no edge: an object pushed beyond the table
    top rests on it instead of falling to the floor (settled scenes drop such objects:
    `on_table_top`)."""
    inspector = scene_graph.model_inspector()
    top = [g for g in _collision_ids(plant, scene_graph, table_body)
           if inspector.GetName(g).endswith("top_collision")]
    if len(top) != 1:
        raise RuntimeError(f"the table model has {len(top)} geometries named top_collision, "
                           "expected 1")
    _add_world_half_space(plant, 0.0, "table_halfspace", _friction(scene_graph, top[0]))
    _drop_collision(plant, scene_graph, table_body)


def connect_sheet_hold(builder, plant, sheet_instance, name: str = "sheet_hold"):
    """Holds the sheet where it is (PD target zero); every PD instance must be connected."""
    from pydrake.systems.primitives import ConstantVectorSource

    n = plant.num_positions(sheet_instance) + plant.num_velocities(sheet_instance)
    source = builder.AddNamedSystem(name, ConstantVectorSource(np.zeros(n)))
    builder.Connect(source.get_output_port(), plant.get_desired_state_input_port(sheet_instance))
    return source


def on_table_top(p_W) -> bool:
    """Whether a point's (x, y) lies over the table top (`TABLE_TOP_X_M`, `TABLE_TOP_Y_M`)."""
    return bool(TABLE_TOP_X_M[0] <= p_W[0] <= TABLE_TOP_X_M[1]
                and TABLE_TOP_Y_M[0] <= p_W[1] <= TABLE_TOP_Y_M[1])
