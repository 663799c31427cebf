"""Does the CNN know when its clutter grasp will fail? Its least predicted distance at the
last control decision, against the outcome.

Replays every CTR attempt of a clutter run from the pile it began on (the record's scene,
scenario and seed; as `analysis/oracle_ctr.py --records` does) with the shipped CNN, and
logs at each control decision the least predicted distance among the candidates (what
Algorithm 1 moves toward). Writes each attempt's log and outcome, and for the last
decision's value: the medians for held and failed attempts and the AUC (the chance that a
failed attempt's value exceeds a held one's; 0.5 = no signal).

    python analysis/clutter_predicted_distance.py analysis/results/paper-bn12/clutter \
        [more runs...] --workers 2 --out analysis/results/oracle-ctr-clutter-bn12/predicted_distance.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def replay(path: str) -> dict:
    """One recorded CTR clutter attempt replayed with the CNN, its decisions logged."""
    from drake_grasp.evaluation.episode_diagram import controller_class
    from drake_grasp.evaluation.replay import recorded_pile
    from drake_grasp.evaluation.trial_worker import _simulate
    from drake_grasp.policies.ctr import CTRController
    from drake_grasp.objects import load_library

    rec, scenario, scene = recorded_pile(path)
    if rec.get("policy") != "ctr":
        raise ValueError(f"{path}: expected a CTR clutter attempt record")
    library = load_library(None)
    least: list[float] = []

    class Logged(CTRController):
        def _ctr_step(self, context, s, t):
            port = self._distances

            class _Port:  # the evaluator's port, its output logged
                @staticmethod
                def Eval(ctx):
                    d = np.asarray(port.Eval(ctx), float)
                    least.append(float(d.min()))
                    return d

            self._distances = _Port
            try:
                return super()._ctr_step(context, s, t)
            finally:
                self._distances = port

    with controller_class(Logged):
        r = _simulate(scenario, library, scene=scene).result
    return {"trial_id": rec["trial_id"], "success": bool(r.success),
            "recorded_success": bool(rec["success"]),
            "failure_class": r.details.get("failure_class"),
            "final_distance_m": r.final_distance_m,
            "recorded_decisions": (rec.get("extra") or {}).get("decisions"),
            "least_predicted_m": least}


def summarize(rows: list[dict]) -> dict:
    held = np.array([r["least_predicted_m"][-1] for r in rows if r["success"] and r["least_predicted_m"]])
    failed = np.array([r["least_predicted_m"][-1] for r in rows
                       if not r["success"] and r["least_predicted_m"]])
    out = {"attempts": len(rows), "held": int(len(held)), "failed": int(len(failed)),
           "replays_as_recorded": sum(r["success"] == r["recorded_success"] for r in rows)}
    if len(held) and len(failed):
        greater = (failed[:, None] > held[None, :]).mean() + 0.5 * (failed[:, None] == held[None, :]).mean()
        out.update({"last_least_predicted_mm": {
            "held_median": round(1000 * float(np.median(held)), 1),
            "held_p10_p90": [round(1000 * float(x), 1) for x in np.percentile(held, [10, 90])],
            "failed_median": round(1000 * float(np.median(failed)), 1),
            "failed_p10_p90": [round(1000 * float(x), 1) for x in np.percentile(failed, [10, 90])]},
            "auc_failed_above_held": round(float(greater), 3)})
        for t_mm in (25, 30, 35, 40):
            out[f"above_{t_mm}mm"] = {"failed": int((failed > t_mm / 1000).sum()),
                                      "held": int((held > t_mm / 1000).sum())}
    return out


def main(argv=None) -> int:
    from drake_grasp.evaluation.montecarlo import parallel_map
    from drake_grasp.core.provenance import code_version

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("records", nargs="+", help="clutter results folders (their trials/)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    args = p.parse_args(argv)
    from drake_grasp.evaluation.records import trial_paths

    paths = []
    for folder in args.records:
        found = [str(f) for f in trial_paths(folder, condition="ctr")]
        if not found:
            print(f"clutter_predicted_distance: error: {folder}: no CTR records",
                  file=sys.stderr)
            return 2
        paths += found
    t0 = time.perf_counter()
    rows = parallel_map(replay, [(f,) for f in paths], workers=args.workers,
                        desc="predicted distance")
    result = {"records": args.records, "code_version": code_version(),
              "wall_s": round(time.perf_counter() - t0, 1), "summary": summarize(rows),
              "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["summary"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
