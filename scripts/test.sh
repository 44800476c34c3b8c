#!/usr/bin/env bash
# The project's test command (README: "Run the tests"). Runs formatting and lint checks, the Rust
# test suites, the no_std build of the core, the release build, and the python-canopen interop
# suite in a venv it creates itself.
set -euo pipefail
cd "$(dirname "$0")/.."
step() { printf '\n=== %s ===\n' "$*"; }

step "cargo fmt --check"
cargo fmt --all --check

step "cargo clippy"
cargo clippy --workspace --all-targets --locked -- -D warnings

step "cargo test"
cargo test --workspace --locked 2>&1 | tee target/cargo-test.log
grep -E '^test result:' target/cargo-test.log | awk '{p+=$4; f+=$6} END {printf "rust: %d passed, %d failed\n", p, f}'

step "core as #![no_std] for thumbv7em-none-eabihf"
if rustup target list --installed 2>/dev/null | grep -q thumbv7em-none-eabihf || rustup target add thumbv7em-none-eabihf; then
  cargo build -p canpos-core --locked --target thumbv7em-none-eabihf
else
  echo "NOTE: rustup could not add thumbv7em-none-eabihf on this machine; embedded build skipped"
fi

step "release build"
cargo build --release --locked -p canpos

step "python-canopen interop suite"
VENV=target/venv-interop
if [ ! -x "$VENV/bin/python" ]; then
  python3 -m venv "$VENV"
fi
"$VENV/bin/pip" install --quiet --disable-pip-version-check -r tests/interop/requirements.txt
CANPOS_BIN="$PWD/target/release/canpos" "$VENV/bin/python" -m pytest -q tests/interop
