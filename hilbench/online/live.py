"""Online identification live, in the fixed-rate loop of a rig of real devices (issue 59).

:class:`IdentifierLaw` is a :class:`hilbench.runners.fixed_rate.LoopLaw` that leaves the excitation's
commands as they are and, every sample, feeds the applied command and the measured output to the
online identifier (:class:`hilbench.online.oiir.OIIR`, paper 000: FPMPI front end, OIIR weights by
RLS): the run records its one-step-ahead prediction ``online`` (um) and the weights after the sample
(``weight_p0`` .., ``weight_q1`` ..) as channels, while it runs. The identifier is the same kernel the
replay of a recording runs (:meth:`OIIR.run`), so a live run and the replay of its recording agree.

A fresh identifier starts each run (:meth:`IdentifierLaw.start_run`), as the replay does.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hilbench.recording.hdf5 import ChannelSpec

#: samples the law's buffers hold before they grow (the runner takes them every chunk)
INITIAL_CAPACITY = 4096


def weight_channel(name: str) -> str:
    return f"weight_{name}"


class IdentifierLaw:
    """The online identifier in the loop; ``make_identifier()`` returns a fresh :class:`OIIR`."""

    reads_reference = False

    def __init__(self, make_identifier: Any, output_unit: str = "um"):
        self._make = make_identifier
        make_identifier().step(0.0, 0.0)  # compiled (or loaded) before the first deadline, on a throwaway
        self.oiir = make_identifier()
        names = self.oiir.weight_names
        self.channels = [ChannelSpec("online", output_unit, "online model output y_m(k), predicted before y(k) "
                                                            "was used (000 eq. 9)")]
        self.channels += [ChannelSpec(weight_channel(n), "", f"OIIR weight {n} after the sample (RLS, 000 eq. 12)")
                          for n in names]
        self._names = [c.name for c in self.channels]
        self._buf = np.empty((INITIAL_CAPACITY, len(self._names)))
        self._n = 0
        self._theta = self.oiir.filter_weights

    def start_run(self) -> None:
        """A fresh identifier for the next run (the replay's convention)."""
        self.oiir = self._make()
        self._theta = self.oiir.filter_weights
        self._n = 0

    def command(self, source: float) -> float:
        return source

    def commit(self, source: float, applied: float, row: dict[str, float]) -> None:
        y_m = self.oiir.step(applied, row["output"])
        n = self._n
        if n == self._buf.shape[0]:  # grows by chunks, not per sample
            self._buf = np.concatenate([self._buf, np.empty_like(self._buf)])
        buf = self._buf[n]
        buf[0] = y_m
        buf[1:] = self._theta
        self._n = n + 1

    def take(self, n: int) -> dict[str, np.ndarray]:
        rows = self._buf[self._n - n:self._n]
        out = {name: rows[:, i].copy() for i, name in enumerate(self._names)}
        self._n = 0
        return out

    def finish_attrs(self, samples: int) -> dict[str, Any]:
        import json

        return {"online_identifier": json.dumps({"M": self.oiir.M, "N": self.oiir.N, **self.oiir.counters(),
                                                 "static_gain": self.oiir.static_gain()}, default=float)}
