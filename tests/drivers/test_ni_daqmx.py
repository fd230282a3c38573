"""Protocol tests of the ni-daqmx driver: NI's real ``nidaqmx`` client against the emulated NI gRPC
Device Server (a real gRPC server on 127.0.0.1, ``drivers/emulators/ni_daqmx.py``).

They read like the NI-DAQmx API: which tasks are created with which channels and timing, which
RPCs the client sends, how volts become amps and micrometres, what the sample clock does. The
tests at the end need no nidaqmx: the driver imports without it and says how to install it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.base import DeviceError, DeviceLost, DeviceTimeout

REPO = Path(__file__).resolve().parents[2]
TEMPLATE = REPO / "configs" / "templates" / "gmm-ni-9263-9234.toml"

try:
    import grpc  # noqa: F401
    import nidaqmx  # noqa: F401

    HAVE_NIDAQMX = True
except ImportError:
    HAVE_NIDAQMX = False
needs_nidaqmx = pytest.mark.skipif(not HAVE_NIDAQMX, reason="nidaqmx is not installed: pip install 'hilbench[nidaqmx]'")

HWTSP = 12522  # nidaqmx.constants.AcquisitionType.HW_TIMED_SINGLE_POINT
FINITE = 10178  # nidaqmx.constants.AcquisitionType.FINITE


class TinyWorld:
    """An amplifier that follows its input at once, 25 um per A at the sensor."""

    def __init__(self) -> None:
        self.commands: list[float] = []
        self.played: list[tuple[np.ndarray, float]] = []

    def command(self, value: float) -> None:
        self.commands.append(float(value))

    def read(self, channel: str) -> float:
        amps = self.commands[-1] if self.commands else 0.0
        return {"current": amps, "output": 25.0 * amps}.get(channel, float("nan"))

    def play(self, waveform: Any, rate_hz: float) -> dict[str, Any]:
        u = np.asarray(waveform, dtype=np.float64)
        self.played.append((u, rate_hz))
        self.commands.append(float(u[-1]))
        return {"time": np.arange(u.size) / rate_hz, "input": u, "output": 25.0 * u, "current": u}


Rig = tuple[Any, Any, TinyWorld]


@pytest.fixture
def make_rig() -> Iterator[Callable[..., Rig]]:
    """Start an emulator and open the driver on it with the given settings; all closed afterwards.
    The emulated device is a PCIe multifunction DAQ by default (C Series modules have no hardware-timed
    single point: the tests of NI 9263/9234 limits name those products)."""
    from drivers.ni_daqmx import DRIVER

    opened: list[Any] = []

    def make(**table: Any) -> Rig:
        world = TinyWorld()
        settings = DRIVER.complete({"url": "grpc://127.0.0.1:0", "ai_current_channel": "cDAQ1Mod2/ai1",
                                    "amplifier_gain_a_per_v": 0.5, "output_um_per_v": 10.0,
                                    "output_offset_um": 1.0, "current_monitor_v_per_a": 2.0,
                                    "sample_rate_hz": 200.0, "timeout_s": 0.5, "rpc_margin_s": 0.5,
                                    "emulated_ao_product": "PCIe-6363", "emulated_ai_product": "PCIe-6363",
                                    "mode": "hw-timed-single-point"} | table)
        emulator = DRIVER.emulator(settings, world)
        opened.append(emulator)
        device = DRIVER.open({**settings, "url": emulator.url})
        opened.append(device)
        return emulator, device, world

    yield make
    for thing in reversed(opened):
        thing.close()


# -- the tasks and what goes over the wire --------------------------------------------------------------
@needs_nidaqmx
def test_open_creates_an_ao_and_an_ai_task_with_hardware_timed_single_point_timing(make_rig):
    emulator, device, _ = make_rig()
    ao = next(t for t in emulator.tasks.values() if t.kind() == "ao")
    ai = next(t for t in emulator.tasks.values() if t.kind() == "ai")
    assert [c.physical for c in ao.channels] == ["cDAQ1Mod1/ao0"]
    assert [(c.min_v, c.max_v) for c in ao.channels] == [(-10.0, 10.0)]  # the AO range asked for
    assert [c.physical for c in ai.channels] == ["cDAQ1Mod2/ai0", "cDAQ1Mod2/ai1"]
    assert (ao.mode, ao.rate_hz, ai.mode, ai.rate_hz) == (HWTSP, 200.0, HWTSP, 200.0)
    assert not ao.running and not ai.running  # started by the first write or read, not at open
    calls = emulator.calls
    assert calls.index("CreateTask") < calls.index("CreateAOVoltageChan") < calls.index("CreateAIVoltageChan")
    assert calls.count("CfgSampClkTiming") == 2
    assert "NI-DAQmx 24.8.0" in device.identity() and "cDAQ1Mod1/ao0" in device.identity()


@needs_nidaqmx
def test_write_is_one_scalar_ao_write_of_amps_over_the_amplifier_gain(make_rig):
    emulator, device, world = make_rig()
    before = len(emulator.calls)
    device.write(1.0)  # 1 A at 0.5 A/V
    assert emulator.ao_writes == [2.0]
    assert world.commands == [1.0]  # the emulated amplifier turned 2 V back into 1 A
    assert emulator.calls[before:].count("WriteAnalogScalarF64") == 1


@needs_nidaqmx
def test_read_waits_for_the_next_sample_clock_then_reads_both_ai_channels_in_one_call(make_rig):
    emulator, device, _ = make_rig()
    device.write(0.8)
    before = len(emulator.calls)
    values = device.read()
    # 0.8 A -> 20 um -> (20 - 1) / 10 = 1.9 V at ai0 -> 20 um; current monitor 1.6 V -> 0.8 A
    assert values == pytest.approx({"output": 20.0, "current": 0.8})
    assert emulator.calls[before:] == ["WaitForNextSampleClock", "ReadAnalogF64"]


@needs_nidaqmx
def test_the_single_point_loop_is_paced_by_the_emulated_sample_clock_and_lateness_is_counted(make_rig):
    emulator, device, _ = make_rig(sample_rate_hz=100.0)
    device.write(0.0)
    device.read()  # the first sample clock after the start
    started = time.monotonic()
    for k in range(10):
        device.write(0.01 * k)
        device.read()
    elapsed = time.monotonic() - started
    # every read waited for a clock edge of its own: 10 edges of 10 ms cannot pass in less than 90 ms
    # (a lower bound that holds however slow the machine; the late ones are counted, not hidden)
    assert elapsed >= 0.09 - 1e-3 or device.late > 0
    late_before = device.late
    time.sleep(0.05)  # five periods without waiting: the edge the next wait wanted has gone by
    device.read()
    assert device.late == late_before + 1
    assert device.clock_stats() == {"samples": 12, "late": device.late}
    assert device.late == emulator.late_ticks  # what the DAQ reported is what the driver counted
    assert emulator.calls.count("WaitForNextSampleClock") == 12


@needs_nidaqmx
def test_on_demand_mode_configures_no_timing_and_never_waits_for_a_clock(make_rig):
    emulator, device, _ = make_rig(mode="on-demand")
    device.write(0.4)
    assert device.read() == pytest.approx({"output": 10.0, "current": 0.4})
    assert "CfgSampClkTiming" not in emulator.calls and "WaitForNextSampleClock" not in emulator.calls
    assert all(t.mode is None for t in emulator.tasks.values())


@needs_nidaqmx
def test_play_writes_the_whole_waveform_and_reads_the_ai_armed_on_the_ao_start_trigger(make_rig):
    emulator, device, world = make_rig()
    device.write(0.2)  # the single point tasks run: play must free the lines first
    device.read()
    wave = np.linspace(0.0, 2.0, 200)
    out = device.play(wave, 2000.0)
    (played, rate), = world.played
    np.testing.assert_allclose(played, wave)  # the AO volts (wave / 0.5 A/V) back in amps
    assert rate == 2000.0
    np.testing.assert_allclose(out["output"], 25.0 * wave, atol=1e-9)
    np.testing.assert_allclose(out["current"], wave, atol=1e-9)
    np.testing.assert_allclose(out["time"], np.arange(200) / 2000.0)
    calls = emulator.calls
    assert "CfgDigEdgeStartTrig" in calls and "WriteAnalogF64" in calls and "WaitUntilTaskDone" in calls
    assert calls.count("ClearTask") == 2  # the two play tasks, cleared; the loop tasks stay
    assert len(emulator.tasks) == 2


@needs_nidaqmx
def test_the_emulator_refuses_an_ai_trigger_it_cannot_route(make_rig):
    _, device, _ = make_rig(start_trigger="/PXI1Slot2/ai/StartTrigger")
    with pytest.raises(DeviceError, match=r"NI-DAQmx error -200077"):
        device.play(np.zeros(10), 1000.0)


@needs_nidaqmx
def test_a_value_outside_the_ao_range_is_refused_before_anything_is_sent(make_rig):
    emulator, device, _ = make_rig()
    before = len(emulator.calls)
    with pytest.raises(DeviceError, match=r"outside the AO range -10\.\.10 V"):
        device.write(6.0)  # 12 V
    assert len(emulator.calls) == before


# -- C Series limits: the NI 9263 / 9234 / 9215 as their specifications say ------------------------------
C_SERIES = {"emulated_ao_product": "NI 9263", "emulated_ai_product": "NI 9234"}


@needs_nidaqmx
def test_c_series_modules_refuse_hardware_timed_single_point_at_open_with_daqmx_200077(make_rig):
    """NI-DAQmx Device Considerations, Timing Considerations for C Series Devices: "C Series devices do
    not support hardware-timed single-point sample mode or Wait for Next Sample Clock"."""
    with pytest.raises(DeviceError) as caught:
        make_rig(mode="hw-timed-single-point", **C_SERIES)
    line = str(caught.value)
    assert "\n" not in line and "NI-DAQmx error -200077" in line
    assert "DAQmx_Val_HWTimedSinglePoint" in line and "(NI 9263)" in line  # the AO task is verified first


@needs_nidaqmx
def test_the_ni_9234_runs_51_2_ks_per_s_over_n_and_a_rate_between_is_refused_at_open(make_rig):
    """NI-9234 Specifications: fs = (13.1072 MHz / 256) / n, n = 1..31; DAQmx coerces a rate up to the
    next one, which the driver reads back (SampClk.Rate) and refuses unless it is the one asked for."""
    from drivers.emulators.ni_daqmx import PRODUCTS

    ni9234 = PRODUCTS["NI 9234"]
    assert [ni9234.rate(51200.0 / n) for n in (1, 2, 25, 31)] == [51200.0, 25600.0, 2048.0, 51200.0 / 31]
    assert ni9234.rate(1000.0) == pytest.approx(1651.6129, rel=1e-6)  # below the range: its lowest rate
    assert ni9234.rate(25000.0) == 25600.0  # between two: the next one up
    with pytest.raises(DeviceError, match=r"sample_rate_hz 1000: DAQmx runs the loop's sample clock of "
                                          r"cDAQ1Mod2/ai0, cDAQ1Mod2/ai1 at 1651\.61 Hz"):
        make_rig(mode="ai-clocked", sample_rate_hz=1000.0, **C_SERIES)
    with pytest.raises(DeviceError, match=r"NI-DAQmx error -200077: .*DAQmx_SampClk_Rate Requested Value: 60000"):
        make_rig(mode="ai-clocked", sample_rate_hz=60000.0, **C_SERIES)
    emulator, device, _ = make_rig(mode="ai-clocked", sample_rate_hz=2048.0, **C_SERIES)
    assert device.sample_clock_hz() == 2048.0 and "TaskControl" in emulator.calls  # verified at open


@needs_nidaqmx
def test_a_play_at_a_rate_the_ni_9234_cannot_run_is_refused_before_anything_moves(make_rig):
    _, device, world = make_rig(mode="on-demand", **C_SERIES)
    with pytest.raises(DeviceError, match=r"play at 1000 Hz: DAQmx runs the AI sample clock of .* at 1651\.61 Hz"):
        device.play(np.linspace(0.0, 1.0, 100), 1000.0)
    assert world.played == []


@needs_nidaqmx
def test_ai_clocked_the_ni_9215s_sample_clock_paces_the_loop_and_a_late_loop_reads_the_newest_sample(make_rig):
    """A continuous acquisition read one sample a tick (a cDAQ's per-sample loop): each wait returns at
    the AI clock's next tick; when the tick came before the wait, DAQmx already holds the samples and
    the wait says late."""
    emulator, device, _ = make_rig(mode="ai-clocked", sample_rate_hz=100.0, emulated_ao_product="NI 9263",
                                       emulated_ai_product="NI 9215")
    assert device.sample_clock_hz() == 100.0 and "continuous AI" in device.sample_clock()
    device.write(0.0)
    device.wait_for_next_sample_clock()  # the acquisition starts: its first sample is there at once
    before = len(emulator.calls)
    started = time.monotonic()
    on_time = 0
    for k in range(10):
        on_time += not device.wait_for_next_sample_clock()
        device.write(0.01 * k)
        device.read()
    elapsed = time.monotonic() - started
    # every on-time wait waited for a tick of its own, 10 ms after the one before on the emulated clock
    assert elapsed >= 0.01 * (on_time - 1) - 1e-3
    calls = emulator.calls[before:]
    assert calls.count("ReadAnalogF64") == 10 + on_time  # all acquired (-1), then the next one when none
    assert "WaitForNextSampleClock" not in calls and "CfgSampClkTiming" not in calls
    device.write(0.4)  # the world moves; the AO was written on demand
    time.sleep(0.05)  # five ticks without a wait
    late_before = device.late
    assert device.wait_for_next_sample_clock() is True and device.late == late_before + 1
    assert device.read() == pytest.approx({"output": 10.0, "current": 0.4})  # the newest sample
    assert device.clock_stats()["samples"] == 12


@needs_nidaqmx
def test_ai_clocked_a_backlog_beyond_daqmxs_buffer_restarts_the_acquisition_and_counts_late(make_rig):
    emulator, device, _ = make_rig(mode="ai-clocked", sample_rate_hz=200.0, ai_buffer_s=0.05,
                                   emulated_ai_product="NI 9215")  # a buffer of 10 samples
    device.write(0.2)
    device.wait_for_next_sample_clock()
    time.sleep(0.15)  # 30 ticks: unread samples overwritten
    assert device.wait_for_next_sample_clock() is True
    assert emulator.calls.count("StopTask") + emulator.calls.count("TaskControl") >= 2  # stopped and started
    assert device.read() == pytest.approx({"output": 5.0, "current": 0.2})


# -- faults ---------------------------------------------------------------------------------------------
@needs_nidaqmx
def test_a_channel_the_chassis_lacks_is_one_device_error_line_with_nis_error_code(make_rig):
    with pytest.raises(DeviceError) as caught:
        make_rig(ai_output_channel="cDAQ1Mod2/ai7")  # the NI 9234 has ai0..ai3
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith("ni-daqmx (grpc://127.0.0.1:")
    assert "NI-DAQmx error -200170: Physical channel specified does not exist on this device" in message


@needs_nidaqmx
def test_a_daqmx_error_reply_becomes_one_device_error_line(make_rig):
    emulator, device, _ = make_rig(mode="on-demand")
    emulator.error_next(-200077)
    with pytest.raises(DeviceError) as caught:
        device.read()
    assert not isinstance(caught.value, DeviceTimeout)  # a refusal is not retried
    assert "\n" not in str(caught.value) and device.name in str(caught.value)
    assert "reading the AI channels: NI-DAQmx error -200077: Requested value is not a supported value" in str(caught.value)
    assert emulator.calls.count("ReadAnalogF64") == 1


@needs_nidaqmx
def test_a_stalled_call_passes_its_deadline_and_is_retried(make_rig):
    emulator, device, _ = make_rig(mode="on-demand", timeout_s=0.1, rpc_margin_s=0.2)
    emulator.stall_next(calls=1, seconds=0.6)
    assert device.read() == pytest.approx({"output": 0.0, "current": 0.0})
    assert emulator.calls.count("ReadAnalogF64") == 2


@needs_nidaqmx
def test_no_answer_after_the_retries_raises_device_timeout(make_rig):
    emulator, device, _ = make_rig(mode="on-demand", timeout_s=0.1, rpc_margin_s=0.2, attempts=3)
    emulator.stall_next(calls=3, seconds=0.6)
    with pytest.raises(DeviceTimeout, match=r"reading the AI channels: no valid answer after 3 tries"):
        device.read()
    assert emulator.calls.count("ReadAnalogF64") == 3


@needs_nidaqmx
def test_a_buffered_read_that_times_out_is_nis_samples_not_yet_available(make_rig):
    emulator, device, _ = make_rig()
    task = device._task("probe")  # an AI task armed on a trigger that never comes
    try:
        task.ai_channels.add_ai_voltage_chan("cDAQ1Mod2/ai2")
        task.timing.cfg_samp_clk_timing(1000.0, samps_per_chan=10)
        task.triggers.start_trigger.cfg_dig_edge_start_trig("/cDAQ1/ao/StartTrigger")
        task.start()
        from nidaqmx.stream_readers import AnalogSingleChannelReader

        reader = AnalogSingleChannelReader(task.in_stream)
        with pytest.raises(DeviceTimeout, match=r"reading: NI-DAQmx error -200284: Some or all of the samples"):
            device._call("reading", lambda: reader.read_many_sample(np.zeros(10), 10, timeout=0.05), retried=False)
    finally:
        task.close()


@needs_nidaqmx
def test_server_gone_mid_use_raises_device_lost_naming_the_device(make_rig):
    emulator, device, _ = make_rig(mode="on-demand")
    device.read()
    emulator.disconnect()
    with pytest.raises(DeviceLost) as caught:
        device.read()
    assert device.name in str(caught.value) and "unreachable or went away" in str(caught.value)


@needs_nidaqmx
def test_opening_a_device_server_that_is_not_there_raises_device_lost():
    import socket

    from drivers.ni_daqmx import DRIVER

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(DeviceLost, match=rf"127\.0\.0\.1:{port} is unreachable"):
        DRIVER.open({"url": f"grpc://127.0.0.1:{port}", "timeout_s": 0.2, "rpc_margin_s": 0.5})


@needs_nidaqmx
def test_methods_the_emulator_lacks_answer_unimplemented(make_rig):
    import grpc
    from nidaqmx._stubs import nidaqmx_pb2, nidaqmx_pb2_grpc

    emulator, _, _ = make_rig()
    with grpc.insecure_channel(emulator.url.removeprefix("grpc://")) as channel:
        stub = nidaqmx_pb2_grpc.NiDAQmxStub(channel)
        with pytest.raises(grpc.RpcError) as caught:
            stub.CreateDIChan(nidaqmx_pb2.CreateDIChanRequest(lines="cDAQ1Mod3/port0/line0"), timeout=5)
    assert caught.value.code() == grpc.StatusCode.UNIMPLEMENTED


@needs_nidaqmx
def test_the_nidaqmx_client_sees_the_ni_error_code_of_a_bad_channel(make_rig):
    """The emulator's error reply as NI's own client reads it: DaqError with error_code -200170."""
    import nidaqmx

    emulator, device, _ = make_rig()
    task = device._task("probe")
    try:
        with pytest.raises(nidaqmx.DaqError) as caught:
            task.ao_channels.add_ao_voltage_chan("cDAQ1Mod1/ao9")
        assert caught.value.error_code == -200170
    finally:
        task.close()


# -- the template through emulate --write-config and a sweep ---------------------------------------------
@needs_nidaqmx
def test_the_template_sweeps_through_its_emulated_device_server(tmp_path):
    import h5py
    from typer.testing import CliRunner

    from hilbench.cli import app
    from hilbench.rig.config import load_rig
    from hilbench.rig.emulation import start_emulators

    runner = CliRunner()
    config = load_rig(TEMPLATE)
    with start_emulators(config) as emulated:
        written = emulated.write_config(tmp_path / "rig-emulated.toml")
        assert load_rig(written).devices["daq"]["url"].startswith("grpc://127.0.0.1:")
        plan = "sine:amplitude=1,offset=1.5,frequency_hz=5,cycles=2"
        check = runner.invoke(app, ["sweep", str(written), "--check", "--json", "-e", plan])
        assert check.exit_code == 0, check.output
        assert json.loads(check.stdout)["round_trips"]["mode"] == "block"  # played by the DAQ's clock
        out = tmp_path / "swept.h5"
        swept = runner.invoke(app, ["sweep", str(written), "-e", plan, "-o", str(out), "-q", "--json"])
        assert swept.exit_code == 0, swept.output
        calls = emulated.emulators["daq"].calls
    with h5py.File(out, "r") as f:
        (run,) = [f["runs"][name] for name in f["runs"]]
        assert run.attrs["status"] == "complete"
        devices = json.loads(run.attrs["devices"])
        output, applied = run["output"][:], run["input"][:]
    assert {d["driver"] for d in devices} == {"ni-daqmx"}
    assert applied.min() == pytest.approx(0.5, abs=1e-3) and applied.max() == pytest.approx(2.5, abs=1e-3)
    assert output.max() - output.min() > 5.0  # the emulated plant moved and the NI 9234 read it
    assert "CfgDigEdgeStartTrig" in calls and "WriteAnalogF64" in calls


# -- without nidaqmx -------------------------------------------------------------------------------------
BLOCK_NIDAQMX = """
import sys
class Blocked:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('nidaqmx', 'session_pb2'):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return None
sys.meta_path.insert(0, Blocked())
"""


def _without_nidaqmx(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", BLOCK_NIDAQMX + code], capture_output=True, text=True,
                          timeout=120, cwd=REPO)


def test_without_nidaqmx_the_driver_imports_and_opening_says_how_to_install_it():
    result = _without_nidaqmx("""
from drivers.base import DeviceError
from drivers.ni_daqmx import DRIVER
assert 'nidaqmx' not in sys.modules
print(DRIVER.install_hint)
try:
    DRIVER.open({'url': 'grpc://127.0.0.1:1'})
except DeviceError as exc:
    print(exc)
""")
    assert result.returncode == 0, result.stderr
    hint, error = result.stdout.strip().splitlines()
    assert hint == "pip install 'hilbench[nidaqmx]'"
    assert error == "ni-daqmx (grpc://127.0.0.1:1): the nidaqmx package is not installed; pip install 'hilbench[nidaqmx]'"


def test_without_nidaqmx_hilbench_devices_lists_the_driver_with_the_install_line():
    result = _without_nidaqmx("""
from hilbench.cli import main
sys.argv = ['hilbench', 'devices']
main()
""")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("ni-daqmx "))
    block = lines[start:start + 5]
    assert any(line.strip() == "needs an optional package: pip install 'hilbench[nidaqmx]'" for line in block), block
    assert any(line.startswith("pi-gcs ") for line in lines)  # the others are listed as before
