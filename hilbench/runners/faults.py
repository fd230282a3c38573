"""What stops a run on a real rig, said in one line, and making the actuator safe exactly once.

* :class:`DeviceFault` - a device call failed (timeout after the driver's retries, garbage, an error
  reply, a lost transport or heartbeat); names the rig's device, its role and the driver's message.
* :class:`InterlockTripped` - a sensor read NaN (the driver's way of saying over range, alarm or not
  valid) or left the ``range`` configured for its channel.
* :class:`LoopStalled` - the fixed-rate loop produced no sample for the watchdog's time.

:class:`SafeStop` makes the actuator safe (``rig.stop(False)``: ramp to rest through the safety
path, then the device's own stop) at most once per run, whoever asks first: the runner's failure
path or the fixed-rate loop's watchdog thread. Its :attr:`SafeStop.note` says what happened, for the
run's ``reason``.
"""

from __future__ import annotations

import threading
from typing import Any


def one_line(text: object) -> str:
    return " ".join(str(text).split())


class RunFault(Exception):
    """A run stopped by its rig; ``device`` is the rig's name for the device (a ``[devices.NAME]``)."""

    def __init__(self, device: str, message: str):
        self.device = device
        self.message = one_line(message)
        super().__init__(self.message)


class DeviceFault(RunFault):
    """A device call failed; the driver's exception is the ``__cause__``."""

    def __init__(self, device: str, driver: str, action: str, error: BaseException):
        self.driver = driver
        self.action = action
        self.error = error
        detail = getattr(error, "message", None) or str(error) or type(error).__name__
        origin = getattr(error, "device", None)
        kind = type(error).__name__
        text = f"device {device!r} ({driver}) failed to {action}: {kind}: {detail}"
        if origin and origin not in detail:
            text = f"device {device!r} ({driver}, {origin}) failed to {action}: {kind}: {detail}"
        super().__init__(device, text)


class InterlockTripped(RunFault):
    """A sensor reading outside its channel's range, or NaN as its driver reports an invalid value."""


class LoopStalled(RunFault):
    """The fixed-rate loop stopped producing samples; the watchdog made the actuator safe."""


class SafeStop:
    """``rig.stop(False)`` at most once, from any thread; ``note`` says what it did."""

    def __init__(self, rig: Any, io_lock: threading.Lock | None = None):
        self.rig = rig
        self.io_lock = io_lock
        self._once = threading.Lock()
        self.done = False
        self.ok = False
        self.note = ""

    def make_safe(self, why: str = "", *, lock_timeout_s: float | None = None) -> str:
        """Ramp the actuator to rest (once); returns the note. ``why`` prefixes the note.

        With an I/O lock, waits up to ``lock_timeout_s`` for the loop to leave the devices (None:
        don't wait for it, the caller holds or does not need it) and goes ahead anyway after that:
        a loop stuck inside one device call must not keep the actuator from being made safe.
        """
        with self._once:
            if self.done:
                return self.note
            got = False
            if self.io_lock is not None and lock_timeout_s is not None:
                got = self.io_lock.acquire(timeout=lock_timeout_s)
            try:
                rest = self.rig.actuator.rest
                unit = self.rig.actuator.unit
                try:
                    self.rig.stop(False)
                    self.ok = True
                    text = f"actuator ramped to rest ({rest:g} {unit})"
                except Exception as exc:  # noqa: BLE001 - reported in the run's reason
                    text = f"the actuator could not be made safe: {type(exc).__name__}: {one_line(exc)}"
                if lock_timeout_s is not None and self.io_lock is not None and not got:
                    text += " (while the loop was still inside a device call)"
                self.note = f"{why}; {text}" if why else text
                self.done = True
                return self.note
            finally:
                if got:
                    self.io_lock.release()  # type: ignore[union-attr]


def summary(error: BaseException) -> str:
    """One line naming what failed: the device and why for a :class:`RunFault`, else the exception."""
    if isinstance(error, RunFault):
        return error.message
    device = getattr(error, "device", None)
    text = one_line(error) or type(error).__name__
    if device and device not in text:
        text = f"{device}: {text}"
    return f"{type(error).__name__}: {text}"
