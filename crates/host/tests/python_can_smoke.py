#!/usr/bin/env python3
"""Smoke test: two python-can socketcand buses talk through the canpos hub.

Usage: python_can_smoke.py PORT   (a hub must already listen on 127.0.0.1:PORT)
Exit status 0 on success.
"""
import sys
import time

import can


def main() -> int:
    port = int(sys.argv[1])
    a = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="can0")
    b = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="can0")
    other = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="can1")
    try:
        sent = [
            can.Message(arbitration_id=0x601, data=[0x40, 0x00, 0x10, 0, 0, 0, 0, 0], is_extended_id=False),
            can.Message(arbitration_id=0x77F, data=[], is_extended_id=False),
            can.Message(arbitration_id=0x1ABCDE, data=[1, 2, 3], is_extended_id=True),
        ]
        for m in sent:
            a.send(m)
        for m in sent:
            r = b.recv(timeout=2.0)
            if r is None:
                print(f"FAIL: no frame for {m}")
                return 1
            if (r.arbitration_id, bytes(r.data), r.is_extended_id) != (m.arbitration_id, bytes(m.data), m.is_extended_id):
                print(f"FAIL: sent {m}, got {r}")
                return 1
            print(f"ok: {r}")
        # Round trip the other way, and timing.
        t0 = time.perf_counter()
        n = 200
        for i in range(n):
            b.send(can.Message(arbitration_id=0x581, data=[i & 0xFF], is_extended_id=False))
            r = a.recv(timeout=2.0)
            if r is None or r.arbitration_id != 0x581 or r.data[0] != i & 0xFF:
                print(f"FAIL: round {i}: {r}")
                return 1
        dt = (time.perf_counter() - t0) / n
        print(f"ok: {n} frames b->a, {dt * 1e6:.0f} us per send+recv")
        # The sender got nothing back, the other channel nothing at all.
        for bus, name in ((a, "sender"), (b, "sender b"), (other, "can1")):
            r = bus.recv(timeout=0.1)
            if r is not None:
                print(f"FAIL: {name} received {r}")
                return 1
        print("PASS")
        return 0
    finally:
        for bus in (a, b, other):
            bus.shutdown()


if __name__ == "__main__":
    sys.exit(main())
