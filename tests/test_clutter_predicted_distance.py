"""analysis/clutter_predicted_distance.py: a recorded CTR clutter attempt replayed with its
decisions logged, and the held/failed summary of the last decision's least prediction."""

from pathlib import Path

import pytest

RECORD = (Path(__file__).resolve().parents[1] / "analysis" / "results" / "paper-bn12" / "clutter"
          / "trials" / "clutter__ctr__0000__attempt01.json")


@pytest.mark.slow
def test_a_replay_logs_one_prediction_per_recorded_decision(analysis_script):
    """Run 0's second attempt (a hammer that slipped in the lift): the replay fails as
    recorded, with one logged prediction per recorded decision (24)."""
    row = analysis_script("clutter_predicted_distance").replay(str(RECORD))
    assert row["success"] is False and row["recorded_success"] is False
    assert row["failure_class"] == "slipped-during-lift"
    assert len(row["least_predicted_m"]) == row["recorded_decisions"] == 24
    assert all(0.0 <= d < 0.5 for d in row["least_predicted_m"])


def test_summary_counts_and_auc(analysis_script):
    """Held last predictions 10, 20, 30 mm; failed 25, 40 mm: of the 6 (failed, held)
    pairs the failed value is larger in 5, so AUC = 5/6."""
    S = analysis_script("clutter_predicted_distance")
    rows = [{"success": ok, "recorded_success": ok, "least_predicted_m": [0.05, d]}
            for ok, d in [(True, 0.010), (True, 0.020), (True, 0.030), (False, 0.025), (False, 0.040)]]
    out = S.summarize(rows)
    assert (out["held"], out["failed"], out["replays_as_recorded"]) == (3, 2, 5)
    assert out["auc_failed_above_held"] == pytest.approx(5 / 6, abs=1e-3)
    assert out["above_25mm"] == {"failed": 1, "held": 1}
    assert out["last_least_predicted_mm"]["held_median"] == 20.0
    assert S.main([str(RECORD.parent / "none"), "--out", "x.json"]) == 2
