"""The emulated E-727 against the manual, over TCP as PI's own GCS library reaches it.

``MANUAL`` is the command overview of the E-727 user manual (E727T0005, "GCS Commands"). Walking it
in order, every command is either implemented (the reply as the manual formats it: ``<id>=<value>``,
multi-line replies continued by a space before the LF) or answered as the controller answers a
command it does not have: error 2 ("Unknown command") in the register, readable by ``ERR?``; a set
command stays silent, a query ends with an empty line (docs/decisions/0095). Then the wave types, the
multi-table ``DRC``, the parameter ids and the closed loop in detail.
"""

from __future__ import annotations

import re
import socket
import time

import numpy as np
import pytest

from drivers.emulators.pi_gcs import HELP, PIGCSEmulator, smooth_ramp
from drivers.pi_gcs import DRIVER


class LinearWorld:
    """output = 2 um/V * input."""

    def __init__(self) -> None:
        self.u = 0.0

    def command(self, value: float) -> None:
        self.u = float(value)

    def read(self, channel: str) -> float:
        return 2.0 * self.u if channel == "output" else self.u

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        u = np.asarray(waveform, float)
        self.u = float(u[-1])
        return {"input": u.copy(), "output": 2.0 * u}


class ButterflyWorld(LinearWorld):
    """A magnetostrictive-like plant: strain -3 um/V^2 * u^2, its gain changes sign at 0 V. An
    integrator run through it (the emulator's old servo) wound up to the voltage limit."""

    def read(self, channel: str) -> float:
        return -3.0 * self.u**2 if channel == "output" else self.u


class Client:
    """A raw TCP client: send bytes, read one whole GCS reply (lines up to one not ending in ' \\n')."""

    def __init__(self, url: str) -> None:
        host, port = url.removeprefix("socket://").split(":")
        self.sock = socket.create_connection((host, int(port)), timeout=2.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # as PI's library: no Nagle delay
        self.buf = b""

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def line(self) -> bytes:
        while b"\n" not in self.buf:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("emulator closed the connection")
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        return line + b"\n"

    def reply(self) -> bytes:
        lines = [self.line()]
        while lines[-1].endswith(b" \n"):
            lines.append(self.line())
        return b"".join(lines)

    def ask(self, command: bytes) -> bytes:
        self.send(command if len(command) == 1 else command + b"\n")
        return self.reply()

    def err(self) -> int:
        return int(self.ask(b"ERR?"))

    def close(self) -> None:
        self.sock.close()


def start(world=None, **settings) -> PIGCSEmulator:
    return DRIVER.emulator({"url": "unused", "tcp_port": 0, **settings}, world or LinearWorld())


@pytest.fixture
def emulator(request):
    emu = start()
    request.addfinalizer(emu.close)
    return emu


@pytest.fixture
def client(emulator, request):
    c = Client(emulator.tcp_url)
    request.addfinalizer(c.close)
    return c


# The E-727 command overview (E727T0005, "GCS Commands"). Each row: what is sent, then either the
# expected reply (bytes or a regex; None = a set command, which never replies) and the ERR? code
# after it, or UNSUPPORTED. Rows run in order on one controller, so later rows see earlier state.
UNSUPPORTED = "unsupported"
MANUAL: list[tuple[bytes, object, int]] = [
    (b"*IDN?", re.compile(rb"\(c\)\d{4} Physik Instrumente \(PI\) GmbH & Co\. KG, E-727, \d+, .+\n"), 0),
    (b"CSV?", b"2.0\n", 0),
    (b"ERR?", b"0\n", 0),
    (b"HLP?", re.compile(rb"The following commands are valid: \n(.+ \n)+end of help\n"), 0),
    (b"SAI?", b"1\n", 0),
    (b"SPA? 1 0x0E000200", b"1 0x0E000200=5.000000e-05\n", 0),
    (b"SPA? 1 234881536", b"1 234881536=5.000000e-05\n", 0),  # the same id in decimal
    (b"SPA? 1 0x16000300", b"1 0x16000300=2\n", 0),
    (b"SVO 1 0", None, 0),
    (b"SVO? 1", b"1=0\n", 0),
    (b"SVA 1 1.5", None, 0),
    (b"SVR 1 0.5", None, 0),
    (b"SVA? 1", b"1=2.000000\n", 0),
    (b"VOL? 1", b"1=2.000000\n", 0),
    (b"POS? 1", b"1=4.000000\n", 0),
    (b"TMN? 1", b"1=0.000000\n", 0),
    (b"TMX? 1", b"1=100.000000\n", 0),
    (b"\x07", b"\xb1\n", 0),  # #7: controller ready
    (b"\x05", b"0\n", 0),  # #5: nothing moving
    (b"\x09", b"0\n", 0),  # #9: no wave generator running
    (b"SVO 1 1", None, 0),
    (b"MOV 1 5", None, 0),
    (b"MVR 1 1", None, 0),
    (b"MOV? 1", b"1=6.000000\n", 0),
    (b"ONT? 1", re.compile(rb"1=[01]\n"), 0),
    (b"STP", None, 10),  # "controller was stopped by command"
    (b"SVO 1 0", None, 0),
    (b"WAV 1 X SIN_P 100 2 1 100 0 50", None, 0),
    (b"WAV 1 & LIN 100 -2 3 100 0 10", None, 0),
    (b"WAV 1 & RAMP 100 2 1 100 0 10 50", None, 0),
    (b"WAV 1 + PNT 1 2 0.5 0.5", None, 0),
    (b"WAV? 1 1", b"1 1=300\n", 0),
    (b"WCL 1", None, 0),
    (b"WAV? 1 1", b"1 1=0\n", 0),
    (b"WSL 1 1", None, 0),
    (b"WSL? 1", b"1=1\n", 0),
    (b"WGC 1 1", None, 0),
    (b"WGC? 1", b"1=1\n", 0),
    (b"WTR 1 10 0", None, 0),
    (b"WTR? 1", b"1=10 0\n", 0),
    (b"WGO? 1", b"1=0\n", 0),
    (b"WGO 1 0", None, 0),
    (b"RTR 10", None, 0),
    (b"RTR?", b"10\n", 0),
    (b"TNR?", b"2\n", 0),
    (b"DRC 1 1 2 2 1 7", None, 0),  # two tables in one command
    (b"DRC? 1 2", b"1=1 2 \n2=1 7\n", 0),
    (b"DRT 0 0 0", None, 0),
    (b"DRT? 1", b"1=0 \n2=0\n", 0),
    (b"DRL? 1", b"1=0\n", 0),
    (b"DRR? 1 1 1", b"\n", 77),  # nothing recorded yet: "not enough recorded data"
    (b"HDR?", re.compile(rb"#RecordOptions \n(.+ \n)+131072 datapoints per table\n"), 0),
    (b"\x18", None, 10),  # #24: stop all
] + [(command, UNSUPPORTED, 2) for command in (
    b"ATZ 1 0", b"ATZ? 1", b"CCL 1 advanced", b"CCL?", b"CTO 1 1 1", b"CTO? 1 1", b"DCO 1 1", b"DCO? 1",
    b"DDL 1 1 0", b"DDL? 1", b"DEL 10", b"DIO? 1", b"DPO 1", b"DTC 1", b"DTL? 1", b"GWD 1 1", b"GWD? 1",
    b"HPA?", b"HPV?", b"IFC IPADR 192.168.0.2:50000", b"IFC? IPADR", b"IFS 100 IPADR 1", b"IFS? IPADR",
    b"IMP 1 1", b"IMP? 1", b"JAS? 1 1", b"JAX 1 1 1", b"JAX? 1 1", b"JBS? 1 1", b"JDT 1 1 1", b"JLT 1 1 1 1",
    b"JON 1 1", b"JON? 1", b"MAC BEG m", b"MAC?", b"MAN? MOV", b"NLM 1 0", b"NLM? 1", b"OSM 1 1", b"OSM? 1",
    b"OVF? 1", b"PLM 1 100", b"PLM? 1", b"RPA", b"SEP 100 1 0x0E000200 5e-5", b"SEP? 1 0x0E000200",
    b"SGA 1 1", b"SGA? 1", b"SPA 1 0x0E000200 5e-5", b"SSN?", b"STE 1 1", b"TAD? 1", b"TIO?", b"TNS? 1",
    b"TPC?", b"TRO 1 1", b"TRO? 1", b"TSC?", b"TSP? 1", b"TWC", b"TWG?", b"TWS 1 1 1", b"VCO 1 1",
    b"VCO? 1", b"VEL 1 1", b"VEL? 1", b"WGR", b"WOS 1 0", b"WOS? 1", b"WPA 100",
)]


def test_every_command_of_the_manual_is_implemented_or_refused_as_the_manual_says(client):
    wrong = []
    for command, expected, code in MANUAL:
        reply = None
        if expected is None or expected is UNSUPPORTED and not command.split()[0].endswith(b"?"):
            client.send(command if len(command) == 1 else command + b"\n")  # a set command: no reply
        else:
            reply = client.ask(command)
        if expected is UNSUPPORTED and reply is not None and reply != b"\n":
            wrong.append((command, "reply", reply))
        elif isinstance(expected, bytes) and reply != expected:
            wrong.append((command, "reply", reply))
        elif isinstance(expected, re.Pattern) and not expected.fullmatch(reply or b""):
            wrong.append((command, "reply", reply))
        error = client.err()  # also proves a set command sent nothing: ERR?'s is the next line
        if error != code:
            wrong.append((command, "ERR?", error))
    assert not wrong, wrong


def test_mnemonics_are_not_case_sensitive(client):
    # "The command mnemonic is not case-sensitive" (GCS syntax 2.0)
    assert client.ask(b"csv?") == b"2.0\n"
    client.send(b"sva 1 3\n")
    assert client.ask(b"pos? 1") == b"1=6.000000\n"
    assert client.err() == 0


def test_hlp_lists_what_is_implemented_the_way_pis_library_reads_it(client, emulator):
    lines = client.ask(b"HLP?").decode("ascii").splitlines()
    names = [line.split()[0] for line in lines[1:-1]]  # PI's library drops the first and last line
    assert set(names) == set(emulator.COMMANDS) | {"#5", "#7", "#9", "#24"}
    assert set(names) <= set(HELP)
    for name in names:
        reply_or_silence = b"" if not name.endswith("?") else client.ask(name.encode())
        assert reply_or_silence != b"\n" or client.err() != 2, name  # listed means known


def test_an_erroneous_query_ends_so_the_client_reads_the_error_at_once(client):
    for query, code in ((b"POS? 2", 15), (b"SPA? 1 0x0E000999", 54), (b"SPA? 1 banana", 1), (b"DRC? 9", 57)):
        assert client.ask(query) == b"\n", query  # not silence: nobody waits for a timeout
        assert client.err() == code, query
        assert client.err() == 0  # read once, then cleared


def _play_and_record(client: Client, table_points: int) -> np.ndarray:
    """Run wave table 1 once (WTR 1) and read back the recorded voltage (DRC option 7)."""
    client.send(b"WSL 1 1\nWGC 1 1\nWTR 1 1 0\nRTR 1\nDRC 1 1 2 2 1 7\nWGO 1 1\n")
    assert client.err() == 0
    deadline = time.monotonic() + 5
    while client.ask(b"\x09") != b"0\n" and time.monotonic() < deadline:
        time.sleep(0.005)
    lines = [line.strip() for line in client.ask(f"DRR? 1 {table_points} 2".encode()).decode().splitlines()]
    body = lines[lines.index("# END_HEADER") + 1:]
    return np.array([float(x) for x in body])


def test_sin_p_is_the_manuals_example(client):
    # manual, "Wave Generator": WAV 2 X SIN_P 2000 20 10 2000 0 1000 -> 2000 points from 10 up to 30
    client.send(b"WAV 1 X SIN_P 2000 20 10 2000 0 1000\n")
    assert client.err() == 0
    v = _play_and_record(client, 2000)
    assert v.size == 2000 and v[0] == pytest.approx(10.0) and v[1000] == pytest.approx(30.0)
    assert v.max() == pytest.approx(30.0) and v.min() == pytest.approx(10.0)
    np.testing.assert_allclose(v[1:1000], v[1999:1000:-1], atol=1e-6)  # symmetric about the centre
    assert np.all(np.diff(v[:1001]) > 0) and np.all(np.diff(v[1000:]) < 0)


def test_lin_appended_goes_from_offset_to_offset_plus_amp_smoothly(client):
    # manual: WAV 2 & LIN 3000 -40 50 3000 0 650, a negative-amplitude line appended to a table
    client.send(b"WAV 1 X PNT 1 1 50\nWAV 1 & LIN 3000 -40 50 3000 0 650\n")
    assert client.err() == 0
    v = _play_and_record(client, 3001)[1:]
    assert v[0] == pytest.approx(50.0) and v[-1] == pytest.approx(10.0)
    steps = np.diff(v)
    assert np.all(steps <= 1e-9)  # monotonic down
    assert abs(steps[0]) < abs(steps[1500]) / 100 and abs(steps[-1]) < abs(steps[1500]) / 100  # smooth ends
    np.testing.assert_allclose(steps[700:2300], steps[1500], atol=2e-6)  # constant speed (6 decimals)


def test_ramp_peaks_at_its_centre_point_and_starts_late(client):
    client.send(b"WAV 1 X RAMP 1000 8 2 800 100 50 500\n")
    assert client.err() == 0
    v = _play_and_record(client, 1000)
    assert np.all(v[:101] == pytest.approx(2.0)) and np.all(v[900:] == pytest.approx(2.0))
    assert int(np.argmax(v)) == 600 and v[600] == pytest.approx(10.0)


def test_wave_parameters_out_of_range_are_error_405_and_bad_syntax_1(client):
    for command, code in ((b"WAV 1 X SIN_P 100 2 1 200 0 50", 405),  # wave longer than its segment
                          (b"WAV 1 X LIN 100 2 1 100 0 60", 405),  # speed-up longer than half the line
                          (b"WAV 1 X RAMP 100 2 1 100 0 10", 1),  # a parameter missing
                          (b"WAV 1 & SIN_P 100 2 1 100 0 50", 401),  # nothing to append to
                          (b"WAV 1 X SIN_P 10 200 0 10 0 5", 405)):  # beyond the output range
        client.send(command + b"\n")
        assert client.err() == code, command


def test_smooth_ramp_starts_and_ends_exactly_and_is_linear_without_speed_up():
    np.testing.assert_allclose(smooth_ramp(5, 0), [0, 0.25, 0.5, 0.75, 1])
    r = smooth_ramp(101, 20)
    assert r[0] == 0 and r[-1] == pytest.approx(1.0) and r[50] == pytest.approx(0.5)
    assert np.all(np.diff(r) > 0)


def test_a_failing_drc_changes_no_table(client):
    client.send(b"DRC 1 1 7 2 1 2\n")  # table 1: option 7 needs output channel 1 -> ok; table 2 fine
    assert client.err() == 0
    client.send(b"DRC 1 1 2 3 1 7\n")  # table 3 does not exist: nothing changes
    assert client.err() == 57
    assert client.ask(b"DRC?") == b"1=1 7 \n2=1 2\n"


# -- the closed loop: a stage with its own bandwidth, on-target window and travel -------------------------
def _wait_on_target(client: Client, timeout_s: float = 10.0) -> list[float]:
    positions = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        positions.append(float(client.ask(b"POS? 1").split(b"=")[1]))
        if client.ask(b"ONT? 1") == b"1=1\n":
            break
        time.sleep(0.01)
    return positions


def test_mov_settles_like_a_stage_of_its_bandwidth(request):
    emu = start(servo_bandwidth_hz=2.0, on_target_um=0.01)  # slow enough to watch: ~1 s to settle
    request.addfinalizer(emu.close)
    client = Client(emu.tcp_url)
    request.addfinalizer(client.close)
    client.send(b"SVA 1 10\nSVO 1 1\nMOV 1 60\n")  # from 20 um (2 um/V) to 60 um
    assert client.err() == 0
    assert client.ask(b"ONT? 1") == b"1=0\n" and client.ask(b"\x05") == b"1\n"  # moving
    positions = _wait_on_target(client)
    assert client.ask(b"ONT? 1") == b"1=1\n" and client.ask(b"\x05") == b"0\n"
    assert abs(float(client.ask(b"POS? 1").split(b"=")[1]) - 60.0) <= 0.01
    assert len(positions) > 5 and all(20.0 - 1e-9 <= p <= 60.0 + 1e-9 for p in positions)
    assert positions == sorted(positions)  # critically damped: no overshoot
    assert emu.stage.settling_time_s(40.0) == pytest.approx(10.0 / (2 * np.pi * 2.0), rel=0.2)


def test_mov_reaches_a_target_on_a_plant_whose_gain_changes_sign(request):
    """The issue: MOV -7.77 um ran to -121.75 um at the 6.5 V limit with ONT? 0. A stage servo does
    not depend on the sign of the plant's gain."""
    emu = start(ButterflyWorld(), travel_min_um=-150.0, travel_max_um=0.0, min_v=-6.5, max_v=6.5)
    request.addfinalizer(emu.close)
    client = Client(emu.tcp_url)
    request.addfinalizer(client.close)
    client.send(b"SVO 1 1\nMOV 1 -7.77\n")
    assert client.err() == 0
    positions = _wait_on_target(client)
    assert client.ask(b"ONT? 1") == b"1=1\n"
    assert abs(float(client.ask(b"POS? 1").split(b"=")[1]) + 7.77) <= 0.02
    assert all(-150.0 <= p <= 0.0 for p in positions)
    assert abs(float(client.ask(b"VOL? 1").split(b"=")[1])) < 6.5  # nothing wound up to a limit


def test_mov_outside_travel_or_with_servo_off_is_refused_and_nothing_moves(client):
    client.send(b"MOV 1 5\n")
    assert client.err() == 5  # servo off
    client.send(b"SVO 1 1\nMOV 1 100.5\n")
    assert client.err() == 7  # beyond TMX? 100
    client.send(b"MOV 1 -0.1\n")
    assert client.err() == 7  # below TMN? 0
    client.send(b"MVR 1 101\n")
    assert client.err() == 7
    assert client.ask(b"MOV? 1") == b"1=0.000000\n" and client.ask(b"POS? 1") == b"1=0.000000\n"
    client.send(b"SVA 1 1\n")
    assert client.err() == 79  # open-loop value with servo on


def test_stp_halts_a_move_where_the_stage_is(request):
    emu = start(servo_bandwidth_hz=1.0)
    request.addfinalizer(emu.close)
    client = Client(emu.tcp_url)
    request.addfinalizer(client.close)
    client.send(b"SVO 1 1\nMOV 1 80\n")
    time.sleep(0.05)
    client.send(b"STP\n")
    assert client.err() == 10
    held = float(client.ask(b"MOV? 1").split(b"=")[1])
    assert 0.0 < held < 80.0
    time.sleep(0.05)
    assert abs(float(client.ask(b"POS? 1").split(b"=")[1]) - held) < 1.0  # stays near where it stopped
