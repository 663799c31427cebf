"""The wire protocol between the station and controller processes of a split episode:
the channel names and the LCM message types they carry (`encode_*` / `decode_*`: joint
status and commands, gripper command, control status, images), `BridgeLink` (LCM-encoded
frames bundled under a control message on one TCP connection, with its framing, size limit
and timeouts), `BridgeError`, the pose lists of the task handshake and the check that a
scenario can run split (`check_bridge_scenario`). `drake_grasp.evaluation.bridge` has the
whole protocol's description.
"""

from __future__ import annotations

import json
import math
import socket
import struct

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
