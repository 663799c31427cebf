"""Contact-simulation settings that go beyond Drake's `MultibodyPlantConfig`.

Helpers applied to a plant's SceneGraph after the models are parsed:
- `apply_hydroelastic_margin`: Drake's `hydroelastic_margin` on the gripper's compliant
  geometry (keeps flat-on-flat contact stable at larger time steps).
- `sheet_collision`: which collision geometry the sheet gets in a given Diagram.
- `table_collision`: which collision geometry the table gets.
"""

from __future__ import annotations

from pydrake.geometry import ProximityProperties, Role, RoleAssign

HYDRO_GROUP = "hydroelastic"


def compliant_geometries(scene_graph) -> list:
    """The ids of every geometry with compliant-hydroelastic proximity properties.

    A compliant geometry carries a hydroelastic modulus; rigid ones do not (pydrake
    cannot read the compliance-type enum itself).
    """
    inspector = scene_graph.model_inspector()
    return [gid for gid in inspector.GetAllGeometryIds(Role.kProximity)
            if inspector.GetProximityProperties(gid).HasProperty(HYDRO_GROUP,
                                                                 "hydroelastic_modulus")]


def apply_hydroelastic_margin(plant, scene_graph, margin_m: float, model_instances) -> int:
    """Sets Drake's hydroelastic margin on the compliant geometries of `model_instances`.

    Used on the gripper (pads and finger bodies). The objects' compliant convex pieces
    cannot take a margin: Drake 1.51 rejected it ("A mesh field element was degenerate")
    on at least one piece of 208 of the 381 built-in objects.

    Args:
        plant: the MultibodyPlant registered with `scene_graph` (finalized or not).
        scene_graph: its SceneGraph (the model, before any Context is made).
        margin_m: the margin [m]; 0 leaves the geometry as it is.
        model_instances: the plant's model instances whose geometry gets the margin.

    Returns:
        How many geometries were changed.
    """
    if not margin_m > 0:
        return 0
    inspector = scene_graph.model_inspector()
    source_id = plant.get_source_id()
    frames = {plant.GetBodyFrameIdOrThrow(b) for m in model_instances
              for b in plant.GetBodyIndices(m)}
    changed = 0
    for gid in compliant_geometries(scene_graph):
        if inspector.GetFrameId(gid) not in frames:
            continue
        props = ProximityProperties(inspector.GetProximityProperties(gid))
        if props.HasProperty(HYDRO_GROUP, "margin"):
            props.UpdateProperty(HYDRO_GROUP, "margin", float(margin_m))
        else:
            props.AddProperty(HYDRO_GROUP, "margin", float(margin_m))
        scene_graph.AssignRole(source_id, gid, props, RoleAssign.kReplace)
        changed += 1
    return changed


def sheet_collision(physics, *, sheet_moves: bool) -> str:
    """The sheet collision ("box" or "halfspace") for a Diagram, from
    `PhysicsConfig.sheet_collision` ("box", "halfspace" or "auto").

    The half space is anchored to the world, so it cannot follow a moving sheet: "auto"
    is the half space where the sheet stays still (settling, the grasp lab, episodes
    without a disturbance) and the box where it moves.

    Raises:
        ValueError: "halfspace" asked for a Diagram whose sheet moves.
    """
    choice = physics.sheet_collision if physics is not None else "box"
    if choice == "auto":
        return "box" if sheet_moves else "halfspace"
    if choice == "halfspace" and sheet_moves:
        raise ValueError("physics.sheet_collision: 'halfspace' is anchored to the world and "
                         "cannot follow the sheet that a disturbance moves; use 'box' or 'auto'")
    return choice


def table_collision(physics) -> str:
    """The table collision ("box" or "halfspace") from `PhysicsConfig.table_collision`
    ("box" without a physics config: the reference settings). Under a half-space sheet
    `table.add_table_and_sheet` gives the table none either way."""
    return physics.table_collision if physics is not None else "box"
