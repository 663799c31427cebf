"""Each physics lever on its own, then combined: the same scripted 5-object clutter
episode (bench seed) run in one process, one configuration after another, starting from
the reference profile. Prints a table and writes JSON.

    python analysis/physics_levers.py --out analysis/results/physics_levers.json

Ratios are against the reference configuration measured in the same run (absolute
timings differ up to 2x between machines).
"""

from __future__ import annotations

import argparse
import json
import time

import yaml

LEVERS = [
    ("reference (2 ms, box sheet, no margin)", ""),
    ("5 ms step", "{plant: {time_step: 0.005}}"),
    ("10 ms step", "{plant: {time_step: 0.01}}"),
    ("half-space sheet", "{physics: {sheet_collision: auto}}"),
    ("pad margin 0.1 mm", "{physics: {hydroelastic_margin_m: 0.0001}}"),
    ("fast profile (5 ms + half space + margin + 5 ms settling)", "{physics: {profile: fast}}"),
    ("fast profile at 10 ms", "{physics: {profile: fast}, plant: {time_step: 0.01}}"),
]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=None, help="write the results as JSON here")
    p.add_argument("--objects", type=int, default=5, help="objects in the pile (default 5)")
    args = p.parse_args(argv)

    from drake_grasp.bench import BENCH_SEED, _machine
    from drake_grasp.episode import simulate_episode
    from drake_grasp.scenario import load_scenario, replace

    rows = []
    for name, text in LEVERS:
        override = yaml.safe_load(text) if text else {}
        override.setdefault("scene", {})["clutter_objects"] = args.objects
        override["policy"] = "scripted"
        scenario = load_scenario(scenario_name="clutter", physics_profile="reference",
                                 scenario_text=json.dumps(override))
        scenario = replace(scenario, seed=BENCH_SEED, visualize=False)
        t0 = time.perf_counter()
        run = simulate_episode(scenario, scenario_name="clutter", record_depth=False)
        wall = time.perf_counter() - t0
        r = run.result
        sim_wall = r.details["simulation_wall_time_s"]
        rows.append({"lever": name, "scenario_text": text, "time_step_s": scenario.plant.time_step,
                     "rtf": round(r.sim_time_s / sim_wall, 3), "simulation_wall_s": round(sim_wall, 2),
                     "episode_wall_s": round(wall, 2), "success": bool(r.success),
                     "failure_class": r.details.get("failure_class")})
        ref = rows[0]
        print(f"{name:60s} rtf {rows[-1]['rtf']:6.3f} ({rows[-1]['rtf'] / ref['rtf']:4.2f}x)  "
              f"episode {wall:6.2f} s ({ref['episode_wall_s'] / wall:4.2f}x)  "
              f"success {r.success}", flush=True)
    for row in rows:
        row["rtf_ratio"] = round(row["rtf"] / rows[0]["rtf"], 2)
        row["episode_speedup"] = round(rows[0]["episode_wall_s"] / row["episode_wall_s"], 2)
    if args.out:
        from drake_grasp.results import atomic_write_text

        atomic_write_text(args.out, json.dumps({"episode": f"scripted, clutter, {args.objects} "
                                                           f"objects, seed {BENCH_SEED}",
                                                "rows": rows, "machine": _machine(),
                                                "date": time.strftime("%Y-%m-%d")}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
