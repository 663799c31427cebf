"""Bring your own policy: the contract between a user's policy system and the harness.

A user policy is named by a spec string ``MODULE:FACTORY`` (the scenario's `policy` key,
`drake-grasp demo --policy`, `drake-grasp evaluate --conditions`). ``MODULE`` is a module
name importable from `sys.path`, or a module file ``MODULE.py`` in the current working
directory (searched last, so it never shadows an installed module); ``FACTORY`` is a
callable in it (a dotted attribute path is allowed). The harness calls
``FACTORY(scenario)`` with the trial's `drake_grasp.config.scenario.Scenario` (seed, camera,
gripper, timing of the grasp motion, ...) once per episode; it returns a pydrake
`LeafSystem` (or a `Diagram` exporting the same ports). Randomness inside it must come
from ``scenario.seed``, so that a trial replays bit for bit.

Input ports: the harness connects each one the system declares, by name; it declares only
what it needs. Policies see sensors only: a name that is not below is an error, and the
privileged outputs of the station (object poses, label images, contacts, the noise-free
depth) are refused by name.

=================  ==========================================================================
name               what the harness connects
=================  ==========================================================================
depth_image        AbstractValue `ImageDepth32F`: the post-processed wrist depth image
                   (`camera.width` x `camera.height`, 64x64 by default; depth along the
                   camera's optical axis in m, with the scenario's depth noise and hole
                   filling; every pixel finite: far or unfillable pixels read
                   `camera.depth_max_m`). Pinhole, principal point at the image centre
                   ((W - 1) / 2, (H - 1) / 2), vertical field of view `camera.fov_y_deg`.
                   The camera looks along the grasp frame's z_G; its pose in the grasp
                   frame is `X_GC`.
gpd_depth_image    AbstractValue `ImageDepth32F`: the GPD baseline's wrist sensor
                   (`scenario.gpd`, 640x480; its pose in the grasp frame is
                   `drake_grasp.world.station.gpd_camera_offset()`). It renders only when the
                   policy evaluates it (costly: evaluate it rarely).
gripper_state      vector of 4: [q_left, q_right, v_left, v_right] of the 2F-85's fingers
                   [m, m/s]; the opening is q_left + q_right.
motion_status      vector of 3: [motion phase, phase start time [s], control step], from the
                   harness's `GraspMotionMonitor`: the phase of the grasp motion as the
                   harness judges it (an index into `MOTION_PHASES`: 0 approach, 1 descend,
                   2 close, 3 lift, 4 hold, 5 done), when that phase began, and the number
                   of `controller.period_s` periods since t = 0. Simulation time is the
                   policy's own `context.get_time()`.
X_WG_start         AbstractValue `RigidTransform`: the grasp frame's pose at t = 0 (top-down,
                   over the scene centre, the wrist camera `arm.start_camera_height_m`
                   above the table, raised over what the wrist camera's survey image
                   shows standing taller: `world.station.survey_top_z`). Constant.
X_GC               AbstractValue `RigidTransform`: the wrist camera in the grasp frame (the
                   gripper model's `camera_mount`). Constant.
=================  ==========================================================================

Output ports:

=================  ==========================================================================
name               meaning
=================  ==========================================================================
X_WG_desired       required; AbstractValue `RigidTransform`: the desired pose of the grasp
                   frame G in the world (between the pads; z_G the approach direction, x_G
                   the closing direction), tracked by the station's differential IK
                   (speed-limited: `arm.max_tcp_speed_m_s`).
gripper_command    required; vector of 2: [width_m, grip_force_n]: the commanded opening
                   (0 to 0.085 m) and the force per pad [N] (`gripper.grip_force_n` is what
                   the built-in policies use). Commanding a width of at most
                   `CLOSE_WIDTH_M` (1 mm; command 0) is closing the gripper on the grasp:
                   it starts the harness's close phase. Wider commands are a pre-shape.
descending         optional; vector of 1: > 0.5 from the moment the policy starts its final
                   descent onto the grasp (read as a latch: it cannot be withdrawn). Without
                   this port the whole approach counts as the descent (see below).
=================  ==========================================================================

What the harness keeps (`drake_grasp.evaluation.episode`): the station, the recording, the seeds and
the `GraspJudge`. The judge reads the motion phase from the harness's
`GraspMotionMonitor` (`drake_grasp.systems.monitor`), never from the policy, with the rules
the built-in policies follow: approach; descend from the policy's `descending` latch (from
t = 0 without that port: every gripper contact before the closing is then judged a
descent contact, and the object pushed is the one nearest the grasp axis at t = 0 -
stricter, never laxer); close from the first command of width <= `CLOSE_WIDTH_M` until the
fingers have stopped (after 0.3 s) or `scripted.close_time_s`; then lift for
`scripted.lift_time_s`, hold for `scripted.hold_time_s`, done. The policy must lift during
the lift phase (the judge wants the object's lowest point `judge.min_lift_m` above the
table at the end of the lift and of the hold; a policy that does not lift fails
"slipped-during-lift", as a built-in whose object stayed behind) and keep the gripper
closed. One grasp per episode: once the closing starts the timeline is the harness's. An
episode whose policy never closes ends at `max_sim_time_s` as a "timeout". Success and the
failure classes (`drake_grasp.evaluation.records.GRASP_FAILURES`) mean what they mean for the built-in
policies.

Not applied to a user policy: the kinematic noise models (`noise.kind` must be "none": the
`KinematicNoise` system reads each commanded move's goal from the built-in controller's
`X_WG_goal` port) and target-object mode (`target` must be ""; it acts inside the
built-in controller).
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

from drake_grasp.config.policy_spec import (  # the contract, re-exported for policy authors
    _EXPECTED, CLOSE_WIDTH_M, INPUT_PORTS, OPTIONAL_OUTPUTS, PRIVILEGED_PORTS, REQUIRED_OUTPUTS,
    SPEC_RE, is_policy_spec, parse_policy_spec)


def condition_name(spec: str) -> str:
    """The experiment condition (and trial-id component) a spec runs as: the spec with
    ":" replaced by "." ("centroid_policy:make_policy" -> "centroid_policy.make_policy"),
    since trial ids are file names.

    Raises:
        ValueError: the spec is malformed, or its name cannot be a trial-id component
            (no "__", no leading or trailing "_").
    """
    module, factory = parse_policy_spec(spec)
    name = f"{module}.{factory}"
    if "__" in name or name.startswith("_") or name.endswith("_"):
        raise ValueError(f"policy {spec!r}: as an evaluate condition it is named {name!r}, "
                         "which cannot be part of a trial id (file name): no '__', no "
                         "leading or trailing '_'; rename the module or factory")
    return name


def _try_import(module: str, spec: str):
    """The module, or None when the module itself (or its package) is not found; any other
    error of the user's module becomes a ValueError naming the spec."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        # Only a missing MODULE itself falls back to the current folder; a module that
        # exists but fails to import one of its own imports is reported as is.
        if e.name is None or not (module == e.name or module.startswith(e.name + ".")):
            raise ValueError(f"policy {spec!r}: importing module {module!r} raised "
                             f"ModuleNotFoundError: {e}") from e
        return None
    except Exception as e:  # noqa: BLE001 - any error in the user's module, with its spec
        raise ValueError(f"policy {spec!r}: importing module {module!r} raised "
                         f"{type(e).__name__}: {e}") from e


def _import(module: str, spec: str):
    """`module`, from sys.path or else from the current folder."""
    found = _try_import(module, spec)
    if found is not None:
        return found
    cwd = os.getcwd()
    searched = [p for p in sys.path if p]
    if cwd not in sys.path and "" not in sys.path:
        # Last on the path: a file in the current folder never shadows an installed module.
        # Kept there, so the module's own sibling imports (and spawned workers) find it.
        sys.path.append(cwd)
        importlib.invalidate_caches()
        found = _try_import(module, spec)
        if found is not None:
            return found
    raise ValueError(f"policy {spec!r}: no module named {module!r} on sys.path or in the "
                     f"current folder ({cwd}; {len(searched)} sys.path entries searched); "
                     f"{_EXPECTED}")


def load_policy_factory(spec: str):
    """The factory a ``MODULE:FACTORY`` spec names (the module is imported).

    Raises:
        ValueError: malformed spec, module not found or raising on import, attribute
            missing, or not callable; each message names the spec and what was expected.
    """
    module_name, factory_path = parse_policy_spec(spec)
    obj = _import(module_name, spec)
    where = f"module {module_name!r} ({getattr(obj, '__file__', None) or 'built-in'})"
    for part in factory_path.split("."):
        if not hasattr(obj, part):
            names = sorted(n for n in dir(obj) if not n.startswith("_") and callable(getattr(obj, n, None)))
            raise ValueError(f"policy {spec!r}: {where} has no attribute {factory_path!r}; "
                             f"expected a factory FACTORY(scenario) -> LeafSystem; its "
                             f"callables: {names[:20]}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ValueError(f"policy {spec!r}: {module_name}.{factory_path} is a "
                         f"{type(obj).__name__}, not callable; expected a factory "
                         "FACTORY(scenario) -> LeafSystem")
    return obj


def policy_source(spec: str) -> dict:
    """What identifies a user policy's code in a run's identity: its module and the sha256
    of the module's file (None for a module without a file). Only that file: modules it
    imports are not covered."""
    from drake_grasp.core.provenance import file_sha256

    module_name, _ = parse_policy_spec(spec)
    load_policy_factory(spec)
    path = getattr(sys.modules[module_name], "__file__", None)
    return {"module": module_name,
            "sha256": file_sha256(path) if path and Path(path).is_file() else None}


def _port_kind(port) -> str:
    from pydrake.systems.framework import PortDataType

    if port.get_data_type() == PortDataType.kVectorValued:
        return f"vector of {port.size()}"
    return "abstract"


def _abstract_type(system, port, *, output: bool):
    """The Python type a port's abstract value holds (None when it cannot be told)."""
    try:
        if output:
            value = port.Allocate()
        else:
            value = system.AllocateInputAbstract(port)
        return type(value.get_value())
    except Exception:  # noqa: BLE001 - a port whose model value cannot be read
        return None


def check_policy_system(system, spec: str) -> None:
    """Checks a user policy system against the contract (module docstring).

    Raises:
        ValueError: not a LeafSystem / Diagram, a required output missing or of the wrong
            kind, an input the harness does not provide (privileged ones named as such) or
            of the wrong kind; the message names the spec, the port and what was expected.
    """
    from pydrake.math import RigidTransform
    from pydrake.systems.framework import Diagram, LeafSystem, PortDataType
    from pydrake.systems.sensors import ImageDepth32F

    if not isinstance(system, (LeafSystem, Diagram)):
        raise ValueError(f"policy {spec!r}: the factory returned a {type(system).__module__}."
                         f"{type(system).__name__}; expected a pydrake LeafSystem (or Diagram) "
                         f"with output ports {', '.join(REQUIRED_OUTPUTS)} "
                         "(see drake_grasp.policies.plugins)")
    outputs = {system.get_output_port(i).get_name(): system.get_output_port(i)
               for i in range(system.num_output_ports())}
    inputs = {system.get_input_port(i).get_name(): system.get_input_port(i)
              for i in range(system.num_input_ports())}
    need = {"X_WG_desired": ("abstract", RigidTransform),
            "gripper_command": ("vector of 2", None),
            "descending": ("vector of 1", None)}
    what = {"X_WG_desired": "an abstract RigidTransform (grasp frame in the world)",
            "gripper_command": "a vector of 2: [width_m, grip_force_n]",
            "descending": "a vector of 1 (> 0.5 once the final descent starts)"}
    for name in REQUIRED_OUTPUTS:
        if name not in outputs:
            raise ValueError(f"policy {spec!r}: the system ({type(system).__name__}) has no "
                             f"output port {name!r}; expected {name}: {what[name]}; required "
                             f"outputs: {', '.join(REQUIRED_OUTPUTS)}; it has: {sorted(outputs)}")
    for name in REQUIRED_OUTPUTS + OPTIONAL_OUTPUTS:
        if name not in outputs:
            continue
        kind, cls = need[name]
        port = outputs[name]
        got = _port_kind(port)
        if got != kind or (cls is not None and
                           _abstract_type(system, port, output=True) not in (cls, None)):
            held = _abstract_type(system, port, output=True) if got == "abstract" else None
            raise ValueError(f"policy {spec!r}: output port {name!r} is {got}"
                             f"{'' if held is None else f' ({held.__name__})'}"
                             f"; expected {what[name]}")
    image = ("abstract", ImageDepth32F, "ImageDepth32F")
    pose = ("abstract", RigidTransform, "RigidTransform")
    want_in = {"depth_image": image, "gpd_depth_image": image,
               "gripper_state": ("vector of 4", None, ""), "motion_status": ("vector of 3", None, ""),
               "X_WG_start": pose, "X_GC": pose}
    for name, port in inputs.items():
        if name in PRIVILEGED_PORTS:
            raise ValueError(f"policy {spec!r}: input port {name!r} is privileged (the grasp "
                             "judge's, or noise-free truth); a policy sees sensors only: "
                             f"{', '.join(INPUT_PORTS)}")
        if name not in want_in:
            raise ValueError(f"policy {spec!r}: input port {name!r} is not one the harness "
                             f"provides; it connects, by name: {', '.join(INPUT_PORTS)}")
        kind, cls, cls_name = want_in[name]
        got = _port_kind(port)
        held = (_abstract_type(system, port, output=False)
                if port.get_data_type() == PortDataType.kAbstractValued else None)
        if got != kind or (cls is not None and held not in (cls, None)):
            if held is not None:
                got += f" ({held.__name__})"
            raise ValueError(f"policy {spec!r}: input port {name!r} is {got}; expected "
                             f"{kind}{' ' + cls_name if cls_name else ''}")


def make_policy_system(spec: str, scenario):
    """Loads the factory of `spec`, calls it with `scenario` and checks the system
    (`check_policy_system`).

    Raises:
        ValueError: see `load_policy_factory`, `check_policy_system`; and when the factory
            itself raises (the message names the spec; the original error is chained).
    """
    factory = load_policy_factory(spec)
    try:
        system = factory(scenario)
    except Exception as e:  # noqa: BLE001 - the user's code: say whose it was
        raise ValueError(f"policy {spec!r}: {spec.split(':', 1)[1]}(scenario) raised "
                         f"{type(e).__name__}: {e}") from e
    check_policy_system(system, spec)
    return system


__all__ = ["CLOSE_WIDTH_M", "INPUT_PORTS", "OPTIONAL_OUTPUTS", "PRIVILEGED_PORTS",
           "REQUIRED_OUTPUTS", "check_policy_system", "condition_name", "is_policy_spec",
           "load_policy_factory", "make_policy_system", "parse_policy_spec", "policy_source"]
