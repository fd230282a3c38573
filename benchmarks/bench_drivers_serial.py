"""Speed of the serial drivers (PI GCS, Keyence LK-G) against their emulators over a pty.

Measured in one run:

* ``pi_gcs.round_trip``: one sample of per-sample control, ``write(volts)`` then ``read()`` - on the
  wire ``SVA 1 v`` + ``ERR?`` (one write, one reply) then ``POS? 1`` + ``VOL? 1`` (one write, two
  replies) - timed one by one over ``--round-trips`` samples: median and p99 in us;
* ``keyence_lk.round_trip``: one ``read()`` (``M1`` -> ``M1,+01.2345``), the same way (a sensor has no
  write, so its round trip is the read);
* the peer of each: the same bytes through bare pyserial (``write`` + ``read_until``), no parsing, no
  error checks, no retry machinery - what the transport alone costs;
* ``pi_gcs.play``: ``play()`` of a ``--play-samples`` waveform at the servo rate (20 kHz) end to end:
  upload in ``WAV`` chunks of 100 points with ``ERR?`` after each, wave generator and recorder setup,
  ``WGO``, polling ``#9``, ``DRR?`` read-back in chunks of 4096. The emulator computes the waveform as
  fast as the world allows (``realtime = false``); a real controller adds the waveform's own duration.

The emulators run in threads of this process, so driver and emulator share the interpreter: the
figures are an upper bound on the driver's cost (a real device answers from its own CPU, but over a
real line at 115200 bit/s a 20-byte reply alone takes ~1.7 ms). Prints one JSON document on stdout.

    python benchmarks/bench_drivers_serial.py [--round-trips 2000] [--play-samples 100000]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import serial

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import _common as C

from drivers import keyence_lk, pi_gcs


class LinearWorld:
    """output = 2 um/V * input (a piezo stage in its linear range, no dynamics)."""

    def __init__(self) -> None:
        self.u = 0.0

    def command(self, value: float) -> None:
        self.u = float(value)

    def read(self, channel: str) -> float:
        if channel == "output":
            return 2.0 * self.u
        raise KeyError(channel)

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        w = np.asarray(waveform, dtype=np.float64)
        self.u = float(w[-1])
        return {"input": w.copy(), "output": 2.0 * w}


def stats_us(times_s: list[float]) -> dict[str, float]:
    us = np.asarray(times_s) * 1e6
    return {"median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)),
            "mean_us": float(us.mean()), "max_us": float(us.max()), "n": int(us.size)}


def time_each(n: int, fn: Any) -> list[float]:
    for _ in range(min(50, n)):  # warm-up: first calls pay for imports and caches
        fn(0)
    times = []
    for k in range(n):
        t0 = time.perf_counter()
        fn(k)
        times.append(time.perf_counter() - t0)
    return times


def bench_pi(round_trips: int, play_samples: int) -> dict[str, Any]:
    world = LinearWorld()
    emu = pi_gcs.DRIVER.emulator({"url": "unused"}, world)
    try:
        dev = pi_gcs.DRIVER.open({"url": emu.url, "timeout_s": 1.0})
        volts = 5.0 + 4.0 * np.sin(np.arange(round_trips) * 0.01)
        try:
            def driver_trip(k: int) -> None:
                dev.write(float(volts[k]))
                dev.read()

            driver_times = time_each(round_trips, driver_trip)
            wave = 5.0 + 4.0 * np.sin(2 * np.pi * 10.0 * np.arange(play_samples) / dev.servo_rate_hz)
            t0 = time.perf_counter()
            result = dev.play(wave, dev.servo_rate_hz)
            play_s = time.perf_counter() - t0
            play_ok = bool(np.allclose(result["output"], 2.0 * wave, atol=2e-6))
        finally:
            dev.close()
        port = serial.serial_for_url(emu.url, timeout=1.0)
        try:
            def peer_trip(k: int) -> None:
                port.write(f"SVA 1 {volts[k]:.6f}\nERR?\n".encode())
                port.read_until(b"\n")
                port.write(b"POS? 1\nVOL? 1\n")
                port.read_until(b"\n")
                port.read_until(b"\n")

            peer_times = time_each(round_trips, peer_trip)
        finally:
            port.close()
    finally:
        emu.close()
    driver, peer = stats_us(driver_times), stats_us(peer_times)
    return {
        "round_trip": {"what": "write(v) + read(): SVA+ERR?, then POS?+VOL?", **driver},
        "peer_bare_pyserial": {"what": "the same bytes with pyserial write/read_until, no parsing", **peer},
        "ratio_median_driver_over_peer": driver["median_us"] / peer["median_us"],
        "play": {"samples": play_samples, "rate_hz": 20000.0, "seconds_end_to_end": play_s,
                 "waveform_duration_s": play_samples / 20000.0, "recorded_matches_world": play_ok,
                 "wav_chunk_points": 100, "drr_chunk_points": 4096},
    }


def bench_keyence(round_trips: int) -> dict[str, Any]:
    world = LinearWorld()
    world.u = 617.25
    emu = keyence_lk.DRIVER.emulator({"url": "unused"}, world)
    try:
        dev = keyence_lk.DRIVER.open({"url": emu.url, "timeout_s": 1.0})
        try:
            driver_times = time_each(round_trips, lambda k: dev.read())
            ok = dev.read()["output"] == 1234.5
        finally:
            dev.close()
        port = serial.serial_for_url(emu.url, timeout=1.0)
        try:
            def peer_trip(k: int) -> None:
                port.write(b"M1\r")
                port.read_until(b"\r")

            peer_times = time_each(round_trips, peer_trip)
        finally:
            port.close()
    finally:
        emu.close()
    driver, peer = stats_us(driver_times), stats_us(peer_times)
    return {"round_trip": {"what": "read(): M1 -> M1,+01.2345", **driver, "value_ok": ok},
            "peer_bare_pyserial": {"what": "the same bytes with pyserial write/read_until", **peer},
            "ratio_median_driver_over_peer": driver["median_us"] / peer["median_us"]}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--round-trips", type=int, default=2000, help="timed round trips per driver (default 2000)")
    ap.add_argument("--play-samples", type=int, default=100_000, help="samples of the PI play() waveform (default 10^5)")
    a = ap.parse_args(argv)
    C.note("pi-gcs ...")
    pi = bench_pi(a.round_trips, a.play_samples)
    C.note("keyence-lk ...")
    kl = bench_keyence(a.round_trips)
    print(json.dumps({"benchmark": "drivers_serial", "environment": C.environment(),
                      "transport": "pty pair, emulator thread in the same process",
                      "pi_gcs": pi, "keyence_lk": kl}, indent=2))


if __name__ == "__main__":
    main()
