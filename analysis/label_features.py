"""What tells a ground-truth grasp that fails in physics from one that holds?

    python analysis/label_features.py --trials 120 --per-scene 4 --workers 2 \
        --out analysis/results/label-features

Takes the `isolation` experiment's scenes (trial i as `evaluate` builds it, as
`label_load_case.py` does) and, per scene, up to `--per-scene` grasps that the torque test
accepts with gravity alone (half of them, where there are enough, among those the lab's
shake load case rejects). For each it records the analytic test's quantities
(`grasps.check_grasp_poses`: the contact normals' lean from the closing line, the torque
ratio with gravity alone and with the shake, the width, the height of the grasp centre
and of the centre of mass above the sheet, how deep along the approach the contacts lie)
and executes it in the grasp lab: held through
lift and hold, and through the shake, and the failure class. `features.json` holds every
grasp; the printout gives the lift-and-hold rate per object and per band of each quantity,
so that a label rule which keeps the hammer's grasps and drops the banana's failures can
be read off (or shown not to exist among these quantities).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


LEAN_LIMITS_DEG = (6.0, 8.0, 10.0, 12.0, 14.1)
RATIO_LIMITS = (0.04, 0.06, 0.08, 0.1, 0.12)


def _lean_deg(check) -> np.ndarray:
    """Per grasp, the larger angle between a contact's inward normal and the closing line."""
    axis = check.contacts[:, 1] - check.contacts[:, 0]
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    # Outward normals: the first contact's points along -axis, the second's along +axis.
    c0 = np.clip(np.einsum("ij,ij->i", -check.contact_normals[:, 0], axis), -1, 1)
    c1 = np.clip(np.einsum("ij,ij->i", check.contact_normals[:, 1], axis), -1, 1)
    return np.degrees(np.maximum(np.arccos(c0), np.arccos(c1)))


def run_scene(index: int, seed: int, per_scene: int) -> dict:
    import drake_grasp.geometry.grasps as G
    from drake_grasp.evaluation.lab import check_grasp
    from drake_grasp.world.table import SHEET_THICKNESS_M
    from label_load_case import _grasps, gravity_only, isolation_scene

    t0 = time.perf_counter()
    scenario, scene, library = isolation_scene(index, seed)
    static = _grasps(scene, library, scenario.seed, shake=False)
    objects = G.ObjectMasses.of_scene(scene, library)
    # The surface samples `find_grasps` drew (same stream, same spacings), so that the
    # contacts below are the ones its tests saw.
    rng_points = np.random.default_rng([scenario.seed, 61])
    meshes = G.scene_meshes(scene, library)
    fine = G.sample_scene_points(meshes, rng_points, spacing_m=0.003)
    coarse = G.sample_scene_points(meshes, rng_points, spacing_m=0.005)
    rows, coverage = [], {}
    if len(static.poses):
        kw = dict(collision_points=coarse, mu=G.FORCE_CLOSURE_MU, objects=objects)
        gravity = G.check_grasp_poses(static.poses, fine, **kw)
        with gravity_only():
            still = G.check_grasp_poses(static.poses, fine, **kw)
        shake_ok = gravity.torque_ratio <= G.MAX_TORQUE_RATIO
        rng = np.random.default_rng([seed, index, 211])
        pools = [np.flatnonzero(~shake_ok), np.flatnonzero(shake_ok)]
        half = per_scene // 2
        take = [rng.choice(p, size=min(len(p), n), replace=False) if len(p) else np.zeros(0, int)
                for p, n in zip(pools, (half, per_scene - half))]
        chosen = np.concatenate(take).astype(int)
        lean = _lean_deg(gravity)
        com_z = objects.com_W[:, 2]
        # How many of the scene's grasps candidate rules keep: normals within LEAN of the
        # closing line and the static torque ratio at most RATIO ("LEAN/RATIO").
        coverage = {f"{a:g}/{b:g}": int(np.sum((lean <= a) & (still.torque_ratio <= b)))
                    for a in LEAN_LIMITS_DEG for b in RATIO_LIMITS}
        for i in chosen:
            r = check_grasp(None, static.poses[i], scene=scene, scenario=scenario,
                            library=library, object_index=int(static.object_index[i]))
            rows.append({
                "shake_test": bool(shake_ok[i]),
                "lean_deg": round(float(lean[i]), 2),
                "torque_ratio_static": round(float(still.torque_ratio[i]), 4),
                "torque_ratio_shake": round(float(gravity.torque_ratio[i]), 4),
                "width_m": round(float(static.widths[i]), 4),
                # How deep along the approach the contacts lie, from the grasp centre
                # (the pads reach +-FINGERTIP_Z_M = 19 mm): the deeper contact's offset.
                "contact_depth_m": round(float(np.max(
                    (gravity.contacts[i] - static.poses[i][:3, 3]) @ static.poses[i][:3, 2])), 4),
                "grasp_height_m": round(float(static.poses[i][2, 3] - SHEET_THICKNESS_M), 4),
                "com_height_m": round(float(com_z[static.object_index[i]] - SHEET_THICKNESS_M), 4),
                "held": bool(r.held), "failure": r.failure,
                "lift_hold": bool(r.held or r.failure == "dropped-by-shake")})
    return {"index": index, "object": scenario.scene.object_ids[0], "pose": scenario.scene.pose,
            "grasps_static": int(len(static.poses)), "coverage": coverage, "grasps": rows,
            "wall_s": round(time.perf_counter() - t0, 2)}


def _bands(rows, key, edges):
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = [r for r in rows if lo <= r[key] < hi]
        if sel:
            out.append(f"[{lo:g}, {hi:g}): {sum(r['lift_hold'] for r in sel)}/{len(sel)}")
    return "; ".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=120)
    p.add_argument("--per-scene", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    if args.trials < 1 or args.per_scene < 1:
        p.error("--trials and --per-scene: expected >= 1")
    from drake_grasp.evaluation.montecarlo import parallel_map
    from drake_grasp.core.provenance import code_version

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scenes = parallel_map(run_scene, [(i, args.seed, args.per_scene) for i in range(args.trials)],
                          workers=args.workers, desc="label features")
    rows = [dict(r, object=s["object"]) for s in scenes for r in s["grasps"]]
    tmp = out / "features.json.tmp"
    tmp.write_text(json.dumps({"seed": args.seed, "per_scene": args.per_scene,
                               "code_version": code_version(), "scenes": scenes}, indent=1))
    tmp.replace(out / "features.json")
    print(f"{len(rows)} grasps in {len(scenes)} scenes; lift-and-hold held / checked:")
    for obj in sorted({r["object"] for r in rows}):
        mine = [r for r in rows if r["object"] == obj]
        print(f"  {obj}: {sum(r['lift_hold'] for r in mine)}/{len(mine)}"
              f" (shake test passed: {sum(r['lift_hold'] for r in mine if r['shake_test'])}"
              f"/{sum(r['shake_test'] for r in mine)})")
    for key, edges in (("lean_deg", [0, 4, 8, 11, 14.1, 90]),
                       ("torque_ratio_static", [0, 0.02, 0.04, 0.06, 0.08, 0.121]),
                       ("torque_ratio_shake", [0, 0.06, 0.12, 0.2, 0.3, 1e9]),
                       ("grasp_height_m", [0, 0.02, 0.03, 0.04, 0.06, 1]),
                       ("width_m", [0, 0.02, 0.04, 0.06, 0.09]),
                       ("contact_depth_m", [-0.02, 0.0, 0.01, 0.014, 0.017, 0.02])):
        for group, sel in (("all", rows), ("banana", [r for r in rows if "banana" in r["object"]]),
                           ("others", [r for r in rows if "banana" not in r["object"]])):
            print(f"  {key} ({group}): {_bands(sel, key, edges)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
