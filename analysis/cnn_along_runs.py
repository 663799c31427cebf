"""The distance CNN along real controller runs: does the predicted best distance fall as
the hand converges, and does it track the true distance?

Runs CTR episodes (the `isolation` scenario by default: held-out object instances,
settled by physics) with the given weights and, at every control step, takes from the
controller's own record (`StepRecord`): the least predicted distance among its candidates
(what Algorithm 1 moves toward) and, from the settled scene's ground-truth grasps (the
dataset's label function), the true distance of the hand where the image was taken and
of the candidate the controller chose. Writes a JSON with every step and a picture.

    python analysis/cnn_along_runs.py --seeds 0-9 --out analysis/results/cnn-along-runs
    python analysis/cnn_along_runs.py --weights data/paper_run/weights.safetensors ...
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def parse_seeds(text: str) -> list[int]:
    """'0-9' or '0,3,7' -> seeds."""
    if "-" in text:
        lo, hi = (int(v) for v in text.split("-"))
        return list(range(lo, hi + 1))
    return [int(v) for v in text.split(",")]


def run(seeds: list[int], *, weights: str = "", scenario_name: str = "isolation") -> dict:
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.scene import scenario_scene
    from drake_grasp.policies.evaluator import load_cnn

    library = load_library(None)
    base = load_scenario(scenario_name=scenario_name)
    base = dataclasses.replace(base, policy="ctr", controller=dataclasses.replace(
        base.controller, weights=weights or base.controller.weights))
    model = load_cnn(base.controller.weights)
    runs = []
    for seed in seeds:
        scenario = dataclasses.replace(base, seed=seed)
        scene = scenario_scene(scenario, library, seed=seed)
        truth = find_grasps(scene, library, np.random.default_rng([seed, 61])).xy_theta
        t0 = time.perf_counter()
        ep = simulate_episode(scenario, library=library, scene=scene, record_depth=False,
                              model=model)
        steps = []
        for s in ep.steps:
            if s.distances is None or len(s.distances) == 0:
                continue
            hand = np.asarray(s.hand, float)[[0, 1, 3]]
            best = int(np.argmin(s.distances))
            true_hand = float(distance_to_nearest_grasp(hand[None], truth)[0])
            chosen = apply_actions(hand[None], np.asarray(s.actions, float)[None, [best]])[0]
            steps.append(dict(iteration=int(s.iteration), time_s=float(s.time_s),
                              predicted_best_m=float(s.distances[best]),
                              true_at_hand_m=true_hand,
                              true_at_chosen_m=float(distance_to_nearest_grasp(chosen, truth)[0])))
        runs.append(dict(seed=seed, success=bool(ep.result.success),
                         failure=ep.result.failure_reason,
                         final_distance_m=ep.result.final_distance_m,
                         wall_s=time.perf_counter() - t0, steps=steps))
        print(f"seed {seed}: {len(steps)} steps, predicted best "
              f"{steps[0]['predicted_best_m'] * 1000 if steps else float('nan'):.0f} -> "
              f"{steps[-1]['predicted_best_m'] * 1000 if steps else float('nan'):.0f} mm, "
              f"true at hand {steps[0]['true_at_hand_m'] * 1000 if steps else float('nan'):.0f} -> "
              f"{steps[-1]['true_at_hand_m'] * 1000 if steps else float('nan'):.0f} mm, "
              f"success {ep.result.success}", flush=True)
    return {"weights": base.controller.weights or "(shipped)", "scenario": scenario_name,
            "runs": runs, "summary": summarize(runs)}


def summarize(runs: list[dict]) -> dict:
    """Per-run first/last predicted best and true distance, and their correlation over
    all steps (Spearman: does a lower prediction mean a closer grasp?)."""
    from drake_grasp.learning.cnn_metrics import spearman

    # A scene without a ground-truth grasp (e.g. an upright object too wide for the
    # 2F-85) has no true distance: its run is left out of the distance statistics.
    with_steps = [r for r in runs if r["steps"]
                  and np.isfinite([s["true_at_chosen_m"] for s in r["steps"]]).all()]
    pred = np.concatenate([[s["predicted_best_m"] for s in r["steps"]] for r in with_steps])
    true = np.concatenate([[s["true_at_chosen_m"] for s in r["steps"]] for r in with_steps])

    def stat(key, where):
        return float(np.median([r["steps"][where][key] for r in with_steps]))

    return {
        "runs": len(runs), "successes": int(sum(r["success"] for r in runs)),
        "runs_with_true_grasps": len(with_steps),
        "median_first_predicted_best_m": stat("predicted_best_m", 0),
        "median_last_predicted_best_m": stat("predicted_best_m", -1),
        "median_first_true_at_hand_m": stat("true_at_hand_m", 0),
        "median_last_true_at_hand_m": stat("true_at_hand_m", -1),
        "fraction_runs_predicted_best_fell": float(np.mean(
            [r["steps"][-1]["predicted_best_m"] < r["steps"][0]["predicted_best_m"]
             for r in with_steps])),
        "spearman_predicted_vs_true_all_steps": float(spearman(pred[None], true[None])[0]),
        "mean_abs_error_predicted_vs_true_chosen_m": float(np.mean(np.abs(pred - true))),
    }


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for r in result["runs"]:
        it = [s["iteration"] for s in r["steps"]]
        colour = "tab:green" if r["success"] else "tab:red"
        axes[0].plot(it, [1000 * s["predicted_best_m"] for s in r["steps"]], color=colour,
                     alpha=0.6)
        axes[1].plot(it, [1000 * s["true_at_chosen_m"] for s in r["steps"]], color=colour,
                     alpha=0.6)
    axes[0].set_title("predicted best distance (CNN)")
    axes[1].set_title("true distance of the chosen candidate")
    for ax in axes:
        ax.set_xlabel("control step")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("distance [mm]  (green: lifted, red: failed)")
    s = result["summary"]
    fig.suptitle(f"CTR along {s['runs']} {result['scenario']} runs; Spearman(predicted, true) "
                 f"over all steps {s['spearman_predicted_vs_true_all_steps']:.2f}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", default="0-9", help="episode seeds: '0-9' or '0,3,7'")
    p.add_argument("--weights", default="", help="CNN weights (default: the shipped ones)")
    p.add_argument("--scenario", default="isolation", help="named scenario (default isolation)")
    p.add_argument("--out", required=True, help="output folder (along_runs.json, along_runs.png)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = run(parse_seeds(args.seeds), weights=args.weights, scenario_name=args.scenario)
    (out / "along_runs.json").write_text(json.dumps(result, indent=1))
    plot(result, out / "along_runs.png")
    print(json.dumps(result["summary"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
