"""The hub's socketcand protocol against independent clients: python-can's stock socketcand
client (unchanged behaviour: remote frames reach it as zero-length data frames, nothing of the
extensions), and a client written here from docs/SOCKETCAND.md that opts into remote frames and
guards a canpos sensor with true RTR frames through the hub."""
import socket
import struct
import threading
import time

import can
import canopen
import pytest


class RawClient:
    """A minimal socketcand client on a plain socket, written from the protocol text."""

    def __init__(self, port, channel="can0"):
        self.s = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buf = b""
        assert self.element() == "< hi >"
        self.cmd(f"< open {channel} >", "< ok >")
        self.cmd("< rawmode >", "< ok >")

    def cmd(self, text, want):
        self.s.sendall(text.encode())
        got = self.element()
        assert got == want, (text, got)

    def element(self, timeout=5.0):
        end = time.monotonic() + timeout
        while b">" not in self.buf:
            left = end - time.monotonic()
            if left <= 0:
                return None
            self.s.settimeout(left)
            try:
                chunk = self.s.recv(4096)
            except socket.timeout:
                return None
            assert chunk, "server closed"
            self.buf += chunk
        i = self.buf.index(b">") + 1
        el, self.buf = self.buf[:i].decode().strip(), self.buf[i:]
        return el[el.index("<"):]

    def close(self):
        self.s.close()


@pytest.fixture
def bus_url(hub):
    """These tests are about the socketcand hub: the sensors join it, whatever the transport."""
    return f"socketcand://127.0.0.1:{hub}/can0"


def test_true_rtr_guarding_through_the_hub(hub, sensors):
    """A client that opted in (`< rtr on >`) guards a canpos TH with true remote frames: each
    `< send 77F 1 R >` gets one answer with the toggle alternating; a python-can client on the
    same channel sees the requests as zero-length data frames, as it always has."""
    observer = can.Bus(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
    master = RawClient(hub)
    try:
        master.cmd("< rtr on >", "< ok >")
        sensors("th")
        end = time.monotonic() + 10
        while True:
            assert time.monotonic() < end, "no boot-up"
            el = master.element(0.5)
            if el is not None and el.startswith("< frame 77F ") and el.endswith(" 00 >"):
                break
        # The observer never speaks, so the hub holds its frames back after its rawmode
        # `< ok >` (at most 500 ms, docs/SOCKETCAND.md): wait until it has the boot-up too.
        m = observer.recv(5.0)
        while m is not None and not (m.arbitration_id == 0x77F and bytes(m.data) == b"\x00"):
            m = observer.recv(5.0)
        assert m is not None, "the observer never got the boot-up"
        answers = []
        for _ in range(6):
            # DLC 1: the length of the guarding answer; only the extension can carry it.
            master.s.sendall(b"< send 77F 1 R >")
            while True:
                el = master.element()
                assert el is not None, "no guarding answer"
                if el.startswith("< frame 77F "):
                    answers.append(bytes.fromhex(el.split()[4]))
                    break
        assert all(len(a) == 1 and a[0] & 0x7F == 0x7F for a in answers), answers
        toggles = [a[0] >> 7 for a in answers]
        assert all(x != y for x, y in zip(toggles, toggles[1:])), toggles
        # python-can: the requests with DLC 1 cannot be written without the extension (the hub
        # counts them); it sees the answers, never an `< rtr … >` element.
        seen = []
        while (m := observer.recv(0.2)) is not None:
            seen.append(m)
        assert [m for m in seen if m.arbitration_id == 0x77F and m.dlc == 1], seen
        assert not [m for m in seen if m.is_remote_frame], seen
        # A DLC-0 remote frame reaches python-can as the zero-length data frame it knows.
        master.s.sendall(b"< sendrtr 123 >")
        m = observer.recv(2.0)
        while m is not None and m.arbitration_id != 0x123:
            m = observer.recv(2.0)
        assert m is not None and m.dlc == 0 and not m.is_remote_frame
    finally:
        master.close()
        observer.shutdown()


def test_python_can_stock_client_unchanged(hub):
    """python-can's socketcand client: handshake, frames both ways, an empty frame, and no
    extension element ever, through the hub."""
    a = can.Bus(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
    b = can.Bus(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
    try:
        time.sleep(0.05)
        a.send(can.Message(arbitration_id=0x181, data=[1, 2, 3], is_extended_id=False))
        a.send(can.Message(arbitration_id=0x80, data=[], is_extended_id=False))
        a.send(can.Message(arbitration_id=0x1234567, data=[9], is_extended_id=True))
        got = [b.recv(2.0) for _ in range(3)]
        assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in got] == [
            (0x181, b"\x01\x02\x03", False), (0x80, b"", False), (0x1234567, b"\x09", True)]
    finally:
        a.shutdown()
        b.shutdown()


def test_bcm_sync_producer_for_a_sensor(hub, sensors):
    """A master's SYNC producer as a socketcand BCM job (`< add 0 10000 080 0 >`): a TH with
    TPDO1 on SYNC (0x1800:2 = 1) answers every SYNC; `< delete 080 >` stops both."""
    observer = can.Bus(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
    bcm = socket.create_connection(("127.0.0.1", hub), timeout=5)
    try:
        sensors("th", extra=["--nmt", "operational"])
        time.sleep(0.5)
        bcm.recv(64)
        bcm.sendall(b"< open can0 >")
        assert bcm.recv(64) == b"< ok >"
        bcm.sendall(b"< send 67F 8 2f 00 18 02 01 00 00 00 >")
        time.sleep(0.2)
        while observer.recv(0.05) is not None:
            pass
        bcm.sendall(b"< add 0 10000 080 0 >")
        # 30 cycles of 10 ms, given up to 2 s: a loaded machine (the UML guest beside a build)
        # may run the hub late, and the job then skips cycles rather than bursting.
        t0 = time.monotonic()
        syncs, pdos = 0, 0
        while syncs < 30 and time.monotonic() - t0 < 2.0:
            m = observer.recv(0.1)
            if m is None:
                continue
            syncs += m.arbitration_id == 0x80
            pdos += m.arbitration_id == 0x1FF
        assert syncs >= 30, syncs
        bcm.sendall(b"< delete 080 >")
        # The answers to the last SYNCs are still on their way: count until the bus is quiet
        # (within a second: a job that does not stop fails here rather than hanging).
        quiet_by = time.monotonic() + 1.0
        while (m := observer.recv(0.3)) is not None:
            syncs += m.arbitration_id == 0x80
            pdos += m.arbitration_id == 0x1FF
            assert time.monotonic() < quiet_by, "the SYNC job did not stop"
        assert pdos >= syncs - 2, (syncs, pdos)
        # ... and stays quiet (another 0.3 s, well past the 10 ms cycle).
        later, end = [], time.monotonic() + 0.3
        while time.monotonic() < end:
            if (m := observer.recv(0.05)) is not None:
                later.append(m)
        assert not [m for m in later if m.arbitration_id in (0x80, 0x1FF)], later
    finally:
        bcm.close()
        observer.shutdown()


def test_canpos_guard_through_the_hub(hub, sensors):
    """canpos's own master guards a canpos sensor through the hub with true remote frames
    (both opt into the RTR extension); python-can on the channel sees no remote frame."""
    import subprocess

    from conftest import BIN

    observer = can.Bus(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
    try:
        sensors("th")
        url = f"socketcand://127.0.0.1:{hub}/can0"
        end = time.monotonic() + 10
        while True:
            r = subprocess.run([BIN, "guard", "--node", "127", "--count", "4", "--bus", url],
                               capture_output=True, text=True, timeout=30)
            if r.returncode == 0 or time.monotonic() > end:
                break
        assert r.returncode == 0, r.stdout + r.stderr
        lines = r.stdout.splitlines()
        assert len(lines) == 4 and all("pre-operational" in line for line in lines), lines
        seen = []
        while (m := observer.recv(0.2)) is not None:
            seen.append(m)
        assert [m for m in seen if m.arbitration_id == 0x77F and m.dlc == 1], seen
        assert not [m for m in seen if m.is_remote_frame], seen
    finally:
        observer.shutdown()


class Sleeper:
    """How late an independent thread wakes from 1 ms sleeps while it runs: the machine's own
    scheduling delay during a timed window. A wall-time figure is judged against it, measured in
    the same run, so that a loaded CI machine (a 2-core VM stalls ~100 ms now and then) does not
    fail a check that a fixed bound alone would.

    The figure is the sum of all oversleeps, not the worst one: a request crosses three processes
    (client, hub, sensor), and two stalls in one window delay it by both (a CI run saw an SDO
    answer 0.413 s after its request while the worst single oversleep was 0.109 s)."""

    def __init__(self):
        self.total = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            t = time.monotonic()
            time.sleep(0.001)
            self.total += max(0.0, time.monotonic() - t - 0.001)

    def stop(self):
        """The sum of the oversleeps seen (the sleep in progress included), in seconds."""
        self._stop.set()
        self._thread.join()
        return self.total


def test_python_canopen_connects_and_reads_at_once(hub, sensors):
    """Issue 36 item 4: a script that connects and reads at once, 20 times in a row. Each fresh
    connection first only listens: a TPDO (every 10 ms) arrives within python-canopen's default
    SDO timeout (0.3 s; the hub used to hold a new client's frames back for up to 500 ms until it
    spoke); then an SDO read with that default timeout answers.

    Both 0.3 s figures are judged against the machine: an independent 1 ms sleeper runs during
    each window, and a figure may exceed 0.3 s by the sum of its oversleeps there. The old hold-back
    (about 450 ms after connecting) passes a connection only if the machine stalled 150 ms in
    that very window, 20 times in a row. An SDO read that python-canopen gave up on counts when
    its answer (seen by a subscriber of its own) still came within 0.3 s + the oversleep; an
    answer that never comes, or comes later, fails."""
    sensors(model="th", node_id=5)
    setup = canopen.Network()
    setup.connect(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
    try:
        node = canopen.RemoteNode(5, canopen.ObjectDictionary())
        setup.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 2.0
        end = time.monotonic() + 10
        while True:  # the sensor boots
            try:
                node.sdo.download(0x1800, 5, struct.pack("<H", 10))
                break
            except canopen.SdoCommunicationError:
                assert time.monotonic() < end, "node 5 never answered"
        setup.nmt.state = "OPERATIONAL"
    finally:
        setup.disconnect()
    for i in range(20):
        net = canopen.Network()
        net.connect(interface="socketcand", host="127.0.0.1", port=hub, channel="can0")
        try:
            tpdo = threading.Event()
            net.subscribe(0x185, lambda *_: tpdo.set())
            sleeper, t0 = Sleeper(), time.monotonic()
            got = tpdo.wait(5.0)
            took, slack = time.monotonic() - t0, sleeper.stop()
            assert got, f"connection {i}: no TPDO within 5 s of connecting"
            assert took <= 0.3 + slack, (
                f"connection {i}: first TPDO {took:.3f} s after connecting "
                f"(an independent sleeper overslept {slack:.3f} s in all)"
            )
            node = canopen.RemoteNode(5, canopen.ObjectDictionary())
            net.add_node(node)
            assert node.sdo.RESPONSE_TIMEOUT == 0.3  # python-canopen's default, kept
            answered = []
            net.subscribe(0x585, lambda *_: answered.append(time.monotonic()))
            sleeper, t0 = Sleeper(), time.monotonic()
            try:
                value = node.sdo.upload(0x1000, 0)
            except canopen.SdoCommunicationError:
                value = None  # judged by when its answer came
            end = time.monotonic() + 5
            while not answered and time.monotonic() < end:
                time.sleep(0.01)
            slack = sleeper.stop()
            assert answered, f"connection {i}: no SDO answer within 5 s"
            took = answered[0] - t0
            assert took <= 0.3 + slack, (
                f"connection {i}: SDO answer {took:.3f} s after the request "
                f"(an independent sleeper overslept {slack:.3f} s in all)"
            )
            if value is not None:
                assert value == bytes.fromhex("96010800"), i
        finally:
            net.disconnect()
