"""Figures and tables from Monte Carlo results directories (see `drake_grasp.evaluation.records`).

`make_report(dir)` writes, into the results dir (or `out_dir`):

- `summary.json`: per-condition statistics (success rate with Wilson 95% interval,
  final-distance statistics, failure classes), the figures written, the paper's numbers
  that apply, and the target checks;
- `report.md`: a Table-1-style success table next to the paper's numbers, Figure-5-style
  histograms of the final distance to the closest true grasp (3 cm bins), the target check
  of the experiment at hand, sweep curves for "name=value" conditions, failure-class counts
  and links to the replay pages of failed trials;
- the PNG figures the report shows.

`make_combined_report(dirs, out_dir)` does the same over several experiments (the three
Table 1 rows side by side, the Figure 5 panels), to publish reference results.

Conventions: success rates are fractions in summary.json and percentages in report.md.
Simulation errors (trials whose simulation raised: failure_class "simulation-error") are
failures of the simulator, not of the policy under test: they are counted in their own
column (`simulation_errors` in summary.json) and left out of success rates and of the
fraction within 3 cm, i.e. rate = successes / (trials - simulation errors). Every other
trial of a grasping condition counts as an attempt. INIT trials attempt no grasp: their
conditions carry distance statistics only.

This module assembles the reports; the statistics and paper numbers live in
`report_stats`, the markdown tables in `report_tables` and the figures in `report_figures`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import Any, Iterable, Sequence

from drake_grasp.evaluation.report_stats import (BIN_M, CONDITION_LABELS, HIST_MAX_M,
    NOISE_CONDITIONS, PAPER_FIGURE5, PAPER_TABLE1, PERCEPTION_CONDITIONS, TABLE1_EXPERIMENTS,
    Results, _condition_order, _lookup, _target_line, canonical_condition, canonical_experiment,
    check_targets, load_results, summarize)
from drake_grasp.evaluation.report_tables import (_ci, _clutter_runs_table, _distance_table,
    _failed_replay_links, _failure_table, _paper_cell, _pct, _success_table, _time_table,
    detection_markdown, fairness_markdown)
from drake_grasp.evaluation.report_figures import (_condition_distances, _figure5_panels, _sweeps,
    plot_distance_histograms, plot_sweep)
from drake_grasp.core.files import atomic_write_text


def _relpath(path: Path, out_dir: Path) -> str:
    return Path(os.path.relpath(path, out_dir)).as_posix()


def _paper_for(exp: str, policies: dict[str, dict]) -> dict:
    paper: dict[str, Any] = {}
    if exp in PAPER_TABLE1:
        paper["table1"] = PAPER_TABLE1[exp]
    if _figure5_panels(policies, exp) or exp == "sim-distance":
        paper["figure5"] = PAPER_FIGURE5
    return paper


def _write_json(path: Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=1, allow_nan=False) + "\n")


def _experiment_sections(res: Results, policies: dict[str, dict], out_dir: Path, *,
                         prefix: str, level: str = "##",
                         histogram: bool = True) -> tuple[list[str], list[Path], list[dict]]:
    """Markdown sections, figures written and targets of one results dir."""
    exp = canonical_experiment(res.experiment)
    figures: list[Path] = []
    md: list[str] = []

    md += [f"{level} Grasp success (Table 1 style)", ""] + _success_table(exp, policies) + [""]

    md += [f"{level} Final distance to the closest true grasp (Figure 5 style)", ""]
    panels = _figure5_panels(policies, exp) if histogram else []
    if panels:
        path = out_dir / f"{prefix}figure5_distance_histogram.png"
        plot_distance_histograms(
            [(t, [(CONDITION_LABELS.get(canonical_condition(c), c),
                   *_condition_distances(res.records, c)) for c in names])
             for t, names in panels], path)
        figures.append(path)
        md += [f"![final distance histograms]({_relpath(path, out_dir)})", ""]
    md += _distance_table(policies) + [""]
    if "figure5" in _paper_for(exp, policies):
        md += [f"Paper (Figure 5, {PAPER_FIGURE5['note']}): " + "; ".join(PAPER_FIGURE5["claims"]) + ".", ""]

    targets = check_targets(exp, policies)
    md += [f"{level} Target check ({exp})", ""]
    md += [_target_line(t) for t in targets] if targets else ["No targets for this experiment."]
    md += [""]

    sweeps = _sweeps(policies)
    if sweeps:
        md += [f"{level} Sweeps", ""]
        for param, series in sorted(sweeps.items()):
            safe = re.sub(r"[^A-Za-z0-9._-]", "_", param)
            path = out_dir / f"{prefix}sweep_{safe}.png"
            plot_sweep(param, series, path)
            figures.append(path)
            md += [f"![sweep over {param}]({_relpath(path, out_dir)})", ""]

    if any("clutter_runs" in st for st in policies.values()):
        md += [f"{level} Clutter runs: attempts per run", ""] + _clutter_runs_table(exp, policies) + [""]
    md += [f"{level} What each policy senses (fairness)", ""] + fairness_markdown(res.records) + [""]
    detections = detection_markdown(res.records)
    if detections:
        md += [f"{level} GPD's detections against the ground truth", ""] + detections + [""]
    md += [f"{level} Time", ""] + _time_table(res, policies) + [""]
    md += [f"{level} Failure classes", ""] + _failure_table(policies) + [""]
    md += [f"{level} Failed trials with replays", ""] + _failed_replay_links(res, policies, out_dir) + [""]
    return md, figures, targets


def _header(res: Results, out_dir: Path) -> list[str]:
    versions = sorted({r.code_version for r in res.records})
    hashes = sorted({r.config_hash for r in res.records})
    conds = sorted({r.condition for r in res.records}, key=_condition_order)
    errors = sum(1 for r in res.records if r.failure_class == "simulation-error")
    lines = [f"- results dir: `{res.results_dir}`",
             f"- trials: {len(res.records)} in {len(conds)} conditions ({', '.join(conds)})"
             + (f", {errors} of them simulation errors" if errors else ""),
             f"- code version: {', '.join(versions)}; config hashes: {len(hashes)}"]
    if res.selection is not None and len(res.records) < res.selection["records_in_folder"]:
        lines.append(f"- this report covers the trials of one `evaluate` call "
                     f"({len(res.records)} of the {res.selection['records_in_folder']} records "
                     "in the folder); `drake-grasp report DIR` reports them all")
    created = res.run_info.get("created_utc") or res.run_info.get("created")
    if created:
        lines.append(f"- run created: {created}")
    return lines


def make_report(results_dir: str | os.PathLike, *, out_dir: str | os.PathLike | None = None,
                trials: Iterable[str] | None = None) -> dict:
    """Writes `summary.json`, `report.md` and PNG figures for one results dir.

    Args:
        results_dir: A dir laid out as `drake_grasp.evaluation.records` describes.
        out_dir: Where to write (default: the results dir).
        trials: Report only these trial ids (a clutter run's id covers its attempts);
            `evaluate` passes the trials it was asked for. None (`drake-grasp report`):
            every record in the folder.

    Returns:
        The summary (as written to summary.json): {"experiment", "results_dir", "policies":
        {condition: stats}, "figures": [paths relative to out_dir], "paper": {...},
        "targets": [...], "run_info", "selection": None or {"trials": ids asked for,
        "records_in_folder": n}}.

    Raises:
        ValueError: No trial records (the dir is named), none of `trials`, or a corrupt
            record.
    """
    trials = None if trials is None else list(trials)
    res = load_results(results_dir, trials=trials)
    out = Path(out_dir) if out_dir is not None else res.results_dir
    out.mkdir(parents=True, exist_ok=True)
    policies = summarize(res.records)
    exp = canonical_experiment(res.experiment)
    sections, figures, targets = _experiment_sections(res, policies, out, prefix="")
    md = [f"# Results: {res.experiment}", ""] + _header(res, out) + [""] + sections
    summary = {
        "experiment": res.experiment,
        "results_dir": str(res.results_dir),
        "policies": policies,
        "figures": [_relpath(p, out) for p in figures],
        "paper": _paper_for(exp, policies),
        "targets": targets,
        "run_info": res.run_info,
        "selection": res.selection,
    }
    _write_json(out / "summary.json", summary)
    atomic_write_text(out / "report.md", "\n".join(md).rstrip() + "\n")
    return summary


# --------------------------------------------------------------------------- several experiments

def _load_many(results_dirs: Sequence[str | os.PathLike], *,
               one_per_experiment: bool = True) -> list[Results]:
    if not results_dirs:
        raise ValueError("no results dirs given")
    loaded = [load_results(d) for d in results_dirs]
    if not one_per_experiment:
        return loaded
    seen: dict[str, Path] = {}
    for res in loaded:
        exp = canonical_experiment(res.experiment)
        if exp in seen:
            raise ValueError(f"experiment {exp!r} appears in both {seen[exp]} and {res.results_dir}; "
                             "give one results dir per experiment")
        seen[exp] = res.results_dir
    return loaded


def _table1_cell(stats: dict | None) -> tuple[str, str]:
    if stats is None or not stats.get("n"):
        return "—", "—"
    return f"{_pct(stats['success_rate'])} ({stats['successes']}/{stats['n']})", _ci(stats)


def table1_rows(loaded: Sequence[Results]) -> dict[str, dict]:
    """{experiment: {"row", "ctr": {"sim": stats|None, "paper": {...}}, "gpd": ...}} for the
    Table 1 experiments present, in the paper's row order."""
    by_exp = {canonical_experiment(r.experiment): summarize(r.records) for r in loaded}
    rows = {}
    for exp in TABLE1_EXPERIMENTS:
        if exp not in by_exp:
            continue
        policies = by_exp[exp]
        rows[exp] = {"row": PAPER_TABLE1[exp]["row"]}
        for cond in ("ctr", "gpd"):
            hit = _lookup(policies, cond)
            rows[exp][cond] = {"sim": None if hit is None else
                               {k: hit[1][k] for k in ("success_rate", "n", "successes", "ci95")},
                               "paper": PAPER_TABLE1[exp][cond]}
    return rows


def table1_markdown(loaded: Sequence[Results]) -> str:
    """Table 1 with the simulated rates (Wilson 95% CI) beside the paper's robot rates."""
    rows = table1_rows(loaded)
    if not rows:
        names = ", ".join(f"{r.results_dir} ({r.experiment})" for r in loaded)
        raise ValueError(f"no Table 1 experiment ({', '.join(TABLE1_EXPERIMENTS)}) among: {names}")
    lines = ["| scenario | CTR (sim) | CTR 95% CI | CTR (paper) | GPD (sim) | GPD 95% CI | GPD (paper) |",
             "|---|---|---|---|---|---|---|"]
    for exp, row in rows.items():
        cells = []
        for cond in ("ctr", "gpd"):
            rate, ci = _table1_cell(row[cond]["sim"])
            cells += [rate, ci, _paper_cell(exp, cond)]
        lines.append(f"| {row['row']} (`{exp}`) | " + " | ".join(cells) + " |")
    notes = [f"{PAPER_TABLE1[e]['row']}, {c.upper()}: {p['note']}" for e in rows for c in ("ctr", "gpd")
             if (p := PAPER_TABLE1[e][c]).get("note")]
    lines += ["", "Sim: this simulation, every trial of the condition an attempt except simulation "
              "errors (excluded; counted in each experiment's success table). Paper: real UR5 "
              "robot, Table 1 of Viereck et al. 2017 (counts from the text)."]
    lines += [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"


def _figure5_sources(loaded: Sequence[Results]) -> dict[str, tuple[Results, str, dict]]:
    """{canonical condition: (results, condition name, stats)} for the Figure 5 arms, taken
    from the experiments that are not Table 1 rows (those have their own ctr/gpd arms)."""
    found: dict[str, tuple[Results, str, dict]] = {}
    for res in loaded:
        if canonical_experiment(res.experiment) in TABLE1_EXPERIMENTS:
            continue
        policies = summarize(res.records)
        for canon in NOISE_CONDITIONS + PERCEPTION_CONDITIONS:
            hit = _lookup(policies, canon)
            if hit is None or hit[1]["distance_n"] == 0:
                continue
            if canon in found:
                raise ValueError(f"Figure 5 condition {canon!r} is in both {found[canon][0].results_dir} "
                                 f"and {res.results_dir}; give one results dir per condition")
            found[canon] = (res, hit[0], hit[1])
    return found


def plot_figure5(loaded: Sequence[Results], path: str | os.PathLike, *, bin_m: float = BIN_M,
                 max_m: float = HIST_MAX_M) -> Path | None:
    """Figure 5: left panel the kinematic-noise arms, right panel the perception arms
    (whichever are present). Returns the PNG written, None when no arm has distances."""
    found = _figure5_sources(loaded)
    panels = []
    for title, group in (("Kinematic noise (Figure 5 left)", NOISE_CONDITIONS),
                         ("Perception (Figure 5 right)", PERCEPTION_CONDITIONS)):
        series = [(CONDITION_LABELS[c], *_condition_distances(found[c][0].records, found[c][1]))
                  for c in group if c in found]
        if series:
            panels.append((title, series))
    if not panels:
        return None
    return plot_distance_histograms(panels, Path(path), bin_m=bin_m, max_m=max_m)


def _load_selected(entries: Sequence[str | os.PathLike]) -> list[Results]:
    """Results dirs, each whole or, written ``DIR@cond,cond``, only those conditions.

    Raises:
        ValueError: Nothing after ``@``, or a condition named there with no records in
            its dir (the message names the dir and what it holds).
    """
    selections = []
    for entry in entries:
        path, at, names = str(entry).rpartition("@") if "@" in Path(str(entry)).name \
            else (str(entry), "", "")
        wanted = [n.strip() for n in names.split(",") if n.strip()] if at else None
        if at and not wanted:
            raise ValueError(f"{entry}: no condition named after '@' (expected DIR@cond,cond)")
        selections.append((path, wanted))
    loaded = _load_many([p for p, _ in selections], one_per_experiment=False)
    for i, (res, (path, wanted)) in enumerate(zip(loaded, selections)):
        if wanted is None:
            continue
        have = {r.condition for r in res.records}
        missing = [n for n in wanted if n not in have]
        if missing:
            raise ValueError(f"{path}: no records of condition(s) {missing} (it holds "
                             f"{sorted(have)})")
        loaded[i] = dataclasses.replace(res, records=[r for r in res.records
                                                      if r.condition in wanted])
    return loaded


def write_figure5(results_dirs: Sequence[str | os.PathLike], out_path: str | os.PathLike, *,
                  bin_m: float = BIN_M, max_m: float = HIST_MAX_M) -> Path:
    """Figure 5 from sim-distance (and perception) results dirs into `out_path` (PNG).
    Several dirs of one experiment may share the figure (e.g. arms run separately on the
    same seed), each Figure 5 condition from one of them; ``DIR@init,gpd`` takes only
    those conditions from DIR.

    Raises:
        ValueError: No dir holds a Figure 5 arm with final distances (the dirs are named),
            two dirs hold the same condition, or a condition named after ``@`` has no
            records in its dir.
    """
    if not (bin_m > 0 and max_m > bin_m):
        raise ValueError(f"need 0 < bin_m < max_m, got bin_m={bin_m}, max_m={max_m}")
    loaded = _load_selected(results_dirs)
    path = plot_figure5(loaded, out_path, bin_m=bin_m, max_m=max_m)
    if path is None:
        names = ", ".join(str(r.results_dir) for r in loaded)
        raise ValueError(f"no Figure 5 condition ({', '.join(NOISE_CONDITIONS + PERCEPTION_CONDITIONS)}) "
                         f"with final distances in: {names}")
    return path


def write_table1(results_dirs: Sequence[str | os.PathLike], out_path: str | os.PathLike) -> Path:
    """Table 1 (Markdown) from isolation / clutter / clutter-shift results dirs.

    One dir per experiment, or several whose conditions do not overlap, e.g. CTR from one
    run and GPD from another on the same seed: ``DIR@ctr`` takes only those conditions
    from DIR. The table then names each row's sources.

    Raises:
        ValueError: Two dirs give one experiment the same condition (both are named), or
            `_load_selected`'s errors.
    """
    merged: dict[str, Results] = {}
    sources: dict[str, list[str]] = {}
    for res in _load_selected(results_dirs):
        exp = canonical_experiment(res.experiment)
        conds = sorted({r.condition for r in res.records})
        sources.setdefault(exp, []).append(f"{', '.join(conds)} from `{res.results_dir}`")
        if exp not in merged:
            merged[exp] = res
            continue
        both = sorted({r.condition for r in merged[exp].records} & set(conds))
        if both:
            raise ValueError(f"experiment {exp!r}: condition(s) {both} in both "
                             f"{merged[exp].results_dir} and {res.results_dir}; take each "
                             "condition from one dir (DIR@ctr, DIR@gpd)")
        merged[exp] = dataclasses.replace(merged[exp],
                                          records=merged[exp].records + res.records)
    text = "# Table 1: grasp success, CTR vs GPD\n\n" + table1_markdown(list(merged.values()))
    if any(len(v) > 1 for v in sources.values()):
        text += "\nSources:\n" + "".join(f"- {exp}: {'; '.join(v)}\n"
                                          for exp, v in sources.items())
    return atomic_write_text(Path(out_path), text)


def make_combined_report(results_dirs: Sequence[str | os.PathLike], out_dir: str | os.PathLike) -> dict:
    """One `report.md` / `summary.json` over several experiments (one results dir each).

    Shows Table 1 with the three rows side by side (those present), the Figure 5 panels
    from the non-Table-1 experiments, every target check, and each experiment's own
    sections (figures prefixed with the experiment name).

    Args:
        results_dirs: One results dir per experiment.
        out_dir: Where to write.

    Returns:
        The summary: {"experiments": {experiment: {"results_dir", "policies", "targets",
        "figures"}}, "table1": ..., "figures": [...], "paper": {...}, "targets": [...]}.

    Raises:
        ValueError: No dirs, an empty dir, or two dirs of one experiment.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    loaded = _load_many(results_dirs)
    md = ["# Reference results", "",
          f"{len(loaded)} experiments: " + ", ".join(f"`{r.experiment}` ({len(r.records)} trials)"
                                                    for r in loaded), ""]
    figures: list[Path] = []
    all_targets: list[dict] = []
    experiments: dict[str, dict] = {}

    rows = table1_rows(loaded)
    if rows:
        md += ["## Table 1: grasp success, CTR vs GPD", "", table1_markdown(loaded)]
    fig5 = plot_figure5(loaded, out / "figure5.png")
    if fig5 is not None:
        figures.append(fig5)
        md += ["## Figure 5: final distance to the closest true grasp", "",
               f"![Figure 5]({_relpath(fig5, out)})", "",
               f"Paper ({PAPER_FIGURE5['note']}): " + "; ".join(PAPER_FIGURE5["claims"]) + ".", ""]

    sections: list[str] = []
    for res in loaded:
        exp = canonical_experiment(res.experiment)
        policies = summarize(res.records)
        prefix = re.sub(r"[^A-Za-z0-9._-]", "_", exp) + "_"
        # The combined Figure 5 already shows the arms of the non-Table-1 experiments.
        sec, figs, targets = _experiment_sections(res, policies, out, prefix=prefix, level="###",
                                                  histogram=exp in TABLE1_EXPERIMENTS)
        figures += figs
        all_targets += targets
        experiments[res.experiment] = {"results_dir": str(res.results_dir), "policies": policies,
                                       "targets": targets, "figures": [_relpath(p, out) for p in figs],
                                       "run_info": res.run_info}
        sections += [f"## Experiment `{res.experiment}`", ""] + _header(res, out) + [""] + sec

    md += ["## Target check", ""]
    md += [_target_line(t) for t in all_targets] if all_targets else ["No targets apply."]
    md += [""] + sections
    summary = {
        "experiments": experiments,
        "table1": rows,
        "figures": [_relpath(p, out) for p in figures],
        "paper": {"table1": PAPER_TABLE1, "figure5": PAPER_FIGURE5},
        "targets": all_targets,
    }
    _write_json(out / "summary.json", summary)
    atomic_write_text(out / "report.md", "\n".join(md).rstrip() + "\n")
    return summary
