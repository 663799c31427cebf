"""analysis/pile_label_check.py: a recorded clutter pile's ground-truth grasps of one
object, executed in the grasp lab with and without the pile around it."""

from pathlib import Path

import pytest

RECORD = (Path(__file__).resolve().parents[1] / "analysis" / "results" / "paper-bn12" / "clutter"
          / "trials" / "clutter__ctr__0007__attempt02.json")


@pytest.mark.slow
def test_a_label_of_a_car_in_a_pile_holds_only_with_its_neighbours(analysis_script):
    """toy_car_004's first drawn label in this pile (seed 16, run 7, attempt 2) holds in the
    lab with the pile present and is missed with the car alone at the same pose, as all 6
    drawn in `oracle-ctr-clutter-bn12/pile_label_check.json` were."""
    result = analysis_script("pile_label_check").check(RECORD, "toy_car_004", 1)
    assert result["true_grasps"] == 79 and result["on_object"] == 36
    assert len(result["checks"]) == 1
    assert result["checks"][0]["neighbours"] == {"held": True, "failure": ""}
    assert result["checks"][0]["alone"]["held"] is False
    assert (result["held_with_neighbours"], result["held_alone"]) == (1, 0)


def test_an_object_not_in_the_pile_is_named_with_the_piles_objects(analysis_script, capsys):
    module = analysis_script("pile_label_check")
    assert module.main([str(RECORD), "nothing_000"]) == 2
    err = capsys.readouterr().err
    assert "object 'nothing_000' not in the pile; it holds ['bottle_004'" in err
    with pytest.raises(SystemExit):
        module.main([str(RECORD), "toy_car_004", "--grasps", "0"])


def test_recorded_pile_reads_a_clutter_attempt_and_names_a_record_without_one(tmp_path):
    import json

    from drake_grasp.evaluation.replay import recorded_pile

    rec, scenario, scene = recorded_pile(RECORD)
    assert rec["trial_id"] == "clutter/ctr/0007/attempt02"
    assert scenario.seed == rec["seed"] and len(scene.objects) == 9
    bare = tmp_path / "r.json"
    bare.write_text(json.dumps({**rec, "extra": {}}))
    with pytest.raises(ValueError, match=r"r\.json: no extra\.scene"):
        recorded_pile(bare)
