"""A line-oriented serial transport for the ASCII-protocol drivers (PI GCS, Keyence LK-G).

Opens any pyserial URL (``serial_for_url``: a device path such as ``/dev/ttyUSB0`` or a pty,
``socket://host:port``, ``rfc2217://...``) and maps the transport's failures onto the driver
contract:

* no complete line within ``timeout_s`` -> :class:`~drivers.base.DeviceTimeout` (the caller retries);
* a closed port, EOF or an I/O error -> :class:`~drivers.base.DeviceLost` naming the device;
* the port cannot be opened -> :class:`~drivers.base.DeviceError`.

Reading is buffered by hand rather than with ``Serial.read_until``: pyserial's ``read_until`` reads
one byte per call, which makes a 100k-line data-recorder dump take seconds of pure syscalls. Here
every call takes whatever the OS holds (``in_waiting``), and lines are cut out of one buffer.
"""

from __future__ import annotations

import time

import serial

from drivers.base import DeviceError, DeviceLost, DeviceTimeout


def short(data: bytes | str, limit: int = 60) -> str:
    """A one-line, bounded rendering of wire data for error messages."""
    text = repr(data)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class SerialLink:
    """One open serial transport with an end-of-line byte sequence and a per-line timeout."""

    def __init__(self, url: str, *, device: str, baud: int, timeout_s: float, eol: bytes):
        self.url = url
        self.device = device
        self.eol = eol
        self.timeout_s = float(timeout_s)
        self._buf = bytearray()
        self._pos = 0  # start of unread data in _buf (compacted lazily: deleting the front per line is O(n))
        try:
            # write_timeout: a peer that stops reading fills the OS buffer; a bounded write turns that
            # into a timeout instead of a hang.
            self.port = serial.serial_for_url(url, baudrate=int(baud), timeout=self.timeout_s,
                                              write_timeout=max(self.timeout_s, 1.0))
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(device, f"cannot open {url}: {exc}") from exc

    # -- writing -----------------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeout(self.device, f"write of {short(data)} timed out") from exc
        except Exception as exc:
            # any transport failure (SerialException, OSError, termios.error from a hung-up pty,
            # pyserial's TypeError after close) means the link is gone
            raise DeviceLost(self.device, f"transport {self.url} closed while writing: {exc}") from exc

    # -- reading -----------------------------------------------------------------------------------
    def _fill(self) -> bool:
        """Append what the OS holds (waiting up to the port timeout for the first byte); False on timeout."""
        try:
            waiting = self.port.in_waiting
            data = self.port.read(waiting if waiting > 0 else 1)
        except Exception as exc:  # the link is gone, whatever the exception type (see write)
            raise DeviceLost(self.device, f"transport {self.url} closed: {exc}") from exc
        if not data:
            return False
        self._buf += data
        return True

    def read_line(self, what: str, timeout_s: float | None = None) -> bytes:
        """The next line without its end-of-line bytes; DeviceTimeout naming ``what`` if none comes."""
        wait_s = self.timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + wait_s
        while True:
            end = self._buf.find(self.eol, self._pos)
            if end >= 0:
                line = bytes(self._buf[self._pos:end])
                self._pos = end + len(self.eol)
                if self._pos > 65536 and self._pos * 2 > len(self._buf):
                    del self._buf[: self._pos]
                    self._pos = 0
                return line
            self._fill()
            # checked after the fill even when bytes came: a peer streaming garbage without an
            # end of line must not keep us here forever
            if time.monotonic() >= deadline and self._buf.find(self.eol, self._pos) < 0:
                partial = bytes(self._buf[self._pos:])
                detail = f" (partial {short(partial)})" if partial else ""
                raise DeviceTimeout(self.device, f"no reply to {what} within {wait_s:g} s{detail}")

    def discard_input(self) -> None:
        """Drop stale bytes (a late reply after a timeout, garbage) so the next reply is the right one."""
        self._buf.clear()
        self._pos = 0
        try:
            self.port.reset_input_buffer()
        except Exception as exc:
            raise DeviceLost(self.device, f"transport {self.url} closed: {exc}") from exc

    def close(self) -> None:
        try:
            self.port.close()
        except Exception:  # noqa: S110 - already gone: closing is best effort
            pass
