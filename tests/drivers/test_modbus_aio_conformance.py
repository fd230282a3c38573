"""The emulated ADAM-6024 as an independent Modbus client sees it: the manual's register map and
function list, and the Modbus specification's exception rules.

The client is not hilbench's driver: pymodbus's own client for what it can send, and raw Modbus TCP
(or RTU) frames on a socket for what a well-behaved client refuses to send (quantities outside the
limits, functions nobody implements, cut-short requests).

Sources: ADAM-6000 Series User Manual, Edition 9: Appendix B.2.4 (the ADAM-6024 table) and section
6.3.2 / B.1.2 "Modbus Function Code Introductions" (the functions, 05 and 08); MODBUS Application
Protocol Specification V1.1b3, section 6 (limits and order of checks of each function) and 7
(exception codes). Where the emulator had to choose (the manual is silent), the test says so.
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Iterator
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

from drivers.emulators.modbus_aio import ModbusAIOEmulator
from drivers.modbus_aio import DRIVER

MANUAL: dict[str, tuple[str, str]] = {
    "00001": ("DI0 value", "Read"), "00002": ("DI1 value", "Read"),
    "00017": ("DO0 value", "R/W"), "00018": ("DO1 value", "R/W"),
    "40001": ("AI0 value", "Read"), "40002": ("AI1 value", "Read"), "40003": ("AI2 value", "Read"),
    "40004": ("AI3 value", "Read"), "40005": ("AI4 value", "Read"), "40006": ("AI5 value", "Read"),
    "40011": ("AO0 value", "R/W"), "40012": ("AO1 value", "R/W"),
    "40021": ("AI0 status", "Read"), "40022": ("AI1 status", "Read"), "40023": ("AI2 status", "Read"),
    "40024": ("AI3 status", "Read"), "40025": ("AI4 status", "Read"), "40026": ("AI5 status", "Read"),
}
"""ADAM-6000 Series User Manual (Ed. 9), Appendix B.2.4 "ADAM-6024 12-Ch Universal I/O Module":
Modicon number -> (description, attribute). The protocol address is the number - 1 within its
table (0X: coils, 4X: registers). Nothing else is listed for this module."""

FUNCTIONS: dict[int, str] = {
    0x01: "Read Coil Status", 0x02: "Read Input Status", 0x03: "Read Holding Registers",
    0x04: "Read Input Registers", 0x05: "Force Single Coil", 0x06: "Preset Single Register",
    0x08: "Loopback Diagnosis", 0x0F: "Force Multiple Coils", 0x10: "Preset Multiple Registers",
}
"""ADAM-6000 Series User Manual (Ed. 9), section 6.3.2, Table 6-1 (and B.1.2): the function codes."""

READS = {"0X": (0x01, 0x02), "4X": (0x03, 0x04)}  # 03 and 04 both read the 4X table (manual 6.3.2)
WALKED = range(40)  # protocol addresses walked in each table: the listed ones and the gaps around


def protocol_address(modicon: str) -> tuple[str, int]:
    return ("0X" if modicon[0] == "0" else "4X"), int(modicon[1:]) - 1


LISTED = {protocol_address(m): attribute for m, (_, attribute) in MANUAL.items()}


class World:
    def __init__(self) -> None:
        self.commands: list[float] = []
        self.values = {"current": 0.25, "output": 0.0}

    def command(self, value: float) -> None:
        self.commands.append(value)

    def read(self, channel: str) -> float:
        return self.values[channel]

    def play(self, waveform: Any, rate_hz: float) -> dict[str, Any]:
        raise NotImplementedError


class RawTCP:
    """Modbus TCP frames on a plain socket: MBAP (transaction, protocol 0, length, unit) + PDU."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
        self.tid = 0

    def adu(self, pdu: bytes, unit: int = 1) -> bytes:
        self.tid += 1
        self.sock.sendall(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, unit) + pdu)
        head = self._recv(7)
        return head + self._recv(struct.unpack(">H", head[4:6])[0] - 1)

    def pdu(self, pdu: bytes, unit: int = 1) -> bytes:
        return self.adu(pdu, unit)[7:]

    def _recv(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            assert chunk, "the server closed the connection"
            data += chunk
        return data


@pytest.fixture
def module() -> Iterator[tuple[ModbusAIOEmulator, World, RawTCP, ModbusTcpClient]]:
    world = World()
    emulator = ModbusAIOEmulator(DRIVER.complete({"url": "tcp://127.0.0.1:0"}), world)
    raw = RawTCP(emulator.port)
    client = ModbusTcpClient("127.0.0.1", port=emulator.port, timeout=2.0)
    assert client.connect()
    yield emulator, world, raw, client
    client.close()
    raw.sock.close()
    emulator.close()


def exception(function: int, code: int) -> bytes:
    return bytes([function | 0x80, code])


# -- the map ------------------------------------------------------------------------------------------
def test_the_default_driver_table_is_emulated_as_the_adam_6024(module) -> None:
    emulator, *_ = module
    assert emulator.model == "ADAM-6024"


@pytest.mark.parametrize("table", ["0X", "4X"])
def test_every_listed_address_reads_and_every_other_answers_02(module, table: str) -> None:
    _, _, raw, _ = module
    for function in READS[table]:
        for address in [*WALKED, 0xFFFF]:
            reply = raw.pdu(struct.pack(">BHH", function, address, 1))
            if (table, address) in LISTED:
                assert reply[:2] == bytes([function, 1 if table == "0X" else 2]), (function, address)
            else:
                assert reply == exception(function, 2), (function, address)


@pytest.mark.parametrize(("request_pdu", "reply_head"), [
    ("03 0000 0006", "03 0C"),  # 40001..40006, the six AIs
    ("04 0014 0006", "04 0C"),  # 40021..40026, the six AI statuses
    ("03 0000 0008", "83 02"),  # 40001..40008: 40007 is not in the table
    ("03 000A 0003", "83 02"),  # 40011..40013: 40013 is not in the table
    ("01 0010 0002", "01 01"),  # 00017..00018, both DOs
    ("02 0000 0003", "82 02"),  # 00001..00003: 00003 is not in the table
], ids=["AIs", "statuses", "past-AI5", "past-AO1", "DOs", "past-DI1"])
def test_a_read_spanning_an_address_not_in_the_table_answers_02(module, request_pdu: str, reply_head: str) -> None:
    _, _, raw, _ = module
    reply = raw.pdu(bytes.fromhex(request_pdu))
    assert reply[:2] == bytes.fromhex(reply_head)
    if reply_head[0] != "8":
        assert len(reply) == 2 + reply[1]


def test_rw_addresses_take_their_write_functions_and_read_back(module) -> None:
    emulator, world, _, client = module
    assert not client.write_coil(16, True, device_id=1).isError()  # 05 on 00017
    assert client.read_coils(16, count=2, device_id=1).bits[:2] == [True, False]
    assert not client.write_coils(16, [False, True], device_id=1).isError()  # 15 on 00017..00018
    assert client.read_discrete_inputs(16, count=2, device_id=1).bits[:2] == [False, True]  # 02 reads 0X too
    assert not client.write_register(11, 1234, device_id=1).isError()  # 06 on 40012 (AO1: not wired)
    assert not client.write_registers(10, [2048, 4095], device_id=1).isError()  # 16 on 40011..40012
    assert client.read_holding_registers(10, count=2, device_id=1).registers == [2048, 4095]
    assert client.read_input_registers(10, count=2, device_id=1).registers == [2048, 4095]
    # AO0 (the driver table's ao_register 10) drives the plant: 2048 counts = 5.0 V = 0.5 A at 0.1 A/V
    assert world.commands == [pytest.approx(2048 / 4095 * 10.0 * 0.1)] == emulator.ao_writes


def test_read_only_addresses_refuse_every_write_with_02_and_keep_their_value(module) -> None:
    _, _, raw, _ = module
    for (table, address), attribute in LISTED.items():
        if attribute != "Read":
            continue
        read = READS[table][0]
        before = raw.pdu(struct.pack(">BHH", read, address, 1))
        if table == "0X":
            writes = [struct.pack(">BHH", 0x05, address, 0xFF00), struct.pack(">BHHBB", 0x0F, address, 1, 1, 1)]
        else:
            writes = [struct.pack(">BHH", 0x06, address, 0x0123), struct.pack(">BHHBH", 0x10, address, 1, 2, 0x0123)]
        for write in writes:
            assert raw.pdu(write) == exception(write[0], 2), (table, address, write.hex())
        assert raw.pdu(struct.pack(">BHH", read, address, 1)) == before


def test_a_multiple_write_reaching_past_the_table_changes_nothing(module) -> None:
    _, world, raw, client = module
    assert raw.pdu(bytes.fromhex("10 000B 0002 04 0100 0200")) == exception(0x10, 2)  # 40012..40013
    assert raw.pdu(bytes.fromhex("0F 0011 0002 01 03")) == exception(0x0F, 2)  # 00018..00019
    assert client.read_holding_registers(10, count=2, device_id=1).registers == [0, 0]
    assert client.read_coils(16, count=2, device_id=1).bits[:2] == [False, False]
    assert world.commands == []


# -- the functions -------------------------------------------------------------------------------------
def test_every_function_the_manual_does_not_list_answers_01(module) -> None:
    _, _, raw, _ = module
    unlisted = [f for f in range(1, 0x80) if f not in FUNCTIONS]
    assert len(unlisted) == 118
    for function in unlisted:  # 07, 0B, 11, 16, 17, 2B ... which pymodbus itself would serve
        assert raw.pdu(bytes([function]) + bytes(4)) == exception(function, 1), hex(function)


def test_loopback_diagnosis_echoes_its_request(module) -> None:
    _, _, raw, _ = module
    assert raw.pdu(bytes.fromhex("08 0000 A537")) == bytes.fromhex("08 0000 A537")
    assert raw.pdu(bytes.fromhex("08 0002 0004")) == bytes.fromhex("08 0002 0004")  # the manual's example


def test_force_single_coil_takes_ff00_0000_and_the_manuals_ffff(module) -> None:
    _, _, raw, client = module
    assert raw.pdu(bytes.fromhex("05 0010 FF00")) == bytes.fromhex("05 0010 FF00")  # echo, DO0 on
    assert raw.pdu(bytes.fromhex("05 0010 FFFF")) == bytes.fromhex("05 0010 FFFF")  # "release the force"
    assert client.read_coils(16, count=1, device_id=1).bits[0] is True  # FFFF left DO0 as it was
    assert raw.pdu(bytes.fromhex("05 0010 0000")) == bytes.fromhex("05 0010 0000")
    assert client.read_coils(16, count=1, device_id=1).bits[0] is False


@pytest.mark.parametrize(("request_pdu", "expected"), [
    ("01 0010 0000", "81 03"), ("01 0010 07D1", "81 03"), ("01 0010 07D0", "81 02"),  # 1..2000 bits
    ("02 0000 0000", "82 03"), ("02 0000 07D1", "82 03"), ("02 0000 07D0", "82 02"),
    ("03 0000 0000", "83 03"), ("03 0000 007E", "83 03"), ("03 0000 007D", "83 02"),  # 1..125 registers
    ("04 0000 0000", "84 03"), ("04 0000 007E", "84 03"), ("04 0000 007D", "84 02"),
    ("05 0010 1234", "85 03"), ("05 0010 00FF", "85 03"),  # only 0000 / FF00 (and the manual's FFFF)
    ("0F 0010 0000 00", "8F 03"),  # 1..1968 bits
    ("0F 0010 07B1 F7" + "00" * 0xF7, "8F 03"),
    ("0F 0010 07B0 F6" + "00" * 0xF6, "8F 02"),
    ("0F 0010 0002 02 0100", "8F 03"),  # byte count must be ceil(N / 8)
    ("0F 0010 0002 01", "8F 03"),  # byte count 1, no data byte
    ("10 000A 0000 00", "90 03"),  # 1..123 registers
    ("10 000A 007C F8" + "0000" * 0x7C, "90 03"),
    ("10 000A 007B F6" + "0000" * 0x7B, "90 02"),
    ("10 000A 0002 02 0001", "90 03"),  # byte count must be 2 N
    ("10 000A 0002 04 0001", "90 03"),  # 4 data bytes announced, 2 sent
    ("03 0000", "83 03"), ("06 000A 0001 00", "86 03"),  # shorter or longer than the fields imply
], ids=lambda v: v[:18])
def test_values_outside_the_specification_answer_03_before_addresses_answer_02(
        module, request_pdu: str, expected: str) -> None:
    _, world, raw, _ = module
    assert raw.pdu(bytes.fromhex(request_pdu)) == bytes.fromhex(expected)
    assert world.commands == []


def test_an_ao_value_outside_its_count_range_answers_03(module) -> None:
    """A choice, not the manual's: the AO is 12 bit (0..4095 in the default driver table)."""
    _, world, raw, client = module
    assert raw.pdu(bytes.fromhex("06 000A 1000")) == exception(0x06, 3)
    assert client.read_holding_registers(10, count=1, device_id=1).registers == [0]
    assert world.commands == []


# -- the frames ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(("request_pdu", "function", "code"), [
    ("2B 0E 01 00", 0x2B, 1), ("41 0000 0001", 0x41, 1), ("03 0006 0001", 0x03, 2), ("10 000A 0000 00", 0x10, 3),
], ids=["2B", "41", "03-absent", "10-quantity"])
def test_an_exception_frame_is_the_function_with_bit_7_set_then_the_code(module, request_pdu, function, code):
    _, _, raw, _ = module
    raw.tid = 0x1233
    reply = raw.adu(bytes.fromhex(request_pdu))
    # MBAP: the request's transaction id, protocol 0, length 3 (unit + 2 PDU bytes), the unit; PDU.
    assert reply == struct.pack(">HHHBBB", 0x1234, 0, 3, 1, function | 0x80, code)


def test_another_unit_id_answers_0b(module) -> None:
    """A choice, not the manual's: what the module does with a foreign unit id is not said."""
    _, _, raw, _ = module
    assert raw.pdu(bytes.fromhex("03 0000 0001"), unit=2) == exception(0x03, 0x0B)


def crc16_modbus(data: bytes) -> bytes:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


@pytest.mark.parametrize(("request_pdu", "expected"), [
    ("03 0000 0001", "03 02 9FFF"), ("03 0006 0001", "83 02"), ("2B 0E 01 00", "AB 01"), ("03 0000 007E", "83 03"),
], ids=["read", "absent", "unlisted", "quantity"])
def test_rtu_frames_answer_the_same(request_pdu: str, expected: str) -> None:
    world = World()
    emulator = ModbusAIOEmulator(DRIVER.complete({"url": "/dev/ttyUSB0"}), world)  # RTU on a socket
    try:
        with socket.create_connection(("127.0.0.1", emulator.port), timeout=2.0) as sock:
            frame = bytes.fromhex("01" + request_pdu)
            sock.sendall(frame + crc16_modbus(frame))
            want = bytes.fromhex("01" + expected)
            reply = b""
            while len(reply) < len(want) + 2:
                chunk = sock.recv(64)
                assert chunk
                reply += chunk
        assert reply == want + crc16_modbus(want)
    finally:
        emulator.close()


# -- the plant behind the registers -------------------------------------------------------------------
def test_ai_values_and_statuses_come_from_the_plant(module) -> None:
    _, world, _, client = module
    world.values = {"current": 0.25, "output": 150.0}  # 2.5 V; 15 V is over the +-10 V input range
    values = client.read_input_registers(0, count=6, device_id=1).registers
    statuses = client.read_holding_registers(20, count=6, device_id=1).registers
    # AI0 current monitor: 0.25 A * 10 V/A = 2.5 V -> 40959; AI1 saturates at 65535; AI2..AI5 read 0 V
    assert values == [40959, 65535, 32768, 32768, 32768, 32768]
    assert statuses == [0, 1, 0, 0, 0, 0]  # AI1 over high
    world.values["output"] = -150.0
    assert client.read_holding_registers(20, count=2, device_id=1).registers == [0, 2]  # AI1 over low
