"""CTR with a perfect distance function: is the CNN or the execution the bottleneck?

Runs the `isolation` experiment's CTR trials (the same scenarios, seeds and objects as
`drake-grasp evaluate --experiment isolation --conditions ctr`) with the CNN's predicted
distances replaced by the true ones: at every control step, each candidate's distance to
the nearest ground-truth grasp of the settled scene (the dataset's label function, the
grasps the judge's final distance uses). Everything else - sampler, r, z steps, the 14 cm
stop rule, the grasp height from the depth image, the grasp motion, the contact judge - is
the policy's own. The truth is privileged (a diagnostic, like the `scripted` reference):
its success rate is what a perfect CNN would give this controller and grasp execution.
The grasps are those of the scene as settled at the start; an object pushed during the
approach is not followed.

    python analysis/oracle_ctr.py --trials 120 --workers 2 --out analysis/results/oracle-ctr

In clutter (`--records DIR`): the piles of a clutter experiment's recorded CTR attempts,
each as it was when its attempt began (the record's `extra["scene"]`, scenario and seed),
simulated twice with the current package: once by CTR with the CNN and once with the true
distances (the ground truth of that pile, every object's grasps). A paired comparison:
does a perfect distance function lift the clutter success, or do the attempts fail in
execution (pushing, collisions, slips) whatever the scores?

    python analysis/oracle_ctr.py --records analysis/results/gpd-view-068/clutter \
        --workers 2 --out analysis/results/oracle-ctr-clutter

`--oracle-phase descent` scores with the truth only the decisions of the descent (those
taken before the stop rule has fired: which object and where the hand goes) and leaves
the decisions at the stop height (convergence, from the one after the rule fired) to the
CNN; `--oracle-phase stop` the other way round. `--arms oracle` skips the CNN's replay
(the records are its outcomes).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


ORACLE_PHASES = ("all", "descent", "stop")


def _oracle_controller(truth_xy_theta: np.ndarray, phase: str = "all"):
    """A CTRController subclass whose candidates are scored by the true distance: at
    every decision (`phase` "all"), only in the descent ("descent": before the stop
    rule has fired) or only at the stop height ("stop": the decisions after it fired)."""
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.policies.ctr import CTRController

    class OracleController(CTRController):
        oracle_steps = 0  # decisions scored by the truth (a check that it was used)

        def _ctr_step(self, context, s, t):
            if phase != "all" and (phase == "stop") != bool(s.converging):
                return super()._ctr_step(context, s, t)  # the CNN decides this step
            hand = s.hand
            port = self._distances

            class _Truth:  # stands in for the evaluator's port during this step
                @staticmethod
                def Eval(ctx):
                    OracleController.oracle_steps += 1
                    actions = np.asarray(self._actions.Eval(ctx), float)
                    poses = apply_actions([hand[0], hand[1], hand[3]], actions)
                    if len(truth_xy_theta) == 0:
                        return np.full(len(actions), np.inf)
                    return distance_to_nearest_grasp(poses, truth_xy_theta)

            self._distances = _Truth
            try:
                return super()._ctr_step(context, s, t)
            finally:
                self._distances = port

    return OracleController


def run_trial(index: int, seed: int, phase: str = "all") -> dict:
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.evaluation.episode_diagram import controller_class
    from drake_grasp.evaluation.experiments import EXPERIMENTS, trial_scenario
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.objects import load_library
    from drake_grasp.world.scene import scenario_scene

    library = load_library(None)
    exp = EXPERIMENTS["isolation"]
    cond = next(c for c in exp.conditions if c.name == "ctr")
    scenario = trial_scenario(exp, cond, index, base_seed=seed, library=library)
    scene = scenario_scene(scenario, library)
    truth = find_grasps(scene, library, np.random.default_rng([scenario.seed, 61])).xy_theta
    t0 = time.perf_counter()
    oracle = _oracle_controller(np.asarray(truth, float), phase)
    with controller_class(oracle):
        ep = simulate_episode(scenario, library=library, scene=scene, record_depth=False)
    r = ep.result
    return {"index": index, "object": scenario.scene.object_ids[0], "pose": scenario.scene.pose,
            "success": bool(r.success), "failure_class": r.details.get("failure_class"),
            "failure_reason": r.failure_reason, "final_distance_m": r.final_distance_m,
            "control_steps": r.control_steps, "stop_reason": r.details.get("stop_reason"),
            "num_true_grasps": int(len(truth)), "oracle_steps": oracle.oracle_steps,
            "wall_s": time.perf_counter() - t0}


def run_attempt(path: str, arms=("cnn", "oracle"), phase: str = "all") -> dict:
    """One recorded clutter attempt's pile, simulated by CTR with the CNN and by the oracle
    (`arms`; the oracle scoring the decisions of `phase`)."""
    import contextlib

    from drake_grasp.evaluation.episode_diagram import controller_class
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.evaluation.replay import recorded_pile
    from drake_grasp.evaluation.trial_worker import _simulate
    from drake_grasp.objects import load_library

    rec, scenario, scene = recorded_pile(path)
    if rec.get("policy") != "ctr":
        raise ValueError(f"{path}: expected a CTR clutter attempt record")
    library = load_library(None)
    truth = find_grasps(scene, library, np.random.default_rng([scenario.seed, 61])).xy_theta
    row = {"trial_id": rec["trial_id"], "objects": len(scene.objects),
           "recorded": {"success": bool(rec["success"]), "failure_class": rec["failure_class"]},
           "num_true_grasps": int(len(truth))}
    for name in arms:
        t0 = time.perf_counter()
        oracle = _oracle_controller(np.asarray(truth, float), phase) if name == "oracle" else None
        with controller_class(oracle) if oracle is not None else contextlib.nullcontext():
            run = _simulate(scenario, library, scene=scene)
        r = run.result
        row[name] = {"success": bool(r.success), "failure_class": r.details.get("failure_class"),
                     "failure_reason": r.failure_reason,
                     "final_distance_m": r.final_distance_m, "control_steps": r.control_steps,
                     "grasped_object_id": r.details.get("grasped_object_id"),
                     "stop_reason": r.details.get("stop_reason"),
                     "oracle_steps": oracle.oracle_steps if oracle is not None else 0,
                     "wall_s": time.perf_counter() - t0}
    return row


def clutter_main(args) -> int:
    from drake_grasp.evaluation.montecarlo import parallel_map
    from drake_grasp.core.provenance import code_version
    from drake_grasp.evaluation.records import wilson_interval

    from drake_grasp.evaluation.records import trial_paths

    paths = [str(p) for p in trial_paths(args.records, condition=args.condition)]
    if args.trials:
        paths = paths[:args.trials]
    if not paths:
        raise SystemExit(f"{args.records}: no records of condition {args.condition!r}")
    arms = tuple(a.strip() for a in args.arms.split(","))
    if not arms or any(a not in ("cnn", "oracle") for a in arms):
        raise SystemExit(f"--arms: {args.arms!r}; expected cnn, oracle or cnn,oracle")
    rows = parallel_map(run_attempt, [(p, arms, args.oracle_phase) for p in paths],
                        workers=args.workers, desc="oracle ctr, clutter")
    summary = {"attempts": len(rows), "records": str(args.records), "condition": args.condition,
               "arms": list(arms), "oracle_phase": args.oracle_phase,
               "code_version": code_version()}
    for name in ("recorded",) + arms:
        k = sum(r[name]["success"] for r in rows)
        classes: dict = {}
        for r in rows:
            classes[r[name]["failure_class"]] = classes.get(r[name]["failure_class"], 0) + 1
        summary[name] = {"successes": k, "rate": k / len(rows),
                         "ci95": list(wilson_interval(k, len(rows))), "failure_classes": classes}
    if "oracle" in arms:  # against the CNN's replay, or its records without one
        ref = "cnn" if "cnn" in arms else "recorded"
        summary["paired_cnn_vs_oracle"] = {
            "cnn_from": ref,
            "both": sum(r[ref]["success"] and r["oracle"]["success"] for r in rows),
            "cnn_only": sum(r[ref]["success"] and not r["oracle"]["success"] for r in rows),
            "oracle_only": sum(r["oracle"]["success"] and not r[ref]["success"] for r in rows),
            "neither": sum(not r[ref]["success"] and not r["oracle"]["success"] for r in rows)}
    summary["without_true_grasps"] = sum(r["num_true_grasps"] == 0 for r in rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "oracle_ctr_clutter.json").write_text(json.dumps({"summary": summary, "rows": rows},
                                                            indent=1))
    print(json.dumps(summary, indent=1))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=None,
                   help="isolation trials (default 40); with --records, the first N attempts (default all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", required=True)
    p.add_argument("--records", default="",
                   help="a clutter experiment's results folder: replay its CTR attempts' piles")
    p.add_argument("--condition", default="ctr", help="with --records: the condition's records")
    p.add_argument("--arms", default="cnn,oracle",
                   help="with --records: cnn, oracle or cnn,oracle (default)")
    p.add_argument("--oracle-phase", default="all", choices=ORACLE_PHASES,
                   help="the decisions the truth scores: all (default), descent (before the "
                        "stop rule fired) or stop (at the stop height, after it fired)")
    args = p.parse_args(argv)
    if args.records:
        return clutter_main(args)
    args.trials = 40 if args.trials is None else args.trials
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from drake_grasp.evaluation.montecarlo import parallel_map
    from drake_grasp.evaluation.records import wilson_interval

    trials = parallel_map(run_trial, [(i, args.seed, args.oracle_phase) for i in range(args.trials)],
                          workers=args.workers, desc="oracle ctr")
    k = sum(t["success"] for t in trials)
    lo, hi = wilson_interval(k, len(trials))
    classes: dict = {}
    for t in trials:
        classes[t["failure_class"]] = classes.get(t["failure_class"], 0) + 1
    from drake_grasp.core.provenance import code_version

    covered = [t for t in trials if t["num_true_grasps"] > 0]
    k_cov = sum(t["success"] for t in covered)
    summary = {"trials": len(trials), "successes": k, "success_rate": k / len(trials),
               "ci95": [lo, hi], "failure_classes": classes, "seed": args.seed,
               # Scenes where the ground truth has a grasp (the oracle's scores mean
               # something there; elsewhere every candidate scores inf and the first
               # sampled one is taken).
               "with_true_grasps": {"trials": len(covered), "successes": k_cov,
                                    "ci95": list(wilson_interval(k_cov, len(covered)))
                                    if covered else None},
               "without_true_grasps": {
                   "trials": len(trials) - len(covered), "successes": k - k_cov,
                   "objects": sorted({f"{t['object']} {t['pose']}" for t in trials
                                      if t["num_true_grasps"] == 0})},
               "code_version": code_version()}
    (out / "oracle_ctr.json").write_text(json.dumps({"summary": summary, "trials": trials},
                                                    indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
