"""Property: whatever the plan and whatever fault, the emulated actuator never leaves its limits or slew rate.

Generated plans (sines and triangles of random amplitude, offset and frequency, many of them beyond
the actuator's range or slew limit) go to run_plan on the emulated Modbus + CANopen rig, some with a
fault injected mid-run. The plan check must refuse exactly the violators (and then nothing moves);
what the emulated analog output really received is checked against the limits, sample by sample.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.base import DeviceError
from hilbench.errors import PlanLimitError
from hilbench.excitation.plan import plan_from_compact
from hilbench.runners.faults import RunFault
from hilbench.runners.sweep import run_plan
from tests.runners.emulated import emulated, ramp_ok

LO, HI, MAX_STEP = -6.5, 6.5, 200.0 / 1000.0
LSB = 20.0 / 65535


def violates(commands: np.ndarray) -> bool:
    return bool(np.any(commands < LO) or np.any(commands > HI)
                or np.any(np.abs(np.diff(commands)) > MAX_STEP * (1 + 1e-9)))


def test_generated_plans_and_faults_never_drive_the_actuator_beyond_its_limits(tmp_path):
    with emulated("modbus-canopen", lvdt={"heartbeat_consumer_ms": 2000, "timeout_s": 0.05}) as (emu, rig):
        aio, lvdt = emu.emulators["aio"], emu.emulators["lvdt"]
        count = iter(range(10**6))

        @settings(max_examples=14, deadline=None, derandomize=True,
                  suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
        @given(kind=st.sampled_from(["sine", "triangle"]),
               amplitude=st.floats(0.0, 9.0), offset=st.floats(-5.0, 5.0), frequency=st.floats(2.0, 25.0),
               fault=st.sampled_from([None, "over-range", "silent", "refused-write"]),
               at=st.integers(0, 150))
        def check(kind, amplitude, offset, frequency, fault, at):
            spec = f"{kind}:amplitude={amplitude!r},offset={offset!r},frequency_hz={frequency!r},cycles=1"
            runs = plan_from_compact([spec])
            commands = runs[0].excitation.generate(1000.0)
            before = len(aio.ao_writes)
            out = tmp_path / f"r{next(count)}.h5"
            if violates(commands):
                with pytest.raises(PlanLimitError):
                    run_plan(rig, runs, out, pace=False, chunk_samples=25)
                assert len(aio.ao_writes) == before  # refused before anything moved
                return
            inject = {None: lambda: None, "over-range": lambda: lvdt.out_of_range(True),
                      "silent": lambda: lvdt.mute_tpdo(True), "refused-write": lambda: aio.exception_next(4)}[fault]
            fired = []

            def progress(index, label, done, total):
                if done >= at and not fired:
                    fired.append(done)
                    inject()

            try:
                run_plan(rig, runs, out, pace=False, chunk_samples=25, progress=progress)
            except (RunFault, DeviceError):
                assert fault is not None and fired
            finally:
                lvdt.out_of_range(False)
                lvdt.mute_tpdo(False)
            written = aio.ao_writes[before - 1:]  # from the value held before this plan
            assert ramp_ok(written, MAX_STEP, LO, HI, LSB), spec
            assert abs(written[-1]) <= LSB  # back at rest

        check()



