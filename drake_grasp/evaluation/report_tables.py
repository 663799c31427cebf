"""Markdown pieces of the Monte Carlo report (see `drake_grasp.evaluation.report`).

Owns the number formatting and the markdown tables report.md is built from: the
success table next to the paper's numbers, distance, clutter-run, timing and
failure-class tables, the links to replay pages of failed trials, and the fairness
(what each policy senses) and detection tables.
"""

from __future__ import annotations

import os
import statistics
from pathlib import Path

from drake_grasp.policies.plugins import is_policy_spec
from drake_grasp.evaluation.records import (FAILURE_CLASSES, LEGACY_FAILURE_CLASSES, REPLAYS_DIR,
    replay_path)
from drake_grasp.evaluation.report_stats import (PAPER_TABLE1, SIMULATION_ERRORS_NOTE, Results,
    _condition_order, canonical_condition)


# --------------------------------------------------------------------------- markdown pieces

def _pct(x: float | None, digits: int = 1) -> str:
    return "—" if x is None else f"{100 * x:.{digits}f}%"


def _ci(stats: dict) -> str:
    return "—" if not stats.get("ci95") else f"[{_pct(stats['ci95'][0])}, {_pct(stats['ci95'][1])}]"


def _cm(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.2f} cm"


def _md_escape(text: str, limit: int = 160) -> str:
    text = " ".join(str(text).split()).replace("|", "\\|")
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _paper_cell(exp: str, condition: str) -> str:
    row = PAPER_TABLE1.get(exp, {})
    paper = row.get(canonical_condition(condition))
    if paper is None:
        return "—"
    counts = (f" ({paper['successes']}/{paper['attempts']})" if paper.get("attempts") else "")
    return f"{paper['rate_percent']:.1f}%{counts}"


def _success_table(exp: str, policies: dict[str, dict]) -> list[str]:
    rows = [(c, s) for c, s in policies.items() if not s["distance_only"]]
    if not rows:
        return ["No grasping conditions (distance-only trials)."]
    paper_row = PAPER_TABLE1.get(exp)
    head = "| condition | successes / attempts | rate | Wilson 95% CI |"
    sep = "|---|---|---|---|"
    if paper_row:
        head += f" paper (Table 1, {paper_row['row']}) |"
        sep += "---|"
    head += " simulation errors (not attempts) |"
    sep += "---|"
    lines = [head, sep]
    for c, s in rows:
        line = f"| {c} | {s['successes']} / {s['n']} | {_pct(s['success_rate'])} | {_ci(s)} |"
        if paper_row:
            line += f" {_paper_cell(exp, c)} |"
        line += f" {s['simulation_errors']} |"
        lines.append(line)
    lines += ["", SIMULATION_ERRORS_NOTE]
    if paper_row:
        notes = [f"{c.upper()}: {p['note']}" for c in ("ctr", "gpd") if (p := paper_row[c]).get("note")]
        lines += ["", "Paper: real UR5 robot, Table 1 of Viereck et al. 2017"
                  + (f" ({'; '.join(notes)})" if notes else "") + "."]
    return lines


def _distance_table(policies: dict[str, dict]) -> list[str]:
    lines = ["| condition | trials | with distance | mean | median | within 3 cm | simulation errors |",
             "|---|---|---|---|---|---|---|"]
    for c, s in policies.items():
        if s["distance_n"] == 0:
            continue
        lines.append(f"| {c} | {s['trials']} | {s['distance_n']} | {_cm(s['mean_final_distance_m'])} | "
                     f"{_cm(s['median_final_distance_m'])} | {_pct(s['fraction_within_3cm'])} | "
                     f"{s['simulation_errors']} |")
    if len(lines) == 2:
        return ["No trial has a final distance."]
    if any(s["simulation_errors"] for s in policies.values() if s["distance_n"]):
        lines += ["", "Within 3 cm: fraction of the trials that are not simulation errors."]
    return lines


def _clutter_runs_table(exp: str, policies: dict[str, dict]) -> list[str]:
    paper_row = PAPER_TABLE1.get(exp, {})
    lines = ["| condition | runs | attempts | attempts per run (mean, min-max) | "
             "paper: attempts per run | grasped per run (mean) | how the runs ended |",
             "|---|---|---|---|---|---|---|"]
    for c, st in policies.items():
        runs = st.get("clutter_runs")
        if runs is None:
            continue
        per = runs["attempts_per_run"]
        paper = paper_row.get(canonical_condition(c)) or {}
        paper_cell = (f"{paper['attempts'] / 10:.1f} ({paper['attempts']} in 10 runs)"
                      if paper.get("attempts") else "—")
        ends = "; ".join(f"{reason}: {k}" for reason, k in runs["run_ends"].items())
        lines.append(f"| {c} | {runs['runs']} | {runs['attempts']} | {per['mean']:.1f} "
                     f"({per['min']}-{per['max']}) | {paper_cell} | "
                     f"{runs['grasped_per_run_mean']:.1f} | {_md_escape(ends, 400)} |")
    lines += ["", "Attempts exclude simulation errors. A run ends by the rule in "
                  "`montecarlo.clutter_run_status`: 3 failed grasps in a row, no object left "
                  "(or none within +-15 cm of the pile's centre), or a cap of attempts. Paper: "
                  "10 runs of 10 objects per policy (Table 1's attempt counts)."]
    return lines


def _time_table(res: Results, policies: dict[str, dict]) -> list[str]:
    lines = ["| condition | trials | trial wall time, summed | median per trial |",
             "|---|---|---|---|"]
    total = 0.0
    for c, st in policies.items():
        w = st.get("trial_wall_time_s")
        if not w:
            continue
        total += w["sum"]
        lines.append(f"| {c} | {w['n']} | {w['sum'] / 3600:.2f} h | {w['median']:.1f} s |")
    lines += ["", f"Summed over conditions: {total / 3600:.2f} worker-hours (each trial on one "
                  "worker, Diagram building and scene settling included)."]
    sessions = res.run_info.get("sessions") or []
    if sessions:
        wall = sum(float(s.get("wall_s", 0.0)) for s in sessions)
        workers = sorted({s.get("workers") for s in sessions if s.get("workers")})
        lines.append(f"Elapsed: {wall / 3600:.2f} h over {len(sessions)} `evaluate` call(s)"
                     + (f" with {'/'.join(map(str, workers))} worker(s)" if workers else "")
                     + " (the whole folder, on the machine that ran it).")
    else:
        lines.append("Elapsed: not recorded (this folder's run.json predates the record of "
                     "`evaluate` calls' wall times).")
    return lines


def _failure_table(policies: dict[str, dict]) -> list[str]:
    legacy = [k for k in LEGACY_FAILURE_CLASSES
              if any(s["failure_classes"].get(k) for s in policies.values())]
    names = list(FAILURE_CLASSES) + legacy
    lines = ["| condition | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for c, s in policies.items():
        lines.append(f"| {c} | " + " | ".join(str(s["failure_classes"].get(k, 0)) for k in names) + " |")
    if legacy:
        lines += ["", f"{', '.join(legacy)}: classes of records judged by the earlier geometric "
                      "judge (an object sample between the pads)."]
    return lines


def _failed_replay_links(res: Results, policies: dict[str, dict], out_dir: Path,
                         limit: int = 200) -> list[str]:
    failed = [r for r in res.records
              if not r.success and not policies[r.condition]["distance_only"]]
    linked = []
    for r in failed:
        page = replay_path(res.results_dir, r.trial_id)
        if page.is_file():
            rel = Path(os.path.relpath(page, out_dir)).as_posix()
            reason = _md_escape(r.failure_reason or "no reason recorded")
            # Reasons usually start with their class ("missed: ..."); say it once.
            why = reason if reason.lower().startswith(r.failure_class) else f"{r.failure_class}: {reason}"
            linked.append(f"- [{r.trial_id}]({rel}) — {why}")
    lines = linked[:limit]
    if len(linked) > limit:
        lines.append(f"- … and {len(linked) - limit} more in `{REPLAYS_DIR}/`")
    if not failed:
        return ["No failed grasp attempts."]
    if len(linked) < len(failed):
        lines += ([""] if lines else []) + [
            f"{len(failed) - len(linked)} of {len(failed)} failed trials have no replay page "
            f"in `{REPLAYS_DIR}/`."]
    return lines


# --------------------------------------------------------------------------- one experiment

# What each policy senses and knows (the fairness table). Sensor sizes come from the
# trial's own scenario; decision times from the controller's record (`extra`).
POLICY_SENSING = {
    "ctr": ("wrist depth camera (`camera`)", "depth images, gripper state, time",
            "one per control step"),
    "cnn-ctr": ("wrist depth camera (`camera`)", "depth images, gripper state, time",
                "one per control step"),
    "cnn-only": ("wrist depth camera (`camera`)", "one depth image at the start pose", "1"),
    "gpd": ("GPD sensor on the wrist (`gpd`), at a fixed viewpoint",
            "one depth image, the believed camera pose", "1"),
    "gpd-track": ("GPD sensor on the wrist (`gpd`) at a fixed viewpoint, then the wrist "
                  "depth camera (`camera`)", "one GPD image, then wrist depth images, the "
                  "believed camera poses", "1 + one per control step"),
    "gpd-geometric": ("wrist depth camera (`camera`)",
                      "one depth image at the start pose, the believed camera pose", "1"),
    "scripted": ("none", "the object's true pose (privileged: a reference, not a policy)", "0"),
    "init": ("none", "nothing (no motion)", "0"),
}


def _user_policy_sensing(policy: str, recs) -> tuple[str, str, str, tuple]:
    """A user policy's row (`drake_grasp.policies.plugins`): the sensors it declared (the record's
    `extra.policy_inputs`), and what it knows said as that: its images and decision time
    are not measured by the harness."""
    inputs = next((r.extra["policy_inputs"] for r in recs
                   if isinstance(r.extra, dict) and "policy_inputs" in r.extra), None)
    if inputs is None:
        return "unknown (no record says)", f"user policy `{policy}`", "not measured", ()
    cams = [c for c, port in (("camera", "depth_image"), ("gpd", "gpd_depth_image"))
            if port in inputs]
    names = {"camera": "wrist depth camera (`camera`)", "gpd": "GPD sensor on the wrist (`gpd`)"}
    sensor = " and ".join(names[c] for c in cams) or "none"
    return (sensor, f"user policy `{policy}`: {', '.join(inputs) or 'no inputs'}",
            "not measured", tuple(cams))


def _sensor_size(policy: str, scenario_yaml: str, cameras: tuple | None = None) -> str:
    """Resolution and field of view of the sensor a policy uses, from a trial's YAML
    (`cameras`: the scenario keys of a user policy's sensors)."""
    if cameras is None:
        cameras = (() if POLICY_SENSING.get(policy, ("none",))[0] == "none"
                   else ("gpd",) if policy == "gpd" else ("gpd", "camera") if policy == "gpd-track"
                   else ("camera",))
    if not cameras or not scenario_yaml:
        return "-"
    try:
        from pydrake.common.yaml import yaml_load_typed

        from drake_grasp.config.scenario import Scenario

        sc = yaml_load_typed(schema=Scenario, data=scenario_yaml)
    except Exception:  # a record from an older schema: say so rather than guess
        return "unknown (older record)"
    return "; ".join(f"{c.width}x{c.height}, {c.fov_y_deg:g} deg vertical"
                     for c in (getattr(sc, k) for k in cameras))


def fairness_markdown(records) -> list[str]:
    """The fairness table: per condition its policy's sensor and resolution, what it knows, how many
    images it takes, and its decision time (median over trials of the wall time of one
    decision: image evaluation and policy computation, from `extra.decision_time_s` /
    `extra.decisions`; "-" where older records lack it)."""
    by_condition: dict[str, list] = {}
    for r in records:
        by_condition.setdefault(r.condition, []).append(r)
    lines = ["| condition | sensor | resolution | knows | images per attempt | decision time (median) | decisions per attempt (median) |",
             "|---|---|---|---|---|---|---|"]
    for condition, recs in sorted(by_condition.items(), key=lambda kv: _condition_order(kv[0])):
        policy = recs[0].policy
        cameras = None
        if is_policy_spec(policy):
            sensor, knows, images, cameras = _user_policy_sensing(policy, recs)
        else:
            sensor, knows, images = POLICY_SENSING.get(policy, ("?", "?", "?"))
        per = [r.extra["decision_time_s"] / r.extra["decisions"] for r in recs
               if isinstance(r.extra, dict) and r.extra.get("decisions")]
        counts = [r.extra["decisions"] for r in recs
                  if isinstance(r.extra, dict) and "decisions" in r.extra]
        t = f"{1000 * statistics.median(per):.0f} ms" if per else "-"
        n = f"{statistics.median(counts):g}" if counts else "-"
        if cameras is not None:  # a user policy: the harness cannot time its decisions
            t = n = "not measured"
        name = condition if condition == policy else f"{condition} ({policy})"
        lines.append(f"| {name} | {sensor} | {_sensor_size(policy, recs[0].scenario_yaml, cameras)} | "
                     f"{knows} | {images} | {t} | {n} |")
    lines += ["", "The paper's controller loop ran at about 5 Hz (200 ms per decision) on the UR5."]
    return lines


def detection_markdown(records) -> list[str]:
    """For the conditions whose records carry the judge's check of a one-shot detection
    (`extra.gpd_detection`, `episode.detection_check`): how many selected grasps passed
    the labels' ground truth on both, one or none of its 2 surface samplings, and how
    many of each succeeded; then the same by the category of the one object both pads touch.
    [] when no record has it (other policies, older records)."""
    by_condition: dict[str, list] = {}
    by_category: dict[str, dict[str, list]] = {}
    for r in records:
        if r.failure_class == "simulation-error" or not isinstance(r.extra, dict):
            continue
        d = r.extra.get("gpd_detection")
        if isinstance(d, dict) and "ground_truth_passes" in d:
            row = (int(d["ground_truth_passes"]), bool(r.success))
            by_condition.setdefault(r.condition, []).append(row)
            by_category.setdefault(r.condition, {}).setdefault(
                _detection_category(d), []).append(row)
    if not by_condition:
        return []
    lines = ["| condition | detections | a true grasp on both samplings (succeeded) | on one | "
             "on none |", "|---|---|---|---|---|"]
    for condition, rows in sorted(by_condition.items(), key=lambda kv: _condition_order(kv[0])):
        cells = []
        for k in (2, 1, 0):
            hit = [ok for passes, ok in rows if passes == k]
            cells.append(f"{len(hit)} ({sum(hit)})")
        lines.append(f"| {condition} | {len(rows)} | " + " | ".join(cells) + " |")
    lines += ["", "The selected grasp as detected (before kinematic noise), checked by the judge "
              "against the ground truth of the GPD classifier's labels (collision, closing "
              "region, force closure, torque limit) in the scene as it was at the decision; "
              "the policy never sees it.", ""]
    lines += ["By the object both pads touch at the decision (ground truth's surface sampling; "
              "\"no single object\": none, or two different objects):", "",
              "| condition | object category | detections | succeeded | a true grasp on both "
              "samplings |", "|---|---|---|---|---|"]
    for condition, rows in sorted(by_category.items(), key=lambda kv: _condition_order(kv[0])):
        for category, hits in sorted(rows.items()):
            lines.append(f"| {condition} | {category} | {len(hits)} | "
                         f"{sum(ok for _, ok in hits)} | {sum(p == 2 for p, _ in hits)} |")
    return lines


def _detection_category(check: dict) -> str:
    """The category of the one object a detection's pads both touch: as recorded, or for records
    made before `object_category` was, read from a built-in id (`mug_003` -> mug)."""
    from drake_grasp.objects.categories import CATEGORIES, NO_SINGLE_OBJECT

    if check.get("object_category"):
        return str(check["object_category"])
    oid = check.get("object_id")
    if not oid:
        return NO_SINGLE_OBJECT
    head, _, tail = str(oid).rpartition("_")
    return head if head in CATEGORIES and tail.isdigit() else str(oid)
