"""Reproduces Table 1 of Viereck et al. 2017 (grasp success, CTR vs GPD) from simulation
results directories, with the paper's robot numbers beside the simulated ones::

    python analysis/table1.py out/isolation out/clutter out/clutter-shift --out table1.md

A row may take CTR from one run and GPD from another (``DIR@ctr DIR@gpd``, e.g. GPD re-run
with another option on the same seed); the table then names its sources.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from drake_grasp.evaluation.report import write_table1


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Table 1 (grasp success rates of CTR and GPD, Wilson 95% intervals, the "
                    "paper's numbers beside them) as Markdown, from Monte Carlo results dirs.")
    parser.add_argument("results_dirs", nargs="+",
                        help="results dirs of the experiments 'isolation', 'clutter' and "
                             "'clutter-shift' (any subset; the experiment name is read from "
                             "run.json or the trial records); conditions 'ctr' and 'gpd' fill "
                             "the CTR and GPD columns; DIR@ctr takes only those conditions from "
                             "DIR, so that one experiment's CTR and GPD may come from two dirs "
                             "(each condition from one)")
    parser.add_argument("--out", required=True, help="Markdown file to write (atomically)")
    args = parser.parse_args(argv)
    try:
        path = write_table1(args.results_dirs, args.out)
    except ValueError as e:
        parser.exit(2, f"table1: error: {e}\n")
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
