"""PNG figures of Monte Carlo results (see `drake_grasp.evaluation.report`).

Owns the matplotlib drawing: Figure-5-style histograms of the final distance to the
closest true grasp, the choice of Figure 5 panels for an experiment, and the sweep curves
of "name=value" conditions (parsing those condition names included). Figures are drawn
with the object API on an Agg canvas, without pyplot global state.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Sequence

from drake_grasp.evaluation.records import TrialRecord
from drake_grasp.evaluation.report_stats import (BIN_M, HIST_MAX_M, NOISE_CONDITIONS,
    PERCEPTION_CONDITIONS, TABLE1_EXPERIMENTS, _as_float, _lookup, canonical_experiment,
    distance_histogram, parse_sweep_condition)
from drake_grasp.core.files import atomic_write_bytes


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
