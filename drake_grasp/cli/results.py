"""`drake-grasp results ...`: housekeeping of `evaluate` results folders."""

from __future__ import annotations

import argparse
import json
import sys


def _cmd_pack(args) -> None:
    from tqdm import tqdm

    from drake_grasp.evaluation.records import pack_records
    from drake_grasp.evaluation.records_table import unpacked_folders

    folders = unpacked_folders(args.folders)
    total = sum(n for _, n in folders)
    if args.dry_run:
        for folder, n in folders:
            print(f"{folder}: {n} trial files")
        print(json.dumps({"folders": len(folders), "trial_files": total}))
        return
    done = []
    with tqdm(total=total, unit="trial", disable=not args.progress, file=sys.stderr) as bar:
        for folder, n in folders:
            bar.set_postfix_str(str(folder), refresh=False)
            done.append(pack_records(folder))
            bar.update(n)
    print(json.dumps({"folders": len(done), "trial_files_packed": sum(d["packed"] for d in done),
                      "packed": done}, indent=1))


def _parser_pack(rsub) -> None:
    p = rsub.add_parser(
        "pack", help="pack the per-trial JSON files of results folders into each folder's "
                     "trials.parquet",
        description="Finds every results folder under the given folders (recursively: a "
                    "folder whose trials/ holds *.json files) and packs its trial records into "
                    "FOLDER/trials.parquet, one row per trial, next to the rows already there "
                    "(as a finished `evaluate` does). The new table is written under a "
                    "temporary name and renamed into place; each JSON file is deleted only "
                    "after the table on disk read back a record equal to the file's (types "
                    "and float bits included), then the empty trials/ folder. Killed at any "
                    "point, a folder reads the same as before (no trial counted twice); "
                    "running the command again finishes it. Replay pages (replays/*.html) "
                    "stay files. Prints one JSON object: folders and files packed.")
    p.add_argument("folders", nargs="+", metavar="DIR",
                   help="results folders, or folders holding results folders at any depth")
    p.add_argument("--dry-run", action="store_true",
                   help="only list the folders that would be packed and their trial files")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                   help="progress bar on stderr, in trial files (default: on)")
    p.set_defaults(func=_cmd_pack)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    pr = sub.add_parser("results", help="results folders of 'drake-grasp evaluate': pack "
                                        "their trial files into one Parquet table")
    rsub = pr.add_subparsers(dest="results_command", required=True)
    _parser_pack(rsub)
