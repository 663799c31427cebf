"""Across a process boundary: the controller Diagram in one process, the simulated station
in another, talking robot-driver messages (Drake's LCM message types) over TCP.

Where the cut is. The station process is the simulated robot cell as a robot driver
shows it: the plant, the UR5's joint PD with gravity feed-forward and its command
interpolator, the 2F-85's force-controlled position control, the wrist camera (and the GPD
sensor), the sheet and its disturbance, and the grasp judge (the harness's observer; a
real cell has none). The controller process is everything a robot PC runs: the policy
(`GraspController` with its `ActionSampler` and `DistanceEvaluator`) and the arm's
differential IK (`station.make_arm_diff_ik`), which turns the policy's grasp-frame target
into UR5 joint positions. So the arm crosses as joint state and joint commands, like a
UR driver's servo interface, and the station is built with
`MakeGraspStation(..., arm_input="arm_position_command")` (no `diff_ik` inside).

Messages (one Drake LCM type each, `encode()`d; channel names as on an LCM bus):

| channel | type | direction | content |
|---|---|---|---|
| `UR5_STATUS` | `lcmt_iiwa_status` | station -> controller | 6 joints: measured positions and velocities, the position command in force |
| `UR5_COMMAND` | `lcmt_iiwa_command` | controller -> station | 6 joint positions (no torques) |
| `ROBOTIQ_2F85_STATUS` | `lcmt_iiwa_status` | station -> controller | the 2 finger joints (left, right): positions and velocities, the station's `gripper_state` |
| `ROBOTIQ_2F85_COMMAND` | `lcmt_schunk_wsg_command` | controller -> station | target opening [mm] and grip force [N] (Drake's gripper-driver command) |
| `WRIST_DEPTH`, `WRIST_LABEL`, `GPD_DEPTH` | `lcmt_image` | station -> controller | 32-bit float depth [m] / 16-bit labels, uncompressed |
| `CONTROL_STATUS` | `lcmt_drake_signal` | controller -> station | [control step, approaching, motion phase]: the harness's; the judge and the sheet disturbance read it |

`utime` fields carry the simulation time in microseconds. Around these, the lockstep
protocol's own messages (channels `BRIDGE_*`, JSON): the task (the scenario, the start
pose, the camera extrinsics the policy believes), tick, image request, evaluation and
goodbye.

Transport. Frames on one TCP connection: a 4-byte magic `DGLB`, the channel name's
length (2 bytes) and the payload's (4 bytes), big-endian, then the name and the LCM-encoded
payload. Tests and the CLI bind 127.0.0.1 only, on a port the OS chooses, with no
multicast: `pydrake.lcm.DrakeLcm` speaks UDP multicast (or in-process memq) only. A robot
deployment replaces the station process with the UR and 2F-85 drivers and a camera node,
and the transport with LCM's UDP multicast on the robot LAN (`DrakeLcm("udpm://...")`, the
same message types and channels) or the drivers' own (UR RTDE, the 2F-85's Modbus).

Exactness. The station process drives the clock: a proxy system (`RemoteController`)
stands for the controller Diagram and declares the controller side's periodic events
(the control period and the IK step); at each of their times its unrestricted update
sends a tick with the joint and gripper status read from the pre-update Context. The
controller process advances its own Simulator to that time, applies its updates with
those inputs, and replies with its commands. Images go only on request: when the policy
reads an image during its update, the controller asks for it and the station renders
it from the same pre-update Context, so the camera renders exactly when the in-process
Diagram would. Drake computes all unrestricted updates of one time from the pre-update
Context and discrete updates after them; the proxy keeps per-tick versions so that
systems reading it at the same instant see what they would in process: the judge (an
unrestricted update) the controller's state before the tick, the station's discrete
systems the policy's state after it with the IK's joint command from before (the IK is
a discrete system of the same time); anything evaluated at another time is asked for
remotely, by time and version. The split episode then reproduces the in-process episode
of the same seed bit for bit (tests/test_bridge.py). A real robot is free-running
instead: the driver streams status at its own rate and the controller acts on the
latest message, so no robot run repeats a simulation exactly.

Supported: the built-in controller policies (ctr, cnn-ctr, cnn-only, gpd,
gpd-geometric, init). `scripted` (which reads the true object poses) and user policies
(`MODULE:FACTORY`) run in process only.
"""

from __future__ import annotations

import json
import math
import os
import socket
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from drake_grasp.policies.decisions import SENSOR_POLICIES

MAGIC = b"DGLB"
PROTOCOL_VERSION = 1
LOOPBACK = "127.0.0.1"
# A frame's payload may not exceed this (a 640x480 float image is 1.2 MB).
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024
_HEADER = struct.Struct(">4sHI")

ARM_STATUS = "UR5_STATUS"
ARM_COMMAND = "UR5_COMMAND"
GRIPPER_STATUS = "ROBOTIQ_2F85_STATUS"
GRIPPER_COMMAND = "ROBOTIQ_2F85_COMMAND"
CONTROL_STATUS = "CONTROL_STATUS"
# The station's image output ports and their channels.
IMAGE_CHANNELS = {"depth_image": "WRIST_DEPTH", "label_image": "WRIST_LABEL",
                  "gpd_depth_image": "GPD_DEPTH"}
CONTROL_STATUS_NAMES = ("control_step", "approaching", "motion_phase")
BRIDGE_POLICIES = SENSOR_POLICIES  # every built-in policy but `scripted`


class BridgeError(ConnectionError):
    """The link between the station and controller processes failed: the peer died or
    went silent, or sent something that is not this protocol."""


def _utime(t: float) -> int:
    return int(round(float(t) * 1e6))


# --- messages: Drake's LCM types <-> what the Diagram ports carry --------------------


def encode_joint_status(t: float, q, v, q_commanded) -> bytes:
    """`lcmt_iiwa_status` of n joints: measured positions `q` and velocities `v`, the
    position command in force; torques are not modelled (zeros)."""
    from drake import lcmt_iiwa_status

    q = [float(x) for x in q]
    msg = lcmt_iiwa_status()
    msg.utime = _utime(t)
    msg.num_joints = len(q)
    msg.joint_position_measured = q
    msg.joint_velocity_estimated = [float(x) for x in v]
    msg.joint_position_commanded = [float(x) for x in q_commanded]
    msg.joint_position_ipo = [float(x) for x in q_commanded]
    zeros = [0.0] * len(q)
    msg.joint_torque_measured = zeros
    msg.joint_torque_commanded = zeros
    msg.joint_torque_external = zeros
    return msg.encode()


def decode_joint_status(data: bytes, num_joints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, v, q_commanded) of an `lcmt_iiwa_status`.

    Raises:
        BridgeError: not an `lcmt_iiwa_status`, or not `num_joints` joints.
    """
    from drake import lcmt_iiwa_status

    msg = _decode(lcmt_iiwa_status, data)
    if msg.num_joints != num_joints:
        raise BridgeError(f"lcmt_iiwa_status: expected {num_joints} joints, got {msg.num_joints}")
    return (np.array(msg.joint_position_measured), np.array(msg.joint_velocity_estimated),
            np.array(msg.joint_position_commanded))


def encode_arm_command(t: float, q) -> bytes:
    """`lcmt_iiwa_command`: joint positions, no torques."""
    from drake import lcmt_iiwa_command

    msg = lcmt_iiwa_command()
    msg.utime = _utime(t)
    msg.num_joints = len(q)
    msg.joint_position = [float(x) for x in q]
    msg.num_torques = 0
    msg.joint_torque = []
    return msg.encode()


def decode_arm_command(data: bytes, num_joints: int = 6) -> np.ndarray:
    from drake import lcmt_iiwa_command

    msg = _decode(lcmt_iiwa_command, data)
    if msg.num_joints != num_joints:
        raise BridgeError(f"lcmt_iiwa_command: expected {num_joints} joints, got {msg.num_joints}")
    return np.array(msg.joint_position)


def encode_gripper_command(t: float, command) -> bytes:
    """`lcmt_schunk_wsg_command` from the policy's [width_m, grip_force_n]."""
    from drake import lcmt_schunk_wsg_command

    width_m, force_n = (float(x) for x in command)
    msg = lcmt_schunk_wsg_command()
    msg.utime = _utime(t)
    msg.target_position_mm = width_m * 1e3
    msg.force = force_n
    return msg.encode()


def decode_gripper_command(data: bytes) -> np.ndarray:
    """[width_m, grip_force_n] of an `lcmt_schunk_wsg_command`."""
    from drake import lcmt_schunk_wsg_command

    msg = _decode(lcmt_schunk_wsg_command, data)
    return np.array([msg.target_position_mm / 1e3, msg.force])


def encode_control_status(t: float, status) -> bytes:
    """`lcmt_drake_signal` with the named [control step, approaching, motion phase]."""
    from drake import lcmt_drake_signal

    msg = lcmt_drake_signal()
    msg.dim = len(CONTROL_STATUS_NAMES)
    msg.val = [float(x) for x in status]
    msg.coord = list(CONTROL_STATUS_NAMES)
    msg.timestamp = _utime(t)
    return msg.encode()


def decode_control_status(data: bytes) -> np.ndarray:
    from drake import lcmt_drake_signal

    msg = _decode(lcmt_drake_signal, data)
    if tuple(msg.coord) != CONTROL_STATUS_NAMES:
        raise BridgeError(f"{CONTROL_STATUS}: expected coordinates {list(CONTROL_STATUS_NAMES)}, "
                          f"got {list(msg.coord)}")
    return np.array(msg.val)


def encode_image(t: float, image, frame_name: str = "") -> bytes:
    """`lcmt_image` of a Drake `ImageDepth32F` (PIXEL_FORMAT_DEPTH, float32) or
    `ImageLabel16I` (PIXEL_FORMAT_LABEL, int16), uncompressed, little-endian."""
    from drake import lcmt_header, lcmt_image
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    if isinstance(image, ImageDepth32F):
        fmt, channel, dtype = lcmt_image.PIXEL_FORMAT_DEPTH, lcmt_image.CHANNEL_TYPE_FLOAT32, "<f4"
    elif isinstance(image, ImageLabel16I):
        fmt, channel, dtype = lcmt_image.PIXEL_FORMAT_LABEL, lcmt_image.CHANNEL_TYPE_INT16, "<i2"
    else:
        raise TypeError(f"encode_image: expected ImageDepth32F or ImageLabel16I, got "
                        f"{type(image).__name__}")
    pixels = np.ascontiguousarray(np.asarray(image.data)[:, :, 0], dtype=dtype)
    header = lcmt_header()
    header.utime = _utime(t)
    header.frame_name = frame_name
    msg = lcmt_image()
    msg.header = header
    msg.width, msg.height = image.width(), image.height()
    msg.row_stride = msg.width * pixels.itemsize
    msg.data = pixels.tobytes()
    msg.size = len(msg.data)
    msg.bigendian = False
    msg.pixel_format = fmt
    msg.channel_type = channel
    msg.compression_method = lcmt_image.COMPRESSION_METHOD_NOT_COMPRESSED
    return msg.encode()


def decode_image(data: bytes):
    """The Drake image (`ImageDepth32F` or `ImageLabel16I`) of an `lcmt_image`.

    Raises:
        BridgeError: not an `lcmt_image`, a compressed or other format, or a size that
            does not match width x height.
    """
    from drake import lcmt_image
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    msg = _decode(lcmt_image, data)
    kinds = {(lcmt_image.PIXEL_FORMAT_DEPTH, lcmt_image.CHANNEL_TYPE_FLOAT32): (ImageDepth32F, "f4"),
             (lcmt_image.PIXEL_FORMAT_LABEL, lcmt_image.CHANNEL_TYPE_INT16): (ImageLabel16I, "i2")}
    kind = kinds.get((msg.pixel_format, msg.channel_type))
    if kind is None or msg.compression_method != lcmt_image.COMPRESSION_METHOD_NOT_COMPRESSED:
        raise BridgeError(f"lcmt_image: expected uncompressed float32 depth or int16 labels, got "
                          f"pixel_format {msg.pixel_format}, channel_type {msg.channel_type}, "
                          f"compression {msg.compression_method}")
    cls, code = kind
    dtype = np.dtype((">" if msg.bigendian else "<") + code)
    if msg.size != msg.width * msg.height * dtype.itemsize or len(msg.data) != msg.size:
        raise BridgeError(f"lcmt_image: {len(msg.data)} bytes for a {msg.width}x{msg.height} "
                          f"image of {dtype.itemsize}-byte pixels")
    image = cls(msg.width, msg.height)
    image.mutable_data[:, :, 0] = np.frombuffer(msg.data, dtype=dtype).reshape(msg.height, msg.width)
    return image


def _decode(cls, data: bytes):
    try:
        return cls.decode(data)
    except Exception as e:  # lcm raises ValueError on a fingerprint mismatch
        raise BridgeError(f"not a {cls.__name__} message ({len(data)} bytes): {e}") from None


# --- transport: LCM-encoded frames on one TCP connection ------------------------------


class BridgeLink:
    """One end of the connection. Messages go in bundles: data frames (LCM payloads on
    their channels) closed by one control frame (a `BRIDGE_*` channel, JSON payload).

    Args:
        sock: a connected TCP socket (it is owned and closed by the link).
        peer: how errors name the other end, e.g. "the controller process".
        timeout_s: how long a receive may wait.
    """

    def __init__(self, sock: socket.socket, *, peer: str, timeout_s: float):
        self._sock = sock
        if sock.family in (socket.AF_INET, socket.AF_INET6):  # lockstep: no Nagle delay
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.settimeout(float(timeout_s))
        self.peer = peer
        self.timeout_s = float(timeout_s)
        self.stats = {"frames_sent": 0, "frames_received": 0, "bytes_sent": 0,
                      "bytes_received": 0}

    def close(self) -> None:
        try:
            self._sock.close()
        except OSError:
            pass

    def send_bundle(self, control: str, body: dict | None = None, frames=()) -> None:
        """Sends the data `frames` [(channel, payload)] and the control frame."""
        parts = []
        items = list(frames) + [(control, json.dumps(body or {}).encode())]
        for channel, payload in items:
            name = channel.encode("ascii")
            parts.append(_HEADER.pack(MAGIC, len(name), len(payload)) + name + payload)
        data = b"".join(parts)
        try:
            self._sock.sendall(data)
        except OSError as e:
            raise BridgeError(f"sending {control} to {self.peer} failed ({e}): did it exit?") from None
        self.stats["frames_sent"] += len(items)
        self.stats["bytes_sent"] += len(data)

    def recv_bundle(self) -> tuple[str, dict, dict]:
        """(control channel, its JSON body, {data channel: payload}).

        Raises:
            BridgeError: the peer closed the connection, was silent for `timeout_s`, or
                sent a frame that is not this protocol's; a `BRIDGE_ERROR` from the peer
                (its message is kept).
        """
        frames = {}
        while True:
            magic, name_len, size = _HEADER.unpack(self._read(_HEADER.size))
            if magic != MAGIC:
                raise BridgeError(f"garbled frame from {self.peer}: expected magic {MAGIC!r}, "
                                  f"got {magic!r} (not a drake_grasp bridge peer?)")
            if size > MAX_PAYLOAD_BYTES:
                raise BridgeError(f"garbled frame from {self.peer}: payload of {size} bytes "
                                  f"(limit {MAX_PAYLOAD_BYTES})")
            try:
                channel = self._read(name_len).decode("ascii")
            except UnicodeDecodeError:
                raise BridgeError(f"garbled frame from {self.peer}: channel name is not ASCII") from None
            payload = self._read(size)
            self.stats["frames_received"] += 1
            if not channel.startswith("BRIDGE_"):
                frames[channel] = payload
                continue
            try:
                body = json.loads(payload.decode("utf-8")) if payload else {}
            except (UnicodeDecodeError, json.JSONDecodeError) as e:
                raise BridgeError(f"garbled {channel} from {self.peer}: {e}") from None
            if channel == "BRIDGE_ERROR":
                raise BridgeError(f"{self.peer} failed: {body.get('message', '?')}")
            return channel, body, frames

    def expect(self, control: str) -> tuple[dict, dict]:
        """`recv_bundle`, requiring the control channel `control`."""
        channel, body, frames = self.recv_bundle()
        if channel != control:
            raise BridgeError(f"{self.peer} sent {channel} where {control} was expected")
        return body, frames

    def _read(self, n: int) -> bytes:
        chunks, got = [], 0
        while got < n:
            try:
                chunk = self._sock.recv(min(n - got, 1 << 20))
            except socket.timeout:
                raise BridgeError(f"no message from {self.peer} within {self.timeout_s:g} s "
                                  "(is it still running?)") from None
            except OSError as e:
                raise BridgeError(f"the connection to {self.peer} failed: {e}") from None
            if not chunk:
                raise BridgeError(f"{self.peer} closed the connection (did it exit?)")
            chunks.append(chunk)
            got += len(chunk)
        self.stats["bytes_received"] += n
        return b"".join(chunks)


def _need(frames: dict, channel: str, where: str) -> bytes:
    if channel not in frames:
        raise BridgeError(f"{where}: no {channel} message in the bundle (got {sorted(frames)})")
    return frames[channel]


def _pose_list(X) -> list:
    return np.asarray(X.GetAsMatrix4()).tolist()


def _pose(values):
    from pydrake.math import RigidTransform

    return RigidTransform(np.asarray(values, dtype=float))


def check_bridge_scenario(scenario) -> None:
    """Raises ValueError when `scenario` cannot run across the process boundary: its
    policy is not a built-in controller policy (`BRIDGE_POLICIES`), or its control period
    or IK step (the times the station ticks at) is not a positive time."""
    if scenario.policy not in BRIDGE_POLICIES:
        raise ValueError(f"policy: {scenario.policy!r} runs in process only; across the process "
                         f"boundary: {', '.join(BRIDGE_POLICIES)}")
    for name, value in (("controller.period_s", scenario.controller.period_s),
                        ("arm.ik_time_step_s", scenario.arm.ik_time_step_s)):
        if not (value > 0 and math.isfinite(value)):
            raise ValueError(f"{name}: expected a positive time, got {value}")


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
    from pydrake.common.value import AbstractValue
    from pydrake.systems.framework import LeafSystem, ValueProducer
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    class _RemoteController(LeafSystem):
        def __init__(self):
            super().__init__()
            self._link = link
            self._images = {
                "depth_image": self.DeclareAbstractInputPort(
                    "depth_image", AbstractValue.Make(ImageDepth32F())),
                "label_image": self.DeclareAbstractInputPort(
                    "label_image", AbstractValue.Make(ImageLabel16I())),
                "gpd_depth_image": self.DeclareAbstractInputPort(
                    "gpd_depth_image", AbstractValue.Make(ImageDepth32F())),
            }
            self._gripper_state = self.DeclareVectorInputPort("gripper_state", 4)
            self._arm_state = self.DeclareVectorInputPort("arm_state", 12)
            self._state = self.DeclareAbstractState(AbstractValue.Make(RemoteReply(
                arm=tuple(float(x) for x in q_initial), mode=initial["mode"],
                done=bool(initial["done"]))))
            for period, offset in periods:
                self.DeclarePeriodicUnrestrictedUpdateEvent(float(period), float(offset), self._Tick)
            deps = {self.abstract_state_ticket(self._state), self.time_ticket()}
            self._remote = self.DeclareCacheEntry(
                "the controller's outputs at this time (asked for remotely)",
                ValueProducer(allocate=lambda: AbstractValue.Make((np.zeros(2), np.zeros(3))),
                              calc=self._CalcRemote), deps)
            self.DeclareVectorOutputPort("arm_position_command", 6, self._CalcArm, deps)
            self.DeclareVectorOutputPort("gripper_command", 2, self._CalcGripper, deps)
            self.DeclareVectorOutputPort("control_status", 3, self._CalcStatus, deps)

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
            t = context.get_time()
            old = self.reply(context)
            if state.get_abstract_state(int(self._state)).get_value().t == t:
                return  # two of the controller's periods fall on this time: one tick
            arm = self._arm_state.Eval(context)
            fingers = self._gripper_state.Eval(context)
            # Each finger's commanded position: half the commanded opening.
            q_fingers = [0.5 * old.gripper[0]] * 2 if old.gripper else [math.nan] * 2
            frames = [(ARM_STATUS, encode_joint_status(t, arm[:6], arm[6:], old.arm)),
                      (GRIPPER_STATUS, encode_joint_status(t, fingers[:2], fingers[2:], q_fingers))]
            version = old.version + 1
            self._link.send_bundle("BRIDGE_TICK", {"version": version, "t": t}, frames)
            while True:
                control, body, got = self._link.recv_bundle()
                if control == "BRIDGE_IMAGE_REQUEST":
                    name = body.get("port")
                    if name not in self._images:
                        raise BridgeError(f"the controller asked for image {name!r}; the station "
                                          f"sends {sorted(self._images)}")
                    image = self._images[name].Eval(context)
                    self._link.send_bundle("BRIDGE_IMAGE", {"port": name}, [
                        (IMAGE_CHANNELS[name], encode_image(t, image, name))])
                elif control == "BRIDGE_TICK_DONE":
                    break
                else:
                    raise BridgeError(f"{self._link.peer} sent {control} during tick {version}")
            if body.get("version") != version or body.get("t") != t:
                raise BridgeError(f"{self._link.peer} answered tick {body.get('version')} at "
                                  f"t = {body.get('t')!r}; expected tick {version} at t = {t!r}")
            state.get_mutable_abstract_state(int(self._state)).set_value(RemoteReply(
                version=version, t=t, arm_prev=old.arm,
                arm=tuple(decode_arm_command(_need(got, ARM_COMMAND, "tick reply"))),
                gripper=tuple(decode_gripper_command(_need(got, GRIPPER_COMMAND, "tick reply"))),
                status=tuple(decode_control_status(_need(got, CONTROL_STATUS, "tick reply"))),
                mode=str(body["mode"]), done=bool(body["done"]), outcome=dict(body["outcome"]),
                decision_time_s=float(body.get("decision_time_s", 0.0)),
                decisions=int(body.get("decisions", 0)),
                last_iteration=body.get("last_iteration")))

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


def listen(port: int = 0, host: str = LOOPBACK) -> socket.socket:
    """A listening TCP socket on `host`:`port` (port 0: the OS chooses; read it with
    `getsockname()[1]`)."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind((host, int(port)))
    server.listen(1)
    return server


def _accept(server: socket.socket, timeout_s: float, child=None, child_log=None) -> socket.socket:
    deadline = time.monotonic() + timeout_s
    server.settimeout(0.2)
    while True:
        try:
            sock, _ = server.accept()
            sock.settimeout(None)
            return sock
        except socket.timeout:
            pass
        if child is not None and child.poll() is not None:
            raise BridgeError(f"the controller process exited with code {child.returncode} "
                              f"before connecting{_log_tail(child_log)}")
        if time.monotonic() > deadline:
            raise BridgeError(f"no controller connected to {server.getsockname()[0]}:"
                              f"{server.getsockname()[1]} within {timeout_s:g} s")


def _log_tail(path, chars: int = 2000) -> str:
    if not path or not os.path.exists(path):
        return ""
    with open(path, "rb") as f:
        text = f.read().decode("utf-8", "replace").strip()
    return f"; its output ends:\n{text[-chars:]}" if text else ""


def controller_command(port: int, *, host: str = LOOPBACK, timeout_s: float = 60.0) -> list[str]:
    """The command line that starts a controller process connecting to `host`:`port`."""
    return [sys.executable, "-m", "drake_grasp.cli.main", "bridge", "controller", "--host", host,
            "--port", str(int(port)), "--timeout", f"{timeout_s:g}"]


def simulate_split_episode(scenario, *, scenario_name: str = "", library=None, scene=None,
                           record_depth: bool = False, timeout_s: float = 60.0,
                           port: int = 0, spawn_controller: bool = True,
                           command=None):
    """One episode with the controller in another process: samples and settles the scene
    like `episode.simulate_episode`, listens on 127.0.0.1:`port`, starts the controller
    process (`controller_command`, or `command(port)` -> argv; with `spawn_controller` False it waits
    for one started by hand, e.g. `drake-grasp bridge controller --port P`), and runs the
    station side. Returns an `episode.EpisodeRun` whose result's `details["bridge"]`
    holds the link's counts.

    Raises:
        ValueError: the scenario cannot run across the boundary (`check_bridge_scenario`).
        BridgeError: the controller process did not connect within `timeout_s`, died,
            went silent for `timeout_s`, or failed (its message and the end of its
            output are kept). The controller process is always ended.
    """
    from drake_grasp.evaluation.episode import _run
    from drake_grasp.objects import load_library
    from drake_grasp.world.scene import scenario_scene

    check_bridge_scenario(scenario)
    wall_start = time.perf_counter()
    server = listen(port)
    bound = server.getsockname()[1]
    child = log_path = None
    link = None
    try:
        if spawn_controller:
            fd, log_path = tempfile.mkstemp(prefix="drake_grasp_controller_", suffix=".log")
            with os.fdopen(fd, "wb") as log:
                argv = (command(bound) if command is not None
                        else controller_command(bound, timeout_s=timeout_s))
                child = subprocess.Popen(argv,
                                         stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        else:
            print(f"drake-grasp bridge: waiting for a controller on {LOOPBACK}:{bound}",
                  file=sys.stderr, flush=True)
        # The controller starts (imports, CNN) while the scene settles.
        library = library if library is not None else load_library(scenario.objects_dir or None)
        if scene is None:
            scene = scenario_scene(scenario, library)
        link = BridgeLink(_accept(server, timeout_s, child, log_path),
                          peer="the controller process", timeout_s=timeout_s)
        try:
            ed = build_station_side(scenario, scene, library, link)
            run = _run(ed, scenario, scenario_name, scene, library, None, record_depth, wall_start)
            link.send_bundle("BRIDGE_BYE", {})
            bye, _ = link.expect("BRIDGE_BYE")
        except BridgeError as e:
            if child is not None:
                try:
                    child.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    pass
                if child.poll() is not None:
                    raise BridgeError(f"{e} [controller process exit code {child.returncode}]"
                                      f"{_log_tail(log_path)}") from None
            raise
        run.steps = []  # iterations only: the step records stay in the controller process
        details = run.result.details
        details["decision_time_s"] = bye.get("decision_time_s")
        details["decisions"] = int(bye.get("decisions", 0))
        details["bridge"] = {"transport": f"tcp://{LOOPBACK}:{bound}", **link.stats,
                             "ticks": int(bye.get("ticks", 0)),
                             "evaluations": int(bye.get("evaluations", 0)),
                             "image_requests": int(bye.get("image_requests", 0))}
        if child is not None:
            try:
                child.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                raise BridgeError(f"the controller process did not exit within {timeout_s:g} s "
                                  "after the episode") from None
            if child.returncode != 0:
                raise BridgeError(f"the controller process exited with code {child.returncode}"
                                  f"{_log_tail(log_path)}")
        return run
    finally:
        if link is not None:
            link.close()
        server.close()
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()
        if log_path:
            try:
                os.unlink(log_path)
            except OSError:
                pass


# --- controller side ----------------------------------------------------------------


def _make_remote_image(link: BridgeLink, name: str, model, counter: dict):
    """A source of image `name` that asks the station for it (once per time)."""
    from pydrake.common.value import AbstractValue
    from pydrake.systems.framework import LeafSystem

    class _RemoteImage(LeafSystem):
        """Output port `image`: the station's image `name` at this time, on request."""

        def __init__(self):
            super().__init__()
            self.DeclareAbstractOutputPort("image", lambda: AbstractValue.Make(model),
                                           self._Calc, {self.time_ticket()})

        def _Calc(self, context, output):
            link.send_bundle("BRIDGE_IMAGE_REQUEST", {"port": name, "t": context.get_time()})
            _, got = link.expect("BRIDGE_IMAGE")
            image = decode_image(_need(got, IMAGE_CHANNELS[name], f"image {name}"))
            if type(image) is not type(model):
                raise BridgeError(f"image {name}: expected {type(model).__name__}, got "
                                  f"{type(image).__name__}")
            counter["image_requests"] += 1
            output.set_value(image)

    return _RemoteImage()


def _control_plant(scenario):
    """The arm's control plant as the station builds it (UR5 + the gripper lumped onto
    tool0, + the grasp frame), from the robot's models alone."""
    from pydrake.multibody.plant import AddMultibodyPlant
    from pydrake.systems.framework import DiagramBuilder

    from drake_grasp.world.station import _add_robot, arm_control_plant

    plant, _ = AddMultibodyPlant(scenario.plant, DiagramBuilder())
    arm, gripper = _add_robot(plant)
    plant.Finalize()
    return arm_control_plant(plant, arm, gripper)


class ControllerSide:
    """The controller process's Diagram and its lockstep: policy systems + the arm's
    differential IK, images fetched from the station on request.

    Args:
        link: the connection to the station process.
        task: the body of the station's `BRIDGE_TASK`.
    """

    def __init__(self, link: BridgeLink, task: dict):
        from pydrake.common.yaml import yaml_load_typed
        from pydrake.systems.analysis import Simulator
        from pydrake.systems.framework import DiagramBuilder
        from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

        from drake_grasp.evaluation.episode_diagram import add_policy_systems
        from drake_grasp.config.scenario import Scenario, dump_scenario
        from drake_grasp.world.station import make_arm_diff_ik
        from drake_grasp.policies.evaluator import load_cnn

        if task.get("protocol") != PROTOCOL_VERSION:
            raise BridgeError(f"the station speaks protocol {task.get('protocol')}, this "
                              f"controller {PROTOCOL_VERSION}")
        text = task["scenario_yaml"]
        scenario = yaml_load_typed(schema=Scenario, data=text, defaults=Scenario())
        if dump_scenario(scenario) != text:
            raise ValueError("BRIDGE_TASK: the scenario does not load back to the text sent "
                             "(a different drake_grasp version on the two sides?)")
        check_bridge_scenario(scenario)
        self.link = link
        self.scenario = scenario
        self.counts = {"ticks": 0, "evaluations": 0, "image_requests": 0}
        c = scenario.controller
        needs_cnn = scenario.policy in ("ctr", "cnn-only", "cnn-ctr")
        model = load_cnn(c.weights, threads=c.torch_threads) if needs_cnn else None
        builder = DiagramBuilder()
        images = {}
        streams = [("depth_image", ImageDepth32F()), ("gpd_depth_image", ImageDepth32F())]
        if scenario.target:  # the label image (ground truth) only in target mode
            streams.append(("label_image", ImageLabel16I()))
        for name, model_image in streams:
            images[name] = builder.AddNamedSystem(f"remote_{name}", _make_remote_image(
                link, name, model_image, self.counts)).get_output_port()
        controller, self.timer, _ = add_policy_systems(
            builder, scenario, model=model, X_WG_start=_pose(task["X_WG_start"]),
            X_GC=_pose(task["X_GC"]), X_GC_gpd=_pose(task["X_GC_gpd"]),
            target_label=task.get("target_label"), detect_fn=None,
            depth=images["depth_image"], label=images.get("label_image"),
            gpd_depth=images["gpd_depth_image"])
        self._control_plant = _control_plant(scenario)  # the IK keeps no reference
        self.diff_ik = builder.AddNamedSystem("diff_ik", make_arm_diff_ik(scenario, self._control_plant))
        builder.Connect(controller.GetOutputPort("X_WG_desired"),
                        self.diff_ik.GetInputPort("X_AE_desired"))
        builder.ExportInput(controller.GetInputPort("gripper_state"), "gripper_state")
        builder.ExportOutput(self.diff_ik.GetOutputPort("joint_positions"), "arm_position_command")
        builder.ExportOutput(controller.GetOutputPort("gripper_command"), "gripper_command")
        builder.ExportOutput(controller.GetOutputPort("control_status"), "control_status")
        self.diagram = builder.Build()
        self.diagram.set_name("grasp_controller_side")
        self.controller = controller
        self.simulator = Simulator(self.diagram)
        self.root = self.simulator.get_mutable_context()
        self._ctrl_context = controller.GetMyContextFromRoot(self.root)
        # The controller's state per tick version, for evaluations at other times.
        self._eval_context = controller.CreateDefaultContext()
        self._versions = {-1: controller.get_controller_state(self._ctrl_context)}
        self._version = -1
        self._initialized = False

    def ready_body(self) -> dict:
        """The `BRIDGE_READY` body: the periodic events the station must tick at (the
        control period and the IK step), the controller's mode before the first tick."""
        s = self.scenario
        periods = sorted({(float(s.controller.period_s), 0.0), (float(s.arm.ik_time_step_s), 0.0)})
        return {"protocol": PROTOCOL_VERSION, "periods": [list(p) for p in periods],
                "mode": self.controller.mode_name(self._ctrl_context),
                "done": bool(self.controller.is_done(self._ctrl_context))}

    def tick(self, body: dict, frames: dict) -> None:
        """Applies the controller side's updates at the tick's time with its status
        messages as inputs, and sends the commands back."""
        version, t = int(body["version"]), float(body["t"])
        if version != self._version + 1:
            raise BridgeError(f"tick {version} after tick {self._version}")
        q, _, _ = decode_joint_status(_need(frames, ARM_STATUS, "tick"), 6)
        gq, gv, _ = decode_joint_status(_need(frames, GRIPPER_STATUS, "tick"), 2)
        gripper_state = np.concatenate([gq, gv])
        port = self.diagram.get_input_port(0)
        if not self._initialized:
            if t != 0.0:
                raise BridgeError(f"the first tick must come at t = 0, got t = {t!r}")
            # The IK starts where the arm is, as a controller starts from the measured
            # joints.
            self.diff_ik.SetPositions(self.diff_ik.GetMyMutableContextFromRoot(self.root), q)
            port.FixValue(self.root, gripper_state)
            self.simulator.Initialize()
            self._initialized = True
        else:
            # To the tick's time with the old inputs (no events in between: the
            # station ticks at every event time of this side), then the events of that
            # time with the new ones.
            self.simulator.AdvanceTo(t)
            port.FixValue(self.root, gripper_state)
        self.simulator.AdvanceTo(t)
        if self.root.get_time() != t:
            raise BridgeError(f"tick {version}: the controller side is at t = "
                              f"{self.root.get_time()!r}, the station at t = {t!r}")
        self._version = version
        self._versions[version] = self.controller.get_controller_state(self._ctrl_context)
        self._versions.pop(version - 2, None)
        self.counts["ticks"] += 1
        out = {name: self.diagram.GetOutputPort(name).Eval(self.root)
               for name in ("arm_position_command", "gripper_command", "control_status")}
        self.link.send_bundle("BRIDGE_TICK_DONE", {
            "version": version, "t": t, "mode": self.controller.mode_name(self._ctrl_context),
            "done": bool(self.controller.is_done(self._ctrl_context)),
            "outcome": self.controller.outcome(self._ctrl_context),
            "last_iteration": self._last_iteration(),
            "decision_time_s": self.timer.seconds, "decisions": self.timer.calls}, [
            (ARM_COMMAND, encode_arm_command(t, out["arm_position_command"])),
            (GRIPPER_COMMAND, encode_gripper_command(t, out["gripper_command"])),
            (CONTROL_STATUS, encode_control_status(t, out["control_status"]))])

    def _last_iteration(self):
        last = self.controller.get_controller_state(self._ctrl_context).last_step
        return None if last is None else int(last.iteration)

    def evaluate(self, body: dict) -> None:
        """The controller's gripper command and status at time `t` in the state of tick
        `version` (what the in-process Diagram shows there)."""
        version, t = int(body["version"]), float(body["t"])
        if version not in self._versions:
            raise BridgeError(f"evaluation at tick {version}: this side keeps ticks "
                              f"{sorted(self._versions)}")
        ctx = self._eval_context
        ctx.SetTime(t)
        ctx.get_mutable_abstract_state(0).set_value(self._versions[version])
        self.counts["evaluations"] += 1
        self.link.send_bundle("BRIDGE_EVAL_DONE", {"version": version, "t": t}, [
            (GRIPPER_COMMAND, encode_gripper_command(
                t, self.controller.GetOutputPort("gripper_command").Eval(ctx))),
            (CONTROL_STATUS, encode_control_status(
                t, self.controller.GetOutputPort("control_status").Eval(ctx)))])

    def serve(self) -> None:
        """Answers the station until its goodbye."""
        while True:
            control, body, frames = self.link.recv_bundle()
            if control == "BRIDGE_TICK":
                self.tick(body, frames)
            elif control == "BRIDGE_EVAL":
                self.evaluate(body)
            elif control == "BRIDGE_BYE":
                self.link.send_bundle("BRIDGE_BYE", {
                    **self.counts, "decision_time_s": self.timer.seconds,
                    "decisions": self.timer.calls})
                return
            else:
                raise BridgeError(f"{self.link.peer} sent {control}, which the controller "
                                  "does not answer")


def connect(port: int, *, host: str = LOOPBACK, timeout_s: float = 60.0) -> BridgeLink:
    """Connects to a station process, retrying until `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            sock = socket.create_connection((host, int(port)), timeout=5.0)
            return BridgeLink(sock, peer="the station process", timeout_s=timeout_s)
        except OSError as e:
            if time.monotonic() > deadline:
                raise BridgeError(f"could not connect to a station at {host}:{port} within "
                                  f"{timeout_s:g} s: {e}") from None
            time.sleep(0.1)


def run_controller(port: int, *, host: str = LOOPBACK, timeout_s: float = 60.0) -> None:
    """The controller process: connects to the station, takes its task, builds the
    controller Diagram and answers ticks until the station says goodbye. A failure is
    reported to the station (`BRIDGE_ERROR`) before it is raised here."""
    link = connect(port, host=host, timeout_s=timeout_s)
    threads = None
    try:
        from drake_grasp.policies.evaluator import needs_torch

        task, _ = link.expect("BRIDGE_TASK")
        try:
            side = ControllerSide(link, task)
            s = side.scenario
            if s.policy in ("ctr", "cnn-only", "cnn-ctr") and needs_torch(s.controller.weights):
                import torch

                threads = torch.get_num_threads()
                torch.set_num_threads(max(1, s.controller.torch_threads))
            link.send_bundle("BRIDGE_READY", side.ready_body())
            side.serve()
        except BridgeError:
            raise
        except Exception as e:
            try:
                link.send_bundle("BRIDGE_ERROR", {"message": f"{type(e).__name__}: {e}"})
            except BridgeError:
                pass
            raise
    finally:
        if threads is not None:
            import torch

            torch.set_num_threads(threads)
        link.close()
