"""Recorded attempts replayed exactly, with the gripper's and named objects' positions read
every 10 ms and printed at the judge's phase starts: were the objects of a 'missed'
attempt lifted after all?

    python default-more-seeds/replay_miss.py default-more-seeds/cnn-clutter-seed28 banana_001,hammer_000 \
        clutter/ctr/0004/attempt06,clutter/ctr/0004/attempt07,clutter/ctr/0004/attempt08   # from analysis/results/

Each line: time, grasp frame xyz (m), left and right pad heights (m), distance between the
pads' reference points (m), and each named object's body origin (m).

    python default-more-seeds/replay_miss.py --count-lifted RUN [RUN...]

replays every failed attempt of the runs and prints the objects whose body origin is more
than 10 cm above the table when the attempt ends (the hand holds at about 17.5 cm; objects
on the table have their origins under 8 cm): a failure with two objects up is a two-object
hold the judge's one-object rule does not count.
"""
import json
import sys

import numpy as np
import pydrake.systems.analysis as A
from pydrake.multibody.tree import ModelInstanceIndex

import drake_grasp.evaluation.episode as E
from drake_grasp.evaluation.replay import recorded_scenario
from drake_grasp.evaluation.records import load_records
from drake_grasp.world.scene import SceneSpec

TRACE = []
PLANT = [None]
BODIES = {}  # object id -> its body in the episode being replayed (looked up once per replay)
COUNT = sys.argv[1] == "--count-lifted"
WATCH = [] if COUNT else sys.argv[2].split(",")
_Base = A.Simulator


def object_body(plant, object_id):
    """The first body of the model instance named '<object_k>::<object_id>'."""
    names = [plant.GetModelInstanceName(ModelInstanceIndex(i)) for i in range(plant.num_model_instances())]
    name = next(n for n in names if n.endswith("::" + object_id))
    return plant.get_body(plant.GetBodyIndices(plant.GetModelInstanceByName(name))[0])


class Tracing(_Base):
    def AdvanceTo(self, t_end):
        ctx = self.get_context()
        while ctx.get_time() < t_end - 1e-9:
            r = _Base.AdvanceTo(self, min(ctx.get_time() + 0.01, t_end))
            plant = PLANT[0]
            pc = plant.GetMyContextFromRoot(ctx)
            g = plant.GetFrameByName("grasp_frame").CalcPoseInWorld(pc).translation()
            pl = plant.GetBodyByName("left_finger").EvalPoseInWorld(pc).multiply(np.array([-0.003, 0, 0.135]))
            pr = plant.GetBodyByName("right_finger").EvalPoseInWorld(pc).multiply(np.array([0.003, 0, 0.135]))
            for n in WATCH:
                if n not in BODIES:
                    BODIES[n] = object_body(plant, n)
            objs = {n: [round(float(v), 4) for v in BODIES[n].EvalPoseInWorld(pc).translation()]
                    for n in WATCH}
            TRACE.append((round(ctx.get_time(), 3), [round(float(v), 4) for v in g], round(float(pl[2]), 4),
                          round(float(pr[2]), 4), round(float(np.linalg.norm(pl - pr)), 4), objs))
        return r


_build = E.build_episode_diagram


def build(*a, **k):
    ed = _build(*a, **k)
    PLANT[0] = ed.station.plant
    return ed


E.build_episode_diagram = build
A.Simulator = Tracing


def replay(rec):
    """The recorded attempt simulated again from its scene, scenario and seed, traced."""
    TRACE.clear()
    BODIES.clear()
    return E.simulate_episode(recorded_scenario(rec.scenario_yaml), scenario_name=rec.scenario_name,
                              scene=SceneSpec.from_dict(rec.extra["scene"]), record_depth=False).result


if COUNT:
    for folder in sys.argv[2:]:
        for rec in load_records(folder):
            if rec.success or rec.failure_class == "simulation-error":
                continue
            WATCH[:] = list(rec.object_ids)
            r = replay(rec)
            up = sorted(n for n, xyz in TRACE[-1][5].items() if xyz[2] > 0.10)
            print(json.dumps({"run": folder, "trial": rec.trial_id, "recorded": rec.failure_class,
                              "replayed_success": bool(r.success), "objects_up_at_end": up}), flush=True)
    sys.exit(0)
want = sys.argv[3].split(",")
for rec in load_records(sys.argv[1]):
    if rec.trial_id not in want:
        continue
    r = replay(rec)
    judge = r.details["judge"]
    print(rec.trial_id, "recorded:", rec.failure_class, "replayed success:", r.success,
          "target:", judge.get("target_object_id"), "held:", judge.get("held_object_id"))
    for phase, t in judge["phase_start_s"].items():
        print(" ", phase, min(TRACE, key=lambda x: abs(x[0] - t)))
