"""analysis/results/cnn-onpolicy-finetune/choose_gate.py: the plan's choice and gate on
fabricated score files."""

import json

import pytest

SCRIPT = "results/cnn-onpolicy-finetune/choose_gate"


def write_score(path, regret_median_mm, spearman, decisions=100):
    block = {"none": {"decisions": decisions, "spearman_mean": spearman,
                      "regret_mean_mm": regret_median_mm + 5,
                      "regret_median_mm": regret_median_mm, "top1_within_1cm": 0.4}}
    path.write_text(json.dumps({"decisions": decisions, "all": block,
                                "by_outcome": {"failed": block}}))


def test_choose_takes_the_lowest_median_regret_then_the_higher_spearman(analysis_script, tmp_path):
    S = analysis_script(SCRIPT)
    write_score(tmp_path / "default.json", 18.0, 0.43)
    write_score(tmp_path / "a-epoch1.json", 17.0, 0.44)
    write_score(tmp_path / "b-epoch2.json", 16.0, 0.45)
    write_score(tmp_path / "c-epoch3.json", 16.0, 0.47)
    out = S.choose(tmp_path)
    assert out["chosen"] == "c-epoch3" and set(out["candidates"]) == {"a-epoch1", "b-epoch2",
                                                                      "c-epoch3"}
    assert out["default"]["regret_median_mm"] == 18.0
    with pytest.raises(FileNotFoundError, match="no <run>-epoch<E>.json"):
        S.choose(tmp_path / "nothing")


@pytest.mark.parametrize("regret,spearman,passed", [
    (17.0, 0.45, True),    # 1.0 mm and 0.02 exactly
    (17.1, 0.50, False),   # regret not low enough
    (10.0, 0.449, False),  # Spearman not high enough
])
def test_gate(analysis_script, tmp_path, regret, spearman, passed):
    S = analysis_script(SCRIPT)
    write_score(tmp_path / "d.json", 18.0, 0.43)
    write_score(tmp_path / "c.json", regret, spearman)
    assert S.gate(tmp_path / "d.json", tmp_path / "c.json")["passed"] is passed
    write_score(tmp_path / "other.json", regret, spearman, decisions=99)
    with pytest.raises(ValueError, match="99 decisions.*not the same states"):
        S.gate(tmp_path / "d.json", tmp_path / "other.json")
