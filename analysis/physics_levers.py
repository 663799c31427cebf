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

    from drake_grasp.cli.bench import BENCH_SEED, _machine, episode_rtf

    rows = []
    for name, text in LEVERS:
        override = yaml.safe_load(text) if text else {}
        override.setdefault("scene", {})["clutter_objects"] = args.objects
        override["policy"] = "scripted"
        r = episode_rtf("clutter", json.dumps(override), physics_profile="reference",
                        record_depth=False)
        rows.append({"lever": name, "scenario_text": text, "time_step_s": r["time_step_s"],
                     "rtf": round(r["rtf"], 3), "simulation_wall_s": round(r["wall_s"], 2),
                     "episode_wall_s": round(r["episode_wall_s"], 2),
                     "success": bool(r["success"]), "failure_class": r["failure_class"]})
        ref = rows[0]
        print(f"{name:60s} rtf {rows[-1]['rtf']:6.3f} ({rows[-1]['rtf'] / ref['rtf']:4.2f}x)  "
              f"episode {r['episode_wall_s']:6.2f} s "
              f"({ref['episode_wall_s'] / r['episode_wall_s']:4.2f}x)  success {r['success']}",
              flush=True)
    for row in rows:
        row["rtf_ratio"] = round(row["rtf"] / rows[0]["rtf"], 2)
        row["episode_speedup"] = round(rows[0]["episode_wall_s"] / row["episode_wall_s"], 2)
    if args.out:
        from drake_grasp.core.files import atomic_write_text

        atomic_write_text(args.out, json.dumps({"episode": f"scripted, clutter, {args.objects} "
                                                           f"objects, seed {BENCH_SEED}",
                                                "rows": rows, "machine": _machine(),
                                                "date": time.strftime("%Y-%m-%d")}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
