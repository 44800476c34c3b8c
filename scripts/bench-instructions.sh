#!/usr/bin/env bash
# Instructions per core operation, measured with callgrind as (I(2N) - I(N)) / N, so process
# start-up and node set-up cancel out (issue 6). Usage:
#   scripts/bench-instructions.sh [BINARY] [N]
# BINARY defaults to the release build of canpos (build it with debug info: the workspace's
# release profile has debug = 1). Prints one line per model and operation.
set -euo pipefail
BIN=${1:-${CARGO_TARGET_DIR:-target}/release/canpos}
N=${2:-100000}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
count() { # model op iterations [extra args…]
    valgrind --tool=callgrind --callgrind-out-file="$tmp/cg.out" \
        "$BIN" bench core --model "$1" --op "$2" --iterations "$3" "${@:4}" >/dev/null 2>"$tmp/err" ||
        { cat "$tmp/err" >&2; exit 1; }
    grep -E '^(summary|totals):' "$tmp/cg.out" | head -1 | awk '{print $2}'
}
for model in th e-series tmi; do
    for op in sdo-upload sdo-download tpdo lss-inquire sdo-upload-alternating sync-tpdo idle foreign-pdo; do
        a=$(count "$model" "$op" "$N")
        b=$(count "$model" "$op" $((2 * N)))
        echo "model=$model op=$op instructions_per_op=$(( (b - a) / N ))"
    done
    # Downloads to other objects: 0x1005 (4 bytes, light checks), 0x1017 (2 bytes, heartbeat).
    for obj in 0x1005 0x1017; do
        a=$(count "$model" sdo-download "$N" --index "$obj")
        b=$(count "$model" sdo-download $((2 * N)) --index "$obj")
        echo "model=$model op=sdo-download object=$obj instructions_per_op=$(( (b - a) / N ))"
    done
done
