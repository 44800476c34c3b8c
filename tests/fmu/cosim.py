"""A small FMI 3.0 co-simulation master for LS-BUS CAN FMUs, on fmpy's low-level fmi3 API.

It routes LS-BUS binaries and clocks between node FMUs and canpos's bus-simulation FMU itself
(the test's own code, not canpos's), on integer nanoseconds of co-simulation time:

1. the bus says when the frame on its wire ends (`nextEventTime` of its last
   `fmi3UpdateDiscreteStates`); the next communication point is that, or the current time plus
   44 bit times (the shortest frame's SOF to end of EOF: a frame handed in within the step
   cannot end inside it), whichever is first;
2. every node FMU steps there with early return; each early return is an event whose `Tx_Data`
   is collected with its time; the controller (this script) adds its frames due in the step;
3. the bus steps from event time to event time and takes each time's operations in event mode
   (every node's of one time in one event, so they arbitrate together);
4. at the communication point the bus delivers in event mode; each node gets its `Rx_Data`
   there, and whatever a node answers at once goes back to the bus at the same time.
"""

import shutil
import struct

from fmpy import extract, read_model_description
from fmpy.fmi3 import FMU3Slave

from harness import transmit

OP_TRANSMIT = 0x10
OP_CONFIRM = 0x20
OP_ARBITRATION_LOST = 0x30
OP_BUS_ERROR = 0x31
OP_CONFIGURATION = 0x40
OP_STATUS = 0x41


def operations(buf):
    """The operations of a binary: (op code, payload bytes after the 8-byte header)."""
    ops, at = [], 0
    while at < len(buf):
        code, length = struct.unpack_from("<II", buf, at)
        assert 8 <= length <= len(buf) - at, (at, length, buf)
        ops.append((code, bytes(buf[at + 8 : at + length])))
        at += length
    return ops


def ns(seconds):
    return int(round(seconds * 1e9))


class Fmu:
    """One instance of an FMU, in event mode use with early return."""

    def __init__(self, path, name, unzipdir=None):
        self.md = read_model_description(path, validate=False)
        # Extracted here: removed again by close().
        self.own_dir = unzipdir is None
        self.unzipdir = unzipdir or extract(path)
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.fmu = FMU3Slave(
            guid=self.md.instantiationToken,
            unzipDirectory=self.unzipdir,
            modelIdentifier=self.md.coSimulation.modelIdentifier,
            instanceName=name,
        )
        self.fmu.instantiate(eventModeUsed=True, earlyReturnAllowed=True)
        self.t = 0

    def start(self, params, terminals=()):
        """Initialization with `params` ({name: (type, value)}); returns what the FMU sends at
        time 0 (the event mode that follows initialization)."""
        f = self.fmu
        f.enterInitializationMode(startTime=0.0)
        for name, (kind, value) in params.items():
            getattr(f, "set" + kind)([self.vr[name]], [value])
        f.exitInitializationMode()
        # An FMU with clocks is in event mode after initialization: its first event is now.
        out = self.tx(terminals)
        self.next_event = self.event([], 0)
        f.enterStepMode()
        return out

    def event(self, rx, t_ns):
        """In event mode at t: hands in `rx` (list of (terminal, bytes)) and updates the
        discrete states; returns the next event time (s) if the FMU gives one."""
        f = self.fmu
        for term, data in rx:
            f.setBinary([self.vr[term + ".Rx_Data"]], [data])
            f.setClock([self.vr[term + ".Rx_Clock"]], [True])
        update = f.updateDiscreteStates()
        return update[5] if update[4] else None

    def tx(self, terminals):
        """The Tx_Data of every terminal whose Tx_Clock ticked (read in event mode)."""
        out = []
        for term in terminals:
            if self.fmu.getClock([self.vr[term + ".Tx_Clock"]])[0]:
                data = self.fmu.getBinary([self.vr[term + ".Tx_Data"]])[0] or b""
                out.append((term, data))
        return out

    def step_to(self, t_ns):
        """doStep with early return towards t; returns (event, time reached ns)."""
        event, _term, _early, last = self.fmu.doStep(self.t / 1e9, (t_ns - self.t) / 1e9)
        self.t = ns(last)
        return event

    def close(self):
        self.fmu.terminate()
        self.fmu.freeInstance()
        if self.own_dir:
            shutil.rmtree(self.unzipdir, ignore_errors=True)


class CoSim:
    """Node FMUs (each on its bus terminal `NodeK`, K from 1) and a controller terminal on the
    bus-simulation FMU; the controller is this script."""

    def __init__(self, bus, nodes, controller_terminal, bit_ns, first_sends=()):
        self.bus, self.nodes, self.ctl = bus, nodes, controller_terminal
        # What the nodes sent at time 0, after their initialization: [(node index, bytes)].
        self.first = list(first_sends)
        self.h = 44 * bit_ns
        self.t = 0
        self.bus_next = None
        self.received = []  # the controller's frames: (id, data, end-of-frame ns)
        self.other = []  # the controller's other operations: (op code, payload, ns)

    def node_tx(self, node):
        f = node.fmu
        f.enterEventMode()
        out = node.tx(["CAN"])
        node.event([], node.t)
        f.enterStepMode()
        return out

    def run(self, until_ns, controller_frames):
        """Runs to `until_ns`; `controller_frames`: sorted [(t_ns, id, data)] to send."""
        pending = list(controller_frames)
        terminals = [f"Node{k + 1}" for k in range(len(self.nodes))]
        while self.t < until_ns:
            t_next = min(self.t + self.h, until_ns)
            if self.bus_next is not None and self.t < ns(self.bus_next) < t_next:
                t_next = ns(self.bus_next)
            # 2. the nodes, each to t_next with early return, their frames collected by time.
            sends = [(0, k, data) for k, data in self.first]
            self.first = []
            for k, node in enumerate(self.nodes):
                while node.t < t_next:
                    if node.step_to(t_next):
                        for _, data in self.node_tx(node):
                            sends.append((node.t, k, data))
            while pending and pending[0][0] <= t_next:
                at, can_id, data = pending.pop(0)
                sends.append((at, len(self.nodes), transmit(can_id, data)))
            sends.sort(key=lambda s: (s[0], s[1]))
            # 3. the bus takes each time's operations in one event (those of t_next in the
            # event at t_next below, with what it delivers then).
            at_end = [s for s in sends if s[0] == t_next]
            sends = [s for s in sends if s[0] < t_next]
            i = 0
            while i < len(sends):
                at = sends[i][0]
                group = []
                while i < len(sends) and sends[i][0] == at:
                    k = sends[i][1]
                    term = terminals[k] if k < len(self.nodes) else self.ctl
                    group.append((term, sends[i][2]))
                    i += 1
                if at > self.bus.t:
                    event = self.bus.step_to(at)
                    assert not event and self.bus.t == at, (at, self.bus.t)
                self.bus.fmu.enterEventMode()
                self.bus_next = self.bus.event(group, at)
                self.bus.fmu.enterStepMode()
            # 4. the bus to t_next; what it delivers there, and the nodes' answers at once.
            if self.bus.t < t_next:
                event = self.bus.step_to(t_next)
                assert self.bus.t == t_next, (t_next, self.bus.t)
            self.t = t_next
            self.bus.fmu.enterEventMode()
            answers = [
                (terminals[k] if k < len(self.nodes) else self.ctl, data)
                for _, k, data in at_end
            ]
            for term, data in self.bus.tx(terminals + [self.ctl]):
                if term == self.ctl:
                    for code, payload in operations(data):
                        if code == OP_TRANSMIT:
                            can_id, _i, _r, n = struct.unpack_from("<IBBH", payload)
                            self.received.append((can_id, bytes(payload[8 : 8 + n]), t_next))
                        else:
                            self.other.append((code, payload, t_next))
                    continue
                node = self.nodes[terminals.index(term)]
                node.fmu.enterEventMode()
                node.event([("CAN", data)], t_next)
                answers += [(term, d) for _, d in node.tx(["CAN"])]
                node.fmu.enterStepMode()
            self.bus_next = self.bus.event(answers, t_next)
            self.bus.fmu.enterStepMode()
