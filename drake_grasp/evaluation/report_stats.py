"""Loading and statistics of Monte Carlo results (see `drake_grasp.evaluation.report`).

Owns the paper's reference numbers and condition names (Table 1, Figure 5, the aliases
other modules use), loading a results directory into `Results`, the per-condition
statistics (success rate with Wilson interval over attempts, i.e. trials minus simulation
errors; final-distance statistics and histogram; clutter runs; wall times) and the target
checks of an experiment against the paper.
"""

from __future__ import annotations

import math
import os
import re
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

from drake_grasp.policies.decisions import NO_GRASP_FOUND
from drake_grasp.evaluation.records import (FAILURE_CLASSES, TABLE_FILE, TrialRecord,
    load_records, read_run_info, wilson_interval)

BIN_M = 0.03  # the paper's Figure 5 bin size
HIST_MAX_M = 0.30  # last regular bin edge; farther trials go to an overflow bin

# Figure 5 (left): kinematic noise comparison; (right): perception, one-shot vs closed loop.
NOISE_CONDITIONS = ("init", "ctr", "ctr_noise", "gpd", "gpd_noise")
PERCEPTION_CONDITIONS = ("cnn-only", "cnn-ctr")
CONDITION_LABELS = {
    "init": "INIT", "ctr": "CTR no noise", "ctr_noise": "CTR with noise",
    "gpd": "GPD no noise", "gpd_noise": "GPD with noise",
    "cnn-only": "CNN only", "cnn-ctr": "CNN+CTR",
    "gpd-track": "GPD-track no noise", "gpd-track_noise": "GPD-track with noise",
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
        raise ValueError(f"{results_dir}: no trial records (neither {TABLE_FILE} nor "
                         "trials/*.json; nothing to report; has the run started?)")
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
        "run_ends": {reason: runs}, and the clutter-removal protocol's two figures:
        "grasp_success_rate" (grasped over attempted grasps: an attempt in which the
        policy found no grasp is not one) and "percent_cleared" (objects grasped over the
        objects the runs started with, from each run's first attempt's scene; None when
        no record holds it), with "grasps_attempted", "no_grasp_found", "objects",
        "cleared"} - a run without an ending record (interrupted; a resume finishes it)
        counts as "unfinished".
    """
    by_run: dict[int, list[TrialRecord]] = {}
    for r in records:
        if r.run_index is None:
            return None
        by_run.setdefault(int(r.run_index), []).append(r)
    if not by_run:
        return None
    attempts, grasped, ends, started, none_found = [], [], {}, [], 0
    for recs in by_run.values():
        real = [r for r in recs if r.failure_class != "simulation-error"]
        attempts.append(len(real))
        grasped.append(sum(1 for r in real if r.success))
        none_found += sum(1 for r in real if r.failure_reason == NO_GRASP_FOUND)
        end = next((r.extra["run_end"] for r in recs if (r.extra or {}).get("run_end")),
                   "unfinished")
        ends[end] = ends.get(end, 0) + 1
        first = min(recs, key=lambda r: r.attempt_index or 0)
        scene = (first.extra or {}).get("scene")
        started.append(len(scene.get("objects", [])) if isinstance(scene, dict) else None)
    tried = sum(attempts) - none_found
    objects = None if None in started else sum(started)
    return {"runs": len(by_run), "attempts": sum(attempts),
            "attempts_per_run": {"mean": statistics.fmean(attempts), "min": min(attempts),
                                 "max": max(attempts)},
            "grasped_per_run_mean": statistics.fmean(grasped),
            "run_ends": dict(sorted(ends.items(), key=lambda kv: (-kv[1], kv[0]))),
            "grasps_attempted": tried, "no_grasp_found": none_found,
            "grasp_success_rate": sum(grasped) / tried if tried else None,
            "objects": objects, "cleared": sum(grasped),
            "percent_cleared": (100.0 * sum(grasped) / objects) if objects else None}


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
