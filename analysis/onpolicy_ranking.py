"""The CNN's ranking on the closed loop's own states: every control decision of recorded
CTR clutter attempts, replayed, with the true distance of each of its candidates.

The ranking metrics of `analysis/cnn_eval.py` use the dataset's images, whose hands are
drawn over the objects and which all hold a grasp near the hand. The controller also
meets sparse piles and bare table (`analysis/results/cnn-view-average/`: an 8-view
average that ranked the dataset's pile images better grasped 5.9 points less in
clutter). This measures the ranking where the controller decides.

`collect` replays each recorded attempt (`replay.recorded_pile`: the record's
scenario, seed and starting pile; the replay must reproduce the recorded outcome, which
is checked and stored), keeps every decision's wrist image, believed hand pose,
candidates and the CNN's distances as the controller saw them, and labels every
candidate with its true distance to the pile's ground-truth grasps (`grasps.find_grasps`
on the starting pile, 1,600 surface points as the pile datasets; objects pushed during
the attempt are not followed; the grasps (x, y, theta) are kept too, so any action on
the kept images can be labelled later). One `.npz` per attempt, written atomically: a killed run
resumes where it stopped. `score` ranks those candidates with other scorers (the views
of `controller.view_average`, other weights) and reports, per scorer, the within-decision
Spearman, regret and top-1 within 1 cm over all decisions and split by the hand's height,
by the best candidate's true distance, and by the attempt's outcome. `labels` labels every
grid node of the kept images against the kept grasps (`dense_labels.label_grids`) into
a folder `train-grid --labels` takes: training on the closed loop's own states.
`--only` / `--exclude` select attempts by their results folder's name (a split by seed).

    python analysis/onpolicy_ranking.py collect analysis/results/cnn-view-average/plain-clutter-seed29 ... \
        --workers 2 --out data/onpolicy/plain
    python analysis/onpolicy_ranking.py score data/onpolicy/plain --views none,d4 \
        --out analysis/results/onpolicy-ranking/plain_states.json
    python analysis/onpolicy_ranking.py labels data/onpolicy/train-grasps \
        --exclude cnn-clutter-seed28 --out data/onpolicy/train_grid
"""
from __future__ import annotations

import argparse
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

GRASP_SAMPLES = 1600  # the pile datasets' (`generate --grasp-samples 1600`)
HEIGHT_EDGES_M = (0.0, 0.06, 0.09, 0.12, 0.15, 1.0)  # the grasp frame's z above the table
BEST_EDGES_M = (0.0, 0.01, 0.03, 0.06, 1.0)  # the best candidate's true distance


def collect_attempt(path: str, out_dir: str) -> dict:
    """Replays one recorded CTR clutter attempt and writes `out_dir/<folder>__<trial>.npz`
    (skipped when it exists). Returns the attempt's summary row."""
    from drake_grasp.geometry.actions import apply_actions
    from drake_grasp.learning.dataset import DatasetConfig
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.evaluation.episode_diagram import controller_class
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.geometry.grasp_metric import distance_to_nearest_grasp
    from drake_grasp.evaluation.replay import recorded_pile
    from drake_grasp.evaluation.trial_worker import _model
    from drake_grasp.objects import load_library
    from drake_grasp.core.files import atomic_write_bytes
    from drake_grasp.policies.ctr import CTRController

    rec, scenario, scene = recorded_pile(path)
    records = str(Path(path).parents[1])
    # Results folders of other seeds hold the same trial ids: the folder is in the name.
    name = f"{Path(records).name}__{rec['trial_id'].replace('/', '__')}"
    target = Path(out_dir) / f"{name}.npz"
    if target.is_file():
        with np.load(target) as f:
            meta = json.loads(str(f["meta"]))
        if (meta["trial_id"], Path(meta["records"]).name) != (rec["trial_id"], Path(records).name):
            raise ValueError(f"{target}: holds {meta['records']} {meta['trial_id']}, "
                             f"expected {records} {rec['trial_id']}")
        return meta
    if rec.get("policy") != "ctr":
        raise ValueError(f"{path}: expected a CTR clutter attempt's record, got policy "
                         f"{rec.get('policy')!r}")
    library = load_library(None)
    t0 = time.perf_counter()
    truth = find_grasps(scene, library, np.random.default_rng([int(rec["seed"]), 61]),
                        **{**DatasetConfig().grasp_search(), "num_samples": GRASP_SAMPLES})
    decided: dict = {}  # iteration -> StepRecord: every move the controller made

    class Logged(CTRController):
        def _ctr_step(self, context, s, t):
            new = super()._ctr_step(context, s, t)
            if new.last_step is not None and new.last_step is not s.last_step:
                decided[new.last_step.iteration] = new.last_step
            return new

    with controller_class(Logged):
        ep = simulate_episode(scenario, library=library, scene=scene, record_depth=False,
                              visualize=False, model=_model(scenario.controller.weights,
                                                            scenario.controller.torch_threads))
    steps = [decided[i] for i in sorted(decided)]
    hand = np.array([s.hand for s in steps], float).reshape(-1, 4)
    actions = np.array([s.actions for s in steps], float)
    true = np.full(actions.shape[:2], np.nan)
    if len(truth.xy_theta):
        for i in range(len(steps)):
            moved = apply_actions(hand[i, [0, 1, 3]][None], actions[i][None])[0]
            true[i] = distance_to_nearest_grasp(moved, truth.xy_theta)
    r = ep.result
    meta = {"trial_id": rec["trial_id"], "records": records,
            "weights": scenario.controller.weights,
            "view_average": scenario.controller.view_average,
            "success": bool(r.success), "failure_class": r.details.get("failure_class"),
            "reproduced": (bool(r.success) == bool(rec["success"])
                           and r.details.get("failure_class") == rec["failure_class"]),
            "decisions": len(steps),
            "recorded_decisions": (rec.get("extra") or {}).get("decisions"),
            "true_grasps": int(len(truth.xy_theta)),
            "objects": len(scene.objects), "wall_s": time.perf_counter() - t0}
    buf = io.BytesIO()
    np.savez_compressed(buf, depth=np.array([s.depth for s in steps], np.float32).reshape(
        -1, *np.shape(steps[0].depth)) if steps else np.zeros((0, 64, 64), np.float32),
        hand=hand, actions=actions, true=true, grasps=np.asarray(truth.xy_theta, float),
        predicted=np.array([s.distances for s in steps], float).reshape(actions.shape[:2]),
        meta=json.dumps(meta))
    atomic_write_bytes(target, buf.getvalue())
    return meta


def attempt_files(folder: Path, only=(), exclude=()) -> list[Path]:
    """The attempt files of a `collect` folder, those of the results folders named in
    `only` (all when empty) and not in `exclude` (a file's name starts with its results
    folder's name and `__`)."""
    files = sorted(Path(folder).glob("*.npz"))
    if not files:
        raise FileNotFoundError(f"{folder}: no *.npz (expected the output of "
                                "`onpolicy_ranking.py collect`)")
    source = {f: f.name.split("__", 1)[0] for f in files}
    for name in (*only, *exclude):
        if name not in source.values():
            raise ValueError(f"{folder}: no attempt of a results folder named {name!r} "
                             f"(it holds {sorted(set(source.values()))})")
    return [f for f in files if (not only or source[f] in only) and source[f] not in exclude]


def build_labels(folder: Path, out: Path, *, only=(), exclude=()) -> dict:
    """Dense labels of every kept decision image (`dense_labels.label_grids` against the
    attempt's starting pile's grasps), one `shard-<attempt>.npz` per attempt in `out`,
    the format of `dense_labels.build_labels` (`train-grid --labels out`). Attempts
    not reproduced or without a true grasp are left out; files already written are
    skipped."""
    from drake_grasp.learning.dense_labels import GRID_CONFIG, label_grids

    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(GRID_CONFIG.to_dict(), indent=1))
    counts = {"attempts": 0, "labelled_attempts": 0, "images": 0, "left_out": {}}
    for f in attempt_files(folder, only, exclude):
        counts["attempts"] += 1
        with np.load(f) as z:
            meta = json.loads(str(z["meta"]))
            why = ("not reproduced" if not meta["reproduced"] else
                   "no decision" if not meta["decisions"] else
                   "no true grasp" if not meta["true_grasps"] else None)
            if why:
                counts["left_out"][why] = counts["left_out"].get(why, 0) + 1
                continue
            if "grasps" not in z.files:
                raise ValueError(f"{f}: holds no 'grasps' (collected before they were "
                                 "kept); collect it again")
            target = out / f"shard-{f.stem}.npz"
            if not target.is_file():
                part = {"depth": z["depth"].astype(np.float16),
                        "grid": label_grids(z["hand"], z["grasps"], GRID_CONFIG),
                        "hand_z": z["hand"][:, 2].astype(np.float32)}
                tmp = out / f"shard-{f.stem}.tmp.npz"
                np.savez(tmp, **part)
                tmp.replace(target)
            counts["labelled_attempts"] += 1
            counts["images"] += int(meta["decisions"])
    return counts


def load_decisions(folder: Path, only=(), exclude=()) -> dict:
    """Every decision of every attempt in a `collect` folder (or of the results folders
    `only` / not `exclude`, `attempt_files`), stacked (attempts without a true grasp,
    whose candidates have no true distance, are left out)."""
    files = attempt_files(folder, only, exclude)
    keys = ("depth", "hand", "actions", "true", "predicted")
    out = {k: [] for k in keys}
    out["success"], out["attempt"], metas = [], [], []
    for i, f in enumerate(files):
        with np.load(f) as z:
            meta = json.loads(str(z["meta"]))
            metas.append(meta)
            if not meta["decisions"] or not meta["true_grasps"]:
                continue
            for k in keys:
                out[k].append(z[k])
            out["success"] += [meta["success"]] * meta["decisions"]
            out["attempt"] += [i] * meta["decisions"]
    data = {k: np.concatenate(v) for k, v in out.items() if k in keys}
    data["success"] = np.array(out["success"], bool)
    data["attempt"] = np.array(out["attempt"])
    return {"data": data, "metas": metas}


def metrics(true: np.ndarray, pred: np.ndarray) -> dict:
    from drake_grasp.learning.cnn_metrics import regret_m, spearman

    regret = regret_m(pred, true)
    return {"decisions": int(len(true)),
            "spearman_mean": float(np.nanmean(spearman(pred, true))),
            "regret_mean_mm": 1e3 * float(regret.mean()),
            "regret_median_mm": 1e3 * float(np.median(regret)),
            "top1_within_1cm": float(np.mean(regret <= 0.01))}


def score(folder: Path, scorers: dict, only=(), exclude=()) -> dict:
    """`scorers`: name -> fn(depth, actions) -> distances. The metrics over all decisions
    (of the attempts `attempt_files` selects) and split by hand height, best true
    distance and outcome."""
    loaded = load_decisions(folder, only, exclude)
    d = loaded["data"]
    preds = {name: np.array([fn(d["depth"][i], d["actions"][i]) for i in range(len(d["true"]))])
             for name, fn in scorers.items()}
    true = d["true"]

    def block(mask):
        return {name: metrics(true[mask], p[mask]) for name, p in preds.items()}

    def split(key, edges):
        return [{"range_m": [lo, hi], **block((key >= lo) & (key < hi))}
                for lo, hi in zip(edges[:-1], edges[1:]) if ((key >= lo) & (key < hi)).any()]

    metas = loaded["metas"]
    out = {"attempts": len(metas), "reproduced": sum(m["reproduced"] for m in metas),
           "attempts_with_true_grasps": sum(bool(m["true_grasps"]) for m in metas),
           "decisions": int(len(true)), "all": block(np.ones(len(true), bool)),
           "by_hand_height": split(d["hand"][:, 2], HEIGHT_EDGES_M),
           "by_best_true_distance": split(true.min(axis=1), BEST_EDGES_M),
           "by_outcome": {k: block(m) for k, m in (("held", d["success"]),
                                                   ("failed", ~d["success"])) if m.any()}}
    if "none" in preds:  # the recorded distances are the plain scorer's, if the weights match
        out["max_abs_recorded_minus_none_m"] = float(np.abs(preds["none"] - d["predicted"]).max())
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("collect", help="replay recorded CTR clutter attempts, keep their decisions")
    c.add_argument("records", nargs="+", help="clutter results folders (their trials/)")
    c.add_argument("--workers", type=int, default=2)
    c.add_argument("--out", required=True, help="folder for one .npz per attempt")
    s = sub.add_parser("score", help="rank a collect folder's candidates with other scorers")
    s.add_argument("folder")
    s.add_argument("--views", default="none,d4", help="comma-separated view_average values")
    s.add_argument("--weights", default="", help="CNN weights (default: the shipped net)")
    s.add_argument("--threads", type=int, default=2)
    s.add_argument("--out", required=True, help="JSON file to write")
    lab = sub.add_parser("labels", help="dense labels of a collect folder's images, for "
                                        "train-grid --labels")
    lab.add_argument("folder")
    lab.add_argument("--out", required=True, help="label folder (one shard per attempt)")
    for q in (s, lab):
        q.add_argument("--only", default="", help="comma-separated results folder names: "
                                                  "only their attempts")
        q.add_argument("--exclude", default="", help="comma-separated results folder names: "
                                                     "not their attempts")
    args = p.parse_args(argv)
    from drake_grasp.core.files import print_json

    if args.cmd == "collect":
        from drake_grasp.evaluation.montecarlo import parallel_map
        from drake_grasp.evaluation.records import trial_paths

        paths = []
        for folder in args.records:
            found = [str(q) for q in trial_paths(folder, condition="ctr")]
            if not found:
                sys.exit(f"onpolicy_ranking: {folder}: no CTR records")
            paths += found
        Path(args.out).mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        rows = parallel_map(collect_attempt, [(q, args.out) for q in paths],
                            workers=args.workers, desc="on-policy decisions")
        print_json({"attempts": len(rows), "reproduced": sum(r["reproduced"] for r in rows),
                    "decisions": sum(r["decisions"] for r in rows),
                    "wall_s": time.perf_counter() - t0}, None)
        return 0
    only = tuple(v for v in args.only.split(",") if v)
    exclude = tuple(v for v in args.exclude.split(",") if v)
    if args.cmd == "labels":
        t0 = time.perf_counter()
        try:
            counts = build_labels(Path(args.folder), Path(args.out), only=only, exclude=exclude)
        except (FileNotFoundError, ValueError) as e:
            sys.exit(f"onpolicy_ranking: {e}")
        print_json({**counts, "seconds": time.perf_counter() - t0}, None)
        return 0
    import torch

    from drake_grasp.policies.evaluator import load_cnn, score_candidates

    torch.set_num_threads(max(1, args.threads))
    if not Path(args.folder).is_dir():
        sys.exit(f"onpolicy_ranking: {args.folder}: no such folder")
    model = load_cnn(args.weights)
    views = [v for v in args.views.split(",") if v]
    scorers = {v: (lambda depth, actions, v=v: score_candidates(model, depth, actions, views=v))
               for v in views}
    t0 = time.perf_counter()
    try:
        result = score(Path(args.folder), scorers, only, exclude)
    except (FileNotFoundError, ValueError) as e:
        sys.exit(f"onpolicy_ranking: {e}")
    result = {"folder": args.folder, "only": list(only), "exclude": list(exclude),
              "weights": args.weights or "(shipped)", **result,
              "seconds": time.perf_counter() - t0}
    print_json(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
