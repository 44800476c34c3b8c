"""A python-can interface for canpos buses: ``can.Bus(interface="canpos", …)``.

It speaks the socketcand protocol of a canpos hub (``canpos bus serve``, or the embedded hub of
``canpos run``) in raw mode with canpos's extensions (docs/SOCKETCAND.md): ``< rtr on >`` so
that remote frames keep their RTR bit and DLC both ways, and ``< errors on >`` so that bus
errors arrive as error frames. Timestamps are the hub's, i.e. the bus timeline's end-of-frame
times. Registered through python-can's ``can.interface`` entry point.

Against a server without the extensions (the reference socketcand daemon) the bus refuses to
open, with the server's answer: use python-can's own ``socketcand`` interface there.
"""
from __future__ import annotations

import select
import socket
import time
from collections import deque
from typing import Deque, Optional, Tuple

import can

__all__ = ["CanposBus"]

DEFAULT_PORT = 29536


class CanposBus(can.BusABC):
    """A connection to one channel of a canpos hub.

    :param channel: the hub channel (default ``can0``).
    :param host: the hub's address (loopback by default).
    :param port: the hub's port (socketcand's 29536 by default).
    :param connect_timeout: seconds to wait for the connection and each handshake answer.
    """

    def __init__(self, channel: str = "can0", host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 connect_timeout: float = 5.0, **kwargs):
        self.channel_info = f"canpos hub {host}:{port}/{channel}"
        self._buf = ""
        self._queue: Deque[can.Message] = deque()
        self._sock = socket.create_connection((host, int(port)), timeout=connect_timeout)
        try:
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            deadline = time.monotonic() + connect_timeout
            self._expect("< hi >", deadline)
            for cmd in (f"< open {channel} >", "< rawmode >", "< rtr on >", "< errors on >"):
                self._sock.sendall(cmd.encode("ascii"))
                self._expect("< ok >", deadline, cmd)
        except BaseException:
            self._sock.close()
            raise
        self._sock.settimeout(None)
        self.channel = channel
        super().__init__(channel=channel, **kwargs)

    # --- the protocol -----------------------------------------------------------------------

    def _element(self, deadline: Optional[float]) -> Optional[str]:
        """The next ``< … >`` element, or None once `deadline` (monotonic) has passed."""
        while True:
            start = self._buf.find("<")
            end = self._buf.find(">", start + 1) if start >= 0 else -1
            if end >= 0:
                el = self._buf[start:end + 1]
                self._buf = self._buf[end + 1:]
                return el
            if start < 0:
                self._buf = ""
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([self._sock], [], [], wait)
            if not ready:
                return None
            data = self._sock.recv(65536)
            if not data:
                raise can.CanOperationError(f"{self.channel_info}: the hub closed the connection")
            self._buf += data.decode("ascii", errors="replace")

    def _expect(self, answer: str, deadline: float, cmd: str = "connect") -> None:
        while True:
            el = self._element(deadline)
            if el is None:
                raise can.CanInitializationError(f"{self.channel_info}: no answer to {cmd}")
            if " ".join(el.split()) == answer:
                return
            msg = self._parse(el)
            if msg is not None:
                self._queue.append(msg)  # a frame that arrived during the handshake
            elif el.startswith("< error"):
                raise can.CanInitializationError(
                    f"{self.channel_info}: {cmd} was answered {el} (not a canpos hub? use "
                    "python-can's socketcand interface)")

    def _parse(self, el: str) -> Optional[can.Message]:
        t = el[1:-1].split()
        try:
            if len(t) >= 3 and t[0] == "frame":
                data = bytes.fromhex(t[3]) if len(t) > 3 else b""
                return can.Message(arbitration_id=int(t[1], 16), is_extended_id=len(t[1]) > 3,
                                   data=data, timestamp=float(t[2]), channel=self.channel)
            if len(t) == 4 and t[0] == "rtr":
                return can.Message(arbitration_id=int(t[1], 16), is_extended_id=len(t[1]) > 3,
                                   is_remote_frame=True, dlc=int(t[3], 16),
                                   timestamp=float(t[2]), channel=self.channel)
            if len(t) >= 3 and t[0] == "error":
                data = bytes(int(b, 16) for b in t[3:11])
                return can.Message(arbitration_id=int(t[1], 16), is_error_frame=True,
                                   data=data, dlc=len(data), timestamp=float(t[2]),
                                   channel=self.channel)
        except ValueError:
            return None
        return None

    # --- can.BusABC ---------------------------------------------------------------------------

    def _recv_internal(self, timeout: Optional[float]) -> Tuple[Optional[can.Message], bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._queue:
            el = self._element(deadline)
            if el is None:
                return None, False
            msg = self._parse(el)
            if msg is not None:
                self._queue.append(msg)
        return self._queue.popleft(), False

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        if msg.is_fd:
            raise can.CanOperationError("a canpos bus carries classic CAN frames only")
        ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
        if msg.is_remote_frame:
            cmd = f"< send {ident} {msg.dlc:X} R >"
        else:
            data = " ".join(f"{b:02X}" for b in msg.data)
            cmd = f"< send {ident} {len(msg.data):X} {data} >"
        try:
            self._sock.sendall(cmd.encode("ascii"))
        except OSError as e:
            raise can.CanOperationError(f"{self.channel_info}: {e}") from e

    def shutdown(self) -> None:
        super().shutdown()
        try:
            self._sock.close()
        except OSError:
            pass
