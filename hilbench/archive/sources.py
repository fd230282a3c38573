"""Which recordings a batch covers, and the content hash that keys their results.

A source is a folder (every ``*.h5``/``*.hdf5`` below it), a glob pattern, a recording, or a list
file (``.txt``/``.lst``: one path per line, relative to the list file; ``#`` starts a comment).
The recordings are keyed by the SHA-256 of their bytes, so a result belongs to the content, not to
the name: a renamed or copied file is not refitted, an edited one is. Hashing reads every file once;
the digests are cached beside the results by path, size and modification time, so a rerun over an
unchanged archive reads nothing.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path

from hilbench.errors import UserError

RECORDING_SUFFIXES = (".h5", ".hdf5")
LIST_SUFFIXES = (".txt", ".lst", ".list")
_BLOCK = 1 << 20  # bytes read per hashing step: large enough for disk throughput, small in memory


def _is_recording(path: Path) -> bool:
    return path.suffix.lower() in RECORDING_SUFFIXES


def _from_list_file(path: Path) -> list[Path]:
    found: list[Path] = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        entry = Path(text).expanduser()
        entry = entry if entry.is_absolute() else path.parent / entry
        if not entry.exists():
            raise UserError(f"line {number}: {text!r} does not exist", where=str(path),
                            hint="paths in a list file are relative to the list file's folder")
        found.extend(_expand(str(entry)))
    return found


def _expand(source: str) -> list[Path]:
    path = Path(source).expanduser()
    if path.is_dir():
        return sorted(p for p in path.rglob("*") if p.is_file() and _is_recording(p))
    if path.is_file():
        if path.suffix.lower() in LIST_SUFFIXES:
            return _from_list_file(path)
        return [path]
    if glob.has_magic(source):
        return sorted(Path(p) for p in glob.glob(os.path.expanduser(source), recursive=True)
                      if Path(p).is_file() and _is_recording(Path(p)))
    raise UserError(f"{source!r}: no such file or folder", where="SOURCE",
                    hint="give folders, recordings (.h5), glob patterns in quotes ('data/**/*.h5') or a list file (.txt)")


def find_recordings(sources: Sequence[str]) -> list[Path]:
    """Every recording the sources name, resolved, each once, in the order given (a folder's sorted)."""
    if not sources:
        raise UserError("no source given", where="SOURCE", hint="a folder, a glob, recordings or a list file")
    seen: set[Path] = set()
    found: list[Path] = []
    for source in sources:
        matches = _expand(source)
        if not matches:
            raise UserError(f"{source!r}: no recordings (.h5, .hdf5) found", where="SOURCE")
        for path in matches:
            resolved = path.resolve()
            if resolved not in seen:
                seen.add(resolved)
                found.append(resolved)
    return found


def content_hash(path: Path) -> str:
    """SHA-256 of the file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            digest.update(block)
    return digest.hexdigest()


class HashCache:
    """Digests of files by (path, size, mtime_ns), kept in a JSON file beside the results."""

    def __init__(self, file: Path):
        self.file = file
        self.entries: dict[str, list] = {}
        if file.exists():
            try:
                self.entries = json.loads(file.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                self.entries = {}  # a damaged cache costs one rehash, nothing else

    def digest(self, path: Path) -> str:
        stat = path.stat()
        stamp = [stat.st_size, stat.st_mtime_ns]
        entry = self.entries.get(str(path))
        if entry is not None and entry[:2] == stamp:
            return str(entry[2])
        value = content_hash(path)
        self.entries[str(path)] = [*stamp, value]
        return value

    def save(self) -> None:
        tmp = self.file.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.entries), encoding="utf-8")
        os.replace(tmp, self.file)
