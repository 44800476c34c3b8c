"""Benchmark (docs/BENCHMARKS.md, not a test): N TH sensor FMUs (node-ids 1 … N) and the
controller on one bus-simulation FMU, for S seconds of co-simulation time, routed by
tests/fmu/cosim.py with fmpy. The controller starts every node (NMT start all) at 50 ms; the
sensors then send TPDO1 at their default 1 ms event timer, far more than the bus carries, so
the bus runs busy from then on. Prints the wall time and what the bus carried.

    CANPOS_BIN=target/release/canpos PYTHONPATH=<fmpy> \\
        python3 tests/fmu/bench_bus_fmu.py --nodes 127 --seconds 10 --bitrate 125
"""

import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(__file__))
from fmpy import extract  # noqa: E402

from cosim import CoSim, Fmu  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--nodes", type=int, default=127)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--bitrate", type=int, default=125)
    a = ap.parse_args()
    exe = os.environ.get("CANPOS_BIN", str(ROOT / "target/release/canpos"))
    out = pathlib.Path(tempfile.mkdtemp())
    th, bus_path = out / "th.fmu", out / "bus.fmu"
    subprocess.run([exe, "fmu", "--model", "th", "-o", str(th)], check=True)
    subprocess.run([exe, "fmu", "--bus-simulation", "--nodes", str(a.nodes + 1),
                    "--bitrate", str(a.bitrate), "-o", str(bus_path)], check=True)
    shared = extract(str(th), unzipdir=str(out / "th"))
    bus_dir = extract(str(bus_path), unzipdir=str(out / "bus"))
    t0 = time.perf_counter()
    bus = Fmu(str(bus_path), "bus", unzipdir=bus_dir)
    bus.start({})
    nodes, first = [], []
    for k in range(a.nodes):
        n = Fmu(str(th), f"th{k + 1}", unzipdir=shared)
        for _, data in n.start({"node_id": ("UInt8", k + 1), "bitrate": ("UInt16", a.bitrate)},
                               ["CAN"]):
            first.append((k, data))
        nodes.append(n)
    setup = time.perf_counter() - t0
    sim = CoSim(bus, nodes, f"Node{a.nodes + 1}", 1_000_000 // a.bitrate, first)
    t1 = time.perf_counter()
    sim.run(int(a.seconds * 1e9), [(50_000_000, 0x000, [0x01, 0x00])])
    wall = time.perf_counter() - t1
    frames = bus.fmu.getUInt64([bus.vr["frames"]])[0]
    lost = bus.fmu.getUInt64([bus.vr["frames_lost"]])[0]
    for f in nodes + [bus]:
        f.close()
    shutil.rmtree(out, ignore_errors=True)
    print(f"{a.nodes} TH FMUs + controller on the bus FMU at {a.bitrate} kbit/s, "
          f"{a.seconds} s simulated: {wall:.1f} s wall ({setup:.1f} s to instantiate), "
          f"{frames} frames carried, {len(sim.received)} received by the controller, "
          f"{lost} lost to full queues")


if __name__ == "__main__":
    main()
