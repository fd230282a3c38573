"""The simulated plant as the physics behind device emulators (``drivers.base.World``).

An emulator speaks a real device's protocol; what it measures comes from here. ``command`` advances
the plant by one sample with the actuator's new input (the loop's sample rate), ``read`` returns the
latest value of a channel, and ``play`` runs a whole waveform (a controller's wave generator). The
world is shared by every emulator of one rig: the Modbus module's analog output moves the plant
that the CANopen sensor then reads, as on a real bench.
"""

from __future__ import annotations

import threading

import numpy as np

from hilbench.sim.plant import Plant


class SimWorld:
    """A :class:`~hilbench.sim.plant.Plant` behind emulators; thread-safe (emulators serve in threads)."""

    def __init__(self, plant: Plant, rest: float = 0.0):
        self.plant = plant
        self._lock = threading.Lock()
        self.commands = 0  # samples advanced through command()
        self.last_command = float(rest)
        self._latest: dict[str, float] = {}
        self.command(rest)  # powered up at rest, like the simulated rig

    def command(self, value: float) -> None:
        """The actuator's input (A or V) for the next sample: advance the plant by one sample."""
        with self._lock:
            result = self.plant.step(float(value))
            self.last_command = float(value)
            self.commands += 1
            self._latest = {"output": float(result.output[0]), "input": float(value),
                            **{k: float(v[0]) for k, v in result.aux.items()}}

    def read(self, channel: str) -> float:
        """Latest value of ``channel`` (``output`` um, ``current`` A, ``temperature`` degC, ...); NaN if unknown."""
        with self._lock:
            return self._latest.get(channel, float("nan"))

    def play(self, waveform: np.ndarray, rate_hz: float) -> dict[str, np.ndarray]:
        """Run ``waveform`` through the plant in one block; the plant's own rate is the loop's.

        A controller's wave generator runs at ``rate_hz``; the plant was built for its rig's sample
        rate, so the two must agree (an emulator refuses a mismatch before playing).
        """
        if abs(rate_hz - self.plant.sample_rate_hz) > 1e-9 * self.plant.sample_rate_hz:
            raise ValueError(f"waveform rate {rate_hz:g} Hz differs from the simulated plant's "
                             f"{self.plant.sample_rate_hz:g} Hz")
        u = np.ascontiguousarray(waveform, dtype=np.float64)
        with self._lock:
            result = self.plant.simulate(u)
            self.commands += u.shape[0]
            if u.shape[0]:
                self.last_command = float(u[-1])
                self._latest = {"output": float(result.output[-1]), "input": float(u[-1]),
                                **{k: float(v[-1]) for k, v in result.aux.items()}}
        n = u.shape[0]
        return {"time": np.arange(n) / rate_hz, "input": u, "output": result.output, **result.aux}
