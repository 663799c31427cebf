"""analysis/results/cnn-rank-loss/gate.py: PLAN.md's gate on fabricated cnn_eval files."""

import importlib.util
import json
from pathlib import Path

import pytest

GATE = Path(__file__).resolve().parents[1] / "analysis" / "results" / "cnn-rank-loss" / "gate.py"


def _load():
    spec = importlib.util.spec_from_file_location("rank_loss_gate", GATE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _write(folder, arm, spearman, regret, paper_l1):
    folder.mkdir(exist_ok=True)
    (folder / f"{arm}_on_clutter_test.json").write_text(json.dumps(
        {"test_l1_m": 0.037, "ranking": {"spearman_mean": spearman, "regret_median_m": regret,
                                         "images": 1000}}))
    (folder / f"{arm}_on_paper_test.json").write_text(json.dumps(
        {"test_l1_m": paper_l1, "ranking": {"spearman_mean": 0.69}}))


def test_the_gate_asks_all_four_checks_and_picks_the_better_passing_arm(tmp_path):
    G = _load()
    _write(tmp_path, "default", 0.255, 0.0276, 0.02357)
    _write(tmp_path, "l1", 0.27, 0.0280, 0.0239)
    _write(tmp_path, "rank01", 0.305, 0.0270, 0.02457)  # every check on its bound
    _write(tmp_path, "rank05", 0.40, 0.0200, 0.02460)   # the paper L1 0.03 mm over
    out = G.gate(G.read(tmp_path))
    assert out["verdicts"]["rank01"]["passed"]
    assert out["verdicts"]["rank05"]["checks"] == {"spearman_over_default": True,
                                                   "spearman_over_l1": True, "regret": True,
                                                   "paper_l1": False}
    assert out["candidate"] == "rank01" and out["stage1"]
    _write(tmp_path, "rank05", 0.40, 0.0200, 0.0240)
    assert G.gate(G.read(tmp_path))["candidate"] == "rank05"
    _write(tmp_path, "l1", 0.38, 0.0280, 0.0239)  # the control alone explains rank01's gain
    out = G.gate(G.read(tmp_path))
    assert not out["verdicts"]["rank01"]["checks"]["spearman_over_l1"]
    _write(tmp_path, "rank05", 0.40, 0.0277, 0.0240)  # worse top choice than the default
    out = G.gate(G.read(tmp_path))
    assert out["candidate"] is None and not out["stage1"]
    (tmp_path / "l1_on_paper_test.json").unlink()
    with pytest.raises(SystemExit, match="l1_on_paper_test.json: not found"):
        G.main([str(tmp_path)])
