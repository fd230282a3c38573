"""Emulator of an NI cDAQ chassis behind NI's gRPC Device Server: a real gRPC server on 127.0.0.1.

It speaks the ``nidaqmx_grpc.NiDAQmx`` service of the NI gRPC Device Server (``nidaqmx.proto``; the
stubs ship with the ``nidaqmx`` package in ``nidaqmx/_stubs``), so NI's own ``nidaqmx`` client runs
unchanged against it through ``nidaqmx.Task(grpc_options=GrpcSessionOptions(channel, name))``.

The chassis holds the modules the driver table names: the AO module of ``ao_channel`` and the AI
module of ``ai_output_channel``/``ai_current_channel``, of the products ``emulated_ao_product`` and
``emulated_ai_product``. The products in :data:`PRODUCTS` keep their specifications' limits:

* NI 9263 (AO, ``ao0..ao3``, +-10 V), NI 9215 (AI, ``ai0..ai3``, +-10 V, simultaneous SAR) and NI 9234
  (AI, ``ai0..ai3``, +-5 V, delta-sigma) are C Series modules: "C Series devices do not support
  hardware-timed single-point sample mode or Wait for Next Sample Clock" (NI-DAQmx Device
  Considerations, Timing Considerations for C Series Devices). A task with that sample mode fails
  when it is verified or started with -200077 (the DAQmx error for a property value the device does
  not support; NI's exact wording for this case was not found, the property named is our reading).
* The NI 9234 samples at fs = (fM / 256) / n, n = 1..31, fM = 13.1072 MHz (its internal master
  timebase): 51.2 kS/s, 25.6 kS/s, ... down to 1.652 kS/s (NI-9234 Specifications, Data Rate Range;
  NI USB-9234 User Guide, "Understanding NI USB-9234 Data Rates"). A rate between them is coerced up
  to the next one (NI KnowledgeBase, input delay and valid rates of the NI 9237/9234: "it will be
  coerced up to the next highest Data Rate"), which ``SampClk.Rate`` reads back; above 51.2 kS/s is
  refused with -200077 at verify or start.
* Any other product name is a generic DAQmx device (a PCIe/PXI multifunction DAQ: 4 lines, +-10 V
  AO, +-5 V AI, any rate, hardware-timed single point supported).

Any other physical channel is refused with DAQmx error -200170, as NI-DAQmx does. Behind the modules
is a :class:`~drivers.base.World`:

* an AO sample (volts) -> amps through ``amplifier_gain_a_per_v`` -> ``world.command(amps)``;
* an AI sample: ``world.read("output")`` um -> volts through ``output_um_per_v``/``output_offset_um``,
  ``world.read("current")`` A -> volts through ``current_monitor_v_per_a``; clipped to the module's
  input range as a real ADC clips;
* a buffered (finite) AO task started while an AI task waits on its start trigger runs the whole
  waveform through ``world.play`` and the AI task acquires what the world recorded;
* a continuous AI task without a trigger acquires sample k at ``t0 + k / rate`` (wall clock) into a
  buffer of ``samps_per_chan`` samples: a read waits until its samples are acquired and returns the
  world as it is then (the world moves only when the AO is written, so a backlog repeats the present
  value); a read of -1 samples returns those already acquired at once (none: none); ``AvailSampPerChan``
  is the backlog; a backlog larger than the buffer fails the next read with -200279, as DAQmx does
  when unread samples were overwritten.

Each started task has a sample clock of its own, paced by the wall clock at the configured rate:
``WaitForNextSampleClock`` sleeps until the next tick and answers ``is_late = True`` (at once, catching
up to the latest tick) when the tick it should have waited for had already passed; a buffered read
waits until its samples have been "acquired" in wall-clock time, or fails with -200284 after its
timeout.

Errors go out as the device server sends them: a failed DAQmx call ends the RPC with a non-OK status,
the error text as details and the DAQmx error code in the ``ni-error`` trailing metadata (which the
client turns into ``nidaqmx.DaqError``). Methods not listed in :data:`IMPLEMENTED` answer UNIMPLEMENTED
(the generated servicer's default).

Fault injection for tests: :meth:`stall_next` (the next calls hang past the client's deadline),
:meth:`error_next` (the next call fails with a given DAQmx error code) and :meth:`disconnect` (the
server stops: the connection is gone). :attr:`calls` lists every RPC method name received.
"""

from __future__ import annotations

import math
import re
import threading
import time
from concurrent import futures
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.base import World

# DAQmx error codes the emulator answers with (nidaqmx.error_codes.DAQmxErrors) and NI's texts.
ERROR_TEXT: dict[int, str] = {
    -200170: "Physical channel specified does not exist on this device.",
    -200220: "Device identifier is invalid.",
    -200088: "Task specified is invalid or does not exist.",
    -200089: "Task name specified conflicts with an existing task name.",
    -200077: "Requested value is not a supported value for this property.",
    -200284: "Some or all of the samples requested have not yet been acquired.",
    -200474: "Specified operation did not complete, because the specified timeout expired.",
    -200479: "Specified operation cannot be performed while the task is running.",
    -200561: "Attempted to write analog data that is too large or too small.",
    -200863: "Wait For Next Sample Clock is not supported by this task: it is not hardware-timed single point.",
    -200462: "Generation cannot be started, because the output buffer is empty.",
    -200022: "Resource requested by this task has already been reserved by a different task.",
    -200279: "Attempted to read samples that are no longer available. The requested sample was previously "
             "available, but has since been overwritten.",
    -200428: "Value passed to the Task/Channels In control is invalid.",
}
FINITE, CONTINUOUS, HW_TIMED_SINGLE_POINT = 10178, 10123, 12522  # nidaqmx.constants.AcquisitionType
MODE_NAMES = {FINITE: "DAQmx_Val_FiniteSamps", CONTINUOUS: "DAQmx_Val_ContSamps",
              HW_TIMED_SINGLE_POINT: "DAQmx_Val_HWTimedSinglePoint"}
SAMP_CLK_RATE = 0x1344  # DAQmx_SampClk_Rate
AVAIL_SAMP_PER_CHAN = 0x1223  # DAQmx_Read_AvailSampPerChan
TASK_VERIFY, TASK_COMMIT = 2, 3  # nidaqmx.constants.TaskMode


@dataclass(frozen=True)
class Product:
    """What the emulator keeps of a module's specifications."""

    kind: str  # "ao" | "ai"
    lines: int
    range_v: float  # +- V
    c_series: bool  # no hardware-timed single point, no Wait For Next Sample Clock
    max_rate_hz: float
    #: delta-sigma: the rates are (fM / 256) / n, n = 1..this; 0 = any rate up to max_rate_hz
    divisors: int = 0

    def rate(self, requested_hz: float) -> float:
        """The rate DAQmx runs for ``requested_hz``: a delta-sigma module's next rate up."""
        if not self.divisors or requested_hz > self.max_rate_hz:
            return requested_hz
        n = max(1, min(self.divisors, math.floor(self.max_rate_hz / requested_hz * (1 + 1e-12))))
        return self.max_rate_hz / n


#: the modules emulated with their specifications' limits (see the module docstring)
PRODUCTS: dict[str, Product] = {
    "NI 9263": Product("ao", 4, 10.0, True, 100e3),  # 100 kS/s/ch
    "NI 9215": Product("ai", 4, 10.0, True, 100e3),  # 100 kS/s/ch, simultaneous SAR
    "NI 9234": Product("ai", 4, 5.0, True, 13.1072e6 / 256, divisors=31),  # 51.2 kS/s / n
}


def product_of(name: str, kind: str) -> Product:
    """The product's limits; a product not in :data:`PRODUCTS` is a generic multifunction DAQ."""
    known = PRODUCTS.get(name)
    if known is not None and known.kind == kind:
        return known
    return Product(kind, 4, 10.0 if kind == "ao" else 5.0, False, math.inf)
GROUP_BY_CHANNEL = 0  # nidaqmx.constants.FillMode.GROUP_BY_CHANNEL
DRIVER_VERSION = (24, 8, 0)  # what GetSystemInfoAttributeUInt32 reports as the NI-DAQmx version

#: The RPC methods this emulator implements; every other one answers UNIMPLEMENTED.
IMPLEMENTED = (
    "GetSystemInfoAttributeUInt32", "GetErrorString", "CreateTask", "ClearTask", "StartTask", "StopTask",
    "TaskControl", "IsTaskDone", "WaitUntilTaskDone", "GetTaskAttributeString", "GetTaskAttributeUInt32",
    "GetReadAttributeUInt32", "GetWriteAttributeUInt32", "GetDeviceAttributeString",
    "CreateAOVoltageChan", "CreateAIVoltageChan", "CfgSampClkTiming", "CfgDigEdgeStartTrig",
    "GetTimingAttributeDouble",
    "WriteAnalogScalarF64", "WriteAnalogF64", "ReadAnalogScalarF64", "ReadAnalogF64", "WaitForNextSampleClock",
)


class DAQmxFault(Exception):
    """A DAQmx error the emulated driver returns for the current call."""

    def __init__(self, code: int, detail: str = ""):
        self.code = code
        text = ERROR_TEXT.get(code, "NI-DAQmx error.")
        super().__init__(f"{text} {detail}".strip())


@dataclass
class Channel:
    kind: str  # "ao" | "ai"
    physical: str  # e.g. "cDAQ1Mod1/ao0"
    name: str
    min_v: float
    max_v: float
    source: str = ""  # ai: the world channel it measures ("output" | "current")


@dataclass
class Task:
    name: str
    channels: list[Channel] = field(default_factory=list)
    mode: int | None = None  # None: on demand (no timing configured)
    rate_hz: float = 0.0
    samps_per_chan: int = 0
    start_trigger: str = ""  # a terminal such as "/cDAQ1/ao/StartTrigger"; "" = start at once
    running: bool = False
    armed: bool = False  # started, waiting for its start trigger
    t0: float = 0.0  # wall-clock time of the first tick (the start or the trigger)
    last_tick: int = 0  # WaitForNextSampleClock's last tick
    buffer: np.ndarray | None = None  # AO: volts, channels x samples
    data: np.ndarray | None = None  # AI buffered: volts, channels x samples
    read_pos: int = 0

    def kind(self) -> str:
        return self.channels[0].kind if self.channels else ""


def _module(physical: str) -> tuple[str, str]:
    """``cDAQ1Mod1/ao0`` -> (``cDAQ1Mod1``, ``ao0``)."""
    device, _, line = physical.strip().strip("/").partition("/")
    return device, line


def _chassis(device: str) -> str:
    """``cDAQ1Mod1`` -> ``cDAQ1`` (the chassis whose timing engines route the triggers)."""
    return re.sub(r"Mod\d+$", "", device)


class NIDAQmxEmulator:
    """A running emulated cDAQ behind a gRPC device server; ``url`` is ``grpc://127.0.0.1:PORT``."""

    def __init__(self, settings: dict[str, Any], world: World, *, workers: int = 8):
        try:
            import grpc

            from nidaqmx._stubs import nidaqmx_pb2, nidaqmx_pb2_grpc
        except ImportError:  # refused like a bad setting: one line with the fix
            raise ValueError("the NI-DAQmx emulator needs the nidaqmx package; "
                             "pip install 'hilbench[nidaqmx]'") from None

        self._grpc = grpc
        self.pb = nidaqmx_pb2
        self.world = world
        self.gain_a_per_v = float(settings["amplifier_gain_a_per_v"])
        self.monitor_v_per_a = float(settings["current_monitor_v_per_a"])
        self.output_um_per_v = float(settings["output_um_per_v"])
        self.output_offset_um = float(settings["output_offset_um"])
        ao_device, _ = _module(str(settings["ao_channel"]))
        ai_device, _ = _module(str(settings["ai_output_channel"]))
        if not ao_device or not ai_device:
            raise ValueError(f"ao_channel {settings['ao_channel']!r} / ai_output_channel "
                             f"{settings['ai_output_channel']!r}: expected DEVICE/aoN and DEVICE/aiN")
        # the modules in the chassis: device name -> (product type, its limits)
        ao_product, ai_product = str(settings["emulated_ao_product"]), str(settings["emulated_ai_product"])
        self.modules: dict[str, tuple[str, Product]] = {
            ao_device: (ao_product, product_of(ao_product, "ao")),
            ai_device: (ai_product, product_of(ai_product, "ai")),
        }
        # which world channel each AI line measures
        self.sources: dict[str, str] = {str(settings["ai_output_channel"]).strip("/"): "output"}
        if str(settings.get("ai_current_channel") or ""):
            self.sources[str(settings["ai_current_channel"]).strip("/")] = "current"

        self.tasks: dict[str, Task] = {}
        self.calls: list[str] = []  # every RPC method received, in order
        self.ao_writes: list[float] = []  # every AO value written on demand or single point, V
        self.late_ticks = 0  # WaitForNextSampleClock answers with is_late = True
        self._lock = threading.RLock()
        self._stall = 0
        self._stall_s = 0.0
        self._error: int | None = None
        self._unnamed = 0

        class Servicer(nidaqmx_pb2_grpc.NiDAQmxServicer):
            pass

        for method in IMPLEMENTED:
            setattr(Servicer, method, self._rpc(method))
        self._server = grpc.server(futures.ThreadPoolExecutor(max_workers=workers))
        nidaqmx_pb2_grpc.add_NiDAQmxServicer_to_server(Servicer(), self._server)
        port = self._server.add_insecure_port("127.0.0.1:0")
        if not port:
            raise OSError("the NI-DAQmx emulator could not bind a port on 127.0.0.1")
        self.port = port
        self.url = f"grpc://127.0.0.1:{port}"
        self._server.start()

    # -- plumbing ---------------------------------------------------------------------------------------
    def _rpc(self, method: str) -> Any:
        handler = getattr(self, f"_{method}")
        grpc = self._grpc

        def call(_servicer: Any, request: Any, context: Any) -> Any:
            with self._lock:
                self.calls.append(method)
                stall, error = self._stall > 0, self._error
                if stall:
                    self._stall -= 1
                self._error = None
            if stall:  # hang past the client's deadline (it gives up; the reply is never read)
                time.sleep(self._stall_s)
                return getattr(self.pb, f"{method}Response")()
            try:
                if error is not None:
                    raise DAQmxFault(error, "(injected)")
                return handler(request)
            except DAQmxFault as fault:
                # the device server's convention: non-OK status, text as details, code in ni-error
                context.set_trailing_metadata((("ni-error", str(fault.code)),))
                context.abort(grpc.StatusCode.UNKNOWN, str(fault))

        call.__name__ = method
        return call

    def _task(self, request: Any) -> Task:
        name = request.task.name
        task = self.tasks.get(name)
        if task is None:
            raise DAQmxFault(-200088, f"Task Name: {name}")
        return task

    def _tick_s(self, task: Task) -> float:
        return 1.0 / task.rate_hz

    # -- system ----------------------------------------------------------------------------------------
    def _GetSystemInfoAttributeUInt32(self, request: Any) -> Any:
        versions = {0x1272: DRIVER_VERSION[0], 0x1923: DRIVER_VERSION[1], 0x2F22: DRIVER_VERSION[2]}
        if request.attribute_raw not in versions:
            raise DAQmxFault(-200077, f"attribute 0x{request.attribute_raw:X}")
        return self.pb.GetSystemInfoAttributeUInt32Response(value=versions[request.attribute_raw])

    def _GetErrorString(self, request: Any) -> Any:
        return self.pb.GetErrorStringResponse(error_string=ERROR_TEXT.get(request.error_code, ""))

    def _GetDeviceAttributeString(self, request: Any) -> Any:
        module = self.modules.get(request.device_name)
        if module is None:
            raise DAQmxFault(-200220, f"Device: {request.device_name}")
        if request.attribute_raw == 0x0631:  # DAQmx_Dev_ProductType
            return self.pb.GetDeviceAttributeStringResponse(value=module[0])
        raise DAQmxFault(-200077, f"attribute 0x{request.attribute_raw:X}")

    # -- tasks -----------------------------------------------------------------------------------------
    def _CreateTask(self, request: Any) -> Any:
        with self._lock:
            name = request.session_name
            if not name:
                name = f"_unnamedTask<{self._unnamed}>"
                self._unnamed += 1
            existing = name in self.tasks
            # session.proto: 1 = INITIALIZE_NEW (must be new), 2 = ATTACH_TO_EXISTING (must exist)
            if existing and request.initialization_behavior == 1:
                raise DAQmxFault(-200089, f"Task Name: {name}")
            if not existing and request.initialization_behavior == 2:
                raise DAQmxFault(-200088, f"Task Name: {name}")
            if not existing:
                self.tasks[name] = Task(name)
            from session_pb2 import Session

            return self.pb.CreateTaskResponse(task=Session(name=name), new_session_initialized=not existing)

    def _ClearTask(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            task.running = task.armed = False
            del self.tasks[task.name]
        return self.pb.ClearTaskResponse()

    def _GetTaskAttributeString(self, request: Any) -> Any:
        task = self._task(request)
        values = {0x1276: task.name,  # DAQmx_Task_Name
                  0x1273: ", ".join(c.name for c in task.channels),  # DAQmx_Task_Channels
                  0x230E: ", ".join(sorted({_module(c.physical)[0] for c in task.channels}))}  # Task_Devices
        if request.attribute_raw not in values:
            raise DAQmxFault(-200077, f"attribute 0x{request.attribute_raw:X}")
        return self.pb.GetTaskAttributeStringResponse(value=values[request.attribute_raw])

    def _GetTaskAttributeUInt32(self, request: Any) -> Any:
        task = self._task(request)
        values = {0x2181: len(task.channels),  # DAQmx_Task_NumChans
                  0x29BA: len({_module(c.physical)[0] for c in task.channels})}  # DAQmx_Task_NumDevices
        if request.attribute_raw not in values:
            raise DAQmxFault(-200077, f"attribute 0x{request.attribute_raw:X}")
        return self.pb.GetTaskAttributeUInt32Response(value=values[request.attribute_raw])

    def _GetReadAttributeUInt32(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if request.attribute_raw == 0x217B:  # DAQmx_Read_NumChans
                return self.pb.GetReadAttributeUInt32Response(value=len(task.channels))
            if request.attribute_raw == AVAIL_SAMP_PER_CHAN:
                return self.pb.GetReadAttributeUInt32Response(value=max(0, self._acquired(task) - task.read_pos))
        raise DAQmxFault(-200077, f"attribute 0x{request.attribute_raw:X}")

    def _GetTimingAttributeDouble(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if request.attribute_raw == SAMP_CLK_RATE and task.mode is not None:
                return self.pb.GetTimingAttributeDoubleResponse(value=task.rate_hz)
        raise DAQmxFault(-200077, f"attribute 0x{request.attribute_raw:X}")

    def _acquired(self, task: Task) -> int:
        """Samples a started hardware-timed AI task has acquired by now (sample 0 at its start)."""
        if not task.running or task.mode not in (FINITE, CONTINUOUS):
            return 0
        count = int((time.monotonic() - task.t0) * task.rate_hz) + 1
        return min(count, task.data.shape[1]) if task.data is not None else count

    def _verify(self, task: Task) -> None:
        """What DAQmx checks when a task is verified or started: the timing its modules can run."""
        for device in sorted({_module(c.physical)[0] for c in task.channels}):
            name, product = self.modules[device]
            if task.mode == HW_TIMED_SINGLE_POINT and product.c_series:
                raise DAQmxFault(-200077, f"Property: DAQmx_SampQuant_SampMode Requested Value: "
                                          f"{MODE_NAMES[HW_TIMED_SINGLE_POINT]} You Can Select: "
                                          f"{MODE_NAMES[FINITE]}, {MODE_NAMES[CONTINUOUS]} Device: {device} ({name}) "
                                          f"Task Name: {task.name}")
            if task.mode is not None and task.rate_hz > product.max_rate_hz:
                raise DAQmxFault(-200077, f"Property: DAQmx_SampClk_Rate Requested Value: {task.rate_hz:g} "
                                          f"Valid Values End with: {product.max_rate_hz:g} Device: {device} "
                                          f"({name}) Task Name: {task.name}")

    def _GetWriteAttributeUInt32(self, request: Any) -> Any:
        task = self._task(request)
        if request.attribute_raw == 0x217E:  # DAQmx_Write_NumChans
            return self.pb.GetWriteAttributeUInt32Response(value=len(task.channels))
        raise DAQmxFault(-200077, f"attribute 0x{request.attribute_raw:X}")

    def _add_channel(self, request: Any, kind: str) -> None:
        task = self._task(request)
        if task.running or task.armed:
            raise DAQmxFault(-200479, f"Task Name: {task.name}")
        for physical in [p.strip().strip("/") for p in request.physical_channel.split(",") if p.strip()]:
            device, line = _module(physical)
            module = self.modules.get(device)
            if module is None:
                raise DAQmxFault(-200220, f"Device: {device} Channel Name: {physical}")
            product, spec = module
            number = line[len(kind):] if line.startswith(kind) else ""
            if spec.kind != kind or not number.isdigit() or int(number) >= spec.lines:
                raise DAQmxFault(-200170, f"Physical Channel Name: {physical} Device: {device} ({product})")
            if task.channels and task.channels[0].kind != kind:
                raise DAQmxFault(-200428, "a task holds channels of one kind")
            for other in self.tasks.values():  # a line belongs to one running task at a time
                if other is not task and (other.running or other.armed) and any(c.physical == physical
                                                                                  for c in other.channels):
                    raise DAQmxFault(-200022, f"Channel: {physical} Task Name: {other.name}")
            name = request.name_to_assign_to_channel or physical
            task.channels.append(Channel(kind, physical, name, request.min_val, request.max_val,
                                         self.sources.get(physical, "")))

    def _CreateAOVoltageChan(self, request: Any) -> Any:
        with self._lock:
            self._add_channel(request, "ao")
        return self.pb.CreateAOVoltageChanResponse()

    def _CreateAIVoltageChan(self, request: Any) -> Any:
        with self._lock:
            self._add_channel(request, "ai")
        return self.pb.CreateAIVoltageChanResponse()

    def _CfgSampClkTiming(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if task.running or task.armed:
                raise DAQmxFault(-200479, f"Task Name: {task.name}")
            if request.sample_mode_raw not in (FINITE, CONTINUOUS, HW_TIMED_SINGLE_POINT):
                raise DAQmxFault(-200077, f"Property: DAQmx_SampQuant_SampMode Requested Value: {request.sample_mode_raw}")
            if not (request.rate > 0 and math.isfinite(request.rate)):
                raise DAQmxFault(-200077, f"Property: DAQmx_SampClk_Rate Requested Value: {request.rate}")
            if request.sample_mode_raw == CONTINUOUS and task.kind() == "ao":
                # a regenerating AO buffer is not emulated: refused rather than played wrongly
                raise DAQmxFault(-200077, "Property: DAQmx_SampQuant_SampMode (continuous AO is not emulated)")
            task.mode = request.sample_mode_raw
            # a rate the modules cannot run is coerced up (delta-sigma); too high fails at verify
            task.rate_hz = max(self.modules[_module(c.physical)[0]][1].rate(float(request.rate))
                               for c in task.channels) if task.channels else float(request.rate)
            task.samps_per_chan = int(request.samps_per_chan)
        return self.pb.CfgSampClkTimingResponse()

    def _CfgDigEdgeStartTrig(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            source = request.trigger_source.strip()
            if not re.fullmatch(r"/[^/]+/ao/StartTrigger", source):
                raise DAQmxFault(-200077, f"Property: DAQmx_DigEdge_StartTrig_Src Requested Value: {source} "
                                          "(the emulator routes /CHASSIS/ao/StartTrigger only)")
            task.start_trigger = source
        return self.pb.CfgDigEdgeStartTrigResponse()

    def _start(self, task: Task) -> None:
        if task.running or task.armed:
            return
        if not task.channels:
            raise DAQmxFault(-200428, f"Task Name: {task.name} has no channels")
        self._verify(task)
        now = time.monotonic()
        task.read_pos, task.last_tick = 0, 0
        if task.kind() == "ai" and task.mode in (FINITE, CONTINUOUS) and task.start_trigger:
            task.armed = True  # waits for the AO task whose start trigger it names
            return
        if task.kind() == "ao" and task.mode == FINITE:
            if task.buffer is None or task.buffer.shape[1] == 0:
                raise DAQmxFault(-200462, f"Task Name: {task.name}")
            self._generate(task, now)
        elif task.kind() == "ai" and task.mode == FINITE:
            values = self._measure(task)  # no trigger: the world as it is, held for the acquisition
            task.data = np.repeat(values[:, None], task.samps_per_chan, axis=1)
        task.running, task.t0 = True, now

    def _generate(self, task: Task, now: float) -> None:
        """A finite AO generation: the waveform through the world; armed AI tasks acquire it."""
        n = task.buffer.shape[1]
        amps = task.buffer[0] * self.gain_a_per_v
        try:
            recorded = self.world.play(amps, task.rate_hz)
        except ValueError as exc:  # the world refuses the rate (a simulated plant runs at its own)
            raise DAQmxFault(-200077, f"Property: DAQmx_SampClk_Rate Requested Value: {task.rate_hz:g} ({exc})") from None
        chassis = _chassis(_module(task.channels[0].physical)[0])
        for other in self.tasks.values():
            if other.armed and other.start_trigger == f"/{chassis}/ao/StartTrigger":
                rows = []
                for c in other.channels:
                    series = np.asarray(recorded.get(c.source, np.full(n, np.nan)), dtype=np.float64)[:n]
                    rows.append(self._to_volts(c, series))
                count = other.samps_per_chan if other.mode == FINITE else n
                data = np.vstack(rows)
                if data.shape[1] < count:  # the AI acquires past the end of the waveform: the last value
                    data = np.hstack([data, np.repeat(data[:, -1:], count - data.shape[1], axis=1)])
                other.data, other.armed, other.running, other.t0 = data[:, :count], False, True, now

    def _to_volts(self, channel: Channel, value: np.ndarray | float) -> np.ndarray:
        value = np.asarray(value, dtype=np.float64)
        if channel.source == "output":
            volts = (value - self.output_offset_um) / self.output_um_per_v
        elif channel.source == "current":
            volts = value * self.monitor_v_per_a
        else:
            volts = np.zeros_like(value)  # an unconnected input reads 0 V
        range_v = self.modules[_module(channel.physical)[0]][1].range_v
        return np.clip(np.nan_to_num(volts, nan=0.0), -range_v, range_v)  # the ADC clips at its range

    def _measure(self, task: Task) -> np.ndarray:
        return np.array([float(self._to_volts(c, self.world.read(c.source) if c.source else 0.0))
                         for c in task.channels])

    def _StartTask(self, request: Any) -> Any:
        with self._lock:
            self._start(self._task(request))
        return self.pb.StartTaskResponse()

    def _StopTask(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            task.running = task.armed = False
        return self.pb.StopTaskResponse()

    def _TaskControl(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if request.action_raw == 0:  # START
                self._start(task)
            elif request.action_raw in (TASK_VERIFY, TASK_COMMIT):
                self._verify(task)
            elif request.action_raw in (1, 6):  # STOP, ABORT
                task.running = task.armed = False
        return self.pb.TaskControlResponse()

    def _done(self, task: Task) -> bool:
        if not task.running or task.mode != FINITE:
            return not task.running
        return time.monotonic() >= task.t0 + task.samps_per_chan / task.rate_hz

    def _IsTaskDone(self, request: Any) -> Any:
        with self._lock:
            return self.pb.IsTaskDoneResponse(is_task_done=self._done(self._task(request)))

    def _WaitUntilTaskDone(self, request: Any) -> Any:
        deadline = time.monotonic() + max(0.0, request.time_to_wait)
        while True:
            with self._lock:
                if self._done(self._task(request)):
                    return self.pb.WaitUntilTaskDoneResponse()
            if time.monotonic() >= deadline:
                raise DAQmxFault(-200474)
            time.sleep(0.002)

    # -- data ------------------------------------------------------------------------------------------
    def _check_ao(self, task: Task, volts: np.ndarray) -> None:
        for c, row in zip(task.channels, np.atleast_2d(volts)):
            if row.size and (np.nanmin(row) < c.min_v - 1e-9 or np.nanmax(row) > c.max_v + 1e-9
                             or not np.all(np.isfinite(row))):
                raise DAQmxFault(-200561, f"Channel Name: {c.name} (min {c.min_v:g} V, max {c.max_v:g} V)")

    def _WriteAnalogScalarF64(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if task.kind() != "ao" or len(task.channels) != 1:
                raise DAQmxFault(-200428, f"Task Name: {task.name}")
            self._check_ao(task, np.array([[request.value]]))
            if task.mode in (FINITE, CONTINUOUS):
                raise DAQmxFault(-200077, "a scalar write needs an on-demand or hardware-timed single-point task")
            self._start(task)  # on demand: auto start; single point: the value goes out from now on
            self.ao_writes.append(float(request.value))
            self.world.command(float(request.value) * self.gain_a_per_v)
        return self.pb.WriteAnalogScalarF64Response()

    def _WriteAnalogF64(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if task.kind() != "ao":
                raise DAQmxFault(-200428, f"Task Name: {task.name}")
            if task.running:
                raise DAQmxFault(-200479, f"Task Name: {task.name}")
            n, chans = int(request.num_samps_per_chan), len(task.channels)
            data = np.asarray(request.write_array, dtype=np.float64)
            if data.size != n * chans:
                raise DAQmxFault(-200077, f"write_array has {data.size} values for {n} x {chans}")
            volts = data.reshape(chans, n) if request.data_layout_raw == GROUP_BY_CHANNEL else data.reshape(n, chans).T
            self._check_ao(task, volts)
            if task.mode == HW_TIMED_SINGLE_POINT or task.mode is None:
                for v in volts[0]:
                    self.world.command(float(v) * self.gain_a_per_v)
                    self.ao_writes.append(float(v))
            else:
                task.buffer = volts.copy()
                if task.mode == FINITE and task.samps_per_chan and n != task.samps_per_chan:
                    task.samps_per_chan = n  # the buffer is what a finite generation plays
            if request.auto_start:
                self._start(task)
        return self.pb.WriteAnalogF64Response(samps_per_chan_written=n)

    def _ReadAnalogScalarF64(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if task.kind() != "ai" or len(task.channels) != 1:
                raise DAQmxFault(-200428, f"Task Name: {task.name}")
            if task.mode in (FINITE, CONTINUOUS):
                raise DAQmxFault(-200077, "a scalar read needs an on-demand or hardware-timed single-point task")
            self._start(task)
            return self.pb.ReadAnalogScalarF64Response(value=float(self._measure(task)[0]))

    def _ReadAnalogF64(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if task.kind() != "ai":
                raise DAQmxFault(-200428, f"Task Name: {task.name}")
            chans, n = len(task.channels), int(request.num_samps_per_chan)
            if task.mode is None or task.mode == HW_TIMED_SINGLE_POINT:
                self._start(task)
                if n not in (1, -1):
                    raise DAQmxFault(-200077, "a single-point task reads one sample per channel")
                values = self._measure(task)
                return self.pb.ReadAnalogF64Response(read_array=values.tolist(), samps_per_chan_read=1)
            own_clock = task.mode == CONTINUOUS and not task.start_trigger
            if n < 0 and not own_clock:
                n = (task.samps_per_chan - task.read_pos) if task.mode == FINITE else 0
            if n * chans > request.array_size_in_samps:
                raise DAQmxFault(-200229, f"{n} x {chans} samples into an array of {request.array_size_in_samps}")
        if own_clock:
            return self._read_continuous(request, n)
        deadline = time.monotonic() + max(0.0, request.timeout)
        while True:
            with self._lock:
                task = self._task(request)
                if task.running and task.data is not None:
                    acquired = min(task.data.shape[1], int((time.monotonic() - task.t0) * task.rate_hz) + 1)
                    if acquired >= task.read_pos + n:
                        block = task.data[:, task.read_pos:task.read_pos + n]
                        task.read_pos += n
                        array = block if request.fill_mode_raw == GROUP_BY_CHANNEL else block.T
                        return self.pb.ReadAnalogF64Response(read_array=array.ravel().tolist(), samps_per_chan_read=n)
                    if task.read_pos + n > task.data.shape[1]:
                        raise DAQmxFault(-200284, f"{n} samples asked after {task.read_pos} of a "
                                                  f"{task.data.shape[1]}-sample acquisition")
            if time.monotonic() >= deadline:
                raise DAQmxFault(-200284, f"Task Name: {task.name}")
            time.sleep(0.002)

    def _read_continuous(self, request: Any, n: int) -> Any:
        """A continuous acquisition on the task's own sample clock (see the module docstring)."""
        deadline = time.monotonic() + max(0.0, request.timeout)
        while True:
            with self._lock:
                task = self._task(request)
                self._start(task)  # a read auto-starts a task that is not running, as DAQmx does
                acquired = self._acquired(task)
                if acquired - task.read_pos > max(1, task.samps_per_chan):
                    raise DAQmxFault(-200279, f"{acquired - task.read_pos} samples behind with a buffer of "
                                              f"{task.samps_per_chan} Task Name: {task.name}")
                count = (acquired - task.read_pos) if n < 0 else n
                if count * len(task.channels) > request.array_size_in_samps:
                    raise DAQmxFault(-200229, f"{count} x {len(task.channels)} samples into an array of "
                                              f"{request.array_size_in_samps}")
                if acquired >= task.read_pos + count:
                    values = self._measure(task)
                    task.read_pos += count
                    block = np.repeat(values[:, None], count, axis=1)
                    array = block if request.fill_mode_raw == GROUP_BY_CHANNEL else block.T
                    return self.pb.ReadAnalogF64Response(read_array=array.ravel().tolist(), samps_per_chan_read=count)
                wake = task.t0 + (task.read_pos + count - 1) / task.rate_hz
            if time.monotonic() >= deadline:
                raise DAQmxFault(-200284, f"Task Name: {task.name}")
            time.sleep(max(0.0, min(wake, deadline) - time.monotonic()))

    def _WaitForNextSampleClock(self, request: Any) -> Any:
        with self._lock:
            task = self._task(request)
            if task.mode != HW_TIMED_SINGLE_POINT:
                raise DAQmxFault(-200863, f"Task Name: {task.name}")
            self._start(task)
            tick = self._tick_s(task)
            now = time.monotonic()
            latest = int((now - task.t0) / tick)  # the last tick that has passed
            wanted = task.last_tick + 1
            late = latest >= wanted
            if late:  # the tick it should have waited for has gone by: say so and catch up
                task.last_tick = latest
                self.late_ticks += 1
                return self.pb.WaitForNextSampleClockResponse(is_late=True)
            task.last_tick = wanted
            wake = task.t0 + wanted * tick
        if wake - now > request.timeout >= 0:
            time.sleep(request.timeout)
            raise DAQmxFault(-200474, f"Task Name: {request.task.name}")
        time.sleep(max(0.0, wake - time.monotonic()))
        return self.pb.WaitForNextSampleClockResponse(is_late=False)

    # -- fault injection and lifetime ---------------------------------------------------------------------
    def stall_next(self, calls: int = 1, seconds: float = 1.0) -> None:
        """The next ``calls`` RPCs hang for ``seconds`` (past the client's deadline) before answering."""
        with self._lock:
            self._stall, self._stall_s = calls, seconds

    def error_next(self, code: int) -> None:
        """The next RPC fails with DAQmx error ``code`` (e.g. -200170)."""
        with self._lock:
            self._error = int(code)

    def disconnect(self) -> None:
        """Stop serving: calls in flight are cancelled and new connections refused."""
        self._server.stop(grace=None)

    def close(self) -> None:
        self._server.stop(grace=0.5).wait(2.0)

    def __enter__(self) -> NIDAQmxEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_emulator(settings: dict[str, Any], world: World) -> NIDAQmxEmulator:
    """Start the emulator for a driver table (``hilbench emulate`` and the tests call this)."""
    return NIDAQmxEmulator(settings, world)
