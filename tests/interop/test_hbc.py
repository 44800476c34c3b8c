"""`canpos run --eds` with a heartbeat consumer (0x1016) and error behaviour (0x1029), driven by
python-canopen (issue 33 items 2 and 3): a heartbeat producer of python-canopen's own (periodic
0x700 + id frames from its network) is consumed, its loss raises EMCY 0x8130 (seen in
python-canopen's emcy consumer), and 0x1029 sub 1 = 0 / 1 / 2 each give their NMT state (seen in
the device's own heartbeat). tests/interop/hbc-device.eds is examples/io-device.eds with the two
objects and without its RPDO."""
import struct
import time

import canopen
import pytest

from conftest import ROOT, wait_bootup
from test_eds_device import abort_code, start_eds

HBC_EDS = ROOT / "tests" / "interop" / "hbc-device.eds"
ID = 5
PEER = 0x20
# The consumer time (ms) and python-canopen's producer period (s): generous, for a loaded host.
CONSUMER_MS = 600
PRODUCER_S = 0.1


def hbc_node(network):
    node = canopen.RemoteNode(ID, str(HBC_EDS))
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    return node


def produce(network):
    """python-canopen as the heartbeat producer of node PEER (operational)."""
    return network.send_periodic(0x700 + PEER, b"\x05", PRODUCER_S)


def state_becomes(node, want, timeout=5.0):
    """The device's own heartbeat says `want` within `timeout` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if node.nmt.wait_for_heartbeat(timeout=2.0) == want:
            return True
    return False


def test_a_heartbeat_of_python_canopen_is_consumed_and_its_loss_raises_8130(network, sensors):
    wait_bootup(network, ID, lambda: start_eds(sensors, HBC_EDS, node_id=ID))
    node = hbc_node(network)
    sdo = node.sdo
    sdo[0x1029][1].raw = 1  # no state change: this test watches the EMCY
    sdo[0x1016][1].raw = PEER << 16 | CONSUMER_MS
    # CiA 301: a node-id watched twice is refused with 0x06040043 and changes nothing.
    dup = struct.pack("<I", PEER << 16 | 900)
    assert abort_code(lambda: sdo.download(0x1016, 2, dup)) == 0x06040043
    assert sdo[0x1016][2].raw == 0
    assert abort_code(lambda: sdo.download(0x1029, 1, b"\x03")) == 0x06090030
    # Monitoring starts with the first heartbeat: nothing while python-canopen is silent.
    time.sleep(2 * CONSUMER_MS / 1000)
    assert node.emcy.log == []
    task = produce(network)
    try:
        time.sleep(1.5)
        assert node.emcy.log == [], "heartbeats keep coming"
    finally:
        task.stop()
    lost = node.emcy.wait(0x8130, timeout=5)
    assert lost is not None, "EMCY 0x8130 after the producer stopped"
    assert lost.register & 0x10, "communication bit of the error register"
    assert lost.data[0] == PEER, "the lost node-id in the first manufacturer byte"
    assert sdo[0x1001].raw & 0x10
    # Its heartbeat again: the error clears (EMCY 0x0000, register 0).
    node.emcy.reset()
    task = produce(network)
    try:
        back = node.emcy.wait(0x0000, timeout=5)
        assert back is not None and back.register == 0
        assert sdo[0x1001].raw == 0
    finally:
        task.stop()


@pytest.mark.parametrize("behaviour, after", [(0, "PRE-OPERATIONAL"), (1, "OPERATIONAL"),
                                              (2, "STOPPED")])
def test_error_behaviour_0_1_2_on_a_lost_heartbeat(network, sensors, behaviour, after):
    wait_bootup(network, ID, lambda: start_eds(sensors, HBC_EDS, node_id=ID))
    node = hbc_node(network)
    sdo = node.sdo
    sdo[0x1029][1].raw = behaviour
    sdo[0x1016][3].raw = PEER << 16 | CONSUMER_MS
    sdo[0x1017].raw = 100
    node.nmt.state = "OPERATIONAL"
    assert state_becomes(node, "OPERATIONAL")
    task = produce(network)
    try:
        time.sleep(1.0)
        assert node.nmt.wait_for_heartbeat(timeout=2.0) == "OPERATIONAL"
    finally:
        task.stop()
    if behaviour != 2:
        # (A stopped node sends no EMCY until it leaves Stopped.)
        assert node.emcy.wait(0x8130, timeout=5) is not None
    assert state_becomes(node, after), f"0x1029 = {behaviour}: {node.nmt.state}"
    # And it stays there (two more heartbeats).
    for _ in range(2):
        assert node.nmt.wait_for_heartbeat(timeout=2.0) == after
