"""Label recall against precision: the ground truth's torque test with and without the
grasp lab's shake among its load cases.

The ground truth (`grasps.find_grasps`) rejects a grasp when gravity, or gravity plus the
lab's shake (`grasps.SHAKE_ACCELERATION_M_S2`, 12.6 m/s^2 along +-x, +-y, +-z), asks the
pads' torsional friction for more than `MAX_TORQUE_RATIO`. Some isolation scenes (the
hammer, the upright tetra pak) then have no grasp at all, although the experiments' success
is lift and hold, without a shake. This script takes the `isolation` experiment's scenes
(trial i as `evaluate` builds it), finds the grasps the static load case alone accepts but
the shake rejects ("admitted by the static test"), executes a random sample of them in the
grasp lab, and reports how many held through lift and hold, and through the shake.

    python analysis/label_load_case.py --trials 120 --per-scene 2 --workers 2 \
        --out analysis/results/label-load-case
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path

import numpy as np


@contextlib.contextmanager
def gravity_only():
    """Within the block, the torque test's load cases are gravity alone (no shake)."""
    import drake_grasp.geometry.hand_checks as G

    original = G._gravity_torque_ratio
    G._gravity_torque_ratio = lambda *a, **k: original(*a, **{**k, "accel_m_s2": 0.0})
    try:
        yield
    finally:
        G._gravity_torque_ratio = original


def _grasps(scene, library, seed: int, *, shake: bool):
    from drake_grasp.geometry.grasps import find_grasps

    with contextlib.nullcontext() if shake else gravity_only():
        return find_grasps(scene, library, np.random.default_rng([seed, 61]))


def isolation_scene(index: int, seed: int):
    """(scenario, settled scene, library) of the `isolation` experiment's trial `index`."""
    from drake_grasp.evaluation.experiments import EXPERIMENTS, trial_scenario
    from drake_grasp.objects import load_library
    from drake_grasp.world.scene import scenario_scene

    library = load_library(None)
    exp = EXPERIMENTS["isolation"]
    scenario = trial_scenario(exp, exp.conditions[0], index, base_seed=seed, library=library)
    return scenario, scenario_scene(scenario, library), library


def run_scene(index: int, seed: int, per_scene: int) -> dict:
    from drake_grasp.evaluation.lab import check_grasp

    t0 = time.perf_counter()
    scenario, scene, library = isolation_scene(index, seed)
    with_shake = _grasps(scene, library, scenario.seed, shake=True)
    static = _grasps(scene, library, scenario.seed, shake=False)
    # The same candidates are drawn either way (same rng); the static set is a superset.
    shake_keys = {tuple(np.round(p[:3, 3], 6)) + tuple(np.round(p[:3, 0], 6))
                  for p in with_shake.poses}
    admitted = [i for i, p in enumerate(static.poses)
                if tuple(np.round(p[:3, 3], 6)) + tuple(np.round(p[:3, 0], 6)) not in shake_keys]
    rng = np.random.default_rng([seed, index, 97])
    chosen = rng.choice(admitted, size=min(per_scene, len(admitted)), replace=False) \
        if admitted else []
    checks = []
    for i in chosen:
        r = check_grasp(None, static.poses[int(i)], scene=scene, scenario=scenario,
                        library=library, object_index=int(static.object_index[int(i)]))
        checks.append({"held": bool(r.held), "failure": r.failure,
                       "lift_hold": bool(r.held or r.failure == "dropped-by-shake")})
    return {"index": index, "object": scenario.scene.object_ids[0],
            "pose": scenario.scene.pose, "grasps_with_shake": int(len(with_shake.poses)),
            "grasps_static": int(len(static.poses)), "admitted_by_static": len(admitted),
            "checks": checks, "wall_s": time.perf_counter() - t0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=120)
    p.add_argument("--per-scene", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    from drake_grasp.evaluation.montecarlo import parallel_map
    from drake_grasp.core.provenance import code_version
    from drake_grasp.evaluation.records import wilson_interval

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scenes = parallel_map(run_scene, [(i, args.seed, args.per_scene) for i in range(args.trials)],
                          workers=args.workers, desc="label load case")

    def rate(checks, key):
        k, n = sum(c[key] for c in checks), len(checks)
        return {"held": k, "checked": n, "rate": k / n if n else None,
                "ci95": list(wilson_interval(k, n)) if n else None}

    checks = [c for s in scenes for c in s["checks"]]
    uncovered = [s for s in scenes if s["grasps_with_shake"] == 0]
    by_object: dict = {}
    for s in scenes:
        by_object.setdefault(s["object"], []).extend(s["checks"])
    summary = {
        "scenes": len(scenes),
        "scenes_without_grasps_with_shake": len(uncovered),
        "of_those_with_static_grasps": sum(s["grasps_static"] > 0 for s in uncovered),
        "admitted_checked_lift_hold": rate(checks, "lift_hold"),
        "admitted_checked_with_shake": rate(checks, "held"),
        "uncovered_scenes_lift_hold": rate([c for s in uncovered for c in s["checks"]],
                                           "lift_hold"),
        "per_object_lift_hold": {o: rate(c, "lift_hold") for o, c in sorted(by_object.items())},
        "seed": args.seed, "per_scene": args.per_scene, "code_version": code_version(),
        "worker_s": sum(s["wall_s"] for s in scenes),
    }
    (out / "label_load_case.json").write_text(json.dumps({"summary": summary, "scenes": scenes},
                                                         indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
