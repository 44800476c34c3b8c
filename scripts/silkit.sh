#!/usr/bin/env bash
# Installs Vector SIL Kit 5.0.3 (libSilKit.so and sil-kit-registry) into target/silkit/ from
# PyPI's SilKit_py 1.0.5 wheel, hash-pinned (docs/SILKIT.md, D35). Idempotent: a second run
# finds the files and only prints their paths. Prints, on its last two lines:
#   CANPOS_SILKIT_LIB=/abs/path/libSilKit.so
#   CANPOS_SILKIT_REGISTRY=/abs/path/sil-kit-registry
# so `eval "$(scripts/silkit.sh | tail -n2 | sed 's/^/export /')"` sets both.
#
# The wheel is built for CPython 3.12, but only its native files are used (libSilKit.so does not
# link Python): pip fetches it from any Python 3 with --python-version / --platform, never
# installs it, and the files are unpacked with Python's zipfile (which drops the execute bit).
set -euo pipefail
cd "$(dirname "$0")/.."
DEST="$PWD/target/silkit"
WHEEL=silkit_py-1.0.5-cp312-cp312-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl
SHA256=7abdd65412ea5fba18edc9eaf4f295f1b4ae6a1fdf32f16883ad671e373137cc
LIB="$DEST/unpacked/SilKit_py/libSilKit.so"
REG="$DEST/unpacked/SilKit_py/bin/sil-kit-registry"
STAMP="$DEST/installed-$SHA256"

if [ "$(uname -m)" != x86_64 ] || [ "$(uname -s)" != Linux ]; then
  echo "silkit: SilKit_py 1.0.5 ships Linux x86_64 wheels only (this is $(uname -s) $(uname -m))" >&2
  exit 1
fi

if [ ! -f "$STAMP" ]; then
  rm -rf "$DEST"
  mkdir -p "$DEST/wheel"
  printf 'SilKit_py==1.0.5 --hash=sha256:%s\n' "$SHA256" >"$DEST/requirements.txt"
  python3 -m pip download --quiet --disable-pip-version-check --no-deps --only-binary=:all: \
    --python-version 3.12 --implementation cp --abi cp312 --platform manylinux_2_28_x86_64 \
    --require-hashes -r "$DEST/requirements.txt" -d "$DEST/wheel"
  # pip checked the hash; checked again here so a wheel left by an older run cannot slip in.
  echo "$SHA256  $DEST/wheel/$WHEEL" | sha256sum --check --quiet
  python3 -m zipfile -e "$DEST/wheel/$WHEEL" "$DEST/unpacked"
  chmod +x "$DEST"/unpacked/SilKit_py/bin/sil-kit-*
  touch "$STAMP"
fi
for f in "$LIB" "$REG"; do
  if [ ! -f "$f" ]; then
    echo "silkit: $f missing from the wheel's layout; remove $DEST and run again" >&2
    exit 1
  fi
done
echo "silkit: SIL Kit from SilKit_py 1.0.5 (sha256 $SHA256) in $DEST"
echo "CANPOS_SILKIT_LIB=$LIB"
echo "CANPOS_SILKIT_REGISTRY=$REG"
