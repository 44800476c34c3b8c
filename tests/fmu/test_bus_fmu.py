"""The bus-simulation FMU (issue 31 item 3, docs/FMU.md "The bus-simulation FMU"): three sensor
FMUs and a controller (this test, through fmpy's fmi3 API) on canpos's bus-simulation FMU at
125 kbit/s give the frames, in the same order and at the same end-of-frame times (within one
bit time), that the same scene gives on a `mem://` bus in canpos's native runtime; an
overloaded bus shows the TMI's "TPDO1 sending will occur partially" reaction (EMCY 0x6000 and
0x1002 bit 15, TMI manual 002 §1.14 / §1.15; docs/BUS.md) and the TH's and E-Series' CAN
overrun (0x8110)."""

import json
import os
import pathlib
import subprocess
import sys

import pytest

sys.path.insert(0, os.path.dirname(__file__))
from cosim import CoSim, Fmu  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]

KBPS = 125
BIT_NS = 1_000_000 // KBPS
SENSORS = [("th", 1), ("e-series", 2), ("tmi", 3)]
END_US = 320_000


@pytest.fixture(scope="module")
def bus_fmus(fmus, tmp_path_factory):
    """The three model FMUs (conftest) and a 4-node bus-simulation FMU at 125 kbit/s, written
    by `canpos fmu --bus-simulation`."""
    exe = os.environ.get("CANPOS_BIN", str(ROOT / "target/debug/canpos"))
    path = tmp_path_factory.mktemp("bus-fmu") / "bus4.fmu"
    args = ["--bus-simulation", "--nodes", "4", "--bitrate", str(KBPS), "--output", str(path)]
    subprocess.run([exe, "fmu", *args], check=True, timeout=300)
    return {**fmus, "bus4": str(path)}


@pytest.fixture(scope="module")
def bus_scene_exe():
    """The native reference (crates/fmu/examples/bus_scene.rs), built by cargo."""
    subprocess.run(
        ["cargo", "build", "--quiet", "--locked", "-p", "canpos-fmu", "--example", "bus_scene"],
        cwd=ROOT, check=True, timeout=1800,
    )
    target = os.environ.get("CARGO_TARGET_DIR", str(ROOT / "target"))
    return os.path.join(target, "debug", "examples", "bus_scene")


def sdo_write_u16(node, index, sub, value):
    return [0x600 + node, [0x2B, index & 0xFF, index >> 8, sub, value & 0xFF, value >> 8, 0, 0]]


def scene():
    """Boot-up; event timers to 20 ms by SDO (pre-operational); NMT start: a light phase;
    back to pre-operational, the TMI and the E-Series to 2 ms and the TH to 1 ms; NMT start:
    more than 125 kbit/s carries, so the losers' transmit queues (the E-Series' 0x182, the
    TMI's 0x183) fill and overflow."""
    ctl = []
    for k, (_, node) in enumerate(SENSORS):
        ctl.append([20_500 + 3_000 * k] + sdo_write_u16(node, 0x1800, 5, 20))
    ctl.append([40_500, 0x000, [0x01, 0x00]])
    ctl.append([90_500, 0x000, [0x80, 0x00]])
    for k, (node, ms) in enumerate([(3, 2), (2, 2), (1, 1)]):
        ctl.append([92_500 + 3_000 * k] + sdo_write_u16(node, 0x1800, 5, ms))
    ctl.append([110_500, 0x000, [0x01, 0x00]])
    return {
        "bitrate": KBPS,
        "end_us": END_US,
        "sensors": [{"model": m, "node_id": n} for m, n in SENSORS],
        "controller": ctl,
    }


def native(tmp_path, bus_scene_exe):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene()))
    out = subprocess.run(
        [bus_scene_exe, str(path)], capture_output=True, text=True, timeout=600, check=True
    ).stdout
    return [
        (f["id"], bytes(f["data"]), f["end_ns"]) for f in map(json.loads, out.splitlines())
    ]


def through_fmus(fmus):
    s = scene()
    bus = Fmu(fmus["bus4"], "bus")
    bus.start({"bitrate": ("UInt32", KBPS)})
    nodes, first = [], []
    for k, (model, node_id) in enumerate(SENSORS):
        n = Fmu(fmus[model], f"{model}{node_id}")
        for _, data in n.start(
            {"node_id": ("UInt8", node_id), "bitrate": ("UInt16", KBPS)}, ["CAN"]
        ):
            first.append((k, data))
        nodes.append(n)
    sim = CoSim(bus, nodes, "Node4", BIT_NS, first)
    ctl = [(at * 1000, can_id, data) for at, can_id, data in s["controller"]]
    sim.run(END_US * 1000, ctl)
    for f in nodes + [bus]:
        f.close()
    return sim.received


def test_three_sensors_through_the_bus_fmu_as_on_a_mem_bus(tmp_path, bus_fmus, bus_scene_exe):
    want = native(tmp_path, bus_scene_exe)
    got = through_fmus(bus_fmus)
    ids = lambda log: [(i, d) for i, d, _ in log]
    # The scene did what it is for: boot-ups, SDO answers, TPDOs of all three, and the
    # overload's EMCYs.
    seen = {i for i, _, _ in want}
    for can_id in (0x701, 0x702, 0x703, 0x581, 0x582, 0x583, 0x181, 0x182, 0x183):
        assert can_id in seen, hex(can_id)
    first_diff = next(
        (k for k, (a, b) in enumerate(zip(ids(want), ids(got))) if a != b), None
    )
    assert first_diff is None and len(want) == len(got), (
        f"{len(want)} frames natively, {len(got)} through the FMUs; first difference at "
        f"{first_diff}: native {want[max(first_diff - 2, 0) : first_diff + 3] if first_diff is not None else ''} "
        f"fmu {got[max(first_diff - 2, 0) : first_diff + 3] if first_diff is not None else ''}"
    )
    late = [(a, b) for a, b in zip(want, got) if abs(a[2] - b[2]) > BIT_NS]
    assert not late, f"{len(late)} frames more than one bit time apart: {late[:5]}"
    # The overload: the TMI's "TPDO1 sending will occur partially", EMCY 0x6000 (error
    # register bit 0, manufacturer bytes 1/0/0); the E-Series' CAN overrun 0x8110; the TH,
    # whose 0x181 wins every arbitration, loses nothing.
    emcy = [(i, d[0] | d[1] << 8, d[2:], t) for i, d, t in got if 0x81 <= i <= 0x83]
    late = [(i, code, rest) for i, code, rest, t in emcy if t > 111_000_000]
    assert (0x83, 0x6000, bytes([0x01, 0x01, 0, 0, 0, 0])) in late, emcy
    assert any(i == 0x82 and code == 0x8110 for i, code, _ in late), emcy
    assert not any(i == 0x81 for i, _, _ in late), emcy
