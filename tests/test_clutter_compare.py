"""analysis/clutter_compare.py: grasps, repeated failures on an unmoved pile, objects
left, and agreement up to the first failure, from two folders of clutter records."""


from drake_grasp.evaluation.records import write_record
from test_results import make_record



def _pile(xs):
    return {"objects": [{"object_id": f"o{i}", "xyz": [x, 0.0, 0.03]} for i, x in enumerate(xs)]}


def _write(folder, outcomes):
    """One ctr run: each outcome (success, how far object o0 moved [m], grasped id)."""
    xs = [0.5, 0.6, 0.7]
    for k, (ok, moved, grasped) in enumerate(outcomes):
        after = [x + (moved if i == 0 else 0.0) for i, x in enumerate(xs)]
        if ok:
            after = [x for i, x in enumerate(after) if f"o{i}" != grasped]
        write_record(folder, make_record(
            trial_id=f"clutter/ctr/0000/attempt{k:02d}", experiment="clutter", condition="ctr",
            success=ok, failure_class="none" if ok else "missed",
            grasped_object_id=grasped if ok else None, run_index=0, attempt_index=k,
            extra={"scene": _pile(xs), "next_scene": _pile(after)}))
        xs = after


def test_counts_repeats_on_an_unmoved_pile_and_the_agreement(tmp_path, analysis_script):
    C = analysis_script("clutter_compare")
    a, b = tmp_path / "a", tmp_path / "b"
    # a: grasp o2, fail (pile still), fail (o0 pushed 3 cm), fail: one repeat on a still pile.
    _write(a, [(True, 0.0, "o2"), (False, 0.0, None), (False, 0.03, None), (False, 0.0, None)])
    # b: the same first two attempts, then three grasps.
    _write(b, [(True, 0.0, "o2"), (False, 0.0, None), (True, 0.0, "o1"), (True, 0.0, "o0")])
    ra, rb = C.runs_of(a), C.runs_of(b)
    sa, sb = C.summary(ra, "ctr"), C.summary(rb, "ctr")
    assert (sa["attempts"], sa["grasped"], sa["repeated_failures"], sa["objects_left"]) == (4, 1, 1, 2)
    assert (sb["attempts"], sb["grasped"], sb["repeated_failures"], sb["objects_left"]) == (4, 3, 0, 0)
    assert sa["failure_classes"] == {"missed": 3}
    assert C.agree_until_first_failure(ra, rb, "ctr") == {"runs": 1, "agree": 1}
    _write(tmp_path / "c", [(True, 0.0, "o1")])  # grasps another object first
    assert C.agree_until_first_failure(ra, C.runs_of(tmp_path / "c"), "ctr") == {"runs": 1,
                                                                                  "agree": 0}
