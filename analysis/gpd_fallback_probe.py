"""GPD's "no grasp detected" clutter attempts, re-run with `gpd.fallback_best`.

In clutter most of GPD's failed attempts are attempts on which no candidate reached its
classifier's threshold (it then closes on nothing and the run usually ends three such
attempts later, objects left on the table). Would its best-ranked candidate have held?
Each such attempt of a results folder is re-run from its recorded scenario and pile twice:
as recorded (it must again detect nothing: the check that this package simulates what
the folder's did) and with `gpd.fallback_best: true`.

    python analysis/gpd_fallback_probe.py RESULTS_DIR [RESULTS_DIR...] --out FILE.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from drake_grasp.evaluation.records import load_records

NO_DETECTION = "missed: no grasp detected"


def probe(folder: Path) -> list[dict]:
    from drake_grasp.evaluation.episode import simulate_episode
    from drake_grasp.evaluation.replay import recorded_scenario
    from drake_grasp.objects import load_library
    from drake_grasp.world.scene import SceneSpec

    library = load_library(None)
    out = []
    for rec in sorted(load_records(folder), key=lambda r: r.trial_id):
        if rec.policy != "gpd" or not (rec.failure_reason or "").startswith(NO_DETECTION):
            continue
        scenario = recorded_scenario(rec.scenario_yaml)
        scene = SceneSpec.from_dict(rec.extra["scene"])
        row = {"trial_id": rec.trial_id, "objects": len(scene.objects)}
        for name, s in (("as recorded", scenario),
                        ("fallback", dataclasses.replace(
                            scenario, gpd=dataclasses.replace(scenario.gpd, fallback_best=True)))):
            t0 = time.perf_counter()
            r = simulate_episode(s, library=library, scene=scene, record_depth=False,
                                 visualize=False).result
            row[name] = {"success": bool(r.success), "failure_reason": r.failure_reason,
                         "grasped_object_id": r.details.get("grasped_object_id"),
                         "wall_s": round(time.perf_counter() - t0, 1)}
        print(json.dumps(row), flush=True)
        out.append(row)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", nargs="+")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    rows = {f: probe(Path(f)) for f in args.results}
    flat = [r for v in rows.values() for r in v]
    summary = {"attempts": len(flat),
               "reproduced_no_detection": sum(
                   (r["as recorded"]["failure_reason"] or "").startswith(NO_DETECTION)
                   for r in flat),
               "held_with_fallback": sum(r["fallback"]["success"] for r in flat)}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"summary": summary, "folders": rows}, indent=1) + "\n")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
