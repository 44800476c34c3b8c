#!/usr/bin/env bash
# The TH firmware (issue 14, docs/FIRMWARE.md): builds it for thumbv7em-none-eabihf at
# opt-level s, measures flash and RAM, runs it under QEMU (mps2-an386) against the host-side
# test, and prints as its last line
#   firmware: flash N B, ram M B, qemu: K passed, F failed
# Missing tools are installed (rustup target, Debian packages via scripts/deps.sh); if that
# fails, this fails. It never skips.
set -euo pipefail
cd "$(dirname "$0")/.."
TARGET=thumbv7em-none-eabihf
fail() { echo "!!! FAILED: $*" >&2; exit 1; }

if ! rustup target list --installed | grep -qx "$TARGET"; then
  rustup target add "$TARGET" || fail "rustup could not add $TARGET"
fi
for tool in qemu-system-arm arm-none-eabi-size arm-none-eabi-gcc python3; do
  command -v "$tool" >/dev/null || scripts/deps.sh
  command -v "$tool" >/dev/null || fail "$tool is missing (scripts/deps.sh installs it)"
done
# newlib-nano (its memcpy / memset are linked into the firmware, firmware/build.rs).
nano() { arm-none-eabi-gcc -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16 -print-file-name=libc_nano.a; }
[ -e "$(nano)" ] || scripts/deps.sh
[ -e "$(nano)" ] || fail "newlib-nano (libc_nano.a) is missing (scripts/deps.sh installs libnewlib-arm-none-eabi)"

# The stack, the encoder and the models with their host features (all models, names, EDS) stay
# no_std-clean for the MCU too.
cargo build -p canpos-stack -p canpos-encoder -p canpos-models --locked --quiet --target "$TARGET"
HOST=$(rustc -vV | sed -n 's/^host: //p')
# The portable part's unit tests (SLCAN lines) run on the host; the rest is built for the MCU.
(cd firmware && cargo fmt --check && cargo clippy --release --locked --quiet -- -D warnings &&
  cargo test --lib --locked --quiet --target "$HOST" &&
  cargo build --release --locked --quiet)
BIN=firmware/target/$TARGET/release

# Section sizes from the ELF: flash = vector table + code + constants + initialised data,
# static RAM = .data + .bss + .uninit (the stack comes on top, measured in QEMU).
sections() {
  arm-none-eabi-size -A "$1" | awk '
    $1==".vector_table"||$1==".text"||$1==".rodata" {f+=$2}
    $1==".data" {f+=$2; r+=$2}
    $1==".bss"||$1==".uninit" {r+=$2}
    END {print f+0, r+0}'
}
read -r th_flash th_static <<<"$(sections "$BIN/th")"
read -r base_flash _ <<<"$(sections "$BIN/baseline")"
# A size reference's stack on its own: its flash less the board's (`baseline`) and its own
# dictionary and model description (the binary's `ENTRIES` and `MODEL`). Prints "flash od stack".
stack_of() {
  local flash od
  read -r flash _ <<<"$(sections "$BIN/$1")"
  od=$(arm-none-eabi-nm -S -C "$BIN/$1" | python3 -c 'import sys
print(sum(int(l.split()[1], 16) for l in sys.stdin
          if l.split()[-1] in (sys.argv[1] + "::ENTRIES", sys.argv[1] + "::MODEL")))' "$1")
  echo "$flash $od $((flash - base_flash - od))"
}
read -r plain_flash plain_od stack_only <<<"$(stack_of plain)"
read -r full_flash full_od full_stack <<<"$(stack_of plain_full)"

mkdir -p target
set +e
timeout 300 python3 tests/firmware/qemu_th.py "$BIN/th" | tee target/firmware-qemu.log
rc=${PIPESTATUS[0]}
set -e
passed=$(grep -oE '^qemu: [0-9]+ passed' target/firmware-qemu.log | grep -oE '[0-9]+' || echo 0)
failed=$(grep -oE ', [0-9]+ failed$' target/firmware-qemu.log | grep -oE '[0-9]+' || echo 1)
stack=$(grep -oE '^stack peak: [0-9]+' target/firmware-qemu.log | grep -oE '[0-9]+' || echo 0)
th_ram=$((th_static + stack))

goal() { if [ "$1" -le "$2" ]; then echo "met"; else echo "NOT met"; fi; }
echo
echo "sizes at opt-level s (arm-none-eabi-size -A; RAM = .data + .bss + stack high-water mark in QEMU):"
echo "  TH firmware        flash $th_flash B (goal <= 32768: $(goal "$th_flash" 32768)), RAM $th_ram B = $th_static static + $stack stack (goal <= 4096: $(goal "$th_ram" 4096))"
echo "  board alone (baseline) flash $base_flash B"
echo "  plain (CiA 301/305 stack with CANopenNode's default services, minimal OD) flash $plain_flash B, its OD $plain_od B"
echo "  stack on its own   $stack_only B = plain - baseline - OD (goal: CANopenNode's default stack objects, ~12.5 KiB: $(goal "$stack_only" 12800))"
echo "  plain_full (every CiA 301/305 service canpos has) flash $full_flash B, its OD $full_od B"
echo "  full stack on its own $full_stack B = plain_full - baseline - OD (CANopenNode with the same services: 12868 B, docs/FIRMWARE.md: $(goal "$full_stack" 12868))"
if [ "$rc" -ne 0 ] && [ "$failed" -eq 0 ]; then failed=1; fi
echo "firmware: flash $th_flash B, ram $th_ram B, qemu: $passed passed, $failed failed"
[ "$failed" -eq 0 ] && [ "$passed" -gt 0 ]
