"""The grasp judge: alone (FixValue inputs), in short scripted episodes judged by contact,
and the rule that no policy system reads privileged ports."""

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.multibody.plant import ContactResults
from pydrake.systems.analysis import Simulator

from drake_grasp.evaluation import episode_diagram as episode_diagram_module
from drake_grasp.evaluation.episode import simulate_episode
from drake_grasp.evaluation.records import GRASP_FAILURES
from drake_grasp.config.scenario import load_scenario
from drake_grasp.config.sections import JudgeConfig
from drake_grasp.policies.decisions import SENSOR_POLICIES
from drake_grasp.systems.judge import GraspJudge
from drake_grasp.systems.supervisor import motion_phase_code

# Bodies of the stand-in plant: 0 world, 1 the object, 2 the gripper base, 3-4 the pads.
CUBE = np.random.default_rng(0).uniform(-0.02, 0.02, (200, 3))


def _judge_alone():
    judge = GraspJudge(config=JudgeConfig(), object_bodies=[1], object_ids=["cube"],
                       object_points=[CUBE], gripper_bodies={2: "robotiq_base", 3: "left_finger",
                                                             4: "right_finger"},
                       pad_bodies=[3, 4], grasp_body=2, X_BG=RigidTransform(),
                       geometry_bodies={})
    sim = Simulator(judge)
    ctx = sim.get_mutable_context()
    judge.GetInputPort("contact_results").FixValue(ctx, ContactResults())
    return judge, sim, ctx


def _poses(object_xy, hand_xy=(0.5, 0.0)):
    return [RigidTransform(), RigidTransform([object_xy[0], object_xy[1], 0.02]),
            RigidTransform([hand_xy[0], hand_xy[1], 0.2]), RigidTransform(), RigidTransform()]


def _walk(judge, sim, ctx, phases, poses_at=None):
    """Feeds the motion phases, 0.05 s each; poses_at(phase) -> body poses."""
    t = 0.0
    for phase in phases:
        judge.GetInputPort("control_status").FixValue(ctx, [0.0, 1.0, motion_phase_code(phase)])
        judge.GetInputPort("body_poses").FixValue(ctx, (poses_at or (lambda p: _poses((0.5, 0.0))))(phase))
        t += 0.05
        sim.AdvanceTo(t)
    return judge.GetOutputPort("judgement").Eval(ctx)


def test_judge_alone_says_timeout_until_the_motion_is_done():
    judge, sim, ctx = _judge_alone()
    verdict = _walk(judge, sim, ctx, ["approach", "descend", "close", "lift"])
    assert not verdict.decided and verdict.failure == "timeout"
    assert verdict.reason.startswith("timeout") and "'lift'" in verdict.reason


def test_judge_alone_nothing_between_the_pads_is_missed():
    judge, sim, ctx = _judge_alone()
    verdict = _walk(judge, sim, ctx, ["approach", "descend", "close", "lift", "hold", "done"])
    assert verdict.decided and verdict.attempted and not verdict.success
    assert verdict.failure == "missed" and verdict.reason.startswith("missed")
    assert not verdict.held_after_close
    assert verdict.details["target_object_id"] == "cube"
    assert verdict.details["phase_start_s"]["lift"] > verdict.details["phase_start_s"]["close"]
    assert verdict.failure in GRASP_FAILURES


def test_judge_alone_an_object_moved_before_the_pads_closed_is_pushed_away():
    judge, sim, ctx = _judge_alone()
    # The cube under the hand when the descent starts, 3 cm away when the closing ends.
    moved = {"approach": (0.5, 0.0), "descend": (0.5, 0.0), "close": (0.53, 0.0)}
    verdict = _walk(judge, sim, ctx, ["approach", "descend", "close", "lift", "hold", "done"],
                    lambda p: _poses(moved.get(p, (0.53, 0.0))))
    assert verdict.failure == "pushed-away", verdict.reason
    assert verdict.details["target_push_m"] == pytest.approx(0.03)
    assert "3.0 cm" in verdict.reason


def test_judge_alone_a_policy_that_never_closes_attempted_nothing():
    judge, sim, ctx = _judge_alone()
    verdict = _walk(judge, sim, ctx, ["approach", "done"])
    assert verdict.decided and not verdict.attempted and verdict.failure == "missed"


# -- short physics episodes -----------------------------------------------------------

def _can(extra: str = ""):
    return load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 0, policy: scripted, scene: {object_ids: [can_000], pose: lying}" + extra + "}"))


def _shifted_plan(monkeypatch, d_W):
    """The scripted supervisor's planned grasp shifted by d_W (world)."""
    original = episode_diagram_module.plan_scripted_grasp

    def shifted(scene, library, seed):
        i, P_O, X = original(scene, library, seed)
        X = np.array(X, dtype=float, copy=True)
        X[:3, 3] += np.asarray(d_W, float)
        return i, P_O, X

    monkeypatch.setattr(episode_diagram_module, "plan_scripted_grasp", shifted)


def test_scripted_grasp_of_a_can_is_judged_a_success(library):
    r = simulate_episode(_can(), library=library, record_depth=False).result
    assert r.success, r.failure_reason
    assert r.failure_reason is None and r.details["failure_class"] == "none"
    assert r.details["grasped_object_id"] == "can_000" and r.details["held_after_close"]
    assert r.object_lowest_point_m >= 0.05
    judge = r.details["judge"]
    assert judge["collision"] is None and judge["after_lift"]["both_pads"]
    assert judge["target_push_m"] < 0.02


def test_pad_contacts_and_the_judge_agree_while_the_can_is_held(library):
    """`pad_contacts` (for code holding the plant, e.g. the grasp lab) reads the same
    contacts as the judge's ports: both pads on the can once the closing has ended."""
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.world.scene import make_scene
    from drake_grasp.systems.judge import pad_contacts

    scenario = _can()
    scene = make_scene(scenario.scene, scenario.seed, library, scenario.plant)
    ed = build_episode_diagram(scenario, scene, library)
    sim = Simulator(ed.diagram)
    root = sim.get_mutable_context()
    ed.station.set_initial_state(ed.station.diagram.GetMyMutableContextFromRoot(root))
    sim.AdvanceTo(1.0)  # approaching: nothing touches the can
    plant = ed.station.plant
    plant_context = plant.GetMyContextFromRoot(root)
    can = ed.station.object_body(0)
    assert pad_contacts(plant, plant_context, can) == set()
    sim.AdvanceTo(3.2)  # closed on the can, lifting
    assert ed.policy.mode_name(ed.policy.GetMyContextFromRoot(root)) == "lift"
    assert pad_contacts(plant, plant_context, can) == {"left_finger", "right_finger"}
    history = ed.judge.get_history(ed.judge.GetMyContextFromRoot(root))
    assert history.closed and history.held == 0 and history.phase == "lift"


def test_grasp_beside_the_can_is_missed(library, monkeypatch):
    _shifted_plan(monkeypatch, [0.0, 0.15, 0.0])  # 15 cm beside the can: touches nothing
    r = simulate_episode(_can(), library=library, record_depth=False).result
    assert not r.success
    assert r.details["failure_class"] == "missed", r.failure_reason
    assert r.failure_reason.startswith("missed: no object touched both pads")
    assert not r.details["held_after_close"] and r.details["judge"]["collision"] is None


def test_a_finger_landing_on_the_can_is_a_collision(library, monkeypatch):
    # A finger comes down on the flat top of an upright can. (On a lying can's curved
    # flank the outcome is ill-conditioned: the finger either pins the can or squeezes
    # it out to roll away, which the judge rightly calls pushed-away.)
    _shifted_plan(monkeypatch, [0.05, 0.0, 0.0])
    upright = load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 0, policy: scripted, scene: {object_ids: [can_000], pose: upright}}"))
    r = simulate_episode(upright, library=library, record_depth=False).result
    assert not r.success
    assert r.details["failure_class"] == "collision", r.failure_reason
    hit = r.details["judge"]["collision"]
    assert hit["object_id"] == "can_000" and hit["gripper_body"].endswith("finger")
    assert hit["gripper_bodies"] == [hit["gripper_body"]]  # the other finger lands beside it
    descend, close = (r.details["judge"]["phase_start_s"][p] for p in ("descend", "close"))
    assert descend <= hit["time_s"] < close
    assert r.details["judge"]["target_push_m"] < 0.02  # touched, not pushed away


def test_too_weak_a_grip_slips_during_the_lift(library):
    # 0.5 N per pad with pad friction ~1 holds at most ~0.1 kg; the can weighs 0.33 kg.
    # (At 0.2 N the force-limited fingers close at ~6 mm/s and do not reach the can
    # within the closing time: that is "missed".)
    r = simulate_episode(_can(", gripper: {grip_force_n: 0.5}"), library=library,
                         record_depth=False).result
    assert not r.success
    assert r.details["held_after_close"], "the pads closed on the can before lifting"
    assert r.details["failure_class"] == "slipped-during-lift", r.failure_reason
    assert r.object_lowest_point_m < 0.05


# -- privileged ports -------------------------------------------------------------------

PRIVILEGED = ("body_poses", "contact_results", "plant_state", "query_object")


def _systems_reading(diagram, names=PRIVILEGED) -> set[str]:
    """Names of the episode's top-level systems with an input port of one of `names`."""
    out = set()
    for system in diagram.GetSystems():
        if system.get_name() == "station":
            continue
        for i in range(system.num_input_ports()):
            if system.get_input_port(i).get_name() in names:
                out.add(system.get_name())
    return out


@pytest.mark.parametrize("policy", SENSOR_POLICIES)
def test_no_controller_policy_has_privileged_ports(policy):
    from drake_grasp.world.station import gripper_frame_offsets, topdown_pose
    from drake_grasp.policies.controllers import make_controller

    _, _, X_GC = gripper_frame_offsets()
    scenario = load_scenario(scenario_name="isolation", scenario_text=f"{{policy: {policy}}}")
    ctrl = make_controller(policy, scenario=scenario, X_WG_start=topdown_pose([0.5, 0], 0.2),
                           X_GC=X_GC)
    ports = {ctrl.get_input_port(i).get_name() for i in range(ctrl.num_input_ports())}
    assert not ports & set(PRIVILEGED), ports
    assert ctrl.GetOutputPort("control_status").size() == 3


def test_only_the_judge_reads_privileged_ports_in_the_episode_diagram(library):
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.world.scene import make_scene

    scenario = load_scenario(scenario_name="isolation", scenario_text=(
        "{seed: 0, policy: gpd, scene: {object_ids: [can_000], pose: lying}}"))
    scene = make_scene(scenario.scene, scenario.seed, library, scenario.plant)
    # A stand-in detector: the wiring is under test, not the classifier.
    ed = build_episode_diagram(scenario, scene, library, detect_fn=lambda depth, X_WC: None)
    assert _systems_reading(ed.diagram) == {"judge"}
    assert ed.diagram.GetSubsystemByName("judge") is ed.judge
