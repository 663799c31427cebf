"""The grasp lab's Diagram reused across checks (`GraspLab`): each check runs in a fresh
Context, so a reused Diagram gives what a Diagram built for the check alone gives, bit
for bit; and the shake's segments (`LabConfig.shake_axes`) are judged one by one.

Short phases (about 1.6 s simulated per check) keep these physics tests small."""

import numpy as np
import pytest


def _short(**kw):
    from drake_grasp.evaluation.lab import LabConfig

    base = dict(descend_s=0.3, lift_m=0.08, lift_s=0.3, hold_s=0.05,
                shake_axes=("x", "yaw"))
    base.update(kw)
    return LabConfig(**base)


@pytest.fixture(scope="module")
def can_scene(library):
    from drake_grasp.evaluation.lab import isolated_scene

    return isolated_scene("can_000", library, lying=True)


def _same(a, b):
    """Two results equal in everything but the wall time."""
    da = {k: v for k, v in a.details.items() if k != "wall_s"}
    db = {k: v for k, v in b.details.items() if k != "wall_s"}
    return (a.held, a.failure, da) == (b.held, b.failure, db)


def test_a_reused_diagram_gives_the_fresh_diagrams_results(can_scene, library, across_can):
    """Held, missed, held again, through one GraspLab: each equal to check_grasp's
    (a Diagram of its own), so nothing of one check leaks into the next."""
    from drake_grasp.evaluation.lab import GraspLab, check_grasp

    lab = _short()
    poses = [across_can(can_scene, library), across_can(can_scene, library, offset_m=0.06),
             across_can(can_scene, library)]
    shared = GraspLab(can_scene, library=library, lab=lab)
    reused = [shared.check(X) for X in poses]
    fresh = [check_grasp(None, X, scene=can_scene, library=library, lab=lab) for X in poses]
    assert [r.held for r in reused] == [True, False, True], [r.details for r in reused]
    assert reused[1].failure == "missed"
    for a, b in zip(reused, fresh):
        assert _same(a, b), (a.details, b.details)
    assert _same(reused[0], reused[2])


def test_check_grasps_reuse_and_rebuild_agree(can_scene, library, across_can):
    from drake_grasp.evaluation.lab import check_grasps

    lab = _short(shake_axes=("yaw",))
    poses = np.stack([across_can(can_scene, library).GetAsMatrix4(),
                      across_can(can_scene, library, offset_m=0.06).GetAsMatrix4()])
    reused = check_grasps(None, poses, scene=can_scene, library=library, lab=lab)
    rebuilt = check_grasps(None, poses, scene=can_scene, library=library, lab=lab, reuse=False)
    assert all(_same(a, b) for a, b in zip(reused, rebuilt))


def test_shake_segments_are_judged_in_order_and_end_the_check(can_scene, library, across_can):
    """The shake lasts the listed segments' periods; with none, the check ends after the
    hold."""
    from drake_grasp.evaluation.lab import GraspLab

    X = across_can(can_scene, library)
    one = _short(shake_axes=("yaw",))
    lab = GraspLab(can_scene, library=library, lab=one)
    held = lab.check(X)
    assert held.held, held.details
    assert held.details["shake_pads"] == ["left_finger", "right_finger"]
    expected = held.details["close_end_s"] + one.lift_s + one.hold_s + one.shake_rotation_period_s
    assert held.details["sim_time_s"] == pytest.approx(expected, abs=0.006)
    none = GraspLab(can_scene, library=library, lab=_short(shake_axes=())).check(X)
    assert none.held and none.details["sim_time_s"] == pytest.approx(
        expected - one.shake_rotation_period_s, abs=0.006)


def test_lab_config_and_loaded_objects_are_checked(can_scene, library):
    from drake_grasp.evaluation.lab import GraspLab, LabConfig

    with pytest.raises(ValueError, match="shake_axes"):
        LabConfig(shake_axes=("x", "spin"))
    with pytest.raises(ValueError, match="shake_axes"):
        LabConfig(shake_axes=("x", "x"))
    assert LabConfig(shake_axes=["yaw"]).shake_axes == ("yaw",)
    with pytest.raises(ValueError, match="loaded"):
        GraspLab(can_scene, library=library, loaded=[3])
    lab = GraspLab(can_scene, library=library, lab=_short())
    with pytest.raises(ValueError, match="object_index"):
        lab.check(np.eye(4), object_index=1)
