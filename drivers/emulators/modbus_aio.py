"""Emulator of the Modbus analog I/O module: a real pymodbus server on 127.0.0.1.

Modbus TCP for a ``tcp://`` driver table; for a serial (RTU) one, RTU frames (with CRC) over a
loopback socket that the driver opens as the serial URL ``socket://127.0.0.1:PORT``.

The server runs in a background thread with its own event loop. Its datastore is a pymodbus
``SimDevice`` whose registers follow the driver settings (AO register read/write, AI registers read
only, every other address answers ILLEGAL DATA ADDRESS like the real module) and whose access hook
ties them to the :class:`~drivers.base.World`:

* a write to the AO register -> counts -> volts -> amps (through the amplifier gain) ->
  ``world.command(amps)``;
* a read of the AI registers -> ``world.read("current")`` / ``world.read("output")`` -> volts ->
  counts.

Fault injection for tests: :meth:`drop_replies` (no reply: the client times out),
:meth:`exception_next` (an exception response to the next request), :meth:`out_of_range` (AI counts
outside the configured range) and :meth:`disconnect` (server shutdown: connections close).
Every frame sent and received is kept in :attr:`frames`, so a test can show the bytes on the wire.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

from drivers.base import World
from drivers.modbus_aio import ai_registers, ai_scale, ao_scale, parse_url


class ModbusAIOEmulator:
    """A running emulated analog I/O module; ``url`` is what the driver table's ``url`` should be."""

    def __init__(self, settings: dict[str, Any], world: World, *, start_timeout_s: float = 5.0):
        from pymodbus.constants import ExcCodes
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        self._exc_codes = ExcCodes
        self.world = world
        self.unit_id = int(settings["unit_id"])
        self.ao_register = int(settings["ao_register"])
        self.ai_regs = ai_registers(settings)
        self.ao = ao_scale(settings)
        self.ai = ai_scale(settings)
        self.gain_a_per_v = float(settings["amplifier_gain_a_per_v"])
        self.monitor_v_per_a = float(settings["current_monitor_v_per_a"])
        self.output_um_per_v = float(settings["output_um_per_v"])
        self.output_offset_um = float(settings["output_offset_um"])

        # What the tests look at: every AO value written (A), and the frames on the wire.
        self.ao_writes: list[float] = []
        self.frames: list[tuple[str, bytes]] = []  # ("rx" | "tx", the ADU: MBAP + PDU, or RTU frame)
        self._lock = threading.Lock()  # the World is called from the server thread only, under it
        self._drop = 0
        self._exception: int | None = None
        self._out_of_range = False

        from pymodbus.framer import FramerType

        host, port = "127.0.0.1", 0
        url = str(settings.get("url", ""))
        # A tcp:// config gets Modbus TCP on its own port (so a real-rig config can be dry-run); a
        # serial (RTU) config gets RTU frames over a loopback socket, reached as socket://host:port.
        self.rtu = not url.startswith("tcp://")
        if not self.rtu:
            _, _, port = parse_url(url)
        blocks = [SimData(self.ao_register, values=0, datatype=DataType.REGISTERS)]
        blocks += [SimData(reg, values=0, datatype=DataType.REGISTERS, readonly=True)
                   for reg in sorted(set(self.ai_regs.values()))]
        device = SimDevice(id=self.unit_id, simdata=blocks, action=self._action)

        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._server: Any = None

        async def start() -> None:
            self._server = ModbusTcpServer(device, address=(host, port), trace_packet=self._trace,
                                           framer=FramerType.RTU if self.rtu else FramerType.SOCKET)
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

        self._thread = threading.Thread(target=run, name="modbus-aio-emulator", daemon=True)
        self._thread.start()
        if not self._ready.wait(start_timeout_s):
            raise RuntimeError("modbus-aio emulator: server did not start")
        if self._error is not None:
            raise RuntimeError(f"modbus-aio emulator: server did not start ({self._error})") from self._error
        bound = self._server.transport.sockets[0].getsockname()
        self.port = int(bound[1])
        self.url = f"{'socket' if self.rtu else 'tcp'}://127.0.0.1:{self.port}"

    # -- the device behind the registers -----------------------------------------------------------
    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> Any:
        with self._lock:
            if self._exception is not None:
                code, self._exception = self._exception, None
                return self._exc_codes(code)
            if set_values is not None:
                for k, value in enumerate(set_values):
                    if address + k == self.ao_register:
                        amps = self.ao.to_volts(int(value)) * self.gain_a_per_v
                        self.ao_writes.append(amps)
                        self.world.command(amps)
                return None
            for name, reg in self.ai_regs.items():
                if address <= reg < address + count:
                    registers[reg - start_address] = self._ai_counts(name)
        return None

    def _ai_counts(self, channel: str) -> int:
        if self._out_of_range:
            return min(self.ai.counts_max + 1, 0xFFFF)
        value = float(self.world.read(channel))
        if channel == "current":
            volts = value * self.monitor_v_per_a
        else:
            volts = (value - self.output_offset_um) / self.output_um_per_v
        counts, _ = self.ai.to_counts(volts)  # a real ADC saturates at its range ends
        return counts

    def _trace(self, sending: bool, data: bytes) -> bytes:
        with self._lock:
            if sending and self._drop > 0:
                self._drop -= 1
                return b""  # nothing goes on the wire: the client sees no reply
            self.frames.append(("tx" if sending else "rx", bytes(data)))
        return data

    # -- fault injection -----------------------------------------------------------------------------
    def drop_replies(self, n: int) -> None:
        """Send no reply to the next ``n`` requests (the request is still executed)."""
        with self._lock:
            self._drop = int(n)

    def exception_next(self, code: int) -> None:
        """Answer the next request with Modbus exception ``code`` (e.g. 2 ILLEGAL DATA ADDRESS)."""
        with self._lock:
            self._exception = int(code)

    def out_of_range(self, on: bool = True) -> None:
        """AI reads return counts above the configured count range (an over-range input)."""
        with self._lock:
            self._out_of_range = bool(on)

    @property
    def last_ao(self) -> float | None:
        """The last AO value written, A (None before any write)."""
        with self._lock:
            return self.ao_writes[-1] if self.ao_writes else None

    def disconnect(self, timeout_s: float = 2.0) -> None:
        """Shut the server down: open connections close and new ones are refused."""
        if self._server is None or not self._loop.is_running():
            return
        asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(timeout_s)

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the server and its thread (idempotent)."""
        if self._thread.is_alive():
            try:
                self.disconnect(timeout_s)
            finally:
                self._loop.call_soon_threadsafe(self._loop.stop)
                self._thread.join(timeout_s)
        if not self._thread.is_alive() and not self._loop.is_closed():
            self._loop.close()


def start_emulator(settings: dict[str, Any], world: World) -> ModbusAIOEmulator:
    """A running Modbus server on 127.0.0.1 (``.url``) backed by ``world``."""
    from drivers.modbus_aio import DRIVER

    return ModbusAIOEmulator(DRIVER.complete(settings), world)
