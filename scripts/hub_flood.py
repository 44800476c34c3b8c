#!/usr/bin/env python3
# Usage: scripts/hub_flood.py PORT HUB_PID N [HOLD_S] (docs/BENCHMARKS.md, "The hub at 10,000 clients").
# 10,000 socketcand connections against a canpos hub: each tries the handshake into raw mode on
# channel "flood" and then stays connected and silent. Prints how many got in / were refused,
# then samples the hub's threads, descriptors and RSS while they hold.
import socket, sys, time, os
port, hub_pid, n = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
conns, admitted, refused, failed = [], 0, 0, 0
t0 = time.time()
for i in range(n):
    try:
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.settimeout(5)
        first = s.recv(64)
        if first.startswith(b"< hi >"):
            s.sendall(b"< open flood >"); s.recv(64)
            s.sendall(b"< rawmode >"); s.recv(64)
            admitted += 1
            conns.append(s)
        else:
            refused += 1
            s.close()
    except OSError as e:
        failed += 1
t1 = time.time()
def proc(pid):
    st = open(f"/proc/{pid}/status").read()
    get = lambda k: [l.split()[1] for l in st.splitlines() if l.startswith(k)][0]
    return int(get("Threads:")), len(os.listdir(f"/proc/{pid}/fd")), int(get("VmRSS:"))
th, fds, rss = proc(hub_pid)
print(f"connections {n}: admitted {admitted}, refused {refused}, failed {failed} in {t1-t0:.1f} s; "
      f"hub: threads {th}, fds {fds}, rss {rss} KiB", flush=True)
time.sleep(float(sys.argv[4]) if len(sys.argv) > 4 else 5)
th, fds, rss = proc(hub_pid)
print(f"after holding: threads {th}, fds {fds}, rss {rss} KiB", flush=True)
