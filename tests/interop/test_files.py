"""Capture and log files (issue 11, docs/FILES.md) against independent readers and writers:
tshark decodes a `canpos record` pcapng as CANopen, python-can reads the ASC and candump logs
canpos records, and `canpos replay` plays logs python-can's writers made.

These run on the host's socketcand hub only (tshark and the files do not depend on the
transport); the UML pass, which sets CANPOS_INTEROP_TRANSPORTS=socketcan, leaves them out.
"""
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import canopen
import pytest

from conftest import BIN, Proc, free_port, wait_port, ctl

pytestmark = pytest.mark.skipif(
    os.environ.get("CANPOS_INTEROP_TRANSPORTS", "socketcand") == "socketcan",
    reason="file formats are checked in the host pass over socketcand",
)

TSHARK_CANOPEN = ["-d", "can.subdissector,canopen"]


def connect(port):
    net = canopen.Network()
    net.connect(interface="socketcand", host="127.0.0.1", port=port, channel="can0")
    return net


def recorder(tmp_path, url, name):
    return Proc(["record", str(tmp_path / name), "--bus", url], tmp_path / f"rec-{name}.log")


def stop_recorder(p):
    # Every frame is flushed as it is written: SIGINT (ctrl-c) keeps the whole file.
    p.p.send_signal(signal.SIGINT)
    try:
        p.p.wait(5)
    except subprocess.TimeoutExpired:
        p.stop()
    p.stop()


def test_tshark_decodes_a_recorded_session_as_canopen(hub, tmp_path):
    assert shutil.which("tshark"), "tshark missing (scripts/deps.sh installs it)"
    url = f"socketcand://127.0.0.1:{hub}/can0"
    names = ("s.pcapng", "s.pcap", "s.asc", "s.log")
    recs = [recorder(tmp_path, url, n) for n in names]
    # `canpos record` creates its file once it is on the bus.
    end = time.monotonic() + 10
    while not all((tmp_path / n).exists() for n in names) and time.monotonic() < end:
        time.sleep(0.02)
    assert all((tmp_path / n).exists() for n in names)
    net = connect(hub)
    control = free_port()
    sensor = None
    try:
        booted = []
        net.subscribe(0x705, lambda cob, data, ts: booted.append(bytes(data)))
        sensor = Proc(["run", "--bus", url, "--model", "th", "--node-id", "5", "--ideal",
                       "--magnet", "250", "--state-dir", str(tmp_path / "st"),
                       "--control", f"127.0.0.1:{control}"], tmp_path / "run.log")
        end = time.monotonic() + 10
        while b"\x00" not in booted and time.monotonic() < end:
            time.sleep(0.01)
        assert b"\x00" in booted, "no boot-up"
        wait_port(control)
        node = canopen.RemoteNode(5, canopen.ObjectDictionary())
        net.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 2.0
        assert int.from_bytes(node.sdo.upload(0x1018, 1), "little") == 0x40  # expedited
        # Heartbeat 100 ms, written in a segmented download.
        node.sdo.download(0x1017, 0, (100).to_bytes(2, "little"), force_segment=True)
        node.nmt.send_command(0x01)  # start: TPDOs
        time.sleep(0.35)
        assert ctl(control, {"cmd": "fault", "name": "missing-magnet", "on": True})["ok"]
        time.sleep(0.1)
        net.lss.send_switch_state_global(net.lss.CONFIGURATION_STATE)
        assert net.lss.inquire_lss_address(canopen.lss.CS_INQUIRE_VENDOR_ID) == 0x40
        net.lss.send_switch_state_global(net.lss.WAITING_STATE)
        node.nmt.send_command(0x02)  # stop
        time.sleep(0.3)
    finally:
        net.disconnect()
        if sensor:
            sensor.stop()
        for r in recs:
            stop_recorder(r)

    out = subprocess.run(
        ["tshark", "-r", str(tmp_path / "s.pcapng"), *TSHARK_CANOPEN, "-T", "fields",
         "-E", "separator=|", "-e", "can.id", "-e", "_ws.col.Protocol", "-e", "_ws.col.Info"],
        check=True, capture_output=True, text=True).stdout
    rows = [line.split("|", 2) for line in out.splitlines() if line]
    assert len(rows) > 20, out
    # Every frame is decoded by the CANopen dissector.
    assert {p for _, p, _ in rows} == {"CANopen"}, out
    infos = [i for _, _, i in rows]

    def has(text):
        assert any(text in i for i in infos), f"no `{text}` in:\n{out}"

    has("NMT Error Control: Boot-up [0x5]")
    has("NMT: Start remote node [0x5]")
    has("NMT: Stop remote node [0x5]")
    has("Default-SDO (rx): Initiate upload request")
    has("Default-SDO (tx): Initiate upload response")
    has("Default-SDO (rx): Initiate download request")
    has("Default-SDO (rx): Download segment request")
    has("Default-SDO (tx): Download segment response")
    has("PDO1 (tx)")
    has("EMCY")
    has("NMT Error Control: Operational")
    has("NMT Error Control: Stopped")
    has("LSS (Master): Switch state global protocol: Configuration state")
    has("LSS (Slave): Inquire identity vendor-ID protocol")
    # pcap decodes the same frames.
    out_pcap = subprocess.run(
        ["tshark", "-r", str(tmp_path / "s.pcap"), *TSHARK_CANOPEN, "-T", "fields",
         "-e", "can.id", "-e", "_ws.col.Info"], check=True, capture_output=True, text=True).stdout
    assert len(out_pcap.splitlines()) == len(rows)

    # python-can reads the ASC and candump recordings of the same session: the same frames
    # (the recorders attached together; each saw every frame on the bus).
    def ids(reader):
        return [(m.arbitration_id, bytes(m.data)) for m in reader if not m.is_error_frame]

    from_tshark = [int(cid, 0) for cid, _, _ in rows]
    asc = ids(can.ASCReader(str(tmp_path / "s.asc")))
    log = ids(can.LogReader(str(tmp_path / "s.log")))
    assert [i for i, _ in asc] == from_tshark
    assert log == asc


def replay(path, url, *extra):
    return subprocess.run([BIN, "replay", str(path), "--bus", url, "--speed", "0", *extra],
                          capture_output=True, text=True, timeout=30)


def receive(bus, n, timeout=5.0):
    got = []
    end = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < end:
        m = bus.recv(0.1)
        if m is not None:
            got.append(m)
    return got


def msgs():
    t = 1700000000.0
    return [
        can.Message(timestamp=t, arbitration_id=0x701, data=b"\x00", is_extended_id=False),
        can.Message(timestamp=t + 0.001, is_error_frame=True, data=b"\x00\x00\x02\x00\x00\x00\x00\x00"),
        can.Message(timestamp=t + 0.002, arbitration_id=0x181, is_fd=True, bitrate_switch=True,
                    data=bytes(range(12)), is_extended_id=False),
        can.Message(timestamp=t + 0.003, arbitration_id=0x1ABCDEF0, data=b"\xAA\xBB",
                    is_extended_id=True),
        can.Message(timestamp=t + 0.004, arbitration_id=0x705, is_remote_frame=True, dlc=0,
                    is_extended_id=False),
        can.Message(timestamp=t + 0.005, arbitration_id=0x605, data=bytes(8), is_extended_id=False),
    ]


EXPECTED = [(0x701, b"\x00"), (0x1ABCDEF0, b"\xAA\xBB"), (0x705, b""), (0x605, bytes(8))]


@pytest.mark.parametrize("ext", ["log", "asc"])
def test_replay_of_python_can_logs(hub, tmp_path, ext):
    """python-can's `can.Logger` (CanutilsLogWriter for .log, ASCWriter for .asc) writes a log
    with an error frame and a CAN FD frame; canpos plays the classical frames, counts the rest."""
    path = tmp_path / f"pc.{ext}"
    with can.Logger(str(path)) as w:
        for m in msgs():
            w.on_message_received(m)
    url = f"socketcand://127.0.0.1:{hub}/can0"
    with can.Bus(interface="socketcand", host="127.0.0.1", port=hub, channel="can0") as bus:
        r = replay(path, url)
        assert r.returncode == 0, r.stderr
        got = receive(bus, len(EXPECTED))
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == EXPECTED, r.stderr
    assert "replayed 4 frames" in r.stderr
    assert "1 error frames, 1 CAN FD frames" in r.stderr, r.stderr


def test_replay_of_a_candump_log_with_error_fd_and_rtr_lines(hub, tmp_path):
    """can-utils' `candump -L` lines: error frames, FD frames (`##`), RTR with and without DLC
    (a canpos hub carries both, with canpos's `< rtr on >` extension, which the listener here
    takes too through the canpos package's python-can interface), and one malformed line."""
    path = tmp_path / "cu.log"
    path.write_text(
        "(1700000000.000000) can0 701#00\n"
        "(1700000000.000100) can0 20000088#0000020000000000\n"
        "(1700000000.000200) can0 20000040#\n"
        "(1700000000.000300) can0 181##1DEADBEEF00112233AABBCCDD\n"
        "(1700000000.000400) can0 12345678##0112233445566778899\n"
        "(1700000000.000500) can0 705#R\n"
        "(1700000000.000600) can0 705#R1\n"
        "(1700000000.000700) can0 garbage\n"
        "(1700000000.000800) can0 1ABCDEF0#AABB\n"
    )
    url = f"socketcand://127.0.0.1:{hub}/can0"
    with can.Bus(interface="canpos", host="127.0.0.1", port=hub, channel="can0") as bus:
        r = replay(path, url)
        assert r.returncode == 1
        assert f"{path}:8: bad frame `garbage`" in r.stderr, r.stderr
        assert receive(bus, 1, timeout=0.5) == []
        r = replay(path, url, "--on-malformed", "skip")
        assert r.returncode == 0, r.stderr
        got = receive(bus, 4)
    assert [(m.arbitration_id, m.is_remote_frame, m.dlc, bytes(m.data)) for m in got] == [
        (0x701, False, 1, b"\x00"), (0x705, True, 0, b""), (0x705, True, 1, b""),
        (0x1ABCDEF0, False, 2, b"\xAA\xBB")]
    assert ("skipped 5 lines: 2 error frames, 2 CAN FD frames, 0 frames this bus cannot carry "
            "(remote frames with a DLC), 1 malformed") in r.stderr, r.stderr


EDS_VALIDATE = str(Path(sys.executable).with_name("eds-validate"))
# eds-utils 0.3.1 reads an empty object list (`SupportedObjects=0`, which CiA 306 allows) as a
# missing section: the E-Series has no manufacturer objects. docs/FILES.md says so.
EDS_UTILS_WRONG = {"AUTO-FIXED: Section [ManufacturerObjects] was missing"}
# It also does not know CiA 306's `ParameterValue` (the current value in a DCF, §4.6.1).
EDS_UTILS_WRONG_DCF = re.compile(r'AUTO-FIXED: Unknown entry "ParameterValue" in \[[0-9A-Fa-f]{4}(sub[0-9A-Fa-f]+)?\]')


def validate(path):
    """eds-utils' `eds-validate` on `path`: what it reports, less what it gets wrong."""
    r = subprocess.run([EDS_VALIDATE, str(path)], capture_output=True, text=True)
    reported = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == (1 if reported else 0), r
    return [line for line in reported
            if line not in EDS_UTILS_WRONG and not EDS_UTILS_WRONG_DCF.fullmatch(line)]


EXPORTS = [("--model", "th"), ("--model", "e-series"), ("--model", "tmi"),
           ("--order-code", "EP00600MD341C304241Z02"),
           ("--order-code", "THM0500MC011DNNC304221Z02"), ("--order-code", "TMI0300000611106")]


@pytest.mark.parametrize("how,what", EXPORTS)
def test_eds_exports_validate_and_import(tmp_path, how, what):
    path = tmp_path / "x.eds"
    subprocess.run([BIN, "eds", how, what, "--output", str(path)], check=True)
    assert validate(path) == []
    od = canopen.import_od(str(path), node_id=5)
    assert od[0x1018][1].default is not None
    info = dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)
    assert info["OrderCode"] == (what if how == "--order-code" else "")
    assert info["CreationDate"] == time.strftime("%m-%d-%Y", time.gmtime())
    if what == "EP00600MD341C304241Z02":
        assert od[0x1000].default == 0x000A0196
        assert od[0x650A][3].default == 60000
        assert [od[0x6402][s].default for s in (1, 2)] == [60000, 60000]


def start_unit(tmp_path, name, args, net, node_id):
    booted = []
    net.subscribe(0x700 + node_id, lambda cob, data, ts: booted.append(bytes(data)))
    p = Proc(["run", *args], tmp_path / f"{name}.log")
    end = time.monotonic() + 10
    while b"\x00" not in booted and time.monotonic() < end:
        time.sleep(0.01)
    net.unsubscribe(0x700 + node_id)
    assert b"\x00" in booted, (tmp_path / f"{name}.log").read_text()
    return p


def read_all(node, od):
    """Every readable object of `od`, uploaded from `node`: {(index, sub): bytes}."""
    out = {}
    for obj in od.values():
        for var in (obj.values() if hasattr(obj, "values") else [obj]):
            if var.readable:
                try:
                    out[(var.index, var.subindex)] = node.sdo.upload(var.index, var.subindex)
                except canopen.SdoAbortedError as e:  # the same refusal counts as the same
                    out[(var.index, var.subindex)] = f"abort 0x{e.code:08X}"
    return out


@pytest.mark.parametrize("unit", [("--model", "th"), ("--order-code", "EP00600MD341C304241Z02"),
                                  ("--model", "tmi")])
def test_dcf_of_a_configured_unit_starts_the_same_unit(hub, tmp_path, unit):
    """Configure a unit over LSS (node-id, bit rate) and SDO (heartbeat, a remapped TPDO, cam
    limits), export its DCF over SDO and from its state file, start a new unit from the DCF
    on another channel and compare every object over SDO."""
    url = f"socketcand://127.0.0.1:{hub}/can0"
    url2 = f"socketcand://127.0.0.1:{hub}/can1"
    net = connect(hub)
    net2 = canopen.Network()
    net2.connect(interface="socketcand", host="127.0.0.1", port=hub, channel="can1")
    procs = []
    try:
        common = ["--ideal", "--magnet", "250", "--magnet", "450"] if unit[0] == "--order-code" \
            else ["--ideal", "--magnet", "250"]
        procs.append(start_unit(tmp_path, "a", [*unit, "--bus", url, "--state-dir",
                                                str(tmp_path / "a"), "--serial", "4242", *common],
                                net, 127))
        lss = net.lss
        lss.send_switch_state_global(lss.CONFIGURATION_STATE)
        lss.configure_node_id(20)
        lss.configure_bit_timing(2)  # 500 kbit/s
        lss.store_configuration()
        lss.send_switch_state_global(lss.WAITING_STATE)
        booted = []
        net.subscribe(0x714, lambda c, d, t: booted.append(bytes(d)))
        net.nmt.send_command(0x81)
        end = time.monotonic() + 5
        while not booted and time.monotonic() < end:
            time.sleep(0.01)
        assert booted, "no boot-up as node 20"
        node = canopen.RemoteNode(20, canopen.ObjectDictionary())
        net.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 2.0
        sdo = node.sdo
        sdo.download(0x1017, 0, (250).to_bytes(2, "little"))
        # TPDO1: position of channel 1 only, event timer 20 ms.
        cob = int.from_bytes(sdo.upload(0x1800, 1), "little")
        sdo.download(0x1800, 1, (cob | 0x80000000).to_bytes(4, "little"))
        sdo.download(0x1A00, 0, b"\x00")
        sdo.download(0x1A00, 1, (0x60200120).to_bytes(4, "little"))
        sdo.download(0x1A00, 0, b"\x01")
        sdo.download(0x1800, 1, cob.to_bytes(4, "little"))
        sdo.download(0x1800, 5, (20).to_bytes(2, "little"))
        sdo.download(0x1010, 1, b"save")

        dcf = tmp_path / "unit.dcf"
        r = subprocess.run([BIN, "dcf", "--node", "20", "--bus", url, "--bitrate", "500",
                            "--output", str(dcf), *(unit if unit[0] == "--order-code" else [])],
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        state = next((tmp_path / "a").glob("*.bin"))
        dcf_state = tmp_path / "state.dcf"
        subprocess.run([BIN, "dcf", "--state", str(state), "--output", str(dcf_state),
                        *(unit if unit[0] == "--order-code" else [])], check=True)

        # Both import into python-canopen with the unit's node-id and bit rate.
        for f in (dcf, dcf_state):
            od = canopen.import_od(str(f))
            assert (od.node_id, od.bitrate) == (20, 500_000), f
            assert od[0x1017].value == 250
            assert od[0x1A00][1].value == 0x60200120
            assert validate(f) == []
        text = dcf.read_text()
        assert "[DeviceComissioning]" in text and "LSS_SerialNumber=0x00001092" in text

        procs.append(start_unit(tmp_path, "b", ["--dcf", str(dcf), "--bus", url2, "--state-dir",
                                                str(tmp_path / "b"), *common], net2, 20))
        assert "node_id=20 bitrate_kbps=500" in (tmp_path / "b.log").read_text()
        node2 = canopen.RemoteNode(20, canopen.ObjectDictionary())
        net2.add_node(node2)
        node2.sdo.RESPONSE_TIMEOUT = 2.0
        od = canopen.import_od(str(dcf))
        after = read_all(node2, od)
        before = read_all(node, od)
        diff = {k: (before[k], after.get(k)) for k in before if before[k] != after.get(k)}
        assert diff == {}, {f"0x{i:04X}/{s}": v for (i, s), v in diff.items()}
        assert len(before) > 100
    finally:
        net.disconnect()
        net2.disconnect()
        for p in procs:
            p.stop()
