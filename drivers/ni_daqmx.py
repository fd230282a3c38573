"""NI-DAQmx analog I/O (an NI 9263 AO and an NI 9234 AI in a cDAQ chassis, or any DAQmx device)
through NI's ``nidaqmx`` package: locally, or through an NI gRPC Device Server.

Roles:

* actuator: one AO voltage channel (``ao_channel``, e.g. ``cDAQ1Mod1/ao0``) drives the input of a
  current amplifier. ``write(amps)`` turns the wanted current into volts (``amplifier_gain_a_per_v``)
  and refuses volts outside ``ao_min_v..ao_max_v`` (the channel's range as DAQmx was told);
* sensor: AI voltage channels: ``ai_output_channel`` (a displacement sensor's analog output, um =
  V x ``output_um_per_v`` + ``output_offset_um``) and, when set, ``ai_current_channel`` (the
  amplifier's current monitor, A = V / ``current_monitor_v_per_a``);
* player: ``play(waveform, rate)`` writes the whole waveform to a finite AO task, arms a finite AI
  task on the AO task's start trigger (``/CHASSIS/ao/StartTrigger``: both start on the same edge and
  run at the same rate from the chassis timebase), starts the AO, reads back every AI sample.

Per-sample work has three modes (``mode``); in the first two the DAQ's sample clock at
``sample_rate_hz`` times the loop (:meth:`NIDAQmxDevice.wait_for_next_sample_clock`, which the
rig's fixed-rate loop calls instead of keeping its own deadlines; a ``read()`` without it waits
first) and the samples the DAQ reports late are counted (:meth:`NIDAQmxDevice.clock_stats`):

* ``hw-timed-single-point`` (default; PCIe/PXI multifunction DAQs): both tasks run
  ``AcquisitionType.HW_TIMED_SINGLE_POINT``; the wait is DAQmx Wait For Next Sample Clock on the AI
  task, whose ``isLate`` says the loop missed the tick. The ``nidaqmx`` package (1.x) has no Python
  method for it, so the driver calls the device server's ``WaitForNextSampleClock`` RPC (stubs shipped
  in ``nidaqmx._stubs``) or, locally, ``DAQmxWaitForNextSampleClock`` from the DAQmx C library that
  ``nidaqmx`` loaded. C Series modules in a cDAQ chassis have neither ("C Series devices do not
  support hardware-timed single-point sample mode or Wait for Next Sample Clock", NI-DAQmx Device
  Considerations, Timing Considerations for C Series Devices): use ``ai-clocked`` there.
* ``ai-clocked`` (a cDAQ): the AI task acquires continuously on its sample clock into DAQmx's buffer
  (``AcquisitionType.CONTINUOUS``, ``ai_buffer_s`` of samples) and the wait reads the next sample,
  which returns when the DAQ has acquired it; the AO is written on demand as soon as the loop has
  its command (NI's "hardware-timed input, software-timed output" control case). The wait first
  reads every sample already acquired (DAQmx Read of -1 samples, timeout 0): any means the tick came
  before the loop got back to wait, as Wait For Next Sample Clock's ``isLate`` says; the newest is
  kept (the loop acts on the latest measurement and waits for the next tick, as a late Wait For
  Next Sample Clock does). None: it reads the next sample, which returns when the DAQ has acquired
  it. A backlog the buffer could not hold (DAQmx -200279) restarts the acquisition and counts as late.
* ``on-demand``: software-timed scalar writes and reads (the rig's loop keeps the time).

At open the tasks are verified (DAQmx TaskControl Verify), so a timing the modules refuse fails then,
with DAQmx's own error, and the sample rate is read back (``SampClk.Rate``): DAQmx coerces a rate a
module cannot run (the NI 9234 runs 51.2 kS/s / n, n = 1..31, and rounds a rate up to the next of
them), and a rate other than ``sample_rate_hz`` is refused in one line naming both. ``play`` reads
its AI task's rate back the same way before anything moves.

``url``: ``grpc://HOST:PORT`` for an NI gRPC Device Server (its default port is 31763), or ``local``
for the NI-DAQmx driver installed on this computer.

Errors: a DAQmx error becomes one :class:`DeviceError` line naming the device, the operation and
NI's error code (``NI-DAQmx error -200170: Physical channel specified does not exist ...``); a
DAQmx timeout (-200284, -200474) or an RPC past its deadline (every RPC carries one: the DAQmx
timeout + ``rpc_margin_s``, so a stalled server cannot hang the loop) is retried with back-off and
then raises :class:`DeviceTimeout`; an unreachable or vanished server raises :class:`DeviceLost`.

``nidaqmx`` is an optional dependency (``pip install 'hilbench[nidaqmx]'``): this module imports
without it and imports it when a device is opened.
"""

from __future__ import annotations

import math
import re
import time
import uuid
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

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

T = TypeVar("T")

INSTALL_HINT = "pip install 'hilbench[nidaqmx]'"
MODES = ("hw-timed-single-point", "ai-clocked", "on-demand")
CLOCKED = ("hw-timed-single-point", "ai-clocked")
SAMPLES_NO_LONGER_AVAILABLE = -200279  # a continuous acquisition's buffer overwrote unread samples
TERMINAL_CONFIGS = {"default": -1, "rse": 10083, "nrse": 10078, "diff": 10106, "pseudodiff": 12529}
# DAQmx errors that mean "not yet": the samples or the clock did not come within the timeout.
TIMEOUT_CODES = {-200284, -200474}
DEFAULT_GRPC_PORT = 31763  # the NI gRPC Device Server's default port


def nidaqmx_available() -> bool:
    """Whether the optional ``nidaqmx`` package and its gRPC extra are installed (found, not imported:
    importing nidaqmx costs time and loads the DAQmx library where there is one)."""
    from importlib.util import find_spec

    try:
        return all(find_spec(name) is not None for name in ("nidaqmx", "grpc", "session_pb2"))
    except (ImportError, ValueError):  # a blocked or half-imported package counts as missing
        return False


def _import_nidaqmx(device: str) -> Any:
    try:
        import nidaqmx
    except ImportError:
        raise DeviceError(device, f"the nidaqmx package is not installed; {INSTALL_HINT}") from None
    return nidaqmx


def parse_url(url: str) -> tuple[str, int] | None:
    """``grpc://HOST:PORT`` -> (host, port); ``local`` -> None (the DAQmx library on this computer)."""
    text = url.strip()
    if text.lower() == "local":
        return None
    match = re.fullmatch(r"grpc://(\[[^\]]+\]|[^:/]+)(?::(\d+))?/?", text)
    if not match:
        raise ValueError(f"url {url!r}: expected grpc://HOST:PORT (an NI gRPC Device Server) or local")
    return match.group(1), int(match.group(2) or DEFAULT_GRPC_PORT)


def chassis_of(physical_channel: str) -> str:
    """``cDAQ1Mod1/ao0`` -> ``cDAQ1``: the chassis whose AO start trigger the AI task waits for."""
    device = physical_channel.strip().strip("/").split("/")[0]
    return re.sub(r"Mod\d+$", "", device)


def _deadline_channel(target: str, deadline_s: Callable[[], float]) -> Any:
    """A gRPC channel to ``target`` on which every call carries a deadline (nidaqmx sets none)."""
    import grpc

    class Deadline(grpc.UnaryUnaryClientInterceptor, grpc.UnaryStreamClientInterceptor):
        def _with_deadline(self, details: Any) -> Any:
            if details.timeout is not None:
                return details
            return _CallDetails(details.method, deadline_s(), details.metadata, details.credentials,
                                getattr(details, "wait_for_ready", None), getattr(details, "compression", None))

        def intercept_unary_unary(self, continuation: Any, details: Any, request: Any) -> Any:
            return continuation(self._with_deadline(details), request)

        def intercept_unary_stream(self, continuation: Any, details: Any, request: Any) -> Any:
            return continuation(self._with_deadline(details), request)

    class _CallDetails(grpc.ClientCallDetails):
        def __init__(self, method: str, timeout: float, metadata: Any, credentials: Any, wait_for_ready: Any,
                     compression: Any):
            self.method, self.timeout, self.metadata = method, timeout, metadata
            self.credentials, self.wait_for_ready, self.compression = credentials, wait_for_ready, compression

    channel = grpc.insecure_channel(target)
    return channel, grpc.intercept_channel(channel, Deadline())


class NIDAQmxDevice:
    """An AO channel (actuator), AI channels (sensor) and buffered AO/AI (player) on NI-DAQmx."""

    def __init__(self, settings: dict[str, Any]):
        self.settings = settings
        self.url = str(settings["url"])
        self.name = str(settings.get("name") or f"ni-daqmx ({self.url})")
        try:
            self.address = parse_url(self.url)
        except ValueError as exc:
            raise DeviceError(self.name, str(exc)) from None
        self.nidaqmx = _import_nidaqmx(self.name)
        self.ao_channel = str(settings["ao_channel"])
        self.ai_channels: dict[str, str] = {"output": str(settings["ai_output_channel"])}
        if str(settings.get("ai_current_channel") or ""):
            self.ai_channels["current"] = str(settings["ai_current_channel"])
        self.ao_min_v, self.ao_max_v = float(settings["ao_min_v"]), float(settings["ao_max_v"])
        self.ai_min_v, self.ai_max_v = float(settings["ai_min_v"]), float(settings["ai_max_v"])
        self.gain_a_per_v = float(settings["amplifier_gain_a_per_v"])
        self.output_um_per_v = float(settings["output_um_per_v"])
        self.output_offset_um = float(settings["output_offset_um"])
        self.monitor_v_per_a = float(settings["current_monitor_v_per_a"])
        self.rate_hz = float(settings["sample_rate_hz"])
        self.mode = str(settings["mode"])
        if self.mode not in MODES:
            raise DeviceError(self.name, f"mode {self.mode!r}: expected one of {', '.join(MODES)}")
        terminal = str(settings["terminal_config"]).lower()
        if terminal not in TERMINAL_CONFIGS:
            raise DeviceError(self.name, f"terminal_config {terminal!r}: expected one of {', '.join(TERMINAL_CONFIGS)}")
        self.terminal = TERMINAL_CONFIGS[terminal]
        self.start_trigger = str(settings.get("start_trigger") or "") or f"/{chassis_of(self.ao_channel)}/ao/StartTrigger"
        self.timeout_s = float(settings["timeout_s"])
        self.rpc_margin_s = float(settings["rpc_margin_s"])
        self.attempts = int(settings["attempts"])
        self.backoff_s = float(settings["backoff_s"])
        self.rest = float(settings["rest"])
        self.play_margin_s = float(settings["play_margin_s"])
        self.ai_buffer_s = float(settings["ai_buffer_s"])
        self.slew_per_s = float(settings["slew_per_s"])
        self._rpc_deadline_s = self.timeout_s + self.rpc_margin_s
        self._token = uuid.uuid4().hex[:8]
        self._raw_channel: Any = None
        self._channel: Any = None
        self._stub: Any = None
        self._ao: Any = None  # the per-sample tasks, created at open, started on first use
        self._ai: Any = None
        self._ai_buffer = np.zeros(len(self.ai_channels), dtype=np.float64)
        # ai-clocked: room for every sample DAQmx's buffer can hold, read at once when the loop is late
        self._ai_backlog = np.zeros(len(self.ai_channels) * max(2, math.ceil(self.rate_hz * self.ai_buffer_s))
                                    if self.mode == "ai-clocked" else 0, dtype=np.float64)
        self._last_amps = self.rest
        self.samples = 0  # clocked modes: sample clocks waited for
        self.late = 0  # ... of which DAQmx reported late
        self._clock_taken = False  # the next read() is for a tick already waited for
        self.version = "?"
        if self.address is not None:
            host, port = self.address
            self._raw_channel, self._channel = _deadline_channel(f"{host}:{port}", lambda: self._rpc_deadline_s)
        try:
            self._open_loop_tasks()
        except BaseException:
            self.close()
            raise

    # -- errors and calls -----------------------------------------------------------------------------
    def _translate(self, exc: BaseException, what: str) -> DeviceError:
        """One DeviceError line for whatever nidaqmx or gRPC raised."""
        import grpc

        errors = self.nidaqmx.errors
        where = f"the NI gRPC device server at {self.address[0]}:{self.address[1]}" if self.address else "NI-DAQmx"
        if isinstance(exc, errors.RpcError) or isinstance(exc, grpc.RpcError):
            code = exc.rpc_code if isinstance(exc, errors.RpcError) else exc.code()
            if code == grpc.StatusCode.DEADLINE_EXCEEDED:
                return DeviceTimeout(self.name, f"{what}: no answer from {where} in {self._rpc_deadline_s:g} s")
            if code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED):
                return DeviceLost(self.name, f"{what}: {where} is unreachable or went away ({code.name})")
            if code == grpc.StatusCode.UNIMPLEMENTED:
                return DeviceError(self.name, f"{what}: not supported by {where} (gRPC UNIMPLEMENTED)")
            if isinstance(exc, grpc.RpcError):  # our own stub call: the DAQmx code is in ni-error
                ni = dict(exc.trailing_metadata() or ()).get("ni-error")
                if ni is not None and ni.lstrip("-").isdigit():
                    return self._daq_error(int(ni), str(exc.details() or ""), what)
            return DeviceError(self.name, f"{what}: gRPC {code.name}: {getattr(exc, 'message', '') or exc}")
        if isinstance(exc, errors.DaqError):
            return self._daq_error(int(exc.error_code), str(exc), what)
        return DeviceError(self.name, f"{what}: {type(exc).__name__}: {exc}")

    def _daq_error(self, code: int, message: str, what: str) -> DeviceError:
        first = next((line.strip() for line in message.splitlines() if line.strip()), "")
        kind = DeviceTimeout if code in TIMEOUT_CODES else DeviceError
        return kind(self.name, f"{what}: NI-DAQmx error {code}: {first}")

    def _call(self, what: str, fn: Callable[[], T], *, retried: bool = True) -> T:
        """``fn`` with nidaqmx's and gRPC's exceptions as DeviceErrors; timeouts retried with back-off."""
        import grpc

        def attempt() -> T:
            try:
                return fn()
            except (self.nidaqmx.errors.DaqError, self.nidaqmx.errors.RpcError, grpc.RpcError) as exc:
                raise self._translate(exc, what) from None

        if not retried:
            return attempt()
        return retry(attempt, device=self.name, what=what, attempts=self.attempts, backoff_s=self.backoff_s)

    def _task(self, role: str) -> Any:
        """A new DAQmx task, on the device server when there is one (its session name = task name)."""
        name = f"hilbench-{role}-{self._token}-{uuid.uuid4().hex[:4]}"
        if self._channel is None:
            return self.nidaqmx.Task(name)
        options = self.nidaqmx.GrpcSessionOptions(self._channel, name)
        return self.nidaqmx.Task(name, grpc_options=options)

    # -- per-sample tasks -----------------------------------------------------------------------------
    def _open_loop_tasks(self) -> None:
        """Create the AO and AI tasks of write/read (bad channel names fail here, at open)."""
        from nidaqmx.constants import AcquisitionType, TaskMode, TerminalConfiguration

        def build() -> None:
            ao = self._task("ao")
            try:
                ao.ao_channels.add_ao_voltage_chan(self.ao_channel, min_val=self.ao_min_v, max_val=self.ao_max_v)
                ai = self._task("ai")
            except BaseException:
                ao.close()
                raise
            try:
                for physical in self.ai_channels.values():
                    ai.ai_channels.add_ai_voltage_chan(physical, terminal_config=TerminalConfiguration(self.terminal),
                                                       min_val=self.ai_min_v, max_val=self.ai_max_v)
                if self.mode == "hw-timed-single-point":
                    for task in (ao, ai):
                        task.timing.cfg_samp_clk_timing(self.rate_hz, sample_mode=AcquisitionType.HW_TIMED_SINGLE_POINT)
                elif self.mode == "ai-clocked":
                    ai.timing.cfg_samp_clk_timing(self.rate_hz, sample_mode=AcquisitionType.CONTINUOUS,
                                                  samps_per_chan=max(2, math.ceil(self.rate_hz * self.ai_buffer_s)))
                if self.mode in CLOCKED:
                    # DAQmx checks timing when a task is verified: a module that cannot run it fails
                    # here, at open, with DAQmx's own error, not at the first sample
                    ai_names = ", ".join(self.ai_channels.values())
                    for task, names in ((ao, self.ao_channel), (ai, ai_names)) if self.mode == "hw-timed-single-point" \
                            else ((ai, ai_names),):
                        task.control(TaskMode.TASK_VERIFY)
                        self._check_rate(task, names)
                self.version = ".".join(str(v) for v in ai._interpreter.driver_version)
            except BaseException:
                ao.close()
                ai.close()
                raise
            self._ao, self._ai = ao, ai

        self._call(f"creating the tasks for {self.ao_channel} and {', '.join(self.ai_channels.values())}", build,
                   retried=False)
        from nidaqmx.stream_readers import AnalogMultiChannelReader
        from nidaqmx.stream_writers import AnalogSingleChannelWriter

        self._writer = AnalogSingleChannelWriter(self._ao.out_stream, auto_start=True)
        self._reader = AnalogMultiChannelReader(self._ai.in_stream)
        self._reader.verify_array_shape = False  # the buffer is ours and fixed: no attribute query per sample
        self._loop_started = False

    def _check_rate(self, task: Any, channels: str) -> None:
        """Refuse a sample rate DAQmx coerced (a module that cannot run ``rate_hz`` exactly)."""
        actual = float(task.timing.samp_clk_rate)
        if not math.isclose(actual, self.rate_hz, rel_tol=1e-9):
            raise DeviceError(self.name, f"sample_rate_hz {self.rate_hz:g}: DAQmx runs the loop's sample clock of "
                                         f"{channels} at {actual:.6g} Hz (the rate the module can run); set "
                                         f"sample_rate_hz (and the rig's) to a rate it runs exactly")

    def _start_loop(self) -> None:
        if self._loop_started:
            return
        self._call("starting the AI task", self._ai.start)
        if self.mode == "hw-timed-single-point":  # ai-clocked: the AO is on demand, started by its writes
            self._call("starting the AO task", self._ao.start)
        self._loop_started = True

    def _stop_loop(self) -> None:
        # always, not only after _start_loop: an on-demand write auto-starts the AO task, and its
        # line stays reserved (DAQmx error -200022 for the play task) until the task stops
        for task in (self._ai, self._ao):
            if task is not None:
                self._call("stopping a task", task.stop, retried=False)
        self._loop_started = False

    def sample_clock_hz(self) -> float | None:
        """Hz of the sample clock that times write/read (None on demand: nothing does)."""
        return self.rate_hz if self.mode in CLOCKED else None

    def sample_clock(self) -> str:
        if self.mode == "hw-timed-single-point":
            return f"DAQmx hardware-timed single point at {self.rate_hz:g} Hz, Wait For Next Sample Clock"
        if self.mode == "ai-clocked":
            return (f"DAQmx continuous AI at {self.rate_hz:g} Hz on {', '.join(self.ai_channels.values())}, "
                    "read one sample a tick; AO on demand")
        return "none (on demand)"

    def wait_for_next_sample_clock(self) -> bool:
        """Wait for the DAQ's next sample clock (see the module docstring); True when DAQmx reports
        the loop late (the tick had already passed). Counted in :meth:`clock_stats`; the next
        :meth:`read` returns that tick's sample."""
        if self.mode == "ai-clocked":
            late = self._next_acquired_sample()
        elif self.mode == "hw-timed-single-point":
            late = self._wait_hwtsp()
        else:
            raise DeviceError(self.name, "mode 'on-demand' has no sample clock to wait for")
        self.samples += 1
        self.late += int(late)
        self._clock_taken = True
        return late

    def _next_acquired_sample(self) -> bool:
        """ai-clocked: the samples already acquired (late: the tick passed before the wait began; the
        newest is kept), else the next one the DAQ acquires (on time)."""
        from nidaqmx.constants import READ_ALL_AVAILABLE, FillMode

        self._start_loop()
        chans, buffer = len(self.ai_channels), self._ai_buffer
        # nidaqmx's readers ask DAQmx how many samples wait before reading them all (one more
        # round trip); DAQmx's own read of all available samples needs none
        interpreter, handle = self._ai._interpreter, self._ai._handle
        waiting = self._ai_backlog

        def acquired() -> int:
            return int(interpreter.read_analog_f64(handle, READ_ALL_AVAILABLE, 0.0, FillMode.GROUP_BY_SCAN_NUMBER.value,
                                                   waiting)[1])

        def next_sample() -> None:
            self._reader.read_one_sample(buffer, timeout=self.timeout_s + 1.0 / self.rate_hz)

        try:
            count = self._call("reading the acquired AI samples", acquired)
        except DeviceError as exc:
            if f"error {SAMPLES_NO_LONGER_AVAILABLE}:" not in str(exc):
                raise
            # the loop fell behind by more than the buffer: start the acquisition afresh (late)
            self._call("restarting the AI acquisition", self._ai.stop, retried=False)
            self._call("restarting the AI acquisition", self._ai.start, retried=False)
            self._call("reading the next acquired AI sample", next_sample)
            return True
        if count:
            buffer[:] = waiting[(count - 1) * chans:count * chans]
            return True
        self._call("waiting for the next acquired AI sample", next_sample)
        return False

    def _wait_hwtsp(self) -> bool:
        """hw-timed-single-point: DAQmx Wait For Next Sample Clock on the AI task."""
        self._start_loop()
        if self._stub is None and self._channel is not None:
            from nidaqmx._stubs import nidaqmx_pb2_grpc

            self._stub = nidaqmx_pb2_grpc.NiDAQmxStub(self._channel)

        def wait() -> bool:
            if self._stub is not None:
                from nidaqmx._stubs import nidaqmx_pb2

                reply = self._stub.WaitForNextSampleClock(
                    nidaqmx_pb2.WaitForNextSampleClockRequest(task=self._ai._handle, timeout=self.timeout_s))
                if reply.status < 0:
                    raise self._daq_error(int(reply.status), "", "WaitForNextSampleClock")
                return bool(reply.is_late)
            return self._local_wait()

        return self._call("waiting for the next sample clock", wait)

    def _local_wait(self) -> bool:
        """DAQmxWaitForNextSampleClock from the DAQmx C library nidaqmx loaded (no Python method exists)."""
        import ctypes

        from nidaqmx._lib import lib_importer

        function = lib_importer.windll.DAQmxWaitForNextSampleClock
        if function.argtypes is None:
            with function.arg_lock:
                if function.argtypes is None:
                    function.argtypes = [lib_importer.task_handle, ctypes.c_double, ctypes.POINTER(ctypes.c_uint)]
        is_late = ctypes.c_uint(0)
        code = function(self._ai._handle, self.timeout_s, ctypes.byref(is_late))
        if code < 0:
            raise self._daq_error(code, "", "DAQmxWaitForNextSampleClock")
        return bool(is_late.value)

    def clock_stats(self) -> dict[str, int]:
        """Sample clocks waited for and how many DAQmx reported late (the clocked modes)."""
        return {"samples": self.samples, "late": self.late}

    # -- device contract ------------------------------------------------------------------------------
    def identity(self) -> str:
        where = f"gRPC device server {self.address[0]}:{self.address[1]}" if self.address else "local"
        return (f"NI-DAQmx {self.version} ({where}): AO {self.ao_channel}, "
                f"AI {', '.join(f'{k}={v}' for k, v in self.ai_channels.items())}")

    def capabilities(self) -> dict[str, Any]:
        return {
            "driver": "ni-daqmx",
            "nidaqmx_driver_version": self.version,
            "ao_channel": self.ao_channel,
            "ai_channels": dict(self.ai_channels),
            "ao_range_v": [self.ao_min_v, self.ao_max_v],
            "ai_range_v": [self.ai_min_v, self.ai_max_v],
            "mode": self.mode,
            "sample_rate_hz": self.rate_hz,
            "clock": self.sample_clock(),
            "play": f"finite AO + AI on the start trigger {self.start_trigger}",
            "channels": {"output": "um", **({"current": "A"} if "current" in self.ai_channels else {}),
                         "input": "A (the AO command)"},
        }

    def _volts(self, amps: float) -> float:
        volts = float(amps) / self.gain_a_per_v
        if not (self.ao_min_v <= volts <= self.ao_max_v) or math.isnan(volts):
            raise DeviceError(self.name, f"{amps!r} A needs {volts:g} V, outside the AO range "
                                         f"{self.ao_min_v:g}..{self.ao_max_v:g} V")
        return volts

    def write(self, value: float) -> None:
        """Amplifier current, A: written as volts to the AO channel (goes out on the next sample clock
        in single point mode)."""
        volts = self._volts(value)
        if self.mode in CLOCKED:
            self._start_loop()
        self._call(f"writing {volts:g} V to {self.ao_channel}", lambda: self._writer.write_one_sample(volts,
                                                                                                    timeout=self.timeout_s))
        self._last_amps = float(value)

    def read(self) -> dict[str, float]:
        """``output`` um (and ``current`` A). In the clocked modes the sample of the tick last waited
        for; without a wait since the last read, it waits for the next tick first."""
        if self.mode in CLOCKED:
            if not self._clock_taken:
                self.wait_for_next_sample_clock()
            self._clock_taken = False
            if self.mode == "ai-clocked":  # the wait read the sample
                return self._physical(self._ai_buffer)
        self._call("reading the AI channels", lambda: self._reader.read_one_sample(self._ai_buffer,
                                                                                   timeout=self.timeout_s))
        return self._physical(self._ai_buffer)

    def _physical(self, volts: np.ndarray) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, name in enumerate(self.ai_channels):
            v = volts[k]
            out[name] = (v * self.output_um_per_v + self.output_offset_um) if name == "output" \
                else v / self.monitor_v_per_a
            if np.ndim(out[name]) == 0:
                out[name] = float(out[name])
        return out

    def stop(self, success: bool) -> None:
        """End of work. ``success=False`` makes safe: ramp the AO from the last command to ``rest``
        at ``slew_per_s`` in steps of ~10 ms, then stop the tasks."""
        if not success and self._ao is not None:
            start, span = self._last_amps, self.rest - self._last_amps
            duration_s = abs(span) / self.slew_per_s if self.slew_per_s > 0 else 0.0
            steps = max(1, min(200, math.ceil(duration_s / 0.01)))
            for k in range(1, steps + 1):
                if duration_s > 0:
                    time.sleep(duration_s / steps)
                self.write(start + span * k / steps)
        self._stop_loop()

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        """Generate ``waveform`` (A) once at ``rate_hz`` and acquire the AI channels on the same start
        trigger; returns ``time`` (s), ``input`` (A, as written), ``output`` (um) and ``current`` (A)."""
        from nidaqmx.constants import AcquisitionType, Edge, TerminalConfiguration
        from nidaqmx.stream_readers import AnalogMultiChannelReader
        from nidaqmx.stream_writers import AnalogSingleChannelWriter

        amps = np.asarray(waveform, dtype=np.float64).ravel()
        n = amps.size
        if n < 2 or not np.all(np.isfinite(amps)):
            raise DeviceError(self.name, "play needs at least 2 finite samples")
        volts = amps / self.gain_a_per_v
        if volts.min() < self.ao_min_v or volts.max() > self.ao_max_v:
            raise DeviceError(self.name, f"waveform needs {volts.min():g}..{volts.max():g} V, outside the AO range "
                                         f"{self.ao_min_v:g}..{self.ao_max_v:g} V")
        rate = float(rate_hz)
        self._stop_loop()  # the lines belong to one running task at a time
        self._clock_taken = False
        duration_s = n / rate
        # the generation's own length, and a margin for a slow start (an emulated plant compiling)
        self._rpc_deadline_s = self.timeout_s + self.rpc_margin_s + duration_s + self.play_margin_s
        tasks: list[Any] = []
        try:
            def arm() -> tuple[Any, Any]:
                ai = self._task("play-ai")
                tasks.append(ai)
                for physical in self.ai_channels.values():
                    ai.ai_channels.add_ai_voltage_chan(physical, terminal_config=TerminalConfiguration(self.terminal),
                                                       min_val=self.ai_min_v, max_val=self.ai_max_v)
                ai.timing.cfg_samp_clk_timing(rate, sample_mode=AcquisitionType.FINITE, samps_per_chan=n)
                actual = float(ai.timing.samp_clk_rate)
                if not math.isclose(actual, rate, rel_tol=1e-9):  # coerced: the AI would not match the AO
                    raise DeviceError(self.name, f"play at {rate:g} Hz: DAQmx runs the AI sample clock of "
                                                 f"{', '.join(self.ai_channels.values())} at {actual:.6g} Hz (the "
                                                 "rate the module can run); set the rig's sample_rate_hz to it")
                ai.triggers.start_trigger.cfg_dig_edge_start_trig(self.start_trigger, trigger_edge=Edge.RISING)
                ao = self._task("play-ao")
                tasks.append(ao)
                ao.ao_channels.add_ao_voltage_chan(self.ao_channel, min_val=self.ao_min_v, max_val=self.ao_max_v)
                ao.timing.cfg_samp_clk_timing(rate, sample_mode=AcquisitionType.FINITE, samps_per_chan=n)
                AnalogSingleChannelWriter(ao.out_stream, auto_start=False).write_many_sample(volts, timeout=self.timeout_s)
                ai.start()  # armed: it waits for the AO start trigger
                ao.start()
                return ai, ao

            ai, ao = self._call("arming the buffered AO/AI tasks", arm, retried=False)
            data = np.zeros((len(self.ai_channels), n), dtype=np.float64)
            reader = AnalogMultiChannelReader(ai.in_stream)
            reader.verify_array_shape = False
            read_timeout = duration_s + self.timeout_s + self.play_margin_s
            # not retried: a partial read cannot be asked again; a timeout here is the DAQ's own
            self._call(f"reading {n} samples", lambda: reader.read_many_sample(
                data, number_of_samples_per_channel=n, timeout=read_timeout), retried=False)
            self._call("waiting for the AO generation", lambda: ao.wait_until_done(timeout=self.timeout_s), retried=False)
        finally:
            self._rpc_deadline_s = self.timeout_s + self.rpc_margin_s
            for task in reversed(tasks):
                try:
                    task.close()
                except Exception:  # noqa: BLE001 - a task on a vanished server: the error above says so
                    pass
        self._last_amps = float(amps[-1])
        out = self._physical(data)
        return {"time": np.arange(n, dtype=np.float64) / rate, "input": amps, **out}

    def close(self) -> None:
        for task in (self._ai, self._ao):
            if task is not None:
                try:
                    task.close()
                except Exception:  # noqa: BLE001 - closing on a vanished server must not raise
                    pass
        self._ai = self._ao = None
        if self._raw_channel is not None:
            self._raw_channel.close()
            self._raw_channel = None

    def __enter__(self) -> NIDAQmxDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_device(settings: dict[str, Any]) -> NIDAQmxDevice:
    return NIDAQmxDevice(DRIVER.complete(settings))


SETTINGS = (
    Setting("url", str, required=True,
            doc="grpc://HOST:PORT of an NI gRPC Device Server (default port 31763), or local (NI-DAQmx on this PC)"),
    Setting("name", str, doc="device name in messages (default: ni-daqmx (url))"),
    Setting("ao_channel", str, default="cDAQ1Mod1/ao0", doc="AO physical channel driving the amplifier (NI 9263)"),
    Setting("ai_output_channel", str, default="cDAQ1Mod2/ai0", doc="AI physical channel of the displacement sensor (NI 9234)"),
    Setting("ai_current_channel", str, default="", doc="AI physical channel of the amplifier's current monitor ('' = none)"),
    Setting("ao_min_v", float, default=-10.0, doc="V, lowest AO voltage (NI 9263: -10)"),
    Setting("ao_max_v", float, default=10.0, doc="V, highest AO voltage (NI 9263: +10)"),
    Setting("ai_min_v", float, default=-5.0, doc="V, AI range low (NI 9234: -5)"),
    Setting("ai_max_v", float, default=5.0, doc="V, AI range high (NI 9234: +5)"),
    Setting("terminal_config", str, default="default", doc="AI terminal configuration: default, pseudodiff, diff, rse, nrse"),
    Setting("amplifier_gain_a_per_v", float, default=1.0, doc="A of amplifier output per V of AO"),
    Setting("output_um_per_v", float, default=1.0, doc="um of displacement per V at the output AI"),
    Setting("output_offset_um", float, default=0.0, doc="um at 0 V on the output AI"),
    Setting("current_monitor_v_per_a", float, default=1.0, doc="V at the current AI per A of amplifier output"),
    Setting("mode", str, default="on-demand",
            doc="per-sample write/read: on-demand (any module; the PC paces), hw-timed-single-point (an "
                "X Series board; not C Series modules) or ai-clocked (a cDAQ: the AI module's clock paces)"),
    Setting("sample_rate_hz", float, default=1000.0, doc="Hz, sample clock of the per-sample tasks (the rig's rate)"),
    Setting("ai_buffer_s", float, default=10.0, doc="s of samples DAQmx buffers in ai-clocked mode"),
    Setting("start_trigger", str, default="", doc="terminal the play AI task starts on ('' = /CHASSIS/ao/StartTrigger)"),
    Setting("timeout_s", float, default=1.0, doc="s, DAQmx timeout of each read, write and clock wait"),
    Setting("rpc_margin_s", float, default=2.0, doc="s added to timeout_s as the deadline of every gRPC call"),
    Setting("attempts", int, default=3, doc="tries per operation on timeouts"),
    Setting("backoff_s", float, default=DEFAULT_BACKOFF_S, doc="s before the first retry (doubles each retry)"),
    Setting("play_margin_s", float, default=5.0, doc="s added to a play's duration before its read gives up"),
    Setting("rest", float, default=0.0, doc="A, where stop(False) ramps to"),
    Setting("slew_per_s", float, default=100.0, doc="A/s, ramp rate of stop(False)"),
    Setting("emulated_ao_product", str, default="NI 9263", doc="emulator: product type of the AO module"),
    Setting("emulated_ai_product", str, default="NI 9234", doc="emulator: product type of the AI module"),
)

DRIVER = DriverSpec(
    name="ni-daqmx",
    roles=("actuator", "sensor", "player"),
    settings=SETTINGS,
    open=open_device,
    emulator=Lazy("drivers.emulators.ni_daqmx:start_emulator"),
    description="NI-DAQmx AO/AI (e.g. NI 9263 + NI 9234 in a cDAQ) through nidaqmx, local or an NI gRPC Device Server",
    transports=("grpc://", "local"),
    install_hint="" if nidaqmx_available() else INSTALL_HINT,
)
