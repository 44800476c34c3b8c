"""The canpos package as a test engineer uses it: only the pytest plugin's fixtures, the
control client and python-canopen / python-can on the fixture's bus."""
import socket
from pathlib import Path
import time

import can
import canopen
import pytest

from canpos import ControlError

pytest_plugins = ["pytester"]


def network_on(bus):
    net = canopen.Network()
    net.connect(**bus.python_can())
    return net


def wait_for(pred, timeout=5.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return False


def test_control_client_moves_the_magnet_and_refuses_bad_requests(canpos_sensor):
    s = canpos_sensor(model="th", node_id=5, ideal=True, magnet=100)
    assert s.state()["node_id"] == 5
    s.control.magnet(0, 250.0)
    assert wait_for(lambda: abs(s.control.positions()[0] - 250.0) < 0.01)
    with pytest.raises(ControlError, match="gremlins"):
        s.control.fault("gremlins", on=True)
    with pytest.raises(ControlError):
        s.control.magnet(7, 10.0)
    assert s.state()["faults"] == []
    assert s.control.timing()["cycle_us"] > 0


def test_control_client_reconnects_after_the_idle_timeout(canpos_sensor):
    # The sensor closes control connections idle past the timeout (docs/CONTROL.md); the
    # client's next request goes on a new connection, once, transparently.
    s = canpos_sensor(model="th", node_id=6, ideal=True, magnet=100, control_idle_timeout=0.3)
    assert s.state()["node_id"] == 6
    time.sleep(1.0)
    s.control.magnet(0, 321.0)
    assert wait_for(lambda: abs(s.control.positions()[0] - 321.0) < 0.01)


def test_sdo_and_tpdo_through_python_canopen(canpos_bus, canpos_sensor):
    s = canpos_sensor(model="th", node_id=127, ideal=True, magnet=300)
    net = network_on(canpos_bus)
    try:
        node = canopen.RemoteNode(127, canopen.ObjectDictionary())
        net.add_node(node)
        step_nm = int.from_bytes(node.sdo.upload(0x6005, 1), "little")
        steps = int.from_bytes(node.sdo.upload(0x6020, 1), "little", signed=True)
        assert abs(steps * step_nm / 1e6 - 300.0) < 0.01
        s.control.magnet(0, 420.0, wait=True)
        steps = int.from_bytes(node.sdo.upload(0x6020, 1), "little", signed=True)
        assert abs(steps * step_nm / 1e6 - 420.0) < 0.01
        pdos = []
        net.subscribe(0x1FF, lambda cob, data, ts: pdos.append(bytes(data)))
        net.nmt.send_command(0x01)
        assert wait_for(lambda: len(pdos) >= 10)
    finally:
        net.disconnect()


def test_order_code_picks_the_model(canpos_sensor):
    s = canpos_sensor(order_code="EP00600MD341C304241Z02", node_id=10)
    st = s.state()
    assert st["model"] == "e-series"
    assert len(st["true_mm"]) == 2


def test_node_guarding_through_the_hub(canpos_bus, canpos_sensor):
    canpos_sensor(model="th", node_id=127)
    net = network_on(canpos_bus)
    try:
        node = canopen.RemoteNode(127, canopen.ObjectDictionary())
        net.add_node(node)
        answers = []
        net.subscribe(0x77F, lambda cob, data, ts: answers.append(bytes(data)))
        node.nmt.start_node_guarding(0.05)
        time.sleep(0.6)
        node.nmt.stop_node_guarding()
        time.sleep(0.05)
        assert len(answers) >= 5, answers
        assert all(len(a) == 1 and a[0] & 0x7F == 0x7F for a in answers), answers
        toggles = [a[0] >> 7 for a in answers]
        assert all(x != y for x, y in zip(toggles, toggles[1:])), toggles
    finally:
        net.disconnect()


def test_node_guarding_with_true_remote_frames_through_the_canpos_interface(canpos_bus,
                                                                           canpos_sensor):
    """python-canopen guards through ``can.Bus(interface="canpos")``: its guard requests reach
    the hub as remote frames (a second listener sees them with the RTR bit), and the node
    answers each with its state and an alternating toggle bit."""
    canpos_sensor(model="th", node_id=127)
    watcher = can.Bus(**canpos_bus.python_can())
    net = network_on(canpos_bus)
    try:
        node = canopen.RemoteNode(127, canopen.ObjectDictionary())
        net.add_node(node)
        answers = []
        net.subscribe(0x77F, lambda cob, data, ts: answers.append(bytes(data)))
        node.nmt.start_node_guarding(0.05)
        seen = []
        end = time.monotonic() + 0.6
        while time.monotonic() < end:
            m = watcher.recv(0.1)
            if m is not None and m.arbitration_id == 0x77F:
                seen.append(m)
        node.nmt.stop_node_guarding()
        time.sleep(0.05)
        requests = [m for m in seen if m.is_remote_frame]
        assert len(requests) >= 5, seen
        assert len(answers) >= 5, answers
        assert all(len(a) == 1 and a[0] & 0x7F == 0x7F for a in answers), answers
        toggles = [a[0] >> 7 for a in answers]
        assert all(x != y for x, y in zip(toggles, toggles[1:])), toggles
        stamps = [m.timestamp for m in seen]
        assert stamps == sorted(stamps), "bus timeline stamps are monotonic"
    finally:
        net.disconnect()
        watcher.shutdown()


def test_python_can_stock_socketcand_client_still_works(canpos_bus, canpos_sensor):
    with can.Bus(**canpos_bus.python_can("socketcand")) as bus:
        canpos_sensor(model="th", node_id=5)
        end = time.monotonic() + 10
        while time.monotonic() < end:
            m = bus.recv(0.5)
            if m is not None and m.arbitration_id == 0x705:
                assert bytes(m.data) == b"\x00"
                break
        else:
            raise AssertionError("no boot-up of node 5")


def test_python_can_sees_the_boot_up(canpos_bus, canpos_sensor):
    with can.Bus(**canpos_bus.python_can()) as bus:
        canpos_sensor(model="tmi", node_id=33)
        end = time.monotonic() + 10
        while time.monotonic() < end:
            m = bus.recv(0.5)
            if m is not None and m.arbitration_id == 0x700 + 33:
                assert bytes(m.data) == b"\x00"
                break
        else:
            pytest.fail("no boot-up of node 33")


def test_fixtures_clean_up_after_a_failing_test(pytester, tmp_path):
    """A test that fails with a sensor running: afterwards neither the sensor's control port
    nor the hub listens any more."""
    ports = tmp_path / "ports"
    pytester.makepyfile(f"""
        def test_fails(canpos_bus, canpos_sensor):
            s = canpos_sensor(model="th", node_id=9)
            open({str(ports)!r}, "w").write(f"{{canpos_bus.port}} {{s.control_port}}")
            assert False, "on purpose"
    """)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(failed=1)
    for port in map(int, ports.read_text().split()):
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()


def test_the_readme_example_passes(pytester):
    """The README's pytest example, as a user copies it."""
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    block = readme.split("## Dashboard and Python", 1)[1].split("```python\n", 1)[1]
    pytester.makepyfile(block.split("```", 1)[0])
    pytester.runpytest_subprocess("-p", "no:cacheprovider").assert_outcomes(passed=1)
