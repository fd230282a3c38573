"""What sample rate each transport can hold: the devices' round trip through the real drivers.

For each kind of real rig hilbench drives, the rig config is pointed at its emulators (the way a user
dry-runs a config) and the rate check of ``hilbench sweep --check`` times ``--round-trips`` round
trips (the actuator written its present value, every sensor read): p50 and p99 per device and for
the whole sample, and the highest rate the loop can hold there (0.8 / p99, as ``--check`` says, with
its interval and the rate it advises). Then, for the per-sample rigs whose emulators run in a process
of their own, what a user does next: the config set to the advised rate and ``hilbench sweep`` run
in a fresh process (its own rate check, compile and start included) on a ``--sweep-seconds`` sine;
the run's lateness p50/p99/max and overruns as the recording keeps them (issue 59: fewer than 1 %
overruns at the rate the check allows), and how late its first three samples were (each less than
one period after warm-up).

* Modbus AIO + Keyence LK-G: Modbus TCP to the amplifier's AO/AI module, the laser's RS-232C
  protocol over a TCP serial server (``configs/templates/gmm-modbus-keyence.toml``);
* Modbus AIO + CANopen LVDT: the amplifier over Modbus TCP, a CiA 404 sensor's TPDO on a CAN bus
  (``configs/templates/gmm-modbus-canopen.toml``);
* PI E-727 per sample: ``SVA``/``ERR?`` and ``POS?``/``VOL?`` over a serial line, one sample at a time
  (``tests/runners/rigs/gmm-pi-gcs.toml``; hilbench plays such a rig's runs on its wave generator
  instead, but the per-sample figure is what feedback through it would have).

The emulators run in a ``hilbench emulate`` process of their own, except the CAN rig's: a python-can
virtual bus reaches no other process, so there they share this interpreter (a pessimistic figure).
A real device answers from its own CPU over a real line: at 115200 bit/s a 20-byte reply alone takes
~1.7 ms, and a Modbus TCP module typically 1-5 ms. Prints one JSON document on stdout.

    python benchmarks/bench_transport_rates.py [--round-trips 1000] [--sweep-seconds 10]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _common as C
from bench_fixed_rate import start_emulate

REPO = Path(__file__).resolve().parents[1]
RIGS = {
    "modbus_aio_keyence": (REPO / "configs" / "templates" / "gmm-modbus-keyence.toml", "separate process"),
    "modbus_aio_canopen": (REPO / "configs" / "templates" / "gmm-modbus-canopen.toml", "this process"),
    "pi_gcs_per_sample": (REPO / "tests" / "runners" / "rigs" / "gmm-pi-gcs.toml", "separate process"),
}


def _in_ms(figures: dict[str, Any]) -> dict[str, Any]:
    """Figures in seconds (keys ending ``_s``) as milliseconds (``_ms``); the others as they are."""
    return {(k[:-2] + "_ms" if k.endswith("_s") else k): (round(v * 1e3, 4) if k.endswith("_s") else v)
            for k, v in figures.items()}


def time_rig(config: Any, round_trips: int) -> dict[str, Any]:
    from hilbench.rig.rig import Rig
    from hilbench.runners.rate_check import time_round_trips
    from hilbench.runners.sweep import select_mode

    with Rig(config) as rig:
        rig.start_run(rig.actuator.rest)
        time_round_trips(rig, 50)  # connections warm
        trips = time_round_trips(rig, round_trips)
        mode = select_mode(rig)
    described = trips.describe()
    devices = described.pop("devices")
    return {"mode": mode, **_in_ms(described),
            "devices_ms": {d: _in_ms(f) for d, f in devices.items()},
            "max_rate_hz": round(described["max_rate_hz"], 1),
            "max_rate_interval_hz": [round(r, 1) for r in described["max_rate_interval_hz"]],
            "set_at_most_hz": described["advised_rate_hz"]}


def sweep_at(written: Path, rate_hz: float, seconds: float, folder: Path) -> dict[str, Any]:
    """``hilbench sweep`` at ``rate_hz`` in a fresh process, on the config ``hilbench emulate``
    wrote: a 1 Hz sine of a fifth of the actuator's range for ``seconds``; the run's loop figures."""
    from hilbench.recording.hdf5 import Recording
    from hilbench.recording.lateness import loop_figures, loop_line
    from hilbench.rig.config import load_rig

    text = written.read_text(encoding="utf-8")
    text, n = re.subn(r"^(\[rig\]\n)", rf"\1sample_rate_hz = {rate_hz!r}\n", text, count=1, flags=re.MULTILINE)
    if n != 1:
        raise RuntimeError(f"{written}: no [rig] table to set sample_rate_hz in")
    config = folder / f"at-{rate_hz:g}-hz.toml"
    config.write_text(text, encoding="utf-8")
    act = load_rig(config).actuator
    amplitude = 0.1 * (act.max - act.min)
    out = folder / f"sweep-{rate_hz:g}-hz.h5"
    sine = (f"sine:amplitude={amplitude:g},offset={0.5 * (act.max + act.min):g},frequency_hz=1,"
            f"cycles={max(1, round(seconds))}")
    done = subprocess.run([sys.executable, "-m", "hilbench.cli", "sweep", str(config), "-o", str(out), "-q", "-e",
                           sine], capture_output=True, text=True, timeout=600, check=False)
    if done.returncode != 0:
        return {"rate_hz": rate_hz, "exit": done.returncode, "error": done.stderr.strip()[-500:]}
    (run,) = Recording(out).runs
    figures = loop_figures(run.attrs)
    first = run.channel("lateness")[:3]  # a stall in the first sample's work shows in the second's
    return {"rate_hz": rate_hz, "exit": 0, "samples": run.n_samples, "status": run.status,
            "first_samples_late_ms": [round(float(x) * 1e3, 4) for x in first],
            **_in_ms({k: v for k, v in figures.items() if k.startswith(("lateness_", "overrun")) or k == "late"}),
            "line": loop_line(figures)}


def run(round_trips: int, sweep_seconds: float = 10.0) -> dict[str, Any]:
    from hilbench.rig.config import load_rig
    from hilbench.rig.emulation import start_emulators

    out: dict[str, Any] = {"benchmark": "transport_rates", "environment": C.environment(), "round_trips": round_trips,
                           "units": "round trips in ms; rates in Hz", "rigs": {}}
    for name, (path, where) in RIGS.items():
        C.note(f"[transports] {name}: {round_trips} round trips ...")
        if where == "separate process":
            with tempfile.TemporaryDirectory() as tmp:
                folder = Path(tmp)
                emu = start_emulate(path, 1200.0, write_config=folder / "emulated.toml")
                try:
                    figures = time_rig(emu.config, round_trips)
                    if sweep_seconds > 0 and figures["mode"] == "fixed-rate":  # not a wave generator's
                        C.note(f"[transports] {name}: hilbench sweep at {figures['set_at_most_hz']:g} Hz ...")
                        figures["sweep_at_advised_rate"] = sweep_at(folder / "emulated.toml",
                                                                 float(figures["set_at_most_hz"]), sweep_seconds, folder)
                finally:
                    emu.close()
        else:
            with start_emulators(load_rig(path)) as emu:
                figures = time_rig(emu.config_for_emulators(), round_trips)
        out["rigs"][name] = {"config": str(path.relative_to(REPO)), "emulators": where, **figures}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--round-trips", type=int, default=1000, help="round trips timed per rig (default 1000, as --check)")
    ap.add_argument("--sweep-seconds", type=float, default=10.0,
                    help="the sweep at the advised rate, s (default 10; 0: no sweep)")
    a = ap.parse_args(argv)
    print(json.dumps(run(max(10, a.round_trips), max(0.0, a.sweep_seconds)), indent=2))


if __name__ == "__main__":
    main()
