"""Bring your own policy: loading MODULE:FACTORY, the port contract, the harness's motion
monitor, and a user policy evaluated next to CTR on the same seeds."""

import sys
import textwrap
from pathlib import Path

import pytest

import drake_grasp.evaluation.montecarlo as m
import drake_grasp.evaluation.trial_worker as trial_worker
from drake_grasp.policies import plugins
from drake_grasp.evaluation.experiments import EXPERIMENTS, Condition, Experiment
from drake_grasp.evaluation.records import GRASP_FAILURES, load_records, read_run_info
from drake_grasp.config.scenario import load_scenario

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
CENTROID = "centroid_policy:make_policy"

# A minimal valid policy; `{extra}` adds lines to its __init__.
_POLICY = """
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem


class Hold(LeafSystem):
    def __init__(self, scenario):
        super().__init__()
        self.DeclareAbstractOutputPort("X_WG_desired", lambda: AbstractValue.Make(RigidTransform()),
                                       lambda c, o: o.set_value(RigidTransform()))
        self.DeclareVectorOutputPort("gripper_command", {width},
                                     lambda c, o: o.SetFromVector(np.zeros({width})))
{extra}

def make(scenario):
    return Hold(scenario)

def make_string(scenario):
    return "not a system"

NOT_CALLABLE = 3
"""


@pytest.fixture
def user_modules(tmp_path, monkeypatch):
    """`write(name, width=2, extra="")`: a policy module `name` on sys.path (both undone
    after the test)."""
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.syspath_prepend(str(tmp_path))
    written = []

    def write(name, width=2, extra=""):
        (tmp_path / f"{name}.py").write_text(_POLICY.format(
            width=width, extra=textwrap.indent(textwrap.dedent(extra), " " * 8)))
        written.append(name)
        return name

    yield write
    for name in written:
        sys.modules.pop(name, None)


def _scenario(policy=CENTROID, text=""):
    return load_scenario(scenario_name="isolation",
                         scenario_text=f"{{policy: {policy!r}{text}}}")


# --------------------------------------------------------------------------- spec and scenario

def test_scenario_accepts_a_spec_and_names_what_is_wrong():
    assert _scenario().policy == CENTROID
    with pytest.raises(ValueError, match=r"policy: got 'ctrl', expected one of .* or MODULE:FACTORY"):
        _scenario("ctrl")
    with pytest.raises(ValueError, match=r"policy 'a:b:c': not a valid user policy spec"):
        _scenario("a:b:c")
    with pytest.raises(ValueError, match=r"noise.kind: got 'gaussian' with the user policy "
                                         r"'centroid_policy:make_policy'; expected 'none'"):
        _scenario(text=", noise: {kind: gaussian}")
    with pytest.raises(ValueError, match=r"target: got 'can_000' with the user policy"):
        _scenario(text=", target: can_000")
    assert plugins.condition_name(CENTROID) == "centroid_policy.make_policy"
    with pytest.raises(ValueError, match=r"'my__mod.f'.*cannot be part of a trial id"):
        plugins.condition_name("my__mod:f")


# --------------------------------------------------------------------------- loading errors

def test_loading_errors_name_the_spec_and_what_was_expected(user_modules, tmp_path):
    with pytest.raises(ValueError, match=r"policy 'no_such_policy_mod:make': no module named "
                                         r"'no_such_policy_mod' on sys.path or in the current "
                                         r"folder .*expected MODULE:FACTORY"):
        plugins.load_policy_factory("no_such_policy_mod:make")
    (tmp_path / "byop_broken.py").write_text("import no_such_dependency_xyz\n")
    with pytest.raises(ValueError, match=r"policy 'byop_broken:make': importing module "
                                         r"'byop_broken' raised ModuleNotFoundError: .*"
                                         r"no_such_dependency_xyz"):
        plugins.load_policy_factory("byop_broken:make")
    sys.modules.pop("byop_broken", None)
    user_modules("byop_ok")
    with pytest.raises(ValueError, match=r"policy 'byop_ok:mkae': module 'byop_ok' \(.*byop_ok.py\) "
                                         r"has no attribute 'mkae'; expected a factory "
                                         r"FACTORY\(scenario\) -> LeafSystem; its callables: .*'make'"):
        plugins.load_policy_factory("byop_ok:mkae")
    with pytest.raises(ValueError, match=r"policy 'byop_ok:NOT_CALLABLE': "
                                         r"byop_ok.NOT_CALLABLE is a int, not callable"):
        plugins.load_policy_factory("byop_ok:NOT_CALLABLE")
    scenario = _scenario()
    with pytest.raises(ValueError, match=r"policy 'byop_ok:make_string': the factory returned a "
                                         r"builtins.str; expected a pydrake LeafSystem"):
        plugins.make_policy_system("byop_ok:make_string", scenario)
    assert plugins.make_policy_system("byop_ok:make", scenario).num_output_ports() == 2


@pytest.mark.parametrize("width,extra,match", [
    (2, 'self.DeclareVectorInputPort("body_poses", 3)',
     r"input port 'body_poses' is privileged .* sensors only: depth_image"),
    (2, 'self.DeclareVectorInputPort("wrist_rgb", 3)',
     r"input port 'wrist_rgb' is not one the harness provides; it connects, by name: depth_image"),
    (2, 'self.DeclareVectorInputPort("depth_image", 3)',
     r"input port 'depth_image' is vector of 3; expected abstract ImageDepth32F"),
    (3, "", r"output port 'gripper_command' is vector of 3; expected a vector of 2: "
            r"\[width_m, grip_force_n\]"),
])
def test_a_system_that_breaks_the_contract_is_refused(user_modules, width, extra, match):
    name = user_modules(f"byop_bad_{width}_{abs(hash(extra)) % 10**6}", width=width, extra=extra)
    with pytest.raises(ValueError, match=rf"policy '{name}:make': {match}"):
        plugins.make_policy_system(f"{name}:make", _scenario())


def test_missing_output_is_refused():
    from pydrake.systems.framework import LeafSystem

    s = LeafSystem()
    s.DeclareVectorOutputPort("gripper_command", 2, lambda c, o: None)
    with pytest.raises(ValueError, match=r"policy 'x:y': the system \(LeafSystem\) has no output "
                                         r"port 'X_WG_desired'; expected X_WG_desired: an abstract "
                                         r"RigidTransform .*it has: \['gripper_command'\]"):
        plugins.check_policy_system(s, "x:y")


def test_a_module_in_the_current_folder_is_found(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    monkeypatch.chdir(tmp_path)
    (tmp_path / "byop_here.py").write_text("def make(scenario):\n    return None\n")
    try:
        assert plugins.load_policy_factory("byop_here:make").__name__ == "make"
        assert sys.path[-1] == str(tmp_path)  # appended last: never shadows installed modules
    finally:
        sys.modules.pop("byop_here", None)


# --------------------------------------------------------------------------- the harness's monitor

def test_monitor_derives_the_phases_from_commands_and_fingers():
    from pydrake.systems.analysis import Simulator

    from drake_grasp.systems.monitor import GraspMotionMonitor
    from drake_grasp.systems.supervisor import MOTION_PHASES

    scenario = _scenario()
    mon = GraspMotionMonitor(scenario=scenario)
    sim = Simulator(mon)
    ctx = sim.get_mutable_context()
    def fix(port, value):
        mon.GetInputPort(port).FixValue(ctx, value)

    fix("gripper_command", [0.085, 60.0])
    fix("gripper_state", [0.0, 0.0, 0.01, 0.01])
    fix("descending", [0.0])

    def phase():
        return MOTION_PHASES[int(mon.GetOutputPort("motion_status").Eval(ctx)[0])]

    sim.AdvanceTo(0.5)
    assert phase() == "approach" and mon.GetOutputPort("control_status").Eval(ctx)[:2].tolist() == [5.0, 1.0]
    fix("descending", [1.0])
    sim.AdvanceTo(0.6)
    assert phase() == "descend"
    fix("descending", [0.0])  # a latch: cannot be withdrawn
    fix("gripper_command", [0.0, 60.0])
    sim.AdvanceTo(0.7)
    assert phase() == "close" and mon.GetOutputPort("control_status").Eval(ctx)[1] == 0.0
    start = mon.GetOutputPort("motion_status").Eval(ctx)[1]
    # The fingers keep moving: the closing lasts `close_time_s`; then the harness's clock.
    m_ = scenario.scripted
    sim.AdvanceTo(start + m_.close_time_s + 0.05)
    assert phase() == "lift"
    sim.AdvanceTo(start + m_.close_time_s + m_.lift_time_s + 0.1)
    assert phase() == "hold" and not mon.is_done(ctx)
    fix("gripper_command", [0.085, 60.0])  # reopening changes nothing
    sim.AdvanceTo(start + m_.close_time_s + m_.lift_time_s + m_.hold_time_s + 0.15)
    assert phase() == "done" and mon.is_done(ctx)


# --------------------------------------------------------------------------- evaluate

@pytest.fixture
def tiny_isolation(monkeypatch):
    monkeypatch.setitem(EXPERIMENTS, "tiny-byop", Experiment(
        name="tiny-byop", scenario="isolation", trials=1, per_object_poses=True,
        description="test", conditions=(Condition("ctr", "ctr"),), controller_profile="robot",
        scenario_text="{max_sim_time_s: 10.0}"))
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.chdir(EXAMPLES)  # `--policy centroid_policy:make_policy` run from examples/
    yield "tiny-byop"
    sys.modules.pop("centroid_policy", None)


def test_centroid_policy_is_evaluated_next_to_ctr_on_the_same_seeds(tiny_isolation, tmp_path):
    out = tmp_path / "byop"
    result = m.evaluate(experiment=tiny_isolation, out=out, trials=2, workers=1, seed=0,
                        progress=False, conditions=["ctr", CENTROID])
    records = load_records(out)
    assert {r.condition for r in records} == {"ctr", "centroid_policy.make_policy"}
    seeds = {}
    for r in records:
        seeds.setdefault(r.condition, {})[r.trial_id.rsplit("/", 1)[1]] = (r.seed, r.object_ids)
    assert seeds["ctr"] == seeds["centroid_policy.make_policy"] and len(seeds["ctr"]) == 2
    mine = [r for r in records if r.condition == "centroid_policy.make_policy"]
    for r in mine:
        assert r.policy == CENTROID
        assert r.success or r.failure_class in GRASP_FAILURES
        assert r.failure_class != "simulation-error", r.failure_reason
        assert r.extra["policy_inputs"] == ["X_GC", "X_WG_start", "depth_image", "motion_status"]
    policies = result["summary"]["policies"]
    assert set(policies) == {"ctr", "centroid_policy.make_policy"}
    assert policies["centroid_policy.make_policy"]["trials"] == 2
    report = (out / "report.md").read_text()
    assert "user policy `centroid_policy:make_policy`" in report
    info = read_run_info(out)
    source = info["plugin_conditions"]["centroid_policy.make_policy"]["policy_source"]
    assert source["module"] == "centroid_policy" and len(source["sha256"]) == 64


def test_user_policy_resume_and_refusals(user_modules, tmp_path, monkeypatch):
    def no_physics(*args, **kwargs):
        raise RuntimeError("no physics here (test)")

    monkeypatch.setattr(trial_worker, "_simulate", no_physics)
    name = user_modules("byop_resume")
    kw = dict(experiment="smoke", out=tmp_path / "run", trials=1, workers=1, seed=3,
              progress=False, report=False)
    first = m.evaluate(conditions=["init", f"{name}:make"], **kw)
    assert first["ran"] == 2
    # a resume may leave the user policy out, or bring it back unchanged
    assert m.evaluate(conditions=["init"], **kw)["ran"] == 0
    assert m.evaluate(conditions=[f"{name}:make"], **kw)["ran"] == 0
    # an edited policy file is another run
    path = tmp_path / f"{name}.py"
    path.write_text(path.read_text() + "\n# edited\n")
    with pytest.raises(ValueError, match=rf"plugin_conditions.{name}.make.policy_source.sha256: "
                                         r".* in the folder, .* now.*--force-new"):
        m.evaluate(conditions=[f"{name}:make"], **kw)
    # a broken policy fails before any trial runs
    with pytest.raises(ValueError, match=rf"policy '{name}:make_string': the factory returned"):
        m.evaluate(conditions=[f"{name}:make_string"], experiment="smoke",
                   out=tmp_path / "other", trials=1, workers=1, seed=3, progress=False)
    assert not (tmp_path / "other" / "trials").exists()
    with pytest.raises(ValueError, match=r"--conditions: \['nope'\] not in experiment smoke.*"
                                         r"or a user policy MODULE:FACTORY"):
        m.evaluate(conditions=["nope"], **kw)


def test_episode_diagram_wires_a_user_policy(library, monkeypatch):
    from drake_grasp.evaluation.episode_diagram import build_episode_diagram
    from drake_grasp.world.scene import make_scene

    monkeypatch.syspath_prepend(str(EXAMPLES))
    scenario = load_scenario(scenario_name="clutter_shift", scenario_text=(
        f"{{seed: 5, policy: {CENTROID!r}, scene: {{kind: isolation, object_ids: [can_000], "
        "pose: lying}}"))
    scene = make_scene(scenario.scene, scenario.seed, library, physics=scenario.physics)
    try:
        ed = build_episode_diagram(scenario, scene, library)
    finally:
        sys.modules.pop("centroid_policy", None)
    names = {s.get_name() for s in ed.diagram.GetSystems()}
    assert {"user_policy", "motion_monitor", "judge", "sheet_disturbance",
            "user_policy_X_WG_start", "user_policy_X_GC"} <= names
    assert ed.policy.get_name() == "motion_monitor" and ed.disturbance is not None
    assert ed.user_policy_inputs == ["X_GC", "X_WG_start", "depth_image", "motion_status"]
    # the judge and the disturbance read the harness's phase, not the policy's
    feeds = {(dst.get_name(), dst.get_input_port(i).get_name()):
             (src.get_name(), src.get_output_port(j).get_name())
             for (dst, i), (src, j) in ed.diagram.connection_map().items()}
    assert feeds[("judge", "control_status")] == ("motion_monitor", "control_status")
    assert feeds[("sheet_disturbance", "control_status")] == ("motion_monitor", "control_status")
    assert feeds[("motion_monitor", "descending")] == ("user_policy", "descending")
    assert feeds[("user_policy", "depth_image")] == ("station", "depth_image")
    assert feeds[("station", "X_WG_desired")] == ("user_policy", "X_WG_desired")
    assert {src for (dst, _), (src, _) in feeds.items() if dst == "user_policy"} == {
        "station", "motion_monitor", "user_policy_X_WG_start", "user_policy_X_GC"}
