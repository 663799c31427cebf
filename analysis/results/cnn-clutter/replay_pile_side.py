"""For recorded collision attempts replayed exactly: where the pile's centre (the mean
position of the objects at the start of the attempt) lies in the hand's frame when the
first collision happens, and which gripper body touched."""
import json, sys
import numpy as np
import drake_grasp.evaluation.episode as E
from drake_grasp.evaluation.replay import recorded_scenario
from drake_grasp.evaluation.records import load_records
from drake_grasp.world.scene import SceneSpec

POSES = []
_fd = E.final_distance
def logged(plant, ctx, station, *a, **k):  # the hand where closing starts: after the descent
    POSES.append(plant.GetFrameByName("grasp_frame").CalcPoseInWorld(ctx))
    return _fd(plant, ctx, station, *a, **k)
E.final_distance = logged
for folder in sys.argv[1:]:
    for rec in load_records(folder):
        if rec.failure_class != "collision":
            continue
        POSES.clear()
        scene = SceneSpec.from_dict(rec.extra["scene"])
        r = E.simulate_episode(recorded_scenario(rec.scenario_yaml), scenario_name=rec.scenario_name,
                               scene=scene, record_depth=False).result
        centre = np.mean([o.xyz for o in scene.objects], axis=0)
        X_WG = POSES[0]
        c_G = X_WG.inverse().multiply(centre)
        print(json.dumps({"trial": f"{folder}/{rec.trial_id}", "body": r.details["judge"]["collision"]["gripper_bodies"],
                          "pile_centre_in_G_mm": [round(1000 * v, 1) for v in c_G[:2]]}), flush=True)
