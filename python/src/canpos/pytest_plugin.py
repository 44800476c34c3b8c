"""pytest fixtures for canpos (registered through the ``pytest11`` entry point):

* ``canpos_bus`` — a socketcand hub on a free loopback port (:class:`canpos.Bus`);
* ``canpos_sensor`` — a factory: ``canpos_sensor(model="th", order_code=None, node_id=127,
  **run_options)`` starts ``canpos run`` on ``canpos_bus`` and returns a :class:`canpos.Sensor`.

Everything a test started is stopped when it ends, passed or failed; the processes' logs are
attached to a failed test's report."""
import shutil
import tempfile
from pathlib import Path

import pytest

from .process import Bus, Sensor


@pytest.fixture
def canpos_bus(request):
    workdir = Path(tempfile.mkdtemp(prefix="canpos-"))
    bus = Bus(workdir)
    yield bus
    bus.stop()
    failed = getattr(request.node, "rep_call", None)
    if failed is not None and failed.failed:
        for log in sorted(workdir.rglob("*.log")):
            request.node.add_report_section("call", f"canpos {log.name}", log.read_text())
    shutil.rmtree(workdir, ignore_errors=True)


@pytest.fixture
def canpos_sensor(canpos_bus):
    started = []

    def start(model=None, order_code=None, node_id=127, **options):
        s = Sensor(canpos_bus, model=model, order_code=order_code, node_id=node_id, **options)
        started.append(s)
        return s

    yield start
    # Sensors first, then the hub (canpos_bus's teardown runs after this one).
    for s in reversed(started):
        s.stop()


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_makereport(item, call):
    # Lets the fixtures see whether the test failed (for the logs in the report).
    outcome = yield
    rep = outcome.get_result()
    setattr(item, "rep_" + rep.when, rep)
