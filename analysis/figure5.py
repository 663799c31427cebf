"""Reproduces Figure 5 of Viereck et al. 2017 from simulation results directories.

Figure 5 shows histograms (3 cm bins) of the final distance of the gripper to the closest
true grasp: left, INIT / CTR / GPD with and without kinematic noise; right, the one-shot
CNN prediction vs CNN followed by the controller. Give the sim-distance results dir (and
the perception one, if run separately)::

    python analysis/figure5.py out/sim-distance out/perception --out figure5.png
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from drake_grasp.evaluation.report import write_figure5
from drake_grasp.evaluation.report_stats import BIN_M, HIST_MAX_M


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Figure 5 (final distance to the closest true grasp, histograms) from "
                    "Monte Carlo results dirs (see drake_grasp.evaluation.records for their layout).")
    parser.add_argument("results_dirs", nargs="+",
                        help="results dirs holding the Figure 5 conditions: init, ctr, ctr_noise, "
                             "gpd, gpd_noise (left panel) and cnn-only, cnn-ctr (right panel); "
                             "each condition may appear in one dir only (several dirs of one "
                             "experiment are fine, e.g. arms run separately on the same seed); "
                             "DIR@init,gpd takes only those conditions from DIR")
    parser.add_argument("--out", required=True, help="PNG file to write (atomically)")
    parser.add_argument("--bin-cm", type=float, default=100 * BIN_M,
                        help="histogram bin width in cm (default: the paper's 3)")
    parser.add_argument("--max-cm", type=float, default=100 * HIST_MAX_M,
                        help="distances at or beyond this (cm) share one overflow bin (default: 30)")
    args = parser.parse_args(argv)
    try:
        path = write_figure5(args.results_dirs, args.out, bin_m=args.bin_cm / 100, max_m=args.max_cm / 100)
    except ValueError as e:
        parser.exit(2, f"figure5: error: {e}\n")
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
