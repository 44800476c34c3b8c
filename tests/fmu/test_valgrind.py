"""One harness session (session.py) under valgrind (Debian's, scripts/deps.sh): no invalid
access, no uninitialised value used, and no block definitely or indirectly lost that the FMU's library allocated.
CPython's own start-up reports (uninitialised bytes from getrandom, interned objects it never
frees, the loader's reads) are not the FMU's and are not counted."""

import os
import pathlib
import re
import shutil
import subprocess
import sys


HERE = pathlib.Path(__file__).resolve().parent


def records(text):
    """Valgrind's report split into its records (blank-line separated)."""
    return [r for r in re.split(r"\n==\d+== \n", text) if r.strip()]


def test_a_session_under_valgrind_leaks_nothing_and_touches_nothing_it_should_not(fmus, tmp_path):
    # A loud failure, not a skip: a CI without valgrind would otherwise pass this unchecked.
    assert shutil.which("valgrind"), "valgrind is not installed (scripts/deps.sh installs it)"
    log = tmp_path / "valgrind.log"
    env = dict(os.environ, PYTHONMALLOC="malloc")
    r = subprocess.run(
        ["valgrind", "--leak-check=full", "--show-leak-kinds=definite,indirect",
         # fmpy unloads the library at fmi3FreeInstance: keep its symbols for the report.
         "--keep-debuginfo=yes",
         "--num-callers=60", f"--log-file={log}", sys.executable, str(HERE / "session.py"),
         fmus["th"]],
        env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "session done" in r.stdout
    text = log.read_text()
    assert "LEAK SUMMARY" in text or "All heap blocks were freed" in text, text[-2000:]
    ours = re.compile(r"canpos|binaries/x86_64-linux")
    bad = []
    # A record is the FMU's when its stack passes through the library (60 frames deep: an
    # access the library makes inside libc still shows the library's frames). The dynamic
    # loader's own reads (glibc's SSE2 strncmp over an $ORIGIN rpath of numpy's modules) and
    # CPython's start-up are not.
    kinds = re.compile(r"Invalid (read|write|free)|Mismatched free|overlap|uninitialised"
                       r"|(definitely|indirectly) lost in loss record")
    for rec in records(text):
        if kinds.search(rec) and ours.search(rec):
            bad.append(rec)
    assert not bad, f"{len(bad)} records:\n\n" + "\n\n".join(bad[:5])
