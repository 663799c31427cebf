"""Where a CTR isolation trial's wall time goes, under each physics profile.

Runs the same isolation trials (one per seed) under each profile, one after another in
one process (after one warm-up trial per profile), and prints the mean wall time per
trial; with `--profile-calls`, cProfile splits it into the contact simulation in C++
(`AdvanceTo`'s own time), the CNN, the record's ground-truth distance, the per-step
Python systems, depth post-processing, settling and building the Diagram.

    python analysis/trial_time_split.py --seeds 0,1,2,3,4,5 \
        --profiles fast,fast10,reference --profile-calls [--out FILE.json]

cProfile adds to the Python parts' time, not to C++'s; compare profiles within one run.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time

# bucket -> (file name suffix, function name): cumulative time per trial
BUCKETS = {
    "cnn": ("evaluator.py", "score_candidates"),
    "final_distance": ("episode.py", "final_distance"),
    "pose_output": ("controller.py", "_CalcPose"),
    "controller_update": ("controller.py", "_Update"),
    "gripper_output": ("gripper.py", "_CalcDesiredState"),
    "gripper_update": ("gripper.py", "_UpdateRamp"),
    "judge": ("judge.py", "_Update"),
    "depth_postprocess": ("depth.py", "_CalcDepthImage"),
    "build_diagram": ("episode.py", "build_episode_diagram"),
    "settle_scene": ("scene.py", "scenario_scene"),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,1,2,3,4,5", help="isolation scenario seeds")
    ap.add_argument("--profiles", default="fast,reference", help="physics profiles")
    ap.add_argument("--profile-calls", action="store_true", help="split the time (cProfile)")
    ap.add_argument("--out", default="", help="JSON file to write")
    args = ap.parse_args(argv)

    from drake_grasp.api import load_library, load_scenario, simulate_episode
    from drake_grasp.config.scenario import apply_physics_profile
    from drake_grasp.policies.evaluator import load_cnn

    seeds = [int(s) for s in args.seeds.split(",")]
    profiles = args.profiles.split(",")
    library = load_library()
    model = load_cnn("", threads=1)

    def scenario(profile: str, seed: int):
        sc = load_scenario(scenario_name="isolation",
                           scenario_text=f"{{seed: {seed}, policy: ctr}}")
        return apply_physics_profile(sc, profile)

    for p in profiles:  # imports, first render, caches
        simulate_episode(scenario(p, 999), library=library, record_depth=False, model=model)
    totals = {p: {"wall": 0.0, "sim": 0.0, "successes": 0} for p in profiles}
    profilers = {p: cProfile.Profile() for p in profiles}
    for seed in seeds:
        for p in profiles:
            sc = scenario(p, seed)
            t0 = time.perf_counter()
            if args.profile_calls:
                profilers[p].enable()
            run = simulate_episode(sc, library=library, record_depth=False, model=model)
            if args.profile_calls:
                profilers[p].disable()
            wall = time.perf_counter() - t0
            totals[p]["wall"] += wall
            totals[p]["sim"] += run.result.sim_time_s
            totals[p]["successes"] += bool(run.result.success)
            print(f"{p} seed {seed}: {'lifted' if run.result.success else 'failed'}, "
                  f"{wall:.2f} s wall, {run.result.sim_time_s:.1f} s simulated", flush=True)
    n = len(seeds)
    result = {}
    for p in profiles:
        row = {"trials": n, "successes": totals[p]["successes"],
               "wall_s_per_trial": totals[p]["wall"] / n,
               "sim_s_per_trial": totals[p]["sim"] / n}
        if args.profile_calls:
            stats = pstats.Stats(profilers[p]).stats
            for key, (suffix, name) in BUCKETS.items():
                row[key] = sum(v[3] for k, v in stats.items()
                               if k[0].endswith(suffix) and k[2] == name) / n
            row["simulation_cpp"] = sum(v[2] for k, v in stats.items() if "AdvanceTo" in k[2]) / n
        result[p] = {k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}
    if "reference" in result:
        ref = result["reference"]
        for p, row in result.items():
            row["trial_speedup_vs_reference"] = round(ref["wall_s_per_trial"]
                                                      / row["wall_s_per_trial"], 2)
            if "simulation_cpp" in row:
                row["simulation_speedup_vs_reference"] = round(ref["simulation_cpp"]
                                                               / row["simulation_cpp"], 2)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
