"""Faults on emulated rigs: every one stops the run safely and says which device and why.

A fault is injected mid-run through the emulators' own fault injection (from the runner's progress
callback, i.e. between chunks of the loop). What is asserted: the actuator command the emulated
device really received came back to rest without leaving the limits or the slew rate, the
recording ends ``failed`` with a first line naming the rig's device, and every sample recorded
before the fault is there and matches the simulated backend's within noise.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from drivers.base import DeviceError, DeviceLost, DeviceTimeout
from hilbench.excitation.plan import plan_from_compact
from hilbench.recording.hdf5 import Recording
from hilbench.rig.config import load_rig
from hilbench.runners.faults import InterlockTripped
from hilbench.runners.sweep import run_plan
from tests.runners.emulated import (
    NOISE_STD_UM,
    RIGS,
    emulated,
    first_line,
    ramp_ok,
    record_sim,
    rms,
)

LSB = 20.0 / 65535  # one AO count, A
MAX_STEP = 200.0 / 1000.0  # max_rate / fs, A per sample
SLOW_HEARTBEAT = {"lvdt": {"heartbeat_consumer_ms": 2000}}
PLAN = "sine:amplitude=5,frequency_hz=1,cycles=2"  # 2001 samples


def fault_at(samples: int, inject):
    """A progress callback that calls ``inject()`` once, when the run has ``samples`` recorded."""
    fired = []

    def progress(index, label, done, total):
        if done >= samples and not fired:
            fired.append(done)
            inject()

    progress.fired = fired
    return progress


def assert_made_safe(emu, rig):
    aio = emu.emulators["aio"]
    assert abs(aio.last_ao) <= LSB and abs(emu.world.last_command) <= LSB  # at rest on the device
    assert ramp_ok(aio.ao_writes, MAX_STEP, -6.5, 6.5, LSB)  # never beyond the limits or the slew rate
    assert rig.last_applied == 0.0


def assert_kept(out, kind, at_least):
    (run,) = Recording(out).runs
    assert run.status == "failed" and run.attrs["made_safe"] == 1
    n = run.n_samples
    assert n >= at_least
    sim = record_sim(load_rig(RIGS[kind]), plan_from_compact([PLAN]), out.with_name("sim.h5"))
    expected = Recording(sim).runs[0].data()
    data = run.data()
    assert rms(data["output"] - expected["output"][:n]) < 3 * NOISE_STD_UM  # every sample before: real data
    np.testing.assert_array_equal(data["input"], expected["input"][:n])
    return run


@pytest.mark.parametrize("kind, device, inject, error", [
    ("modbus-keyence", "laser", lambda emu: emu.emulators["laser"].disconnect(), DeviceLost),
    # the node leaves the bus: on CAN that is silence, so the SYNC goes unanswered (before the
    # heartbeat consumer, 2 s here, would call it lost)
    ("modbus-canopen", "lvdt", lambda emu: emu.emulators["lvdt"].close(), DeviceTimeout),
])
def test_a_sensor_transport_closed_mid_run_ramps_the_actuator_to_rest(kind, device, inject, error, tmp_path):
    out = tmp_path / "r.h5"
    with emulated(kind, **({} if kind == "modbus-keyence" else SLOW_HEARTBEAT)) as (emu, rig):
        progress = fault_at(600, lambda: inject(emu))
        with pytest.raises(error) as info:
            run_plan(rig, plan_from_compact([PLAN]), out, pace=False, chunk_samples=100, progress=progress)
        assert "\n" not in str(info.value)
        assert_made_safe(emu, rig)
    run = assert_kept(out, kind, 600)
    line = first_line(run.attrs["reason"])
    assert f"device {device!r}" in line and "actuator ramped to rest" in line


def test_a_canopen_heartbeat_lost_mid_run_stops_the_run_safely(tmp_path):
    out = tmp_path / "r.h5"
    with emulated("modbus-canopen", lvdt={"heartbeat_consumer_ms": 300}) as (emu, rig):
        progress = fault_at(300, emu.emulators["lvdt"].stop_heartbeat)
        with pytest.raises(DeviceLost, match="no heartbeat"):
            run_plan(rig, plan_from_compact([PLAN]), out, pace=False, chunk_samples=100, progress=progress)
        assert_made_safe(emu, rig)
    run = assert_kept(out, "modbus-canopen", 300)
    assert "device 'lvdt' (canopen-sensor" in first_line(run.attrs["reason"])
    assert "no heartbeat" in first_line(run.attrs["reason"])


def test_the_actuator_transport_closed_mid_run_fails_naming_it_and_says_it_could_not_be_made_safe(tmp_path):
    out = tmp_path / "r.h5"
    with emulated("modbus-keyence") as (emu, rig):
        progress = fault_at(500, emu.emulators["aio"].disconnect)
        with pytest.raises(DeviceLost):
            run_plan(rig, plan_from_compact([PLAN]), out, pace=False, chunk_samples=100, progress=progress)
    (run,) = Recording(out).runs
    line = first_line(run.attrs["reason"])
    # the host cannot move an actuator whose own link is gone: the run says so instead of pretending
    assert run.status == "failed" and run.attrs["made_safe"] == 0
    assert "device 'aio' (modbus-aio" in line and "could not be made safe" in line
    assert run.n_samples == 500


def test_a_timeout_is_retried_with_back_off_and_the_run_goes_on(tmp_path):
    out = tmp_path / "r.h5"
    with emulated("modbus-keyence") as (emu, rig):
        laser = emu.emulators["laser"]
        progress = fault_at(200, lambda: laser.drop_replies(1))
        result = run_plan(rig, plan_from_compact(["sine:amplitude=2,frequency_hz=2,cycles=1"]), out,
                          pace=False, chunk_samples=100, progress=progress)
        commands = [data for direction, data in laser.traffic if direction == "in"]
    assert result.status == "complete" and result.runs[0].samples == 501
    assert commands.count(b"M1") == 501 + 1  # one read sent twice: the retry


def test_a_timeout_that_persists_fails_after_the_retries_and_ramps_to_rest(tmp_path):
    out = tmp_path / "r.h5"
    with emulated("modbus-keyence") as (emu, rig):
        progress = fault_at(400, lambda: emu.emulators["laser"].silence(10.0))
        with pytest.raises(DeviceTimeout, match="no valid answer after 3 tries"):
            run_plan(rig, plan_from_compact([PLAN]), out, pace=False, chunk_samples=100, progress=progress)
        assert_made_safe(emu, rig)
    run = assert_kept(out, "modbus-keyence", 400)
    assert "device 'laser' (keyence-lk" in first_line(run.attrs["reason"])


@pytest.mark.parametrize("inject, match", [
    (lambda emu: emu.emulators["laser"].garble_next(), r"garbled reply to M1"),
    (lambda emu: emu.emulators["laser"].error_next("01"), r"M1 refused: ER code 01: status error"),
    (lambda emu: emu.emulators["aio"].exception_next(4), r"code 4 SERVER DEVICE FAILURE"),
])
def test_garbage_and_error_replies_are_one_line_errors_and_the_run_fails_safely(inject, match, tmp_path):
    out = tmp_path / "r.h5"
    with emulated("modbus-keyence") as (emu, rig):
        with pytest.raises(DeviceError, match=match) as info:
            run_plan(rig, plan_from_compact([PLAN]), out, pace=False, chunk_samples=100,
                     progress=fault_at(300, lambda: inject(emu)))
        assert "\n" not in str(info.value)
        assert_made_safe(emu, rig)
    run = assert_kept(out, "modbus-keyence", 300)
    assert match.split(":")[0].replace("\\", "") in first_line(run.attrs["reason"])


def test_a_sensor_over_range_trips_the_interlock(tmp_path):
    out = tmp_path / "r.h5"
    with emulated("modbus-keyence") as (emu, rig):
        progress = fault_at(300, lambda: emu.emulators["laser"].force("+FFFFFFF"))
        with pytest.raises(InterlockTripped, match=r"sensor 'output' of device 'laser'.*NaN \(over_range_positive\)"):
            run_plan(rig, plan_from_compact([PLAN]), out, pace=False, chunk_samples=100, progress=progress)
        assert_made_safe(emu, rig)
    assert_kept(out, "modbus-keyence", 300)


def test_a_stalled_loop_is_made_safe_by_the_watchdog(tmp_path):
    """The laser stops answering for longer than the watchdog allows (its driver waits 1 s per try):
    the watchdog ramps the actuator (on its own, working Modbus link) to rest while the loop is
    still stuck in the laser's read; the run then fails saying both."""
    out = tmp_path / "r.h5"
    with emulated("modbus-keyence", laser={"timeout_s": 1.0, "attempts": 1}) as (emu, rig):
        laser = emu.emulators["laser"]
        at_rest_while_stuck = []

        def stall():
            laser.silence(1.5)

            def watch():  # what the actuator did while the loop was stuck
                deadline = time.monotonic() + 0.9
                while time.monotonic() < deadline and not at_rest_while_stuck:
                    if emu.emulators["aio"].last_ao is not None and abs(emu.emulators["aio"].last_ao) <= LSB:
                        at_rest_while_stuck.append(True)
                    time.sleep(0.005)

            threading.Thread(target=watch, daemon=True).start()

        with pytest.raises(DeviceTimeout):
            run_plan(rig, plan_from_compact([PLAN]), out, pace=False, chunk_samples=100,
                     watchdog_periods=100, progress=fault_at(300, stall))
        assert_made_safe(emu, rig)
    assert at_rest_while_stuck == [True]
    run = assert_kept(out, "modbus-keyence", 300)
    reason = first_line(run.attrs["reason"])
    assert "watchdog" in reason and "no sample for" in reason and "actuator ramped to rest" in reason


def test_ctrl_c_is_deferred_to_the_end_of_the_chunk_then_the_run_is_aborted_at_rest(tmp_path):
    out = tmp_path / "r.h5"
    with emulated("modbus-keyence") as (emu, rig):
        progress = fault_at(300, lambda: os.kill(os.getpid(), signal.SIGINT))
        result = run_plan(rig, plan_from_compact([PLAN, PLAN]), out, pace=False, chunk_samples=100,
                          progress=progress)
        assert_made_safe(emu, rig)
    assert result.status == "aborted" and len(result.runs) == 1
    (run,) = Recording(out).runs
    assert run.status == "aborted" and run.n_samples == 300 and "ramped to rest" in run.attrs["reason"]


def test_the_pi_controller_lost_mid_play_fails_naming_it(tmp_path):
    """A PI controller playing a run on its own when its serial link closes: the run fails naming it;
    the controller cannot be reached to ramp it, and the recording says so. The run before is kept."""
    out = tmp_path / "r.h5"
    with emulated("pi-gcs", pi={"realtime": True}) as (emu, rig):
        pi = emu.emulators["pi"]

        def cut_when_playing():
            deadline = time.monotonic() + 10
            while pi._wave is None and time.monotonic() < deadline:
                time.sleep(0.002)
            pi.disconnect()

        def progress(index, label, done, total):
            if index == 1 and done == total:
                threading.Thread(target=cut_when_playing, daemon=True).start()

        with pytest.raises(DeviceLost):
            run_plan(rig, plan_from_compact(["sine:amplitude=2,frequency_hz=4,cycles=1",
                                             "sine:amplitude=3,frequency_hz=1,cycles=1"]),
                     out, chunk_samples=100, progress=progress)
    first, second = Recording(out).runs
    assert first.status == "complete" and first.n_samples == 251
    assert second.status == "failed" and second.n_samples == 0 and second.attrs["made_safe"] == 0
    assert "device 'pi' (pi-gcs" in first_line(second.attrs["reason"])


def test_a_pi_error_reply_mid_sweep_fails_safely_ramping_from_what_the_controller_holds(tmp_path):
    out = tmp_path / "r.h5"
    with emulated("pi-gcs") as (emu, rig):
        pi = emu.emulators["pi"]

        before_fault = []

        def progress(index, label, done, total):
            if index == 1 and done == total:
                before_fault.append(len(pi.commanded_v))
                pi.fail_next(73)  # the next command (run 2's first) is refused

        with pytest.raises(DeviceError, match=r"refused: GCS error 73") as info:
            run_plan(rig, plan_from_compact(["sine:amplitude=2,offset=3,frequency_hz=4,cycles=1",
                                             "sine:amplitude=3,frequency_hz=1,cycles=1"]),
                     out, chunk_samples=100, progress=progress)
        assert "\n" not in str(info.value)
        assert abs(pi.last_commanded_v) < 1e-9 and abs(emu.world.last_command) < 1e-9
        # from the value the controller held when the fault came (run 1's end, 3 V), back to rest
        # through SVA steps within the limits and the slew rate
        tail = pi.commanded_v[before_fault[0] - 1:]
        assert tail[0] == pytest.approx(3.0) and len(tail) > 10 and ramp_ok(tail, MAX_STEP, -6.5, 6.5, 1e-6)
        assert min(pi.commanded_v) >= -6.5 and max(pi.commanded_v) <= 6.5
    first, second = Recording(out).runs
    assert first.status == "complete" and second.status == "failed" and second.attrs["made_safe"] == 1
    assert "device 'pi' (pi-gcs" in first_line(second.attrs["reason"])
