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
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import re
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

from drake_grasp.policies.plugins import is_policy_spec
from drake_grasp.evaluation.records import (FAILURE_CLASSES, LEGACY_FAILURE_CLASSES, REPLAYS_DIR,
    TrialRecord, load_records, read_run_info, replay_path, wilson_interval)
from drake_grasp.core.files import atomic_write_bytes, atomic_write_text

BIN_M = 0.03  # the paper's Figure 5 bin size
HIST_MAX_M = 0.30  # last regular bin edge; farther trials go to an overflow bin

# Figure 5 (left): kinematic noise comparison; (right): perception, one-shot vs closed loop.
NOISE_CONDITIONS = ("init", "ctr", "ctr_noise", "gpd", "gpd_noise")
PERCEPTION_CONDITIONS = ("cnn-only", "cnn-ctr")
CONDITION_LABELS = {
    "init": "INIT", "ctr": "CTR no noise", "ctr_noise": "CTR with noise",
    "gpd": "GPD no noise", "gpd_noise": "GPD with noise",
    "cnn-only": "CNN only", "cnn-ctr": "CNN+CTR",
}
# Spellings other modules or people may use for the same arms.
_CONDITION_ALIASES = {
    "ctr_no_noise": "ctr", "ctr-no-noise": "ctr", "ctr-noise": "ctr_noise",
    "ctr_with_noise": "ctr_noise", "gpd_no_noise": "gpd", "gpd-no-noise": "gpd",
    "gpd-noise": "gpd_noise", "gpd_with_noise": "gpd_noise", "cnn_only": "cnn-only",
    "cnn_ctr": "cnn-ctr", "cnn+ctr": "cnn-ctr",
}
DISTANCE_ONLY_CONDITIONS = ("init",)

TABLE1_EXPERIMENTS = ("isolation", "clutter", "clutter-shift")
_EXPERIMENT_ALIASES = {
    "clutter-rotations": "clutter-shift", "clutter-with-rotations": "clutter-shift",
    "shift": "clutter-shift", "clutter-shifted": "clutter-shift",
    "figure5": "sim-distance", "fig5": "sim-distance", "simdistance": "sim-distance",
}

# Table 1 of the paper (real UR5). Counts are the ones stated in the text; where the printed
# rate differs from the stated counts, both are kept and the note says so.
PAPER_TABLE1: dict[str, dict] = {
    "isolation": {
        "row": "Objects in isolation",
        "ctr": {"rate_percent": 97.5, "successes": 39, "attempts": 40},
        "gpd": {"rate_percent": 97.5, "successes": None, "attempts": None,
                "note": "the text says only that GPD achieves the same rate"},
    },
    "clutter": {
        "row": "Clutter",
        "ctr": {"rate_percent": 88.9, "successes": 66, "attempts": 74,
                "note": "the text's 8 failures of 74 give 89.2%; Table 1 prints 88.9%"},
        "gpd": {"rate_percent": 94.8, "successes": 91, "attempts": 96},
    },
    "clutter-shift": {
        "row": "Clutter with rotations (pile shifted once per trial)",
        "ctr": {"rate_percent": 77.3, "successes": 58, "attempts": 75},
        "gpd": {"rate_percent": 22.5, "successes": 11, "attempts": 49,
                "note": "the text's 38 failures of 49 give 22.4%; Table 1 prints 22.5%"},
    },
}
PAPER_FIGURE5 = {
    "source": "Viereck et al. 2017, Figure 5 (400 simulated trials per scenario, 3 cm bins)",
    "claims": [
        "without kinematic noise CTR and GPD reach a grasp about equally well",
        "with kinematic noise (0.4 w |delta|, w ~ N(0, 1) per step) CTR compensates, GPD does not",
        "CNN+CTR ends closer to a true grasp than the one-shot CNN prediction alone",
    ],
    "note": "the paper prints no numbers for Figure 5; compare shapes, not values",
}

# Targets from the project's issue, per experiment.
_TOL = 1e-9

SIMULATION_ERRORS_NOTE = (
    "Simulation errors (trials whose simulation raised an exception) are not attempts: they "
    "are counted in their own column and excluded from success rates and from the fraction "
    "within 3 cm, i.e. rate = successes / (trials - simulation errors).")


@dataclass
class Results:
    """One results directory, loaded."""

    results_dir: Path
    experiment: str
    run_info: dict
    records: list[TrialRecord]
    # {"trials": ids asked for, "records_in_folder": n} when only some records are loaded.
    selection: dict | None = None


# --------------------------------------------------------------------------- loading

def canonical_experiment(name: str) -> str:
    """Lower-case, '-'-separated experiment name with known aliases resolved."""
    key = re.sub(r"[\s_]+", "-", str(name).strip().lower())
    return _EXPERIMENT_ALIASES.get(key, key)


def canonical_condition(name: str) -> str:
    """Condition name with known aliases resolved ("cnn_only" -> "cnn-only")."""
    key = str(name).strip().lower()
    return _CONDITION_ALIASES.get(key, key)


def select_records(records: Sequence[TrialRecord], trials: Iterable[str]) -> list[TrialRecord]:
    """The records of the given trial ids; a clutter run's id ("clutter/ctr/0003") selects
    its attempts ("clutter/ctr/0003/attempt00", ...)."""
    wanted = set(trials)
    out = []
    for r in records:
        parts = r.trial_id.split("/")
        if any("/".join(parts[:k]) in wanted for k in range(1, len(parts) + 1)):
            out.append(r)
    return out


def load_results(results_dir: str | os.PathLike, *,
                 trials: Iterable[str] | None = None) -> Results:
    """Loads the records and run info of a results dir.

    The experiment name comes from run.json's "experiment", else from the records.

    Args:
        results_dir: The results dir.
        trials: Only these trial ids (see `select_records`); None for every record.

    Raises:
        ValueError: The dir has no trial records (or none of those asked for; named in the
            message), or a record is corrupt.
    """
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise ValueError(f"{results_dir}: results dir does not exist")
    records = load_records(results_dir)
    if not records:
        raise ValueError(f"{results_dir}: no trial records in {results_dir / 'trials'} "
                         "(nothing to report; has the run started?)")
    if trials is not None:
        in_folder = len(records)
        records = select_records(records, trials)
        if not records:
            raise ValueError(f"{results_dir}: none of its {in_folder} trial records is one of "
                             "the trials asked for")
    try:
        run_info = read_run_info(results_dir)
    except FileNotFoundError:
        run_info = {}
    experiment = run_info.get("experiment")
    if not isinstance(experiment, str) or not experiment:
        experiment = "+".join(sorted({r.experiment for r in records}))
    selection = None if trials is None else {"trials": len(set(trials)),
                                             "records_in_folder": in_folder}
    return Results(results_dir, experiment, run_info, records, selection)


# --------------------------------------------------------------------------- statistics

def _is_distance_only(condition: str, records: Sequence[TrialRecord]) -> bool:
    if canonical_condition(condition) in DISTANCE_ONLY_CONDITIONS:
        return True
    return all(r.policy.lower() == "init"
               or (r.failure_reason or "").lower().startswith("init")
               or r.extra.get("distance_only") is True for r in records)


def distance_histogram(distances: Iterable[float], *, bin_m: float = BIN_M,
                       max_m: float = HIST_MAX_M) -> tuple[list[float], list[int]]:
    """Counts per bin [k*bin_m, (k+1)*bin_m) up to max_m, plus one overflow bin (>= max_m).

    Returns:
        (bin edges [m] including max_m, counts with len(edges) entries: the last one is the
        overflow bin).
    """
    nbins = int(round(max_m / bin_m))
    edges = [round(k * bin_m, 10) for k in range(nbins + 1)]
    counts = [0] * (nbins + 1)
    for d in distances:
        # floor division with a tiny tolerance so 0.03 - 1e-16 stays in bin 0 and 0.03 goes to 1
        k = int(math.floor(d / bin_m + 1e-9)) if d >= 0 else 0
        counts[min(k, nbins)] += 1
    return edges, counts


def summarize_condition(condition: str, records: Sequence[TrialRecord]) -> dict:
    """Statistics of one condition (see the module docstring for the conventions).

    `trials` counts every record; `simulation_errors` those whose simulation raised;
    `n` (the attempts) = trials - simulation_errors, and `success_rate` = successes / n
    (None when n is 0). `fraction_within_3cm` is over the same n trials: a trial without a
    measured distance that is not a simulation error counts as not within 3 cm. It is None
    when no trial has a distance.
    """
    distance_only = _is_distance_only(condition, records)
    dists = [r.final_distance_m for r in records if r.final_distance_m is not None]
    classes = {c: 0 for c in FAILURE_CLASSES}
    for r in records:  # records of the geometric judge add their legacy classes
        classes[r.failure_class] = classes.get(r.failure_class, 0) + 1
    errors = classes["simulation-error"]
    attempts = len(records) - errors
    out: dict[str, Any] = {
        "policies_run": sorted({r.policy for r in records}),
        "trials": len(records),
        "simulation_errors": errors,
        "distance_only": distance_only,
        "success_rate": None, "n": None, "successes": None, "ci95": None,
    }
    if not distance_only:
        k = sum(1 for r in records if r.success)
        lo, hi = wilson_interval(k, attempts)
        out.update(success_rate=k / attempts if attempts else None, n=attempts, successes=k,
                   ci95=[lo, hi] if attempts else None)
    edges, counts = distance_histogram(dists)
    within = sum(1 for d in dists if d < BIN_M - _TOL)
    out.update({
        "distance_n": len(dists),
        "mean_final_distance_m": statistics.fmean(dists) if dists else None,
        "median_final_distance_m": statistics.median(dists) if dists else None,
        "fraction_within_3cm": within / attempts if dists and attempts else None,
        "within_3cm_ci95": (list(wilson_interval(within, attempts))
                            if dists and attempts else None),
        "median_final_distance_ci95": median_interval(dists),
        "histogram": {"bin_edges_m": edges, "counts": counts,
                      "note": "last count: distances >= the last edge"},
        "failure_classes": classes,
        "config_hashes": sorted({r.config_hash for r in records}),
        "code_versions": sorted({r.code_version for r in records}),
        "trial_wall_time_s": _wall_times(records),
    })
    runs = clutter_runs(records)
    if runs is not None:
        out["clutter_runs"] = runs
    return out


def _wall_times(records: Sequence[TrialRecord]) -> dict | None:
    """Sum and median of the trials' own wall times (one worker each; a trial's seconds
    include building its Diagram and settling its scene)."""
    walls = [float(r.wall_time_s) for r in records if r.wall_time_s is not None]
    if not walls:
        return None
    return {"sum": sum(walls), "median": statistics.median(walls), "n": len(walls)}


def clutter_runs(records: Sequence[TrialRecord]) -> dict | None:
    """Attempts per clutter run and why each run ended, for one condition; None when the
    records are not clutter-run attempts.

    Returns:
        {"runs", "attempts" (simulation errors excluded, as in the success table),
        "attempts_per_run": {"mean", "min", "max"}, "grasped_per_run_mean",
        "run_ends": {reason: runs}} - a run without an ending record (interrupted; a
        resume finishes it) counts as "unfinished".
    """
    by_run: dict[int, list[TrialRecord]] = {}
    for r in records:
        if r.run_index is None:
            return None
        by_run.setdefault(int(r.run_index), []).append(r)
    if not by_run:
        return None
    attempts, grasped, ends = [], [], {}
    for recs in by_run.values():
        real = [r for r in recs if r.failure_class != "simulation-error"]
        attempts.append(len(real))
        grasped.append(sum(1 for r in real if r.success))
        end = next((r.extra["run_end"] for r in recs if (r.extra or {}).get("run_end")),
                   "unfinished")
        ends[end] = ends.get(end, 0) + 1
    return {"runs": len(by_run), "attempts": sum(attempts),
            "attempts_per_run": {"mean": statistics.fmean(attempts), "min": min(attempts),
                                 "max": max(attempts)},
            "grasped_per_run_mean": statistics.fmean(grasped),
            "run_ends": dict(sorted(ends.items(), key=lambda kv: (-kv[1], kv[0])))}


def median_interval(values: Sequence[float], z: float = 1.959964) -> list[float] | None:
    """A distribution-free 95% interval of the median: the order statistics at ranks
    n/2 -+ z sqrt(n)/2 (the binomial(n, 1/2) normal approximation), clipped to the
    sample. None for fewer than 3 values."""
    xs = sorted(values)
    n = len(xs)
    if n < 3:
        return None
    half = 0.5 * z * math.sqrt(n)
    lo = max(0, int(math.floor(n / 2 - half)))
    hi = min(n - 1, int(math.ceil(n / 2 + half)))
    return [xs[lo], xs[hi]]


def _condition_order(name: str) -> tuple:
    canon = canonical_condition(name)
    known = NOISE_CONDITIONS + PERCEPTION_CONDITIONS
    if canon in known:
        return (0, known.index(canon), "")
    sweep = parse_sweep_condition(name)
    if sweep is not None:
        series, param, value = sweep
        v = _as_float(value)
        return (2, series or "", param, 0 if v is not None else 1, v if v is not None else 0.0, value)
    return (1, 0, name)


def summarize(records: Sequence[TrialRecord]) -> dict[str, dict]:
    """`summarize_condition` for every condition, in a stable order (paper arms first)."""
    by_condition: dict[str, list[TrialRecord]] = {}
    for r in records:
        by_condition.setdefault(r.condition, []).append(r)
    return {c: summarize_condition(c, by_condition[c])
            for c in sorted(by_condition, key=_condition_order)}


def _lookup(policies: dict[str, dict], canonical: str) -> tuple[str, dict] | None:
    for name, stats in policies.items():
        if canonical_condition(name) == canonical:
            return name, stats
    return None


# --------------------------------------------------------------------------- targets

def _target(tid: str, experiment: str, description: str, value: float | None,
            threshold: float, comparison: str, units: str, note: str = "", *,
            value_units: str = "%") -> dict:
    if value is None:
        return {"id": tid, "experiment": experiment, "description": description, "value": None,
                "value_units": value_units, "threshold": threshold, "comparison": comparison,
                "units": units, "met": None, "margin": None,
                "note": note or "not evaluated: data missing"}
    margin = value - threshold if comparison == ">=" else threshold - value
    met = margin >= -_TOL if comparison == ">=" else margin > _TOL
    return {"id": tid, "experiment": experiment, "description": description, "value": value,
            "value_units": value_units, "threshold": threshold, "comparison": comparison,
            "units": units, "met": bool(met), "margin": margin, "note": note}


def _rate_percent(stats: dict | None) -> float | None:
    if stats is None or stats.get("n") in (None, 0):
        return None
    return 100.0 * stats["successes"] / stats["n"]


def check_targets(experiment: str, policies: dict[str, dict]) -> list[dict]:
    """The project's targets that apply to `experiment`, each met/missed and by how much.

    Targets: CTR success >= 97.5% (isolation), >= 94.8% (clutter), >= 90% and >= 40
    points above GPD (clutter-shift); sim-distance: CTR with noise keeps >= 70% of trials
    in the first 3 cm bin while GPD with noise does not. `margin` > 0 means met with room
    to spare (percentage points).

    Args:
        experiment: Experiment name (aliases resolved with `canonical_experiment`).
        policies: `summarize(...)` output.

    Returns:
        Target dicts (id, description, value, threshold, comparison, units, met, margin,
        note); [] for an experiment without targets.
    """
    exp = canonical_experiment(experiment)
    get = lambda c: (_lookup(policies, c) or (None, None))[1]  # noqa: E731
    out = []
    thresholds = {"isolation": 97.5, "clutter": 94.8, "clutter-shift": 90.0}
    if exp in thresholds:
        ctr = get("ctr")
        missing = "" if ctr is not None else "not evaluated: no 'ctr' condition"
        out.append(_target(f"{exp}/ctr-success", exp,
                           f"CTR grasp success >= {thresholds[exp]:g}% ({exp})",
                           _rate_percent(ctr), thresholds[exp], ">=", "points", missing))
    if exp == "clutter-shift":
        ctr, gpd = _rate_percent(get("ctr")), _rate_percent(get("gpd"))
        diff = None if ctr is None or gpd is None else ctr - gpd
        out.append(_target("clutter-shift/ctr-minus-gpd", exp,
                           "CTR success >= 40 points above GPD (clutter-shift)", diff, 40.0, ">=",
                           "points", "" if diff is not None else
                           "not evaluated: needs both 'ctr' and 'gpd' conditions",
                           value_units=" points"))
    has_noise_arms = get("ctr_noise") is not None and get("gpd_noise") is not None
    if exp == "sim-distance" or (exp not in thresholds and has_noise_arms):
        for cond, cmp, desc in (("ctr_noise", ">=", "CTR with noise: >= 70% of trials within 3 cm"),
                                ("gpd_noise", "<", "GPD with noise: < 70% of trials within 3 cm")):
            stats = get(cond)
            frac = None if stats is None or stats.get("fraction_within_3cm") is None \
                else 100.0 * stats["fraction_within_3cm"]
            out.append(_target(f"sim-distance/{cond}-within-3cm", "sim-distance", desc, frac,
                               70.0, cmp, "points", "" if frac is not None else
                               f"not evaluated: no '{cond}' distances"))
    return out


def _target_line(t: dict) -> str:
    if t["met"] is None:
        return f"- **not evaluated** {t['description']}: {t['note']}"
    verdict = "met" if t["met"] else "missed"
    how = (f"by {abs(t['margin']):.1f} {t['units']}" if abs(t["margin"]) > _TOL
           else "exactly at the threshold")
    line = f"- **{verdict}** {t['description']}: {t['value']:.1f}{t['value_units']} ({verdict} {how})"
    return line + (f"; {t['note']}" if t["note"] else "")


# --------------------------------------------------------------------------- figures

def _new_figure(width: float, height: float):
    # The object API with an explicit Agg canvas: no pyplot global state, so reports can be
    # made from threads and under any configured backend.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def _save_png(fig, path: Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return atomic_write_bytes(path, buf.getvalue())


def _figure5_panels(policies: dict[str, dict], experiment: str) -> list[tuple[str, list[str]]]:
    """[(panel title, condition names present)] in Figure 5 order; empty groups are left out."""
    exp = canonical_experiment(experiment)
    panels = []
    # Table 1 experiments have ctr/gpd arms too, but no noise comparison: say what is shown.
    noise_title = "CTR vs GPD" if exp in TABLE1_EXPERIMENTS else "kinematic noise"
    for title, group in ((noise_title, NOISE_CONDITIONS),
                         ("perception: one-shot vs closed loop", PERCEPTION_CONDITIONS)):
        names = [hit[0] for c in group if (hit := _lookup(policies, c)) is not None
                 and hit[1]["distance_n"] > 0]
        if names:
            panels.append((f"{exp}: {title}" if exp else title, names))
    return panels


def plot_distance_histograms(panels: list[tuple[str, list[tuple[str, list[float], int]]]],
                             path: str | os.PathLike, *, bin_m: float = BIN_M,
                             max_m: float = HIST_MAX_M) -> Path:
    """Grouped-bar histograms of the final distance, one panel per entry (Figure 5 style).

    Bars are fractions of each condition's trials (conditions may differ in trial count;
    trials without a distance count in the denominator); the last group collects distances
    >= max_m.

    Args:
        panels: [(title, [(label, final distances [m], number of trials)])]; the report
            passes the trials that are not simulation errors.
        path: PNG file to write (atomically).
        bin_m: Bin width [m].
        max_m: Start of the overflow bin [m].
    """
    import numpy as np

    fig = _new_figure(6.4 * len(panels), 3.8)
    nbins = int(round(max_m / bin_m))
    for i, (title, series) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1)
        width = 0.8 / max(1, len(series))
        x = np.arange(nbins + 1)
        for j, (label, dists, trials) in enumerate(series):
            _, counts = distance_histogram(dists, bin_m=bin_m, max_m=max_m)
            frac = np.asarray(counts, float) / max(1, trials)
            ax.bar(x - 0.4 + width * (j + 0.5), frac, width=width, label=f"{label} (n={trials})")
        ax.set_xticks(x)
        ax.set_xticklabels([f"{100 * k * bin_m:g}-{100 * (k + 1) * bin_m:g}" for k in range(nbins)]
                           + [f"≥{100 * max_m:g}"], fontsize=7, rotation=45)
        ax.set_xlabel(f"final distance to closest true grasp [cm], {100 * bin_m:g} cm bins")
        ax.set_ylabel("fraction of trials")
        ax.set_ylim(0, 1)
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8)
    return _save_png(fig, Path(path))


def _condition_distances(records: Sequence[TrialRecord], condition: str) -> tuple[list[float], int]:
    """(final distances, trials that are not simulation errors) of one condition."""
    sel = [r for r in records
           if r.condition == condition and r.failure_class != "simulation-error"]
    return [r.final_distance_m for r in sel if r.final_distance_m is not None], len(sel)


_SWEEP_RE = re.compile(r"^(?:(?P<series>[^=/:]+)[/:])?(?P<name>[A-Za-z_][\w.\-]*)=(?P<value>[^=]+)$")


def parse_sweep_condition(condition: str) -> tuple[str | None, str, str] | None:
    """"noise_scale=0.4" -> (None, "noise_scale", "0.4"); "ctr/noise_scale=0.4" ->
    ("ctr", "noise_scale", "0.4"); None for a condition that is not a sweep point."""
    m = _SWEEP_RE.match(condition.strip())
    if m is None:
        return None
    return m.group("series"), m.group("name"), m.group("value")


def _as_float(text: str) -> float | None:
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def _sweeps(policies: dict[str, dict]) -> dict[str, dict[str | None, list[tuple[str, str, dict]]]]:
    """{param: {series: [(value text, condition, stats)]}} for the "name=value" conditions."""
    out: dict[str, dict] = {}
    for cond, stats in policies.items():
        parsed = parse_sweep_condition(cond)
        if parsed is None:
            continue
        series, name, value = parsed
        out.setdefault(name, {}).setdefault(series, []).append((value, cond, stats))
    return out


def plot_sweep(param: str, series: dict[str | None, list[tuple[str, str, dict]]], path: Path) -> Path:
    """Success rate vs the swept value (Wilson 95% error bars) and, when distances were
    measured, the fraction of trials within 3 cm (Wilson 95%) and the median final
    distance (distribution-free 95% interval, `median_interval`). Non-numeric values
    are spaced evenly."""
    values = sorted({v for pts in series.values() for v, _, _ in pts},
                    key=lambda v: (_as_float(v) is None, _as_float(v) or 0.0, v))
    numeric = all(_as_float(v) is not None for v in values)
    xpos = {v: (_as_float(v) if numeric else float(i)) for i, v in enumerate(values)}
    has_success = any(s["n"] for pts in series.values() for _, _, s in pts)
    has_dist = any(s["fraction_within_3cm"] is not None for pts in series.values() for _, _, s in pts)
    kinds = [k for k, on in (("success", has_success), ("within", has_dist),
                             ("median", has_dist)) if on] or ["success"]
    fig = _new_figure(5.2 * len(kinds), 3.6)
    for i, kind in enumerate(kinds):
        ax = fig.add_subplot(1, len(kinds), i + 1)
        for label, pts in sorted(series.items(), key=lambda kv: kv[0] or ""):
            pts = sorted(pts, key=lambda p: xpos[p[0]])
            if kind == "success":
                pts = [p for p in pts if p[2]["n"]]
                ys = [p[2]["success_rate"] for p in pts]
                lo = [y - p[2]["ci95"][0] for y, p in zip(ys, pts)]
                hi = [p[2]["ci95"][1] - y for y, p in zip(ys, pts)]
                ax.errorbar([xpos[p[0]] for p in pts], ys, yerr=[lo, hi], marker="o", capsize=3,
                            label=label or "all")
            elif kind == "within":
                pts = [p for p in pts if p[2]["fraction_within_3cm"] is not None]
                ys = [p[2]["fraction_within_3cm"] for p in pts]
                cis = [p[2].get("within_3cm_ci95") or [y, y] for y, p in zip(ys, pts)]
                ax.errorbar([xpos[p[0]] for p in pts], ys,
                            yerr=[[y - c[0] for y, c in zip(ys, cis)],
                                  [c[1] - y for y, c in zip(ys, cis)]],
                            marker="s", capsize=3, label=label or "all")
            else:
                pts = [p for p in pts if p[2]["median_final_distance_m"] is not None]
                ys = [100 * p[2]["median_final_distance_m"] for p in pts]
                cis = [[100 * v for v in p[2].get("median_final_distance_ci95") or []] or [y, y]
                       for y, p in zip(ys, pts)]
                ax.errorbar([xpos[p[0]] for p in pts], ys,
                            yerr=[[y - c[0] for y, c in zip(ys, cis)],
                                  [c[1] - y for y, c in zip(ys, cis)]],
                            marker="^", capsize=3, label=label or "all")
        if not numeric:
            ax.set_xticks([xpos[v] for v in values])
            ax.set_xticklabels(values)
        ax.set_xlabel(param)
        ax.set_ylabel({"success": "grasp success rate (Wilson 95% CI)",
                       "within": "trials within 3 cm (Wilson 95% CI)",
                       "median": "median final distance [cm] (95% CI)"}[kind])
        if kind != "median":
            ax.set_ylim(-0.02, 1.02)
        else:
            ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
        if len(series) > 1 or next(iter(series)) is not None:
            ax.legend(fontsize=8)
    return _save_png(fig, path)


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
                   else ("gpd",) if policy == "gpd" else ("camera",))
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
