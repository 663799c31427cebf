"""How exact are the distance labels? The ground-truth grasp search samples its candidates,
so a label (the distance from an offset hand pose to the nearest true grasp) depends on
the draw. This script regenerates scenes of a dataset split exactly as `generate` does
(same seeds, same settling, same images' hand poses and offsets), then recomputes every
label with two more independent searches of the dataset's size and one 10x denser
search, and reports:

- the L1 between labels of two independent searches (the label's own noise),
- the L1 and mean difference against the dense search (the sparse search's bias: a
  sparser set of true grasps is farther away), by label range,
- the scenes where the searches disagree by more than 2 cm on average (an object whose
  few grasps one search finds and another misses),
- the within-image Spearman rank correlation between two searches' distances of the
  controller's candidates (`--candidates` per image, drawn as `cnn_metrics` draws them:
  within 4 cm and 45 degrees of the image's hand pose): how well a perfect predictor of
  one search's labels can rank against another search's - the ceiling of
  `cnn_metrics`' `spearman_mean` set by the labels' own noise.

This is the floor under any network's test L1 measured on such labels.

    python analysis/label_noise.py --scenes 100 --out analysis/results/label-noise

Writes OUT/summary.json (and OUT/labels.npz with every label set; with --save-candidates
OUT/candidates.npz, every candidate's distance under each search); --workers splits the
scenes over processes.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

DENSE_FACTOR = 10


def _scene_task(index, seed, split, num_samples, candidates=128):
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.policies.decisions import sample_candidates
    from drake_grasp.learning.dataset import DatasetConfig, SceneSamples, generate_scene
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.scene import SceneSpec

    scenario = load_scenario(scenario_name="random")
    config = DatasetConfig()
    library = load_library(None)
    for attempt in range(config.max_attempts_per_scene):
        r = generate_scene(index, seed=seed, split=split, scenario=scenario, config=config,
                           library=library, attempt=attempt)
        if isinstance(r, SceneSamples):
            break
    else:
        return None
    spec = SceneSpec.from_dict(json.loads(r.spec_json))
    moved = apply_actions(r.hand_pose[:, [0, 1, 3]], r.offsets.astype(float)).reshape(-1, 3)
    labels = {"dataset": r.labels.reshape(-1).astype(float)}
    # The controller's candidates around every image's hand pose (cnn_metrics' defaults).
    rng = np.random.default_rng([index, seed, 11])
    cand = np.stack([sample_candidates(rng, candidates, xy_m=0.04, theta_deg=45.0)
                     for _ in range(len(r.hand_pose))])
    cand_moved = apply_actions(r.hand_pose[:, [0, 1, 3]], cand).reshape(-1, 3)
    ranked = {"dataset": distance_to_nearest_grasp(cand_moved, r.grasp_xy_theta)
              .reshape(len(r.hand_pose), candidates)}
    timings = {}
    for name, stream, samples in (("a", 2, num_samples), ("b", 3, num_samples),
                                  ("dense", 4, DENSE_FACTOR * num_samples)):
        t0 = time.perf_counter()
        g = find_grasps(spec, library, np.random.default_rng([index, seed, stream]),
                        num_samples=samples, mu=config.friction_coefficient,
                        max_torque_ratio=config.max_torque_ratio)
        timings[name] = time.perf_counter() - t0
        labels[name] = (distance_to_nearest_grasp(moved, g.xy_theta) if len(g)
                        else np.full(len(moved), np.inf))
        ranked[name] = (distance_to_nearest_grasp(cand_moved, g.xy_theta).reshape(
            len(r.hand_pose), candidates) if len(g) else np.full(cand.shape[:2], np.inf))
    return {"scene_index": index, "objects": [o.object_id for o in spec.objects],
            "labels": labels, "candidates": ranked, "search_s": timings}


def _l1_mm(x, y) -> float:
    return round(1000.0 * float(np.mean(np.abs(x - y))), 2) if len(x) else float("nan")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=100, help="scenes 0..N-1 of the split")
    p.add_argument("--seed", type=int, default=1, help="the dataset seed (the shipped test set: 1)")
    p.add_argument("--split", default="test", choices=("train", "test"))
    p.add_argument("--num-samples", type=int, default=400,
                   help="the search size the dataset uses (grasps.find_grasps' default)")
    p.add_argument("--candidates", type=int, default=128,
                   help="controller candidates per image for the ranking ceiling")
    p.add_argument("--save-candidates", action="store_true",
                   help="also write OUT/candidates.npz (every candidate's distance under "
                        "each search; 15 MB for 100 scenes)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    if args.scenes < 1:
        raise SystemExit(f"--scenes: expected >= 1, got {args.scenes}")
    if args.candidates < 2:
        raise SystemExit(f"--candidates: expected >= 2 (a ranking), got {args.candidates}")

    from drake_grasp.evaluation.montecarlo import parallel_map
    from drake_grasp.core.files import atomic_write_text

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = [r for r in parallel_map(_scene_task, [(i, args.seed, args.split, args.num_samples,
                                                   args.candidates)
                                                  for i in range(args.scenes)],
                                    workers=args.workers, desc="label-noise") if r is not None]
    L = {k: np.concatenate([r["labels"][k] for r in rows]) for k in rows[0]["labels"]}
    finite = np.all([np.isfinite(v) for v in L.values()], axis=0)
    F = {k: v[finite] for k, v in L.items()}
    by_range = {}
    for lo, hi in ((0.0, 0.03), (0.03, 0.1), (0.1, np.inf)):
        m = (F["dense"] >= lo) & (F["dense"] < hi)
        by_range[f"dense label in [{lo}, {hi}) m"] = {
            "labels": int(m.sum()),
            "l1_a_b_mm": _l1_mm(F["a"][m], F["b"][m]),
            "l1_dataset_dense_mm": _l1_mm(F["dataset"][m], F["dense"][m]),
            "mean_dataset_minus_dense_mm": round(1000.0 * float(np.mean(F["dataset"][m] - F["dense"][m])), 2)}
    per_scene = []
    for r in rows:
        a, b, d = (np.asarray(r["labels"][k]) for k in ("a", "b", "dataset"))
        ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(d)
        per_scene.append({"scene_index": r["scene_index"], "objects": r["objects"],
                          "l1_a_b_mm": _l1_mm(a[ok], b[ok]),
                          "l1_dataset_a_mm": _l1_mm(d[ok], a[ok]),
                          "labels_without_grasp": int((~ok).sum())})
    pairs = [("dataset", "a"), ("a", "b"), ("dataset", "dense"), ("a", "dense")]
    from drake_grasp.learning.cnn_metrics import spearman

    C = {k: np.concatenate([r["candidates"][k] for r in rows]) for k in rows[0]["candidates"]}
    rows_ok = np.all([np.isfinite(v).all(axis=1) for v in C.values()], axis=0)
    ranking = {"images": int(rows_ok.sum()), "candidates": args.candidates}
    for x, y in pairs:
        rho = spearman(C[x][rows_ok], C[y][rows_ok])
        best_x = C[x][rows_ok].argmin(axis=1)
        regret = C[y][rows_ok][np.arange(rows_ok.sum()), best_x] - C[y][rows_ok].min(axis=1)
        ranking[f"{x}/{y}"] = {
            "spearman_mean": round(float(np.nanmean(rho)), 4),
            "spearman_median": round(float(np.nanmedian(rho)), 4),
            "constant_rows": int(np.isnan(rho).sum()),
            # the candidate x ranks first, judged by y: as cnn_metrics' regret / top-1
            "regret_mean_mm": round(1000.0 * float(regret.mean()), 2),
            "top1_within_1cm": round(float(np.mean(regret <= 0.01)), 4)}
    summary = {
        "scenes": len(rows), "seed": args.seed, "split": args.split,
        "num_samples": args.num_samples, "dense_num_samples": DENSE_FACTOR * args.num_samples,
        "labels": int(len(finite)), "labels_compared": int(finite.sum()),
        "l1_mm": {f"{x}/{y}": _l1_mm(F[x], F[y]) for x, y in pairs},
        "median_abs_diff_mm": {f"{x}/{y}": round(1000.0 * float(np.median(np.abs(F[x] - F[y]))), 2)
                               for x, y in pairs},
        "by_range": by_range,
        "candidate_ranking": ranking,
        "scenes_with_l1_over_20mm": {
            "dataset/a or a/b": sum(max(s["l1_a_b_mm"], s["l1_dataset_a_mm"]) > 20 for s in per_scene)},
        "search_s_mean": {k: round(float(np.mean([r["search_s"][k] for r in rows])), 3)
                          for k in rows[0]["search_s"]},
        "per_scene": per_scene,
        "wall_s": round(time.perf_counter() - t0, 1), "date": time.strftime("%Y-%m-%d"),
    }
    np.savez_compressed(out / "labels.npz", **L)
    if args.save_candidates:
        np.savez_compressed(out / "candidates.npz", **C)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "per_scene"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
