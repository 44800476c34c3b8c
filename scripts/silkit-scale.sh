#!/usr/bin/env bash
# Scale run of canpos on Vector SIL Kit with canpos as the network simulator (issue 32,
# docs/BENCHMARKS.md "SIL Kit: canpos bus netsim at scale"): one sil-kit-registry on
# 127.0.0.1, one `canpos bus netsim` process simulating NETWORKS CAN networks, and on each
# network one `canpos scenario` process running SENSORS TH sensors (operational, moving), for
# DURATION seconds, and one `canpos record` per network as a listener (the sensors of one
# scenario process share its one SIL Kit controller and hear each other inside the process,
# so the recorder is the controller that receives what they send). Prints, per network, the
# frames the simulator carried, its deliveries and the frames the recorder got, requests
# refused (queue full / cancelled) and every controller's state; and the CPU time of each
# process (utime + stime from /proc, as % of one core over the run).
#
# Usage: scripts/silkit-scale.sh [DURATION_S [NETWORKS [SENSORS [KBPS]]]]   (60 16 8 125)
# Needs a release build (cargo build --release -p canpos) and SIL Kit (scripts/silkit.sh).
# Loopback only; every process is started here and stopped at the end (trap).
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION=${1:-60}
NETWORKS=${2:-16}
SENSORS=${3:-8}
KBPS=${4:-125}
BIN=${CANPOS_BIN:-$PWD/target/release/canpos}
[ -x "$BIN" ] || { echo "silkit-scale: no $BIN (cargo build --release -p canpos)" >&2; exit 1; }
eval "$(scripts/silkit.sh | tail -n2 | sed 's/^/export /')"
WORK=$(mktemp -d /tmp/canpos-silkit-scale.XXXXXX)
PIDS=()
cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  wait 2>/dev/null || true
  rm -rf "$WORK"
}
trap cleanup EXIT

PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
URI="silkit://127.0.0.1:$PORT"
"$CANPOS_SILKIT_REGISTRY" --listen-uri "$URI" --log off >"$WORK/registry.log" 2>&1 &
PIDS+=($!)
REG_PID=$!
for _ in $(seq 100); do
  (exec 3<>/dev/tcp/127.0.0.1/"$PORT") 2>/dev/null && break
  sleep 0.1
done

NETARGS=()
for n in $(seq 1 "$NETWORKS"); do NETARGS+=(--network "CAN$n"); done
# The simulator runs a little longer than the sensors, so its counters cover the whole run.
${NETSIM_WRAP:-} "$BIN" -q bus netsim --registry "$URI" "${NETARGS[@]}" --bitrate "$KBPS" \
  --stats-interval 0 --duration $((DURATION + 8)) >"$WORK/netsim.out" 2>&1 &
PIDS+=($!)
NETSIM_PID=$!
sleep 2

REC_PIDS=()
for n in $(seq 1 "$NETWORKS"); do
  "$BIN" -q record --bus "$URI/CAN$n" --format candump \
    --duration $((DURATION + 4)) "$WORK/rec-$n.log" >"$WORK/rec-$n.out" 2>&1 &
  PIDS+=($!)
  REC_PIDS+=($!)
done
sleep 1
SCEN_PIDS=()
for n in $(seq 1 "$NETWORKS"); do
  f="$WORK/scenario-$n.toml"
  {
    echo "bus = \"$URI/CAN$n\""
    echo "bus_bitrate = $KBPS"
    echo "state_dir = \"$WORK/state-$n\""
    echo "duration = $DURATION"
    for s in $(seq 1 "$SENSORS"); do
      echo "[[sensor]]"
      echo "model = \"th\""
      echo "node_id = $s"
      echo "serial = $((n * 100 + s))"
      echo "nmt = \"operational\""
      echo "motion = \"sine:center=500,amp=300,period=$((2 + s))\""
    done
  } >"$f"
  "$BIN" -q scenario "$f" --participant "scale-$n" >"$WORK/scenario-$n.log" 2>&1 &
  PIDS+=($!)
  SCEN_PIDS+=($!)
  # Staggered: 16 processes of 8 sensors starting at once on a loaded 2-core machine missed
  # the scenario's 10 s start-up answer (7 of 16 in the first run).
  sleep 1
done

ticks() { awk '{print $14 + $15}' "/proc/$1/stat" 2>/dev/null || echo gone; }
# `canpos bus netsim` simulates in a worker process it restarts after a SIL Kit crash (D57):
# its CPU is its own and its worker's (a worker restarted within the window is not counted).
netsim_ticks() {
  local t c w
  t=$(ticks "$1")
  [ "$t" = gone ] && { echo gone; return; }
  for c in $(pgrep -P "$1"); do
    w=$(ticks "$c")
    [ "$w" = gone ] || t=$((t + w))
  done
  echo "$t"
}
HZ=$(getconf CLK_TCK)
declare -A T0
ALL=("$NETSIM_PID" "$REG_PID" "${SCEN_PIDS[@]}" "${REC_PIDS[@]}")
for p in "${ALL[@]}"; do T0[$p]=$(ticks "$p"); done
T0[$NETSIM_PID]=$(netsim_ticks "$NETSIM_PID")
START=$(date +%s.%N)
# The window ends before the first scenario process (started NETWORKS s before START) ends:
# /proc of a process that has exited reads 0 ticks, which printed negative figures.
WINDOW=$((DURATION - NETWORKS - 2))
[ "$WINDOW" -ge 1 ] || WINDOW=1
sleep "$WINDOW"
declare -A T1
for p in "${ALL[@]}"; do T1[$p]=$(ticks "$p"); done
T1[$NETSIM_PID]=$(netsim_ticks "$NETSIM_PID")
END=$(date +%s.%N)
wait "${SCEN_PIDS[@]}" "${REC_PIDS[@]}" 2>/dev/null || true
NETSIM_STATUS=0
wait "$NETSIM_PID" 2>/dev/null || NETSIM_STATUS=$?

WALL=$(echo "$END - $START" | bc -l)
cpu() {
  # A process gone before the window closed has no figure (not a negative one).
  if [ "${T0[$1]}" = gone ] || [ "${T1[$1]}" = gone ]; then echo "n/a(exited)"; return; fi
  echo "scale=1; 100 * (${T1[$1]} - ${T0[$1]}) / $HZ / $WALL" | bc -l
}
echo "== SIL Kit scale run: $NETWORKS networks x $SENSORS TH sensors, $KBPS kbit/s, ${DURATION} s"
echo "== processes: 1 registry, 1 canpos bus netsim, $NETWORKS canpos scenario"
echo "netsim exit status=$NETSIM_STATUS (0 expected)"
echo "netsim restarts after a SIL Kit crash=$(grep -c "part crashed" "$WORK/netsim.out")"
echo "cpu_pct netsim=$(cpu "$NETSIM_PID") registry=$(cpu "$REG_PID")"
i=1
for p in "${SCEN_PIDS[@]}"; do echo "cpu_pct scenario-$i=$(cpu "$p")"; i=$((i + 1)); done
i=1
for p in "${REC_PIDS[@]}"; do echo "cpu_pct record-$i=$(cpu "$p")"; i=$((i + 1)); done
python3 - "$WORK/netsim.out" "$DURATION" "$WORK" <<'EOF'
import json, os, sys
nets = [json.loads(l) for l in open(sys.argv[1]) if l.startswith("{")]
dur = float(sys.argv[2])
work = sys.argv[3]
tot = {"frames": 0, "deliveries": 0, "queue_full": 0, "canceled": 0, "bad_frames": 0}
states = {}
for n in nets:
    for k in tot:
        tot[k] += n[k]
    for c in n["controllers"]:
        key = (c["mode"], c["state"], "left" if c["left"] else "present")
        states[key] = states.get(key, 0) + 1
    lost = sum((c["lost_overflow"] or 0) + (c["lost_bus_off"] or 0) for c in n["controllers"])
    rec = os.path.join(work, "rec-" + n["network"][3:] + ".log")
    recorded = sum(1 for _ in open(rec)) if os.path.exists(rec) else 0
    print(f'{n["network"]}: frames={n["frames"]} ({n["frames"] / dur:.0f}/s) '
          f'deliveries={n["deliveries"]} recorded={recorded} queue_full={n["queue_full"]} '
          f'canceled={n["canceled"]} lost_in_controllers={lost} '
          f'controllers={len(n["controllers"])}')
print("total:", " ".join(f"{k}={v}" for k, v in tot.items()))
print("controller states (mode/error state/at exit):",
      ", ".join(f"{m}/{s}/{p}: {c}" for (m, s, p), c in sorted(states.items(), key=str)))
EOF
for n in $(seq 1 "$NETWORKS"); do
  if grep -qiE "error|panick" "$WORK/scenario-$n.log"; then
    echo "scenario-$n log:"; grep -iE "error|panick" "$WORK/scenario-$n.log" | head -5
  fi
done
