#!/usr/bin/env bash
# Short runs of every cargo-fuzz target (fuzz/), part of scripts/test.sh.
#
# Needs the nightly toolchain (libFuzzer instrumentation). Without nightly this prints a loud NOTE
# and exits 0: the rest of CI must not depend on it. cargo-fuzz is installed when missing.
# A crash in any target fails (exit 1); its input is left in fuzz/artifacts/TARGET/.
#
#   FUZZ_SECONDS=N   seconds per target (default 20)
#   FUZZ_TARGETS="a b"  subset of targets (default: all)
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${FUZZ_SECONDS:-20}
targets=${FUZZ_TARGETS:-"node_frames socketcand_stream state_file text_parsers"}

if ! cargo +nightly --version >/dev/null 2>&1; then
  echo "!!! NOTE: no nightly toolchain: the fuzz smoke runs were SKIPPED (rustup toolchain install nightly)" >&2
  exit 0
fi
if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
  echo "installing cargo-fuzz"
  if ! cargo install --locked cargo-fuzz; then
    echo "!!! NOTE: cargo-fuzz could not be installed: the fuzz smoke runs were SKIPPED" >&2
    exit 0
  fi
fi

t0=$(date +%s)
cd fuzz
cargo +nightly fuzz build
for t in $targets; do
  # New inputs go to a scratch corpus (first directory), so CI never grows the committed one.
  scratch=target/ci-corpus/$t
  mkdir -p "$scratch"
  echo "--- fuzz $t for ${secs} s"
  if ! cargo +nightly fuzz run "$t" "$scratch" "corpus/$t" -- \
      -max_total_time="$secs" -print_final_stats=1 >"target/ci-$t.log" 2>&1; then
    tail -n 40 "target/ci-$t.log" >&2
    echo "!!! FAILED: fuzz target $t found a crash (input in fuzz/artifacts/$t/)" >&2
    exit 1
  fi
  grep -E '^#[0-9]+[[:space:]]+DONE' "target/ci-$t.log" || tail -n 3 "target/ci-$t.log"
done
echo "fuzz smoke: $(wc -w <<<"$targets") targets x ${secs} s clean in $(($(date +%s) - t0)) s"
