"""`canpos run --eds` / `--dcf`: a plain CiA 301 device from an EDS or DCF file, driven by
python-canopen. Two files: the EDS canpos exports for the TH, and examples/io-device.eds, a small
generic I/O device written by hand (manufacturer objects of several types with limits, one
TPDO mapping three of them, one RPDO mapping one)."""
import struct
import time

import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError

from conftest import (ROOT, add_node, assert_period, check_defaults, export_eds, guard_for_half_a_second,
                      wait_bootup)

IO_EDS = ROOT / "examples" / "io-device.eds"


def start_eds(sensors, path, node_id=None, state_dir=None, flag="--eds", extra=()):
    return sensors(model=None, ideal=False, magnet=None, node_id=node_id, state_dir=state_dir,
                   extra=[flag, str(path), *extra])


def io_node(network, node_id=5):
    node = canopen.RemoteNode(node_id, str(IO_EDS))
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    return node


def abort_code(fn):
    with pytest.raises(SdoAbortedError) as e:
        fn()
    return e.value.code


def test_exported_th_eds_served_as_a_plain_device(network, sensors, tmp_path):
    eds = export_eds("th", tmp_path / "th.eds")
    wait_bootup(network, 10, lambda: start_eds(sensors, eds, node_id=10))
    node = canopen.RemoteNode(10, str(eds))
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    assert check_defaults(node, node.object_dictionary) > 50
    # The TPDO service runs the file's mapping: TPDO1 position, velocity, cam state.
    node.tpdo.read()
    pdo1 = node.tpdo[1]
    assert pdo1.enabled and pdo1.cob_id == 0x18A
    assert [(v.index, v.subindex) for v in pdo1.map] == [(0x6020, 1), (0x6030, 1), (0x6300, 1)]
    node.nmt.state = "OPERATIONAL"
    pdo1.wait_for_reception(2)
    assert [v.raw for v in pdo1.map] == [0, 0, 0]
    # Limits of the file: 0x6010 preset is INTEGER32 without limits, 0x1017 a plain U16.
    node.sdo["Producer heartbeat time"].raw = 700
    assert node.sdo["Producer heartbeat time"].raw == 700
    assert abort_code(lambda: node.sdo.download(0x1018, 1, b"\0\0\0\0")) == 0x06010002


def test_hand_written_eds_values_and_limits(network, sensors):
    wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5))
    node = io_node(network)
    sdo = node.sdo
    assert sdo["Device type"].raw == 0x000F0191
    assert sdo["Manufacturer device name"].raw == "canpos I/O"
    assert sdo["Firmware tag"].raw == "v1.2-io"
    assert sdo["Identity object"]["Vendor-ID"].raw == 0xCA7
    assert sdo["COB-ID EMCY"].raw == 0x85
    assert sdo["Digital inputs"].raw == 0x5A
    assert sdo["Analogue inputs"]["Analogue input 1"].raw == -1234
    assert sdo["Offset"].raw == -500
    assert sdo["Scale"].raw == 1
    # Limits: too high 0x06090031, too low 0x06090032, BOOLEAN 2 invalid 0x06090030.
    assert abort_code(lambda: sdo.download(0x2101, 0, struct.pack("<H", 1001))) == 0x06090031
    assert abort_code(lambda: sdo.download(0x2101, 0, struct.pack("<H", 0))) == 0x06090032
    assert abort_code(lambda: sdo.download(0x2102, 0, struct.pack("<i", 100001))) == 0x06090031
    assert abort_code(lambda: sdo.download(0x2103, 0, struct.pack("<b", -11))) == 0x06090032
    assert abort_code(lambda: sdo.download(0x2100, 0, b"\x02")) == 0x06090030
    sdo["Scale"].raw = -10
    sdo["Filter time"].raw = 1000
    sdo["Offset"].raw = -100000
    sdo["Output enable"].raw = True
    assert (sdo["Scale"].raw, sdo["Filter time"].raw, sdo["Offset"].raw) == (-10, 1000, -100000)
    assert sdo["Output enable"].raw is True
    # Access types: ro / const refuse writes, wo refuses reads; wrong length; the RPDO's COB-ID.
    assert abort_code(lambda: sdo.download(0x2000, 0, b"\x01")) == 0x06010002
    assert abort_code(lambda: sdo.download(0x1008, 0, b"x")) == 0x06010002
    assert abort_code(lambda: sdo.upload(0x2200, 0)) == 0x06010001
    sdo.download(0x2200, 0, struct.pack("<H", 3))
    assert abort_code(lambda: sdo.download(0x2101, 0, b"\x01")) == 0x06070013
    assert sdo["RPDO1 communication parameter"]["COB-ID used by RPDO"].raw == 0x205
    assert abort_code(lambda: sdo.upload(0x2001, 3)) == 0x06090011


def test_hand_written_eds_tpdo_remap_and_reception(network, sensors):
    wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5))
    node = io_node(network)
    node.tpdo.read()
    pdo1 = node.tpdo[1]
    assert [(v.index, v.subindex) for v in pdo1.map] == [(0x2000, 0), (0x2001, 1), (0x2102, 0)]
    assert not node.tpdo[2].enabled
    node.sdo["Offset"].raw = 4321
    pdo1.clear()
    pdo1.add_variable(0x2101)
    pdo1.add_variable(0x2102)
    pdo1.add_variable(0x2001, 2)
    pdo1.trans_type = 254
    pdo1.event_timer = 20
    pdo1.enabled = True
    pdo1.save()
    node.tpdo.read()
    assert [(v.index, v.subindex) for v in node.tpdo[1].map] == [
        (0x2101, 0), (0x2102, 0), (0x2001, 2)]
    stamps = []
    node.network.subscribe(0x185, lambda c, d, t: stamps.append(t))
    node.nmt.state = "OPERATIONAL"
    node.tpdo[1].wait_for_reception(2)
    assert [v.raw for v in node.tpdo[1].map] == [10, 4321, 2000]
    assert_period(stamps, 0.02, 0.5, 12, 35)
    # A string cannot be mapped (0x06040041); entries change only at count 0 (0x06010000).
    pdo1 = node.tpdo[1]
    pdo1.enabled = False
    pdo1.save()
    entry = struct.pack("<I", 0x21010010)
    assert abort_code(lambda: node.sdo.download(0x1A00, 1, entry)) == 0x06010000
    node.sdo.download(0x1A00, 0, b"\x00")
    assert abort_code(
        lambda: node.sdo.download(0x1A00, 1, struct.pack("<I", 0x23000008))) == 0x06040041


def test_hand_written_eds_rpdo_writes_and_its_deadline_raises_emcy(network, sensors):
    """python-canopen's RPDO API (a master transmits the device's RPDOs): the value it sends is
    what an SDO upload then reads; the RPDO's event timer is its deadline, EMCY 0x8250 when no
    RPDO came in time, cleared (EMCY 0x0000) by the next one; a value beyond the object's
    limits leaves the PDO unprocessed."""
    wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5))
    node = io_node(network)
    emcys = []
    node.emcy.add_callback(lambda e: emcys.append(e.code))
    node.rpdo.read()
    rpdo1 = node.rpdo[1]
    assert rpdo1.enabled and rpdo1.cob_id == 0x205
    assert [(v.index, v.subindex) for v in rpdo1.map] == [(0x2101, 0)]
    rpdo1.event_timer = 200
    rpdo1.save()
    assert node.sdo.upload(0x1400, 5) == struct.pack("<H", 200)
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.1)
    rpdo1["Filter time"].raw = 500
    rpdo1.transmit()
    deadline = time.monotonic() + 2
    while node.sdo["Filter time"].raw != 500:
        assert time.monotonic() < deadline, "RPDO value never landed"
        time.sleep(0.05)
    rpdo1["Filter time"].raw = 1001
    rpdo1.transmit()
    # Nothing more: the 200 ms deadline passes (generous bound for a loaded machine).
    deadline = time.monotonic() + 3
    while 0x8250 not in emcys:
        assert time.monotonic() < deadline, f"no RPDO timeout EMCY: {emcys}"
        time.sleep(0.05)
    assert node.sdo["Filter time"].raw == 500
    assert node.sdo["Error register"].raw & 0x10
    rpdo1["Filter time"].raw = 42
    rpdo1.transmit()
    deadline = time.monotonic() + 2
    while node.sdo["Filter time"].raw != 42 or 0x0000 not in emcys:
        assert time.monotonic() < deadline, f"no error reset: {emcys}"
        time.sleep(0.05)
    assert emcys[emcys.index(0x8250):][:2] == [0x8250, 0x0000]


def test_hand_written_eds_heartbeat_and_guarding(network, sensors):
    wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5))
    node = io_node(network)
    node.sdo["Producer heartbeat time"].raw = 100
    beats, times = [], []
    network.subscribe(0x705, lambda c, d, t: (beats.append(bytes(d)), times.append(t)))
    assert_period(times, 0.1, 1.05, 8, 12)
    assert all(b == b"\x7f" for b in beats)
    node.sdo["Producer heartbeat time"].raw = 0
    time.sleep(0.2)
    beats.clear()
    guard_for_half_a_second(node, beats)


def test_hand_written_eds_store_power_cycle_restore(network, sensors, tmp_path):
    state = tmp_path / "persist"
    p = wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5, state_dir=state))
    node = io_node(network)
    sdo = node.sdo
    sdo["Producer heartbeat time"].raw = 500
    sdo["Filter time"].raw = 321
    # Communication parameters only (0x1010/2).
    sdo.download(0x1010, 2, b"save")
    p.stop()
    p = wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5, state_dir=state))
    assert sdo["Producer heartbeat time"].raw == 500
    assert sdo["Filter time"].raw == 10
    # Application parameters (0x1010/3).
    sdo["Filter time"].raw = 321
    sdo["Offset"].raw = -42
    sdo.download(0x1010, 3, b"save")
    p.stop()
    p = wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5, state_dir=state))
    assert (sdo["Producer heartbeat time"].raw, sdo["Filter time"].raw,
            sdo["Offset"].raw) == (500, 321, -42)
    # Restore all defaults: effective after reset node, and after a power cycle.
    sdo.download(0x1011, 1, b"load")
    node.nmt.send_command(0x81)
    time.sleep(0.3)
    assert (sdo["Producer heartbeat time"].raw, sdo["Filter time"].raw,
            sdo["Offset"].raw) == (0, 10, -500)
    p.stop()
    wait_bootup(network, 5, lambda: start_eds(sensors, IO_EDS, node_id=5, state_dir=state))
    assert sdo["Filter time"].raw == 10
    assert abort_code(lambda: sdo.download(0x1010, 1, b"nope")) == 0x08000020


def test_dcf_from_python_canopen(network, sensors, tmp_path):
    od = canopen.import_od(str(IO_EDS), 5)
    od["Filter time"].value = 77
    od["Offset"].value = -9
    od["Producer heartbeat time"].value = 0
    od.node_id = 0x21
    od.bitrate = 500000
    dcf = tmp_path / "io.dcf"
    canopen.export_od(od, str(dcf), doc_type="dcf")
    text = dcf.read_text()
    assert "ParameterValue=" in text and "[DeviceComissioning]" in text
    p = wait_bootup(network, 0x21, lambda: start_eds(sensors, dcf, flag="--dcf"))
    node = add_node(network, 0x21)
    assert struct.unpack("<H", node.sdo.upload(0x2101, 0))[0] == 77
    assert struct.unpack("<i", node.sdo.upload(0x2102, 0))[0] == -9
    assert struct.unpack("<I", node.sdo.upload(0x1014, 0))[0] == 0x80 + 0x21
    assert struct.unpack("<I", node.sdo.upload(0x1800, 1))[0] == 0x180 + 0x21
    p.stop()
    # --node-id wins over the DCF's NodeID.
    wait_bootup(network, 0x22, lambda: start_eds(sensors, dcf, node_id=0x22, flag="--dcf"))
    node = add_node(network, 0x22)
    assert struct.unpack("<H", node.sdo.upload(0x2101, 0))[0] == 77


def test_malformed_eds_is_refused_with_its_line(tmp_path):
    import subprocess

    from conftest import BIN

    bad = tmp_path / "bad.eds"
    text = IO_EDS.read_text().replace("DataType=0x0006\nAccessType=rw\nDefaultValue=10",
                                      "DataType=0x0042\nAccessType=rw\nDefaultValue=10")
    bad.write_text(text)
    line = text.splitlines().index("DataType=0x0042") + 1
    r = subprocess.run([BIN, "run", "--eds", str(bad), "--bus", "mem://x"],
                       capture_output=True, text=True, timeout=10)
    assert r.returncode == 1
    assert f"bad.eds:{line}: unknown DataType 0x0042" in r.stderr, r.stderr
