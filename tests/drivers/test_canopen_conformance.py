"""CiA 301 / CiA 404 conformance of the CANopen sensor emulator, judged by a master of its own.

The master here speaks raw python-can frames on a virtual bus (not hilbench's driver, not the
``canopen`` package), so it checks the emulator against the standard rather than against the code
that talks to it. What it expects comes from:

* CiA 301 (CANopen application layer), read through CiA's public "Network management" page,
  CANopenNode's ``301/`` sources and vendor manuals quoting it (section numbers are not given: the
  standard's text was not at hand): the NMT state machine and which services each state serves
  (SDO not in STOPPED, PDO only in OPERATIONAL), NMT commands 01h/02h/80h/81h/82h, boot-up message
  (700h + id, 00h), heartbeat state bytes 04h/05h/7Fh and period 1017h, SDO expedited and segmented
  transfer, the SDO abort codes (the same numbers in CANopenNode ``301/CO_SDOserver.h`` and canopen
  ``sdo/exceptions.py``), the PDO mapping procedure, the EMCY frame;
* CiA 404 (measuring devices): device type 1000h = 0002_0194h (analogue input block, profile 404;
  Axiomatic AX030541 manual 3.2.1), AI PV 6130h/7130h/9130h, AI status 6150h bits 0/1/2 (esd
  CAN-CBX-Pt100 manual 8.10.9), AI filter 61A0h/61A1h (Axiomatic AX030301 manual 3.3.17-18).

Where the emulator follows CANopenNode because the text of CiA 301 could not be read (0607 0012 /
0607 0013 for too long / too short data, 0800 0022 for a mapping change while the PDO is valid),
the test says so next to the case.
"""

from __future__ import annotations

import itertools
import statistics
import struct
import time
from collections.abc import Iterator
from typing import Any

import can
import pytest

from drivers.canopen_sensor import DRIVER
from drivers.emulators.canopen_sensor import CanopenSensorEmulator

NODE = 7
SDO_RX, SDO_TX, HEARTBEAT, TPDO1, EMCY, SYNC = 0x600 + NODE, 0x580 + NODE, 0x700 + NODE, 0x180 + NODE, 0x80 + NODE, 0x80
BOOT_UP, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
START, STOP, ENTER_PRE_OPERATIONAL, RESET_NODE, RESET_COMMUNICATION = 0x01, 0x02, 0x80, 0x81, 0x82

#: The object dictionary as the device manual would print it: index, sub-index, name, struct format
#: (or "str"), access, value after boot-up (None: a measurement), PDO-mappable. Sources: CiA 301
#: mandatory objects 1000h, 1001h, 1017h (heartbeat instead of node guarding), 1018h:01 and the
#: TPDO1 objects; CiA 404 for 6xxxh (see the module docstring).
MANUAL: list[tuple[int, int, str, str, str, Any, bool]] = [
    (0x1000, 0, "device type", "I", "ro", 0x0002_0194, False),
    (0x1001, 0, "error register", "B", "ro", 0, True),
    (0x1005, 0, "COB-ID SYNC", "I", "rw", 0x80, False),
    (0x1008, 0, "manufacturer device name", "str", "const", "hilbench CiA 404 AI emulator", False),
    (0x100A, 0, "manufacturer software version", "str", "const", "hilbench emulator 1", False),
    (0x1014, 0, "COB-ID EMCY", "I", "ro", 0x80 + NODE, False),
    (0x1017, 0, "producer heartbeat time (ms)", "H", "rw", 0, False),
    (0x1018, 0, "identity: highest sub-index", "B", "const", 4, False),
    (0x1018, 1, "vendor-ID", "I", "ro", 0, False),
    (0x1018, 2, "product code", "I", "ro", 404, False),
    (0x1018, 3, "revision number", "I", "ro", 0x00010000, False),
    (0x1018, 4, "serial number", "I", "ro", 1, False),
    (0x1800, 0, "TPDO1 comm: highest sub-index", "B", "const", 5, False),
    (0x1800, 1, "TPDO1 COB-ID", "I", "rw", 0x180 + NODE, False),
    (0x1800, 2, "TPDO1 transmission type", "B", "rw", 254, False),
    (0x1800, 3, "TPDO1 inhibit time (100 us)", "H", "rw", 0, False),
    (0x1800, 5, "TPDO1 event timer (ms)", "H", "rw", 0, False),
    (0x1A00, 0, "TPDO1 number of mapped objects", "B", "rw", 1, False),
    (0x1A00, 1, "TPDO1 mapped object 1", "I", "rw", 0x6130_0120, False),
    (0x6130, 0, "AI input PV (REAL32): entries", "B", "const", 1, False),
    (0x6130, 1, "AI input PV 1 (REAL32)", "f", "ro", None, True),
    (0x7130, 1, "AI input PV 1 (INTEGER16)", "h", "ro", None, True),
    (0x9130, 1, "AI input PV 1 (INTEGER32)", "i", "ro", None, True),
    (0x6150, 0, "AI status: entries", "B", "const", 1, False),
    (0x6150, 1, "AI status 1", "B", "ro", 0, True),
    (0x61A0, 1, "AI filter type", "B", "rw", 0, False),
    (0x61A1, 1, "AI filter constant", "B", "rw", 1, False),
]


#: rw entries that a valid TPDO1 locks, and the abort a write gets then: the inhibit time (0609 0030,
#: CANopenNode) and the mapping (0800 0022 here; CANopenNode answers 0601 0000, CiA 301 text not read)
LOCKED_WHILE_VALID = {(0x1800, 3): 0x0609_0030, (0x1A00, 0): 0x0800_0022, (0x1A00, 1): 0x0800_0022}


class Aborted(Exception):
    def __init__(self, code: int):
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


class World:
    def __init__(self) -> None:
        self.values = {"output": 0.0, "temperature": 20.0}

    def command(self, value: float) -> None:
        raise AssertionError("a sensor is never commanded")

    def read(self, channel: str) -> float:
        return self.values[channel]


class Master:
    """An NMT master and SDO client on raw frames; it keeps every frame it sees, with its time."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.log: list[tuple[float, int, bytes]] = []
        self._read = 0  # log entries already consumed by expect()

    def send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _pump(self, timeout_s: float) -> None:
        msg = self.bus.recv(timeout=timeout_s)
        while msg is not None:
            self.log.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))
            msg = self.bus.recv(timeout=0)

    def expect(self, cob_id: int, timeout_s: float = 1.0) -> bytes | None:
        """The next frame on ``cob_id`` after those already consumed, or None after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            for k in range(self._read, len(self.log)):
                if self.log[k][1] == cob_id:
                    self._read = k + 1
                    return self.log[k][2]
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._pump(min(left, 0.02))

    def drain(self, seconds: float = 0.0) -> None:
        """Listen for ``seconds`` and mark everything seen as consumed."""
        deadline = time.monotonic() + seconds
        while True:
            self._pump(max(0.0, min(0.02, deadline - time.monotonic())))
            if time.monotonic() >= deadline:
                break
        self._read = len(self.log)

    def frames(self, cob_id: int, since: float = 0.0) -> list[tuple[float, bytes]]:
        self._pump(0)
        return [(t, d) for t, c, d in self.log if c == cob_id and t >= since]

    def nmt(self, command: int, node: int = NODE) -> None:
        self.send(0x000, bytes([command, node]))

    def sdo(self, request: bytes, timeout_s: float = 1.0) -> bytes | None:
        self.drain()
        self.send(SDO_RX, request.ljust(8, b"\0"))
        return self.expect(SDO_TX, timeout_s)

    def _answer(self, request: bytes) -> bytes:
        reply = self.sdo(request)
        assert reply is not None, f"no SDO answer to {request.hex(' ')}"
        assert len(reply) == 8, f"SDO answers are 8 bytes (CiA 301 SDO protocols), got {reply.hex(' ')}"
        if reply[0] == 0x80:
            assert reply[1:4] == request[1:4], "an abort names the index and sub-index of the transfer"
            raise Aborted(int.from_bytes(reply[4:8], "little"))
        return reply

    def upload(self, index: int, subindex: int) -> bytes:
        """SDO upload, expedited or segmented, the protocol the server chooses."""
        head = index.to_bytes(2, "little") + bytes([subindex])
        reply = self._answer(bytes([0x40]) + head)
        assert reply[0] & 0xE0 == 0x40 and reply[1:4] == head, reply.hex(" ")
        if reply[0] & 0x02:  # expedited: e = 1, s = 1, n = bytes of d without data
            assert reply[0] & 0x01, "expedited uploads of this device indicate the size"
            return reply[4:8 - (reply[0] >> 2 & 0x03)]
        size, data, toggle = int.from_bytes(reply[4:8], "little"), b"", 0
        while True:
            segment = self.sdo(bytes([0x60 | toggle]))
            assert segment is not None and segment[0] & 0xE0 == 0x00 and segment[0] & 0x10 == toggle, segment
            data += segment[1:8 - (segment[0] >> 1 & 0x07)]
            toggle ^= 0x10
            if segment[0] & 0x01:
                assert len(data) == size, f"indicated {size} bytes, received {len(data)}"
                return data

    def download(self, index: int, subindex: int, data: bytes) -> None:
        """Expedited SDO download with the size indicated."""
        head = index.to_bytes(2, "little") + bytes([subindex])
        reply = self._answer(bytes([0x23 | (4 - len(data)) << 2]) + head + data)
        assert reply == bytes([0x60]) + head + b"\0\0\0\0", reply.hex(" ")


@pytest.fixture
def setup(request: pytest.FixtureRequest) -> Iterator[tuple[Master, CanopenSensorEmulator, World]]:
    channel = f"conformance-{request.node.name}"
    master = Master(channel)  # first, so it sees the boot-up message
    world = World()
    node = CanopenSensorEmulator(DRIVER.complete({"channel": channel, "node_id": NODE}), world)
    yield master, node, world
    node.close()
    master.bus.shutdown()
    assert node.errors == []


def u32(value: int) -> bytes:
    return value.to_bytes(4, "little")


def state_after(master: Master, command: int) -> tuple[int, bool, bool]:
    """Send an NMT command, then: the heartbeat state byte, whether SDO answers, whether SYNC gives a TPDO."""
    master.nmt(command)
    master.drain(0.05)
    beat = master.expect(HEARTBEAT, 0.5)
    assert beat is not None and len(beat) == 1
    answers_sdo = master.sdo(bytes([0x40, 0x00, 0x10, 0x00]), timeout_s=0.2) is not None
    master.drain()
    master.send(SYNC, b"")
    gives_tpdo = master.expect(TPDO1, 0.2) is not None
    return beat[0], answers_sdo, gives_tpdo


def configure_tpdo(master: Master, *entries: int, transmission_type: int = 1) -> None:
    """The CiA 301 mapping procedure: PDO invalid, 00h = 0, entries, 00h = n, type, PDO valid."""
    master.download(0x1800, 1, u32(0x8000_0000 | TPDO1))
    master.download(0x1A00, 0, b"\x00")
    for k, entry in enumerate(entries, start=1):
        master.download(0x1A00, k, u32(entry))
    master.download(0x1A00, 0, bytes([len(entries)]))
    master.download(0x1800, 2, bytes([transmission_type]))
    master.download(0x1800, 1, u32(TPDO1))


# -- NMT --------------------------------------------------------------------------------------------------
def test_boot_up_message_then_pre_operational_without_heartbeat(setup) -> None:
    master, node, _ = setup
    assert master.expect(HEARTBEAT, 1.0) == bytes([BOOT_UP])
    assert node.nmt_state == "PRE-OPERATIONAL"
    assert master.upload(0x1000, 0) == u32(0x0002_0194)  # SDO is served in PRE-OPERATIONAL
    master.drain(0.2)
    assert master.frames(HEARTBEAT, since=time.monotonic() - 0.2) == []  # 1017h = 0: no heartbeat


def test_each_nmt_state_serves_what_cia_301_allows(setup) -> None:
    master, _, _ = setup
    master.download(0x1017, 0, struct.pack("<H", 20))
    configure_tpdo(master, 0x6130_0120, 0x6150_0108)
    # (heartbeat byte, SDO answered, TPDO after SYNC) per state
    assert state_after(master, START) == (OPERATIONAL, True, True)
    assert state_after(master, STOP) == (STOPPED, False, False)
    assert state_after(master, ENTER_PRE_OPERATIONAL) == (PRE_OPERATIONAL, True, False)
    assert state_after(master, STOP) == (STOPPED, False, False)
    assert state_after(master, START) == (OPERATIONAL, True, True)  # STOPPED -> OPERATIONAL is allowed
    assert state_after(master, ENTER_PRE_OPERATIONAL) == (PRE_OPERATIONAL, True, False)


def test_nmt_commands_for_another_node_are_ignored_and_node_0_means_all(setup) -> None:
    master, node, _ = setup
    master.nmt(START, node=NODE + 1)
    master.drain(0.1)
    assert node.nmt_state == "PRE-OPERATIONAL"
    master.nmt(START, node=0)
    master.drain(0.1)
    assert node.nmt_state == "OPERATIONAL"
    master.send(0x000, bytes([0x03, NODE]))  # not a CiA 301 command specifier
    master.send(0x000, bytes([STOP]))  # one byte: not an NMT command frame
    master.drain(0.1)
    assert node.nmt_state == "OPERATIONAL"


def test_heartbeat_period_is_1017h_and_starts_when_written(setup) -> None:
    master, _, _ = setup
    master.drain()
    master.download(0x1017, 0, struct.pack("<H", 25))
    written = time.monotonic()
    master.drain(0.4)
    beats = master.frames(HEARTBEAT, since=written)
    assert beats and {d for _, d in beats} == {bytes([PRE_OPERATIONAL])}
    intervals = [b[0] - a[0] for a, b in itertools.pairwise(beats)]
    # 25 ms nominal; loose bounds because the test shares two busy cores (no timing claim beyond that)
    assert 0.0125 < statistics.median(intervals) < 0.05
    master.download(0x1017, 0, b"\x00\x00")  # 0 switches the producer off
    master.drain(0.05)
    stopped = time.monotonic()
    master.drain(0.2)
    assert master.frames(HEARTBEAT, since=stopped) == []


def test_reset_communication_restores_1xxxh_and_reset_node_also_the_application(setup) -> None:
    master, node, _ = setup
    master.download(0x1017, 0, struct.pack("<H", 20))
    master.download(0x61A0, 1, b"\x01")  # moving average: an application parameter
    master.nmt(START)
    master.drain(0.05)
    master.nmt(RESET_COMMUNICATION)
    assert master.expect(HEARTBEAT, 0.5) is not None
    boot = [d for _, d in master.frames(HEARTBEAT)]
    assert bytes([BOOT_UP]) in boot
    assert node.nmt_state == "PRE-OPERATIONAL"
    assert master.upload(0x1017, 0) == b"\x00\x00"  # communication parameter: back to its default
    assert master.upload(0x61A0, 1) == b"\x01"  # application parameter: kept
    master.nmt(RESET_NODE)
    master.drain(0.1)
    assert [d for _, d in master.frames(HEARTBEAT)].count(bytes([BOOT_UP])) == 3  # power-on + two resets
    assert master.upload(0x61A0, 1) == b"\x00"  # reset node: application parameters too
    assert node.nmt_state == "PRE-OPERATIONAL"


# -- the object dictionary --------------------------------------------------------------------------------
@pytest.mark.parametrize("index, subindex, name, fmt, access, default, mappable", MANUAL,
                         ids=[f"{i:04X}h:{s:02X}" for i, s, *_ in MANUAL])
def test_every_object_reads_and_writes_as_the_manual_says(setup, index, subindex, name, fmt, access, default,
                                                          mappable) -> None:
    master, _, world = setup
    world.values["output"] = 3.0
    raw = master.upload(index, subindex)
    value = raw.decode("ascii") if fmt == "str" else struct.unpack("<" + fmt, raw)[0]
    assert value == (3.0 if default is None else default), name
    if access in ("ro", "const"):
        with pytest.raises(Aborted) as info:
            master.download(index, subindex, raw[:4])
        assert info.value.code == 0x0601_0002  # attempt to write a read only object
    elif (index, subindex) in LOCKED_WHILE_VALID:  # TPDO1 is valid after boot-up
        with pytest.raises(Aborted) as info:
            master.download(index, subindex, raw)
        assert info.value.code == LOCKED_WHILE_VALID[index, subindex]
    else:
        master.download(index, subindex, raw)  # writing the value back is accepted
        assert master.upload(index, subindex) == raw
    # a PV or status maps into TPDO1 only when the manual says it is mappable
    master.download(0x1800, 1, u32(0x8000_0000 | TPDO1))
    master.download(0x1A00, 0, b"\x00")
    entry = index << 16 | subindex << 8 | 8 * len(raw)
    if mappable:
        master.download(0x1A00, 1, u32(entry))
    else:
        with pytest.raises(Aborted) as info:
            master.download(0x1A00, 1, u32(entry))
        assert info.value.code == 0x0604_0041  # object cannot be mapped to the PDO


def test_an_object_or_sub_index_not_in_the_manual_does_not_exist(setup) -> None:
    master, _, _ = setup
    known = {(i, s) for i, s, *_ in MANUAL}
    for index, subindex, code in ((0x2000, 0, 0x0602_0000), (0x6000, 1, 0x0602_0000), (0x1018, 5, 0x0609_0011),
                                  (0x1800, 4, 0x0609_0011), (0x6130, 2, 0x0609_0011)):
        assert (index, subindex) not in known
        with pytest.raises(Aborted) as info:
            master.upload(index, subindex)
        assert info.value.code == code, f"{index:04X}h:{subindex:02X}"


# -- SDO protocol and abort codes -------------------------------------------------------------------------
def h(index: int, subindex: int) -> bytes:
    return index.to_bytes(2, "little") + bytes([subindex])


#: request -> abort code, with why (CiA 301 abort code table unless said otherwise)
ABORTS = [
    ("unknown command specifier 7", bytes([0xE0]) + h(0x1000, 0), 0x0504_0001),
    ("block download (not supported)", bytes([0xC2]) + h(0x1017, 0), 0x0504_0001),
    ("block upload (not supported)", bytes([0xA0]) + h(0x1017, 0), 0x0504_0001),
    ("write the read-only device type", bytes([0x23]) + h(0x1000, 0) + u32(404), 0x0601_0002),
    ("write the const device name", bytes([0x21]) + h(0x1008, 0) + u32(8), 0x0601_0002),  # segmented initiate
    ("read an object that does not exist", bytes([0x40]) + h(0x2000, 0), 0x0602_0000),
    ("read a sub-index that does not exist", bytes([0x40]) + h(0x1018, 9), 0x0609_0011),
    # too long / too short: CANopenNode's codes (canopen's LocalNode answers 0607 0010 for both)
    ("4 bytes into UNSIGNED16 1017h", bytes([0x23]) + h(0x1017, 0) + u32(20), 0x0607_0012),
    ("1 byte into UNSIGNED16 1017h", bytes([0x2F]) + h(0x1017, 0) + b"\x14", 0x0607_0013),
    ("segmented, 4 bytes indicated for UNSIGNED16", bytes([0x21]) + h(0x1017, 0) + u32(4), 0x0607_0012),
    ("filter type 3 (0..2 defined)", bytes([0x2F]) + h(0x61A0, 1) + b"\x03", 0x0609_0030),
    ("filter constant 0", bytes([0x2F]) + h(0x61A1, 1) + b"\x00", 0x0609_0030),
    ("reserved transmission type 245", bytes([0x2F]) + h(0x1800, 2) + b"\xf5", 0x0609_0030),
    ("SYNC producer bit 30 in 1005h", bytes([0x23]) + h(0x1005, 0) + u32(0x4000_0080), 0x0609_0030),
    ("another COB-ID while TPDO1 is valid", bytes([0x23]) + h(0x1800, 1) + u32(0x281), 0x0609_0030),
    ("inhibit time while TPDO1 is valid", bytes([0x2B]) + h(0x1800, 3) + b"\x0a\x00", 0x0609_0030),
    # mapping change while the PDO is valid: 0800 0022 here; CANopenNode answers 0601 0000
    ("mapping count while TPDO1 is valid", bytes([0x2F]) + h(0x1A00, 0) + b"\x00", 0x0800_0022),
    ("upload segment without an upload", bytes([0x60]) + h(0, 0), 0x0504_0001),
    ("download segment without a download", bytes([0x00]) + h(0, 0), 0x0504_0001),
]


@pytest.mark.parametrize("request_, code", [(r, c) for _, r, c in ABORTS], ids=[w for w, _, _ in ABORTS])
def test_a_refused_request_is_aborted_with_the_cia_301_code(setup, request_, code) -> None:
    master, _, _ = setup
    reply = master.sdo(request_)
    assert reply is not None and len(reply) == 8
    assert reply[0] == 0x80, reply.hex(" ")
    assert int.from_bytes(reply[4:8], "little") == code
    if request_[0] & 0xE0 in (0x20, 0x40, 0xA0, 0xC0):  # an initiate names its object in the abort
        assert reply[1:4] == request_[1:4]


def test_mapping_aborts_follow_the_cia_301_procedure(setup) -> None:
    master, _, _ = setup
    master.download(0x1800, 1, u32(0x8000_0000 | TPDO1))  # step 1: PDO invalid
    with pytest.raises(Aborted) as info:  # step 2 not done: entries are locked while 00h != 0
        master.download(0x1A00, 1, u32(0x9130_0120))
    assert info.value.code == 0x0800_0022
    master.download(0x1A00, 0, b"\x00")
    with pytest.raises(Aborted) as info:
        master.download(0x1A00, 2, u32(0x2000_0020))  # an object that does not exist
    assert info.value.code == 0x0602_0000
    with pytest.raises(Aborted) as info:
        master.download(0x1A00, 2, u32(0x6130_0110))  # a REAL32 mapped with 16 bits
    assert info.value.code == 0x0604_0041
    for k, entry in enumerate((0x6130_0120, 0x9130_0120, 0x6150_0108), start=1):
        master.download(0x1A00, k, u32(entry))
    with pytest.raises(Aborted) as info:  # 72 bits do not fit 8 bytes
        master.download(0x1A00, 0, b"\x03")
    assert info.value.code == 0x0604_0042
    with pytest.raises(Aborted) as info:  # more entries than the record has
        master.download(0x1A00, 0, b"\x09")
    assert info.value.code == 0x0604_0042
    with pytest.raises(Aborted) as info:  # a PDO without mapped objects cannot be made valid
        master.download(0x1800, 1, u32(TPDO1))
    assert info.value.code == 0x0609_0030
    master.download(0x1A00, 0, b"\x02")
    master.download(0x1800, 1, u32(TPDO1))


def test_segmented_upload_of_the_device_name_with_toggle_bits(setup) -> None:
    master, _, _ = setup
    reply = master.sdo(bytes([0x40]) + h(0x1008, 0))
    assert reply is not None and reply[0] == 0x41  # segmented, size indicated
    size = int.from_bytes(reply[4:8], "little")
    segments = [master.sdo(bytes([0x60 | toggle])) for toggle in (0x00, 0x10, 0x00, 0x10)]
    assert [s[0] & 0x10 for s in segments] == [0x00, 0x10, 0x00, 0x10]  # the server echoes the toggle
    assert [s[0] & 0x01 for s in segments] == [0, 0, 0, 1]  # c: last segment
    name = b"".join(s[1:8 - (s[0] >> 1 & 0x07)] for s in segments)
    assert size == len(name) == 28 and name == b"hilbench CiA 404 AI emulator"
    # a repeated toggle is a protocol error
    master.sdo(bytes([0x40]) + h(0x1008, 0))
    master.sdo(bytes([0x60]))
    reply = master.sdo(bytes([0x60]))
    assert reply is not None and reply[0] == 0x80 and int.from_bytes(reply[4:8], "little") == 0x0503_0000


def test_segmented_download_is_accepted_for_a_short_object(setup) -> None:
    master, _, _ = setup
    assert master.sdo(bytes([0x21]) + h(0x1017, 0) + u32(2)) == bytes([0x60]) + h(0x1017, 0) + bytes(4)
    # one segment: toggle 0, n = 5 bytes without data, c = 1
    assert master.sdo(bytes([0x00 | 5 << 1 | 1]) + struct.pack("<H", 30)) == bytes([0x20]) + bytes(7)
    assert master.upload(0x1017, 0) == struct.pack("<H", 30)


def test_an_sdo_request_of_other_than_8_bytes_is_ignored(setup) -> None:
    master, _, _ = setup
    master.drain()
    master.send(SDO_RX, bytes([0x40]) + h(0x1000, 0))
    assert master.expect(SDO_TX, 0.2) is None


# -- SYNC, PDO, EMCY, CiA 404 -------------------------------------------------------------------------------
def test_sync_gives_a_tpdo_every_nth_sync_only_when_operational(setup) -> None:
    master, _, world = setup
    configure_tpdo(master, 0x6130_0120, 0x6150_0108, transmission_type=3)
    world.values["output"] = -1.5
    for _ in range(6):
        master.send(SYNC, b"")
    master.drain(0.1)
    assert master.frames(TPDO1) == []  # PRE-OPERATIONAL: no PDO
    master.nmt(START)
    master.drain(0.05)
    for _ in range(7):
        master.send(SYNC, b"")
        master.drain(0.01)
    master.drain(0.1)
    assert [d for _, d in master.frames(TPDO1)] == [struct.pack("<f", -1.5) + b"\x00"] * 2  # 3rd and 6th SYNC


def test_emcy_frame_and_error_register_and_no_emcy_when_stopped(setup) -> None:
    master, node, _ = setup
    node.emcy(0x4210, register=0x09, extra=b"\x01")
    assert master.expect(EMCY, 0.5) == bytes.fromhex("1042 09 0100000000")
    assert master.upload(0x1001, 0) == b"\x09"
    master.nmt(STOP)
    master.drain(0.05)
    node.emcy(0x0000, register=0x00)  # error reset: not sent in STOPPED
    assert master.expect(EMCY, 0.2) is None
    master.nmt(ENTER_PRE_OPERATIONAL)
    master.drain(0.05)
    assert master.upload(0x1001, 0) == b"\x00"


def test_ai_status_bits_as_cia_404_defines_them(setup) -> None:
    master, node, world = setup
    configure_tpdo(master, 0x7130_0110, 0x6150_0108)  # INTEGER16 PV (scale 1: one count per um), status
    master.nmt(START)
    master.drain(0.05)

    def sample() -> bytes:
        master.drain()
        master.send(SYNC, b"")
        frame = master.expect(TPDO1, 0.5)
        assert frame is not None
        return frame

    world.values["output"] = 120.0
    assert sample() == struct.pack("<h", 120) + b"\x00"
    world.values["output"] = 40000.0  # beyond INTEGER16
    assert sample() == struct.pack("<h", 32767) + b"\x03"  # not valid + positive overload
    world.values["output"] = -40000.0
    assert sample() == struct.pack("<h", -32768) + b"\x05"  # not valid + negative overload
    world.values["output"] = float("nan")
    assert sample()[-1] == 0x01  # not valid only
    world.values["output"] = 5.0
    node.out_of_range()
    assert sample()[-1] == 0x03


def test_the_61a0h_moving_average_filters_the_pv(setup) -> None:
    master, _, world = setup
    master.download(0x61A0, 1, b"\x01")  # moving average
    master.download(0x61A1, 1, b"\x04")  # y += (x - y) / 4
    configure_tpdo(master, 0x6130_0120)
    master.nmt(START)
    master.drain(0.05)
    pvs = []
    for x in (0.0, 8.0, 8.0, 8.0):
        world.values["output"] = x
        master.drain()
        master.send(SYNC, b"")
        frame = master.expect(TPDO1, 0.5)
        assert frame is not None
        pvs.append(struct.unpack("<f", frame)[0])
    assert pvs == [0.0, 2.0, 3.5, 4.625]
