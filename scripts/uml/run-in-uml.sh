#!/usr/bin/env bash
# Runs CMD... inside a User-Mode Linux guest with SocketCAN and `vcan0` up, and exits with its
# exit status. Usable as a cargo runner:
#   CARGO_TARGET_X86_64_UNKNOWN_LINUX_GNU_RUNNER=scripts/uml/run-in-uml.sh cargo test ...
#
# The guest's root is the host's / through hostfs, read-only; the working directory is kept, the
# environment is passed in, TMPDIR is a tmpfs (/run/tmp), and CANPOS_VCAN=1 is set. Writable host
# directories: CANPOS_UML_RW="DIR1 DIR2" (mounted read-write by hostfs). The guest's console
# (stdout and stderr of CMD, merged) goes to this script's stdout.
#
# Environment: CANPOS_UML_CACHE (kit; fetched by fetch-kit.sh when missing), CANPOS_UML_TIMEOUT
# (seconds, default 600), CANPOS_UML_MEM (default 512M).
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
ROOT="$(cd "$HERE/../.." && pwd)"
if [ $# -eq 0 ]; then
  echo "usage: $0 CMD [ARG...]" >&2
  exit 2
fi
KIT=$("$HERE/fetch-kit.sh" | tail -n1)
BB="$KIT/busybox"

RUNS="${CANPOS_UML_RUNDIR:-$ROOT/target/uml-run}"
mkdir -p "$RUNS"
RUN=$(mktemp -d "$RUNS/run.XXXXXX")
trap 'rm -rf "$RUN"' EXIT

# Single-quotes a string for the guest's (busybox) shell.
q() { printf "'%s'" "${1//\'/\'\\\'\'}"; }

{
  echo "#!$BB sh"
  echo 'export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin'
  while IFS= read -r -d '' kv; do
    name=${kv%%=*}
    case "$name" in
      PWD | OLDPWD | SHLVL | _ | PATH | TMPDIR | TERM) continue ;;
    esac
    [[ "$name" =~ ^[A-Za-z_][A-Za-z0-9_]*$ ]] || continue
    echo "export $name=$(q "${kv#*=}")"
  done < <(env -0)
  echo "export PATH=$(q "$PATH")"
  echo "export TMPDIR=/run/tmp CANPOS_VCAN=1 TERM=dumb"
} >"$RUN/env"

{
  printf 'cd %s || exit 97\n' "$(q "$PWD")"
  printf 'exec'
  for a in "$@"; do printf ' %s' "$(q "$a")"; done
  printf '\n'
} >"$RUN/cmd"

RW="$RUN ${CANPOS_UML_RW:-}"
# A tmpfs over /tmp would hide a checkout, kit or run directory that lives under /tmp (CI clones
# anywhere): the guest's scratch space is /run/tmp, and /tmp gets a tmpfs only when nothing of
# ours is below it.
TMP_MOUNT='$B mount -t tmpfs tmp /tmp'
for p in "$ROOT" "$KIT" "$RUN" "$PWD"; do
  case "$p/" in /tmp/*) TMP_MOUNT=':' ;; esac
done
cat >"$RUN/init" <<INIT
#!$BB sh
B=$BB
M=$KIT/modules
\$B mount -t proc proc /proc
\$B mount -t sysfs sys /sys
\$B mount -t devtmpfs dev /dev 2>/dev/null || \$B mount -t tmpfs dev /dev
\$B mount -t tmpfs run /run
\$B mkdir -p /run/tmp
${TMP_MOUNT}
\$B mkdir -p /dev/pts /dev/shm
\$B mount -t devpts pts /dev/pts 2>/dev/null
\$B mount -t tmpfs shm /dev/shm 2>/dev/null
for d in $RW; do \$B mount -t hostfs -o "\$d" none "\$d" || echo "uml: cannot mount \$d writable"; done
fail() { echo "uml: \$*"; echo 98 > $RUN/status; \$B poweroff -f; }
for m in net/can/can net/can/can-raw net/can/can-bcm drivers/net/can/dev/can-dev drivers/net/can/vcan; do
  \$B insmod \$M/\$m.ko || fail "insmod \$m.ko failed"
done
\$B ip link set lo up
\$B ip link add dev vcan0 type vcan || fail "cannot create vcan0"
\$B ip link set up vcan0 || fail "cannot bring vcan0 up"
( . $RUN/env; . $RUN/cmd ) </dev/null
echo \$? > $RUN/status
\$B sync
\$B poweroff -f
INIT
chmod +x "$RUN/init"

set +e
# The host's TMPDIR holds UML's memory file; it must allow exec-less mmap (any normal tmp does).
timeout -k 5 "${CANPOS_UML_TIMEOUT:-600}" "$KIT/linux.uml" "mem=${CANPOS_UML_MEM:-512M}" \
  root=/dev/root rootfstype=hostfs rootflags=/ ro "init=$RUN/init" \
  con0=null,fd:1 con=null ssl=null quiet </dev/null
rc=$?
set -e
if [ -f "$RUN/status" ]; then
  exit "$(cat "$RUN/status")"
fi
if [ $rc -eq 124 ] || [ $rc -eq 137 ]; then
  echo "run-in-uml: the guest timed out after ${CANPOS_UML_TIMEOUT:-600} s" >&2
else
  echo "run-in-uml: the guest ended (linux.uml exit $rc) without reporting the command's status" >&2
fi
exit 125
