#!/usr/bin/env bash
# Mutation testing of the device crates (canpos-stack, canpos-encoder, canpos-models) with
# cargo-mutants (pinned below), against their own tests only: a rule they state must be
# enforced by their tests. Every mutant runs the tests of all three (`--test-package`): the
# stack's rules are mostly tested through the models' nodes (crates/models/tests/suite).
# (Doctests are left out: they restate the crate docs, and each one is a separate build.)
#
#   scripts/mutants.sh                       all three crates (target/mutants/full)
#   scripts/mutants.sh --iterate             again, only the mutants the last whole run and
#                                            its iterations did not catch (new tests since)
#   scripts/mutants.sh --shard K/N           one shard of the whole run (to split it)
#   scripts/mutants.sh --file PATH [...]     the mutants of these files
#   scripts/mutants.sh --in-diff REV         the mutants on lines changed since REV
#   scripts/mutants.sh --check ...           any of the above; exit 1 when a missed mutant is
#                                            not listed as equivalent in docs/MUTANTS.md
#
# Results go under target/mutants/<run>/; the script prints one line per file with its score
# (caught / viable, a timeout counts as caught) and, last, `mutants: N caught, M missed,
# T timeout, U unviable`. docs/MUTANTS.md lists the survivors that are equivalent.
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=27.1.0
JOBS=${MUTANTS_JOBS:-2}

# shellcheck source=scripts/tools.sh
. scripts/tools.sh
if [ "$(cargo mutants --version 2>/dev/null || true)" != "cargo-mutants $VERSION" ]; then
  echo "mutants: installing cargo-mutants $VERSION into target/tools" >&2
  install_tool cargo-mutants "$VERSION"
fi

# The property tests take nearly all of the suite's 2.3 s; with 32 cases each instead of 256 a
# mutant costs about half as much, and the hand-written tests still run in full.
export PROPTEST_CASES=${PROPTEST_CASES:-32}
base=(cargo mutants --package canpos-stack --package canpos-encoder --package canpos-models
  --test-package canpos-stack,canpos-encoder,canpos-models
  --no-shuffle --jobs "$JOBS" --profile mutants --cargo-test-arg=--tests
  --timeout 10 --build-timeout 600 --exclude 'crates/models/benches/**' --exclude 'crates/models/tests/**'
  # Reached only in a one-model (firmware) build; the default features this run builds with
  # cannot reach them (docs/MUTANTS.md).
  --exclude-re '^crates/models/src/lib.rs:.*(table::stored|built_alone)'
  # Taken only without inline-hot-paths: the firmware's table search (docs/MUTANTS.md).
  --exclude-re '^crates/stack/src/od/mod.rs:.*search_entries')
mkdir -p target/mutants
runs=()
run() { # NAME ARGS...
  local name=$1; shift
  local out=target/mutants/$name
  if [ "${1:-}" = --iterate ]; then
    # cargo-mutants renames the last output to mutants.out.old: keep every run's outcomes, so
    # that the summary is the whole run's, the later outcome of a mutant winning.
    [ -f "$out/mutants.out/outcomes.json" ] || { echo "mutants: no whole run to iterate on" >&2; exit 1; }
    local n; n=$(find "$out" -maxdepth 1 -name 'outcomes-*.json' | wc -l)
    cp "$out/mutants.out/outcomes.json" "$out/outcomes-$n.json"
    for ((k = 0; k <= n; k++)); do runs+=("$out/outcomes-$k.json"); done
  else
    rm -rf "$out"
  fi
  # cargo-mutants exits 2 when mutants are missed and 3 on timeouts: the summary reports them.
  "${base[@]}" --output "$out" "$@" >"target/mutants/$name.log" 2>&1 || {
    rc=$?
    if [ "$rc" -ne 2 ] && [ "$rc" -ne 3 ]; then
      tail -n 30 "target/mutants/$name.log" >&2
      echo "mutants: cargo-mutants failed (exit $rc); log: target/mutants/$name.log" >&2
      exit 1
    fi
  }
  runs+=("$out/mutants.out/outcomes.json")
}

check=0
current=
if [ "${1:-}" = --check ]; then check=1; shift; fi

case "${1:-}" in
  "" | --iterate)
    # The mutants of the tree as it is now: a mutant of an earlier run that no longer exists
    # (its code changed) does not count.
    "${base[@]}" --list --json >target/mutants/current.json
    current=target/mutants/current.json
    if [ -n "${1:-}" ]; then run full --iterate; else run full; fi ;;
  --shard) run "shard-${2%/*}" --shard "$2" ;;
  --file) shift; args=(); for f in "$@"; do args+=(--file "$f"); done; run files "${args[@]}" ;;
  --in-diff)
    git diff "$2" -- crates/stack/src crates/encoder/src crates/models/src >target/mutants/in-diff.diff
    if [ ! -s target/mutants/in-diff.diff ]; then
      echo "mutants: no change to crates/{stack,encoder,models}/src since $2"
      echo "mutants: 0 caught, 0 missed, 0 timeout, 0 unviable"
      exit 0
    fi
    run in-diff --in-diff target/mutants/in-diff.diff ;;
  *) sed -n '2,12p' "$0" >&2; exit 2 ;;
esac

python3 - "$check" "${current:-}" "${runs[@]}" <<'PY'
import collections, json, re, sys
check = sys.argv.pop(1) == "1"
current = sys.argv.pop(1)
current = {m["name"] for m in json.load(open(current))} if current else None
listed = set(re.findall(r"^\| `([^`]+)` \|", open("docs/MUTANTS.md").read(), re.M))
listed = {k.replace("\\|", "|") for k in listed}
per = collections.defaultdict(collections.Counter)
missed = []
unlisted = []
# Each mutant's last outcome (an --iterate run re-tests only what earlier runs did not catch).
last = {}
for path in sys.argv[1:]:
    try:
        outcomes = json.load(open(path))["outcomes"]
    except FileNotFoundError:
        continue  # a shard with no mutants writes none
    for o in outcomes:
        m = o["scenario"]
        if not isinstance(m, dict) or "Mutant" not in m:
            continue
        m = m["Mutant"]
        kind = {"CaughtMutant": "caught", "MissedMutant": "missed", "Timeout": "timeout",
                "Unviable": "unviable"}.get(o["summary"], o["summary"])
        if current is None or m["name"] in current:
            last[m["name"]] = (m, kind)
for m, kind in last.values():
        per[m["file"]][kind] += 1
        if kind == "missed":
            missed.append(m["name"])
            # The equivalence key: the file and the description, without line and column.
            key = re.sub(r"^([^:]+):\d+:\d+: ", r"\1: ", m["name"])
            if key in listed:
                per[m["file"]]["equivalent"] += 1
            elif check:
                unlisted.append(key)
total = collections.Counter()
for f in sorted(per):
    c = per[f]
    total.update(c)
    viable = c["caught"] + c["missed"] + c["timeout"]
    score = 100.0 * (c["caught"] + c["timeout"]) / viable if viable else 100.0
    print(f"{f}: {score:5.1f} % ({c['caught'] + c['timeout']}/{viable} viable caught, {c['unviable']} unviable)")
for name in missed:
    print(f"MISSED {name}")
viable = total["caught"] + total["missed"] + total["timeout"]
if viable:
    print(f"score: {100.0 * (total['caught'] + total['timeout']) / viable:.1f} % of viable mutants caught")
if current is not None and current - set(last):
    print(f"untested: {len(current - set(last))} mutants of the tree have no outcome yet")
for key in unlisted:
    print(f"UNLISTED SURVIVOR {key}")
print(f"equivalent: {total['equivalent']} of the missed are listed in docs/MUTANTS.md")
print(f"mutants: {total['caught']} caught, {total['missed']} missed, {total['timeout']} timeout, {total['unviable']} unviable")
sys.exit(1 if unlisted else 0)
PY
