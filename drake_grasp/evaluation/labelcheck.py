"""Label precision: do the dataset's ground-truth grasps hold in physics?

`run_label_check` samples scenes exactly as `drake-grasp generate` does (the `random`
scene config, 1-5 objects of one split, settled with the dataset's settling settings, an
unsettled pile replaced by the next seed of its scene), finds the ground-truth grasps
with the dataset's test and random stream, and executes a random sample of them - and
of the candidates the test rejected although the open hand reaches them with both pads
on one object - in the grasp physics lab (`lab.check_grasp`) with the scene's other
objects present. A label's "true" is then compared with what physics does:

    precision = held / checked among accepted grasps   (how often "true" holds)
    rejected_held / rejected_checked                   (grasps the test throws away)

Each scene is one JSON record under `OUT/scenes/`, written atomically, and packed into
`OUT/scenes.parquet` when the run ends (`scene_records`); `OUT/run.json`
holds the run's identity (seed, scenario, dataset and lab settings, sample sizes, object
library, code version), so a killed run re-run with the same command skips finished
scenes and counts nothing twice, and a different run is refused. `OUT/summary.json` and
`OUT/report.md` (with `failures.png`, top views of failed "true" grasps) are rebuilt
from the records at the end of every call (`make_label_report`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drake_grasp.geometry.contact_physics import MAX_TORQUE_RATIO
from drake_grasp.evaluation.records import wilson_interval
from drake_grasp.core.files import atomic_write_bytes, atomic_write_text
from drake_grasp.evaluation import scene_records
from drake_grasp.evaluation.scene_records import (RECORDS, done_scene_indices,
                                                  pack_scene_records, record_path)

FORMAT = "drake_grasp.label_check/1"


@dataclass
class LabelCheckConfig:
    """What one label-check run samples (per scene) and how it executes it."""

    # Ground-truth grasps executed per scene (fewer when the scene has fewer).
    grasps_per_scene: int = 3
    # Rejected candidates executed per scene.
    rejected_per_scene: int = 1
    # Object split the scenes draw from (the dataset makes both).
    split: str = "train"
    # The scene's other objects are loaded in the lab (they can block or disturb).
    neighbours: bool = True
    # The ground truth's torque limit (`dataset.DatasetConfig.max_torque_ratio`) the
    # grasps checked are labelled with.
    max_torque_ratio: float = MAX_TORQUE_RATIO
    # The objects' orientation before the settle (`dataset.DatasetConfig.initial_pose`,
    # `label-check --initial-pose`), as `generate` samples it.
    initial_pose: str = "uniform"

    def dataset_config(self):
        """The `dataset.DatasetConfig` this check samples and labels with."""
        from drake_grasp.learning.dataset import DatasetConfig

        return DatasetConfig(max_torque_ratio=self.max_torque_ratio,
                             initial_pose=self.initial_pose)

    def validate(self) -> None:
        if self.grasps_per_scene < 0 or self.rejected_per_scene < 0:
            raise ValueError("grasps_per_scene / rejected_per_scene: expected >= 0, got "
                             f"{self.grasps_per_scene} / {self.rejected_per_scene}")
        if self.grasps_per_scene + self.rejected_per_scene == 0:
            raise ValueError("grasps_per_scene + rejected_per_scene: expected >= 1 check per scene")
        if self.split not in ("train", "test"):
            raise ValueError(f"split: got {self.split!r}, expected 'train' or 'test'")
        if not 0 < self.max_torque_ratio < float("inf"):
            raise ValueError(f"max_torque_ratio: expected a finite number > 0, got "
                             f"{self.max_torque_ratio}")
        self.dataset_config().validate()  # initial_pose


def check_scene(scene_index: int, *, seed: int, scenario, library, config: LabelCheckConfig,
                dataset_config=None, lab=None) -> dict:
    """Samples, settles and labels scene `scene_index` as the dataset would, then executes
    a random sample of its accepted and rejected candidates in the lab. Returns the record.
    """
    from drake_grasp.learning.dataset import sample_dataset_scene
    from drake_grasp.geometry.grasps import find_grasps
    from drake_grasp.evaluation.lab import scene_labs
    from drake_grasp.world.scene import settle_scene

    dataset_config = (dataset_config if dataset_config is not None
                      else config.dataset_config())
    t0 = time.perf_counter()
    # As `dataset.generate_scene`: the profile's sheet, the dataset config's settling step.
    physics = dataclasses.replace(scenario.physics,
                                  settle_time_step_s=dataset_config.settle_time_step_s)
    attempts = []
    for attempt in range(dataset_config.max_attempts_per_scene):
        sampled = sample_dataset_scene(scenario, split=config.split, seed=seed,
                                       scene_index=scene_index, attempt=attempt,
                                       library=library,
                                       initial_pose=dataset_config.initial_pose)
        s_seed = sampled.seed  # scene_seed(seed, scene_index, attempt)
        spec = settle_scene(sampled, library,
                            plant_config=scenario.plant, physics=physics,
                            speed_tol_m_s=dataset_config.settle_speed_tol_m_s,
                            max_time_s=dataset_config.settle_max_time_s, verified=True)
        if not spec.settled:
            attempts.append({"seed": s_seed, "rejected": "unsettled"})
            continue
        # The dataset's random stream for this scene: the same grasps it would label with.
        accepted, rejected = find_grasps(spec, library, np.random.default_rng([s_seed, 1]),
                                         return_rejected=True, **dataset_config.grasp_search())
        if len(accepted) == 0:
            attempts.append({"seed": s_seed, "rejected": "no_grasp"})
            continue
        break
    else:
        raise RuntimeError(f"scene {scene_index}: no settled scene with a true grasp in "
                           f"{dataset_config.max_attempts_per_scene} seeds")
    pick = np.random.default_rng([s_seed, 53])
    # The scene's lab Diagram, built once and reused by its checks (each a fresh Context).
    labs = scene_labs(spec, scenario=scenario, library=library, lab=lab,
                      neighbours=config.neighbours)
    checks = []
    for kind, grasps, count in (("accepted", accepted, config.grasps_per_scene),
                                ("rejected", rejected, config.rejected_per_scene)):
        chosen = (pick.choice(len(grasps), size=min(count, len(grasps)), replace=False)
                  if len(grasps) else [])
        for i in sorted(int(c) for c in chosen):
            index = int(grasps.object_index[i])
            result = labs(index).check(grasps.poses[i], object_index=index)
            object_id = spec.objects[index].object_id
            checks.append({
                "kind": kind, "grasp_index": i, "object_index": index,
                "object_id": object_id, "category": library.get(object_id).category,
                "width_m": round(float(grasps.widths[i]), 5),
                "X_WG": np.asarray(grasps.poses[i]).round(6).tolist(),
                "held": bool(result.held), "failure": result.failure,
                "details": {k: v for k, v in result.details.items() if k != "X_WG"}})
    return {"format": FORMAT, "scene_index": int(scene_index), "seed": int(s_seed),
            "replaced_attempts": attempts, "scene": spec.to_dict(),
            "num_accepted": len(accepted), "num_rejected": len(rejected),
            "checks": checks, "wall_s": round(time.perf_counter() - t0, 3)}


def _task(scene_index: int, out: str, seed: int, scenario_yaml: str, objects_dir: str,
          config: dict, lab: dict) -> dict:
    """One worker task: a scene's record, written atomically."""
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.evaluation.lab import LabConfig
    from drake_grasp.objects import load_library
    from drake_grasp.config.scenario import Scenario

    scenario = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    library = load_library(objects_dir or None)
    record = check_scene(scene_index, seed=seed, scenario=scenario, library=library,
                         config=LabelCheckConfig(**config), lab=LabConfig(**lab))
    atomic_write_text(record_path(Path(out), scene_index), json.dumps(record))
    return record


def _identity(*, seed, scenario, library, config, lab) -> dict:
    from drake_grasp.core.provenance import code_version
    from drake_grasp.config.scenario import dump_scenario

    # initial_pose enters through the dataset's identity (left out there at "uniform"), so
    # that the folders made before it resume.
    label_check = {k: v for k, v in dataclasses.asdict(config).items() if k != "initial_pose"}
    return {"format": FORMAT, "seed": int(seed), "scenario": dump_scenario(scenario),
            "label_check": label_check,
            # In run.json's JSON form (shake_axes a list), so a resumed run compares equal.
            "lab": {**dataclasses.asdict(lab), "shake_axes": list(lab.shake_axes)},
            "dataset": config.dataset_config().identity(),
            "object_library_hash": library.content_hash(), "code_version": code_version()}


def _first_difference(a, b, path="") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            sub = f"{path}.{key}" if path else str(key)
            if key not in a or key not in b:
                return f"{sub}: {'missing in the folder' if key not in a else 'missing now'}"
            d = _first_difference(a[key], b[key], sub)
            if d:
                return d
        return None
    return None if a == b else f"{path}: {a!r} in the folder, {b!r} now"


def prepare_run_folder(out: Path, identity: dict, *, what: str) -> None:
    """Creates `out` with `run.json` = `identity` and `out/scenes/`, or checks that an
    existing folder holds the same run (resume).

    Raises:
        ValueError: `out` holds another run (the first difference named) or something
            that is not such a run.
    """
    run_json = out / "run.json"
    if run_json.exists():
        try:
            stored = json.loads(run_json.read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"{run_json}: not a {what} run file ({e})") from None
        diff = _first_difference(stored, identity)
        if diff:
            raise ValueError(f"{run_json}: {diff}. Resuming into {out} would mix two different "
                             f"{what} runs; choose another --out.")
    elif out.exists() and any(out.iterdir()):
        raise ValueError(f"{out}: exists and is not a {what} folder (no run.json); "
                         "choose another --out")
    (out / RECORDS).mkdir(parents=True, exist_ok=True)
    if not run_json.exists():
        atomic_write_text(run_json, json.dumps(identity, indent=1))


def run_label_check(*, num_scenes: int, seed: int, out, scenario, library,
                    config: LabelCheckConfig | None = None, lab=None, workers: int = 1,
                    objects_dir: str = "", show_progress: bool = True) -> dict:
    """Checks the labels of `num_scenes` scenes (see the module docstring); resumable.

    Raises:
        ValueError: a bad argument, or `out` holds a different run (first difference named).
    """
    from tqdm import tqdm

    from drake_grasp.evaluation.lab import LabConfig
    from drake_grasp.config.scenario import dump_scenario

    config = config if config is not None else LabelCheckConfig()
    config.validate()
    lab = lab if lab is not None else LabConfig()
    if num_scenes < 1:
        raise ValueError(f"num_scenes: expected >= 1, got {num_scenes}")
    if workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    out = Path(out)
    identity = _identity(seed=seed, scenario=scenario, library=library, config=config, lab=lab)
    prepare_run_folder(out, identity, what="label-check")
    done_before = done_scene_indices(out)
    todo = [i for i in range(num_scenes) if i not in done_before]
    bar = tqdm(total=num_scenes, initial=num_scenes - len(todo), desc="label-check",
               unit="scene", disable=not show_progress)
    t0 = time.perf_counter()
    args = dict(out=str(out), seed=int(seed), scenario_yaml=dump_scenario(scenario),
                objects_dir=str(objects_dir or ""), config=dataclasses.asdict(config),
                lab=dataclasses.asdict(lab))
    counts = {"checked": 0, "held": 0}

    def done(record):
        for c in record["checks"]:
            if c["kind"] == "accepted" and c["failure"] != "simulation-error":
                counts["checked"] += 1
                counts["held"] += c["held"]
        bar.set_postfix(precision=f"{counts['held']}/{counts['checked']}")
        bar.update(1)

    if workers == 1:
        for i in todo:
            done(_task(i, **args))
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
            futures = [pool.submit(_task, i, **args) for i in todo]
            for f in as_completed(futures):
                done(f.result())
    bar.close()
    pack_scene_records(out)
    return make_label_report(out, num_scenes=num_scenes, wall_s=time.perf_counter() - t0,
                             library=library)


def _rate(held: int, n: int) -> dict:
    lo, hi = wilson_interval(held, n)
    return {"checked": n, "held": held, "precision": held / n if n else None,
            "ci95": [round(lo, 4), round(hi, 4)]}


def read_records(out, num_scenes: int | None = None, *, format: str = FORMAT) -> list[dict]:
    """The scene records of a run folder (the first `num_scenes`, or all; files or
    `scenes.parquet`), each checked to be of `format` (a label check's by default)."""
    return scene_records.read_records(out, num_scenes, format=format)


def summarize(records: list[dict]) -> dict:
    """Counts, precision with Wilson 95% intervals, per category and per failure class."""
    from drake_grasp.evaluation.lab import FAILURES

    accepted = [c for r in records for c in r["checks"]
                if c["kind"] == "accepted" and c["failure"] != "simulation-error"]
    rejected = [c for r in records for c in r["checks"]
                if c["kind"] == "rejected" and c["failure"] != "simulation-error"]
    errors = sum(c["failure"] == "simulation-error" for r in records for c in r["checks"])
    held = sum(c["held"] for c in accepted)
    # Lift and hold only (what the station's judge asks of an episode): shake failures count
    # as held here.
    held_lift_hold = sum(c["held"] or c["failure"] == "dropped-by-shake" for c in accepted)
    overall = _rate(held, len(accepted))
    per_category = {}
    for cat in sorted({c["category"] for c in accepted}):
        cs = [c for c in accepted if c["category"] == cat]
        per_category[cat] = _rate(sum(c["held"] for c in cs), len(cs))
    rej_held = sum(c["held"] for c in rejected)
    return {
        "scenes": len(records), "checked": len(accepted), "held": held,
        "precision": overall["precision"], "precision_ci95": overall["ci95"],
        "precision_lift_hold": held_lift_hold / len(accepted) if accepted else None,
        "rejected_checked": len(rejected), "rejected_held": rej_held,
        "rejected_hold_rate": rej_held / len(rejected) if rejected else None,
        "simulation_errors": errors,
        "failures": {name: sum(c["failure"] == name for c in accepted) for name in FAILURES},
        "per_category": per_category,
        "min_category_precision": (min(v["precision"] for v in per_category.values())
                                   if per_category else None),
        "replaced_scenes": sum(len(r["replaced_attempts"]) for r in records),
        "worker_s": round(sum(r["wall_s"] for r in records), 1),
    }


def failure_picture(records: list[dict], path, *, library, max_panels: int = 16) -> int:
    """Top views of failed "true" grasps: the scene's objects (target in colour), the
    pads where they would close, the failure class. Returns the number of panels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from drake_grasp.geometry.hand_model import PAD_HALF_WIDTH_M
    from drake_grasp.geometry.scene_samples import scene_meshes
    from drake_grasp.world.scene import SceneSpec

    fails = [(r, c) for r in records for c in r["checks"]
             if c["kind"] == "accepted" and not c["held"] and c["failure"] != "simulation-error"]
    fails = fails[:max_panels]
    if not fails:
        return 0
    cols = min(4, len(fails))
    rows = (len(fails) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (r, c) in zip(axes.ravel(), fails):
        spec = SceneSpec.from_dict(r["scene"])
        meshes = scene_meshes(spec, library)
        for k, mesh in enumerate(meshes):
            # Filled silhouettes: every triangle projected onto the table.
            tris = np.asarray(mesh.vertices)[np.asarray(mesh.faces)][:, :, :2]
            color = "tab:orange" if k == c["object_index"] else "0.7"
            ax.add_collection(PolyCollection(tris, facecolors=color, edgecolors="none"))
        X = np.asarray(c["X_WG"])
        p, x_axis, y_axis = X[:3, 3], X[:3, 0], X[:3, 1]
        for side in (-1.0, 1.0):
            centre = p + side * (0.5 * c["width_m"] + 0.003) * x_axis
            ends = np.array([centre - PAD_HALF_WIDTH_M * y_axis, centre + PAD_HALF_WIDTH_M * y_axis])
            ax.plot(ends[:, 0], ends[:, 1], "b-", lw=3)
        ax.plot(*p[:2], "b+", ms=8)
        ax.set_title(f"{c['object_id']}\n{c['failure']}", fontsize=8)
        ax.set_aspect("equal")
        ax.set_xlim(p[0] - 0.12, p[0] + 0.12)
        ax.set_ylim(p[1] - 0.12, p[1] + 0.12)
    fig.suptitle("Failed ground-truth grasps, top view\n(pads blue, grasped object orange)",
                 fontsize=9)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return len(fails)


def _scenario_time_step(run: dict) -> float:
    """The plant step of a run.json's scenario (the lab's step when it sets none)."""
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.config.scenario import Scenario

    return yaml_load_typed(schema=Scenario, data=run["scenario"]).plant.time_step


def make_label_report(out, *, num_scenes: int | None = None, wall_s: float | None = None,
                      library=None) -> dict:
    """`summary.json` and `report.md` (+ `failures.png`) from the folder's records."""
    out = Path(out)
    records = read_records(out, num_scenes)
    summary = summarize(records)
    run = json.loads((out / "run.json").read_text())
    summary["seed"] = run["seed"]
    summary["lab_time_step_s"] = run["lab"].get("time_step_s") or _scenario_time_step(run)
    if wall_s is not None:
        summary["wall_s_this_call"] = round(wall_s, 1)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1))
    panels = failure_picture(records, out / "failures.png", library=library) if library else 0

    def pct(v):
        return "n/a" if v is None else f"{100 * v:.1f}%"

    lines = [
        "# Label check: ground-truth grasps executed in the grasp physics lab", "",
        f"{summary['scenes']} scenes (seed {summary['seed']}), sampled and labelled as "
        "`drake-grasp generate` does; each checked grasp is executed with the scene's "
        "other objects present (descend, close, lift, hold, shake; lab step "
        f"{summary['lab_time_step_s']} s).", "",
        "| | checked | held | rate | 95% CI |", "|---|---|---|---|---|",
        f"| accepted (\"true\") grasps | {summary['checked']} | {summary['held']} | "
        f"{pct(summary['precision'])} | [{pct(summary['precision_ci95'][0])}, "
        f"{pct(summary['precision_ci95'][1])}] |",
        f"| rejected candidates | {summary['rejected_checked']} | {summary['rejected_held']} | "
        f"{pct(summary['rejected_hold_rate'])} | |", "",
        f"Precision through lift and hold only (a shake failure counted as held): "
        f"{pct(summary['precision_lift_hold'])}. Simulation errors (left out): "
        f"{summary['simulation_errors']}.", "",
        "| category | checked | held | precision | 95% CI |", "|---|---|---|---|---|"]
    for cat, v in summary["per_category"].items():
        lines.append(f"| {cat} | {v['checked']} | {v['held']} | {pct(v['precision'])} | "
                     f"[{pct(v['ci95'][0])}, {pct(v['ci95'][1])}] |")
    lines += ["", "Failures of accepted grasps: " + ", ".join(
        f"{k} {v}" for k, v in summary["failures"].items() if v) or "none", ""]
    if panels:
        lines += [f"![failed ground-truth grasps](failures.png) (the first {panels})", ""]
    atomic_write_text(out / "report.md", "\n".join(lines))
    return summary


__all__ = ["LabelCheckConfig", "check_scene", "make_label_report", "prepare_run_folder",
           "read_records", "record_path", "run_label_check", "summarize"]
