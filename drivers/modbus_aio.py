"""Modbus TCP/RTU analog I/O module (ADAM-6024 style) between the bench and a current amplifier.

Roles:

* actuator: one analog output (AO) drives the input of a current amplifier. ``write(amps)`` turns
  the wanted current into the amplifier's input voltage (``amplifier_gain_a_per_v``), then into AO
  counts (the AO count range mapped linearly onto the AO voltage range), clamped to the count range,
  and writes it with function 06 (Write Single Register).
* sensor: analog inputs (AI) read the amplifier's current monitor (``current``, A) and a
  displacement sensor's analog output (``output``, um) with one function 03 (Read Holding Registers;
  ADAM-6000 modules keep their AI values in the 4X area) or 04 (Read Input Registers) request.

Default register map, ADAM-6024 (ADAM-6000 Series User Manual, Appendix B.2.4): AI values at
40001..40006 (protocol addresses 0..5, read only), AO values at 40011..40012 (addresses 10..11,
read/write), AI status at 40021..40026. The AO is 12 bit, 0..4095 over 0..10 V; the AI default here
is 16 bit offset binary, 0..65535 over -10..+10 V. Every address and range is a setting, so another
module with a different map needs only a different driver table.

Errors: a request without a valid reply in ``timeout_s`` (none, or bytes that are not a Modbus
reply, which the message shows) is retried with back-off (:func:`drivers.base.retry`) and then
raises :class:`DeviceTimeout`; a Modbus exception response
raises :class:`DeviceError` naming the function and the exception code's meaning; a refused or
closed connection raises :class:`DeviceLost` naming the device.
"""

from __future__ import annotations

import inspect
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

from drivers.base import (
    DEFAULT_BACKOFF_S,
    DeviceError,
    DeviceLost,
    DeviceTimeout,
    DriverSpec,
    Lazy,
    Setting,
    retry,
)

# Modbus Application Protocol Specification V1.1b3, section 7 (exception codes) and 6 (functions).
EXCEPTION_MEANINGS: dict[int, str] = {
    0x01: "ILLEGAL FUNCTION",
    0x02: "ILLEGAL DATA ADDRESS",
    0x03: "ILLEGAL DATA VALUE",
    0x04: "SERVER DEVICE FAILURE",
    0x05: "ACKNOWLEDGE",
    0x06: "SERVER DEVICE BUSY",
    0x08: "MEMORY PARITY ERROR",
    0x0A: "GATEWAY PATH UNAVAILABLE",
    0x0B: "GATEWAY TARGET DEVICE FAILED TO RESPOND",
}
FUNCTION_NAMES: dict[int, str] = {
    0x03: "Read Holding Registers",
    0x04: "Read Input Registers",
    0x06: "Write Single Register",
    0x10: "Write Multiple Registers",
}

AI_CHANNELS = ("current", "output")  # the channel names read() can return


@dataclass(frozen=True)
class CountScale:
    """A linear map between register counts and volts (the module's configured range)."""

    counts_min: int
    counts_max: int
    volts_min: float
    volts_max: float

    def to_counts(self, volts: float) -> tuple[int, bool]:
        """Counts for ``volts`` (rounded), clamped to the count range; second item: clamped?"""
        span_v = self.volts_max - self.volts_min
        raw = self.counts_min + (volts - self.volts_min) / span_v * (self.counts_max - self.counts_min)
        if math.isnan(raw):
            raise ValueError("cannot convert NaN to counts")
        counts = round(raw)
        clamped = min(max(counts, self.counts_min), self.counts_max)
        return clamped, clamped != counts

    def to_volts(self, counts: int) -> float:
        """Volts for ``counts``; NaN when the counts lie outside the count range (over/under range)."""
        if not self.counts_min <= counts <= self.counts_max:
            return math.nan
        span_c = self.counts_max - self.counts_min
        return self.volts_min + (counts - self.counts_min) / span_c * (self.volts_max - self.volts_min)


def parse_url(url: str) -> tuple[str, str, int]:
    """``tcp://host:port`` -> ("tcp", host, port); anything else is a serial port for RTU."""
    if url.startswith("tcp://"):
        parsed = urlparse(url)
        if not parsed.hostname:
            raise ValueError(f"no host in Modbus URL {url!r}; expected tcp://host:port")
        return "tcp", parsed.hostname, 502 if parsed.port is None else parsed.port
    if url.startswith("rtu://"):  # rtu:///dev/ttyUSB0 spells the serial port explicitly
        return "rtu", url[len("rtu://"):], 0
    return "rtu", url, 0


def ao_scale(settings: dict[str, Any]) -> CountScale:
    return CountScale(int(settings["ao_counts_min"]), int(settings["ao_counts_max"]),
                      float(settings["ao_volts_min"]), float(settings["ao_volts_max"]))


def ai_scale(settings: dict[str, Any]) -> CountScale:
    return CountScale(int(settings["ai_counts_min"]), int(settings["ai_counts_max"]),
                      float(settings["ai_volts_min"]), float(settings["ai_volts_max"]))


def ai_registers(settings: dict[str, Any]) -> dict[str, int]:
    """Channel -> AI register address (0-based protocol address) for the channels in use (>= 0)."""
    regs = {"current": int(settings["ai_current_register"]), "output": int(settings["ai_output_register"])}
    return {name: reg for name, reg in regs.items() if reg >= 0}


def _device_kw(method: Callable[..., Any]) -> str:
    """The keyword pymodbus wants for the unit id: ``device_id`` (3.10+), ``slave`` or ``unit`` before."""
    params = inspect.signature(method).parameters
    for name in ("device_id", "slave", "unit"):
        if name in params:
            return name
    raise RuntimeError("this pymodbus client takes no unit id keyword (device_id/slave/unit)")


def stale_transactions(heard: bytes) -> list[int] | None:
    """The transaction ids of ``heard`` when it is nothing but complete, well-formed Modbus TCP replies
    (MBAP header, protocol id 0, a read-registers, write-register(s) or exception PDU whose length
    agrees with its header): the answers to earlier requests that timed out, arriving late, which the
    client skips for their transaction ids. None for anything else (a garbled or cut-short reply)."""
    ids: list[int] = []
    at = 0
    while at < len(heard):
        if len(heard) - at < 8:
            return None
        tid, pid, length = (int.from_bytes(heard[at + k:at + k + 2], "big") for k in (0, 2, 4))
        end = at + 6 + length
        if pid != 0 or length < 3 or end > len(heard):
            return None
        function = heard[at + 7]
        body = length - 2  # after the unit id and the function code
        if function & 0x80:
            ok = body == 1  # an exception response: its code
        elif function in (3, 4):
            ok = body >= 1 and body == 1 + heard[at + 8]  # a byte count, then the registers
        elif function in (6, 16):
            ok = body == 4  # the register (or first register) and the value (or count) echoed
        else:
            ok = False
        if not ok:
            return None
        ids.append(tid)
        at = end
    return ids or None


class ModbusAIO:
    """One analog I/O module: AO -> amplifier input (actuator), AIs -> current and output (sensor)."""

    def __init__(self, settings: dict[str, Any]):
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient
        from pymodbus.framer import FramerType

        self.settings = dict(settings)
        self.url = str(settings["url"])
        self.unit_id = int(settings["unit_id"])
        self.name = f"modbus-aio {self.url} unit {self.unit_id}"
        self.timeout_s = float(settings["timeout_s"])
        self.attempts = int(settings["attempts"])
        self.ao_register = int(settings["ao_register"])
        self.ai_function = str(settings["ai_function"])
        if self.ai_function not in ("holding", "input"):
            raise DeviceError(self.name, f"ai_function must be 'holding' (03) or 'input' (04), got {self.ai_function!r}")
        self.ao = ao_scale(settings)
        self.ai = ai_scale(settings)
        self.ai_regs = ai_registers(settings)
        self.gain_a_per_v = float(settings["amplifier_gain_a_per_v"])
        self.monitor_v_per_a = float(settings["current_monitor_v_per_a"])
        self.output_um_per_v = float(settings["output_um_per_v"])
        self.output_offset_um = float(settings["output_offset_um"])
        self.rest_a = float(settings["rest"])
        self.slew_a_per_s = float(settings["slew_per_s"])
        self.ramp_step_s = float(settings["ramp_step_s"])
        self.last_a: float | None = None  # what the AO really holds (after clamping and quantising)
        self.clamped_writes = 0

        self._heard = b""  # what came back for the request in flight (to name a reply that is not Modbus)
        kind, host, port = parse_url(self.url)
        self._tcp = kind == "tcp"  # MBAP frames carry transaction ids (late replies can be named)
        # retries=0: pymodbus would resend silently; base.retry does it visibly, with back-off.
        if kind == "tcp":
            self.client = ModbusTcpClient(host, port=port, timeout=self.timeout_s, retries=0,
                                          trace_packet=self._trace)
        else:
            self.client = ModbusSerialClient(host, framer=FramerType.RTU, baudrate=int(settings["baudrate"]),
                                             timeout=self.timeout_s, retries=0, trace_packet=self._trace)
        self._unit_kw = _device_kw(self.client.read_holding_registers)
        if not self.client.connect():
            raise DeviceLost(self.name, f"cannot connect to {self.url}")

    # -- one request ---------------------------------------------------------------------------------
    def _request(self, what: str, call: Callable[[], Any]) -> Any:
        """Run one Modbus request; timeouts retried, then typed errors naming this device."""
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        def once() -> Any:
            try:
                reply = call()
            except ConnectionException as exc:
                raise DeviceLost(self.name, f"{what}: connection lost ({exc})") from exc
            except ModbusIOException as exc:
                stale = stale_transactions(self._heard) if self._tcp else None
                if stale:  # answers to requests that timed out before: the module is slower than timeout_s
                    raise DeviceTimeout(self.name, f"{what}: only late replies to earlier requests came back "
                                                   f"(transaction ids {', '.join(map(str, stale))}), none to this "
                                                   f"one within {self.timeout_s} s: the module answers slower than "
                                                   "timeout_s") from exc
                if self._heard:  # bytes came back, but no Modbus reply could be read from them
                    raise DeviceTimeout(self.name, f"{what}: a reply that is not Modbus "
                                                   f"({len(self._heard)} bytes: {self._heard[:16].hex(' ')})") from exc
                if self.client.connected or self._reachable():
                    raise DeviceTimeout(self.name, f"{what}: no reply within {self.timeout_s} s") from exc
                raise DeviceLost(self.name, f"{what}: connection closed by the device ({exc})") from exc
            if reply.isError():
                raise self._exception_error(what, reply)
            return reply

        return retry(once, device=self.name, what=what, attempts=self.attempts, backoff_s=DEFAULT_BACKOFF_S)

    def _trace(self, sending: bool, data: bytes) -> bytes:
        """pymodbus's packet hook: a request clears what was heard; received bytes accumulate."""
        self._heard = b"" if sending else bytes(data)
        return data

    def _reachable(self) -> bool:
        """After a failed request: can the transport be opened again (else the device is gone)?"""
        try:
            return bool(self.client.connect())
        except Exception:  # noqa: BLE001 - any failure to reconnect means unreachable
            return False

    def _exception_error(self, what: str, reply: Any) -> DeviceError:
        code = int(getattr(reply, "exception_code", 0))
        function = int(getattr(reply, "function_code", 0)) & 0x7F  # the reply sets bit 7
        meaning = EXCEPTION_MEANINGS.get(code, "unknown exception code")
        fname = FUNCTION_NAMES.get(function, "function")
        return DeviceError(self.name, f"{what}: exception response to function {function:02d} ({fname}): "
                                      f"code {code} {meaning}")

    # -- actuator ------------------------------------------------------------------------------------
    def counts_for(self, amps: float) -> tuple[int, bool]:
        """AO counts for a wanted amplifier current (A): A -> V (amplifier input) -> counts."""
        return self.ao.to_counts(amps / self.gain_a_per_v)

    def write(self, value: float) -> None:
        """Command the amplifier current ``value`` (A); the AO is clamped to its count range."""
        counts, clamped = self.counts_for(float(value))
        self.clamped_writes += int(clamped)
        kw = {self._unit_kw: self.unit_id}
        self._request(f"write AO register {self.ao_register} = {counts}",
                      lambda: self.client.write_register(self.ao_register, counts, **kw))
        self.last_a = self.ao.to_volts(counts) * self.gain_a_per_v

    def stop(self, success: bool) -> None:
        """Bring the AO to ``rest`` (A) at ``slew_per_s`` (A/s), one write per ``ramp_step_s``.

        Also on success (as the simulated rig does) when the AO is not at rest; on failure the rest
        value is written even when the AO is believed at rest, since the last write may not have
        landed.
        """
        start = self.last_a
        if start is None:  # nothing written yet: the AO state is unknown, so set rest outright
            self.write(self.rest_a)
            return
        if abs(start - self.rest_a) < 1e-12:
            if not success:
                self.write(self.rest_a)
            return
        step = self.slew_a_per_s * self.ramp_step_s
        n = max(1, math.ceil(abs(self.rest_a - start) / step)) if step > 0 else 1
        for k in range(1, n + 1):
            self.write(start + (self.rest_a - start) * k / n)
            if k < n:
                time.sleep(self.ramp_step_s)

    # -- sensor --------------------------------------------------------------------------------------
    def read_counts(self) -> dict[str, int]:
        """Raw AI counts of the channels in use, read with one request over their address span."""
        if not self.ai_regs:
            return {}
        first, last = min(self.ai_regs.values()), max(self.ai_regs.values())
        count = last - first + 1
        kw = {self._unit_kw: self.unit_id}
        # 03 for the ADAM-6000 4X area, 04 for modules that keep their AIs in the 3X area.
        method = self.client.read_holding_registers if self.ai_function == "holding" else self.client.read_input_registers
        reply = self._request(f"read AI registers {first}..{last}", lambda: method(first, count=count, **kw))
        regs = list(reply.registers)
        if len(regs) < count:
            raise DeviceError(self.name, f"read AI registers {first}..{last}: {len(regs)} registers in the reply")
        return {name: int(regs[reg - first]) for name, reg in self.ai_regs.items()}

    def read(self) -> dict[str, float]:
        """``current`` (A) and/or ``output`` (um); NaN for a channel whose counts are out of range."""
        out: dict[str, float] = {}
        for name, counts in self.read_counts().items():
            volts = self.ai.to_volts(counts)
            if name == "current":
                out[name] = volts / self.monitor_v_per_a
            else:
                out[name] = volts * self.output_um_per_v + self.output_offset_um
        return out

    # -- description ---------------------------------------------------------------------------------
    def identity(self) -> str:
        return f"Modbus analog I/O module at {self.url}, unit {self.unit_id}"

    def capabilities(self) -> dict[str, Any]:
        return {
            "ao_register": self.ao_register, "ai_registers": dict(self.ai_regs), "ai_function": self.ai_function,
            "ao_counts": [self.ao.counts_min, self.ao.counts_max], "ao_volts": [self.ao.volts_min, self.ao.volts_max],
            "ai_counts": [self.ai.counts_min, self.ai.counts_max], "ai_volts": [self.ai.volts_min, self.ai.volts_max],
            "amplifier_gain_a_per_v": self.gain_a_per_v, "current_monitor_v_per_a": self.monitor_v_per_a,
            "output_um_per_v": self.output_um_per_v, "rest": self.rest_a, "slew_per_s": self.slew_a_per_s,
        }

    def close(self) -> None:
        self.client.close()


def open_device(settings: dict[str, Any]) -> ModbusAIO:
    return ModbusAIO(DRIVER.complete(settings))


SETTINGS = (
    Setting("url", str, required=True, doc="tcp://host:port (Modbus TCP) or a serial port / pyserial URL such as /dev/ttyUSB0 or socket://host:port (RTU)"),
    Setting("baudrate", int, default=9600, doc="RTU only: bit/s"),
    Setting("unit_id", int, default=1, doc="Modbus unit (slave) id"),
    Setting("ao_register", int, default=10, doc="AO holding register, 0-based (ADAM-6024 AO0 = 40011 -> 10)"),
    Setting("ai_current_register", int, default=0, doc="AI register of the amplifier's current monitor (40001 -> 0); -1 = none"),
    Setting("ai_output_register", int, default=1, doc="AI register of the displacement sensor (40002 -> 1); -1 = none"),
    Setting("ai_function", str, default="holding", doc="'holding' (function 03, ADAM-6000) or 'input' (function 04)"),
    Setting("ao_counts_min", int, default=0, doc="AO counts at ao_volts_min"),
    Setting("ao_counts_max", int, default=4095, doc="AO counts at ao_volts_max (12 bit)"),
    Setting("ao_volts_min", float, default=0.0, doc="V"),
    Setting("ao_volts_max", float, default=10.0, doc="V"),
    Setting("ai_counts_min", int, default=0, doc="AI counts at ai_volts_min"),
    Setting("ai_counts_max", int, default=65535, doc="AI counts at ai_volts_max (16 bit)"),
    Setting("ai_volts_min", float, default=-10.0, doc="V"),
    Setting("ai_volts_max", float, default=10.0, doc="V"),
    Setting("amplifier_gain_a_per_v", float, default=0.1, doc="amplifier output current per input volt, A/V"),
    Setting("current_monitor_v_per_a", float, default=10.0, doc="amplifier current monitor, V/A"),
    Setting("output_um_per_v", float, default=10.0, doc="displacement sensor analog output scale, um/V"),
    Setting("output_offset_um", float, default=0.0, doc="displacement at 0 V, um"),
    Setting("timeout_s", float, default=0.2, doc="reply timeout per request, s"),
    Setting("attempts", int, default=3, doc="tries per request when replies time out"),
    Setting("rest", float, default=0.0, doc="rest current, A"),
    Setting("slew_per_s", float, default=1.0, doc="ramp rate to rest, A/s"),
    Setting("ramp_step_s", float, default=0.01, doc="time between ramp writes, s"),
)

DRIVER = DriverSpec(
    name="modbus-aio",
    roles=("actuator", "sensor"),
    settings=SETTINGS,
    open=open_device,
    emulator=Lazy("drivers.emulators.modbus_aio:start_emulator"),
    description="Modbus TCP/RTU analog I/O module (ADAM-6024 map by default): AO -> current amplifier, "
                "AIs -> current monitor and displacement sensor",
    transports=("tcp://", "serial"),
)
