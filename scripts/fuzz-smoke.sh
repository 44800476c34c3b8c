#!/usr/bin/env bash
# Short runs of every cargo-fuzz target (fuzz/), part of scripts/test.sh.
#
# Needs the nightly toolchain (libFuzzer instrumentation). Without nightly this prints a loud NOTE
# and exits 0: the rest of CI must not depend on it. cargo-fuzz is installed when missing
# (into target/tools, scripts/tools.sh).
# A crash in any target fails (exit 1); its input is left in fuzz/artifacts/TARGET/.
#
# Every run uses a fixed seed, a fresh scratch corpus seeded from the committed one and a
# bound on executions as well as time, so a CI failure reproduces from the printed command.
#
#   FUZZ_SECONDS=N   upper bound in seconds per target (default 45)
#   FUZZ_RUNS=N      executions per target (default: per target, about 10 s each here)
#   FUZZ_SEED=N      libFuzzer seed (default 1)
#   FUZZ_TARGETS="a b"  subset of targets (default: all)
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${FUZZ_SECONDS:-45}
# Executions that take about 10 s per target on the 2-core development machine (control_requests
# and durations from loaded smoke runs after the merge of main: about 220 and 23,000-90,000
# executions/s). A smoke run, so that the test command stays under 30 minutes; longer runs are
# FUZZ_RUNS / FUZZ_SECONDS.
declare -A default_runs=([node_frames]=8000 [socketcand_stream]=100000 [socketcand_session]=50000 [state_file]=18000
  [text_parsers]=65000 [control_requests]=3000 [durations]=225000)
seed=${FUZZ_SEED:-1}
targets=${FUZZ_TARGETS:-"node_frames socketcand_stream socketcand_session state_file text_parsers control_requests durations"}

if ! cargo +nightly --version >/dev/null 2>&1; then
  echo "!!! NOTE: no nightly toolchain: the fuzz smoke runs were SKIPPED (rustup toolchain install nightly)" >&2
  exit 0
fi
# shellcheck source=scripts/tools.sh
. scripts/tools.sh
if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
  echo "installing cargo-fuzz 0.13.2 into target/tools"
  if ! install_tool cargo-fuzz 0.13.2; then
    echo "!!! NOTE: cargo-fuzz could not be installed: the fuzz smoke runs were SKIPPED" >&2
    exit 0
  fi
fi

t0=$(date +%s)
cd fuzz
cargo +nightly fuzz build
for t in $targets; do
  # New inputs go to a scratch corpus (first directory), so CI never grows the committed one.
  runs=${FUZZ_RUNS:-${default_runs[$t]:-20000}}
  scratch=target/ci-corpus/$t
  rm -rf "$scratch"
  mkdir -p "$scratch"
  echo "--- fuzz $t: seed $seed, $runs runs, at most ${secs} s"
  if ! cargo +nightly fuzz run "$t" "$scratch" "corpus/$t" -- -seed="$seed" -runs="$runs" \
      -max_total_time="$secs" -print_final_stats=1 >"target/ci-$t.log" 2>&1; then
    # The panic message and the libFuzzer verdict first: the tail alone may be only statistics.
    grep -E "panicked at|^thread '|ERROR: libFuzzer|SUMMARY|Test unit written|^Error:" \
      "target/ci-$t.log" | head -n 20 >&2 || true
    grep -A3 "panicked at" "target/ci-$t.log" | head -n 12 >&2 || true
    tail -n 25 "target/ci-$t.log" >&2
    echo "!!! FAILED: fuzz target $t (input in fuzz/artifacts/$t/; rerun:" \
      "cd fuzz && cargo +nightly fuzz run $t fuzz/artifacts/$t/<file>)" >&2
    exit 1
  fi
  grep -E '^#[0-9]+[[:space:]]+DONE' "target/ci-$t.log" || tail -n 3 "target/ci-$t.log"
done
rm -rf target/scratch
echo "fuzz smoke: $(wc -w <<<"$targets") targets (seed $seed, a fixed number of runs or ${secs} s each) clean in $(($(date +%s) - t0)) s"
