#!/usr/bin/env python3
"""Flash of a firmware ELF by the source file its code comes from (docs/FIRMWARE.md, "Where the
flash goes"): every instruction that `arm-none-eabi-objdump -d` lists is counted at its innermost
frame in `crates/stack`, `crates/encoder` or `crates/models` of `arm-none-eabi-addr2line -i`
(what the Rust library inlines counts where those crates called it), other code at its innermost
frame.

    python3 scripts/firmware-by-file.py firmware/target/thumbv7em-none-eabihf/release/plain
"""
import collections
import re
import subprocess
import sys

CRATES = ("stack", "encoder", "models")
# A source path in one of the three device crates: everything before `crates/` is dropped.
OURS = re.compile(r".*/crates/(stack|encoder|models)/src/")


def main(elf: str) -> None:
    dis = subprocess.run(["arm-none-eabi-objdump", "-d", elf],
                         capture_output=True, text=True, check=True).stdout
    addrs = sorted(int(m.group(1), 16) for m in re.finditer(r"^ +([0-9a-f]+):", dis, re.M))
    out = subprocess.run(["arm-none-eabi-addr2line", "-e", elf, "-i", "-a"],
                         input="\n".join(hex(a) for a in addrs),
                         capture_output=True, text=True, check=True).stdout
    chains: dict[int, list[str]] = {}
    cur = None
    for line in out.splitlines():
        if line.startswith("0x"):
            cur = int(line, 16)
            chains[cur] = []
        elif line and cur is not None:
            chains[cur].append(line.split(":")[0])
    by_file: collections.Counter[str] = collections.Counter()
    for a, b in zip(addrs, addrs[1:]):
        size = b - a
        if size > 8:  # the gap before a literal pool or the next function: one instruction
            size = 4
        chain = chains.get(a) or ["??"]
        ours = [f for f in chain if OURS.search(f)]
        f = ours[0] if ours else chain[0]
        f = OURS.sub(r"crates/\1/src/", f)
        f = re.sub(r".*/firmware/src/(bin/\.\./)?", "firmware/src/", f)
        by_file[f] += size
    for f, n in by_file.most_common():
        print(f"{n:7d} {f}")
    totals = {c: sum(n for f, n in by_file.items() if f.startswith(f"crates/{c}/"))
              for c in CRATES}
    for c in CRATES:
        print(f"{totals[c]:7d} crates/{c} in all")
    print(f"{sum(totals.values()):7d} stack+encoder+models in all")


if __name__ == "__main__":
    main(sys.argv[1])
