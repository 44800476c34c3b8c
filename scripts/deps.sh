#!/usr/bin/env bash
# Installs the Debian packages the test command needs (idempotent; quick when all are present).
# Each suite that needs a package lists it here, with the reason, so one apt run serves them all.
set -euo pipefail
PACKAGES=(
  # (add packages here, one per line, with the suite that needs it)
  tshark # tests/interop/test_files.py: decodes a `canpos record` pcapng as CANopen
  chromium # the dashboard test drives the page in it (tests/dashboard, playwright-core)
  qemu-system-arm   # scripts/firmware.sh: runs the TH firmware on mps2-an386
  gcc-arm-none-eabi # scripts/firmware.sh: arm-none-eabi-size / -nm measure the firmware
  libnewlib-arm-none-eabi # firmware/build.rs: newlib-nano's memcpy / memset (size-optimised)
  valgrind # tests/fmu/test_valgrind.py: one FMU session, no leak and no invalid access
)
missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
done
if [ "${#missing[@]}" -eq 0 ]; then
  echo "deps: all ${#PACKAGES[@]} Debian packages present"
  exit 0
fi
echo "deps: installing ${missing[*]}"
as_root=()
[ "$(id -u)" -eq 0 ] || as_root=(sudo)
export DEBIAN_FRONTEND=noninteractive
"${as_root[@]}" apt-get update -qq
"${as_root[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
echo "deps: installed ${missing[*]}"
