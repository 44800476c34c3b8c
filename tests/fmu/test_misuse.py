"""Bad calls get clear answers (issue 31 item 4): every misuse returns fmi3Error with its
reason in the importer's log, and the instance goes on as if the call had not been made."""

import ctypes
import struct

import pytest
from fmpy.fmi1 import FMICallException
from fmpy.fmi3 import FMU3Slave

from harness import Session, transmit

ERROR = 3


def refused(s, call, reason):
    """`call` fails with fmi3Error and the log's last error names `reason`."""
    before = len(s.log)
    with pytest.raises(FMICallException) as e:
        call()
    assert e.value.status == ERROR
    errors = [m for st, m in s.log[before:] if st == ERROR]
    assert errors and reason in errors[-1], (reason, s.log[before:])


def still_works(s):
    t = s.t
    s.step_to(t + 0.002)
    assert s.t == pytest.approx(t + 0.002)


def test_calls_out_of_order(fmus):
    s = Session(fmus["th"])
    vr_tx = s.vr["CAN.Tx_Clock"]
    refused(s, lambda: s.fmu.doStep(0.0, 0.001), "not allowed in Instantiated mode")
    refused(s, lambda: s.fmu.exitInitializationMode(), "not allowed in Instantiated mode")
    refused(s, lambda: s.fmu.enterStepMode(), "not allowed in Instantiated mode")
    s.start(node_id=5)
    refused(s, lambda: s.fmu.enterInitializationMode(), "not allowed in Step mode")
    refused(s, lambda: s.fmu.getClock([vr_tx]), "not allowed in Step mode")
    refused(s, lambda: s.fmu.updateDiscreteStates(), "not allowed in Step mode")
    refused(s, lambda: s.fmu.setClock([s.vr["CAN.Rx_Clock"]], [True]), "cannot be set in Step mode")
    refused(s, lambda: s.fmu.setUInt8([s.vr["node_id"]], [7]), "cannot be set in Step mode")
    refused(s, lambda: s.fmu.setFloat64([s.vr["true_position[1]"]], [1.0]), "(Output)")
    # A step that does not start where the last one ended.
    refused(s, lambda: s.fmu.doStep(s.t + 0.5, 0.001), "but the instance is at")
    refused(s, lambda: s.fmu.doStep(s.t, -0.001), "not positive")
    still_works(s)
    assert s.get("node_id") == 5
    s.close()


def test_null_pointers_wrong_sizes_and_wrong_types(fmus):
    s = Session(fmus["th"])
    s.start()
    f, c = s.fmu, s.fmu.component
    vr = (ctypes.c_uint32 * 1)(s.vr["magnet_position[1]"])
    out = (ctypes.c_double * 2)()
    refused(s, lambda: f.fmi3GetFloat64(c, vr, 1, out, 2), "nValues = 2 for 1 value references")
    refused(s, lambda: f.fmi3GetFloat64(c, None, 1, out, 1), "is null")
    refused(s, lambda: f.fmi3SetFloat64(c, vr, 1, None, 1), "is null")
    refused(s, lambda: f.fmi3GetUInt8(c, vr, 1, (ctypes.c_uint8 * 1)(), 1), "is a Float64, not a UInt8")
    refused(s, lambda: s.fmu.getFloat64([99999]), "no variable with value reference 99999")
    refused(s, lambda: s.fmu.getInt32([s.vr["node_id"]]), "is a UInt8")
    big = bytes(10_000)
    refused(s, lambda: s.fmu.setBinary([s.vr["CAN.Rx_Data"]], [big]), "its maxSize is")
    refused(s, lambda: s.fmu.setFloat64([s.vr["magnet_position[1]"]], [float("nan")]), "not a finite number")
    refused(s, lambda: s.fmu.setFloat64([s.vr["ambient_temperature"]], [1e9]), "not plausible")
    # Nothing of a refused call was applied.
    assert s.get("magnet_position[1]") == pytest.approx(500.0)
    still_works(s)
    s.close()


def test_malformed_ls_bus_operations_are_refused_whole(fmus):
    s = Session(fmus["th"])
    s.start(node_id=5)
    s.step_to(0.002)
    s.fmu.enterEventMode()
    good = transmit(0x000, bytes([0x01, 5]))
    rx = s.vr["CAN.Rx_Data"]
    for bad, reason in [
        (good + b"\x10\x00\x00", "shorter than the 8-byte header"),
        (good + struct.pack("<II", 0x10, 400), "runs past the buffer"),
        (good + transmit(0x601, bytes(9), dlc=9), "above 8"),
        (good + struct.pack("<II", 0x7777, 8), "not a CAN operation"),
        (good + struct.pack("<IIIBBB", 0x31, 15, 0x185, 9, 1, 1), "Bus Error code 9"),
    ]:
        refused(s, lambda: s.fmu.setBinary([rx], [bad]), reason)
        assert "malformed LS-BUS operation at byte" in s.log[-1][1]
    s.fmu.updateDiscreteStates()
    s.fmu.enterStepMode()
    still_works(s)
    # The NMT start in the refused buffers was not taken.
    assert s.get("nmt_state") == 127
    s.close()


def test_a_wrong_instantiation_token_is_refused(fmus):
    s = Session(fmus["th"])
    s.fmu.freeInstance()
    log = []
    wrong = FMU3Slave(guid="{00000000-0000-0000-0000-000000000000}", unzipDirectory=s.dir,
                      modelIdentifier=s.md.coSimulation.modelIdentifier, instanceName="wrong")

    def logger(env, status, category, message):
        log.append((status, message.decode()))

    with pytest.raises(Exception):
        wrong.instantiate(eventModeUsed=True, logMessage=logger)
    assert any(st == ERROR and "instantiationToken" in m and "not this FMU's" in m
               for st, m in log), log


def test_unsupported_functions_and_freed_instances(fmus):
    s = Session(fmus["th"])
    s.start()
    refused(s, lambda: s.fmu.getFMUState(), "canGetAndSetFMUState is false")
    refused(s, lambda: s.fmu.fmi3GetNumberOfContinuousStates(s.fmu.component, None),
            "Model Exchange only")
    still_works(s)
    # A pointer that is not one of its instances (a freed one, another library's) is not
    # dereferenced: refused (stderr says why: such a pointer has no logger).
    foreign = ctypes.create_string_buffer(64)
    ev, term, early, last = (ctypes.c_bool(), ctypes.c_bool(), ctypes.c_bool(), ctypes.c_double())
    with pytest.raises(FMICallException) as e:
        s.fmu.fmi3DoStep(ctypes.addressof(foreign), s.t, 0.001, True, ctypes.byref(ev),
                         ctypes.byref(term), ctypes.byref(early), ctypes.byref(last))
    assert e.value.status == ERROR
    still_works(s)
    s.close()
