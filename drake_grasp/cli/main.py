"""The `drake-grasp` command line. Thin: parses flags and calls library functions.

Each command group lives in its own module (run.py, learn.py, gpd.py, experiments.py,
lab.py, results.py, tools.py), which adds its subcommands with `add_parsers(sub)`; what several
commands share (argument types, the scenario flags) is in args.py.
"""

from __future__ import annotations

import argparse
import sys

from drake_grasp.cli import run, learn, gpd, experiments, lab, results, tools

# In the order `drake-grasp --help` lists them.
GROUPS = (run, learn, gpd, experiments, lab, results, tools)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="drake-grasp",
        description="Closed-loop visuomotor grasping (Viereck et al., CoRL 2017) as a Drake diagram.")
    sub = parser.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.add_parsers(sub)
    return parser


def _log_to_stderr() -> None:
    """The package's informational messages (e.g. "replaced the earlier episode") go to
    stderr, prefixed like the CLI's errors; other libraries' logging is left alone."""
    import logging

    log = logging.getLogger("drake_grasp")
    for h in [h for h in log.handlers if getattr(h, "_drake_grasp_cli", False)]:
        log.removeHandler(h)  # an earlier main() in this process; sys.stderr may differ now
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("drake-grasp: %(message)s"))
    handler._drake_grasp_cli = True
    log.addHandler(handler)
    log.setLevel(logging.INFO)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _log_to_stderr()
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError, KeyError) as e:  # OSError: a file exists, a full disk, ...
        print(f"drake-grasp {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
