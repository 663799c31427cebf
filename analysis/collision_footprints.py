"""What the wrist image showed under the fingers when CTR decided to descend.

Re-runs recorded clutter attempts exactly (their resolved scenario and the pile they
started from, as `drake-grasp replay` does) and, at the descent decision, reads the
depth image the grasp height was read from: the highest surface seen under each open
finger's footprint (|x_G| from the inner pad face to the finger's outer face,
|y_G| <= the pad's half width, widened by 0 and 5 mm), relative to the planned
fingertips. The controller's `_grasp_from_depth` is wrapped to see its inputs; nothing
else changes.

    python analysis/collision_footprints.py RUN[,RUN...] collision OUT.jsonl SHARD NSHARDS
    python analysis/collision_footprints.py RUN[,RUN...] 25 OUT.jsonl SHARD NSHARDS

`collision`: every attempt the judge classed as a collision; a number N: N grasped
attempts per run folder, drawn with random.Random(0). OUT.jsonl gets one line per
attempt (a rerun skips the ones there); SHARD / NSHARDS split the list between processes.
Records written by another package version may not replay (the message says which).
"""

import json
import random
import sys
from pathlib import Path

from drake_grasp.evaluation.episode import simulate_episode
from drake_grasp.geometry.hand_model import (FINGER_OUTER_X_M, FINGERTIP_Z_M, PAD_HALF_WIDTH_M,
                                             STROKE_M)
from drake_grasp.evaluation.replay import recorded_scenario
from drake_grasp.policies.decisions import heights_in_hand_box, image_points_W
from drake_grasp.evaluation.records import load_records
from drake_grasp.world.scene import SceneSpec
from drake_grasp.policies import controller as C

LOG = []
_grasp_from_depth = C.GraspController._grasp_from_depth


def _logged(self, depth, seen_from, hand):
    out = _grasp_from_depth(self, depth, seen_from, hand)
    X_WC = (C.hand_to_pose(seen_from) @ self._X_GC).GetAsMatrix4()
    X_WG = C.hand_to_pose(out).GetAsMatrix4()
    res = {"hand": [float(v) for v in hand], "grasp": [float(v) for v in out]}
    tip = out[2] - FINGERTIP_Z_M
    P_W = image_points_W(depth, self._focal, X_WC, self._s.camera.depth_max_m)
    for margin in (0.0, 0.005):
        z, x = heights_in_hand_box(P_W, X_WG, FINGER_OUTER_X_M + margin, PAD_HALF_WIDTH_M + margin,
                                   return_x=True)
        for side, sel in (("left", x < -0.5 * STROKE_M), ("right", x > 0.5 * STROKE_M)):
            zz = z[sel]
            res[f"{side}_m{margin}"] = {"n": int(zz.size),
                                        "max_above_tip": float(zz.max() - tip) if zz.size else None}
    LOG.append(res)
    return out


C.GraspController._grasp_from_depth = _logged


def run(folder: str, trial_id: str) -> dict:
    rec = next(r for r in load_records(folder) if r.trial_id == trial_id)
    scenario = recorded_scenario(rec.scenario_yaml)
    LOG.clear()
    r = simulate_episode(scenario, scenario_name=rec.scenario_name,
                         scene=SceneSpec.from_dict(rec.extra["scene"]), record_depth=False)
    return {"folder": str(folder), "trial": trial_id, "rec_class": rec.failure_class,
            "rec_reason": rec.failure_reason, "now_class": r.result.details["failure_class"],
            "now_reason": r.result.failure_reason, "stop": rec.extra.get("stop_reason"),
            "log": list(LOG)}


def main(argv) -> int:
    if len(argv) != 5:
        print(__doc__, file=sys.stderr)
        return 2
    folders, which, out = argv[0].split(","), argv[1], Path(argv[2])
    shard, nshards = int(argv[3]), int(argv[4])
    done = set()
    if out.exists():
        for line in out.open():
            row = json.loads(line)
            done.add((row["folder"], row["trial"]))
    todo = []
    for f in folders:
        recs = load_records(f)
        if which == "collision":
            todo += [(f, r.trial_id) for r in recs if r.failure_class == "collision"]
        else:
            ok = [r for r in recs if r.success]
            todo += [(f, r.trial_id) for r in random.Random(0).sample(ok, min(int(which), len(ok)))]
    for i, (f, t) in enumerate(todo):
        if i % nshards != shard or (str(f), t) in done:
            continue
        res = run(f, t)
        with out.open("a") as fh:
            fh.write(json.dumps(res) + "\n")
        print(i, t, res["rec_class"], "->", res["now_class"], flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
