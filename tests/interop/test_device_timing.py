"""A device's own timing against python-canopen's timeouts: an SDO response delay longer than
the master's timeout makes the master time out, a shorter one does not; the boot delay and the
stall fault (docs/CONTROL.md, "Device timing")."""
import time

import pytest
from canopen.sdo.exceptions import SdoCommunicationError

from conftest import add_node, ctl, free_port, wait_bootup


def test_sdo_delay_against_the_master_timeout(network, sensors):
    wait_bootup(network, 127, lambda: sensors("th", extra=["--sdo-delay", "150"]))
    node = add_node(network, 127)
    node.sdo.MAX_RETRIES = 1  # one attempt (0 would retry forever)
    node.sdo.RESPONSE_TIMEOUT = 0.05
    with pytest.raises(SdoCommunicationError):
        node.sdo.upload(0x1008, 0)
    time.sleep(0.3)  # the late answer passes by
    node.sdo.RESPONSE_TIMEOUT = 2.0
    t0 = time.monotonic()
    assert node.sdo.upload(0x1000, 0) == bytes.fromhex("96010800")
    assert time.monotonic() - t0 >= 0.15


def test_boot_delay_and_stall_through_the_control_interface(network, sensors):
    port = free_port()
    t0 = time.monotonic()
    wait_bootup(network, 127, lambda: sensors(
        "th", extra=["--boot-delay", "300", "--control", f"127.0.0.1:{port}"]))
    assert time.monotonic() - t0 >= 0.3
    assert ctl(port, {"cmd": "timing", "sdo_delay_ms": -1})["ok"] is False
    r = ctl(port, {"cmd": "fault", "name": "stall", "on": True, "value": 0.5})
    assert r["ok"] and r["faults"] == ["stall"], r
    node = add_node(network, 127)
    node.sdo.MAX_RETRIES = 1  # one attempt (0 would retry forever)
    node.sdo.RESPONSE_TIMEOUT = 0.2
    with pytest.raises(SdoCommunicationError):
        node.sdo.upload(0x1008, 0)
    time.sleep(0.5)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    assert node.sdo.upload(0x1000, 0) == bytes.fromhex("96010800")
