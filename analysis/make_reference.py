"""Today's headline numbers in one place: `analysis/results/reference/`.

Table 1 (isolation, clutter, clutter-shift; CTR and GPD) and Figure 5 (INIT, CTR and GPD
with and without kinematic noise; the CNN's one shot and CNN + CTR) are each taken from the
results folder and condition that `TABLE1` and `FIGURE5` below name (and Table 1 again with
robot-like depth sensing, `TABLE1_SENSOR_NOISE`, beside the noiseless cells), read with
drake_grasp's own loaders (`report_stats.load_results`) and summarised with the report's
statistics (`summarize`, `table1_rows`, `check_targets`, `write_figure5`). It writes:

- `summary.json`: the keys `drake-grasp report` writes for several experiments
  (`experiments`, `table1`, `figures`, `paper`, `targets`), plus `table1_sensor_noise`
  (per cell: the success with sensor noise, the noiseless cell's, the difference and its
  exact test), `figure5` (per arm the
  fraction within 3 cm with its Wilson 95% interval, and the success rate where the arm
  grasps) and `sources` (per folder: the records' code versions, run.json's code version,
  tree, creation time and `evaluate` sessions with their wall times, and the commands that
  made the records); every Table 1 cell and Figure 5 arm names its folder and condition;
- `table1.md` (the report's Table 1, the paper's numbers beside ours), `figure5.png`
  (`report.write_figure5`) and `README.md` (what is there and where each number comes from).

Regenerate (from the repository root)::

    python analysis/make_reference.py

When a default changes, edit `TABLE1`, `TABLE1_SENSOR_NOISE`, `FIGURE5` and `COMMANDS` and
run it again.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Sequence

from drake_grasp.core.files import atomic_write_text
from drake_grasp.evaluation.proportions import mcnemar_exact_p
from drake_grasp.evaluation.report import table1_markdown, table1_rows, write_figure5
from drake_grasp.evaluation.report_stats import (CONDITION_LABELS, PAPER_FIGURE5, PAPER_TABLE1,
    Results, canonical_experiment, check_targets, load_results, summarize)

RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_OUT = RESULTS / "reference"
COMMAND = "python analysis/make_reference.py"

# --------------------------------------------------------------------------- what comes from where
# (folder under analysis/results/, condition). The CNN's arms run the shipped default, the
# net stored in float16 (models/cnn-grid-bn12500-ep3-fp16/), from one code version
# (fp16-default/, a worktree of 1621b9d37): Table 1's CTR on Table 1's seeds, Figure 5's
# CTR with and without kinematic noise, and its right panel (the CNN's one shot, CNN +
# CTR). GPD (with its fallback) and INIT do not use the CNN: Table 1's GPD on Table 1's
# seeds with the package after the layout refactor (layout-2026-12-07/), Figure 5's INIT
# and GPD arms from the run that made the left panel at one code version
# (figure5-2026-12-07/, 4e97cd8a1), on the same trials as fp16-default/sim-distance; the
# two commits run INIT and GPD identically (fp16-default/figure5-same-code-check/).
TABLE1 = {
    "isolation": {"ctr": ("fp16-default/isolation", "ctr"),
                  "gpd": ("layout-2026-12-07/isolation", "gpd")},
    "clutter": {"ctr": ("fp16-default/clutter", "ctr"),
                "gpd": ("layout-2026-12-07/clutter-gpd", "gpd")},
    "clutter-shift": {"ctr": ("fp16-default/clutter-shift", "ctr"),
                      "gpd": ("layout-2026-12-07/clutter-shift", "gpd")},
}
FIGURE5 = {
    "init": ("figure5-2026-12-07/sim-distance", "init"),
    "ctr": ("fp16-default/sim-distance", "ctr"),
    "ctr_noise": ("fp16-default/sim-distance", "ctr_noise"),
    "gpd": ("figure5-2026-12-07/sim-distance", "gpd"),
    "gpd_noise": ("figure5-2026-12-07/sim-distance", "gpd_noise"),
    "cnn-only": ("fp16-default/perception", "cnn-only"),
    "cnn-ctr": ("fp16-default/perception", "cnn-ctr"),
}
# Table 1 with robot-like sensing (issue 69 item 3, `table1-sensor-noise/PLAN.md`): the same
# policies on the same seeds with the depth noise model and hole filling on for the wrist
# camera and GPD's sensor; each cell is reported beside its noiseless cell of `TABLE1`.
TABLE1_SENSOR_NOISE = {
    "isolation": {"ctr": ("table1-sensor-noise/isolation", "ctr"),
                  "gpd": ("table1-sensor-noise/isolation", "gpd")},
    "clutter": {"ctr": ("table1-sensor-noise/clutter", "ctr"),
                "gpd": ("table1-sensor-noise/clutter", "gpd")},
    "clutter-shift": {"ctr": ("table1-sensor-noise/clutter-shift", "ctr"),
                      "gpd": ("table1-sensor-noise/clutter-shift", "gpd")},
}
# The commands that made each folder's records, from the folder's (or its parent's)
# README: run.json records no command line. Used only where run.json has none.
_W = "--weights models/cnn-grid-bn12500-ep3/weights.safetensors"
_W16 = "--weights models/cnn-grid-bn12500-ep3-fp16/weights.safetensors"
_FP16 = "(from a worktree of 1621b9d37; README there)"
_NOISY = "'all={depth_noise: {enabled: true}, gpd: {noise: {enabled: true}}}'"
_T1SN = "(from a worktree of 3fe05ecae; PLAN.md there)"
COMMANDS = {
    "fp16-default/isolation": [
        f"drake-grasp evaluate --experiment isolation --trials 120 --seed 11 --conditions ctr {_W16} --workers 2 --out isolation {_FP16}"],
    "fp16-default/clutter": [
        f"drake-grasp evaluate --experiment clutter --trials 10 --seed 16 --conditions ctr {_W16} --workers 2 --out clutter {_FP16}"],
    "fp16-default/clutter-shift": [
        f"drake-grasp evaluate --experiment clutter-shift --trials 10 --seed 8 --conditions ctr {_W16} --workers 2 --out clutter-shift {_FP16}"],
    "fp16-default/sim-distance": [
        f"drake-grasp evaluate --experiment sim-distance --trials 400 --seed 0 --conditions ctr,ctr_noise {_W16} --workers 2 --out sim-distance {_FP16}"],
    "fp16-default/perception": [
        f"drake-grasp evaluate --experiment perception --seed 0 --conditions cnn-only,cnn-ctr {_W16} --workers 2 --out perception {_FP16}"],
    "layout-2026-12-07/isolation": [
        "drake-grasp evaluate --experiment isolation --trials 120 --seed 11 --conditions ctr,gpd --workers 2 --out isolation"],
    "layout-2026-12-07/clutter": [
        "drake-grasp evaluate --experiment clutter --trials 10 --seed 16 --conditions ctr --workers 2 --out clutter"],
    "layout-2026-12-07/clutter-gpd": [
        "drake-grasp evaluate --experiment clutter --trials 10 --seed 16 --conditions gpd --workers 2 --out clutter-gpd"],
    "layout-2026-12-07/clutter-shift": [
        "drake-grasp evaluate --experiment clutter-shift --trials 10 --seed 8 --conditions ctr,gpd --workers 2 --out clutter-shift"],
    "paper-bn12500-ep3/isolation": [
        f"drake-grasp evaluate --experiment isolation --conditions ctr,ctr-sim --trials 120 --seed 11 {_W} --workers 2 --out isolation"],
    "paper-bn12500-ep3/clutter": [
        f"drake-grasp evaluate --experiment clutter --conditions ctr --seed 16 {_W} --workers 2 --out clutter"],
    "paper-bn12500-ep3/clutter-shift": [
        f"drake-grasp evaluate --experiment clutter-shift --conditions ctr --seed 8 {_W} --workers 2 --out clutter-shift"],
    "paper-bn12500-ep3/sim-distance-ctr-seed0": [
        f"drake-grasp evaluate --experiment sim-distance --conditions ctr --trials 400 --seed 0 {_W} --workers 2 --out sim-distance-ctr-seed0"],
    "paper-bn12500-ep3/simdist-noise-400-seed0": [
        f"drake-grasp evaluate --experiment sim-distance --conditions ctr_noise --trials 400 --seed 0 {_W} --workers 2 --out simdist-noise-400-seed0"],
    "paper-bn12500-ep3/perception": [
        f"drake-grasp evaluate --experiment perception --seed 0 {_W} --workers 2 --out perception"],
    "failure-memory/isolation-seed11-gpd-fallback": [
        "drake-grasp evaluate --experiment isolation --conditions gpd --trials 120 --workers 2 --seed 11 --gpd-fallback --out isolation-seed11-gpd-fallback"],
    "failure-memory/clutter-seed16-gpd-fallback": [
        "drake-grasp evaluate --experiment clutter --conditions gpd --workers 2 --seed 16 --gpd-fallback --out clutter-seed16-gpd-fallback"],
    "failure-memory/clutter-shift-seed8-gpd-fallback": [
        "drake-grasp evaluate --experiment clutter-shift --conditions gpd --workers 2 --seed 8 --gpd-fallback --out clutter-shift-seed8-gpd-fallback"],
    "gpd-fallback/sim-distance-gpd-seed0": [
        "drake-grasp evaluate --experiment sim-distance --conditions gpd,gpd_noise --trials 400 --workers 2 --seed 0 --gpd-fallback --out sim-distance-gpd-seed0"],
    "table1-sensor-noise/isolation": [
        f"drake-grasp evaluate --experiment isolation --trials 120 --seed 11 --conditions ctr,gpd --patch {_NOISY} --workers 2 --out isolation {_T1SN}"],
    "table1-sensor-noise/clutter": [
        f"drake-grasp evaluate --experiment clutter --trials 10 --seed 16 --conditions ctr,gpd --patch {_NOISY} --workers 2 --out clutter {_T1SN}"],
    "table1-sensor-noise/clutter-shift": [
        f"drake-grasp evaluate --experiment clutter-shift --trials 10 --seed 8 --conditions ctr,gpd --patch {_NOISY} --workers 2 --out clutter-shift {_T1SN}"],
    "figure5-2026-12-07/sim-distance": [
        "drake-grasp evaluate --experiment sim-distance --trials 400 --seed 0 --workers 2 "
        "--out figure5-2026-12-07/sim-distance (from a worktree of 4e97cd8a1; README there)"],
    "paper-grid/sim-distance": [
        "drake-grasp evaluate --experiment sim-distance --workers 2 --seed 0 --out paper-grid/sim-distance "
        "(begun at 0.1.0+tree.95a84cd6aba7 and resumed from a worktree of 9ab6fd4; README there)"],
}


# --------------------------------------------------------------------------- loading

def _folders() -> list[str]:
    """Every folder the tables name, in table order, each once."""
    seen: dict[str, None] = {}
    for table in (TABLE1, TABLE1_SENSOR_NOISE):
        for row in table.values():
            for folder, _ in row.values():
                seen[folder] = None
    for folder, _ in FIGURE5.values():
        seen[folder] = None
    return list(seen)


def _load(results: Path) -> dict[str, Results]:
    """{folder: its Results, labelled with the folder's path under analysis/results/}."""
    loaded = {}
    for folder in _folders():
        res = load_results(results / folder)
        loaded[folder] = dataclasses.replace(res, results_dir=Path(folder))
    return loaded


def _only(res: Results, conditions: Sequence[str]) -> Results:
    have = {r.condition for r in res.records}
    missing = [c for c in conditions if c not in have]
    if missing:
        raise ValueError(f"{res.results_dir}: no records of condition(s) {missing} "
                         f"(it holds {sorted(have)})")
    return dataclasses.replace(res, records=[r for r in res.records if r.condition in conditions])


def _merged(loaded: dict[str, Results], sources: Sequence[tuple[str, str]]) -> Results:
    """One Results of the named (folder, condition) pairs (the first folder's run info)."""
    parts = [_only(loaded[folder], [cond]) for folder, cond in sources]
    return dataclasses.replace(parts[0], records=[r for p in parts for r in p.records])


# --------------------------------------------------------------------------- blocks

def _source(folder: str, condition: str) -> dict:
    return {"folder": folder, "condition": condition}


def _provenance(res: Results) -> dict:
    """What a folder's run.json says of the records' making, and the commands."""
    info = res.run_info
    commands = info.get("commands") or info.get("command") or info.get("argv")
    sessions = [{k: s.get(k) for k in ("started_utc", "wall_s", "workers", "records_added")}
                for s in info.get("sessions") or []]
    return {
        "experiment": res.experiment,
        "seed": info.get("seed"),
        "records": len(res.records),
        "record_code_versions": sorted({r.code_version for r in res.records}),
        "run_code_version": info.get("code_version"),
        "run_code_tree": info.get("code_tree"),
        "created_utc": info.get("created_utc") or info.get("created"),
        "sessions": sessions,
        "sessions_wall_s": round(sum(float(s["wall_s"] or 0.0) for s in sessions), 3),
        "sessions_records_added": sum(int(s["records_added"] or 0) for s in sessions),
        "commands": commands if commands else COMMANDS.get(str(res.results_dir), []),
        "commands_from": "run.json" if commands else f"{res.results_dir.parent}/README.md",
    }


def table1_block(loaded: dict[str, Results]) -> dict:
    """The report's Table 1 rows, each cell with its source folder and condition."""
    merged = [dataclasses.replace(_merged(loaded, list(row.values())),
                                  experiment=exp) for exp, row in TABLE1.items()]
    rows = table1_rows(merged)
    for exp, row in rows.items():
        for cond, (folder, name) in TABLE1[exp].items():
            stats = summarize(_only(loaded[folder], [name]).records)[name]
            row[cond]["source"] = _source(folder, name)
            row[cond]["code_versions"] = stats["code_versions"]
            row[cond]["trial_wall_time_s"] = stats["trial_wall_time_s"]
    return rows


def _paired_mcnemar(noisy: Results, noiseless: Results) -> dict:
    """Exact McNemar test of two runs of the same trials, paired by trial id."""
    a = {r.trial_id.split("/", 1)[-1]: bool(r.success) for r in noisy.records}
    b = {r.trial_id.split("/", 1)[-1]: bool(r.success) for r in noiseless.records}
    ids = sorted(set(a) & set(b))
    only_noisy = sum(a[i] and not b[i] for i in ids)
    only_noiseless = sum(b[i] and not a[i] for i in ids)
    return {"test": "exact McNemar, paired by trial", "paired_trials": len(ids),
            "only_with_noise": only_noisy, "only_without_noise": only_noiseless,
            "p": mcnemar_exact_p(only_noisy, only_noiseless)}


def _fisher(noisy: dict, noiseless: dict) -> dict:
    """Fisher's exact test (two-sided) of two success proportions."""
    from scipy.stats import fisher_exact

    table = [[noisy["successes"], noisy["n"] - noisy["successes"]],
             [noiseless["successes"], noiseless["n"] - noiseless["successes"]]]
    return {"test": "Fisher's exact, two-sided", "p": float(fisher_exact(table)[1])}


def table1_sensor_noise_block(loaded: dict[str, Results], table1: dict) -> dict:
    """Per Table 1 cell: the success with sensor noise (`TABLE1_SENSOR_NOISE`), the
    noiseless cell's (`table1`), their difference and its test (isolation: the same
    trials, paired; clutter: new attempts on the same piles, unpaired)."""
    rows: dict = {}
    for exp, row in TABLE1_SENSOR_NOISE.items():
        rows[exp] = {}
        for cond, (folder, name) in row.items():
            noisy = _only(loaded[folder], [name])
            stats = summarize(noisy.records)[name]
            sim = {k: stats[k] for k in ("successes", "n", "success_rate", "ci95")}
            clean = table1[exp][cond]["sim"]
            clean_folder, clean_name = TABLE1[exp][cond]
            test = (_paired_mcnemar(noisy, _only(loaded[clean_folder], [clean_name]))
                    if exp == "isolation" else _fisher(sim, clean))
            rows[exp][cond] = {
                "sim": sim, "noiseless": {k: clean[k] for k in ("successes", "n", "success_rate")},
                "difference_points": round(100 * (sim["success_rate"] - clean["success_rate"]), 2),
                "comparison": test, "source": _source(folder, name),
                "noiseless_source": _source(clean_folder, clean_name),
                "code_versions": stats["code_versions"],
                "trial_wall_time_s": stats["trial_wall_time_s"]}
    return rows


def figure5_block(loaded: dict[str, Results]) -> dict:
    """Per arm: the fraction of trials within 3 cm (the report's `fraction_within_3cm`
    over the trials that are not simulation errors) with its Wilson 95% interval, the
    median final distance, and the grasp success where the arm grasps."""
    arms = {}
    for arm, (folder, cond) in FIGURE5.items():
        stats = summarize(_only(loaded[folder], [cond]).records)[cond]
        attempts = stats["trials"] - stats["simulation_errors"]
        frac = stats["fraction_within_3cm"]
        arms[arm] = {
            "label": CONDITION_LABELS[arm],
            "source": _source(folder, cond),
            "trials": stats["trials"],
            "simulation_errors": stats["simulation_errors"],
            "within_3cm_rate": frac,
            "within_3cm_count": None if frac is None else round(frac * attempts),
            "within_3cm_n": attempts,
            "within_3cm_ci95": stats["within_3cm_ci95"],
            "median_final_distance_m": stats["median_final_distance_m"],
            **{k: stats[k] for k in ("success_rate", "n", "successes", "ci95")},
            "code_versions": stats["code_versions"],
            "trial_wall_time_s": stats["trial_wall_time_s"],
        }
    return arms


def experiments_block(loaded: dict[str, Results]) -> tuple[dict, list[dict]]:
    """`drake-grasp report`'s per-experiment entries over the selected conditions, and
    every target check."""
    groups: dict[str, list[tuple[str, str]]] = {}
    for exp, row in TABLE1.items():
        groups[exp] = list(row.values())
    for folder, cond in FIGURE5.values():
        groups.setdefault(canonical_experiment(loaded[folder].experiment), []).append((folder, cond))
    experiments, targets = {}, []
    for exp, sources in groups.items():
        policies = summarize(_merged(loaded, sources).records)
        checks = check_targets(exp, policies)
        targets += checks
        experiments[exp] = {"results_dirs": [f"{f}@{c}" for f, c in sources],
                            "policies": policies, "targets": checks}
    return experiments, targets


def make_summary(results: Path = RESULTS) -> tuple[dict, dict[str, Results]]:
    """The summary.json content (no file written) and the loaded folders."""
    loaded = _load(results)
    experiments, targets = experiments_block(loaded)
    table1 = table1_block(loaded)
    summary = {
        "generated_by": COMMAND,
        "experiments": experiments,
        "table1": table1,
        "table1_sensor_noise": table1_sensor_noise_block(loaded, table1),
        "figure5": figure5_block(loaded),
        "figures": ["figure5.png"],
        "paper": {"table1": PAPER_TABLE1, "figure5": PAPER_FIGURE5},
        "targets": targets,
        "sources": {folder: _provenance(res) for folder, res in loaded.items()},
    }
    return summary, loaded


# --------------------------------------------------------------------------- writing

def _pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.1f}%"


def _ci(ci: list[float] | None) -> str:
    return "—" if not ci else f"[{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def _table1_text(loaded: dict[str, Results]) -> str:
    merged = [dataclasses.replace(_merged(loaded, list(row.values())), experiment=exp)
              for exp, row in TABLE1.items()]
    lines = ["# Table 1: grasp success, CTR vs GPD", "", table1_markdown(merged).rstrip(), "",
             "Sources (under `analysis/results/`):"]
    for exp, row in TABLE1.items():
        lines.append(f"- {exp}: " + "; ".join(f"{c} from `{f}` (condition `{n}`)"
                                               for c, (f, n) in row.items()))
    lines += ["", f"Written by `{COMMAND}`."]
    return "\n".join(lines) + "\n"


def _readme_text(summary: dict) -> str:
    lines = ["# Reference results: today's headline numbers", "",
             "Table 1 and Figure 5 with the shipped default CNN (`models/cnn-grid-bn12500-ep3-fp16/`, "
             "the 3-epoch grid head stored in float16) "
             "and GPD with its fallback, each number taken from the trial records of the "
             "folder named beside it (under `analysis/results/`). Every file here is written "
             "by one command, from the repository root:", "", f"    {COMMAND}", "",
             "- `summary.json`: `drake-grasp report`'s keys (`experiments`, `table1`, `figures`, "
             "`paper`, `targets`) over the conditions below, plus `figure5` (per arm) and "
             "`sources` (per folder: code versions, `evaluate` sessions and wall times, the "
             "commands that made the records);",
             "- `table1.md`: Table 1 as the report writes it, the paper's numbers beside ours;",
             "- `figure5.png`: Figure 5 (left: INIT, CTR, GPD with and without kinematic noise; "
             "right: the CNN's one shot and CNN + CTR);", "- this README.", "",
             "Which folder and condition each number comes from is the table at the top of "
             "`analysis/make_reference.py`; change it there when a default changes. The other "
             "folders of `analysis/results/` are dated studies (`../README.md`).", "",
             "## Table 1", "", "| experiment | policy | success | 95% CI | paper | from |",
             "|---|---|---|---|---|---|"]
    for exp, row in summary["table1"].items():
        for cond in ("ctr", "gpd"):
            sim, paper, src = row[cond]["sim"], row[cond]["paper"], row[cond]["source"]
            lines.append(f"| {exp} | {cond.upper()} | {_pct(sim['success_rate'])} "
                         f"({sim['successes']}/{sim['n']}) | {_ci(sim['ci95'])} | "
                         f"{paper['rate_percent']:.1f}% | `{src['folder']}` `{src['condition']}` |")
    lines += ["", "## Table 1 with sensor noise", "",
              "The same policies and seeds with the depth noise model and hole filling on for "
              "the wrist camera and GPD's sensor (`table1-sensor-noise/PLAN.md`). Isolation "
              "pairs each trial with its noiseless twin (exact McNemar); clutter compares "
              "attempts (Fisher's exact test).", "",
              "| experiment | policy | with noise | 95% CI | without | difference | p | from |",
              "|---|---|---|---|---|---|---|---|"]
    for exp, row in summary["table1_sensor_noise"].items():
        for cond in ("ctr", "gpd"):
            c = row[cond]
            sim, clean = c["sim"], c["noiseless"]
            lines.append(f"| {exp} | {cond.upper()} | {_pct(sim['success_rate'])} "
                         f"({sim['successes']}/{sim['n']}) | {_ci(sim['ci95'])} | "
                         f"{_pct(clean['success_rate'])} ({clean['successes']}/{clean['n']}) | "
                         f"{c['difference_points']:+.1f} points | {c['comparison']['p']:.2f} | "
                         f"`{c['source']['folder']}` `{c['source']['condition']}` |")
    lines += ["", "## Figure 5", "",
              "| arm | within 3 cm | 95% CI | grasped | median final distance | from |",
              "|---|---|---|---|---|---|"]
    for arm in summary["figure5"].values():
        grasped = "—" if arm["n"] is None else f"{arm['successes']}/{arm['n']}"
        median = arm["median_final_distance_m"]
        lines.append(f"| {arm['label']} | {_pct(arm['within_3cm_rate'])} "
                     f"({arm['within_3cm_count']}/{arm['within_3cm_n']}) | "
                     f"{_ci(arm['within_3cm_ci95'])} | {grasped} | "
                     f"{'—' if median is None else f'{1000 * median:.1f} mm'} | "
                     f"`{arm['source']['folder']}` `{arm['source']['condition']}` |")
    lines += ["", "## The folders", "",
              "| folder | records | code version | made | `evaluate` sessions: wall time (records added) |",
              "|---|---|---|---|---|"]
    for folder, p in summary["sources"].items():
        lines.append(f"| `{folder}` | {p['records']} | {', '.join(p['record_code_versions'])} | "
                     f"{p['created_utc']} | {p['sessions_wall_s'] / 60:.1f} min "
                     f"({p['sessions_records_added']}) |")
    lines += ["", "Records: every condition in the folder (the tables above use the named ones). "
              "Wall times are the `evaluate` sessions run.json records (a folder resumed from "
              "an earlier package lists only the sessions after the resume), 2 workers on the "
              "2-core machines each folder's README names; the commands that made each folder "
              "are in `summary.json` (`sources`)."]
    return "\n".join(lines) + "\n"


def write_reference(out_dir: Path, *, results: Path = RESULTS) -> dict:
    """Writes summary.json, table1.md, figure5.png and README.md into `out_dir`.

    Returns:
        The summary written.

    Raises:
        ValueError: A folder or condition the tables name has no records.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    summary, loaded = make_summary(results)
    by_folder: dict[str, list[str]] = {}
    for folder, cond in FIGURE5.values():
        by_folder.setdefault(folder, []).append(cond)
    write_figure5([f"{results / f}@{','.join(c)}" for f, c in by_folder.items()],
                  out_dir / "figure5.png")
    atomic_write_text(out_dir / "table1.md", _table1_text(loaded))
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=1, allow_nan=False) + "\n")
    atomic_write_text(out_dir / "README.md", _readme_text(summary))
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Writes analysis/results/reference/ (summary.json, table1.md, figure5.png, "
                    "README.md): Table 1 and Figure 5 from the results folders and conditions "
                    "named in this script's TABLE1 and FIGURE5 tables.")
    parser.add_argument("--out", default=str(DEFAULT_OUT),
                        help="folder to write (default: analysis/results/reference)")
    parser.add_argument("--results", default=str(RESULTS),
                        help="the folder the tables' folders are under (default: analysis/results)")
    args = parser.parse_args(argv)
    try:
        summary = write_reference(Path(args.out), results=Path(args.results))
    except ValueError as e:
        parser.exit(2, f"make_reference: error: {e}\n")
    for key in ("table1", "table1_sensor_noise"):
        for exp, row in summary[key].items():
            print(f"{key} {exp}: " + ", ".join(
                f"{c} {row[c]['sim']['successes']}/{row[c]['sim']['n']}" for c in ("ctr", "gpd")))
    print("figure5 within 3 cm: " + ", ".join(f"{a} {v['within_3cm_count']}/{v['within_3cm_n']}"
                                               for a, v in summary["figure5"].items()))
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
