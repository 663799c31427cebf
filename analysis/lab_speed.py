"""The grasp lab's speed levers, side by side in one process: `bench_grasp_checks_per_s`'s
six grasps of a lying can (default physics profile, one core), checked under each lab
variant in turn, the rounds alternated so that other load on the machine falls on all.

    python analysis/lab_speed.py --rounds 2 --out analysis/results/lab-speed-2026-12-07/speed.json
    python analysis/lab_speed.py --old-tree /tmp/old ...   # adds the package at another commit

Variants: `rebuild_six` (a Diagram per check, the six-segment shake: the lab before
2026-12-07, trajectory for trajectory), `reuse_six` (one Diagram per scene),
`rebuild_five` (the shake x, y, z, yaw, pitch), `reuse_five` (both: today's default). With
`--old-tree DIR` (a checkout of an earlier commit), `old_code` runs that package's
`check_grasps` in a subprocess, timed the same way, in the same rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

_SETUP = """
import numpy as np
from drake_grasp.cli.bench import BENCH_SEED
from drake_grasp.config.scenario import load_scenario
from drake_grasp.evaluation.lab import check_grasps, isolated_scene
from drake_grasp.geometry.grasps import find_grasps
from drake_grasp.objects import load_library

library = load_library(None)
rng = np.random.default_rng(BENCH_SEED)
scene = isolated_scene("can_000", library, lying=True)
found = find_grasps(scene, library, rng)
chosen = rng.choice(len(found), size=min(6, len(found)), replace=False)[:GRASPS]
scenario = load_scenario(physics_profile="")
"""

_OLD = _SETUP + """
import json, sys, time
t0 = time.perf_counter()
results = check_grasps(None, found.poses[chosen], scene=scene, library=library,
                       object_indices=found.object_index[chosen], scenario=scenario)
wall = time.perf_counter() - t0
print(json.dumps({"wall_s": wall, "held": [bool(r.held) for r in results],
                  "sim_s": [r.details["sim_time_s"] for r in results]}))
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=2, help="alternated rounds (default 2)")
    p.add_argument("--old-tree", default=None,
                   help="a checkout of an earlier commit whose check_grasps is timed too")
    p.add_argument("--grasps", type=int, default=6,
                   help="the first N of the bench's six grasps (default 6)")
    p.add_argument("--variants", default="rebuild_six,reuse_six,rebuild_five,reuse_five",
                   help="comma-separated variants to time, in this order in each round")
    p.add_argument("--out", required=True, help="JSON file to write")
    args = p.parse_args(argv)

    namespace: dict = {"GRASPS": args.grasps}
    exec(_SETUP, namespace)  # the bench's scene, grasps and scenario
    from drake_grasp.core.files import atomic_write_text
    from drake_grasp.evaluation.lab import SHAKE_AXES, LabConfig, check_grasps

    known = {"rebuild_six": (False, SHAKE_AXES), "reuse_six": (True, SHAKE_AXES),
             "rebuild_five": (False, None), "reuse_five": (True, None)}
    names = [v for v in args.variants.split(",") if v]
    if not set(names) <= set(known):
        raise SystemExit(f"--variants: expected names from {sorted(known)}, got {names}")
    variants = {k: known[k] for k in names}
    n = namespace
    runs: dict[str, list] = {k: [] for k in variants}
    if args.old_tree:
        runs["old_code"] = []
    # One warm-up check (imports, first Diagram) outside the timing.
    check_grasps(None, n["found"].poses[n["chosen"][:1]], scene=n["scene"], library=n["library"],
                 object_indices=n["found"].object_index[n["chosen"][:1]], scenario=n["scenario"])
    for _ in range(args.rounds):
        for name, (reuse, axes) in variants.items():
            lab = LabConfig() if axes is None else LabConfig(shake_axes=axes)
            t0 = time.perf_counter()
            results = check_grasps(None, n["found"].poses[n["chosen"]], scene=n["scene"],
                                   library=n["library"], scenario=n["scenario"], lab=lab,
                                   object_indices=n["found"].object_index[n["chosen"]],
                                   reuse=reuse)
            runs[name].append({"wall_s": time.perf_counter() - t0,
                               "held": [bool(r.held) for r in results],
                               "sim_s": [r.details["sim_time_s"] for r in results]})
            print(name, json.dumps(runs[name][-1]), os.getloadavg(), flush=True)
        if args.old_tree:
            # Run from the old tree: "python -c" puts the working folder first on sys.path.
            env = dict(os.environ, PYTHONPATH=args.old_tree)
            done = subprocess.run([sys.executable, "-c", f"GRASPS = {args.grasps}\n" + _OLD],
                                  env=env, check=True, cwd=args.old_tree,
                                  capture_output=True, text=True)
            runs["old_code"].append(json.loads(done.stdout.strip().splitlines()[-1]))
            print("old_code", json.dumps(runs["old_code"][-1]), os.getloadavg(), flush=True)
    checks = len(n["chosen"])
    summary = {name: {"checks_per_s": [round(checks / r["wall_s"], 3) for r in rs],
                      "held": rs[0]["held"], "sim_s_per_check": round(sum(rs[0]["sim_s"]) / checks, 3)}
               for name, rs in runs.items()}
    out = {"machine": _machine(), "date": time.strftime("%Y-%m-%d %H:%M"),
           "load_average": os.getloadavg(), "checks_per_round": checks,
           "rounds": args.rounds, "variants": summary}
    atomic_write_text(args.out, json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))
    return 0


def _machine() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line.split(":", 1)[1].strip() for line in f if "model name" in line)
    except (OSError, StopIteration):
        model = "unknown CPU"
    return f"{model}, {os.cpu_count()} cores"


if __name__ == "__main__":
    raise SystemExit(main())
