"""The clutter-removal protocol's table: grasp success rate and percent cleared per policy,
mean +- standard deviation over seeds, with the published figures beside as context.

    python analysis/removal_table.py RUN [RUN ...] [--out FILE.md] [--json FILE.json]

Each RUN is a results folder of `drake-grasp evaluate --experiment removal-pile` (or
`removal-packed`), one seed each (the protocol: 5 seeds of 100 rounds). Per folder and
condition the two figures come from `report_stats.clutter_runs` (a round is a clutter run:
it ends when the table is clear, no grasp is found or 2 grasps fail in a row); the table
gives their mean and sample standard deviation (n - 1) over the folders.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from drake_grasp.core.files import atomic_write_text, print_json
from drake_grasp.evaluation.records import load_records, read_run_info
from drake_grasp.evaluation.report_stats import clutter_runs

# Published figures (context, not a like-for-like claim: another simulator, gripper and
# object set): GSR and DR (percent cleared) in percent, mean +- std over 5 seeds.
PUBLISHED = {
    "pile": [("GIGA-High (Jiang et al., RSS 2021)", "PyBullet, Panda gripper", 74.1, 1.5, None, None),
             ("Edge Grasp Network (Huang et al., 2022)", "PyBullet, Panda gripper", 89.9, 1.8, 92.8, 1.6)],
    "packed": [("GIGA-High (Jiang et al., RSS 2021)", "PyBullet, Panda gripper", 88.5, 2.0, None, None)],
}


def _mean_std(values: list[float]) -> tuple[float, float]:
    return statistics.fmean(values), (statistics.stdev(values) if len(values) > 1 else 0.0)


def removal_table(runs: list[Path]) -> dict:
    """{"experiment", "seeds", "policies": {condition: {"per_seed": [...], "gsr_mean",
    "gsr_std", "cleared_mean", "cleared_std"}}} over the result folders `runs`."""
    experiments, seeds, per = set(), [], {}
    for run in runs:
        info = read_run_info(run) or {}
        experiments.add(info.get("experiment"))
        seeds.append(info.get("seed"))
        by_condition: dict[str, list] = {}
        for r in load_records(run):
            by_condition.setdefault(r.condition, []).append(r)
        for condition, records in sorted(by_condition.items()):
            stats = clutter_runs(records)
            if stats is None or stats["grasp_success_rate"] is None:
                raise ValueError(f"{run}: condition {condition!r} has no clutter-run attempts "
                                 "(expected a folder of evaluate --experiment removal-*)")
            per.setdefault(condition, []).append({
                "run": str(run), "seed": info.get("seed"), "rounds": stats["runs"],
                "gsr_percent": 100.0 * stats["grasp_success_rate"],
                "percent_cleared": stats["percent_cleared"], "run_ends": stats["run_ends"]})
    if len(experiments) != 1 or not str(next(iter(experiments))).startswith("removal-"):
        raise ValueError(f"expected folders of one removal experiment, got {sorted(map(str, experiments))}")
    policies = {}
    for condition, rows in per.items():
        gsr = _mean_std([row["gsr_percent"] for row in rows])
        cleared = _mean_std([row["percent_cleared"] for row in rows
                             if row["percent_cleared"] is not None] or [float("nan")])
        policies[condition] = {"per_seed": rows, "gsr_mean": gsr[0], "gsr_std": gsr[1],
                               "cleared_mean": cleared[0], "cleared_std": cleared[1]}
    return {"experiment": experiments.pop(), "seeds": seeds, "policies": policies}


def markdown(table: dict) -> str:
    kind = table["experiment"].removeprefix("removal-")
    lines = [f"# Clutter removal, {kind}: {len(table['seeds'])} seed(s) {table['seeds']}", "",
             "| policy | rounds per seed | grasp success rate [%] | percent cleared [%] |",
             "|---|---|---|---|"]
    for condition, p in table["policies"].items():
        rounds = ", ".join(str(row["rounds"]) for row in p["per_seed"])
        lines.append(f"| {condition} (this simulator: Drake, UR5 + Robotiq 2F-85) | {rounds} | "
                     f"{p['gsr_mean']:.1f} +- {p['gsr_std']:.1f} | "
                     f"{p['cleared_mean']:.1f} +- {p['cleared_std']:.1f} |")
    for name, sim, gsr, gsr_sd, dr, dr_sd in PUBLISHED.get(kind, []):
        cleared = "not given" if dr is None else f"{dr:.1f} +- {dr_sd:.1f}"
        lines.append(f"| {name} ({sim}; published) | 100 | {gsr:.1f} +- {gsr_sd:.1f} | {cleared} |")
    lines += ["", "Mean +- sample standard deviation over the seeds. The published rows are "
              "context: another simulator, gripper and object set."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="evaluate result folders, one seed each")
    ap.add_argument("--out", type=Path, help="markdown file to write")
    ap.add_argument("--json", type=Path, help="JSON file to write")
    args = ap.parse_args(argv)
    table = removal_table(args.runs)
    text = markdown(table)
    if args.out:
        atomic_write_text(args.out, text)
    if args.json:
        print_json(table, args.json)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
