"""A threaded server for line-based ASCII instruments, on a pty and optionally on loopback TCP.

The pty pair stands in for the RS-232 cable: the emulator owns the master side and the driver opens
the slave's path (``url``) with pyserial exactly as it opens ``/dev/ttyUSB0``. With ``tcp_port``
set (0 = any free port) the same protocol is also served on ``127.0.0.1`` only, for drivers that
reach the instrument as ``socket://127.0.0.1:PORT`` (PI controllers listen on TCP port 50000).

Subclasses implement :meth:`LineServer.handle` (one command -> reply bytes or None) and may override
:meth:`LineServer.split` (how a byte stream is cut into commands). Everything runs in one thread,
so the device state needs no lock; tests read plain attributes.

Fault injection, for the driver tests:

* :meth:`drop_replies` - the next n commands get no reply (the driver times out);
* :meth:`silence` - no replies at all for a while (a device that stops answering, then recovers);
* :meth:`garble_next` - the next reply is replaced by garbage bytes;
* :meth:`disconnect` - the transport closes (pty master closed, sockets closed): the driver sees EOF.

``traffic`` keeps every (direction, bytes) pair, so a test can show what was on the wire.
"""

from __future__ import annotations

import errno
import os
import select
import socket
import threading
import time
import tty
from collections import deque


class _Conn:
    """One byte stream: the pty master or an accepted TCP client."""

    def __init__(self, fd: int, sock: socket.socket | None = None):
        self.fd = fd
        self.sock = sock
        self.buf = b""

    def recv(self) -> bytes | None:
        """Bytes read; b"" at EOF (TCP client gone); None when there was nothing after all."""
        try:
            return self.sock.recv(65536) if self.sock is not None else os.read(self.fd, 65536)
        except BlockingIOError:
            return None
        except OSError as exc:
            if exc.errno == errno.EIO:  # pty: no slave has it open right now; not a disconnect
                return None
            raise

    def close(self) -> None:
        try:
            if self.sock is not None:
                self.sock.close()
            else:
                os.close(self.fd)
        except OSError:
            pass


class LineServer:
    """Serve a line protocol on a pty (``url``) and optionally 127.0.0.1 TCP (``tcp_url``)."""

    eol: bytes = b"\n"
    name: str = "emulator"

    def __init__(self, *, tcp_port: int | None = None, traffic_limit: int = 2000):
        master, slave = os.openpty()
        # Raw mode before anyone talks: with the default cooked mode the slave would echo our replies
        # back to us and translate CR/LF.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master = master
        self._slave = slave  # kept open so the pty survives the driver closing and reopening it
        self.url = os.ttyname(slave)
        self._conns: list[_Conn] = [_Conn(master)]
        self._listener: socket.socket | None = None
        self.tcp_url: str | None = None
        if tcp_port is not None:
            listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind(("127.0.0.1", int(tcp_port)))  # loopback only: an emulator is never on the network
            listener.listen(2)
            listener.setblocking(False)
            self._listener = listener
            self.tcp_url = f"socket://127.0.0.1:{listener.getsockname()[1]}"
        self.traffic: deque[tuple[str, bytes]] = deque(maxlen=traffic_limit)
        self._drop = 0
        self._silent_until = 0.0
        self._garbage: bytes | None = None
        self._disconnect = threading.Event()
        self._stop = threading.Event()
        self.disconnected = False
        self.thread_error: BaseException | None = None  # an exception that ended the serving thread
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-emulator", daemon=True)

    def start(self) -> LineServer:
        self._thread.start()
        return self

    # -- what subclasses provide ---------------------------------------------------------------------
    def handle(self, command: bytes) -> bytes | None:  # pragma: no cover - abstract
        raise NotImplementedError

    def split(self, data: bytes) -> tuple[list[bytes], bytes]:
        """Cut complete commands (without end of line) off the front of ``data``; return the rest."""
        *commands, rest = data.split(self.eol)
        return commands, rest

    def idle(self) -> None:
        """Called about every 20 ms from the serving thread (background work such as a wave generator)."""

    # -- fault injection -------------------------------------------------------------------------------
    def drop_replies(self, n: int = 1) -> None:
        """The next ``n`` commands are executed but get no reply."""
        self._drop = int(n)

    def silence(self, seconds: float) -> None:
        """Answer nothing for ``seconds`` (commands are still executed)."""
        self._silent_until = time.monotonic() + float(seconds)

    def garble_next(self, data: bytes | None = None) -> None:
        """Replace the next reply by ``data`` (default: non-ASCII bytes ending in the protocol's end of line)."""
        self._garbage = bytes(data) if data is not None else b"\x8f\xfe#!garbled\xff" + self.eol

    def disconnect(self, timeout_s: float = 2.0) -> None:
        """Close the transport as a pulled cable or a powered-off controller would."""
        self._disconnect.set()
        deadline = time.monotonic() + timeout_s
        while not self.disconnected and self._thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.005)

    # -- serving -------------------------------------------------------------------------------------
    def _reply_for(self, command: bytes) -> bytes | None:
        self.traffic.append(("in", command))
        reply = self.handle(command)
        if reply is None:
            return None
        if self._drop > 0:
            self._drop -= 1
            return None
        if time.monotonic() < self._silent_until:
            return None
        if self._garbage is not None:
            reply, self._garbage = self._garbage, None
        self.traffic.append(("out", reply))
        return reply

    def _send(self, conn: _Conn, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._stop.is_set():
            try:
                n = conn.sock.send(view) if conn.sock is not None else os.write(conn.fd, view)
                view = view[n:]
            except BlockingIOError:
                # the reader is slow (a large data-recorder dump): wait until it drains, but keep
                # honouring close() so the thread can always be stopped
                select.select([], [conn.fd], [], 0.05)

    def _close_transport(self) -> None:
        for conn in self._conns:
            conn.close()
        self._conns = []
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        self.disconnected = True

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self._disconnect.is_set():
                    self._close_transport()
                    self._disconnect.clear()
                if self.disconnected:
                    time.sleep(0.02)
                    continue
                fds = [c.fd for c in self._conns] + ([self._listener.fileno()] if self._listener else [])
                ready, _, _ = select.select(fds, [], [], 0.02)
                if self._listener is not None and self._listener.fileno() in ready:
                    try:
                        client, _ = self._listener.accept()
                        client.setblocking(False)
                        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                        self._conns.append(_Conn(client.fileno(), client))
                    except BlockingIOError:
                        pass
                for conn in list(self._conns):
                    if conn.fd not in ready:
                        continue
                    data = conn.recv()
                    if data is None:
                        time.sleep(0.002)  # pty without a reader (EIO): wait for the driver
                        continue
                    if not data:  # TCP client left
                        conn.close()
                        self._conns.remove(conn)
                        continue
                    commands, conn.buf = self.split(conn.buf + data)
                    replies = [r for r in (self._reply_for(c) for c in commands) if r]
                    if replies:
                        self._send(conn, b"".join(replies))
                self.idle()
        except BaseException as exc:  # kept for the test to see: a serving thread never dies silently
            self.thread_error = exc
            raise
        finally:
            if not self.disconnected:
                self._close_transport()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop serving and release the pty and sockets (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        if self._slave is not None:
            try:
                os.close(self._slave)
            except OSError:
                pass
            self._slave = None

    def __enter__(self) -> LineServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
