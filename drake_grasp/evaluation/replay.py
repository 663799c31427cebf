"""Replaying recorded trials: the `Scenario` a trial record's YAML describes, with the
defaults of the day filled in for records older than a setting (`recorded_scenario`), the
CNN weights its run loaded (`recorded_weights`: the shipped file with the recorded sha256
where the named one is not here), a clutter attempt's record, scenario and starting pile
(`recorded_pile`), what a replay on this machine can promise (`machine_note`), and the
exact re-run of one recorded trial with its replay page (`replay_trial`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

from drake_grasp.evaluation.experiments import CNN_POLICIES
from drake_grasp.core.provenance import code_version, file_sha256, machine


def recorded_scenario(scenario_yaml: str):
    """The `Scenario` a trial record's YAML describes. A record written before physics
    profiles existed has no `physics:` entry: it ran the reference settings (its
    `plant.time_step` is in the record), so it gets the `reference` profile. One written
    before `physics.table_collision` existed ran with the table's box (the `fast`
    profile's half-space table came later), so it gets "box". One written before
    `gripper.force_mode` existed pressed with at most the grip force, so it gets
    "limit"; one written before `gpd.fallback_best` existed ran GPD's strict threshold,
    so it gets false."""
    from pydrake.common.yaml import yaml_load_typed

    from drake_grasp.config.scenario import Scenario, apply_physics_profile

    try:
        scenario = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    except RuntimeError as e:
        # e.g. "The fields ['stop_window_fraction'] were unknown to the schema": a key
        # this version of the package no longer has.
        raise ValueError(f"the recorded scenario does not load in drake_grasp {code_version()}: "
                         f"{e}") from None
    if not re.search(r"^physics:", scenario_yaml, re.MULTILINE):
        scenario = apply_physics_profile(scenario, "reference", keep={
            "plant.time_step", "plant.discrete_contact_approximation"})
    elif not re.search(r"^physics:\n(?:  .*\n)*  table_collision:", scenario_yaml, re.MULTILINE):
        # Recorded before `physics.table_collision` existed: the table had its box.
        scenario.physics.table_collision = "box"
    if not re.search(r"^gripper:\n(?:  .*\n)*  force_mode:", scenario_yaml, re.MULTILINE):
        # Recorded before `gripper.force_mode` existed: the grip force was a limit.
        scenario.gripper.force_mode = "limit"
    if not re.search(r"^gpd:\n(?:  .*\n)*  fallback_best:", scenario_yaml, re.MULTILINE):
        # Recorded before `gpd.fallback_best` existed: no detection over the threshold
        # was no detection (the fallback became the default later).
        scenario.gpd.fallback_best = False
    return scenario


def recorded_weights(scenario, run_info: dict, condition: str, *, source: str = "run.json"):
    """The scenario with the CNN weights its run loaded. A record written with
    `controller.weights: ""` ran the default of its day; run.json holds that file's sha256
    (`condition_identity`). When it is not today's default, the shipped weights file with
    that sha256 (any `models/*/weights.safetensors`) is named instead, so that the record
    replays as it ran. A record that named its weights (`--weights`, one file or an
    ensemble's) keeps them where the files exist; a named file that does not exist here
    (a path of another machine or working directory) is replaced by the shipped file with
    its recorded sha256. Records without a sha256 (older run.json, no CNN) are returned as
    they are. Raises ValueError (naming `source`, the condition and the sha256) when no
    shipped file has it."""
    from drake_grasp.policies.evaluator import weights_files

    if scenario.policy not in CNN_POLICIES:
        return scenario
    shas = next((c.get("weights_sha256") for c in run_info.get("conditions", [])
                 if c.get("name") == condition), None)
    if not shas:
        return scenario
    named = scenario.controller.weights
    files = weights_files(named)
    shas = shas.split(",")
    if named:
        if all(Path(f).is_file() for f in files) or len(shas) != len(files):
            return scenario
        resolved = [f if Path(f).is_file() else str(_shipped_weights(sha, source, condition, f))
                    for f, sha in zip(files, shas)]
        weights = ",".join(resolved)
    else:
        if shas[0] == file_sha256(files[0]):
            return scenario
        weights = str(_shipped_weights(shas[0], source, condition, None))
    return dataclasses.replace(
        scenario, controller=dataclasses.replace(scenario.controller, weights=weights))


def _shipped_weights(sha: str, source: str, condition: str, missing: str | None) -> Path:
    """The shipped `models/*/weights.safetensors` whose sha256 is `sha` (for
    `recorded_weights`); ValueError naming what was looked for when none is."""
    from drake_grasp.core.assets import (REPOSITORY_WEIGHTS_SHA256, models_dir,
                                         not_installed_message)

    for f in sorted(models_dir().glob("*/weights.safetensors")):
        if file_sha256(f) == sha:
            return f
    in_repository = [net for net, h in REPOSITORY_WEIGHTS_SHA256.items() if h == sha]
    if in_repository:
        # A net the repository's models/ holds and the wheel does not carry.
        raise ValueError(f"{source}: condition {condition!r} ran the net with weights sha256 "
                         f"{sha}: " + not_installed_message(
                             f"{in_repository[0]}/weights.safetensors",
                             hint="replay from a checkout of the repository, or copy that "
                                  f"folder to {models_dir() / in_repository[0]}"))
    if missing is None:
        raise ValueError(f"{source}: condition {condition!r} ran the default CNN of its day "
                         f"(weights sha256 {sha}), which no shipped "
                         "models/*/weights.safetensors is; replay it with the package that "
                         "recorded it")
    raise ValueError(f"{source}: condition {condition!r} ran {missing} (weights sha256 "
                     f"{sha}), which does not exist here and is no shipped "
                     "models/*/weights.safetensors; put the file at that path to replay it")


def recorded_pile(path: str | Path) -> tuple:
    """(record, scenario, scene) of a clutter attempt: its trial record (the JSON file, as
    a dict; once its folder is packed, the path still names the trial: `records.record_at`
    reads its row of `RESULTS/trials.parquet`), its scenario and the pile it began on
    (`extra.scene`); what the analysis scripts replay an attempt from. The scenario names
    the weights the attempt ran (`recorded_weights`, from the run.json of the record's
    results folder, `RESULTS/trials/RECORD.json`, when there is one).

    Raises:
        ValueError: The record holds no pile (the message names the file).
    """
    from drake_grasp.evaluation.records import RUN_INFO_FILE, read_run_info, record_at
    from drake_grasp.world.scene import SceneSpec

    rec = json.loads(Path(path).read_text()) if Path(path).is_file() else \
        record_at(path).to_dict()
    if not (rec.get("extra") or {}).get("scene"):
        raise ValueError(f"{path}: no extra.scene (expected a clutter attempt's record)")
    scenario = recorded_scenario(rec["scenario_yaml"])
    run_json = Path(path).parent.parent / RUN_INFO_FILE
    if run_json.is_file():
        scenario = recorded_weights(scenario, read_run_info(run_json.parent), rec["condition"],
                                    source=str(run_json))
    return rec, scenario, SceneSpec.from_dict(rec["extra"]["scene"])


# Measured in analysis/results/machine-repro/ (README *Reproducibility*).
_ACROSS_MACHINES = ("a replay is bit for bit only on a machine like the recording one; across "
                    "machines isolation trials kept every outcome, clutter attempts did not "
                    "(their poured piles settle apart)")


def machine_note(run_info: dict) -> str | None:
    """What a replay on this machine can promise for a run folder's records: None when one
    of its evaluate sessions ran on a machine like this one (`provenance.machine`: the same
    CPU and package versions), else a one-line note naming the recorded machines (or
    saying that none was recorded: folders written before sessions carried one)."""
    here = machine()
    seen = [s["machine"] for s in run_info.get("sessions") or []
            if isinstance(s, dict) and isinstance(s.get("machine"), dict)]
    key = ("cpu", "packages")
    if any(all(m.get(k) == here[k] for k in key) for m in seen):
        return None
    if not seen:
        return ("the run folder does not say which machine made its records (written before "
                f"run.json's sessions carried one): {_ACROSS_MACHINES}")
    named = "; ".join(sorted({f"{m.get('cpu')} with {m.get('packages')}" for m in seen}))
    return (f"recorded on {named}; this machine is {here['cpu']} with {here['packages']}: "
            f"{_ACROSS_MACHINES}")


def replay_trial(results_dir: str | Path, *, trial_id: str, out: str | Path | None = None):
    """Re-runs one recorded trial exactly (its resolved scenario, and for clutter attempts
    the pile it started from) and writes its episode files with the replay page."""
    from drake_grasp.evaluation.episode import run_episode
    from drake_grasp.evaluation.records import (RUN_INFO_FILE, find_record, read_run_info,
                                                replay_path)
    from drake_grasp.world.scene import SceneSpec

    results_dir = Path(results_dir)
    rec = find_record(results_dir, trial_id)  # its file, or its row of the folder's table
    if not rec.scenario_yaml:
        raise ValueError(f"{results_dir}: trial {trial_id!r} has no scenario to replay (building "
                         f"it failed: {rec.failure_reason})")
    try:
        scenario = recorded_scenario(rec.scenario_yaml)
    except ValueError as e:
        raise ValueError(f"{results_dir}: trial {trial_id!r} was recorded by drake_grasp "
                         f"{rec.code_version}; {e}. Replay it with that version.") from None
    if (results_dir / RUN_INFO_FILE).is_file():
        scenario = recorded_weights(scenario, read_run_info(results_dir), rec.condition,
                                    source=str(results_dir / RUN_INFO_FILE))
    scene = SceneSpec.from_dict(rec.extra["scene"]) if "scene" in rec.extra else None
    page = replay_path(results_dir, trial_id)
    out = Path(out) if out else page.with_suffix("")
    result = run_episode(scenario, out_dir=out, scenario_name=rec.scenario_name, scene=scene)
    if out == page.with_suffix(""):
        # The report links failed trials to replays/<trial>.html; the episode's other
        # files stay in the folder beside it.
        os.replace(out / "replay.html", page)
    return result, out
