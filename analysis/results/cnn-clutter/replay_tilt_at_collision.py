"""For recorded collision attempts replayed exactly: the grasp frame's tilt and the pads'
height difference every 10 ms, reported at the judge's first collision time."""
import json, sys
import numpy as np
import pydrake.systems.analysis as A
import drake_grasp.evaluation.episode as E
from drake_grasp.evaluation.replay import recorded_scenario
from drake_grasp.evaluation.records import load_records
from drake_grasp.world.scene import SceneSpec

TRACE = []
_Base = A.Simulator


class Tracing(_Base):
    def AdvanceTo(self, t_end):
        ctx = self.get_context()
        while ctx.get_time() < t_end - 1e-9:
            r = _Base.AdvanceTo(self, min(ctx.get_time() + 0.01, t_end))
            plant = PLANT[0]
            pc = plant.GetMyContextFromRoot(ctx)
            R = plant.GetFrameByName("grasp_frame").CalcPoseInWorld(pc).rotation().matrix()
            zl = plant.GetBodyByName("left_finger").EvalPoseInWorld(pc).multiply(np.array([-0.003, 0, 0.135]))[2]
            zr = plant.GetBodyByName("right_finger").EvalPoseInWorld(pc).multiply(np.array([0.003, 0, 0.135]))[2]
            TRACE.append((ctx.get_time(), float(np.degrees(np.arcsin(R[2, 0]))), float(1000 * (zl - zr))))
        return r


PLANT = [None]
_build = E.build_episode_diagram
def build(*a, **k):
    ed = _build(*a, **k)
    PLANT[0] = ed.station.plant
    return ed
E.build_episode_diagram = build
A.Simulator = Tracing
for folder in sys.argv[1:]:
    for rec in load_records(folder):
        if rec.failure_class != "collision":
            continue
        TRACE.clear()
        r = E.simulate_episode(recorded_scenario(rec.scenario_yaml), scenario_name=rec.scenario_name,
                               scene=SceneSpec.from_dict(rec.extra["scene"]), record_depth=False).result
        hit = r.details["judge"]["collision"]
        t0 = r.details["judge"]["phase_start_s"]["descend"]
        at = min(TRACE, key=lambda x: abs(x[0] - hit["time_s"]))
        during = [x for x in TRACE if t0 <= x[0] <= hit["time_s"]]
        print(json.dumps({"trial": rec.trial_id, "body": hit["gripper_bodies"],
                          "at_hit_tilt_x_deg": round(at[1], 3), "at_hit_dz_left_minus_right_mm": round(at[2], 3),
                          "descent_max_abs_dz_mm": round(max(abs(x[2]) for x in during), 3) if during else None}), flush=True)
