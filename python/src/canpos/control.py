"""A client of the JSON-lines control interface (docs/CONTROL.md): one typed method per
request; an ``"ok": false`` answer raises :class:`ControlError`."""
import json
import socket
import time
from typing import Any, Dict, List, Optional


class ControlError(RuntimeError):
    """The sensor refused a request (nothing changed); ``str()`` is its reason."""


class ControlClient:
    """One connection to ``canpos run --control HOST:PORT`` (or a scenario's control).

    ``sensor`` selects the sensor of a scenario (0-based) for every request unless a method
    is given another. The sensor closes a connection idle past its timeout (30 s by default,
    ``--control-idle-timeout``); the client then connects again for its next request."""

    def __init__(self, host: str = "127.0.0.1", port: int = 29600, sensor: Optional[int] = None,
                 timeout: float = 10.0):
        self.address = (host, port)
        self.sensor = sensor
        self._timeout = timeout
        self._connect()

    def _connect(self) -> None:
        self._sock = socket.create_connection(self.address, timeout=self._timeout)
        self._file = self._sock.makefile("rw", encoding="utf-8", newline="\n")

    def close(self) -> None:
        try:
            self._file.close()
        except OSError:
            pass  # the sensor closed it first; nothing buffered matters any more
        self._sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def request(self, cmd: str, sensor: Optional[int] = None, **fields: Any) -> Dict[str, Any]:
        """Sends one request (fields that are ``None`` are left out) and returns its answer;
        raises ControlError on a refusal."""
        return self._send({"cmd": cmd, **{k: v for k, v in fields.items() if v is not None}},
                          sensor)

    def _send(self, req: Dict[str, Any], sensor: Optional[int]) -> Dict[str, Any]:
        s = self.sensor if sensor is None else sensor
        if s is not None:
            req["sensor"] = s
        line = self._exchange(json.dumps(req) + "\n")
        answer = json.loads(line)
        if not answer.get("ok"):
            raise ControlError(answer.get("error", "request refused"))
        return answer

    def _exchange(self, request: str) -> str:
        """Sends one request line and reads its answer line. A connection the sensor closed
        as idle ran nothing of the request (a request that arrives whole is always answered
        before a close), so the request goes once more on a new connection."""
        for attempt in range(2):
            try:
                self._file.write(request)
                self._file.flush()
                line = self._file.readline()
            except (BrokenPipeError, ConnectionResetError):
                line = ""
            if line:
                return line
            if attempt == 0:
                self.close()
                self._connect()
        raise ConnectionError(f"control interface {self.address} closed the connection")

    # --- magnets and motion
    def magnet(self, index: int, mm: Optional[float], velocity: Optional[float] = None,
               sensor: Optional[int] = None, wait: bool = False) -> Dict[str, Any]:
        """Moves magnet ``index`` to ``mm`` (``None`` takes it off the rod); ``velocity``
        (mm/s) moves it there at that speed instead of jumping. ``wait=True`` returns once a
        master reads the new position (the sensor publishes it with its next measurement,
        up to a cycle and the output delay later; see :meth:`wait_position`)."""
        # mm is always sent: null takes the magnet off the rod.
        req = {"cmd": "magnet", "index": index, "mm": mm}
        if velocity is not None:
            req["velocity"] = velocity
        answer = self._send(req, sensor)
        if wait and mm is not None:
            self.wait_position(index, mm, sensor=sensor)
        return answer

    def wait_position(self, channel: int, mm: float, tolerance: float = 0.5,
                      timeout: float = 5.0, sensor: Optional[int] = None) -> float:
        """Waits until the position a master reads on ``channel`` (``reported_mm``) is within
        ``tolerance`` mm of ``mm``; returns it, or raises TimeoutError."""
        end = time.monotonic() + timeout
        while True:
            got = self.state(sensor)["reported_mm"][channel]
            if got is not None and abs(got - mm) <= tolerance:
                return got
            if time.monotonic() > end:
                raise TimeoutError(f"channel {channel} reads {got} mm, not {mm} mm, after {timeout} s")
            time.sleep(0.005)

    def motion(self, spec: str, sensor: Optional[int] = None) -> Dict[str, Any]:
        """Starts a motion profile now, e.g. ``sine:center=500,amp=200,period=4``."""
        return self.request("motion", sensor, spec=spec)

    # --- faults and power
    def fault(self, name: str, on: bool = True, value: Optional[float] = None,
              channel: Optional[int] = None, sensor: Optional[int] = None) -> Dict[str, Any]:
        """Turns a fault (``missing-magnet``, ``supply-voltage``, …) on or off."""
        return self.request("fault", sensor, name=name, on=bool(on), value=value,
                            channel=channel)

    def power_cycle(self, sensor: Optional[int] = None) -> Dict[str, Any]:
        """Power off and on: stored data reloaded, boot-up, power-on EMCY."""
        return self.request("power-cycle", sensor)

    def ambient(self, celsius: float, sensor: Optional[int] = None) -> Dict[str, Any]:
        """Ambient temperature of the thermal model, °C."""
        return self.request("ambient", sensor, celsius=celsius)

    def nmt(self, command: str, sensor: Optional[int] = None) -> Dict[str, Any]:
        """Hands the sensor an NMT command (start, stop, preop, reset, reset-comm)."""
        return self.request("nmt", sensor, command=command)

    def set_input(self, index: int, sub: int, value: int) -> Dict[str, Any]:
        """Sets an input of a device served from an EDS (a read-only object of 0x6000-0x9FFF)
        as its own process would; a TPDO that maps it sends the change."""
        return self.request("set-input", index=index, sub=sub, value=value)

    # --- state and timing
    def state(self, sensor: Optional[int] = None) -> Dict[str, Any]:
        """The sensor's state (NMT, node-id, positions, faults, timing, …)."""
        return self.request("state", sensor)

    def positions(self, sensor: Optional[int] = None) -> List[float]:
        """Positions a master reads (0x6020 × step), mm."""
        return self.state(sensor)["reported_mm"]

    def timing(self, sensor: Optional[int] = None) -> Dict[str, Any]:
        """The timing of the last published measurement (cycle, time of flight, delays)."""
        return self.state(sensor)["timing"]

    def reset_lateness(self) -> Dict[str, Any]:
        """Restarts the runtime's wake-up lateness statistics."""
        return self.request("reset-lateness")
