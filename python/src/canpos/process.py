"""canpos processes on free loopback ports: a socketcand hub (:class:`Bus`) and sensors on it
(:class:`Sensor`). Each is a child process that is always ended and reaped by ``stop()``."""
import os
import shutil
import signal
import socket
import subprocess
import sysconfig
import tempfile
import time
from pathlib import Path
from typing import List, Optional

from .control import ControlClient


def binary() -> str:
    """The canpos binary: ``$CANPOS_BIN``, else the one this wheel installed, else on PATH."""
    env = os.environ.get("CANPOS_BIN")
    if env:
        return env
    scripts = Path(sysconfig.get_path("scripts")) / "canpos"
    if scripts.exists():
        return str(scripts)
    found = shutil.which("canpos")
    if found:
        return found
    raise FileNotFoundError("no canpos binary: install the canpos wheel or set CANPOS_BIN")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, proc: subprocess.Popen, log: Path, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"canpos exited with {proc.returncode}:\n{log.read_text()}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.02)
    raise RuntimeError(f"canpos did not listen on 127.0.0.1:{port} within {timeout} s:\n"
                       f"{log.read_text()}")


class _Child:
    def __init__(self, args: List[str], log: Path):
        self.log = log
        self._out = open(log, "ab")
        self.proc = subprocess.Popen([binary(), *args], stdout=self._out,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)

    def stop(self) -> None:
        """Ctrl-C (canpos stops cleanly), then a kill after 5 s; always reaped."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._out.close()


class Bus:
    """A socketcand hub (``canpos bus serve``) on a free loopback port."""

    def __init__(self, workdir: Optional[Path] = None, channel: str = "can0"):
        self.workdir = Path(workdir or tempfile.mkdtemp(prefix="canpos-bus-"))
        self.host = "127.0.0.1"
        self.port = free_port()
        self.channel = channel
        self._child = _Child(["bus", "serve", "--listen", f"{self.host}:{self.port}"],
                             self.workdir / "hub.log")
        try:
            _wait_port(self.port, self._child.proc, self._child.log)
        except BaseException:
            self._child.stop()
            raise

    @property
    def url(self) -> str:
        """The bus URL for ``canpos … --bus``."""
        return f"socketcand://{self.host}:{self.port}/{self.channel}"

    def python_can(self, interface: str = "canpos") -> dict:
        """Keyword arguments of ``can.Bus`` for this bus: through this package's ``canpos``
        interface (true remote frames, bus errors, the bus timeline's timestamps), or with
        ``interface="socketcand"`` through python-can's own socketcand client."""
        return {"interface": interface, "host": self.host, "port": self.port,
                "channel": self.channel}

    def stop(self) -> None:
        self._child.stop()


class Sensor:
    """``canpos run`` on a bus, with its control interface on a free loopback port and its
    state file in a directory of its own. ``control`` is a connected :class:`ControlClient`."""

    def __init__(self, bus: Bus, model: Optional[str] = None, order_code: Optional[str] = None,
                 node_id: Optional[int] = 127, serial: Optional[int] = None,
                 extra_args: Optional[List[str]] = None, **options):
        self.bus = bus
        self.node_id = node_id
        self.control_port = free_port()
        self.state_dir = Path(tempfile.mkdtemp(prefix="canpos-sensor-", dir=bus.workdir))
        args = ["run", "--bus", bus.url, "--control", f"127.0.0.1:{self.control_port}",
                "--state-dir", str(self.state_dir)]
        if model is not None:
            args += ["--model", model]
        if order_code is not None:
            args += ["--order-code", order_code]
        if node_id is not None:
            args += ["--node-id", str(node_id)]
        if serial is not None:
            args += ["--serial", str(serial)]
        # Other `canpos run` options by name: motion="sine:…", magnet=[100, 200], ideal=True.
        for k, v in options.items():
            flag = "--" + k.replace("_", "-")
            for item in (v if isinstance(v, (list, tuple)) else [v]):
                if item is True:
                    args.append(flag)
                elif item is not False and item is not None:
                    args += [flag, str(item)]
        args += extra_args or []
        self._child = _Child(args, self.state_dir / "sensor.log")
        try:
            _wait_port(self.control_port, self._child.proc, self._child.log)
            self.control = ControlClient("127.0.0.1", self.control_port)
        except BaseException:
            self._child.stop()
            raise

    def state(self) -> dict:
        return self.control.state()

    def stop(self) -> None:
        try:
            self.control.close()
        except (AttributeError, OSError):
            pass
        self._child.stop()
