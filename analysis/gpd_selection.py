"""Which GPD selection picks ground-truth grasps in piles: variants side by side on dev scenes.

In the clutter experiment every GPD detection that passed the labels' ground truth was
grasped, and every failure was a detection the ground truth rejects (the report's table
*GPD's detections against the ground truth*). So the selected grasp's precision is what
limits GPD there. This script compares selection rules and classifiers on the same
candidates, on piles that are *not* the experiments' (seeds from `--seed`, default 101;
the experiments use 0): poured piles of 10, 7, 5 and 3 objects in turn (a clutter run's
pile shrinks as objects are removed), test-split object instances, settled and seen from
the experiments' viewpoint. For each scene: the cloud and GPD's candidates once, the
probabilities of each classifier, the top-1 grasp of each variant, and that grasp checked
with the ground truth (`gpd_training.ground_truth_passes`, 2 surface samplings, as the
episodes' `detection_check`). The lever-arm variants prefer candidates whose closing
axis passes near the centroid of the cloud segment under them (`lever_arms`).

    python analysis/gpd_selection.py --scenes 40 --workers 2 \\
        --weights-b data/gpd3_model/weights.safetensors --out analysis/results/gpd-selection.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

PILE_SIZES = (10, 7, 5, 3)


def segment_cloud(points: np.ndarray, radius_m: float = 0.005) -> np.ndarray:
    """Label (N,) of each cloud point's segment: the connected components of the graph
    joining points closer than `radius_m` (Euclidean clustering, as point-cloud grasping
    pipelines segment a table-top scene). Objects that touch share a segment."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(points).query_pairs(radius_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def lever_arms(points: np.ndarray, labels: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Per candidate, the horizontal distance [m] from the centroid of the seen segment
    under its grasp centre to the vertical plane through its closing axis: the lever arm
    of the object's weight about the axis between the pads, if the centroid of what the
    camera sees stands for the centre of mass. Pads resist a torque about that axis
    only by their patch's torsional friction, so a long object held far from its middle
    turns out of the grip as it is lifted."""
    from scipy.spatial import cKDTree

    if len(poses) == 0 or len(points) == 0:
        return np.zeros(len(poses))
    counts = np.bincount(labels)
    centroids = np.stack([np.bincount(labels, weights=points[:, j]) / counts for j in range(3)], 1)
    centre = poses[:, :3, 3]
    seg = labels[cKDTree(points).query(centre)[1]]
    r = (centroids[seg] - centre)[:, :2]
    x = poses[:, :2, 0]
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    x = np.where(norm > 1e-9, x / np.maximum(norm, 1e-9), 0.0)
    along = np.sum(r * x, axis=1, keepdims=True) * x
    return np.linalg.norm(r - along, axis=1)


def variants(poses: np.ndarray, prob_a: np.ndarray, prob_b: np.ndarray | None,
             arms: np.ndarray | None = None) -> dict:
    """Index of the top-1 candidate of each variant (None: nothing accepted). `arms`:
    each candidate's lever arm (`gpd.lever_arms`) for the balance variants."""
    from drake_grasp.policies.gpd_ranking import Selection, cluster_scores, cluster_support, select

    out = {}

    def first(order):
        return int(order[0]) if len(order) else None

    out["shipped: cluster mean (the detector's)"] = first(select(poses, prob_a))
    acc = np.flatnonzero(prob_a >= 0.5)
    out["shipped: highest probability"] = int(acc[np.argmax(prob_a[acc])]) if len(acc) else None
    out["shipped: cluster mean 2 cm / 30 deg"] = first(select(
        poses, prob_a, Selection(cluster_distance_m=0.02, cluster_angle_deg=30.0)))
    if len(acc):
        _, total = cluster_support(poses[acc], prob_a[acc])
        out["shipped: cluster sum (support)"] = int(acc[np.argmax(total)])
    else:
        out["shipped: cluster sum (support)"] = None
    out["shipped: cluster mean, threshold 0.9"] = first(select(poses, prob_a, Selection(threshold=0.9)))
    if arms is not None and len(acc):
        score = cluster_scores(poses, prob_a)[acc]
        for w in (0.1, 0.2, 0.4):
            out[f"shipped: cluster mean - {w} per 5 cm of lever arm"] = int(
                acc[np.argmax(score - w * arms[acc] / 0.05)])
        for tol in (0.05, 0.1):
            near = score >= score.max() - tol
            out[f"shipped: least lever arm within {tol} of the best cluster mean"] = int(
                acc[near][np.argmin(arms[acc][near])])
    if prob_b is not None:
        out["retrained: cluster mean"] = first(select(poses, prob_b))
        out["mean of both: cluster mean"] = first(select(poses, 0.5 * (prob_a + prob_b)))
    return out


def scene_row(i: int, seed: int, weights_b: str) -> dict:
    from drake_grasp.policies import gpd
    from drake_grasp.learning.dataset import scene_seed
    from drake_grasp.evaluation.experiments import EXPERIMENTS
    from drake_grasp.learning.gpd_training import GpdDataConfig, experiment_view, ground_truth_passes
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import load_scenario

    library = load_library(None)
    exp = EXPERIMENTS["clutter"]
    scenario = load_scenario(scenario_name=exp.scenario, scenario_text=exp.scenario_text)
    k = PILE_SIZES[i % len(PILE_SIZES)]
    scenario.scene = dataclasses.replace(scenario.scene, clutter_objects=k)
    s_seed = scene_seed(seed, i)
    t0 = time.perf_counter()
    settled, X_WC, depth = experiment_view(scenario, s_seed, library)
    detector = gpd.make_detector(dataclasses.replace(scenario, seed=s_seed)).detector
    cloud = gpd.cloud_from_depth(depth, fov_y_deg=detector.fov_y_deg, X_WC=X_WC,
                                 depth_min_m=detector.depth_min_m,
                                 depth_max_m=detector.depth_max_m, center_xy=detector.center_xy)
    hands = gpd.sample_hands(cloud, np.random.default_rng([s_seed, 59]), detector.search)
    row = dict(scene=i, seed=int(s_seed), objects=len(settled.objects), pile=k,
               candidates=len(hands), picks={})
    if len(hands) == 0:
        row["seconds"] = time.perf_counter() - t0
        return row
    images = gpd.grasp_images(cloud, hands.poses)
    prob_a = detector.classifier.probabilities(images)
    prob_b = gpd.load_classifier(weights_b).probabilities(images) if weights_b else None
    arms = lever_arms(cloud.points, segment_cloud(cloud.points), hands.poses)
    picks = variants(hands.poses, prob_a, prob_b, arms)
    chosen = sorted({v for v in picks.values() if v is not None})
    passes, obj = ground_truth_passes(settled, library, hands.poses[chosen],
                                      np.random.default_rng([s_seed, 62]), GpdDataConfig(),
                                      samplings=2)
    verdict = {c: (int(p), settled.objects[int(o)].object_id if o >= 0 else None)
               for c, p, o in zip(chosen, passes, obj)}
    for name, c in picks.items():
        row["picks"][name] = None if c is None else {
            "candidate": c, "ground_truth_passes": verdict[c][0], "object_id": verdict[c][1],
            "probability_shipped": float(prob_a[c]), "lever_arm_m": float(arms[c])}
    row["seconds"] = time.perf_counter() - t0
    return row


def summarize(rows: list[dict]) -> dict:
    from drake_grasp.evaluation.records import wilson_interval

    names = list(dict.fromkeys(n for r in rows for n in r["picks"]))
    out = {}
    for name in names:
        picks = [r["picks"].get(name) for r in rows]
        det = [p for p in picks if p is not None]
        both = sum(p["ground_truth_passes"] == 2 for p in det)
        lo, hi = wilson_interval(both, len(det)) if det else (None, None)
        out[name] = dict(scenes=len(rows), detected=len(det), true_on_both=both,
                         true_on_one=sum(p["ground_truth_passes"] == 1 for p in det),
                         precision=both / len(det) if det else None, ci95=[lo, hi])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=40)
    p.add_argument("--seed", type=int, default=101)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--weights-b", default="", help="a second classifier (e.g. a retrained one)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(scene_row, range(args.scenes), [args.seed] * args.scenes,
                             [args.weights_b] * args.scenes))
    result = dict(scenes=args.scenes, seed=args.seed, weights_b=args.weights_b,
                  wall_s=round(time.perf_counter() - t0, 1), summary=summarize(rows), rows=rows)
    print(json.dumps(result["summary"], indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
