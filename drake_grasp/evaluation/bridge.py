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

This module runs a split episode: the station process's side (`listen`,
`simulate_split_episode`, which starts the controller process and drives the station's
Simulator) and the controller process's side (`ControllerSide`, `connect`,
`run_controller`). The messages and their transport are `bridge_protocol`; the station's
stand-in for the controller Diagram and the station-side Diagram are `bridge_station`.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

from drake_grasp.evaluation.bridge_protocol import (ARM_COMMAND, ARM_STATUS, CONTROL_STATUS,
                                                    GRIPPER_COMMAND, GRIPPER_STATUS,
                                                    IMAGE_CHANNELS, LOOPBACK, PROTOCOL_VERSION,
                                                    BridgeError, BridgeLink, _need, _pose,
                                                    check_bridge_scenario, decode_image,
                                                    decode_joint_status, encode_arm_command,
                                                    encode_control_status, encode_gripper_command)
from drake_grasp.evaluation.bridge_station import build_station_side

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
        from drake_grasp.systems.kinematic_noise import connect_with_noise
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
        connect_with_noise(builder, scenario, controller, self.diff_ik.GetInputPort("X_AE_desired"),
                           X_WG_start=_pose(task["X_WG_start"]))
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
