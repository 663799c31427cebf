"""`drake-grasp results ...`: housekeeping of `evaluate` results folders."""

from __future__ import annotations

import argparse
import json
import sys


def _cmd_pack(args) -> None:
    from tqdm import tqdm

    from drake_grasp.evaluation.records import pack_records
    from drake_grasp.evaluation.records_table import unpacked_folders
    from drake_grasp.evaluation.scene_records import pack_scene_records, unpacked_scene_folders

    trials = unpacked_folders(args.folders)
    scenes = unpacked_scene_folders(args.folders)
    if args.dry_run:
        for folder, n in trials:
            print(f"{folder}: {n} trial files")
        for folder, n in scenes:
            print(f"{folder}: {n} scene files")
        print(json.dumps({"folders": len(trials) + len(scenes),
                          "trial_files": sum(n for _, n in trials),
                          "scene_files": sum(n for _, n in scenes)}))
        return
    done = []
    jobs = [(f, n, pack_records) for f, n in trials] + [(f, n, pack_scene_records)
                                                         for f, n in scenes]
    with tqdm(total=sum(n for _, n, _ in jobs), unit="file", disable=not args.progress,
              file=sys.stderr) as bar:
        for folder, n, pack in jobs:
            bar.set_postfix_str(str(folder), refresh=False)
            done.append(pack(folder))
            bar.update(n)
    print(json.dumps({"folders": len(done),
                      "trial_files_packed": sum(d["packed"] for d in done[:len(trials)]),
                      "scene_files_packed": sum(d["packed"] for d in done[len(trials):]),
                      "packed": done}, indent=1))


def _parser_pack(rsub) -> None:
    p = rsub.add_parser(
        "pack", help="pack the per-trial (per-scene) JSON files of results folders into each "
                     "folder's trials.parquet (scenes.parquet)",
        description="Finds every results folder under the given folders (recursively: a "
                    "folder whose trials/ holds *.json files) and packs its trial records into "
                    "FOLDER/trials.parquet, one row per trial, next to the rows already there "
                    "(as a finished `evaluate` does). The new table is written under a "
                    "temporary name and renamed into place; each JSON file is deleted only "
                    "after the table on disk read back a record equal to the file's (types "
                    "and float bits included), then the empty trials/ folder. Killed at any "
                    "point, a folder reads the same as before (no trial counted twice); "
                    "running the command again finishes it. Replay pages (replays/*.html) "
                    "stay files. The per-scene records of label-check and grasp-tolerance "
                    "folders (scenes/*.json beside run.json) go into FOLDER/scenes.parquet "
                    "the same way, as those commands do when they finish. Prints one JSON "
                    "object: folders and files packed.")
    p.add_argument("folders", nargs="+", metavar="DIR",
                   help="results folders, or folders holding results folders at any depth")
    p.add_argument("--dry-run", action="store_true",
                   help="only list the folders that would be packed and their files")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                   help="progress bar on stderr, in files (default: on)")
    p.set_defaults(func=_cmd_pack)


def add_parsers(sub) -> None:
    """Add this group's subcommands to the `drake-grasp` parser."""
    pr = sub.add_parser("results", help="results folders of 'drake-grasp evaluate': pack "
                                        "their trial files into one Parquet table")
    rsub = pr.add_subparsers(dest="results_command", required=True)
    _parser_pack(rsub)
