"""Simulation speed on fixed scenes: the same initial states for every package version.

A benchmark episode settles its own scene, and a change to the physics changes the
settled pile (settling is chaotic), so two versions of the package then time different
piles. This script times what does not depend on that:

- `settle`: settling the first attempts of 8 dataset scenes (`random` scenario, seed 3;
  scenes 1, 2, 13, 11, 21, 24, 0, 28: 1-5 objects) - wall time and simulated time;
- `clutter5`: the scripted grasp in a stored 5-object pile (`--pile`), twice - the real-time
  factor of the simulation loop (wrist depth rendered at 10 Hz, as in `bench`);
- `isolation`: the scripted grasp of a stored isolated object (`--isolated`), three times;
- with `--shift-pile`: the scripted grasp in a stored 5-object pile while the sheet is
  shifted (`clutter_shift`), with the table's collision a box and a half space
  (`physics.table_collision`), alternated twice in this process.

Run it with each package version, alternating, from a folder outside the checkout:

    cd /tmp && PYTHONPATH=/path/to/old python /path/to/analysis/fixed_scene_speed.py \\
        --pile P.json --isolated I.json

`--make-scenes` writes the two scene files (settled by the package on the path).
One JSON line per measurement on stdout.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

SETTLE_SCENES = (1, 2, 13, 11, 21, 24, 0, 28)


def _episode_rtf(scenario, library, scene, repeats: int) -> dict:
    from drake_grasp.evaluation.episode import simulate_episode

    rtf = []
    for _ in range(repeats):
        r = simulate_episode(scenario, library=library, scene=scene, record_depth=True,
                             visualize=False).result
        rtf.append(round(r.sim_time_s / r.details["simulation_wall_time_s"], 3))
    return {"rtf": rtf, "success": r.success, "final_distance_m": r.final_distance_m}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pile", required=True, help="the 5-object pile (SceneSpec JSON)")
    parser.add_argument("--isolated", required=True, help="the isolated object (SceneSpec JSON)")
    parser.add_argument("--shift-pile", default="",
                        help="a 5-object pile for clutter_shift (SceneSpec JSON); with "
                             "--make-scenes it is written too")
    parser.add_argument("--make-scenes", action="store_true",
                        help="settle and write the scene files, then stop")
    args = parser.parse_args(argv)

    from drake_grasp.learning.dataset import sample_dataset_scene
    from drake_grasp.objects import load_library
    from drake_grasp.core.provenance import code_version
    from drake_grasp.config.scenario import load_scenario, replace
    from drake_grasp.world.scene import SceneSpec, build_scene_world, scenario_scene, settle_world

    library = load_library(None)
    version = code_version()
    pile = replace(load_scenario(scenario_name="clutter", scenario_text=(
        "{policy: scripted, scene: {clutter_objects: 5}}")), seed=3, visualize=False)
    isolated = replace(load_scenario(scenario_name="isolation",
                                     scenario_text="{policy: scripted}"), seed=3, visualize=False)
    shift = replace(load_scenario(scenario_name="clutter_shift", scenario_text=(
        "{policy: scripted, scene: {clutter_objects: 5}}")), seed=3, visualize=False)
    if args.make_scenes:
        for scenario, path in ((pile, args.pile), (isolated, args.isolated),
                               (shift, args.shift_pile)):
            if path:
                Path(path).write_text(json.dumps(scenario_scene(scenario, library).to_dict()))
        return

    random = load_scenario(scenario_name="random", scenario_text="{seed: 3}")
    worlds = []
    for i in SETTLE_SCENES:
        spec = sample_dataset_scene(random, split="train", seed=3, scene_index=i, attempt=0,
                                    library=library)
        plant_config = copy.deepcopy(random.plant)
        plant_config.time_step = 0.005
        worlds.append((build_scene_world(spec, library, plant_config=plant_config,
                                         renderer_name="vtk", physics=random.physics), spec))
    t0 = time.perf_counter()
    sim = 0.0
    for world, spec in worlds:
        settle_world(world, spec, speed_tol_m_s=0.01, max_time_s=3.0, verified=True)
        sim += world.simulator.get_context().get_time()
    print(json.dumps({"version": version, "what": "settle", "scenes": len(worlds),
                      "wall_s": round(time.perf_counter() - t0, 3), "sim_s": round(sim, 3)}))
    for what, scenario, path, repeats in (("clutter5", pile, args.pile, 2),
                                          ("isolation", isolated, args.isolated, 3)):
        scene = SceneSpec.from_dict(json.loads(Path(path).read_text()))
        print(json.dumps({"version": version, "what": what,
                          **_episode_rtf(scenario, library, scene, repeats)}))
    if args.shift_pile:
        scene = SceneSpec.from_dict(json.loads(Path(args.shift_pile).read_text()))
        for table in ("box", "halfspace") * 2:
            scenario = copy.deepcopy(shift)
            scenario.physics.table_collision = table
            print(json.dumps({"version": version, "what": f"clutter5-shift table {table}",
                              **_episode_rtf(scenario, library, scene, 2)}))


if __name__ == "__main__":
    main()
