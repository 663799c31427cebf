"""Per-shake-segment judge on the checks today's lab fails in the hold or the shake.

Made for the lab before 2026-12-07 (evaluation/lab.py at 3cb1c84f6, whose `_run_checks`
it wraps to stop after each of the six shake segments); run it from such a checkout:

    python analysis/results/lab-speed-2026-12-07/shake_segments.py dropped-by-shake,slipped-during-hold

Prints, per check: scene, check, kind, today's failure, the re-run's, and after each
segment (x, y, z, yaw, pitch, roll) the pads touching and the rise [m]. Its output is
`shake_segments.json`. The lab now judges after each segment itself
(`details["shake_failed_after"]`; `fidelity_guard.py --shake-axes x,y,z,yaw,pitch,roll`).
"""
import json, glob, sys, time
import numpy as np
import drake_grasp.evaluation.lab as lab
from drake_grasp.systems.judge import pad_contacts
from drake_grasp.evaluation.labelcheck import read_records
from drake_grasp.objects import load_library
from drake_grasp.config.scenario import load_scenario
from drake_grasp.world.scene import SceneSpec

SEG = []
orig_run = lab._run_checks
def patched(simulator, plant, plant_context, gripper, body, L, scenario, phases, **kw):
    real_adv = simulator.AdvanceTo
    z_rest = kw["z_rest"]
    class S:
        def __getattr__(s, k): return getattr(simulator, k)
        def AdvanceTo(s, t):
            if abs(t - phases_box[0]["shake"]) < 1e-9:
                t0 = phases_box[0]["hold"]
                ends = np.cumsum([L.shake_translation_period_s]*3 + [L.shake_rotation_period_s]*3) + t0
                for e in ends:
                    real_adv(float(e))
                    pads = pad_contacts(plant, plant_context, body)
                    rise = float(plant.EvalBodyPoseInWorld(plant_context, body).translation()[2]) - z_rest
                    SEG.append((len(pads), round(rise, 4)))
                return
            return real_adv(t)
    phases_box = [phases]
    # track phase updates from close settle
    orig_bt = lab._base_trajectory
    def bt(*a, **k):
        r = orig_bt(*a, **k); phases_box[0] = r[2]; return r
    lab._base_trajectory = bt
    try:
        return orig_run(S(), plant, plant_context, gripper, body, L, scenario, phases, **kw)
    finally:
        lab._base_trajectory = orig_bt
lab._run_checks = patched

fast = {}
for f in glob.glob("analysis/results/fast10/fidelity-guard/fast/*.json"):
    d = json.load(open(f)); fast[d["scene_index"]] = d["checks"]
records = read_records("analysis/results/label-check-force-410", 100)
scenario = load_scenario(physics_profile="fast"); scenario.gripper.force_mode = "constant"
library = load_library(None)
want = set(sys.argv[1].split(","))
out = []
for r in records:
    for k, c in enumerate(r["checks"]):
        f = fast[r["scene_index"]][k]
        if f["failure"] not in want: continue
        SEG.clear()
        res = lab.check_grasp(None, np.asarray(c["X_WG"]), scene=SceneSpec.from_dict(r["scene"]), scenario=scenario,
                              library=library, object_index=c["object_index"], neighbours=True)
        print(r["scene_index"], k, c["kind"], "old", f["failure"] or "held", "now", res.failure or "held", SEG, flush=True)
