"""How the clutter pile is poured, and why clutter runs end with objects left on the table.

Three commands:

    # per run of a clutter results folder: objects outside the start view (+-15 cm of the
    # pile's centre) before the first attempt and at the run's end, piles not at rest,
    # and per pile the objects' footprints summed
    python analysis/clutter_pour.py results analysis/results/paper/clutter

    # settle sampled 10-object piles with today's column drop, with a box around the
    # column that is then removed, or with the dataset's verified settling (the objects'
    # angular velocity damped, rest judged by displacement: scene.settle_world)
    python analysis/clutter_pour.py settle --mode column --seeds 0,1,2

    # where the objects of one pile are while it settles (distance from the centre, speed)
    python analysis/clutter_pour.py trace --seed 0

`settle` and `trace` build the scene world as `drake_grasp.world.scene.settle_scene` does (the
`clutter` scenario with 10 objects in a +-6 cm region, as the `clutter` experiment), with
the modes' additions; they measure, they do not change what the experiments use.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import time

import numpy as np

# The clutter run end rule's "in view": within +-15 cm of the pile's centre.
from drake_grasp.evaluation.trial_worker import IN_VIEW_HALF_EXTENT_M as VIEW_HALF_M


def out_of_view(objects: list[dict], center) -> list[str]:
    return [o["object_id"] for o in objects
            if max(abs(o["xyz"][0] - center[0]), abs(o["xyz"][1] - center[1])) > VIEW_HALF_M]


def footprint_cm2(objects: list[dict]) -> float:
    """The objects' footprints summed: the area of each settled mesh's convex hull
    projected on the table [cm^2] (what the pile would cover laid out in one layer)."""
    from scipy.spatial import ConvexHull

    from drake_grasp.objects import load_library, visual_mesh
    from drake_grasp.world.scene import ObjectPlacement

    library = load_library(None)
    total = 0.0
    for o in objects:
        R = ObjectPlacement(o["object_id"], o["xyz"], o["quat_wxyz"]).pose().rotation().matrix()
        V = np.asarray(visual_mesh(library.get(o["object_id"])).vertices) @ R.T
        total += ConvexHull(V[:, :2]).volume  # the area, in 2-D
    return 1e4 * total


def results(folder: str) -> dict:
    """Per run: objects out of view at the start and at the end, how the run ended."""
    from drake_grasp.evaluation.records import load_records

    records = [r.to_dict() for r in load_records(folder)]
    if not records:
        raise SystemExit(f"{folder}: no trial records")
    runs = collections.defaultdict(list)
    for r in records:
        runs[(r["condition"], r["run_index"])].append(r)
    rows, per_category, seen = [], collections.Counter(), collections.Counter()
    piles = {}
    for (condition, run), rs in sorted(runs.items()):
        rs.sort(key=lambda r: r["attempt_index"])
        start = rs[0]["extra"]["scene"]
        end = rs[-1]["extra"].get("next_scene") or {"objects": []}
        piles[start["seed"]] = start
        rows.append({
            "condition": condition, "run": run, "attempts": len(rs),
            "grasped": sum(bool(r["success"]) for r in rs),
            "out_of_view_at_start": len(out_of_view(start["objects"], start["center_xy_m"])),
            "left_at_end": len(end["objects"]),
            "left_at_end_out_of_view": len(out_of_view(end["objects"], start["center_xy_m"])),
            "start_pile_at_rest": bool(start.get("settled")),
            "run_end": rs[-1]["extra"].get("run_end", "")})
    for pile in piles.values():
        outside = set(out_of_view(pile["objects"], pile["center_xy_m"]))
        for o in pile["objects"]:
            category = o["object_id"].rsplit("_", 1)[0]
            seen[category] += 1
            per_category[category] += o["object_id"] in outside
    return {"runs": rows,
            "piles": len(piles),
            "footprint_cm2_per_pile": [round(footprint_cm2(p["objects"])) for p in piles.values()],
            "piles_at_rest": sum(bool(p.get("settled")) for p in piles.values()),
            "out_of_view_at_start_by_category": {
                c: {"outside": per_category[c], "objects": seen[c]} for c in sorted(seen)}}


def _scenario_and_library():
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario

    scenario = load_scenario(scenario_name="clutter")
    config = dataclasses.replace(scenario.scene, clutter_objects=10, region_half_extent_m=0.06)
    return scenario, config, load_library(None)


def _add_walls(plant, center, half_m: float, height_m: float = 1.6, thick_m: float = 0.02):
    """Four rigid walls around the column (the 'box' the pile is poured from)."""
    from pydrake.geometry import AddContactMaterial, AddRigidHydroelasticProperties, Box, ProximityProperties
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import CoulombFriction

    props = ProximityProperties()
    AddRigidHydroelasticProperties(props)
    AddContactMaterial(friction=CoulombFriction(0.3, 0.3), properties=props)
    cx, cy = center
    side = 2 * half_m + 2 * thick_m
    for i, (dx, dy, sx, sy) in enumerate([(half_m + thick_m / 2, 0, thick_m, side),
                                          (-half_m - thick_m / 2, 0, thick_m, side),
                                          (0, half_m + thick_m / 2, 2 * half_m, thick_m),
                                          (0, -half_m - thick_m / 2, 2 * half_m, thick_m)]):
        plant.RegisterCollisionGeometry(
            plant.world_body(), RigidTransform([cx + dx, cy + dy, height_m / 2 + 0.003]),
            Box(sx, sy, height_m), f"pour_wall_{i}", props)


def _world(spec, library, physics, *, walls_half_m: float = 0.0):
    from pydrake.multibody.plant import AddMultibodyPlant
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    from drake_grasp.world import scene as S
    from drake_grasp.world import table as T

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(S.default_scene_plant_config(), builder)
    _, sheet = T.add_table_and_sheet(plant, scene_graph, spec.center_xy_m,
                                     sheet_collision=S.sheet_collision(physics, sheet_moves=False))
    instances = S.add_scene_objects(plant, spec, library)
    if walls_half_m > 0:
        _add_walls(plant, spec.center_xy_m, walls_half_m)
    plant.Finalize()
    T.connect_sheet_hold(builder, plant, sheet)
    diagram = builder.Build()
    world = S.SceneWorld(diagram, plant, scene_graph, instances, Simulator(diagram))
    S.set_object_poses(plant, world.plant_context(), spec, instances)
    return world


def settle(mode: str, seeds: list[int], *, box_half_m: float) -> list[dict]:
    from drake_grasp.world import scene as S

    scenario, config, library = _scenario_and_library()
    rows = []
    for seed in seeds:
        t0 = time.perf_counter()
        spec = S.sample_scene(config, seed, library)
        if mode == "box":
            boxed = S.settle_world(_world(spec, library, scenario.physics, walls_half_m=box_half_m),
                                   spec, max_time_s=3.0)
            out = S.settle_world(_world(boxed, library, scenario.physics), boxed, max_time_s=4.0)
        else:
            out = S.settle_world(_world(spec, library, scenario.physics), spec, max_time_s=4.0,
                                 verified=mode == "verified")
        placed = [{"object_id": o.object_id, "xyz": list(o.xyz)} for o in out.objects]
        outside = out_of_view(placed, out.center_xy_m) + ["(fell off)"] * (len(spec.objects)
                                                                         - len(out.objects))
        rows.append({"mode": mode, "seed": seed, "outside": len(outside),
                     "outside_objects": outside, "at_rest": bool(out.settled),
                     "column_top_m": round(max(o.xyz[2] for o in spec.objects), 3),
                     "wall_s": round(time.perf_counter() - t0, 1)})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def trace(seed: int, times=(0.25, 0.5, 1.0, 2.0, 4.0)) -> None:
    from drake_grasp.world import scene as S

    scenario, config, library = _scenario_and_library()
    spec = S.sample_scene(config, seed, library)
    world = _world(spec, library, scenario.physics)
    plant, context, simulator = world.plant, world.plant_context(), world.simulator
    simulator.Initialize()
    cx, cy = spec.center_xy_m
    print("start heights [m]:", [round(o.xyz[2], 2) for o in spec.objects])
    for t in times:
        simulator.AdvanceTo(t)
        rows = []
        for placement, body in zip(spec.objects, world.bodies()):
            p = plant.EvalBodyPoseInWorld(context, body).translation()
            v = plant.EvalBodySpatialVelocityInWorld(context, body).translational()
            rows.append((placement.object_id, round(max(abs(p[0] - cx), abs(p[1] - cy)), 2),
                         round(float(np.linalg.norm(v)), 2)))
        print(f"t = {t} s: outside +-15 cm {sum(r[1] > VIEW_HALF_M for r in rows)}; "
              "(object, distance m, speed m/s):", rows, flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("results", help="objects out of view per run of a clutter results folder")
    r.add_argument("folder")
    s = sub.add_parser("settle", help="settle sampled piles with a pour mode")
    s.add_argument("--mode", choices=["column", "box", "verified"], default="column")
    s.add_argument("--seeds", default="0", help="'0,1,2'")
    s.add_argument("--box-half-m", type=float, default=0.10, help="box inner half width")
    t = sub.add_parser("trace", help="positions and speeds of one pile while it settles")
    t.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.command == "results":
        print(json.dumps(results(args.folder), indent=1))
    elif args.command == "settle":
        settle(args.mode, [int(v) for v in args.seeds.split(",")],
               box_half_m=args.box_half_m)
    else:
        trace(args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
