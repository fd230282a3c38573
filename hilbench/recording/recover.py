"""Recover a recording whose writer was killed while it was in SWMR mode.

HDF5 marks a file open for (SWMR) writing in the superblock's file consistency flags. A writer killed
with SIGKILL cannot clear them, so afterwards plain ``h5py.File(path, "r")`` refuses the file ("file
is already open for write") although its content is consistent (that is what SWMR guarantees);
``h5py.File(path, "r", swmr=True)`` opens it, and so does every hilbench reader.

:func:`clear_stale_write_flags` does what HDF5's ``h5clear -s`` does, in pure Python: when no process
holds the file's lock (HDF5 takes an exclusive ``flock`` while a writer has the file open), it zeroes
the flags and rewrites the superblock checksum (Jenkins lookup3, as the HDF5 format specifies).
"""

from __future__ import annotations

import fcntl
import os
import struct
from pathlib import Path

_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_MASK = 0xFFFFFFFF


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _MASK


def lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle``, the checksum of HDF5 metadata."""
    length = len(data)
    a = b = c = (0xDEADBEEF + length + initval) & _MASK
    i = 0
    while length - i > 12:
        a = (a + int.from_bytes(data[i : i + 4], "little")) & _MASK
        b = (b + int.from_bytes(data[i + 4 : i + 8], "little")) & _MASK
        c = (c + int.from_bytes(data[i + 8 : i + 12], "little")) & _MASK
        a = (a - c) & _MASK; a ^= _rot(c, 4); c = (c + b) & _MASK  # noqa: E702
        b = (b - a) & _MASK; b ^= _rot(a, 6); a = (a + c) & _MASK  # noqa: E702
        c = (c - b) & _MASK; c ^= _rot(b, 8); b = (b + a) & _MASK  # noqa: E702
        a = (a - c) & _MASK; a ^= _rot(c, 16); c = (c + b) & _MASK  # noqa: E702
        b = (b - a) & _MASK; b ^= _rot(a, 19); a = (a + c) & _MASK  # noqa: E702
        c = (c - b) & _MASK; c ^= _rot(b, 4); b = (b + a) & _MASK  # noqa: E702
        i += 12
    tail = data[i:]
    if not tail:
        return c
    tail = tail + b"\x00" * (12 - len(tail))
    a = (a + int.from_bytes(tail[0:4], "little")) & _MASK
    b = (b + int.from_bytes(tail[4:8], "little")) & _MASK
    c = (c + int.from_bytes(tail[8:12], "little")) & _MASK
    c ^= b; c = (c - _rot(b, 14)) & _MASK  # noqa: E702
    a ^= c; a = (a - _rot(c, 11)) & _MASK  # noqa: E702
    b ^= a; b = (b - _rot(a, 25)) & _MASK  # noqa: E702
    c ^= b; c = (c - _rot(b, 16)) & _MASK  # noqa: E702
    a ^= c; a = (a - _rot(c, 4)) & _MASK  # noqa: E702
    b ^= a; b = (b - _rot(a, 14)) & _MASK  # noqa: E702
    c ^= b; c = (c - _rot(b, 24)) & _MASK  # noqa: E702
    return c


def write_flags(path: str | os.PathLike[str]) -> int:
    """The superblock's file consistency flags (0 = closed cleanly); -1 for old superblocks."""
    with open(path, "rb") as f:
        head = f.read(12)
    if head[:8] != _SIGNATURE or head[8] not in (2, 3):
        return -1
    return head[11]


def clear_stale_write_flags(path: str | os.PathLike[str]) -> bool:
    """Clear the write flags left by a killed writer; returns True when something was cleared.

    Refuses (returns False) when another process holds the file's lock, i.e. a writer is alive.
    """
    path = Path(path)
    with open(path, "r+b") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False  # a live writer holds it: its flags are not stale
        try:
            head = f.read(12)
            if head[:8] != _SIGNATURE or head[8] not in (2, 3) or head[11] == 0:
                return False
            offsets = head[9]
            size = 12 + 4 * offsets
            f.seek(0)
            block = bytearray(f.read(size + 4))
            (stored,) = struct.unpack("<I", bytes(block[size : size + 4]))
            if lookup3(bytes(block[:size])) != stored:
                return False  # not the superblock we understand: leave it alone
            block[11] = 0
            block[size : size + 4] = struct.pack("<I", lookup3(bytes(block[:size])))
            f.seek(0)
            f.write(bytes(block))
            f.flush()
            os.fsync(f.fileno())
            return True
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
