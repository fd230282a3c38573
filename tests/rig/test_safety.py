"""The actuator path's ramp: every step within the slew limit as the limiter itself checks it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from hilbench.rig.safety import command_path, ramp


def test_a_ramp_passes_the_slew_limiter_unchanged_and_ends_exactly_on_its_target():
    # linspace's rounding can put a step an ulp past max_step; the limiter would clip it and a
    # ramp to rest would end at -2.8e-16 instead of 0 (a CANopen fault test caught it)
    # Starts a sine's sample away from rest, and starts a whole number of steps away, are where
    # the quotient distance / max_step sits on an integer and rounding decides.
    rng = np.random.default_rng(20261201)
    starts = [5.0 * np.sin(2 * np.pi * k / 1000) for k in range(2001)]
    cases = [(s, 0.0, 0.2) for s in starts]
    cases += [(k * 0.2, 0.0, 0.2) for k in range(-32, 33)] + [(k * 0.01, 0.0, 0.01) for k in range(-650, 651)]
    cases += [(float(rng.uniform(-6.5, 6.5)), float(rng.uniform(-6.5, 6.5)), float(rng.uniform(0.001, 1.0)))
              for _ in range(5000)]
    for start, target, max_step in cases:
        commands = ramp(start, target, max_step)
        state = np.array([start])
        out = np.empty_like(commands)
        changed = command_path(commands, -6.5, 6.5, max_step, state, out)
        assert changed == 0, (start, target, max_step)
        assert state[0] == target, (start, target, max_step)


def test_a_ramp_to_where_it_stands_is_empty():
    assert ramp(1.5, 1.5, 0.1).shape == (0,)


def test_the_actuator_path_is_compiled_at_import_not_at_the_loops_first_sample() -> None:
    # a lazy compile at the fixed-rate loop's first sample took 0.26-2 s and tripped its watchdog
    code = ("from hilbench.rig.safety import command_path; "
            "print(len(command_path.nopython_signatures), command_path._can_compile)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.stdout.split() == ["1", "False"], done.stderr
