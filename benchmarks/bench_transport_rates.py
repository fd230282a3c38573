"""What sample rate each transport can hold: the devices' round trip through the real drivers.

For each kind of real rig hilbench drives, the rig config is pointed at its emulators (the way a user
dry-runs a config) and the rate check of ``hilbench sweep --check`` times ``--round-trips`` round
trips (the actuator written its present value, every sensor read): p50 and p99 per device and for
the whole sample, and the highest rate the loop can hold there (0.8 / p99, as ``--check`` says).

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

    python benchmarks/bench_transport_rates.py [--round-trips 500]
"""

from __future__ import annotations

import argparse
import json
import sys
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


def time_rig(config: Any, round_trips: int) -> dict[str, Any]:
    from hilbench.rig.rig import Rig
    from hilbench.runners.rate_check import _round_down, time_round_trips

    with Rig(config) as rig:
        rig.start_run(rig.actuator.rest)
        time_round_trips(rig, 50)  # connections warm
        trips = time_round_trips(rig, round_trips)
    described = trips.describe()
    return {**{(k[:-2] + "_ms" if k.endswith("_s") else k): (round(v * 1e3, 4) if k.endswith("_s") else v)
               for k, v in described.items() if k != "devices"},
            "devices_ms": {d: {k[:-2] + "_ms": round(v * 1e3, 4) for k, v in f.items()}
                           for d, f in described["devices"].items()},
            "max_rate_hz": round(trips.max_rate_hz, 1), "set_at_most_hz": _round_down(trips.max_rate_hz)}


def run(round_trips: int) -> dict[str, Any]:
    from hilbench.rig.config import load_rig
    from hilbench.rig.emulation import start_emulators

    out: dict[str, Any] = {"benchmark": "transport_rates", "environment": C.environment(), "round_trips": round_trips,
                           "units": "round trips in ms; rates in Hz", "rigs": {}}
    for name, (path, where) in RIGS.items():
        C.note(f"[transports] {name}: {round_trips} round trips ...")
        if where == "separate process":
            emu = start_emulate(path, 600.0)
            try:
                figures = time_rig(emu.config, round_trips)
            finally:
                emu.close()
        else:
            with start_emulators(load_rig(path)) as emu:
                figures = time_rig(emu.config_for_emulators(), round_trips)
        out["rigs"][name] = {"config": str(path.relative_to(REPO)), "emulators": where, **figures}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--round-trips", type=int, default=500, help="round trips timed per rig (default 500)")
    a = ap.parse_args(argv)
    print(json.dumps(run(max(10, a.round_trips)), indent=2))


if __name__ == "__main__":
    main()
