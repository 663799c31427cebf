"""PLAN.md's choice and gate, from `onpolicy_ranking.py score` outputs.

    python analysis/results/cnn-onpolicy-finetune/choose_gate.py choose analysis/results/cnn-onpolicy-finetune/validation
    python analysis/results/cnn-onpolicy-finetune/choose_gate.py gate \
        analysis/results/cnn-onpolicy-finetune/gate/default.json analysis/results/cnn-onpolicy-finetune/gate/candidate.json

`choose`: the epoch file with the lowest median regret on the validation states (ties:
the higher Spearman), among every `<run>-epoch<E>.json` of the folder; `default.json`
there is the shipped net's, reported beside them. `gate`: the candidate passes iff its
median regret is at least 1.0 mm below the default's and its Spearman mean at least
0.02 above, on the same states.
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

GATE_REGRET_MM = 1.0
GATE_SPEARMAN = 0.02


def figures(path: Path) -> dict:
    out = json.loads(Path(path).read_text())
    if "all" not in out or "none" not in out["all"]:
        raise ValueError(f"{path}: expected `onpolicy_ranking.py score --views none` output")
    return {"decisions": out["decisions"], **out["all"]["none"],
            "failed_spearman": out["by_outcome"].get("failed", {}).get("none", {}).get(
                "spearman_mean")}


def choose(folder: Path) -> dict:
    rows = {}
    for f in sorted(Path(folder).glob("*.json")):
        if re.fullmatch(r".+-epoch\d+\.json", f.name):
            rows[f.stem] = figures(f)
    if not rows:
        raise FileNotFoundError(f"{folder}: no <run>-epoch<E>.json score files")
    best = min(rows, key=lambda k: (rows[k]["regret_median_mm"], -rows[k]["spearman_mean"]))
    default = figures(Path(folder) / "default.json")
    return {"default": default, "candidates": rows, "chosen": best}


def gate(default_path: Path, candidate_path: Path) -> dict:
    d, c = figures(default_path), figures(candidate_path)
    if d["decisions"] != c["decisions"]:
        raise ValueError(f"{candidate_path}: {c['decisions']} decisions, the default's "
                         f"{default_path} {d['decisions']}: not the same states")
    regret_ok = c["regret_median_mm"] <= d["regret_median_mm"] - GATE_REGRET_MM
    spearman_ok = c["spearman_mean"] >= d["spearman_mean"] + GATE_SPEARMAN
    return {"default": d, "candidate": c, "regret_ok": regret_ok, "spearman_ok": spearman_ok,
            "passed": bool(regret_ok and spearman_ok)}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        if argv[:1] == ["choose"] and len(argv) == 2:
            out = choose(Path(argv[1]))
        elif argv[:1] == ["gate"] and len(argv) == 3:
            out = gate(Path(argv[1]), Path(argv[2]))
        else:
            sys.exit(__doc__)
    except (FileNotFoundError, ValueError) as e:
        sys.exit(f"choose_gate: {e}")
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
