"""Settling the dataset's scenes from uniform vs stable initial poses, side by side.

For dataset scenes 0..N-1 (seed S, attempt 0, the train split, the `random` scenario),
each drawn both ways (`DatasetConfig.initial_pose` "uniform" and "stable", interleaved
scene by scene so machine load hits both alike), this runs exactly what
`dataset.generate_scene` runs before the grasp search - the scene world with the
dataset's settling step, then `scene.settle_world(verified=True)` with the dataset's
tolerance and time cap - and records, per scene and side: settled or not (not settled:
the scene is thrown away and its next seed drawn), the simulated time to rest, the wall
seconds of build and settle, and the objects that fell off the table.

    python analysis/stable_pose_settle.py --scenes 60 --seed 3 --out DIR

writes DIR/settle.json (per-scene rows and the totals).
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path


def settle_one(scenario, config, library, *, seed: int, index: int, initial_pose: str) -> dict:
    from drake_grasp.learning.dataset import sample_dataset_scene
    from drake_grasp.world.scene import build_scene_world, settle_world

    t0 = time.perf_counter()
    spec = sample_dataset_scene(scenario, split="train", seed=seed, scene_index=index,
                                attempt=0, library=library, initial_pose=initial_pose)
    plant_config = copy.deepcopy(scenario.plant)
    plant_config.time_step = config.settle_time_step_s
    world = build_scene_world(spec, library, plant_config=plant_config,
                              physics=scenario.physics)
    t1 = time.perf_counter()
    settled = settle_world(world, spec, speed_tol_m_s=config.settle_speed_tol_m_s,
                           max_time_s=config.settle_max_time_s, verified=True)
    t2 = time.perf_counter()
    return {"scene": index, "initial_pose": initial_pose, "objects": len(spec.objects),
            "settled": settled.settled, "fell_off": len(spec.objects) - len(settled.objects),
            "sim_s": round(world.simulator.get_context().get_time(), 3),
            "sample_build_s": round(t1 - t0, 3), "settle_s": round(t2 - t1, 3)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=60)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.learning.dataset import DatasetConfig
    from drake_grasp.objects import load_library

    scenario = load_scenario(scenario_name="random", scenario_text=f"{{seed: {args.seed}}}")
    config, library = DatasetConfig(), load_library(None)
    rows = []
    for i in range(args.scenes):
        for pose in ("uniform", "stable"):
            rows.append(settle_one(scenario, config, library, seed=args.seed, index=i,
                                   initial_pose=pose))
            print(json.dumps(rows[-1]), flush=True)
    totals = {}
    for pose in ("uniform", "stable"):
        rs = [r for r in rows if r["initial_pose"] == pose]
        totals[pose] = {"scenes": len(rs), "unsettled": sum(not r["settled"] for r in rs),
                        "fell_off_objects": sum(r["fell_off"] for r in rs),
                        "sim_s": round(sum(r["sim_s"] for r in rs), 2),
                        "settle_wall_s": round(sum(r["settle_s"] for r in rs), 2),
                        "sample_build_wall_s": round(sum(r["sample_build_s"] for r in rs), 2)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "settle.json").write_text(json.dumps({"seed": args.seed, "totals": totals,
                                                 "rows": rows}, indent=1))
    print(json.dumps(totals, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
