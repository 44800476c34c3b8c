"""The CiA 401 I/O module of examples/io-401.eds (`canpos run --eds examples/io-401.eds
--control ADDR`, docs/EDS_DEVICE.md) against python-canopen: its default PDO mapping read back by
SDO, inputs set through canpos's control interface (`canpos ctl set-input`, the JSON request)
received by python-canopen's TPDO API, and outputs written by python-canopen's RPDO API (what a
master transmits to the module's RPDOs) shown by `canpos ctl state`.

The RPDO test needs the stack's RPDO service (issue 33 item 1): without it the module serves
no 0x1400-0x17FF and the test fails on reading the RPDO parameters by SDO (0x06020000)."""
import json
import subprocess
import threading
import time

import canopen

from conftest import BIN, ROOT, ctl, free_port, wait_bootup, wait_port

IO401 = ROOT / "examples" / "io-401.eds"
NODE = 7


def start_io401(network, sensors):
    """The module on node-id 7 with a control interface; returns (node, control port)."""
    port = free_port()
    wait_bootup(network, NODE, lambda: sensors(
        model=None, ideal=False, magnet=None, node_id=NODE,
        extra=["--eds", str(IO401), "--control", f"127.0.0.1:{port}"]))
    wait_port(port)
    node = canopen.RemoteNode(NODE, str(IO401))
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    return node, port


def canpos_ctl(port, *args):
    """`canpos ctl --control 127.0.0.1:PORT ARGS…`: (exit code, stdout, stderr)."""
    p = subprocess.run([BIN, "ctl", "--control", f"127.0.0.1:{port}", *args],
                       capture_output=True, text=True, timeout=20)
    return p.returncode, p.stdout, p.stderr


def process(state, index, sub):
    for o in state["process"]:
        if int(o["index"], 16) == index and o["sub"] == sub:
            return o
    raise AssertionError(f"0x{index:04X}/{sub} not in the state: {state}")


class Received:
    """Every reception of a TPDO, with its mapped values (python-canopen's TPDO API)."""

    def __init__(self, pdo):
        self.values = []
        self.cond = threading.Condition()
        pdo.add_callback(self.on)

    def on(self, pdo):
        with self.cond:
            self.values.append([v.raw for v in pdo.map])
            self.cond.notify_all()

    def wait(self, n, timeout=5.0):
        """The values of the n-th reception (1-based), waiting up to `timeout` for it."""
        end = time.monotonic() + timeout
        with self.cond:
            while len(self.values) < n:
                left = end - time.monotonic()
                assert left > 0, f"TPDO received {len(self.values)} times, not {n}: {self.values}"
                self.cond.wait(left)
            return self.values[n - 1]


def test_io401_eds_imports_in_python_canopen():
    od = canopen.import_od(str(IO401), node_id=NODE)
    assert od[0x1000].default == 0x000F0191
    assert od[0x6000][1].data_type == canopen.objectdictionary.UNSIGNED8
    assert od[0x6401][12].data_type == canopen.objectdictionary.INTEGER16
    assert od[0x6411][1].data_type == canopen.objectdictionary.INTEGER16
    assert od[0x1800][1].default == 0x180 + NODE
    assert od[0x1403][1].default == 0x500 + NODE
    assert od[0x1A03][1].default == 0x64010910
    assert od[0x1603][4].default == 0x64110C10
    assert od.device_information.nr_of_RXPDO == 4 and od.device_information.nr_of_TXPDO == 4


def test_io401_default_pdo_mapping_and_identity(network, sensors):
    node, port = start_io401(network, sensors)
    sdo = node.sdo
    # Device type: profile 401, digital and analogue inputs and outputs.
    assert sdo["Device type"].raw == 0x000F0191
    assert sdo["Identity object"]["Product code"].raw == 0x401
    node.tpdo.read()
    maps = [[(v.index, v.subindex) for v in node.tpdo[n].map] for n in (1, 2, 3, 4)]
    assert maps == [[(0x6000, 1), (0x6000, 2)]] + [
        [(0x6401, c) for c in range(4 * k + 1, 4 * k + 5)] for k in range(3)]
    assert [node.tpdo[n].cob_id for n in (1, 2, 3, 4)] == [0x187, 0x287, 0x387, 0x487]
    assert all(node.tpdo[n].trans_type == 255 for n in (1, 2, 3, 4))
    st = ctl(port, {"cmd": "state"})
    assert st["ok"] and st["nmt"] == "pre-operational" and st["node_id"] == NODE, st
    assert len(st["process"]) == 28, st


def test_inputs_set_through_the_control_interface_reach_python_canopens_tpdos(network, sensors):
    node, port = start_io401(network, sensors)
    node.tpdo.read()
    digital, analogue = Received(node.tpdo[1]), Received(node.tpdo[3])
    node.nmt.state = "OPERATIONAL"
    deadline = time.monotonic() + 5
    while ctl(port, {"cmd": "state"})["nmt"] != "operational":
        assert time.monotonic() < deadline, "not operational"
        time.sleep(0.02)
    # `canpos ctl set-input` (digital inputs 1-8) and the JSON request (analogue input 7).
    code, out, err = canpos_ctl(port, "set-input", "0x6000", "1", "0xA5")
    assert code == 0, err
    assert json.loads(out)["changed"] is True
    assert digital.wait(1) == [0xA5, 0]
    r = ctl(port, {"cmd": "set-input", "index": "0x6401", "sub": 7, "value": -1234})
    assert r["ok"] and r["changed"], r
    assert analogue.wait(1) == [0, 0, -1234, 0]
    assert ctl(port, {"cmd": "set-input", "index": 0x6000, "sub": 2, "value": 3})["ok"]
    assert digital.wait(2) == [0xA5, 3]
    # Refused: an output, a value out of range, an object that does not exist; nothing sent.
    code, _, err = canpos_ctl(port, "set-input", "0x6200", "1", "1")
    assert code == 1 and "is an output" in err, err
    r = ctl(port, {"cmd": "set-input", "index": "0x6401", "sub": 1, "value": 40000})
    assert not r["ok"] and "out of range" in r["error"], r
    r = ctl(port, {"cmd": "set-input", "index": "0x6000", "sub": 3, "value": 1})
    assert not r["ok"] and "does not exist" in r["error"], r
    # The SDO view is the same values.
    assert node.sdo[0x6401][7].raw == -1234
    assert node.sdo[0x6000][1].raw == 0xA5
    time.sleep(0.3)
    assert len(digital.values) == 2 and len(analogue.values) == 1, (digital.values, analogue.values)


def test_outputs_written_by_python_canopens_rpdos_show_in_ctl_state(network, sensors):
    """Needs the RPDO service (issue 33 item 1)."""
    node, port = start_io401(network, sensors)
    # The RPDO parameters by SDO, as a master configures them.
    node.rpdo.read()
    maps = [[(v.index, v.subindex) for v in node.rpdo[n].map] for n in (1, 2, 3, 4)]
    assert maps == [[(0x6200, 1), (0x6200, 2)]] + [
        [(0x6411, c) for c in range(4 * k + 1, 4 * k + 5)] for k in range(3)]
    assert [node.rpdo[n].cob_id for n in (1, 2, 3, 4)] == [0x207, 0x307, 0x407, 0x507]
    node.nmt.state = "OPERATIONAL"
    deadline = time.monotonic() + 5
    while ctl(port, {"cmd": "state"})["nmt"] != "operational":
        assert time.monotonic() < deadline, "not operational"
        time.sleep(0.02)
    rpdo1, rpdo4 = node.rpdo[1], node.rpdo[4]
    rpdo1.map[0].raw = 0x3C
    rpdo1.map[1].raw = 0x81
    rpdo1.transmit()
    for i, v in enumerate([-32768, -1, 1, 32767]):
        rpdo4.map[i].raw = v
    rpdo4.transmit()
    want = {(0x6200, 1): 0x3C, (0x6200, 2): 0x81, (0x6411, 9): -32768, (0x6411, 10): -1,
            (0x6411, 11): 1, (0x6411, 12): 32767}
    deadline = time.monotonic() + 5
    while True:
        code, out, err = canpos_ctl(port, "state")
        assert code == 0, err
        st = json.loads(out)
        got = {k: process(st, *k)["value"] for k in want}
        if got == want:
            break
        assert time.monotonic() < deadline, f"outputs {got}, not {want}"
        time.sleep(0.05)
    assert all(process(st, *k)["direction"] == "output" for k in want)
    # The outputs no RPDO wrote stay at their defaults; the SDO view agrees.
    assert process(st, 0x6411, 1)["value"] == 0
    assert node.sdo[0x6200][1].raw == 0x3C
    assert node.sdo[0x6411][9].raw == -32768
