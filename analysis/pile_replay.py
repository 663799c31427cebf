"""Another distance function on the same clutter piles: each recorded CTR attempt of one
or more clutter runs replayed from the pile it began on, with other weights, paired with
the recorded outcome.

Clutter runs of two nets are not paired beyond their first attempts (each attempt's pile
depends on the attempts before it), so two runs of 10 piles differ by as much as their
intervals are wide. Replaying every recorded attempt's starting pile (the record's
`extra.scene`, scenario and seed; `replay.recorded_pile`) with `--weights` pairs the
two nets attempt by attempt on the same piles: how many only one of them grasped, and
the exact McNemar test on those.

    python analysis/pile_replay.py analysis/results/paper-bn12/clutter \
        analysis/results/more-scenes/bn12-clutter-seed14 \
        analysis/results/more-scenes/bn12-clutter-seed15 \
        --weights models/fcn-heightmap/weights.safetensors --workers 2 \
        --out analysis/results/fcn-closed-loop/pile_replay.json

`--also-recorded` replays each pile with the record's own weights as well: a check that
the current package reproduces the recorded outcomes (the comparison is with them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path


def replay(path: str, weights: str) -> dict:
    """One recorded CTR clutter attempt's pile, simulated by CTR with `weights` ("": the
    record's own)."""
    from drake_grasp.evaluation.replay import recorded_pile
    from drake_grasp.evaluation.trial_worker import _simulate
    from drake_grasp.objects import load_library

    rec, scenario, scene = recorded_pile(path)
    if rec.get("policy") != "ctr":
        raise ValueError(f"{path}: expected a CTR clutter attempt's record, got policy "
                         f"{rec.get('policy')!r}")
    if weights:
        scenario = dataclasses.replace(scenario, controller=dataclasses.replace(
            scenario.controller, weights=weights))
    t0 = time.perf_counter()
    r = _simulate(scenario, load_library(None), scene=scene).result
    return {"success": bool(r.success), "failure_class": r.details.get("failure_class"),
            "final_distance_m": r.final_distance_m, "control_steps": r.control_steps,
            "grasped_object_id": r.details.get("grasped_object_id"),
            "wall_s": time.perf_counter() - t0}


def run_attempt(path: str, weights: str, also_recorded: bool) -> dict:
    from drake_grasp.evaluation.records import record_at

    rec = record_at(path).to_dict()  # the file, or its row once the folder is packed
    row = {"trial_id": rec["trial_id"], "records": str(Path(path).parents[1]),
           "recorded": {"success": bool(rec["success"]), "failure_class": rec["failure_class"],
                        "final_distance_m": rec["final_distance_m"]},
           "replay": replay(path, weights)}
    if also_recorded:
        row["recorded_weights_replay"] = replay(path, "")
    return row


def summarize(rows: list[dict]) -> dict:
    from drake_grasp.evaluation.records import mcnemar_exact_p, wilson_interval

    out = {"attempts": len(rows)}
    for name in ("recorded", "replay", "recorded_weights_replay"):
        if name not in rows[0]:
            continue
        k = sum(r[name]["success"] for r in rows)
        classes: dict = {}
        for r in rows:
            c = r[name]["failure_class"]
            classes[c] = classes.get(c, 0) + 1
        out[name] = {"successes": k, "rate": k / len(rows),
                     "ci95": list(wilson_interval(k, len(rows))), "failure_classes": classes}
    only_rec = sum(r["recorded"]["success"] and not r["replay"]["success"] for r in rows)
    only_new = sum(r["replay"]["success"] and not r["recorded"]["success"] for r in rows)
    out["paired"] = {"both": sum(r["recorded"]["success"] and r["replay"]["success"] for r in rows),
                     "recorded_only": only_rec, "replay_only": only_new,
                     "neither": sum(not r["recorded"]["success"] and not r["replay"]["success"]
                                    for r in rows),
                     "mcnemar_p": mcnemar_exact_p(only_rec, only_new)}
    if "recorded_weights_replay" in rows[0]:
        out["recorded_reproduced"] = sum(
            r["recorded_weights_replay"]["success"] == r["recorded"]["success"]
            and r["recorded_weights_replay"]["failure_class"] == r["recorded"]["failure_class"]
            for r in rows)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("records", nargs="+", help="clutter results folders (their trials/)")
    p.add_argument("--weights", required=True, help="the weights to replay the piles with "
                   "(A,B: an ensemble, as controller.weights takes it)")
    p.add_argument("--condition", default="ctr")
    p.add_argument("--trials", type=int, default=0, help="the first N attempts per folder (0: all)")
    p.add_argument("--also-recorded", action="store_true",
                   help="also replay each pile with the record's own weights")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", required=True, help="JSON file to write")
    args = p.parse_args(argv)
    from drake_grasp.evaluation.montecarlo import parallel_map
    from drake_grasp.core.provenance import code_version
    from drake_grasp.core.files import atomic_write_text
    from drake_grasp.evaluation.records import trial_paths

    for f in args.weights.split(","):
        if not Path(f).is_file():
            raise SystemExit(f"--weights: {f}: no such file")
    paths = []
    for folder in args.records:
        found = [str(q) for q in trial_paths(folder, condition=args.condition)]
        if not found:
            raise SystemExit(f"{folder}: no records of condition {args.condition!r}")
        paths += found[:args.trials] if args.trials else found
    t0 = time.perf_counter()
    rows = parallel_map(run_attempt, [(q, args.weights, args.also_recorded) for q in paths],
                        workers=args.workers, desc="pile replay")
    result = {"weights": args.weights, "code_version": code_version(),
              "wall_s": time.perf_counter() - t0, "all": summarize(rows),
              "by_records": {f: summarize([r for r in rows if r["records"] == str(Path(f))])
                             for f in args.records},
              "rows": rows}
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("weights", "wall_s", "all", "by_records")}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
