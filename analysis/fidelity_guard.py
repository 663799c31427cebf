"""Fidelity guard of the physics profiles: the same grasps, executed in the grasp lab under
each profile, must be held as often.

It re-executes the checks recorded by a `drake-grasp label-check` run (same settled
scenes, same grasp poses, neighbours present) under each physics profile named, and
writes per profile: checked, held, hold rate of the accepted ("true") grasps with its
Wilson 95% interval, the rejected candidates' hold rate, and how often each profile's
verdict agrees with the others' and with the verdict recorded by the label-check run.

    python analysis/fidelity_guard.py analysis/results/label-check --scenes 84 \
        --profiles reference,fast --workers 2 --out analysis/results/fidelity-guard

Each (profile, scene) result is one file written atomically under OUT/<profile>/; a
re-run skips the finished ones.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


APPROXIMATIONS = ("lagged", "sap", "similar")


def _parse_profile(profile: str) -> tuple[str, str, str]:
    """NAME[@STEP][:APPROXIMATION] -> (name, step or "", approximation or "")."""
    head, _, approximation = profile.partition(":")
    name, _, step = head.partition("@")
    return name, step, approximation


def _scene_task(args) -> dict:
    record, profile, out_file, force_mode, close, shake_axes = args
    import numpy as np

    from drake_grasp.evaluation.lab import LabConfig, check_grasps
    from drake_grasp.objects import load_library
    from drake_grasp.core.files import atomic_write_text
    from drake_grasp.config.scenario import load_scenario
    from drake_grasp.world.scene import SceneSpec

    name, step, approximation = _parse_profile(profile)
    scenario = load_scenario(physics_profile=name)
    if step:
        scenario.plant.time_step = float(step)
    if approximation:
        scenario.plant.discrete_contact_approximation = approximation
    if force_mode:
        scenario.gripper.force_mode = force_mode
    library = load_library(None)
    scene = SceneSpec.from_dict(record["scene"])
    t0 = time.perf_counter()
    options = {} if shake_axes is None else {"shake_axes": tuple(shake_axes)}
    lab = (LabConfig(close_settle_s=None, **options) if close == "fixed"
           else LabConfig(**options))
    # One lab Diagram for the scene, reused by its checks (each in a fresh Context).
    results = check_grasps(None, [np.asarray(c["X_WG"]) for c in record["checks"]],
                           scene=scene, scenario=scenario, library=library, lab=lab,
                           object_indices=[c["object_index"] for c in record["checks"]],
                           neighbours=True)
    checks = []
    for c, r in zip(record["checks"], results):
        checks.append({"kind": c["kind"], "category": c["category"], "held": bool(r.held),
                       "failure": r.failure, "recorded_held": bool(c["held"]),
                       "sim_time_s": r.details["sim_time_s"],
                       "shake_failed_after": r.details.get("shake_failed_after", "")})
    out = {"scene_index": record["scene_index"], "profile": profile, "checks": checks,
           "wall_s": round(time.perf_counter() - t0, 2)}
    atomic_write_text(out_file, json.dumps(out))
    return out


def summarize(results: dict[str, list[dict]]) -> dict:
    """Hold rates per profile (`labelcheck.summarize`, the label-check's own definition)
    and verdict agreement between profiles (same checks)."""
    from drake_grasp.evaluation.labelcheck import summarize as label_summary

    summary = {}
    for profile, scenes in results.items():
        base = label_summary([{**s, "replaced_attempts": []} for s in scenes])
        checks = [c for s in scenes for c in s["checks"]]
        summary[profile] = {
            "checked": base["checked"], "held": base["held"],
            "precision": round(base["precision"], 4) if base["precision"] is not None else None,
            "precision_ci95": [round(v, 4) for v in base["precision_ci95"]],
            "rejected_checked": base["rejected_checked"], "rejected_held": base["rejected_held"],
            "agree_with_recorded": sum(c["held"] == c["recorded_held"] for c in checks),
            "checks": len(checks),
            "sim_s_per_check": round(sum(c.get("sim_time_s", float("nan")) for c in checks)
                                     / max(len(checks), 1), 3),
            "wall_s_per_check": round(sum(s["wall_s"] for s in scenes) / max(len(checks), 1), 3)}
    names = list(results)
    pairs = {}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            va = {s["scene_index"]: [c["held"] for c in s["checks"]] for s in results[a]}
            vb = {s["scene_index"]: [c["held"] for c in s["checks"]] for s in results[b]}
            common = sorted(set(va) & set(vb))
            both = [(x, y) for k in common for x, y in zip(va[k], vb[k])]
            pairs[f"{a}/{b}"] = {"checks": len(both), "agree": sum(x == y for x, y in both),
                                 f"held_{a}_only": sum(x and not y for x, y in both),
                                 f"held_{b}_only": sum(y and not x for x, y in both)}
    return {"profiles": summary, "agreement": pairs}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("label_check", help="folder of a `drake-grasp label-check` run (built-in objects)")
    p.add_argument("--scenes", type=int, required=True, help="its first N scene records")
    p.add_argument("--profiles", default="reference,fast",
                   help="comma-separated physics profiles, each optionally with another plant "
                        "step and discrete contact approximation as NAME[@SECONDS][:APPROX], "
                        "e.g. fast@0.01 or fast@0.01:sap (default: reference,fast)")
    from drake_grasp.config.sections import GRIP_FORCE_MODES

    p.add_argument("--force-mode", choices=GRIP_FORCE_MODES, default=None,
                   help="gripper.force_mode for every profile (default: the scenario's; "
                        "label-check runs before that field existed ran with 'limit')")
    p.add_argument("--close", choices=("settled", "fixed"), default="settled",
                   help="the lab's closing phase: ends once the grasp has settled (the "
                        "default, `LabConfig.close_settle_s`) or lasts the fixed `close_s` "
                        "(every check before 2026-11-25)")
    p.add_argument("--shake-axes", default=None,
                   help="comma-separated shake segments in order (LabConfig.shake_axes, from "
                        "x,y,z,yaw,pitch,roll; default: LabConfig's)")
    p.add_argument("--scene-list", default=None,
                   help="comma-separated scene indices among the first --scenes: only these "
                        "(default: all)")
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--out", required=True, help="results folder (re-running resumes)")
    args = p.parse_args(argv)

    from drake_grasp.evaluation.labelcheck import read_records
    from drake_grasp.core.files import atomic_write_text
    from drake_grasp.config.sections import PHYSICS_PROFILES

    profiles = [x for x in args.profiles.split(",") if x]
    unknown = [x for x in profiles if _parse_profile(x)[0] not in PHYSICS_PROFILES]
    if unknown:
        raise SystemExit(f"--profiles: unknown {unknown}; known: {list(PHYSICS_PROFILES)}")
    bad = [x for x in profiles if _parse_profile(x)[2] not in ("",) + APPROXIMATIONS]
    if bad:
        raise SystemExit(f"--profiles: unknown contact approximation in {bad}; "
                         f"expected one of {APPROXIMATIONS}")
    shake_axes = None if args.shake_axes is None else [a for a in args.shake_axes.split(",") if a]
    src, out = Path(args.label_check), Path(args.out)
    records = read_records(src, args.scenes)  # its scenes/*.json or scenes.parquet
    have = {r["scene_index"] for r in records}
    missing = [i for i in range(args.scenes) if i not in have]
    if missing:
        raise SystemExit(f"{src}: no record of scene {missing[0]} (expected {args.scenes} "
                         "scene records)")
    if args.scene_list:
        wanted = {int(x) for x in args.scene_list.split(",") if x}
        if not wanted <= have:
            raise SystemExit(f"--scene-list: no record of scenes {sorted(wanted - have)}")
        records = [r for r in records if r["scene_index"] in wanted]
    names = [f"scene-{r['scene_index']:05d}.json" for r in records]
    todo = []
    for profile in profiles:
        (out / profile).mkdir(parents=True, exist_ok=True)
        for r, name in zip(records, names):
            target = out / profile / name
            if not target.is_file():
                todo.append((r, profile, str(target), args.force_mode, args.close, shake_axes))
    print(f"{len(todo)} scene checks to run ({len(records)} scenes x {len(profiles)} profiles, "
          f"{len(records) * len(profiles) - len(todo)} done)", flush=True)
    t0 = time.perf_counter()
    if todo:
        import multiprocessing as mp

        from tqdm import tqdm

        with mp.get_context("spawn").Pool(args.workers) as pool:
            for _ in tqdm(pool.imap_unordered(_scene_task, todo), total=len(todo)):
                pass
    results = {profile: [json.loads((out / profile / name).read_text()) for name in names]
               for profile in profiles}
    summary = summarize(results)
    summary.update({"label_check": str(src), "scenes": args.scenes,
                    "scene_list": args.scene_list or "all",
                    "force_mode": args.force_mode or "scenario default",
                    "close": args.close, "shake_axes": args.shake_axes or "LabConfig's",
                    "wall_s_this_call": round(time.perf_counter() - t0, 1),
                    "date": time.strftime("%Y-%m-%d")})
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
