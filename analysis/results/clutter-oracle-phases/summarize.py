"""Pools `analysis/oracle_ctr.py --records R --arms oracle --oracle-phase P` over the
default's five clutter seeds, beside the records (the CNN at every decision) and the truth
at every decision (`../clutter-controller/oracle/`): successes with Wilson intervals,
paired counts against the records and against the full oracle (exact McNemar), failure
classes, and the share of the full oracle's gain each phase recovers (PLAN.md's reading).

    PYTHONPATH=. python analysis/results/clutter-oracle-phases/summarize.py   # writes summary.json, summary.txt
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np

from drake_grasp.evaluation.records import mcnemar_exact_p, wilson_interval

HERE = Path(__file__).resolve().parent
SEEDS = (16, 25, 26, 27, 28)
PHASES = ("descent", "stop")


def rows_of(folder: Path) -> dict[str, dict]:
    """trial_id+seed -> row, over the seeds present in `folder/seedS/`."""
    out = {}
    for seed in SEEDS:
        f = folder / f"seed{seed}" / "oracle_ctr_clutter.json"
        if f.is_file():
            for r in json.loads(f.read_text())["rows"]:
                out[f"{seed}:{r['trial_id']}"] = r
    return out


def paired(a: dict[str, bool], b: dict[str, bool]) -> dict:
    keys = sorted(set(a) & set(b))
    only_a = sum(a[k] and not b[k] for k in keys)
    only_b = sum(b[k] and not a[k] for k in keys)
    return {"attempts": len(keys), "only_first": only_a, "only_second": only_b,
            "mcnemar_exact_p": round(mcnemar_exact_p(only_a, only_b), 4)}


def distances(runs: dict[str, dict]) -> dict:
    """Final distance to the pile's nearest true grasp over the attempts that have one."""
    d = np.array([r["final_distance_m"] for r in runs.values() if r["final_distance_m"] is not None])
    return {"n": int(len(d)), "median_mm": round(1000 * float(np.median(d)), 1),
            "within_1cm": round(float(np.mean(d < 0.01)), 3),
            "within_3cm": round(float(np.mean(d < 0.03)), 3)}


def main() -> None:
    full = rows_of(HERE.parent / "clutter-controller" / "oracle")
    records = {k: r["recorded"]["success"] for k, r in full.items()}
    truth = {k: r["oracle"]["success"] for k, r in full.items()}
    n, k_cnn, k_truth = len(full), sum(records.values()), sum(truth.values())
    gain = k_truth - k_cnn
    summary = {"attempts": n, "cnn_every_decision": k_cnn, "truth_every_decision": k_truth,
               "gain": gain, "phases": {}}
    lines = [f"{n} clutter attempts (seeds {', '.join(map(str, SEEDS))}): CNN at every decision "
             f"{k_cnn} ({100 * k_cnn / n:.1f}%), truth at every decision {k_truth} "
             f"({100 * k_truth / n:.1f}%), gain {gain}"]
    for phase in PHASES:
        rows = rows_of(HERE / phase)
        if not rows:
            lines.append(f"truth in the {phase} only: no results yet")
            continue
        ok = {k: r["oracle"]["success"] for k, r in rows.items()}
        k = sum(ok.values())
        lo, hi = wilson_interval(k, len(ok))
        rec = {key: records[key] for key in ok}
        base = sum(rec.values())
        share = (k - base) / gain if len(ok) == n and gain else None
        classes = Counter(r["oracle"]["failure_class"] for r in rows.values()
                          if not r["oracle"]["success"])
        summary["phases"][phase] = {
            "attempts": len(ok), "successes": k, "ci95": [lo, hi],
            "seeds": sorted({int(key.split(":")[0]) for key in ok}),
            "vs_records": paired(rec, ok), "vs_truth_every_decision": paired(
                {key: truth[key] for key in ok}, ok),
            "share_of_gain": share, "failure_classes": dict(classes),
            "truth_scored_decisions": sum(r["oracle"]["oracle_steps"] for r in rows.values()),
            "decisions": sum(r["oracle"]["control_steps"] for r in rows.values())}
        p = summary["phases"][phase]
        lines.append(
            f"truth in the {phase} only: {k}/{len(ok)} {100 * k / len(ok):.1f}% "
            f"[{100 * lo:.1f}, {100 * hi:.1f}]; vs the records (CNN) only / only this: "
            f"{p['vs_records']['only_first']} / {p['vs_records']['only_second']} "
            f"(p = {p['vs_records']['mcnemar_exact_p']}); vs the truth at every decision: "
            f"{p['vs_truth_every_decision']['only_first']} / "
            f"{p['vs_truth_every_decision']['only_second']} "
            f"(p = {p['vs_truth_every_decision']['mcnemar_exact_p']}); share of the gain "
            f"{'n/a' if share is None else f'{share:.2f}'}; failures {dict(classes)}; "
            f"truth-scored decisions {p['truth_scored_decisions']} of {p['decisions']}")
    arms = {"CNN at every decision": {k: r["cnn"] for k, r in full.items()},
            "truth at every decision": {k: r["oracle"] for k, r in full.items()}}
    for phase in PHASES:
        arms[f"truth in the {phase} only"] = {k: r["oracle"] for k, r in rows_of(HERE / phase).items()}
    summary["final_distance"] = {}
    for name, runs in arms.items():
        if not runs:
            continue
        d = summary["final_distance"][name] = distances(runs)
        lines.append(f"{name}: final distance median {d['median_mm']} mm, within 1 cm "
                     f"{d['within_1cm']:.2f}, within 3 cm {d['within_3cm']:.2f} (n = {d['n']})")
    for phase in PHASES:  # the truth's successes this arm lost: how far they ended
        runs = arms[f"truth in the {phase} only"]
        lost = sorted(round(1000 * runs[k]["final_distance_m"]) for k in runs
                      if truth[k] and not runs[k]["success"] and runs[k]["final_distance_m"] is not None)
        if lost:
            summary["phases"][phase]["lost_final_distance_mm"] = lost
            lines.append(f"truth in the {phase} only, the {len(lost)} attempts with a final distance "
                         f"it lost of the truth's successes: {lost[0]}-{lost[-1]} mm, median "
                         f"{int(np.median(lost))} mm")
    (HERE / "summary.json").write_text(json.dumps(summary, indent=1))
    (HERE / "summary.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
