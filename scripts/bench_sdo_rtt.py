#!/usr/bin/env python3
"""SDO round trip of python-canopen against a canpos sensor through a socketcand hub (issue 6).

The counterpart of `canpos bench sdo-rtt`: the same request (SDO upload of 0x1000), the same hub
and sensor, so the two figures compare the masters. Prints one JSON line.

    python3 -m venv target/venv-bench && target/venv-bench/bin/pip install canopen python-can
    target/venv-bench/bin/python scripts/bench_sdo_rtt.py --host 127.0.0.1 --port 29536 \
        --channel can0 --node 127 --count 5000
"""
import argparse
import json
import math
import time

import canopen


def quantile(sorted_us, q):
    k = min(max(math.ceil(len(sorted_us) * q), 1), len(sorted_us))
    return sorted_us[k - 1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=29536)
    ap.add_argument("--channel", default="can0")
    ap.add_argument("--node", type=int, default=127)
    ap.add_argument("--count", type=int, default=5000)
    a = ap.parse_args()
    net = canopen.Network()
    net.connect(interface="socketcand", host=a.host, port=a.port, channel=a.channel)
    try:
        node = canopen.RemoteNode(a.node, canopen.ObjectDictionary())
        net.add_node(node)
        want = node.sdo.upload(0x1000, 0)
        for _ in range(100):
            node.sdo.upload(0x1000, 0)
        us = []
        for _ in range(a.count):
            t = time.perf_counter_ns()
            v = node.sdo.upload(0x1000, 0)
            us.append((time.perf_counter_ns() - t) / 1e3)
            assert v == want, v
        us.sort()
        print(json.dumps({
            "bench": "sdo-rtt",
            "client": "python-canopen " + canopen.__version__,
            "bus": f"socketcand://{a.host}:{a.port}/{a.channel}",
            "node": a.node,
            "count": len(us),
            "median_us": quantile(us, 0.5),
            "p99_us": quantile(us, 0.99),
            "mean_us": sum(us) / len(us),
            "min_us": us[0],
            "max_us": us[-1],
        }))
    finally:
        net.disconnect()


if __name__ == "__main__":
    main()
