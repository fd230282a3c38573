"""A device lost mid-run under `hilbench track` and `online` on real drivers (issue 59): the Modbus AIO +
Keyence template pointed at its emulators, the command in another process, paced with --allow-late.
Mid-run the laser stops answering (its replies withheld: the driver's retries time out) or its
transport is closed. Either way: one line naming the device and the recording, exit 1, no traceback;
the run kept ``failed`` with its samples and a reason naming the device; the actuator ramped to rest
(the emulated amplifier's last command is 0 A, never beyond the slew rate).
(`sweep` is tested the same way in tests/runners/test_emulated_faults.py.)
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hilbench.recording.hdf5 import Recording
from hilbench.rig.config import load_rig
from hilbench.rig.emulation import start_emulators
from hilbench.runners.fixed_rate import (
    DEFAULT_WATCHDOG_S,
    device_patience_s,
    watchdog_s,
)
from tests.runners.emulated import RIGS, config_file, first_line
from tests.runners.test_emulated_signals import LONG, LSB, model_file  # noqa: F401 (the fixture)

TEMPLATE = RIGS["modbus-keyence"]
FAULTS = {
    "stops answering": lambda emu: emu.emulators["laser"].silence(30.0),
    "transport closed": lambda emu: emu.emulators["laser"].disconnect(),
}


def _argv(kind: str, config: Path, out: Path, model: tuple[Path, str]) -> list[str]:
    if kind == "online":  # the fault comes during the training run
        return ["online", str(config), "-e", LONG, "-e", LONG, "--record", str(out), "-q", "--allow-late"]
    return ["track", str(config), "--model", str(model[0]), "-r", model[1], "-o", str(out), "--allow-late"]


def _patient_amplifier(config: Path) -> Path:
    """The amplifier's module waits 1 s a reply (its default 0.2): its emulator serves from the test's
    process, which a loaded CI machine stalled past three 0.2 s tries, and once past three 0.5 s tries,
    before the laser's fault came. The loop's watchdog grows with it (watchdog_s); the fault under test is
    the laser's."""
    text = config.read_text(encoding="utf-8")
    config.write_text(text.replace("[devices.aio]\n", "[devices.aio]\ntimeout_s = 1.0\n", 1), encoding="utf-8")
    return config


def test_the_watchdog_outlasts_the_most_patient_devices_retries(tmp_path):
    """A device configured patient fails in its own words: the watchdog waits longer than its retries."""
    config = tmp_path / "rig.toml"
    config.write_text(TEMPLATE.read_text(encoding="utf-8"), encoding="utf-8")
    rig = SimpleNamespace(config=load_rig(config))
    assert watchdog_s(rig) == DEFAULT_WATCHDOG_S > device_patience_s(rig)  # the drivers' defaults
    text = config.read_text(encoding="utf-8").replace("[devices.aio]\n", "[devices.aio]\ntimeout_s = 1.0\n"
                                                       "attempts = 4\n", 1)
    config.write_text(text, encoding="utf-8")
    rig = SimpleNamespace(config=load_rig(config))
    assert device_patience_s(rig) == pytest.approx(4 * 1.0 + 0.02 * (1 + 2 + 4))
    assert watchdog_s(rig) > device_patience_s(rig) > DEFAULT_WATCHDOG_S


@pytest.mark.parametrize("fault", list(FAULTS))
@pytest.mark.parametrize("kind", ["track", "online"])
def test_a_device_lost_mid_run_fails_in_one_line_keeps_the_run_and_ramps_to_rest(kind, fault, model_file, tmp_path):
    out = tmp_path / f"{kind}.h5"
    with start_emulators(load_rig(TEMPLATE)) as emu:
        aio = emu.emulators["aio"]
        config = _patient_amplifier(config_file(emu, TEMPLATE, tmp_path))
        assert load_rig(config).devices["aio"]["timeout_s"] == 1.0
        proc = subprocess.Popen([sys.executable, "-m", "hilbench.cli", *_argv(kind, config, out, model_file)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        while len(aio.ao_writes) < 1500:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"the run did not get under way: {proc.communicate()[1][-2000:]}")
            time.sleep(0.02)
        FAULTS[fault](emu)
        _, err = proc.communicate(timeout=120)
        assert abs(aio.last_ao) <= LSB and abs(emu.world.last_command) <= LSB  # ramped to rest
        assert np.abs(np.diff(aio.ao_writes)).max() <= 200.0 / 1000.0 + LSB  # never faster than the slew limit
    assert proc.returncode == 1 and "Traceback" not in err, err[-2000:]
    (line,) = err.strip().splitlines()
    assert line.startswith("error: device 'laser': ") and str(out) in line
    (run,) = Recording(out).runs
    assert run.status == "failed" and run.attrs["made_safe"] == 1
    reason = first_line(run.attrs["reason"])
    assert "device 'laser' (keyence-lk" in reason and "actuator ramped to rest" in reason
    data = run.data()
    assert run.n_samples > 1000 and all(v.size == run.n_samples for v in data.values())
    assert np.all(np.isfinite(data["output"]))
