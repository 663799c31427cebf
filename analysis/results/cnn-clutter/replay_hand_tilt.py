"""At the moment the fingers start to close, the grasp frame's tilt: the z of the left and
right finger pad centres in the world, and the angle of the grasp frame's z axis from
vertical, for recorded attempts replayed exactly."""
import json, sys
import numpy as np
import drake_grasp.evaluation.episode as E
from drake_grasp.evaluation.replay import recorded_scenario
from drake_grasp.evaluation.records import load_records
from drake_grasp.world.scene import SceneSpec
LOG = []
_fd = E.final_distance
def logged(plant, ctx, station, *a, **k):
    G = plant.GetFrameByName("grasp_frame").CalcPoseInWorld(ctx)
    R = G.rotation().matrix()
    zl = plant.GetBodyByName("left_finger").EvalPoseInWorld(ctx).multiply(np.array([-0.003, 0, 0.135]))[2]
    zr = plant.GetBodyByName("right_finger").EvalPoseInWorld(ctx).multiply(np.array([0.003, 0, 0.135]))[2]
    LOG.append({"tilt_x_deg": float(np.degrees(np.arcsin(R[2, 0]))),  # G's x axis out of the horizontal
                "tilt_y_deg": float(np.degrees(np.arcsin(R[2, 1]))),
                "pad_z_left_minus_right_mm": float(1000 * (zl - zr))})
    return _fd(plant, ctx, station, *a, **k)
E.final_distance = logged
folder, n = sys.argv[1], int(sys.argv[2])
for rec in load_records(folder)[:n]:
    LOG.clear()
    E.simulate_episode(recorded_scenario(rec.scenario_yaml), scenario_name=rec.scenario_name,
                       scene=SceneSpec.from_dict(rec.extra["scene"]) if "scene" in rec.extra else None, record_depth=False)
    print(rec.trial_id, json.dumps(LOG[0] if LOG else None), flush=True)
