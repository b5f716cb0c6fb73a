"""Atomic result folders: every output lands whole or not at all, the record last.

:class:`OutputFolder` is opened before any work starts, so an unusable ``--out`` (an
existing file, ``/dev/full``, a read-only or full folder, the filesystem root, a folder that is or
holds one of the run's inputs) is refused at once, before anything in it is touched. It takes a
lock (``.geopose.lock``; a second run into the same folder is refused while the first
holds it), clears the previous run's results (the completion marker first), and writes
each file to a temporary name in the same folder, flushed to disk, then renames it into
place. The record (``result.json``) is written last and lists the SHA-256 of every file
written beside it, so a record never describes files that are not there: a run killed at
any point leaves either no record or a complete, matching set.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Any, Callable, Mapping

from .errors import InputError

__all__ = ["OutputFolder", "LOCK_NAME", "RECORD_NAME", "TEMP_PREFIX", "atomic_write", "check_holds_no_input"]

LOCK_NAME = ".geopose.lock"
RECORD_NAME = "result.json"
#: Temporary files start with this (and are removed when a new run opens the folder).
TEMP_PREFIX = ".geopose-tmp-"


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # e.g. Windows: folders cannot be opened
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: Path, write: Callable[[Path], Any]) -> Path:
    """Call ``write(tmp)`` for a temporary file beside ``path`` (same suffix), flush it to disk and
    rename it to ``path``; the temporary file is removed if anything fails."""
    fd, tmp_name = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the file the mode a plain open() would
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def check_holds_no_input(folder: Path, inputs: Mapping[str, Path]) -> None:
    """Refuse an output folder that is the filesystem root, or is or contains any of ``inputs`` (label -> file
    or folder; symlinks resolved): clearing or writing it could delete or replace an input."""
    where = folder.resolve()
    if where == Path(where.anchor):
        raise InputError(f"--out {folder} is the filesystem root: choose a folder of its own for the results")
    for label, path in inputs.items():
        target = path.resolve()
        if target == where or where in target.parents:
            what = "is" if target == where else "contains"
            raise InputError(f"--out {folder} {what} the input {path} ({label}): the run's outputs could replace or delete it; "
                             "choose an --out folder that holds none of the inputs")


class _Lock:
    """An exclusive lock on ``folder/.geopose.lock``, released when the process ends (flock / msvcrt)."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / LOCK_NAME
        self.handle = open(self.path, "a+")
        try:
            try:
                import fcntl

                fcntl.flock(self.handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except ImportError:  # Windows
                import msvcrt

                self.handle.seek(0)
                msvcrt.locking(self.handle.fileno(), msvcrt.LK_NBLCK, 1)
        except OSError:
            self.handle.seek(0)
            holder = self.handle.read().strip() or "another process"
            self.handle.close()
            raise InputError(f"another geopose run ({holder}) is writing into {folder}: wait for it to finish or choose "
                             "another --out folder") from None
        self.handle.seek(0)
        self.handle.truncate()
        self.handle.write(f"pid {os.getpid()}\n")
        self.handle.flush()

    def release(self) -> None:
        if not self.handle.closed:
            self.handle.close()


class OutputFolder:
    """The output folder of one run; use as a context manager around the whole run.

    ``names`` are the files a run writes (besides the record); they and the record are
    removed when the folder is opened. Files go in with :meth:`write_file` / :meth:`write_bytes`;
    :meth:`commit` writes the record last, with ``outputs`` = the SHA-256 of each file written.
    """

    def __init__(self, folder: str | os.PathLike, names: tuple[str, ...] = (), record_name: str = RECORD_NAME,
                 inputs: Mapping[str, str | os.PathLike] | None = None) -> None:
        self.folder = Path(folder)
        self.inputs = {label: Path(p) for label, p in (inputs or {}).items() if p is not None}
        self.record_name = record_name
        self.names = tuple(names)
        self.written: dict[str, str] = {}
        self._lock: _Lock | None = None

    def __enter__(self) -> "OutputFolder":
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def open(self) -> None:
        """Check that the folder can be written and holds no input, lock it and clear the previous results."""
        folder = self.folder
        check_holds_no_input(folder, self.inputs)
        if folder.exists() and not folder.is_dir():
            raise InputError(f"--out {folder} exists and is not a folder: choose a folder (it is created if missing)")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"cannot create the output folder {folder} ({exc.strerror or exc}): choose a writable --out") from None
        try:
            probe = atomic_write(folder / f"{TEMP_PREFIX}probe.txt", lambda p: p.write_bytes(b"geopose write test\n" * 64))
            probe.unlink()
        except OSError as exc:
            raise InputError(f"cannot write into {folder} ({exc.strerror or exc}): free space or choose a writable --out") from None
        try:
            self._lock = _Lock(folder)
        except OSError as exc:
            raise InputError(f"cannot lock {folder / LOCK_NAME} ({exc.strerror or exc}): choose a writable --out") from None
        for name in (self.record_name, *self.names):  # the completion marker first
            (folder / name).unlink(missing_ok=True)
        for stale in folder.glob(f"{TEMP_PREFIX}*"):
            stale.unlink(missing_ok=True)
        _fsync_dir(folder)

    def close(self) -> None:
        """Release the lock (the lock file stays: removing it could let two later runs lock two files)."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def _check(self, name: str) -> Path:
        if self._lock is None:
            raise RuntimeError("OutputFolder used before open()")
        if name not in self.names:
            raise RuntimeError(f"{name} is not one of the outputs {self.names} declared when the folder was opened")
        return self.folder / name

    def write_file(self, name: str, write: Callable[[Path], Any]) -> Path:
        """Write output ``name`` with ``write(tmp_path)`` (e.g. an image writer), atomically."""
        path = atomic_write(self._check(name), write)
        self.written[name] = hashlib.sha256(path.read_bytes()).hexdigest()
        return path

    def write_bytes(self, name: str, data: bytes) -> Path:
        return self.write_file(name, lambda p: p.write_bytes(data))

    def commit(self, record: dict) -> Path:
        """Write the record last: ``record`` plus ``outputs`` (name -> SHA-256 of every file written)."""
        if self._lock is None:
            raise RuntimeError("OutputFolder used before open()")
        full = {**record, "outputs": dict(self.written)}
        return atomic_write(self.folder / self.record_name, lambda p: p.write_text(json.dumps(full, indent=1)))
