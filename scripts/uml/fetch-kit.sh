#!/usr/bin/env bash
# Fetches and prepares the User-Mode Linux kit the SocketCAN tests run in (see
# ../../README.md "SocketCAN tests" and docs of TRANSPORT.md): linux.uml 7.2 with its CAN modules
# (Debian testing), the glibc it needs (private copy, patchelf'd in), and a static busybox for the
# guest's init. Nothing is installed system-wide except, when missing, `patchelf`.
#
# Cache: $CANPOS_UML_CACHE, default target/uml-kit. Idempotent: a complete kit is reused as is.
# Prints the kit directory on the last line of stdout. Exits non-zero, loudly, when the kit cannot
# be fetched.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
KIT="${CANPOS_UML_CACHE:-$ROOT/target/uml-kit}"
# UML >= 7.2 is needed (older ones die on this CPU with "ptrace set fp regs failed").
UML_SUITES="${CANPOS_UML_SUITES:-forky sid}"
BUSYBOX_SUITE="${CANPOS_UML_BUSYBOX_SUITE:-bookworm}"

die() {
  {
    echo
    echo "!!! ================================================================= !!!"
    echo "!!! canpos UML kit: $*"
    echo "!!! The SocketCAN-on-vcan tests cannot run without it."
    echo "!!! ================================================================= !!!"
  } >&2
  exit 1
}

ready() {
  [ -x "$KIT/linux.uml" ] && [ -x "$KIT/busybox" ] && [ -f "$KIT/modules/net/can/can.ko" ] &&
    [ -f "$KIT/modules/drivers/net/can/vcan.ko" ] && [ -f "$KIT/modules/net/can/can-bcm.ko" ] &&
    [ -f "$KIT/.complete" ]
}

if ready; then
  echo "$KIT"
  exit 0
fi

command -v apt-get >/dev/null || die "apt-get not found (a Debian-based machine is needed)"
command -v dpkg-deb >/dev/null || die "dpkg-deb not found"

# The machine's own Debian mirror (deb822 .sources or one-line .list), default deb.debian.org.
mirror() {
  local m=""
  m=$(grep -hsE '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null |
    awk '{print $2}' | grep -E '/debian/?$' | head -n1 || true)
  if [ -z "$m" ]; then
    m=$(grep -hsE '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null |
      awk '{for (i = 2; i <= NF; i++) if ($i ~ /^https?:/) {print $i; exit}}' |
      grep -E '/debian/?$' | head -n1 || true)
  fi
  echo "${m:-http://deb.debian.org/debian}"
}
MIRROR="${CANPOS_UML_MIRROR:-$(mirror)}"
MIRROR="${MIRROR%/}"
KEYRING=/usr/share/keyrings/debian-archive-keyring.gpg

WORK="$KIT.work"
rm -rf "$WORK"
mkdir -p "$WORK/lists/partial" "$WORK/cache/archives/partial" "$WORK/debs" "$WORK/etc/preferences.d"
touch "$WORK/status"

# apt against a private sources list / state / cache: nothing of the machine's apt is touched.
apt_priv() {
  local suite=$1
  shift
  local signed=""
  [ -f "$KEYRING" ] && signed=" [signed-by=$KEYRING]"
  echo "deb$signed $MIRROR $suite main" >"$WORK/etc/$suite.list"
  apt-get -q \
    -o Dir::Etc::sourcelist="$WORK/etc/$suite.list" \
    -o Dir::Etc::sourceparts=- \
    -o Dir::Etc::preferencesparts="$WORK/etc/preferences.d" \
    -o Dir::State::lists="$WORK/lists/$suite" \
    -o Dir::State::status="$WORK/status" \
    -o Dir::Cache="$WORK/cache" \
    -o Dir::Cache::archives="$WORK/cache/archives" \
    -o APT::Architecture=amd64 \
    -o Debug::NoLocking=1 \
    -o Acquire::Retries=3 \
    "$@"
}

fetch() { # suite package...
  local suite=$1
  shift
  mkdir -p "$WORK/lists/$suite/partial"
  apt_priv "$suite" update >"$WORK/update-$suite.log" 2>&1 || {
    cat "$WORK/update-$suite.log" >&2
    return 1
  }
  (cd "$WORK/debs" && apt_priv "$suite" download "$@") >"$WORK/download-$suite.log" 2>&1 || {
    cat "$WORK/download-$suite.log" >&2
    return 1
  }
}

echo "canpos UML kit: fetching into $KIT (mirror $MIRROR)" >&2
got=""
for s in $UML_SUITES; do
  if fetch "$s" user-mode-linux libc6; then
    got=$s
    break
  fi
  echo "canpos UML kit: suite $s failed, trying the next" >&2
done
[ -n "$got" ] || die "could not download user-mode-linux and libc6 from $MIRROR (suites: $UML_SUITES)"
fetch "$BUSYBOX_SUITE" busybox-static ||
  die "could not download busybox-static ($BUSYBOX_SUITE) from $MIRROR"

X="$WORK/x"
mkdir -p "$X"
for deb in "$WORK"/debs/*.deb; do
  dpkg-deb --fsys-tarfile "$deb" | tar -x -C "$X" || die "cannot extract $deb"
done

uml=$(find "$X/usr/bin" -name linux.uml -o -name 'linux.uml*' -type f | head -n1)
[ -n "$uml" ] || uml=$(find "$X" -name 'linux.uml' -type f | head -n1)
[ -n "$uml" ] || die "linux.uml not found in the user-mode-linux package"
modroot=$(find "$X" -type f -name vcan.ko\* -path '*drivers/net/can/*' | head -n1)
[ -n "$modroot" ] || die "vcan.ko not found in the user-mode-linux package"
modroot=${modroot%/drivers/net/can/*}
libc=$(find "$X" -name libc.so.6 | head -n1)
ld=$(find "$X" -name ld-linux-x86-64.so.2 | head -n1)
[ -n "$libc" ] && [ -n "$ld" ] || die "libc.so.6 / ld-linux-x86-64.so.2 not found in libc6 ($got)"
bb=$(find "$X" -path '*bin/busybox' -type f | head -n1)
[ -n "$bb" ] || die "busybox not found in busybox-static"

NEW="$KIT.new"
rm -rf "$NEW"
mkdir -p "$NEW/lib" "$NEW/modules/net/can" "$NEW/modules/drivers/net/can/dev"
cp "$uml" "$NEW/linux.uml"
cp -L "$libc" "$NEW/lib/libc.so.6"
cp -L "$ld" "$NEW/lib/ld-linux-x86-64.so.2"
cp "$bb" "$NEW/busybox"
# Modules, decompressed if the package ships them compressed.
# can-bcm: python-can's periodic sends (python-canopen node guarding, SYNC producer).
for m in net/can/can net/can/can-raw net/can/can-bcm drivers/net/can/dev/can-dev drivers/net/can/vcan; do
  src=$(ls "$modroot/$m".ko* 2>/dev/null | head -n1)
  [ -n "$src" ] || die "module $m.ko missing from the user-mode-linux package"
  case "$src" in
    *.ko) cp "$src" "$NEW/modules/$m.ko" ;;
    *.ko.xz) xz -dc "$src" >"$NEW/modules/$m.ko" ;;
    *.ko.zst) zstd -qdc "$src" >"$NEW/modules/$m.ko" ;;
    *.ko.gz) gzip -dc "$src" >"$NEW/modules/$m.ko" ;;
    *) die "unknown module format: $src" ;;
  esac
done

if ! command -v patchelf >/dev/null; then
  echo "canpos UML kit: installing patchelf (apt-get install -y patchelf)" >&2
  if ! apt-get install -y -q patchelf >"$WORK/patchelf.log" 2>&1; then
    # Without root: fetch its deb the same private way and run it from the work dir.
    fetch "$BUSYBOX_SUITE" patchelf || die "cannot get patchelf"
    dpkg-deb --fsys-tarfile "$WORK"/debs/patchelf_*.deb | tar -x -C "$X"
    PATH="$X/usr/bin:$PATH"
  fi
fi
command -v patchelf >/dev/null || die "patchelf unavailable"
# The paths are those of the kit's final place ($NEW is renamed to $KIT below).
patchelf --set-interpreter "$KIT/lib/ld-linux-x86-64.so.2" --set-rpath "$KIT/lib" "$NEW/linux.uml" ||
  die "patchelf failed on linux.uml"
chmod +x "$NEW/linux.uml" "$NEW/busybox"
ver=$(ls "$WORK"/debs/user-mode-linux_*.deb | sed 's/.*user-mode-linux_\([^_]*\)_.*/\1/')
echo "user-mode-linux $ver ($got), $(ls "$WORK"/debs | tr '\n' ' ')" >"$NEW/VERSION"
touch "$NEW/.complete"
rm -rf "$KIT"
mv "$NEW" "$KIT"
rm -rf "$WORK"
ready || die "kit incomplete after preparation"
echo "canpos UML kit ready: $(cat "$KIT/VERSION")" >&2
echo "$KIT"
