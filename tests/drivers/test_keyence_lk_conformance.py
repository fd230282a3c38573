"""The emulated LK-G3000 and LK-G5000 against their RS-232C command lists, over the pty as any client reaches them.

``MANUAL_LK_G3000`` and ``MANUAL_LK_G5000`` follow the order of the command lists: measurement control
commands (general mode), mode change, setting change / confirmation commands (communication mode),
the order of LK-G Series user manual LK-G-M-NO5-E chapter 5 and of Keyence's LkIF/LkIF2 DLL headers,
which mirror it. The formats are the manual's (5-5 "Outline of the command format": CR-terminated,
the received command repeated as the header, ``ER,<main command>,<code>``; 5-6 "Measurement value
format"). The mnemonics the stored manual pages did not show come from independent clients; the last
field of each entry says which (docs/decisions/0098 lists them):

* ``manual``  - the LK-G Series manual pages 5-5, 5-6;
* ``DESY``    - DESY cmstkmodlab's LK-G3000 driver (the replies it checks; ``V``/``W``/``DO``/``DQ``
  in code it left commented out), ``ISIS`` - ISIS's keylkg IOC emulator (LK-G3000);
* ``clients`` - LK-G5000 clients: LSST ts5 metrology scripts, a Japanese stress-head driver
  (``VS``/``WS``/``KL``/``PW``/``PR``/``A*``), theion-batteries firmware, a C# KeyenceSILib;
* ``inferred`` - not seen anywhere: the single/multiple/all pattern of ``MS``/``MM``/``MA`` applied
  to timing (``T``/``U``), auto-zero (``V``/``W``) and reset (``R``); ``OI`` from LkIF2.h's order.

Walking a list, every command gets the reply given (implemented, or refused as not executable with
the status error); then the same command in the other mode is refused with the status error, which
is what the controller does with a measurement command in communication mode and a setting command
in general mode (and with ``Q0`` / ``R0`` in the mode they would enter). The plant behind the
commands (auto-zero, timing hold, storage, display unit) is checked after the walk.
"""

from __future__ import annotations

import time

import pytest
import serial

from drivers.keyence_lk import DRIVER


class LinearWorld:
    """output = 2 um/V * input (no output2: OUT2 and up read OUT1's value)."""

    def __init__(self) -> None:
        self.u = 617.25  # 1234.5 um = +01.2345 mm

    def command(self, value: float) -> None:
        self.u = float(value)

    def read(self, channel: str) -> float:
        if channel != "output":
            raise KeyError(channel)
        return 2.0 * self.u


# (what, mode, command, reply, source); the world reads 1234.5 um, shown in mm with 4 decimals.
MANUAL_LK_G3000 = [
    ("measured value output, OUT1 and OUT2", "general", "M0", "M0,+01.2345,+01.2345", "manual, DESY, ISIS"),
    ("measured value output, OUT1", "general", "M1", "M1,+01.2345", "manual, DESY, ISIS"),
    ("measured value output, OUT2", "general", "M2", "M2,+01.2345", "manual, ISIS"),
    ("auto-zero ON, OUT1", "general", "V1", "V1", "DESY"),
    ("auto-zero OFF, OUT1", "general", "W1", "W1", "DESY"),
    ("auto-zero ON, both OUTs", "general", "V0", "V0", "DESY"),
    ("auto-zero OFF, both OUTs", "general", "W0", "W0", "DESY"),
    ("reset, OUT1", "general", "VR,1", "VR", "DESY, ISIS"),
    ("panel lock ON", "general", "KL,1", "KL", "DESY"),
    ("panel lock OFF", "general", "KL,0", "KL", "DESY"),
    ("program change", "general", "PW,3", "PW", "DESY"),
    ("program check", "general", "PR", "PR,3", "DESY"),
    ("statistical results output (format unknown: not executable)", "general", "DO,1", "ER,DO,01", "DESY"),
    ("clearing statistics (not executable)", "general", "DQ,1", "ER,DQ,01", "DESY"),
    ("data storage start", "general", "AS", "AS", "DESY"),
    ("data storage stop", "general", "AP", "AP", "DESY"),
    ("data storage initialize", "general", "AQ", "AQ", "DESY"),
    ("data storage output, OUT1 (empty after AQ)", "general", "AO,1", "AO", "DESY"),
    ("data storage status", "general", "AN", "AN,0,0000000,0000000", "DESY"),
    ("change to communication mode", "general", "Q0", "Q0", "manual 5-5, DESY, ISIS"),
    ("set sampling cycle (2 = 100 us)", "communication", "SW,CA,2", "SW,CA", "DESY"),
    ("check sampling cycle", "communication", "SR,CA", "SR,CA,2", "ISIS (SR reply form)"),
    ("set measurement mode (not modelled: not executable)", "communication", "SW,HB,1,0", "ER,SW,01", "DESY, ISIS"),
    ("change to general mode", "communication", "R0", "R0", "manual 5-5, DESY, ISIS"),
]

MANUAL_LK_G5000 = [
    ("measured value output, single", "general", "MS,01", "MS,01,+01.2345", "clients"),
    ("measured value output, multiple", "general", "MM,110000000000", "MM,110000000000,+01.2345,+01.2345", "clients"),
    ("measured value output, all", "general", "MA", "MA,+01.2345,+01.2345", "clients"),
    ("timing ON, single", "general", "TS,01", "TS", "inferred"),
    ("timing ON, multiple", "general", "TM,010000000000", "TM", "inferred"),
    ("timing ON, all", "general", "TA", "TA", "inferred"),
    ("timing OFF, single", "general", "US,01", "US", "inferred"),
    ("timing OFF, multiple", "general", "UM,010000000000", "UM", "inferred"),
    ("timing OFF, all", "general", "UA", "UA", "inferred"),
    ("auto-zero ON, single", "general", "VS,01", "VS", "clients"),
    ("auto-zero ON, multiple", "general", "VM,010000000000", "VM", "inferred"),
    ("auto-zero ON, all", "general", "VA", "VA", "inferred"),
    ("auto-zero OFF, single", "general", "WS,01", "WS", "clients"),
    ("auto-zero OFF, multiple", "general", "WM,010000000000", "WM", "inferred"),
    ("auto-zero OFF, all", "general", "WA", "WA", "inferred"),
    ("measured value reset, single", "general", "RS,01", "RS", "inferred"),
    ("measured value reset, multiple", "general", "RM,110000000000", "RM", "inferred"),
    ("measured value reset, all", "general", "RA", "RA", "inferred"),
    ("panel lock", "general", "KL,1", "KL", "clients"),
    ("program change", "general", "PW,5", "PW", "clients"),
    ("program check", "general", "PR", "PR,5", "clients"),
    ("data storage start", "general", "AS", "AS", "clients"),
    ("data storage stop", "general", "AP", "AP", "clients"),
    ("data storage initialize", "general", "AQ", "AQ", "clients"),
    ("data storage output, OUT01 (empty after AQ)", "general", "AO,01", "AO", "clients"),
    ("data storage status", "general", "AN", "AN,0,0000000,0000000", "clients"),
    ("change to communication mode", "general", "Q0", "Q0", "clients"),
    ("set sampling cycle (5 = 100 us)", "communication", "SW,CA,5", "SW,CA", "clients"),
    ("check sampling cycle", "communication", "SR,CA", "SR,CA,5", "clients (SR reply form: ISIS)"),
    ("set data storage (points, cycle)", "communication", "SW,CF,0001000,00", "SW,CF", "clients"),
    ("check data storage", "communication", "SR,CF", "SR,CF,0001000,00", "clients (SR reply form: ISIS)"),
    ("set minimum display unit (2 = 0.0001 mm)", "communication", "SW,OI,01,2", "SW,OI", "inferred"),
    ("check minimum display unit", "communication", "SR,OI,01", "SR,OI,01,2", "inferred"),
    ("set detection mode (not modelled: not executable)", "communication", "SW,HB,M,01,0", "ER,SW,51", "clients"),
    ("change to general mode", "communication", "R0", "R0", "clients"),
]
STATUS_ERROR = {"M": "01", "MS": "51"}


def start(protocol: str, request, **settings):
    world = LinearWorld()
    emu = DRIVER.emulator({"url": "unused", "protocol": protocol, **settings}, world)
    request.addfinalizer(emu.close)
    port = serial.serial_for_url(emu.url, timeout=1.0)
    request.addfinalizer(port.close)

    def talk(command: str) -> str:
        port.write(command.encode("ascii") + b"\r")
        reply = port.read_until(b"\r")
        assert reply.endswith(b"\r"), f"no CR-terminated reply to {command}: {reply!r}"
        return reply[:-1].decode("ascii")

    return emu, world, talk


def enter(talk, mode: str) -> None:
    """Put the controller in ``mode`` (either answer to the mode change means it is there now)."""
    command = "Q0" if mode == "communication" else "R0"
    assert talk(command) in (command, f"ER,{command},01", f"ER,{command},51")


@pytest.mark.parametrize("protocol, manual", [("M", MANUAL_LK_G3000), ("MS", MANUAL_LK_G5000)],
                         ids=["LK-G3000", "LK-G5000"])
def test_the_command_list_in_order_each_implemented_or_refused_as_the_manual_says(protocol, manual, request):
    emu, _, talk = start(protocol, request)
    for what, mode, command, reply, _source in manual:
        enter(talk, mode)
        assert talk(command) == reply, f"{what}: {command}"
    head_status = STATUS_ERROR[protocol]
    for what, mode, command, _reply, _source in manual:
        enter(talk, "general" if mode == "communication" else "communication")
        assert talk(command) == f"ER,{command.split(',')[0]},{head_status}", f"{what} in the wrong mode"
    assert emu.general_mode  # the last entry, R0, was refused in general mode


@pytest.mark.parametrize("protocol, codes", [("M", ("00", "21", "22")), ("MS", ("50", "61", "62"))],
                         ids=["LK-G3000", "LK-G5000"])
def test_command_count_and_parameter_errors_have_the_models_codes(protocol, codes, request):
    _, _, talk = start(protocol, request)
    command_error, count_error, parameter_error = codes
    assert talk("ZZ") == f"ER,ZZ,{command_error}"
    assert talk("KL") == f"ER,KL,{count_error}"
    assert talk("KL,2") == f"ER,KL,{parameter_error}"
    assert talk("PW,8") == f"ER,PW,{parameter_error}"  # programs 0-7
    assert talk("kl,1") == "KL"  # lower case is accepted (manual 5-5)
    assert talk("Q0") == "Q0"
    assert talk("SW,CA,9") == f"ER,SW,{parameter_error}"  # no such sampling cycle on either model
    assert talk("SW,ZZ,1") == f"ER,SW,{parameter_error}"  # no such setting


def test_lk_g3000_auto_zero_makes_the_present_value_zero_until_it_is_off(request):
    _, world, talk = start("M", request)
    assert talk("V1") == "V1"
    assert talk("M0") == "M0,+00.0000,+01.2345"  # OUT2 keeps its own zero
    world.u += 5.0  # +10 um
    assert talk("M1") == "M1,+00.0100"
    assert talk("W1") == "W1"
    assert talk("M1") == "M1,+01.2445"
    assert talk("M3") == "ER,M3,22"  # no OUT3 on an LK-G3000


def test_lk_g5000_timing_holds_the_value_and_reset_takes_it_again(request):
    _, world, talk = start("MS", request)
    assert talk("TS,01") == "TS"
    world.u = 0.0
    assert talk("MA") == "MA,+01.2345,+00.0000"  # OUT1 held, OUT2 live
    assert talk("RS,01") == "RS"
    world.u = 100.0
    assert talk("MS,01") == "MS,01,+00.0000"  # held again at the reset
    assert talk("US,01") == "US"
    assert talk("MS,01") == "MS,01,+00.2000"
    assert talk("VA") == "VA" and talk("MA") == "MA,+00.0000,+00.0000"


def test_lk_g5000_data_storage_fills_to_the_set_count_then_stops(request):
    _, _, talk = start("MS", request)
    assert talk("Q0") == "Q0" and talk("SW,CF,0000005,00") == "SW,CF" and talk("R0") == "R0"
    assert talk("AQ") == "AQ" and talk("AS") == "AS"
    deadline = time.monotonic() + 3.0
    while talk("AN").startswith("AN,1") and time.monotonic() < deadline:
        time.sleep(0.02)
    assert talk("AN") == "AN,0,0000005,0000005"
    assert talk("AO,01") == "AO," + ",".join(["+01.2345"] * 5)
    assert talk("AO,13") == "ER,AO,62"


def test_lk_g5000_display_unit_changes_the_measured_value_format(request):
    _, _, talk = start("MS", request)
    assert talk("Q0") == "Q0" and talk("SR,OI,01") == "SR,OI,01,2"  # mm, 4 decimals: 0.0001 mm
    assert talk("SW,OI,01,5") == "SW,OI" and talk("R0") == "R0"  # 0.01 um
    assert talk("MS,01") == "MS,01,+1234.50"


def test_an_lk_g3000_has_no_lk_g5000_commands_and_the_reverse(request):
    _, _, g3000 = start("M", request)
    _, _, g5000 = start("MS", request)
    for command in ("MS,01", "MA", "VS,01", "TS,01"):
        assert g3000(command) == f"ER,{command.split(',')[0]},00"
    for command in ("M1", "M0", "V1", "VR,1", "DO,1"):
        assert g5000(command) == f"ER,{command.split(',')[0]},50"
