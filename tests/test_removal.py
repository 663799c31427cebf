"""The clutter-removal protocol (issue: VGN/GIGA/Edge's benchmark): packed scenes, the
round's end when no grasp is found, and its two figures per seed and over seeds."""

import sys
from pathlib import Path

import numpy as np
import pytest

from drake_grasp.evaluation.experiments import EXPERIMENTS
from drake_grasp.evaluation.records import TrialRecord, write_record, write_run_info
from drake_grasp.evaluation.report_stats import clutter_runs
from drake_grasp.evaluation.trial_worker import clutter_run_status
from drake_grasp.policies.decisions import NO_GRASP_FOUND

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "analysis"))


def _attempt(run, a, *, success, reason=None, objects=5, end=None, condition="gpd",
             experiment="removal-pile"):
    placed = [{"object_id": f"o{i}", "xyz": [0.5, 0.0, 0.05], "quat_wxyz": [1.0, 0.0, 0.0, 0.0]}
              for i in range(objects)]
    scene = {"kind": "clutter", "seed": run, "center_xy_m": [0.5, 0.0], "objects": placed}
    nxt = {**scene, "objects": placed[: objects - 1 if success else objects]}
    return TrialRecord(
        trial_id=f"{experiment}/{condition}/{run:04d}/attempt{a:02d}", experiment=experiment,
        condition=condition, policy=condition, noise="none", noise_scale=None, depth_noise=False,
        offset_m=None, disturbance={}, scenario_name="clutter", scenario_yaml="seed: 0\n",
        seed=run, config_hash="abc", code_version="0.1.0", success=success,
        failure_class="none" if success else "missed",
        failure_reason=None if success else (reason or "missed: nothing between the pads"),
        final_distance_m=None, sim_time_s=5.0, wall_time_s=1.0, control_steps=1,
        object_ids=[], grasped_object_id="o0" if success else None, run_index=run,
        attempt_index=a, extra={"scene": scene, "next_scene": nxt,
                                **({"run_end": end} if end else {})})


def test_a_removal_round_ends_when_no_grasp_is_found_and_a_clutter_run_does_not():
    records = [_attempt(0, 0, success=True), _attempt(0, 1, success=False, reason=NO_GRASP_FOUND,
                                                      objects=4)]
    assert clutter_run_status(records, EXPERIMENTS["removal-pile"]) == "no grasp found"
    assert clutter_run_status(records, EXPERIMENTS["clutter"]) is None
    # two failed grasps in a row end a removal round (three a Table 1 clutter run)
    two = [_attempt(0, 0, success=False), _attempt(0, 1, success=False)]
    assert clutter_run_status(two, EXPERIMENTS["removal-packed"]) == "2 consecutive failed grasps"
    assert clutter_run_status(two, EXPERIMENTS["clutter"]) is None


def test_grasp_success_rate_leaves_out_rounds_ends_without_a_grasp_and_percent_cleared_counts_objects():
    # round 0: 3 grasped of 5, then no grasp found; round 1: 1 grasped, 2 failed
    records = ([_attempt(0, a, success=True, objects=5 - a) for a in range(3)]
               + [_attempt(0, 3, success=False, reason=NO_GRASP_FOUND, objects=2)]
               + [_attempt(1, 0, success=True), _attempt(1, 1, success=False, objects=4),
                  _attempt(1, 2, success=False, objects=4)])
    stats = clutter_runs(records)
    assert stats["no_grasp_found"] == 1
    assert stats["grasps_attempted"] == 6
    assert stats["grasp_success_rate"] == pytest.approx(4 / 6)
    assert stats["objects"] == 10 and stats["cleared"] == 4
    assert stats["percent_cleared"] == pytest.approx(40.0)


def test_removal_table_is_the_mean_and_std_over_seed_folders(tmp_path):
    import removal_table

    folders = []
    for seed, grasped in ((100, 5), (101, 3)):
        d = tmp_path / f"seed{seed}"
        write_run_info(d, {"experiment": "removal-pile", "seed": seed})
        for a in range(grasped):
            write_record(d, _attempt(0, a, success=True, objects=5 - a))
        if grasped < 5:
            for a in (grasped, grasped + 1):
                write_record(d, _attempt(0, a, success=False, objects=5 - grasped))
        folders.append(d)
    table = removal_table.removal_table(folders)
    gpd = table["policies"]["gpd"]
    assert [row["gsr_percent"] for row in gpd["per_seed"]] == [100.0, 60.0]
    assert gpd["gsr_mean"] == pytest.approx(80.0)
    assert gpd["gsr_std"] == pytest.approx(np.std([100.0, 60.0], ddof=1))
    assert gpd["cleared_mean"] == pytest.approx(80.0)  # 5/5 and 3/5
    text = removal_table.markdown(table)
    assert "| gpd (this simulator" in text and "80.0 +- 28.3" in text
    assert "Edge Grasp Network" in text
    with pytest.raises(ValueError, match="one removal experiment"):
        write_run_info(tmp_path / "iso", {"experiment": "isolation", "seed": 0})
        write_record(tmp_path / "iso", _attempt(0, 0, success=True, experiment="isolation"))
        removal_table.removal_table([tmp_path / "iso"])


def test_packed_scenes_stand_their_objects_upright_side_by_side(library):
    from drake_grasp.config.sections import SceneConfig
    from drake_grasp.world.scene import sample_scene

    spec = sample_scene(SceneConfig(kind="packed", clutter_objects=5, region_half_extent_m=0.08),
                        3, library)
    assert len(spec.objects) == 5
    for o in spec.objects:
        w, x, y, z = o.quat_wxyz
        assert abs(x) < 1e-9 and abs(y) < 1e-9, o  # a turn about the vertical only
        assert o.xyz[2] < 0.3  # on the sheet, not stacked in a column
    xy = np.array([o.xyz[:2] for o in spec.objects])
    assert np.abs(xy - np.asarray(spec.center_xy_m)).max() < 0.25
