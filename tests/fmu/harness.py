"""A co-simulation importer for the tests: fmpy's FMI 3.0 API only (no canpos code), with the
FMI-LS-BUS 1.0 CAN operations written and read here from the layered standard's layout."""

import struct

from fmpy import extract, read_model_description
from fmpy.fmi3 import FMU3Slave

TRANSMIT, FD_TRANSMIT, CONFIRM, ARB_LOST, BUS_ERROR, CONFIGURATION, STATUS, WAKEUP = (
    0x10, 0x11, 0x20, 0x30, 0x31, 0x40, 0x41, 0x42)


def transmit(can_id, data=b"", rtr=False, ide=False, dlc=None):
    """A CAN Transmit operation (header, id, ide, rtr, data length, data)."""
    n = len(data) if dlc is None else dlc
    body = struct.pack("<IBBH", can_id, int(ide), int(rtr), n) + (b"" if rtr else bytes(data))
    return struct.pack("<II", TRANSMIT, 8 + len(body)) + body


def op(code, body=b""):
    """Any operation: its header and body."""
    return struct.pack("<II", code, 8 + len(body)) + body


def parse(buf):
    """The operations of a buffer: (code, fields); raises on a malformed one."""
    ops, at = [], 0
    while at < len(buf):
        code, length = struct.unpack_from("<II", buf, at)
        assert 8 <= length <= len(buf) - at, f"bad length {length} at {at}"
        body = buf[at + 8:at + length]
        if code == TRANSMIT:
            can_id, ide, rtr, n = struct.unpack_from("<IBBH", body)
            ops.append((code, (can_id, bytes(body[8:8 + n]) if not rtr else None)))
        elif code == CONFIGURATION:
            ops.append((code, (body[0], struct.unpack_from("<I", body, 1)[0])))
        elif code == STATUS:
            ops.append((code, body[0]))
        else:
            ops.append((code, bytes(body)))
        at += length
    return ops


class Session:
    """One FMU instance stepped like an LS-BUS importer does: doStep with early return, event
    mode whenever the FMU asks for it or the harness puts frames on its bus."""

    def __init__(self, path, name="th", start=0.0, early=True):
        self.md = read_model_description(path)
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.dir = extract(path)
        self.log = []
        self.fmu = FMU3Slave(
            guid=self.md.instantiationToken,
            unzipDirectory=self.dir,
            modelIdentifier=self.md.coSimulation.modelIdentifier,
            instanceName=name,
        )
        self.fmu.instantiate(loggingOn=False, eventModeUsed=True, earlyReturnAllowed=early,
                             logMessage=self._logger())
        self.t = start
        self.ops = []  # (time, code, fields) of everything the FMU sent
        self.events = 0

    def _logger(self):
        def log(env, status, category, message):
            self.log.append((status, message.decode() if message else ""))
        return log

    def start(self, **params):
        self.fmu.enterInitializationMode(startTime=self.t)
        for name, value in params.items():
            vr = [self.vr[name]]
            if isinstance(value, bool):
                self.fmu.setBoolean(vr, [value])
            elif isinstance(value, float):
                self.fmu.setFloat64(vr, [value])
            else:
                self.fmu.setUInt8(vr, [value])
        self.fmu.exitInitializationMode()
        # In event mode now (eventModeUsed).
        self.fmu.updateDiscreteStates()
        self._read_tx()
        self.fmu.enterStepMode()

    def _read_tx(self):
        if self.fmu.getClock([self.vr["CAN.Tx_Clock"]])[0]:
            data = self.fmu.getBinary([self.vr["CAN.Tx_Data"]])[0]
            assert data, "Tx_Clock ticked with an empty Tx_Data"
            for code, fields in parse(data):
                self.ops.append((self.t, code, fields))

    def step_to(self, t_end, h=0.001):
        """Steps of h (shortened by early returns) until t_end; handles the FMU's events."""
        while self.t < t_end - 1e-12:
            step = min(h, t_end - self.t)
            event, terminate, early, last = self.fmu.doStep(self.t, step)
            assert not terminate
            self.t = last if early else self.t + step
            if event:
                self.events += 1
                self.fmu.enterEventMode()
                self._read_tx()
                self.fmu.updateDiscreteStates()
                self.fmu.enterStepMode()

    def send(self, *operations):
        """Puts operations on the FMU's bus now (an event), and reads what it answers at once."""
        self.fmu.enterEventMode()
        self.fmu.setBinary([self.vr["CAN.Rx_Data"]], [b"".join(operations)])
        self.fmu.setClock([self.vr["CAN.Rx_Clock"]], [True])
        self.fmu.updateDiscreteStates()
        self._read_tx()
        self.fmu.enterStepMode()

    def frames(self, can_id=None):
        """(time, id, data) of the CAN frames the FMU sent."""
        return [(t, f[0], f[1]) for t, code, f in self.ops
                if code == TRANSMIT and (can_id is None or f[0] == can_id)]

    def get(self, name):
        v = next(v for v in self.md.modelVariables if v.name == name)
        getter = getattr(self.fmu, "get" + v.type)
        return getter([v.valueReference])[0]

    def set(self, name, value):
        v = next(v for v in self.md.modelVariables if v.name == name)
        getattr(self.fmu, "set" + v.type)([v.valueReference], [value])

    def close(self):
        self.fmu.terminate()
        self.fmu.freeInstance()
