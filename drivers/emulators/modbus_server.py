"""A Modbus server whose function layer answers as the Modbus specification says, on pymodbus.

pymodbus (3.16) frames and transports the requests here (Modbus TCP, or RTU frames on a loopback
socket); the function layer is this module's, because pymodbus's own differs from the specification
where an independent client looks:

* a quantity outside the specification's limits makes pymodbus's request decoder fail, and the
  server answers exception 01 in a frame whose function byte is 0x80, not function | 0x80 with 03;
* a function code pymodbus does not know gets the same 0x80 01 frame;
* every function pymodbus knows (07, 0B, 0C, 11, 14, 15, 16, 17, 18, 2B...) is served, whether
  the emulated device has it or not.

MODBUS Application Protocol Specification V1.1b3, section 6 (each function's state diagram) and 7
(exception codes): a request is checked in this order, the first failure answering
``function | 0x80`` and the code:

1. the function is one the device supports, else 01 ILLEGAL FUNCTION;
2. the quantity is within the function's limits (01/02: 1..2000 bits; 03/04: 1..125 registers;
   15: 1..1968 bits with byte count = ceil(N/8); 16: 1..123 registers with byte count = 2N), the
   value of a 05 request is 0000 or FF00, and the request has the length its fields imply, else 03
   ILLEGAL DATA VALUE;
3. every address from the start to start + quantity - 1 exists in the device's map (and, for a
   write, is writable), else 02 ILLEGAL DATA ADDRESS;
4. the device does it, or refuses with its own code (e.g. 04 SERVER DEVICE FAILURE).

The limits above are the specification's, as the stored copies of device manuals quoting it give
them (the specification itself was not among the searchable copies). A request to another unit id
than the device's is answered 0B GATEWAY TARGET DEVICE FAILED TO RESPOND (a choice: what a Modbus
TCP module does with a foreign unit id is device specific).
"""

from __future__ import annotations

import asyncio
import struct
import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol

ILLEGAL_FUNCTION = 0x01
ILLEGAL_DATA_ADDRESS = 0x02
ILLEGAL_DATA_VALUE = 0x03
GATEWAY_TARGET_FAILED = 0x0B

READ_BITS_MAX = 0x07D0  # functions 01, 02
READ_REGISTERS_MAX = 0x007D  # functions 03, 04
WRITE_BITS_MAX = 0x07B0  # function 15
WRITE_REGISTERS_MAX = 0x007B  # function 16
COIL_ON, COIL_OFF = 0xFF00, 0x0000  # function 05


class Refused(Exception):
    """The device refuses a request with Modbus exception ``code``."""

    def __init__(self, code: int):
        super().__init__(f"Modbus exception {code}")
        self.code = int(code)


class ModbusDevice(Protocol):
    """What the function layer needs of the device behind it; every method may raise :class:`Refused`."""

    unit_id: int
    functions: frozenset[int]  # function codes the device supports (01..06, 08, 15, 16 handled here)
    coil_values_without_effect: frozenset[int]  # 05 values besides 0000/FF00 it accepts and ignores

    def admit(self, function: int) -> None:
        """Called first for every request to this unit (fault injection can refuse it here)."""

    def read(self, function: int, address: int, count: int) -> list[int] | list[bool]:
        """Bits (01, 02) or registers (03, 04) from ``address``; Refused(2) for an address not there."""

    def write(self, function: int, address: int, values: Sequence[int] | Sequence[bool]) -> None:
        """Bits (05, 15) or registers (06, 16) from ``address``, all or none; an empty ``values``
        checks that ``address`` is writable and changes nothing."""


# -- the functions -----------------------------------------------------------------------------------
def _fields(data: bytes, fmt: str, exact: bool = True) -> tuple[int, ...]:
    """The request's fields; a request shorter (or, if ``exact``, longer) than they imply is refused 03."""
    size = struct.calcsize(fmt)
    if len(data) < size or (exact and len(data) != size):
        raise Refused(ILLEGAL_DATA_VALUE)
    return struct.unpack(fmt, data[:size])


def _pack_bits(bits: Sequence[bool]) -> bytes:
    """Bits packed as the specification says: the first bit in the low bit of the first byte."""
    out = bytearray((len(bits) + 7) // 8)
    for k, bit in enumerate(bits):
        if bit:
            out[k // 8] |= 1 << (k % 8)
    return bytes(out)


def _unpack_bits(data: bytes, count: int) -> list[bool]:
    return [bool(data[k // 8] >> (k % 8) & 1) for k in range(count)]


def _read(device: ModbusDevice, function: int, data: bytes) -> bytes:
    address, count = _fields(data, ">HH")
    limit = READ_BITS_MAX if function in (1, 2) else READ_REGISTERS_MAX
    if not 1 <= count <= limit:
        raise Refused(ILLEGAL_DATA_VALUE)
    values = device.read(function, address, count)
    if function in (1, 2):
        packed = _pack_bits([bool(v) for v in values])
        return bytes([len(packed)]) + packed
    return bytes([2 * count]) + struct.pack(f">{count}H", *values)


def _write_single_coil(device: ModbusDevice, function: int, data: bytes) -> bytes:
    address, value = _fields(data, ">HH")
    if value in (COIL_ON, COIL_OFF):
        device.write(function, address, [value == COIL_ON])
    elif value in device.coil_values_without_effect:
        device.write(function, address, [])
    else:
        raise Refused(ILLEGAL_DATA_VALUE)
    return data  # the normal response is an echo of the request


def _write_single_register(device: ModbusDevice, function: int, data: bytes) -> bytes:
    address, value = _fields(data, ">HH")
    device.write(function, address, [value])
    return data  # the normal response is an echo of the request


def _write_multiple_coils(device: ModbusDevice, function: int, data: bytes) -> bytes:
    address, count, byte_count = _fields(data, ">HHB", exact=False)
    if not 1 <= count <= WRITE_BITS_MAX or byte_count != (count + 7) // 8 or len(data) != 5 + byte_count:
        raise Refused(ILLEGAL_DATA_VALUE)
    device.write(function, address, _unpack_bits(data[5:], count))
    return data[:4]  # start address and quantity


def _write_multiple_registers(device: ModbusDevice, function: int, data: bytes) -> bytes:
    address, count, byte_count = _fields(data, ">HHB", exact=False)
    if not 1 <= count <= WRITE_REGISTERS_MAX or byte_count != 2 * count or len(data) != 5 + byte_count:
        raise Refused(ILLEGAL_DATA_VALUE)
    device.write(function, address, list(struct.unpack(f">{count}H", data[5:])))
    return data[:4]


def _echo(device: ModbusDevice, function: int, data: bytes) -> bytes:
    """08 as the ADAM-6000 manual has it: the request's data come back unchanged (the spec's
    sub-function 0000 Return Query Data does the same)."""
    return data


def _illegal_function(device: ModbusDevice, function: int, data: bytes) -> bytes:
    raise Refused(ILLEGAL_FUNCTION)


Handler = Callable[[ModbusDevice, int, bytes], bytes]
HANDLERS: dict[int, Handler] = {
    1: _read, 2: _read, 3: _read, 4: _read, 5: _write_single_coil, 6: _write_single_register,
    8: _echo, 15: _write_multiple_coils, 16: _write_multiple_registers,
}
FIXED_RTU_SIZE = {fc: 8 for fc in (1, 2, 3, 4, 5, 6)}  # unit, function, 2 x 2 bytes, CRC


# -- pymodbus PDUs carrying them ---------------------------------------------------------------------
def request_classes(device: ModbusDevice) -> list[type[Any]]:
    """One pymodbus request class for every function code 1..127, answering for ``device``.

    Registered as the server's ``custom_pdu``, they replace pymodbus's own decoding and handling
    of every function (1..127), so each answer follows the order of checks above.
    """
    from pymodbus.pdu import ExceptionResponse, ModbusPDU

    class Reply(ModbusPDU):
        def __init__(self, function: int, payload: bytes):
            super().__init__()
            self.function_code = function
            self.payload = payload

        def encode(self) -> bytes:
            return self.payload

    class Request(ModbusPDU):
        handler: Handler = _illegal_function
        data = b""

        def decode(self, data: bytes) -> None:
            self.data = bytes(data)  # checked when handled, so a bad field is answered, not dropped

        @classmethod
        def calculateRtuFrameSize(cls, data: bytes) -> int:
            if cls.rtu_frame_size or cls.rtu_byte_count_pos:
                return super().calculateRtuFrameSize(data)
            # A function of no fixed length: the bytes received so far (the RTU silence ends a frame).
            return len(data) if len(data) >= 4 else 0

        async def datastore_update(self, context: Any, device_id: int) -> ModbusPDU:
            function = self.function_code
            try:
                if device_id != device.unit_id:
                    raise Refused(GATEWAY_TARGET_FAILED)
                device.admit(function)
                payload = type(self).handler(device, function, self.data)
            except Refused as refusal:
                return ExceptionResponse(function, refusal.code)
            return Reply(function, payload)

    classes: list[type[Any]] = []
    for function in range(1, 0x80):
        handler = HANDLERS[function] if function in device.functions and function in HANDLERS else _illegal_function
        attrs: dict[str, Any] = {"function_code": function, "handler": staticmethod(handler),
                                 "rtu_frame_size": FIXED_RTU_SIZE.get(function, 0),
                                 "rtu_byte_count_pos": 6 if function in (15, 16) else 0}
        classes.append(type(f"Request{function:02X}", (Request,), attrs))
    return classes


class ModbusServerThread:
    """A pymodbus server on 127.0.0.1 in a background thread with its own event loop.

    ``rtu``: RTU frames (with CRC) over the socket, reached by a serial URL ``socket://host:port``;
    otherwise Modbus TCP. ``trace(sending, frame) -> frame`` sees every frame (b"" sends nothing).
    """

    def __init__(self, device: ModbusDevice, *, rtu: bool, port: int = 0,
                 trace: Callable[[bool, bytes], bytes] | None = None, start_timeout_s: float = 5.0):
        from pymodbus.framer import FramerType
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        # pymodbus wants a datastore; the request classes above answer every request without it.
        placeholder = SimDevice(id=0, simdata=SimData(0, values=0, datatype=DataType.REGISTERS))
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._server: Any = None

        async def start() -> None:
            self._server = ModbusTcpServer(placeholder, address=("127.0.0.1", port), trace_packet=trace,
                                           framer=FramerType.RTU if rtu else FramerType.SOCKET,
                                           custom_pdu=request_classes(device))
            await self._server.serve_forever(background=True)

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._loop.run_until_complete(start())
            except BaseException as exc:  # noqa: BLE001 - handed to the starting thread
                self._error = exc
                self._ready.set()
                return
            self._ready.set()
            self._loop.run_forever()

        self.thread = threading.Thread(target=run, name="modbus-server", daemon=True)
        self.thread.start()
        if not self._ready.wait(start_timeout_s):
            raise RuntimeError("Modbus server did not start")
        if self._error is not None:
            raise RuntimeError(f"Modbus server did not start ({self._error})") from self._error
        self.port = int(self._server.transport.sockets[0].getsockname()[1])

    def shutdown(self, timeout_s: float = 2.0) -> None:
        """Stop serving: open connections close and new ones are refused."""
        if self._server is None or not self._loop.is_running():
            return
        asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(timeout_s)

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the server and its thread (idempotent)."""
        if self.thread.is_alive():
            try:
                self.shutdown(timeout_s)
            finally:
                self._loop.call_soon_threadsafe(self._loop.stop)
                self.thread.join(timeout_s)
        if not self.thread.is_alive() and not self._loop.is_closed():
            self._loop.close()
