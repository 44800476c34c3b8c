"""Builds the FMUs the tests use with `canpos fmu` (CANPOS_BIN, default target/debug/canpos)."""

import os
import pathlib
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
# The three model FMUs and one order-code FMU (a two-magnet E-Series).
UNITS = {
    "th": ["--model", "th"],
    "e-series": ["--model", "e-series"],
    "tmi": ["--model", "tmi"],
    "EP00600MD341C304241Z02": ["--order-code", "EP00600MD341C304241Z02"],
}


def canpos_bin():
    return os.environ.get("CANPOS_BIN", str(ROOT / "target/debug/canpos"))


@pytest.fixture(scope="session")
def fmus(tmp_path_factory):
    out = tmp_path_factory.mktemp("fmus")
    paths = {}
    for name, args in UNITS.items():
        path = out / f"{name}.fmu"
        subprocess.run([canpos_bin(), "fmu", *args, "--output", str(path)], check=True,
                       timeout=120)
        paths[name] = str(path)
    return paths
