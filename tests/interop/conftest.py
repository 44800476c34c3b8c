"""Fixtures: a bus (canpos socketcand hub, or Linux SocketCAN vcan0), canpos sensors on it, and a
python-canopen network on it.

python-canopen and python-can are the independent master here: everything they see goes
through the same socketcand protocol or SocketCAN interface a user's tools would use.

Every test runs once per transport (`test_x[socketcand]`, `test_x[socketcan]`): socketcand always,
SocketCAN where `vcan0` exists (the UML step of scripts/test.sh runs the suite inside a guest
with vcan0: scripts/uml/run-in-uml.sh). `CANPOS_INTEROP_TRANSPORTS=socketcan` (comma-separated)
picks the transports explicitly.
"""
import os
import socket
import subprocess
import time
from pathlib import Path

import can
import canopen
import pytest

ROOT = Path(__file__).resolve().parents[2]
BIN = os.environ.get("CANPOS_BIN", str(ROOT / "target" / "release" / "canpos"))
VCAN = "vcan0"


def vcan_available():
    return Path(f"/sys/class/net/{VCAN}").exists()


def transports():
    env = os.environ.get("CANPOS_INTEROP_TRANSPORTS")
    if env:
        return [t.strip() for t in env.split(",") if t.strip()]
    return ["socketcand", "socketcan"] if vcan_available() else ["socketcand"]


@pytest.fixture(params=transports())
def transport(request):
    if request.param == "socketcan" and not vcan_available():
        pytest.skip(f"no {VCAN} here (run under scripts/uml/run-in-uml.sh)")
    return request.param


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.02)
    raise RuntimeError(f"nothing listens on 127.0.0.1:{port}")


class Proc:
    """A canpos child process that is always reaped."""

    def __init__(self, args, log):
        self.args = [BIN, *args]
        self.log = open(log, "ab")
        self.p = subprocess.Popen(self.args, stdout=self.log, stderr=subprocess.STDOUT)

    def stop(self, sig_kill=False):
        if self.p.poll() is None:
            self.p.kill() if sig_kill else self.p.terminate()
            try:
                self.p.wait(5)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)
        self.log.close()


@pytest.fixture
def hub(canpos_bus):
    """The port of the hub every socketcand test runs on: the ``canpos_bus`` fixture of the
    canpos Python package (python/, installed into the suite's venv by scripts/test.sh)."""
    return canpos_bus.port


@pytest.fixture
def bus_url(transport, request):
    if transport == "socketcan":
        return f"socketcan://{VCAN}"
    return f"socketcand://127.0.0.1:{request.getfixturevalue('hub')}/can0"


@pytest.fixture
def network(transport, bus_url):
    net = canopen.Network()
    if transport == "socketcan":
        net.connect(interface="socketcan", channel=VCAN)
        # The master's receive queue: the default (about 200 frames) overflows in the slow UML
        # guest when python falls behind a sensor's 1000 TPDOs/s, and the frames a test waits
        # for go with it. 8 MiB asked (the kernel doubles it), as a master host would size it.
        so_rcvbufforce = 33  # linux/socket.h; root may exceed rmem_max
        try:
            net.bus.socket.setsockopt(socket.SOL_SOCKET, so_rcvbufforce, 8 << 20)
        except OSError:
            net.bus.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    else:
        port = int(bus_url.rsplit(":", 1)[1].split("/")[0])
        net.connect(interface="socketcand", host="127.0.0.1", port=port, channel="can0")
    try:
        yield net
    finally:
        net.disconnect()


@pytest.fixture
def sensors(bus_url, tmp_path):
    """Starts canpos sensors on the hub: ``sensors(model="th", node_id=127, ...)``; ``model=None``
    leaves the model to ``extra`` (e.g. ``--order-code``)."""
    procs = []

    def start(model="th", node_id=None, serial=None, state_dir=None, extra=(), ideal=True,
              magnet=250):
        args = ["run", "--bus", bus_url, "--state-dir", str(state_dir or tmp_path / "state")]
        if model is not None:
            args += ["--model", model]
        if ideal:
            args += ["--ideal"]
        if magnet is not None:
            args += ["--magnet", str(magnet)]
        if node_id is not None:
            args += ["--node-id", str(node_id)]
        if serial is not None:
            args += ["--serial", str(serial)]
        args += list(extra)
        p = Proc(args, tmp_path / f"run-{len(procs)}.log")
        procs.append(p)
        return p

    yield start
    for p in procs:
        p.stop()


def wait_bootup(network, node_id, proc_start, timeout=10.0):
    """Starts the sensor with ``proc_start()`` and waits for its boot-up on 0x700 + id."""
    seen = []

    def cb(cob_id, data, ts):
        if len(data) == 1 and data[0] == 0:
            seen.append(ts)

    network.subscribe(0x700 + node_id, cb)
    try:
        proc = proc_start()
        end = time.monotonic() + timeout
        while not seen and time.monotonic() < end:
            time.sleep(0.005)
        assert seen, f"no boot-up from node {node_id}"
        return proc
    finally:
        network.unsubscribe(0x700 + node_id, cb)


def add_node(network, node_id, model="th"):
    node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    return node


def export_eds(model, path):
    subprocess.run([BIN, "eds", "--model", model, "--output", str(path)], check=True)
    return path


def check_defaults(node, od):
    """Reads every readable object of ``od`` that has a default from ``node`` by SDO and checks
    it; returns how many were checked."""
    checked = 0
    for obj in od.values():
        for var in (obj.values() if hasattr(obj, "values") else [obj]):
            if not var.readable or var.default is None or var.data_type in (0x0F,):
                continue
            raw = node.sdo.upload(var.index, var.subindex)
            if var.data_type == 0x09:
                assert raw.decode() == var.default, (hex(var.index), var.subindex)
            else:
                assert var.decode_raw(raw) == var.default, (hex(var.index), var.subindex, raw)
            checked += 1
    return checked


def assert_period(stamps, period, window, at_least, at_most, tries=3, key=lambda s: s):
    """A producer's frames every ``period`` s: ``stamps`` is the list its subscription appends to
    (``key`` gives a receive time in s). The list is emptied and watched for ``window`` s, which
    must then hold ``at_least`` to ``at_most`` frames with the median gap within 20 % of the
    period. A median, not a count in a window, so that one stall does not hide a wrong period.
    A window the machine stalled through (about 100 ms every few minutes here; longer and more
    often in the loaded UML guest, whose late frames arrive in bursts of short gaps) is watched
    again, up to ``tries`` windows: a wrong period fails every one of them."""
    why = None
    for _ in range(tries):
        del stamps[:]
        time.sleep(window)
        times = [key(s) for s in list(stamps)]
        gaps = sorted(b - a for a, b in zip(times, times[1:]))
        if not at_least <= len(times) <= at_most:
            why = ("count", len(times), (at_least, at_most), gaps)
        elif abs(gaps[len(gaps) // 2] - period) > 0.2 * period:
            why = ("median gap", gaps[len(gaps) // 2], period, gaps)
        else:
            return list(stamps)
    raise AssertionError(why)


def guard_for_half_a_second(node, answers):
    """Node guarding by python-canopen every 50 ms for 0.5 s; ``answers`` (filled by a
    subscription to the node's 0x700 + id) must then hold at least 5 pre-operational answers
    with the toggle bit alternating."""
    node.nmt.start_node_guarding(0.05)
    time.sleep(0.5)
    node.nmt.stop_node_guarding()
    time.sleep(0.05)
    assert len(answers) >= 5, answers
    assert all(len(a) == 1 and a[0] & 0x7F == 0x7F for a in answers), answers
    toggles = [a[0] >> 7 for a in answers]
    assert all(x != y for x, y in zip(toggles, toggles[1:])), toggles


def ctl(port, req):
    """One request on canpos's JSON-lines control interface."""
    import json

    with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
        s.sendall((json.dumps(req) + "\n").encode())
        return json.loads(s.makefile().readline())
