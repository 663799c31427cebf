"""Grasp tolerance: physical success as a function of the paper's distance metric.

Figure 5 of the paper reports how often a controller ends within a distance d of a true
grasp (d in the paper's metric, Euclidean in (x, y, 0.001 m/deg x theta)); Table 1 reports
physical success. `run_grasp_tolerance` ties the two: in isolation scenes of test objects
(the `isolation` scene config, settled by physics) it takes a ground-truth grasp that holds
in the grasp physics lab (`lab.check_grasp`; up to `max_verify` tries per scene), then
executes copies of it displaced by known planar offsets - a random direction in
(x, y, theta / 0.001 m/deg) space scaled to each of `offsets_mm` - at the same height,
with the same lab protocol (descend, close, lift, hold, shake). Each execution records
whether it held, the offset, and the displaced pose's distance to the NEAREST ground-truth
grasp of the scene (what Figure 5 measures; it can be smaller than the offset).

Records, resume and refusal of a different run work as in `labelcheck`.
`OUT/summary.json` holds the success rate with Wilson 95% intervals per offset and per
nearest-distance bin; `OUT/tolerance.png` draws both curves.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from drake_grasp.evaluation.labelcheck import prepare_run_folder, read_records
from drake_grasp.evaluation.scene_records import (done_scene_indices, pack_scene_records,
                                                  record_path)
from drake_grasp.evaluation.records import wilson_interval
from drake_grasp.core.files import atomic_write_bytes, atomic_write_text

FORMAT = "drake_grasp.grasp_tolerance/1"
DEFAULT_OFFSETS_MM = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0)
# Bins of the nearest-grasp distance [mm] for the summary (upper edges, inclusive).
DISTANCE_BINS_MM = (2.5, 7.5, 12.5, 17.5, 25.0, 35.0, 50.0)


def displaced_pose(X_WG: np.ndarray, offset_xy_theta) -> np.ndarray:
    """X_WG moved by (dx [m], dy [m]) in the world's xy plane and turned by dtheta [deg]
    about the world's vertical through the grasp centre (height unchanged)."""
    dx, dy, dtheta = (float(v) for v in offset_xy_theta)
    c, s = np.cos(np.deg2rad(dtheta)), np.sin(np.deg2rad(dtheta))
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    X = np.array(X_WG, dtype=float, copy=True)
    X[:3, :3] = Rz @ X[:3, :3]
    X[:3, 3] += [dx, dy, 0.0]
    return X


def random_offset(rng: np.random.Generator, distance_m: float,
                  angle_weight_m_per_deg: float = 0.001) -> np.ndarray:
    """An offset (dx, dy, dtheta_deg) of metric length `distance_m` in a uniformly random
    direction of (x, y, w theta) space."""
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    v = float(distance_m) * u
    return np.array([v[0], v[1], v[2] / angle_weight_m_per_deg])


def tolerance_scene(scene_index: int, *, seed: int, scenario, library, offsets_mm,
                    max_verify: int = 3, lab=None) -> dict:
    """One isolation scene: a lab-verified ground-truth grasp and its displaced copies."""
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.evaluation.lab import check_grasp
    from drake_grasp.world.scene import make_scene

    t0 = time.perf_counter()
    s_seed = int(np.random.default_rng([int(seed), int(scene_index), 71]).integers(2**31 - 1))
    config = dataclasses.replace(scenario.scene, kind="isolation", split="test", object_ids=[])
    spec = make_scene(config, s_seed, library, plant_config=scenario.plant,
                      physics=scenario.physics,
                      sheet_moves=scenario.sheet_moves)
    rng = np.random.default_rng([s_seed, 1])
    grasps = find_grasps(spec, library, rng)
    record = {"format": FORMAT, "scene_index": int(scene_index), "seed": s_seed,
              "scene": spec.to_dict(), "object_id": spec.objects[0].object_id if spec.objects
              else None, "num_grasps": len(grasps), "verify": [], "trials": []}
    if spec.objects:
        record["category"] = library.get(spec.objects[0].object_id).category
    order = rng.permutation(len(grasps))[:max_verify]
    base = None
    for i in order:
        result = check_grasp(None, grasps.poses[i], scene=spec, scenario=scenario,
                             library=library, lab=lab, object_index=int(grasps.object_index[i]))
        record["verify"].append({"grasp_index": int(i), "held": result.held,
                                 "failure": result.failure})
        if result.held:
            base = int(i)
            break
    if base is not None:
        X0 = grasps.poses[base]
        hand0 = grasps.xy_theta[base]
        for d_mm in offsets_mm:
            offset = random_offset(rng, d_mm / 1000.0)
            X = displaced_pose(X0, offset)
            moved = np.array([[X[0, 3], X[1, 3], np.mod(hand0[2] + offset[2], 180.0)]])
            nearest = float(grasps.distances(moved)[0])
            result = check_grasp(None, X, scene=spec, scenario=scenario, library=library,
                                 lab=lab, object_index=int(grasps.object_index[base]))
            record["trials"].append({
                "offset_mm": float(d_mm), "offset_xy_theta": [float(v) for v in offset],
                "nearest_distance_mm": round(1000.0 * nearest, 3),
                "held": result.held, "failure": result.failure})
    record["wall_s"] = round(time.perf_counter() - t0, 3)
    return record


def _task(scene_index: int, out: str, seed: int, scenario_yaml: str, objects_dir: str,
          offsets_mm: list, max_verify: int, lab: dict) -> dict:
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.evaluation.lab import LabConfig
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import Scenario

    record = tolerance_scene(scene_index, seed=seed,
                             scenario=yaml_load_typed(schema=Scenario, data=scenario_yaml),
                             library=load_library(objects_dir or None), offsets_mm=offsets_mm,
                             max_verify=max_verify, lab=LabConfig(**lab))
    atomic_write_text(record_path(Path(out), scene_index), json.dumps(record))
    return record


def run_grasp_tolerance(*, num_scenes: int, seed: int, out, scenario, library,
                        offsets_mm=DEFAULT_OFFSETS_MM, max_verify: int = 3, lab=None,
                        workers: int = 1, objects_dir: str = "",
                        show_progress: bool = True) -> dict:
    """Runs (or resumes) the grasp-tolerance experiment; returns the summary."""
    from tqdm import tqdm

    from drake_grasp.evaluation.lab import LabConfig
    from drake_grasp.core.provenance import code_version
    from drake_grasp.config.scenario import dump_scenario

    lab = lab if lab is not None else LabConfig()
    offsets_mm = [float(v) for v in offsets_mm]
    if num_scenes < 1 or workers < 1 or max_verify < 1:
        raise ValueError(f"num_scenes, workers, max_verify: expected >= 1, got {num_scenes}, "
                         f"{workers}, {max_verify}")
    if not offsets_mm or min(offsets_mm) < 0:
        raise ValueError(f"offsets_mm: expected non-negative distances, got {offsets_mm}")
    out = Path(out)
    identity = {"format": FORMAT, "seed": int(seed), "scenario": dump_scenario(scenario),
                "offsets_mm": offsets_mm, "max_verify": int(max_verify),
                "lab": dataclasses.asdict(lab), "object_library_hash": library.content_hash(),
                "code_version": code_version()}
    prepare_run_folder(out, identity, what="grasp-tolerance")
    done_before = done_scene_indices(out)
    todo = [i for i in range(num_scenes) if i not in done_before]
    args = dict(out=str(out), seed=int(seed), scenario_yaml=dump_scenario(scenario),
                objects_dir=str(objects_dir or ""), offsets_mm=offsets_mm,
                max_verify=int(max_verify), lab=dataclasses.asdict(lab))
    bar = tqdm(total=num_scenes, initial=num_scenes - len(todo), desc="grasp-tolerance",
               unit="scene", disable=not show_progress)
    if workers == 1:
        for i in todo:
            _task(i, **args)
            bar.update(1)
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
            for f in as_completed([pool.submit(_task, i, **args) for i in todo]):
                f.result()
                bar.update(1)
    bar.close()
    pack_scene_records(out)
    return make_tolerance_report(out, num_scenes=num_scenes)


def _rate(trials: list[dict]) -> dict:
    n = len(trials)
    held = sum(t["held"] for t in trials)
    lo, hi = wilson_interval(held, n)
    return {"n": n, "held": held, "success": held / n if n else None,
            "ci95": [round(lo, 4), round(hi, 4)]}


def summarize_tolerance(records: list[dict]) -> dict:
    """Success per offset and per nearest-distance bin (simulation errors left out)."""
    trials = [t for r in records for t in r["trials"] if t["failure"] != "simulation-error"]
    by_offset = {}
    for d in sorted({t["offset_mm"] for t in trials}):
        by_offset[f"{d:g}"] = _rate([t for t in trials if t["offset_mm"] == d])
    by_distance, lower = {}, 0.0
    for upper in DISTANCE_BINS_MM:
        sel = [t for t in trials if lower <= t["nearest_distance_mm"] < upper
               or (lower == 0.0 and t["nearest_distance_mm"] == 0.0)]
        by_distance[f"{lower:g}-{upper:g}"] = _rate(sel)
        lower = upper
    verified = [r for r in records if r["trials"]]
    return {"scenes": len(records), "scenes_with_verified_grasp": len(verified),
            "verify_checks": sum(len(r["verify"]) for r in records),
            "verify_held": sum(v["held"] for r in records for v in r["verify"]),
            "trials": len(trials), "by_offset_mm": by_offset,
            "by_nearest_distance_mm": by_distance,
            "simulation_errors": sum(t["failure"] == "simulation-error"
                                     for r in records for t in r["trials"])}


def tolerance_picture(summary: dict, path) -> None:
    """Success vs offset and vs nearest-grasp distance, with Wilson 95% intervals."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    for key, label, shift, fmt in (("by_offset_mm", "offset from a verified grasp", -0.4, "o-"),
                                   ("by_nearest_distance_mm", "distance to the nearest true "
                                    "grasp (bin centre)", 0.4, "s--")):
        xs, ys, lo, hi = [], [], [], []
        for name, v in summary[key].items():
            if not v["n"]:
                continue
            if "-" in name:
                a, b = (float(x) for x in name.split("-"))
                x = 0.5 * (a + b)
            else:
                x = float(name)
            xs.append(x + shift)
            ys.append(100 * v["success"])
            lo.append(100 * (v["success"] - v["ci95"][0]))
            hi.append(100 * (v["ci95"][1] - v["success"]))
        ax.errorbar(xs, ys, yerr=[lo, hi], fmt=fmt, capsize=3, label=label)
    ax.set_xlabel("distance in the paper's metric [mm] (1 mm = 1 degree)")
    ax.set_ylabel("held in the grasp lab [%]")
    ax.set_ylim(0, 105)
    ax.axvline(30, color="0.6", lw=0.8, ls=":")
    ax.text(30.5, 5, "3 cm (Figure 5)", color="0.4", fontsize=8)
    ax.legend(fontsize=8, loc="lower left")
    ax.set_title(f"Grasp tolerance: {summary['trials']} executions, "
                 f"{summary['scenes_with_verified_grasp']} scenes", fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def make_tolerance_report(out, *, num_scenes: int | None = None) -> dict:
    """`summary.json`, `tolerance.png` and `report.md` from the folder's records."""
    out = Path(out)
    records = read_records(out, num_scenes, format=FORMAT)
    summary = summarize_tolerance(records)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    tolerance_picture(summary, out / "tolerance.png")

    def row(name, v):
        if not v["n"]:
            return f"| {name} | 0 | | |"
        return (f"| {name} | {v['n']} | {100 * v['success']:.1f}% | "
                f"[{100 * v['ci95'][0]:.1f}, {100 * v['ci95'][1]:.1f}] |")

    lines = ["# Grasp tolerance: physical success vs the paper's distance metric", "",
             f"{summary['scenes_with_verified_grasp']} of {summary['scenes']} isolation scenes "
             "(test objects) had a ground-truth grasp that held in the grasp lab "
             f"({summary['verify_held']} of {summary['verify_checks']} verification checks "
             "held); each such grasp was executed again displaced by each offset in a random "
             "direction of (x, y, 0.001 m/deg x theta) space.", "",
             "![success vs distance](tolerance.png)", "",
             "| offset [mm] | executions | held | 95% CI |", "|---|---|---|---|"]
    lines += [row(k, v) for k, v in summary["by_offset_mm"].items()]
    lines += ["", "| distance to the nearest true grasp [mm] | executions | held | 95% CI |",
              "|---|---|---|---|"]
    lines += [row(k, v) for k, v in summary["by_nearest_distance_mm"].items()]
    atomic_write_text(out / "report.md", "\n".join(lines) + "\n")
    return summary


__all__ = ["DEFAULT_OFFSETS_MM", "displaced_pose", "make_tolerance_report", "random_offset",
           "run_grasp_tolerance", "summarize_tolerance", "tolerance_scene"]
