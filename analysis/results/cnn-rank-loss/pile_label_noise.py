"""How well can anything rank the controller's candidates on pile labels? The held-out
piles' labels come from one sampled ground-truth search per pile (1,600 surface points);
this script runs a second, independent search of the same size on every stored pile
(`scene_spec` of the shards: the settled poses), draws the controller's 128 candidates
around each image's hand pose (within 4 cm and 45 degrees, as `cnn_metrics` draws them)
and ranks them by one search's distances against the other's: the ceiling the labels' own
noise sets on `cnn_metrics`' within-image Spearman and regret, for piles (the paper's
random scenes: README *How exact the labels are*, 0.908).

    python analysis/results/cnn-rank-loss/pile_label_noise.py data/clutter_test \
        --out analysis/results/cnn-rank-loss/pile_label_noise.json

Every image of every pile is used; the second search's seed is ([scene seed], 1001).
First checks that the dataset's own search ([scene seed], 1) on the first stored pile
reproduces its stored grasps.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    import h5py

    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.learning.cnn_metrics import regret_m, spearman
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.objects import load_library
    from drake_grasp.policies.decisions import sample_candidates
    from drake_grasp.core.files import print_json
    from drake_grasp.world.scene import SceneSpec

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path, help="a `generate` folder")
    p.add_argument("--candidates", type=int, default=128)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    config = json.loads((args.data / "manifest.json").read_text())["config"]["dataset"]
    search = {"mu": config["friction_coefficient"], "max_torque_ratio": config["max_torque_ratio"],
              "num_samples": config["grasp_samples"]}
    library = load_library(None)
    rng = np.random.default_rng([0, 11])
    rho, regret, regret_rev, found_a, found_b = [], [], [], [], []
    checked = False
    for shard in sorted(args.data.glob("shard-*.h5")):
        with h5py.File(shard, "r") as f:
            specs = [SceneSpec.from_dict(json.loads(s)) for s in f["scene_spec"][:]]
            index = f["scene_index"][:]
            hand = f["hand_pose"][:]
            image_scene = f["image_scene"][:]
            grasp_scene = f["grasp_scene"][:]
            grasps = f["grasp_xy_theta"][:]
        for spec, s in zip(specs, index):
            a = grasps[grasp_scene == s]
            if not checked:  # the stored pile and the dataset's own seed give its grasps
                again = find_grasps(spec, library, np.random.default_rng([int(spec.seed), 1]),
                                    **search).xy_theta
                if again.shape != a.shape or not np.allclose(again, a):
                    raise SystemExit(f"{shard}: pile {s}: the dataset's search does not "
                                     "reproduce the stored grasps; the piles are not the ones "
                                     "this code would label")
                checked = True
            b = find_grasps(spec, library, np.random.default_rng([int(spec.seed), 1001]),
                            **search).xy_theta
            found_a.append(len(a))
            found_b.append(len(b))
            if len(a) == 0 or len(b) == 0:
                continue
            for h in hand[image_scene == s]:
                actions = sample_candidates(rng, args.candidates, xy_m=0.04, theta_deg=45.0)
                poses = apply_actions(h[[0, 1, 3]][None], actions[None])[0]
                da = distance_to_nearest_grasp(poses, a)
                db = distance_to_nearest_grasp(poses, b)
                rho.append(spearman(db[None], da[None])[0])
                regret.append(regret_m(db[None], da[None])[0])
                regret_rev.append(regret_m(da[None], db[None])[0])
        print(shard.name, len(rho), flush=True)
    rho, regret = np.array(rho), np.array(regret)
    out = {"data": str(args.data), "piles": len(found_a), "images": int(len(rho)),
           "candidates": args.candidates, "search": search,
           "true_grasps_per_pile_median": {"dataset": float(np.median(found_a)),
                                           "second_search": float(np.median(found_b))},
           "spearman_mean": float(np.nanmean(rho)), "spearman_median": float(np.nanmedian(rho)),
           "regret_median_m": float(np.median(regret)), "regret_mean_m": float(regret.mean()),
           "top1_within_1cm": float(np.mean(regret <= 0.01)),
           "regret_median_m_reversed": float(np.median(regret_rev))}
    print_json(out, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
