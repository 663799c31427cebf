"""The station side of a split episode: `make_remote_controller`, the LeafSystem that
stands in for the controller Diagram in the station process (its ports as the controller's,
one tick per periodic event of the controller side: it sends the arm and gripper status,
serves the image requests, and takes the commands and the control status the tick
answers), `RemoteReply` (its abstract state), the task handshake (`_send_task`) and
`build_station_side` (the station, the proxy, the sheet command and the judge in one
Diagram).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from drake_grasp.evaluation.bridge_protocol import (ARM_COMMAND, ARM_STATUS, CONTROL_STATUS,
                                                    GRIPPER_COMMAND, GRIPPER_STATUS,
                                                    IMAGE_CHANNELS, PROTOCOL_VERSION, BridgeError,
                                                    BridgeLink, _need, _pose_list,
                                                    check_bridge_scenario, decode_arm_command,
                                                    decode_control_status, decode_gripper_command,
                                                    encode_image, encode_joint_status)

# --- station side -------------------------------------------------------------------


@dataclass(frozen=True)
class RemoteReply:
    """What the station knows of the controller after tick `version` (the proxy's
    abstract state). `version` -1: before the first tick."""

    version: int = -1
    t: float = math.nan
    arm_prev: tuple = ()   # joint command in force before this tick (the IK's previous state)
    arm: tuple = ()        # joint command after it
    gripper: tuple = ()    # [width_m, grip_force_n] at t, after the tick
    status: tuple = ()     # control status at t, after the tick
    mode: str = ""
    done: bool = False
    outcome: dict = field(default_factory=dict)
    decision_time_s: float = 0.0
    decisions: int = 0
    # The iteration of the policy's last control step (None before its first).
    last_iteration: int | None = None

    @property
    def last_step(self):
        """The last control step as far as the station knows it: its iteration only (its
        images and candidates stay in the controller process)."""
        return None if self.last_iteration is None else RemoteStep(self.last_iteration)


@dataclass(frozen=True)
class RemoteStep:
    iteration: int


def make_remote_controller(link: BridgeLink, *, periods: list, q_initial, initial: dict):
    """The station side's stand-in for the controller Diagram (a LeafSystem).

    Input ports:
        depth_image, label_image, gpd_depth_image: the images the policy may ask for
            (sent only on request, evaluated in the tick's pre-update Context).
        gripper_state: [q_left, q_right, v_left, v_right] -> `ROBOTIQ_2F85_STATUS`.
        arm_state: UR5 [q, v] -> `UR5_STATUS`.
    Output ports:
        arm_position_command: the UR5 joint positions (`UR5_COMMAND`).
        gripper_command: [width_m, grip_force_n] (`ROBOTIQ_2F85_COMMAND`).
        control_status: [control step, approaching, motion phase] (`CONTROL_STATUS`).
    State:
        abstract `RemoteReply`.

    Args:
        link: the connection to the controller process (after the task handshake).
        periods: [(period_s, offset_s)] of the controller side's periodic events; one
            tick at each of their times.
        q_initial: the joint command before the first tick (the start configuration).
        initial: the controller's state before the first tick: {"mode", "done"}.
    """
    from pydrake.systems.framework import LeafSystem

    class _RemoteController(LeafSystem):
        def __init__(self):
            super().__init__()
            self._link = link
            _declare_remote_ports(self, periods=periods, q_initial=q_initial, initial=initial)

        # -- what the episode runner asks a policy ------------------------------------
        def reply(self, context) -> RemoteReply:
            return context.get_abstract_state(self._state).get_value()

        def is_done(self, context) -> bool:
            return self.reply(context).done

        def mode_name(self, context) -> str:
            return self.reply(context).mode

        def outcome(self, context) -> dict:
            return dict(self.reply(context).outcome)

        def get_controller_state(self, context) -> RemoteReply:
            """What the episode runner counts control steps with (`last_step`)."""
            return self.reply(context)

        # -- the tick -----------------------------------------------------------------
        def _Tick(self, context, state):
            _remote_tick(self, context, state)

        # -- outputs ------------------------------------------------------------------
        def _CalcRemote(self, context, value):
            """The controller's gripper command and status at a time other than the
            last tick's: asked for by time and version."""
            r = self.reply(context)
            t = context.get_time()
            self._link.send_bundle("BRIDGE_EVAL", {"version": r.version, "t": t})
            body, got = self._link.expect("BRIDGE_EVAL_DONE")
            value.set_value((decode_gripper_command(_need(got, GRIPPER_COMMAND, "evaluation")),
                             decode_control_status(_need(got, CONTROL_STATUS, "evaluation"))))

        def _at_tick(self, context) -> bool:
            return context.get_time() == self.reply(context).t

        def _CalcArm(self, context, output):
            r = self.reply(context)
            # At the tick's own time the IK's update of that time has not yet been seen
            # by the station's discrete systems (they update alongside it).
            output.SetFromVector(r.arm_prev if self._at_tick(context) else r.arm)

        def _CalcGripper(self, context, output):
            if self._at_tick(context):
                output.SetFromVector(self.reply(context).gripper)
            else:
                output.SetFromVector(self._remote.Eval(context)[0])

        def _CalcStatus(self, context, output):
            if self._at_tick(context):
                output.SetFromVector(self.reply(context).status)
            else:
                output.SetFromVector(self._remote.Eval(context)[1])

    return _RemoteController()


def _declare_remote_ports(system, *, periods, q_initial, initial) -> None:
    """Declares the remote controller's input ports, its `RemoteReply` state (from
    `q_initial` and `initial`), one periodic tick per entry of `periods`, the cache entry
    of its remotely evaluated outputs and its output ports, in this order, on `system`."""
    from pydrake.common.value import AbstractValue
    from pydrake.systems.framework import ValueProducer
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    system._images = {
        "depth_image": system.DeclareAbstractInputPort(
            "depth_image", AbstractValue.Make(ImageDepth32F())),
        "label_image": system.DeclareAbstractInputPort(
            "label_image", AbstractValue.Make(ImageLabel16I())),
        "gpd_depth_image": system.DeclareAbstractInputPort(
            "gpd_depth_image", AbstractValue.Make(ImageDepth32F())),
    }
    system._gripper_state = system.DeclareVectorInputPort("gripper_state", 4)
    system._arm_state = system.DeclareVectorInputPort("arm_state", 12)
    system._state = system.DeclareAbstractState(AbstractValue.Make(RemoteReply(
        arm=tuple(float(x) for x in q_initial), mode=initial["mode"],
        done=bool(initial["done"]))))
    for period, offset in periods:
        system.DeclarePeriodicUnrestrictedUpdateEvent(float(period), float(offset), system._Tick)
    deps = {system.abstract_state_ticket(system._state), system.time_ticket()}
    system._remote = system.DeclareCacheEntry(
        "the controller's outputs at this time (asked for remotely)",
        ValueProducer(allocate=lambda: AbstractValue.Make((np.zeros(2), np.zeros(3))),
                      calc=system._CalcRemote), deps)
    system.DeclareVectorOutputPort("arm_position_command", 6, system._CalcArm, deps)
    system.DeclareVectorOutputPort("gripper_command", 2, system._CalcGripper, deps)
    system.DeclareVectorOutputPort("control_status", 3, system._CalcStatus, deps)


def _remote_tick(system, context, state) -> None:
    """One tick of the remote controller: sends the arm and gripper status of this time,
    serves the controller's image requests until it answers, and stores its answer as the
    new `RemoteReply` (once per time: two periods falling on one time make one tick)."""
    t = context.get_time()
    old = system.reply(context)
    if state.get_abstract_state(int(system._state)).get_value().t == t:
        return  # two of the controller's periods fall on this time: one tick
    arm = system._arm_state.Eval(context)
    fingers = system._gripper_state.Eval(context)
    # Each finger's commanded position: half the commanded opening.
    q_fingers = [0.5 * old.gripper[0]] * 2 if old.gripper else [math.nan] * 2
    frames = [(ARM_STATUS, encode_joint_status(t, arm[:6], arm[6:], old.arm)),
              (GRIPPER_STATUS, encode_joint_status(t, fingers[:2], fingers[2:], q_fingers))]
    version = old.version + 1
    system._link.send_bundle("BRIDGE_TICK", {"version": version, "t": t}, frames)
    body, got = _serve_images_until_tick_done(system, context, t, version)
    if body.get("version") != version or body.get("t") != t:
        raise BridgeError(f"{system._link.peer} answered tick {body.get('version')} at "
                          f"t = {body.get('t')!r}; expected tick {version} at t = {t!r}")
    state.get_mutable_abstract_state(int(system._state)).set_value(
        _tick_reply(old, version, t, body, got))


def _serve_images_until_tick_done(system, context, t: float, version: int) -> tuple:
    """Answers the controller's image requests of tick `version` (each image evaluated in
    the tick's Context) until its BRIDGE_TICK_DONE; returns that message's (body, frames)."""
    while True:
        control, body, got = system._link.recv_bundle()
        if control == "BRIDGE_IMAGE_REQUEST":
            name = body.get("port")
            if name not in system._images:
                raise BridgeError(f"the controller asked for image {name!r}; the station "
                                  f"sends {sorted(system._images)}")
            image = system._images[name].Eval(context)
            system._link.send_bundle("BRIDGE_IMAGE", {"port": name}, [
                (IMAGE_CHANNELS[name], encode_image(t, image, name))])
        elif control == "BRIDGE_TICK_DONE":
            break
        else:
            raise BridgeError(f"{system._link.peer} sent {control} during tick {version}")
    return body, got


def _tick_reply(old: RemoteReply, version: int, t: float, body: dict, got: dict) -> RemoteReply:
    """The `RemoteReply` after tick `version`, from the controller's BRIDGE_TICK_DONE."""
    return RemoteReply(
        version=version, t=t, arm_prev=old.arm,
        arm=tuple(decode_arm_command(_need(got, ARM_COMMAND, "tick reply"))),
        gripper=tuple(decode_gripper_command(_need(got, GRIPPER_COMMAND, "tick reply"))),
        status=tuple(decode_control_status(_need(got, CONTROL_STATUS, "tick reply"))),
        mode=str(body["mode"]), done=bool(body["done"]), outcome=dict(body["outcome"]),
        decision_time_s=float(body.get("decision_time_s", 0.0)),
        decisions=int(body.get("decisions", 0)),
        last_iteration=body.get("last_iteration"))


def _send_task(link: BridgeLink, scenario, station, target_label) -> dict:
    """The task handshake: the scenario and what the policy believes of the cell; returns
    the controller's READY body (its periodic events, its initial mode)."""
    from drake_grasp.config.scenario import dump_scenario

    link.send_bundle("BRIDGE_TASK", {
        "protocol": PROTOCOL_VERSION, "scenario_yaml": dump_scenario(scenario),
        "X_WG_start": _pose_list(station.X_WG_start), "X_GC": _pose_list(station.X_GC),
        "X_GC_gpd": _pose_list(station.X_GC_gpd), "target_label": target_label})
    body, _ = link.expect("BRIDGE_READY")
    if body.get("protocol") != PROTOCOL_VERSION:
        raise BridgeError(f"{link.peer} speaks protocol {body.get('protocol')}, this station "
                          f"{PROTOCOL_VERSION}")
    return body


def build_station_side(scenario, scene, library, link: BridgeLink):
    """The station process's Diagram: the station (joint-command arm input), the proxy
    of the controller ("remote_controller"), the sheet command and the judge. Does the
    task handshake on `link`. Returns an `episode_diagram.EpisodeDiagram`."""
    from pydrake.systems.framework import DiagramBuilder

    from drake_grasp.evaluation.episode_diagram import (
        EpisodeDiagram,
        _add_judge,
        _drive_sheet,
        policy_image_ports,
        target_object,
    )
    from drake_grasp.world.station import MakeGraspStation

    check_bridge_scenario(scenario)
    if not scene.objects:
        raise ValueError("scene has no objects on the table (all fell off while settling?)")
    station = MakeGraspStation(scenario, scene, library, arm_input="arm_position_command")
    target, target_label = target_object(scenario, scene, station)
    ready = _send_task(link, scenario, station, target_label)
    builder = DiagramBuilder()
    sd = builder.AddNamedSystem("station", station.diagram)
    proxy = builder.AddNamedSystem("remote_controller", make_remote_controller(
        link, periods=ready["periods"], q_initial=station.q_start, initial=ready))
    # The policy's images as in process: through the timing's frame buffers where the
    # scenario has them.
    ports = policy_image_ports(builder, scenario, sd)
    for name, key in (("depth_image", "depth"), ("label_image", "label"),
                      ("gpd_depth_image", "gpd_depth")):
        if ports[key] is not None:  # the label image: target mode only
            builder.Connect(ports[key], proxy.GetInputPort(name))
    for name in ("gripper_state", "arm_state"):
        builder.Connect(sd.GetOutputPort(name), proxy.GetInputPort(name))
    for name in ("arm_position_command", "gripper_command"):
        builder.Connect(proxy.GetOutputPort(name), sd.GetInputPort(name))
    out = EpisodeDiagram(diagram=None, station=station, policy=proxy, target=target)
    out.disturbance = _drive_sheet(builder, scenario, sd, proxy.GetOutputPort("control_status"),
                                   scenario.controller.period_s)
    out.judge = _add_judge(builder, scenario, scene, library, station, proxy)
    out.diagram = builder.Build()
    out.diagram.set_name("grasp_episode_station_side")
    return out
