"""Does the dataset's settling give the same scenes at rest with a larger time step?

    python analysis/settle_step.py --scenes 120 --steps 0.005,0.01 --out analysis/results/settle-step

Settles the dataset's scenes exactly as `drake-grasp generate` does (`dataset.
sample_dataset_scene`, `scene.settle_world(verified=True)`, the `DatasetConfig`'s
tolerance and cap, the `random` scenario's physics profile) once per settling time step,
then judges every result in the physics the episodes and the grasp lab simulate: a fresh
scene world at the scenario's own plant step (5 ms with `fast`), the objects placed at
the settled poses, simulated for 1 s without any damping. A settled object that moves
there was not at rest.

Writes `summary.json` (per step: settled share of the first attempts, by object count and
category, settling wall and simulated time per attempt and per kept scene, the drift in
the episodes' physics) with one row per scene and step.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np


def settle_once(index: int, seed: int, step_s: float, scenario, library) -> dict:
    from drake_grasp.learning.dataset import DatasetConfig, sample_dataset_scene
    from drake_grasp.world.scene import build_scene_world, settle_world

    cfg = DatasetConfig()
    spec = sample_dataset_scene(scenario, split="train", seed=seed, scene_index=index,
                                attempt=0, library=library)
    plant_config = copy.deepcopy(scenario.plant)
    plant_config.time_step = step_s
    world = build_scene_world(spec, library, plant_config=plant_config,
                              physics=scenario.physics)
    t0 = time.perf_counter()
    out = settle_world(world, spec, speed_tol_m_s=cfg.settle_speed_tol_m_s,
                       max_time_s=cfg.settle_max_time_s, verified=True)
    wall = time.perf_counter() - t0
    row = {"scene": index, "step_s": step_s, "objects": [o.object_id for o in spec.objects],
           "settled": bool(out.settled), "wall_s": round(wall, 4),
           "sim_s": round(world.simulator.get_context().get_time(), 3), "drift_mm": []}
    if out.settled and out.objects:
        row["drift_mm"] = drift_in_episode_physics(out, scenario, library)
    return row


def drift_in_episode_physics(spec, scenario, library, seconds: float = 1.0) -> list[float]:
    """How far each object of a settled spec moves in `seconds` of the scenario's own
    plant (its time step, no damping), placed at the spec's poses [mm]."""
    from drake_grasp.world.scene import build_scene_world

    world = build_scene_world(spec, library, plant_config=copy.deepcopy(scenario.plant),
                              physics=scenario.physics)
    plant, context = world.plant, world.plant_context()
    bodies = world.bodies()
    before = [plant.EvalBodyPoseInWorld(context, b).translation() for b in bodies]
    world.simulator.Initialize()
    world.simulator.AdvanceTo(seconds)
    after = [plant.EvalBodyPoseInWorld(context, b).translation() for b in bodies]
    return [round(1000 * float(np.linalg.norm(b - a)), 2) for a, b in zip(before, after)]


def summarize(rows: list[dict]) -> dict:
    from settle_check import settle_stats

    out = {}
    for step in sorted({r["step_s"] for r in rows}):
        mine = [r for r in rows if r["step_s"] == step]
        drift = np.array([d for r in mine if r["settled"] for d in r["drift_mm"]])
        out[f"{step:g}"] = {
            **settle_stats(mine, digits=4),
            "settled": int(sum(r["settled"] for r in mine)),
            "settled_objects": int(drift.size),
            "drift_1s_over_1mm": int((drift > 1).sum()),
            "drift_1s_over_3mm": int((drift > 3).sum()),
            "drift_1s_max_mm": round(float(drift.max()), 1) if drift.size else None,
            "drift_1s_median_mm": round(float(np.median(drift)), 3) if drift.size else None,
        }
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=120, help="dataset scenes (first attempts)")
    p.add_argument("--seed", type=int, default=0, help="dataset seed (`generate --seed`)")
    p.add_argument("--steps", default="0.005,0.01", help="settling time steps [s], comma-separated")
    p.add_argument("--out", required=True, help="folder for summary.json")
    args = p.parse_args(argv)
    if args.scenes < 1:
        p.error(f"--scenes: expected >= 1, got {args.scenes}")
    try:
        steps = [float(s) for s in args.steps.split(",")]
    except ValueError:
        p.error(f"--steps: expected comma-separated numbers, got {args.steps!r}")
    if any(not 0 < s <= 0.05 for s in steps):
        p.error(f"--steps: expected steps in (0, 0.05] s, got {args.steps!r}")
    from tqdm import tqdm

    from drake_grasp.objects import load_library
    from drake_grasp.core.files import atomic_write_text
    from drake_grasp.config.scenario import load_scenario

    scenario, library = load_scenario(scenario_name="random"), load_library(None)
    # Alternate the steps scene by scene: both see the same machine load.
    rows = [settle_once(i, args.seed, s, scenario, library)
            for i in tqdm(range(args.scenes), desc="scenes") for s in steps]
    summary = {"scenes": args.scenes, "seed": args.seed,
               "episode_plant_time_step_s": scenario.plant.time_step,
               "steps": summarize(rows)}
    atomic_write_text(Path(args.out) / "summary.json",
                      json.dumps({**summary, "rows": rows}, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
