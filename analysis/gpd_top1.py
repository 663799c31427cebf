"""Top-1 precision of the GPD baseline: against the ground truth and in the grasp lab.

For seeded held-out scenes (test object instances; isolation, 1-5 objects, poured piles),
settled as the experiments settle them, the GPD sensor's image at the experiments'
viewpoint goes through the whole detector (`drake_grasp.policies.gpd`, shipped or given weights);
its selected grasp is checked with the ground truth (`grasps.check_grasp_poses`, the
dataset's friction and torque limits) and executed in the grasp lab (`drake_grasp.evaluation.lab`,
neighbours present). Reports the share of scenes with a detection and
the share of detections that are true grasps, per scene kind, with the detection time.

    python analysis/gpd_top1.py --scenes 30 --out analysis/results/gpd-top1.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np


def run(num_scenes: int, seed: int, weights: str = "", selection=None, physics: bool = True) -> dict:
    from drake_grasp.policies import gpd
    from drake_grasp.learning.dataset import scene_seed
    from drake_grasp.learning.gpd_training import GpdDataConfig, experiment_view, ground_truth_passes
    from drake_grasp.evaluation.lab import check_grasp
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario

    library = load_library(None)
    data_cfg = GpdDataConfig()
    model = gpd.load_classifier(weights)
    rows = []
    for i in range(num_scenes):
        kind = ("isolation", "random", "clutter")[i % 3]
        scenario = load_scenario(scenario_name={"isolation": "isolation", "random": "random",
                                                "clutter": "clutter"}[kind])
        s_seed = scene_seed(seed, i)
        settled, X_WC, depth = experiment_view(scenario, s_seed, library)
        detector = gpd.make_detector(dataclasses.replace(scenario, seed=s_seed), classifier=model).detector
        if selection is not None:
            detector.selection = selection
        t0 = time.perf_counter()
        found = detector.detect(depth, X_WC, np.random.default_rng([s_seed, 59]))
        seconds = time.perf_counter() - t0
        row = dict(scene=i, kind=kind, seed=int(s_seed), objects=len(settled.objects),
                   detected=len(found.poses) > 0, seconds=seconds,
                   candidates=found.num_candidates)
        if found.poses.shape[0]:
            passes, obj = ground_truth_passes(settled, library, found.poses[:1],
                                              np.random.default_rng(0), data_cfg)
            row.update(true_grasp=bool(passes[0] == 1), probability=float(found.probabilities[0]),
                       tilt_deg=float(np.degrees(np.arccos(-found.poses[0, 2, 2]))))
            if physics:
                # Executed in the grasp lab with the neighbours present; pads on no single
                # object: the grasp cannot hold anything (counted as not held).
                if obj[0] >= 0:
                    res = check_grasp(None, found.poses[0], scene=settled, scenario=scenario,
                                      library=library, object_index=int(obj[0]), neighbours=True)
                    row.update(held=bool(res.held), lab_failure=res.failure)
                else:
                    row.update(held=False, lab_failure="no single object between the pads")
        rows.append(row)
    summary = {}
    for kind in ("isolation", "random", "clutter", "all"):
        sel = [r for r in rows if kind == "all" or r["kind"] == kind]
        det = [r for r in sel if r["detected"]]
        summary[kind] = dict(scenes=len(sel), detected=len(det),
                             top1_true=sum(r["true_grasp"] for r in det),
                             top1_precision=(sum(r["true_grasp"] for r in det) / len(det)) if det else None,
                             median_detect_s=float(np.median([r["seconds"] for r in sel])) if sel else None,
                             lab_held=sum(r.get("held", False) for r in det))
    return dict(summary=summary, scenes=rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=30)
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--weights", default="")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    result = run(args.scenes, args.seed, args.weights)
    print(json.dumps(result["summary"], indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
