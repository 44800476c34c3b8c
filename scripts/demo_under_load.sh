#!/bin/sh
# The README's demo for 60 s beside two CPU hogs per core, watched by `canpos monitor` through
# the hub (docs/CLOCK.md, issue 36 item 1). Prints the TPDO count, the TPDO periods on the bus
# timeline that are not 1 ms (± 0.2 ms: the stuff bits of a changing position), the largest
# gap, the EMCY lines and the demo's warnings. Everything is bounded by `timeout`.
#
#   scripts/demo_under_load.sh [BIN]   (default target/release/canpos)
set -eu
B=${1:-target/release/canpos}
D=$(mktemp -d)
trap 'rm -rf "$D"' EXIT
P=$(python3 -c "import socket;s=socket.socket();s.bind(('127.0.0.1',0));print(s.getsockname()[1])")
timeout 75 "$B" demo --listen "127.0.0.1:$P" --duration 60 >"$D/demo.out" 2>"$D/demo.err" &
DP=$!
sleep 0.7
timeout 65 "$B" monitor --bus "socketcand://127.0.0.1:$P/can0" >"$D/mon.out" 2>"$D/mon.err" &
MP=$!
cores=$(nproc)
i=0
while [ "$i" -lt $((2 * cores)) ]; do
    timeout 60 sh -c 'yes >/dev/null' &
    i=$((i + 1))
done
echo "load at start: $(cat /proc/loadavg)"
wait "$DP" || true
wait "$MP" || true
echo "load at end: $(cat /proc/loadavg)"
python3 - "$D" <<'PY'
import re, sys
d = sys.argv[1]
t, emcy = [], []
for line in open(f"{d}/mon.out"):
    m = re.match(r"\[\s*([\d.]+)\] node \d+ (\S+)", line)
    if m and m.group(2) == "TPDO1":
        t.append(float(m.group(1)))
    elif m and m.group(2) == "EMCY":
        emcy.append(line.strip())
gaps = [b - a for a, b in zip(t, t[1:])]
off = [g for g in gaps if abs(g - 0.001) > 0.0002]
print(f"TPDOs {len(t)} over {t[-1] - t[0]:.2f} s of bus time; periods not 1 ms: {len(off)}; "
      f"largest gap {max(gaps) * 1e3:.1f} ms; EMCY lines {len(emcy)}")
for e in emcy[:6]:
    print("  ", e)
err = open(f"{d}/demo.err").read().splitlines()
warns = [l for l in err if " WARN " in l]
print(f"demo warnings: {len(warns)}")
for l in warns[:6] + [l for l in err if "runtime stopped" in l]:
    print("  ", l[28:])
PY
