"""The controller and the station in two processes (drake_grasp.evaluation.bridge): the same episode
as in process, driver messages that survive the wire, clear errors for a bad peer."""

import socket
import sys
import time
from dataclasses import asdict

import numpy as np
import pytest

from drake_grasp.evaluation import bridge, bridge_protocol
from drake_grasp.evaluation.bridge_protocol import BridgeError, BridgeLink
from drake_grasp.config.scenario import load_scenario


@pytest.fixture(scope="module")
def ctr_episode(library):
    from drake_grasp.world.scene import make_scene

    scenario = load_scenario(scenario_name="isolation", scenario_text="{seed: 0, policy: ctr}")
    scene = make_scene(scenario.scene, scenario.seed, library, scenario.plant,
                       physics=scenario.physics)
    return scenario, scene


def test_split_episode_equals_the_in_process_episode(ctr_episode, library):
    from drake_grasp.evaluation.episode import simulate_episode

    scenario, scene = ctr_episode
    t0 = time.perf_counter()
    local = simulate_episode(scenario, library=library, scene=scene, record_depth=False)
    t1 = time.perf_counter()
    split = bridge.simulate_split_episode(scenario, library=library, scene=scene, timeout_s=60.0)
    t2 = time.perf_counter()
    a, b = local.result, split.result
    print(f"in process {t1 - t0:.1f} s, split {t2 - t1:.1f} s: {b.details['bridge']}")
    assert (b.success, b.failure_reason) == (a.success, a.failure_reason)
    assert b.details["failure_class"] == a.details["failure_class"]
    assert b.control_steps == a.control_steps and b.control_steps > 0
    assert b.sim_time_s == a.sim_time_s
    assert b.final_X_WG == a.final_X_WG
    assert b.object_lowest_point_m == a.object_lowest_point_m
    assert b.final_distance_m == a.final_distance_m
    assert b.details["judge"] == a.details["judge"]
    # Everything the episode reports but wall-clock times and the link's counts.
    wall = ("simulation_wall_time_s", "decision_time_s", "bridge")
    same = lambda r: {**asdict(r), "wall_time_s": None,
                      "details": {k: v for k, v in r.details.items() if k not in wall}}
    assert same(b) == same(a)
    # The whole plant, bit for bit.
    np.testing.assert_array_equal(split.final_plant_state, local.final_plant_state)
    # It really went through the link: a tick per IK step, the CNN's images on request.
    link = b.details["bridge"]
    assert link["transport"].startswith("tcp://127.0.0.1:")
    assert link["ticks"] >= int(a.sim_time_s / scenario.arm.ik_time_step_s)
    assert link["image_requests"] >= a.control_steps
    assert b.details["decisions"] == a.details["decisions"]


def test_driver_messages_round_trip_bit_for_bit():
    from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

    rng = np.random.default_rng(0)
    q, v, qc = rng.normal(size=6), rng.normal(size=6), rng.normal(size=6)
    got = bridge_protocol.decode_joint_status(bridge_protocol.encode_joint_status(0.125, q, v, qc), 6)
    for sent, back in zip((q, v, qc), got):
        np.testing.assert_array_equal(back, sent)
    fingers = rng.normal(size=4)
    gq, gv, _ = bridge_protocol.decode_joint_status(
        bridge_protocol.encode_joint_status(0.0, fingers[:2], fingers[2:], [0.0, 0.0]), 2)
    np.testing.assert_array_equal(np.concatenate([gq, gv]), fingers)
    np.testing.assert_array_equal(bridge_protocol.decode_arm_command(bridge_protocol.encode_arm_command(1.0, q)), q)
    for command in ([0.085, 5.0], [0.0, 5.0], [0.04, 0.2]):
        np.testing.assert_array_equal(
            bridge_protocol.decode_gripper_command(bridge_protocol.encode_gripper_command(0.0, command)), command)
    status = [3.0, 1.0, 2.0]
    np.testing.assert_array_equal(
        bridge_protocol.decode_control_status(bridge_protocol.encode_control_status(0.0, status)), status)
    depth = ImageDepth32F(64, 48)
    depth.mutable_data[:, :, 0] = rng.uniform(0.1, 1.0, size=(48, 64)).astype(np.float32)
    depth.mutable_data[0, :3, 0] = [0.0, np.inf, np.nan]  # below the near clip, beyond the far one
    back = bridge_protocol.decode_image(bridge_protocol.encode_image(0.5, depth, "depth_image"))
    assert isinstance(back, ImageDepth32F) and (back.width(), back.height()) == (64, 48)
    np.testing.assert_array_equal(back.data, depth.data)
    labels = ImageLabel16I(8, 4)
    labels.mutable_data[:, :, 0] = rng.integers(-1, 300, size=(4, 8)).astype(np.int16)
    back = bridge_protocol.decode_image(bridge_protocol.encode_image(0.5, labels))
    assert isinstance(back, ImageLabel16I)
    np.testing.assert_array_equal(back.data, labels.data)


def test_a_message_of_another_type_is_refused_by_name():
    with pytest.raises(BridgeError, match="not a lcmt_iiwa_command"):
        bridge_protocol.decode_arm_command(bridge_protocol.encode_gripper_command(0.0, [0.085, 5.0]))
    with pytest.raises(BridgeError, match="expected 6 joints, got 2"):
        bridge_protocol.decode_joint_status(bridge_protocol.encode_joint_status(0.0, [0, 0], [0, 0], [0, 0]), 6)


def _pair(timeout_s=5.0):
    """A BridgeLink and the raw socket of its peer, over loopback TCP."""
    server = bridge.listen(0)
    try:
        b = socket.create_connection(server.getsockname(), timeout=5.0)
        a, _ = server.accept()
    finally:
        server.close()
    return BridgeLink(a, peer="the test peer", timeout_s=timeout_s), b


def test_bundles_cross_the_link():
    near, far_sock = _pair()
    far = BridgeLink(far_sock, peer="near", timeout_s=5.0)
    payload = bridge_protocol.encode_arm_command(0.0, np.arange(6.0))
    near.send_bundle("BRIDGE_TICK", {"version": 3, "t": 0.1}, [(bridge_protocol.ARM_COMMAND, payload)])
    control, body, frames = far.recv_bundle()
    assert (control, body, frames) == ("BRIDGE_TICK", {"version": 3, "t": 0.1},
                                       {bridge_protocol.ARM_COMMAND: payload})
    near.close()
    far.close()


def test_garbled_dead_and_silent_peers_give_clear_errors():
    link, peer = _pair()
    peer.sendall(b"GET / HTTP/1.1\r\n\r\n")
    with pytest.raises(BridgeError, match="garbled frame from the test peer.*expected magic"):
        link.recv_bundle()
    link.close()
    peer.close()

    link, peer = _pair()
    peer.close()
    with pytest.raises(BridgeError, match="the test peer closed the connection"):
        link.recv_bundle()
    link.close()

    link, peer = _pair(timeout_s=0.2)
    with pytest.raises(BridgeError, match=r"no message from the test peer within 0.2 s"):
        link.recv_bundle()
    link.close()
    peer.close()

    link, peer = _pair()
    BridgeLink(peer, peer="station", timeout_s=1.0).send_bundle(
        "BRIDGE_ERROR", {"message": "ValueError: weights file missing"})
    with pytest.raises(BridgeError, match="the test peer failed: ValueError: weights file missing"):
        link.recv_bundle()
    link.close()


def test_a_controller_process_that_dies_is_reported_with_its_exit_code_and_output(
        ctr_episode, library):
    scenario, scene = ctr_episode
    dies = [sys.executable, "-c", "import sys; sys.stderr.write('no CNN here'); sys.exit(3)"]
    t0 = time.perf_counter()
    with pytest.raises(BridgeError, match=r"(?s)exited with code 3 before connecting.*no CNN here"):
        bridge.simulate_split_episode(scenario, library=library, scene=scene, timeout_s=30.0,
                                      command=lambda port: dies)
    assert time.perf_counter() - t0 < 20.0


def test_a_peer_speaking_another_protocol_is_refused(ctr_episode, library):
    scenario, scene = ctr_episode
    garbler = ("import socket, sys, time; s = socket.create_connection(('127.0.0.1', int(sys.argv[1])));"
               " s.sendall(b'HELLO' * 10); time.sleep(2)")
    with pytest.raises(BridgeError, match="garbled frame from the controller process"):
        bridge.simulate_split_episode(
            scenario, library=library, scene=scene, timeout_s=30.0,
            command=lambda port: [sys.executable, "-c", garbler, str(port)])


def test_policies_that_cannot_cross_are_refused_before_anything_starts():
    scenario = load_scenario(scenario_name="isolation", scenario_text="{policy: scripted}")
    with pytest.raises(ValueError, match="policy: 'scripted' runs in process only"):
        bridge.simulate_split_episode(scenario)


def test_station_refuses_an_unknown_arm_input():
    from drake_grasp.world.station import MakeGraspStation

    scenario = load_scenario(scenario_name="isolation")
    with pytest.raises(ValueError, match="arm_input: expected 'X_WG_desired' or "
                                         "'arm_position_command', got 'joints'"):
        MakeGraspStation(scenario, None, None, arm_input="joints")


def test_controller_refuses_a_task_of_another_protocol_version():
    with pytest.raises(BridgeError, match="the station speaks protocol 99"):
        bridge.ControllerSide(None, {"protocol": 99})
