# Sourced by scripts/mutants.sh and scripts/fuzz-smoke.sh (from the repository's root): the
# cargo tools the test command builds itself when they are missing, cached under target/tools
# so that a second run on the same checkout finds them (a tool already on PATH at the right
# version is used as it is). Debug builds: the tools only drive cargo, and a debug build takes
# about 40 % of a release build's CPU time (cargo-mutants 27.1.0 on this 2-core machine: 1 min
# 13 s user against 3 min 8 s, 2026-12-07; cargo-fuzz 25 s). The price: a debug cargo-mutants
# lists the mutants of the core in 4.7 s instead of 1 s, once per run.
TOOLS_ROOT="$PWD/target/tools"
export PATH="$TOOLS_ROOT/bin:$PATH"

# install_tool CRATE VERSION: builds and installs CRATE into target/tools/bin; fails as cargo
# install does (also where the caller tests it, so `set -e` does not apply).
install_tool() {
  cargo install --locked --quiet --debug --root "$TOOLS_ROOT" --target-dir "$TOOLS_ROOT/build" \
    "$1" --version "$2" || return
  # The binary is what is kept; its build tree (hundreds of MB) is not needed again.
  rm -rf "$TOOLS_ROOT/build"
}
