"""Replays every collision attempt of the given run folders and prints which gripper
bodies touched an object at the judge's first touching sample."""
import json, sys
from drake_grasp.evaluation.episode import simulate_episode
from drake_grasp.evaluation.replay import recorded_scenario
from drake_grasp.evaluation.records import load_records
from drake_grasp.world.scene import SceneSpec
out = open(sys.argv[1], "a")
for f in sys.argv[2:]:
    for rec in load_records(f):
        if rec.failure_class != "collision":
            continue
        r = simulate_episode(recorded_scenario(rec.scenario_yaml), scenario_name=rec.scenario_name,
                             scene=SceneSpec.from_dict(rec.extra["scene"]), record_depth=False).result
        row = {"folder": f, "trial": rec.trial_id, "now_class": r.details["failure_class"],
               "collision": r.details["judge"]["collision"]}
        out.write(json.dumps(row) + "\n"); out.flush()
        print(row, flush=True)
