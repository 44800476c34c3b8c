"""python-canopen against canpos sensors on a Vector SIL Kit network (docs/SILKIT.md), through
`canpos bus bridge silkit://… socketcand://…`: a `sil-kit-registry` on 127.0.0.1, a TH and a
TMI in their own `canpos run` processes on the SIL Kit network, the bridge to the suite's
socketcand hub, and python-canopen on the hub.

Needs scripts/silkit.sh (target/silkit); without it the tests are skipped, unless
CANPOS_SILKIT_REQUIRED=1 (the test command sets it), where they fail.
"""
import os
import subprocess
import time
from pathlib import Path

import canopen
import pytest

from conftest import BIN, ROOT, transports

REGISTRY = os.environ.get(
    "CANPOS_SILKIT_REGISTRY",
    str(ROOT / "target" / "silkit" / "unpacked" / "SilKit_py" / "bin" / "sil-kit-registry"),
)
# Wall-clock bound for processes to start on a loaded machine.
START = 60.0


@pytest.fixture
def registry(tmp_path):
    if "socketcand" not in transports():
        # The SocketCAN pass (inside the UML guest) is about SocketCAN; SIL Kit runs once, in
        # the socketcand pass on the host.
        pytest.skip("SIL Kit runs in the socketcand pass")
    if not Path(REGISTRY).exists():
        if os.environ.get("CANPOS_SILKIT_REQUIRED") == "1":
            pytest.fail(f"CANPOS_SILKIT_REQUIRED=1 but no {REGISTRY} (scripts/silkit.sh)")
        pytest.skip(f"no {REGISTRY} (scripts/silkit.sh)")
    cfg = tmp_path / "registry.yaml"
    proc = subprocess.Popen(
        [REGISTRY, "--listen-uri", "silkit://127.0.0.1:0", "--generate-configuration", str(cfg),
         "--log", "off"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    end = time.monotonic() + START
    uri = None
    while uri is None:
        if cfg.exists():
            for line in cfg.read_text().splitlines():
                if "RegistryUri:" in line:
                    uri = line.split("RegistryUri:")[1].strip().strip("'\"")
        if uri is None:
            assert proc.poll() is None, "sil-kit-registry ended"
            assert time.monotonic() < end, "sil-kit-registry did not listen"
            time.sleep(0.02)
    yield uri
    proc.kill()
    proc.wait()


def start(args, log):
    return subprocess.Popen([BIN, *args], stdin=subprocess.DEVNULL, stdout=log,
                            stderr=subprocess.STDOUT)


def wait_text(path, needle, proc):
    end = time.monotonic() + START
    while needle not in path.read_text():
        assert proc.poll() is None, path.read_text()
        assert time.monotonic() < end, f"no `{needle}` in: {path.read_text()}"
        time.sleep(0.02)


@pytest.fixture
def rig(registry, hub, tmp_path):
    """TH (node 5) and TMI (node 6) on the SIL Kit network `can0`, simulated by `canpos bus
    netsim` at 125 kbit/s (issue 32's rig), bridged to the hub."""
    bus = f"{registry}/can0"
    procs = []
    try:
        log = tmp_path / "netsim.log"
        netsim = start(["bus", "netsim", "--registry", registry, "--network", "can0",
                        "--bitrate", "125", "--participant", "netsim"], log.open("w"))
        procs.append(netsim)
        wait_text(log, "simulating can0 at 125 kbit/s", netsim)
        for model, serial, node in (("th", 31, 5), ("tmi", 32, 6)):
            log = tmp_path / f"{model}.log"
            p = start(["run", "--model", model, "--serial", str(serial), "--node-id", str(node),
                       "--bus", bus, "--state-dir", str(tmp_path)], log.open("w"))
            procs.append(p)
            wait_text(log, f"as {model}-{serial};", p)
        log = tmp_path / "bridge.log"
        bridge = start(["bus", "bridge", f"{bus}?participant=bridge",
                        f"socketcand://127.0.0.1:{hub}/can0"], log.open("w"))
        procs.append(bridge)
        yield tmp_path
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_python_canopen_reaches_sensors_on_sil_kit_through_the_bridge(rig, hub):
    net = canopen.Network()
    net.connect(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
    try:
        th = net.add_node(5, canopen.ObjectDictionary())
        tmi = net.add_node(6, canopen.ObjectDictionary())
        # SDO through the bridge; the bridge's SIL Kit participant may need a moment to be
        # known to the sensors' participants: a few tries.
        serial = None
        for _ in range(20):
            try:
                serial = th.sdo.upload(0x1018, 4)
                break
            except canopen.SdoCommunicationError:
                time.sleep(0.2)
        assert serial == (31).to_bytes(4, "little")
        assert tmi.sdo.upload(0x1008, 0) == b"TMI"
        # NMT start: the TH's TPDO1 (0x185) reaches python-canopen.
        seen = []
        net.subscribe(0x185, lambda cob, data, ts: seen.append(bytes(data)))
        net.nmt.send_command(0x01)
        end = time.monotonic() + START
        while len(seen) < 5:
            assert time.monotonic() < end, "no TPDO from the TH on SIL Kit"
            time.sleep(0.05)
    finally:
        net.disconnect()
    # Every frame went through canpos's bus timeline: each sensor and the bridge say so.
    for name in ("th", "tmi", "bridge"):
        text = (rig / f"{name}.log").read_text()
        assert "network can0: simulated by 'netsim' (bit-timed)" in text, text
