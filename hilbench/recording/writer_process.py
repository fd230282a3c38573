"""A recording streamed by its own process, so that a fixed-rate loop never waits for HDF5.

h5py holds the GIL for every call, and an append plus a flush costs hundreds of microseconds: in the
loop's thread (or in another thread of its process) that is lateness. Here the loop stores each
sample into a slot of a ring buffer in shared memory (``slots`` x channels x ``chunk`` float64,
allocated once per sweep; chunk ``c`` goes into slot ``c % slots``) and, at the end of a chunk, hands
it over by storing its sample count and then the count of chunks handed over into the ring's header.
The writer process polls the header every ``POLL_S``, appends each new chunk to the run's datasets in
SWMR mode, accumulates the run's lateness figures (:class:`~hilbench.recording.lateness.LoopStats`),
flushes at least every ``flush_interval_s`` and stores the count of chunks written, which frees their
slots. The loop waits only when every slot is still with the writer (the disk is more than ``slots``
chunks behind).

Plain stores are enough on x86-64, whose stores become visible to other cores in program order (and
loads are not reordered with older loads or later stores); a hand-over costs the loop about a
microsecond. On other processors every hand-over is also one byte on a socket, and every chunk
written one byte back: the system calls order the stores and wake the writer at once (tens of
microseconds each on a virtual machine, the reason x86-64 does without them).

Runs are opened and closed over a second socket (pickled messages): the writer closes the file and
answers with the samples written and the lateness figures, then the loop's process writes the run's
attributes, the status last (SWMR does not cover attribute changes).

The writer ignores SIGINT and SIGTERM and lives in a session of its own, so a terminal's Ctrl-C never
reaches it: the loop, not a signal, ends a run. When the loop's process dies (SIGKILL), the sockets
close: the writer writes every slot it was handed, flushes, closes the file and exits; the run stays
``running`` with every sample the loop handed over.

It is a fresh interpreter (``python -m hilbench.recording.writer_process``): not a fork of the loop's
process (with its numba and device threads), and not multiprocessing's spawn, which would import the
user's script again. The ring is an unlinked file mapped by both (in /dev/shm where it exists); ring
and sockets are inherited descriptors, so nothing is left behind when either process dies.
"""

from __future__ import annotations

import signal

if __name__ == "__main__":  # the writer process: the loop, not a signal, ends a run (before the slow imports)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)

import mmap  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import socket  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Mapping  # noqa: E402
from multiprocessing.connection import Connection, wait  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from hilbench.errors import RecordingWriterError  # noqa: E402
from hilbench.recording.hdf5 import ChannelSpec, RunWriter  # noqa: E402
from hilbench.recording.lateness import LoopStats  # noqa: E402
from hilbench.recording.recover import clear_stale_write_flags  # noqa: E402

#: how long the loop waits for the writer to free a slot (or to close a run) before giving up, s
WRITER_TIMEOUT_S = 30.0
#: how often the writer looks for new chunks, s
POLL_S = 0.002
#: stores become visible to other processes in program order (x86-64's TSO memory model)
ORDERED_STORES = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")
# the ring's header, int64: chunks handed over, chunks written, samples flushed of the run, what the writer
# is doing and since when (CLOCK_MONOTONIC, ns: one clock for every process), then per slot the samples in it
_HANDED, _WRITTEN, _FLUSHED, _DOING, _SINCE, _COUNTS = 0, 1, 2, 3, 4, 5
#: what the writer is doing (header[_DOING]), told when it frees no slot in time: was it waiting for
#: chunks, or in which call on the file has it been stuck
_POLLING, _APPENDING, _FLUSHING, _OPENING, _CLOSING = 0, 1, 2, 3, 4
_DOINGS = {_APPENDING: "appending a chunk to the file", _FLUSHING: "flushing the file",
           _OPENING: "opening the file", _CLOSING: "closing the file"}


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def _map_ring(fd: int, shape: tuple[int, int, int]) -> tuple[mmap.mmap, np.ndarray, np.ndarray]:
    slots, channels, chunk = shape
    n_header = _COUNTS + slots
    mapped = mmap.mmap(fd, 8 * (n_header + slots * channels * chunk))
    header = np.frombuffer(mapped, dtype=np.int64, count=n_header)
    ring = np.frombuffer(mapped, dtype=np.float64, offset=8 * n_header).reshape(shape)
    return mapped, header, ring


def _doing(header: np.ndarray, what: int) -> None:
    """Stamp what the writer starts doing now (the time first: the loop reads the code, then the time)."""
    header[_SINCE] = time.monotonic_ns()
    header[_DOING] = what


def _process_state(pid: int) -> str:
    """The kernel's word on a process (Linux): its state letter and, if told, the call it sleeps in."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        state = stat[stat.rindex(")") + 2:].split(" ", 1)[0]
    except (OSError, ValueError, IndexError):
        return ""
    states = {"R": "running", "S": "sleeping", "D": "in uninterruptible I/O", "T": "stopped", "t": "stopped",
              "Z": "a zombie"}
    told = f"process state {state} ({states.get(state, 'other')})"
    try:
        wchan = Path(f"/proc/{pid}/wchan").read_text().strip()
    except OSError:
        wchan = ""
    return f"{told}, in {wchan}" if wchan and wchan != "0" else told


def _serve(control: Connection, data: socket.socket, header: np.ndarray, ring: np.ndarray, ordered: bool) -> None:
    """The writer process: runs opened and closed on ``control``, chunks taken from the ring."""
    slots = ring.shape[0]
    run: RunWriter | None = None
    names: list[str] = []
    stats: LoopStats | None = None
    late_row = -1
    failed = ""
    written = int(header[_WRITTEN])
    _doing(header, _POLLING)

    def drain() -> None:
        """Write every chunk handed over (a chunk of a failed run is skipped but freed all the same)."""
        nonlocal written, failed
        handed = int(header[_HANDED])
        while written < handed:
            slot = written % slots
            n = int(header[_COUNTS + slot])
            if run is not None and not failed:
                block = ring[slot, :, :n]
                try:
                    _doing(header, _APPENDING)
                    run.append({name: block[i] for i, name in enumerate(names)})
                    if stats is not None:
                        stats.add(block[late_row])
                except Exception as exc:  # noqa: BLE001 - told to the loop when it closes the run
                    failed = _one_line(exc)
            written += 1
            header[_FLUSHED] = run.n_flushed if run is not None else 0
            header[_WRITTEN] = written
            if not ordered:
                data.sendall(b"\x01")

    try:
        while True:
            idle = run.flush_interval_s if run is not None else None
            ready = wait([control, data], POLL_S if ordered else idle)
            if data in ready and not data.recv(65536):
                return  # the loop's process is gone (SIGKILL): the finally keeps what it handed over
            before = written
            drain()
            if written == before and run is not None and run.n_flushed != run.n_samples and (
                    not ordered or time.monotonic() - run.last_flush >= run.flush_interval_s):
                _doing(header, _FLUSHING)
                run.flush()  # appends stopped coming (a slow rate, a loop waiting): flush anyway
                header[_FLUSHED] = run.n_flushed
                _doing(header, _POLLING)
            if control not in ready:
                continue
            message = control.recv()
            try:
                if message[0] == "open":
                    _, path, group, names, flush_interval_s, period_s, paced = message
                    _doing(header, _OPENING)
                    run = RunWriter(Path(path), group, [ChannelSpec(n, "") for n in names], flush_interval_s)
                    run.open()
                    late_row = names.index("lateness") if "lateness" in names else -1
                    stats = LoopStats(period_s, paced) if late_row >= 0 and period_s > 0 else None
                    failed = ""
                    header[_FLUSHED] = 0
                    _doing(header, _POLLING)
                    control.send(("opened",))
                elif message[0] == "close":
                    drain()  # the loop handed its last chunk over before it sent this
                    _doing(header, _CLOSING)
                    n = run.close() if run is not None else 0
                    _doing(header, _POLLING)
                    control.send(("error", failed) if failed else ("closed", n, stats.attrs() if stats else {}))
                    run, stats, failed = None, None, ""
                elif message[0] == "exit":
                    return
            except (EOFError, OSError):
                raise
            except Exception as exc:  # noqa: BLE001 - told to the loop, which fails the run with it
                control.send(("error", _one_line(exc)))
    except (EOFError, OSError):
        pass  # the loop's process is gone (SIGKILL): keep what it handed over
    finally:
        if run is not None:
            drain()
            run.close()


class WriterProcess:
    """The writer process and its ring for one sweep: channels fixed, ``chunk`` samples a slot."""

    def __init__(self, n_channels: int, chunk: int, slots: int = 8, ordered: bool = ORDERED_STORES):
        self.shape = (slots, n_channels, chunk)
        self.ordered = ordered
        fd, name = tempfile.mkstemp(prefix="hilbench-ring-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
        os.unlink(name)  # only the descriptors keep it
        control, control_theirs = socket.socketpair()
        self._data, data_theirs = socket.socketpair()
        try:
            os.ftruncate(fd, 8 * (_COUNTS + slots + slots * n_channels * chunk))
            self._map, self.header, self.ring = _map_ring(fd, self.shape)
            self.ring[:] = 0.0  # touch every page now, not in the loop
            fds = (fd, control_theirs.fileno(), data_theirs.fileno())
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(
                [str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
            self._process = subprocess.Popen(
                [sys.executable, "-m", __name__, *map(str, fds), *map(str, self.shape), str(int(ordered))],
                pass_fds=fds, start_new_session=True, env=env, stdin=subprocess.DEVNULL)
        finally:
            os.close(fd)
            control_theirs.close()
            data_theirs.close()
        self._conn = Connection(control.detach())
        self.pid = self._process.pid
        #: chunks handed over; chunks known written (from the header, or counted from the socket)
        self.handed = 0
        self.acked = 0

    def open_run(self, run: RunWriter, period_s: float = 0.0, paced: bool = False) -> StreamedRun:
        """Stream ``run`` (begun by :meth:`RecordingWriter.begin_run`, not yet appended to) through this
        process; ``period_s`` and ``paced``: a fixed-rate run whose ``lateness`` channel it accumulates."""
        if len(run.channels) != self.shape[1]:
            raise ValueError(f"the ring holds {self.shape[1]} channels, the run has {len(run.channels)}")
        try:
            self._conn.send(("open", str(run.path), run.group_name, [c.name for c in run.channels],
                             run.flush_interval_s, period_s, paced))
        except OSError as exc:
            raise self._ended() from exc
        self._expect("opened")
        return StreamedRun(self, run)

    def hand_over(self, slot: int, n: int) -> None:
        self.header[_COUNTS + slot] = n
        self.handed += 1
        self.header[_HANDED] = self.handed
        if not self.ordered:
            try:
                self._data.sendall(b"\x01")
            except OSError as exc:  # BrokenPipeError: the writer is gone
                raise self._ended() from exc

    def written(self, timeout_s: float = 0.0) -> int:
        """Chunks the writer has written; with ``timeout_s``, waits that long for one more."""
        if self.ordered:
            deadline = time.monotonic() + timeout_s
            before = self.acked
            while True:
                self.acked = int(self.header[_WRITTEN])
                if self.acked > before or time.monotonic() >= deadline:
                    return self.acked
                if not self.alive:
                    raise self._ended()
                time.sleep(2e-4)
        self._data.settimeout(timeout_s)
        try:
            got = self._data.recv(65536)
        except (BlockingIOError, InterruptedError, TimeoutError):
            return self.acked
        except OSError as exc:
            raise self._ended() from exc
        if not got:
            raise self._ended()
        self.acked += len(got)
        return self.acked

    @property
    def n_flushed(self) -> int:
        return int(self.header[_FLUSHED])

    def doing(self) -> str:
        """What the writer process is doing and for how long, and the kernel's word on it when it is
        in a call on the file (its state letter: D is a disk that does not answer)."""
        what = int(self.header[_DOING])
        for_s = (time.monotonic_ns() - int(self.header[_SINCE])) / 1e9
        if what == _POLLING:  # stamped at every look: an old stamp is a writer not given the processor
            told = f"it is waiting for chunks and last looked {for_s:.1f} s ago"
        else:
            told = f"it has been {_DOINGS.get(what, 'doing something unknown')} for {for_s:.1f} s"
        state = _process_state(self.pid)
        return f"{told} ({state})" if state else told

    def _ended(self) -> RecordingWriterError:
        return RecordingWriterError(f"the recording's writer process ended (exit code {self._process.poll()})")

    def _expect(self, kind: str) -> tuple[Any, ...]:
        if not self._conn.poll(WRITER_TIMEOUT_S):
            raise RecordingWriterError(f"the recording's writer process gave no answer in {WRITER_TIMEOUT_S:g} s: "
                                       f"{self.doing()}")
        try:
            reply = self._conn.recv()
        except (EOFError, OSError) as exc:
            raise self._ended() from exc
        if reply[0] == "error":
            raise RecordingWriterError(f"the recording's writer process failed: {reply[1]}")
        if reply[0] != kind:
            raise RecordingWriterError(f"the recording's writer process answered {reply[0]!r}, expected {kind!r}")
        return reply

    @property
    def alive(self) -> bool:
        return self._process.poll() is None

    def close(self) -> None:
        try:
            self._conn.send(("exit",))
        except (OSError, ValueError):
            pass
        try:
            self._process.wait(WRITER_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait(5.0)
        self._conn.close()
        self._data.close()

    def __enter__(self) -> WriterProcess:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class StreamedRun:
    """One run written by a :class:`WriterProcess`; stands in for its :class:`RunWriter` in the loop.

    The loop asks for the next slot (:meth:`slot`, ``rows[channel]`` its row), fills up to ``chunk``
    samples of it and hands them over with :meth:`commit`. ``n_samples`` counts what was handed
    over, ``n_flushed`` what the writer has flushed. :meth:`finish` adds the lateness figures the
    writer accumulated to the run's attributes.
    """

    def __init__(self, writer: WriterProcess, run: RunWriter):
        self.writer = writer
        self.run = run
        self.group_name = run.group_name
        self.channels = run.channels
        self.rows = {c.name: i for i, c in enumerate(run.channels)}
        self.chunk = writer.shape[2]
        self.n_samples = 0
        self._slot: int | None = None
        self._closed = False

    @property
    def n_flushed(self) -> int:
        return self.writer.n_flushed

    def slot(self) -> np.ndarray:
        """The next slot (channels x chunk), waiting for the writer when every slot is still with it."""
        w = self.writer
        slots = w.shape[0]
        if w.handed - w.acked >= slots and w.handed - w.written() >= slots:
            deadline = time.monotonic() + WRITER_TIMEOUT_S
            while w.handed - w.written(min(0.1, max(0.0, deadline - time.monotonic()))) >= slots:
                if time.monotonic() >= deadline:
                    raise RecordingWriterError(f"the recording's writer process freed no slot in "
                                               f"{WRITER_TIMEOUT_S:g} s: {w.doing()}")
        self._slot = w.handed % slots
        return w.ring[self._slot]

    def commit(self, n: int) -> None:
        """Hand the current slot's first ``n`` samples to the writer (nothing when ``n`` is 0)."""
        slot, self._slot = self._slot, None
        assert slot is not None, "commit without a slot"
        if n:
            self.writer.hand_over(slot, n)
            self.n_samples += n

    def finish(self, status: str, reason: str = "", extra_attrs: Mapping[str, Any] | None = None) -> None:
        """Wait for the writer to write every chunk and close the file, then write the run's status."""
        error: RecordingWriterError | None = None
        attrs = dict(extra_attrs or {})
        if not self._closed:
            self._closed = True
            w = self.writer
            try:
                try:
                    w._conn.send(("close",))
                except OSError as exc:
                    raise w._ended() from exc
                _, written, loop_attrs = w._expect("closed")
                deadline = time.monotonic() + WRITER_TIMEOUT_S
                while w.written() < w.handed and time.monotonic() < deadline:
                    w.written(0.1)  # the socket's acknowledgements (sent before the answer)
                self.n_samples = int(written)
                attrs = {**loop_attrs, **attrs}
            except RecordingWriterError as exc:
                error = exc
                reason = f"{reason}; {error}" if reason else str(error)
                status = "failed"
                if not w.alive:  # it died with the file open for SWMR writing
                    clear_stale_write_flags(self.run.path)
        self.run.n_samples = self.n_samples
        self.run.finish(status, reason, attrs)
        if error is not None:
            raise error


def main(argv: list[str]) -> None:
    """``python -m hilbench.recording.writer_process RING_FD CONTROL_FD DATA_FD SLOTS CHANNELS CHUNK ORDERED``."""
    ring_fd, control_fd, data_fd, slots, channels, chunk, ordered = (int(a) for a in argv)
    _, header, ring = _map_ring(ring_fd, (slots, channels, chunk))
    _serve(Connection(control_fd), socket.socket(fileno=data_fd), header, ring, bool(ordered))


if __name__ == "__main__":
    main(sys.argv[1:])
