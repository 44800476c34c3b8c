"""One harness session (run under valgrind by test_valgrind.py): a TH FMU instantiated,
initialised, configured by SDO, started, stepped at 1 ms for 50 ms with a moving magnet, given
a malformed LS-BUS buffer, reset, stepped again, terminated and freed."""

import struct
import sys

from fmpy.fmi1 import FMICallException

from harness import Session, transmit


def main(path):
    s = Session(path)
    s.start(node_id=5)
    s.step_to(0.003)
    s.send(transmit(0x605, struct.pack("<BHBI", 0x40, 0x1018, 4, 0)))
    s.send(transmit(0x605, struct.pack("<BHBI", 0x2B, 0x1017, 0, 10)))
    s.send(transmit(0x000, bytes([0x01, 5])))
    for k in range(50):
        s.set("magnet_position[1]", 300.0 + 0.1 * k)
        s.step_to(0.003 + (k + 1) * 0.001)
    try:
        s.fmu.setBinary([s.vr["CAN.Rx_Data"]], [b"\x10\x00\x00\x00\xff\x00\x00\x00"])
        raise SystemExit("a malformed buffer was taken")
    except FMICallException:
        pass
    assert s.get("nmt_state") == 5
    tpdos = len(s.frames(0x185))
    assert tpdos >= 45, tpdos
    s.fmu.reset()
    s.t = 0.0
    s.start(node_id=6)
    s.step_to(0.005)
    s.close()
    print(f"session done: {tpdos} TPDOs, {len(s.ops)} operations after the reset")


if __name__ == "__main__":
    main(sys.argv[1])
