"""What is on the table: serializable scene specs, sampled from a seed and settled by physics.

A `SceneSpec` lists object ids with their poses. `sample_scene` draws one from a
`SceneConfig` and a seed (objects placed in the air, not touching); `settle_scene`
drops them onto the sheet on the table and simulates until every object is at rest,
so no trial starts interpenetrating. The same seed always gives the same scene.

Also here: the objects' plant-building pieces shared by settling and the station, so both
use one implementation (the table and the sheet: `world.table`).
"""

from __future__ import annotations

import copy
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drake_grasp.objects import ObjectLibrary, visual_mesh
from drake_grasp.objects.stable_poses import stable_poses
from drake_grasp.config.physics import sheet_collision, table_collision
from drake_grasp.config.sections import SceneConfig
from drake_grasp.world.table import (SHEET_THICKNESS_M, add_table_and_sheet, connect_sheet_hold,
                                     on_table_top)

OBJECT_BODY_NAME = "body"


@dataclass
class ObjectPlacement:
    """One object of a scene: its library id and its pose in the world."""

    object_id: str
    xyz: list[float]
    quat_wxyz: list[float]

    def pose(self):
        """The pose as a Drake `RigidTransform` X_WO."""
        from pydrake.common.eigen_geometry import Quaternion
        from pydrake.math import RigidTransform, RotationMatrix

        q = Quaternion(np.asarray(self.quat_wxyz, dtype=float))
        return RigidTransform(RotationMatrix(q), np.asarray(self.xyz, dtype=float))


@dataclass
class SceneSpec:
    """A scene: kind, seed, sheet placement and objects. `settled` once at rest."""

    kind: str
    seed: int
    center_xy_m: list[float]
    objects: list[ObjectPlacement] = field(default_factory=list)
    settled: bool = False

    def object_ids(self) -> list[str]:
        return [o.object_id for o in self.objects]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> SceneSpec:
        try:
            objects = [ObjectPlacement(**o) for o in data["objects"]]
            return cls(
                kind=data["kind"],
                seed=int(data["seed"]),
                center_xy_m=list(data["center_xy_m"]),
                objects=objects,
                settled=bool(data.get("settled", False)),
            )
        except (KeyError, TypeError) as e:
            raise ValueError(f"scene spec: missing or bad key ({e}); got keys {list(data)}") from None

    def save(self, path: str | Path) -> None:
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1))
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> SceneSpec:
        return cls.from_dict(json.loads(Path(path).read_text()))


# ----------------------------------------------------------------------------
# Plant building, shared with the station.


def add_scene_objects(plant, spec: SceneSpec, library: ObjectLibrary) -> list:
    """Adds the spec's objects as free bodies; returns their model instances in order."""
    from pydrake.multibody.parsing import Parser

    instances = []
    for i, placement in enumerate(spec.objects):
        info = library.get(placement.object_id)
        parser = Parser(plant, f"object_{i}")
        (instance,) = parser.AddModels(str(info.model_path))
        instances.append(instance)
    return instances


def set_object_poses(plant, plant_context, spec: SceneSpec, instances) -> None:
    """Puts each object body at its pose from the spec."""
    for placement, instance in zip(spec.objects, instances):
        body = plant.GetBodyByName(OBJECT_BODY_NAME, instance)
        plant.SetFreeBodyPose(plant_context, body, placement.pose())


# ----------------------------------------------------------------------------
# Sampling.


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation matrix (from a uniform unit quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _quat_wxyz(R: np.ndarray) -> list[float]:
    from pydrake.math import RotationMatrix

    q = RotationMatrix(R).ToQuaternion()
    return [float(q.w()), float(q.x()), float(q.y()), float(q.z())]


def _object_vertices(library: ObjectLibrary, object_id: str) -> np.ndarray:
    return np.asarray(visual_mesh(library.get(object_id)).vertices, dtype=float)


def scene_top_z(spec: SceneSpec, library: ObjectLibrary) -> float:
    """Height of the highest point of any object in the scene [m] (0 when empty)."""
    top = 0.0
    for placement in spec.objects:
        V = _object_vertices(library, placement.object_id)
        X = placement.pose()
        top = max(top, float((V @ X.rotation().matrix().T + X.translation())[:, 2].max()))
    return top


def _pick_ids(config: SceneConfig, library: ObjectLibrary, count: int,
              rng: np.random.Generator) -> list[str]:
    if config.object_ids:
        missing = [i for i in config.object_ids if i not in set(library.ids())]
        if missing:
            raise ValueError(f"scene.object_ids: unknown object ids {missing}")
        return list(config.object_ids[:count]) if count else list(config.object_ids)
    pool = library.ids(split=config.split or None)
    if len(pool) < count:
        raise ValueError(
            f"scene: need {count} objects but the library split {config.split!r} has {len(pool)}"
        )
    picked = rng.choice(len(pool), size=count, replace=False)
    return [pool[int(i)] for i in picked]


INITIAL_POSES = ("uniform", "stable")


def sample_scene(config: SceneConfig, seed: int, library: ObjectLibrary, *,
                 initial_pose: str = "uniform") -> SceneSpec:
    """Draws an unsettled scene from a config and a seed (deterministic).

    isolation: one object, lying (rotated 90 deg about a horizontal axis) or upright,
    random yaw; random: 1-5 objects spread over the region; clutter: objects stacked in a
    column above a small region, so they pour into a pile when settled; packed:
    `clutter_objects` objects standing upright side by side over the region, random yaw
    (the clutter-removal benchmarks' "packed" scenes: VGN, Breyer et al. 2020). The random and
    clutter objects' orientation (`initial_pose`): "uniform", uniformly random (they
    tumble when dropped); "stable", one of the object's resting poses on a plane drawn
    with its probability, random yaw (`objects.stable_poses`; an object that does not
    land on another is then already at rest, 2 mm above the sheet).
    """
    if initial_pose not in INITIAL_POSES:
        raise ValueError(f"initial_pose: expected one of {', '.join(INITIAL_POSES)}, "
                         f"got {initial_pose!r}")
    rng = np.random.default_rng([int(seed), 7919])
    cx, cy = (float(v) for v in config.center_xy_m)
    half = float(config.region_half_extent_m)
    if config.kind == "isolation":
        count = 1
    elif config.kind == "random":
        count = int(rng.integers(config.num_objects_min, config.num_objects_max + 1))
    elif config.kind in ("clutter", "packed"):
        count = int(config.clutter_objects)
    else:
        raise ValueError(f"scene.kind: got {config.kind!r}, expected isolation|random|clutter"
                         "|packed")
    if config.object_ids and config.kind == "isolation":
        count = 1
    ids = _pick_ids(config, library, count, rng)

    placements: list[ObjectPlacement] = []
    stack_z = SHEET_THICKNESS_M + 0.003
    occupied: list[tuple[float, float, float]] = []
    for object_id in ids:
        V = _object_vertices(library, object_id)
        if config.kind == "isolation":
            pose = config.pose
            if pose == "any":
                pose = "upright" if rng.random() < 0.25 else "lying"
            R = _rot_z(rng.uniform(-np.pi, np.pi))
            if pose == "lying":
                tilt = _rot_x(np.pi / 2) if rng.random() < 0.5 else _rot_y(np.pi / 2)
                R = R @ tilt
        elif config.kind == "packed":
            R = _rot_z(rng.uniform(-np.pi, np.pi))
        elif initial_pose == "stable":
            R = stable_poses(library.get(object_id)).sample(rng)
        else:
            R = _random_rotation(rng)
        Vr = V @ R.T
        center = 0.5 * (Vr.max(axis=0) + Vr.min(axis=0))
        radius = float(np.linalg.norm((Vr - center)[:, :2], axis=1).max())
        height = float(Vr[:, 2].max() - Vr[:, 2].min())
        if config.kind == "clutter":
            x = cx + rng.uniform(-half, half)
            y = cy + rng.uniform(-half, half)
            z_bottom = stack_z
            stack_z += height + 0.01
        else:
            # Spread objects without overlap where possible; stack what does not fit.
            for _ in range(100):
                x = cx + rng.uniform(-half, half)
                y = cy + rng.uniform(-half, half)
                if all(np.hypot(x - ox, y - oy) > radius + orad for ox, oy, orad in occupied):
                    z_bottom = SHEET_THICKNESS_M + 0.002
                    break
            else:
                z_bottom = stack_z
            stack_z = max(stack_z, z_bottom + height + 0.01)
            occupied.append((x, y, radius))
        # Object origin so that its rotated bounding box centre sits at (x, y) and its
        # lowest point at z_bottom.
        p = np.array([x - center[0], y - center[1], z_bottom - Vr[:, 2].min()])
        placements.append(ObjectPlacement(object_id, [float(v) for v in p], _quat_wxyz(R)))
    return SceneSpec(kind=config.kind, seed=int(seed), center_xy_m=[cx, cy], objects=placements)


@dataclass
class SceneWorld:
    """A plant with the table, the sheet and a scene's objects, ready to simulate/render."""

    diagram: object
    plant: object
    scene_graph: object
    instances: list
    simulator: object

    def plant_context(self):
        return self.plant.GetMyMutableContextFromRoot(self.simulator.get_mutable_context())

    def bodies(self) -> list:
        return [self.plant.GetBodyByName(OBJECT_BODY_NAME, i) for i in self.instances]


def default_scene_plant_config():
    """The plant settings of scene worlds built without any: the station's defaults."""
    from pydrake.multibody.plant import MultibodyPlantConfig

    return MultibodyPlantConfig(time_step=0.002, contact_model="hydroelastic_with_fallback",
                                discrete_contact_approximation="lagged")


def build_scene_world(spec: SceneSpec, library: ObjectLibrary, *, plant_config=None,
                      renderer_name: str | None = None, physics=None,
                      sheet_moves: bool = False) -> SceneWorld:
    """Table, sheet (held still) and the spec's objects at their poses, no robot.

    Args:
        renderer_name: also add a VTK renderer of this name (for depth images).
        physics: a `scenario.PhysicsConfig` (its sheet collision; a scene world has no
            gripper to take the margin); None: the reference settings.
        sheet_moves: the episode that will use the scene moves the sheet
            (`Scenario.sheet_moves`): the sheet then keeps its box collision, as in that
            episode, so that what rests beyond the sheet's edge here rests there too.
    """
    from pydrake.multibody.plant import AddMultibodyPlant
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    if plant_config is None:
        plant_config = default_scene_plant_config()
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(plant_config, builder)
    _, sheet = add_table_and_sheet(plant, scene_graph, spec.center_xy_m,
                                   sheet_collision=sheet_collision(physics,
                                                                   sheet_moves=sheet_moves),
                                   table_collision=table_collision(physics))
    instances = add_scene_objects(plant, spec, library)
    plant.Finalize()
    connect_sheet_hold(builder, plant, sheet)
    if renderer_name is not None:
        from pydrake.geometry import MakeRenderEngineVtk, RenderEngineVtkParams

        from drake_grasp.core.native import load_llvm_users_first

        # Before the first render: Mesa's LLVM must not shadow triton's (drake_grasp.core.native).
        load_llvm_users_first()
        scene_graph.AddRenderer(renderer_name, MakeRenderEngineVtk(RenderEngineVtkParams()))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    world = SceneWorld(diagram, plant, scene_graph, instances, simulator)
    set_object_poses(plant, world.plant_context(), spec, instances)
    return world


def _on_table(plant, plant_context, body) -> bool:
    """Not fallen off: above z = -5 cm, with its centre of mass over the table top."""
    X = plant.EvalBodyPoseInWorld(plant_context, body)
    p_com = X.multiply(body.CalcCenterOfMassInBodyFrame(plant_context))
    return bool(X.translation()[2] >= -0.05 and on_table_top(p_com))


# Settling. A free rigid body on a rigid plane has no rolling resistance, and the
# discrete contact solvers dissipate little at small speeds: dropped cylinders roll on,
# and some objects rock on a curved face for seconds (a camera body rocked +-4 degrees
# for over 4 s at 2 and 5 ms steps). Flat faces rattle in place instead (Drake issue
# 22213): a box on its face shows 10-25 mm/s and 0.3-0.6 rad/s at any instant while its
# pose changes by 0.1-0.6 mm in 2 s, so a speed sampled at one instant says little.
# `settle_world(..., verified=True)` therefore
# - gives each object's floating joint an angular damping while settling (a stand-in
#   for rolling resistance): its largest principal moment of inertia over
#   `SETTLE_DAMPING_TIME_S` (0.05 s made a mug lying on its side oscillate; 0.2 s took
#   twice as long as 0.1 s to stop the rocking camera);
# - judges rest by displacement, not speed: over a window of `SETTLE_WINDOW_S` every
#   object stays within speed_tol x window of where the window began (its centre of
#   mass, and its rotation angle times its half-length);
# - checks the pose with the damping off for another window: only a pose that stays put
#   in the undamped plant that the episodes simulate counts as settled.
SETTLE_DAMPING_TIME_S = 0.1
SETTLE_WINDOW_S = 0.2
_SETTLE_CHECK_S = 0.05


def _floating_joint(plant, body):
    """The free body's floating joint (the only joint of an object's model instance)."""
    (index,) = plant.GetJointIndices(body.model_instance())
    return plant.get_joint(index)


def _settle_scales(plant, bodies) -> tuple[list, list]:
    """Per body: the settling angular damping [N m s] (largest principal moment of
    inertia about the centre of mass / `SETTLE_DAMPING_TIME_S`), and the half-length
    sqrt(3 I_max / m) (exact for a thin rod) that turns a rotation into a displacement."""
    damping, half_length = [], []
    for body in bodies:
        M = body.default_spatial_inertia()
        i_max = float(np.linalg.eigvalsh(M.CalcRotationalInertia().CopyToFullMatrix3()).max())
        damping.append(i_max / SETTLE_DAMPING_TIME_S)
        half_length.append(float(np.sqrt(3.0 * i_max / M.get_mass())))
    return damping, half_length


def _set_settle_damping(plant, plant_context, bodies, damping, on: bool) -> None:
    for body, c in zip(bodies, damping):
        _floating_joint(plant, body).SetDampingVector(
            plant_context, np.array([c, c, c, 0.0, 0.0, 0.0]) if on else np.zeros(6))


def _at_rest_by_speed(plant, plant_context, bodies, speed_tol_m_s: float,
                      on_table_only: bool) -> bool:
    """Every object (still on the table) slower than the tolerance at this instant."""
    speeds = [np.linalg.norm(plant.EvalBodySpatialVelocityInWorld(plant_context, b).translational())
              for b in bodies if not on_table_only or _on_table(plant, plant_context, b)]
    return bool(not speeds or max(speeds) < speed_tol_m_s)


def settle_world(world: SceneWorld, spec: SceneSpec, *, speed_tol_m_s: float = 0.005,
                 max_time_s: float = 4.0, verified: bool = False) -> SceneSpec:
    """Simulates `world` until every object is at rest (or the time is up) and returns
    the resting spec; objects that fell off the table (below it, or with their centre of
    mass beyond its edge: `on_table_top`) are dropped.

    At rest, `verified` False: every object on the table slower than `speed_tol_m_s` at
    one instant (checked every 50 ms, from 0.3 s). `verified` True: settled with angular
    damping, judged by displacement over a window and checked without the damping (see
    `SETTLE_DAMPING_TIME_S`); objects falling off the table do not hold it up.
    The returned spec has `settled=True` only when the objects came to rest within
    `max_time_s`; otherwise `settled=False` (callers that need a scene at rest, such as
    the dataset generator, re-sample it). A verified world's damping is off on return.
    """
    simulator = world.simulator
    plant, plant_context = world.plant, world.plant_context()
    simulator.Initialize()
    bodies = world.bodies()
    t = t_start = simulator.get_context().get_time()
    t_end = t + max_time_s
    if verified:
        converged = _settle_verified(world, bodies, speed_tol_m_s, t_end)
    else:
        converged = False
        while t < t_end:
            t += _SETTLE_CHECK_S
            simulator.AdvanceTo(t)
            if t >= 0.3 and _at_rest_by_speed(plant, plant_context, bodies, speed_tol_m_s, False):
                converged = True
                break
        if not converged and t > t_start:
            # The time cap: at rest only if every object still on the table is slow (one
            # falling off the table never comes to rest, and is dropped below).
            converged = _at_rest_by_speed(plant, plant_context, bodies, speed_tol_m_s, True)
    settled = []
    for placement, body in zip(spec.objects, bodies):
        X = plant.EvalBodyPoseInWorld(plant_context, body)
        if not _on_table(plant, plant_context, body):
            continue  # fell off the table
        q = X.rotation().ToQuaternion()
        settled.append(ObjectPlacement(
            placement.object_id,
            [float(v) for v in X.translation()],
            [float(q.w()), float(q.x()), float(q.y()), float(q.z())],
        ))
    return SceneSpec(kind=spec.kind, seed=spec.seed, center_xy_m=list(spec.center_xy_m),
                     objects=settled, settled=converged)


def _settle_verified(world: SceneWorld, bodies, speed_tol_m_s: float, t_end: float) -> bool:
    """`settle_world`'s verified rest; True when reached before `t_end`."""
    simulator = world.simulator
    plant, plant_context = world.plant, world.plant_context()
    damping, half_length = _settle_scales(plant, bodies)
    reach = speed_tol_m_s * SETTLE_WINDOW_S  # how far an object may move in a window
    window = round(SETTLE_WINDOW_S / _SETTLE_CHECK_S)

    def poses():
        return [plant.EvalBodyPoseInWorld(plant_context, b) for b in bodies]

    def moved(X0, X1) -> bool:
        for body, a, b, r in zip(bodies, X0, X1, half_length):
            if not _on_table(plant, plant_context, body):
                continue  # falling off the table: dropped by the caller
            angle = a.rotation().inverse().multiply(b.rotation()).ToAngleAxis().angle()
            if max(np.linalg.norm(b.translation() - a.translation()), angle * r) > reach:
                return True
        return False

    _set_settle_damping(plant, plant_context, bodies, damping, True)
    t = simulator.get_context().get_time()
    t_min = t + 0.3
    anchor, calm_checks, damped = poses(), 0, True
    try:
        while t < t_end - 1e-9:
            t += _SETTLE_CHECK_S
            simulator.AdvanceTo(t)
            X = poses()
            if moved(anchor, X):
                anchor, calm_checks = X, 0
                if not damped:  # it moves again without the damping: settle on, damped
                    _set_settle_damping(plant, plant_context, bodies, damping, True)
                    damped = True
                continue
            calm_checks += 1
            if calm_checks >= window and t >= t_min:
                if not damped:
                    return True  # a window at rest without the damping
                _set_settle_damping(plant, plant_context, bodies, damping, False)
                anchor, calm_checks, damped = X, 0, False
        return False
    finally:
        _set_settle_damping(plant, plant_context, bodies, damping, False)


def _settle_plant_config(plant_config, physics):
    """`plant_config` with the physics profile's settling time step, if it has one."""
    if physics is None or physics.settle_time_step_s <= 0:
        return plant_config
    # A Drake config: no dataclasses.replace.
    plant_config = copy.deepcopy(plant_config or default_scene_plant_config())
    plant_config.time_step = float(physics.settle_time_step_s)
    return plant_config


def settle_scene(spec: SceneSpec, library: ObjectLibrary, *, plant_config=None,
                 speed_tol_m_s: float = 0.005, max_time_s: float = 4.0,
                 physics=None, sheet_moves: bool = False, verified: bool = False) -> SceneSpec:
    """Drops the objects onto the sheet and simulates until all are at rest.

    Objects that fell off the table (below it or beyond its edge) are removed. Returns a
    new spec with the final poses; `settled` says whether every remaining object came to rest
    within `max_time_s` (see `settle_world`, also for `verified`). `physics` (a
    `scenario.PhysicsConfig`) sets the margin, the sheet's collision and the settling time
    step; `sheet_moves`: see `build_scene_world`.
    """
    world = build_scene_world(spec, library,
                              plant_config=_settle_plant_config(plant_config, physics),
                              physics=physics, sheet_moves=sheet_moves)
    return settle_world(world, spec, speed_tol_m_s=speed_tol_m_s, max_time_s=max_time_s,
                        verified=verified)


def release_above(pile: SceneSpec, placement: ObjectPlacement, library: ObjectLibrary,
                  gap_m: float) -> ObjectPlacement:
    """`placement` (its x, y and orientation) moved up or down so that its lowest point is
    `gap_m` above the highest point of `pile` (or of the sheet, for an empty pile)."""
    V = _object_vertices(library, placement.object_id)
    R = placement.pose().rotation().matrix()
    z_bottom = max(scene_top_z(pile, library), SHEET_THICKNESS_M) + gap_m
    xyz = list(placement.xyz)
    xyz[2] = float(z_bottom - (V @ R.T)[:, 2].min())
    return ObjectPlacement(placement.object_id, xyz, list(placement.quat_wxyz))


def pour_scene(spec: SceneSpec, library: ObjectLibrary, *, plant_config=None, physics=None,
               drop_gap_m: float = 0.02, step_s: float = 0.5, speed_tol_m_s: float = 0.005,
               max_time_s: float = 4.0, sheet_moves: bool = False,
               verified: bool = False) -> SceneSpec:
    """Pours a clutter spec's objects one at a time, then settles the pile.

    Object k keeps its sampled x, y and orientation and is released with its lowest point
    `drop_gap_m` above the highest point of the pile poured before it, which has had
    `step_s` to come down (a pile poured from low height, as objects emptied from a box
    land; the column of `sample_scene` drops the last objects from over a metre, and the
    impacts scatter the pile). The whole pile then settles as in `settle_scene`
    (`verified`: see `settle_world`).
    """
    plant_config = _settle_plant_config(plant_config, physics)
    poured: list[ObjectPlacement] = []
    for placement in spec.objects:
        step = dataclasses.replace(spec, objects=poured + [release_above(
            dataclasses.replace(spec, objects=poured), placement, library, drop_gap_m)])
        world = build_scene_world(step, library, plant_config=plant_config, physics=physics,
                                  sheet_moves=sheet_moves)
        poured = settle_world(world, step, speed_tol_m_s=speed_tol_m_s, max_time_s=step_s).objects
    pile = dataclasses.replace(spec, objects=poured)
    world = build_scene_world(pile, library, plant_config=plant_config, physics=physics,
                              sheet_moves=sheet_moves)
    return settle_world(world, pile, speed_tol_m_s=speed_tol_m_s, max_time_s=max_time_s,
                        verified=verified)


def settle_options(config: SceneConfig) -> dict:
    """A scene config's settling (`settle_speed_tol_m_s`, `settle_max_time_s`, `settle`)
    as the keywords of `settle_scene` and `pour_scene`."""
    return {"speed_tol_m_s": config.settle_speed_tol_m_s,
            "max_time_s": config.settle_max_time_s,
            "verified": config.settle == "verified"}


def make_scene(config: SceneConfig, seed: int, library: ObjectLibrary, plant_config=None,
               physics=None, sheet_moves: bool = False) -> SceneSpec:
    """`sample_scene` then `settle_scene` (a clutter pile with `pour: sequential`:
    `pour_scene`) with the config's settling (`settle_options`). `sheet_moves`: pass
    `Scenario.sheet_moves` of the episode that will use the scene (`build_scene_world`)."""
    spec = sample_scene(config, seed, library)
    settle = pour_scene if config.kind == "clutter" and config.pour == "sequential" else settle_scene
    return settle(spec, library, plant_config=plant_config, physics=physics,
                  sheet_moves=sheet_moves, **settle_options(config))


def scenario_scene(scenario, library: ObjectLibrary, *, seed: int | None = None) -> SceneSpec:
    """`make_scene` for a `Scenario` (its scene config, seed, plant and physics), settled as
    its episode will hold it (`Scenario.sheet_moves`). `seed`: another seed than the
    scenario's."""
    return make_scene(scenario.scene, scenario.seed if seed is None else seed, library,
                      scenario.plant, physics=scenario.physics,
                      sheet_moves=scenario.sheet_moves)
