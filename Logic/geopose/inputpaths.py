"""What a user's input path may be: a regular file or a folder, read within a byte bound.

A device (``/dev/zero``), a FIFO or a socket, also behind a symlink, is refused before it is
opened (``os.stat`` follows links; opening a FIFO blocks until a writer comes, reading a device
never ends). Files are read with :func:`read_bounded`, which opens without blocking, checks the
open handle, refuses a size over its bound and sizes its buffer by the regular file's size (a file
that changes while it is read is refused, not read on). Every refusal is an
:class:`~geopose.errors.InputError` naming the path.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from .errors import InputError

__all__ = ["input_kind", "regular_file", "read_bounded", "folder_files"]

_REMEDY = "give a regular file or a folder (not a device, FIFO or socket)"


def _special(mode: int) -> str:
    for test, name in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def input_kind(path: Path, what: str) -> str:
    """``"file"`` or ``"folder"`` for an existing regular file or folder (symlinks followed); a missing path
    or a special file is an :class:`InputError` naming ``what`` (e.g. "DSA run")."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise InputError(f"{what} not found: {path} (check the path)") from None
    except OSError as exc:
        raise InputError(f"cannot read the {what} {path} ({exc.strerror or exc}): check the path and its permissions") from None
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "folder"
    raise InputError(f"the {what} {path} is {_special(mode)}: {_REMEDY}")


def regular_file(path: Path, what: str) -> Path:
    """``path`` if it is a regular file (symlinks followed), else an :class:`InputError`."""
    if input_kind(path, what) != "file":
        raise InputError(f"the {what} {path} is a folder, not a file: give the file itself")
    return path


def read_bounded(path: Path, limit_bytes: int, what: str, remedy: str) -> bytes:
    """The bytes of the regular file ``path``; more than ``limit_bytes`` is an :class:`InputError` ending in
    ``remedy``. The file is opened without blocking and checked on its open handle (a FIFO swapped in after
    the check cannot block), and the buffer is sized by the handle's size, never by the bound."""
    regular_file(path, what)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    with os.fdopen(fd, "rb") as handle:
        status = os.fstat(handle.fileno())
        if not stat.S_ISREG(status.st_mode):
            raise InputError(f"the {what} {path} is {_special(status.st_mode)}: {_REMEDY}")
        if status.st_size > limit_bytes:
            raise InputError(f"{path.name} has {status.st_size} bytes, more than the {limit_bytes} a {what} may have here; {remedy}")
        data = handle.read(status.st_size + 1)
    if len(data) != status.st_size:
        raise InputError(f"{path.name} changed while it was read ({status.st_size} bytes at the start, {len(data)} read): "
                         "wait until it is completely copied, then run again")
    return data


def folder_files(folder: Path, what: str) -> list[Path]:
    """The regular files of ``folder`` (symlinks followed), sorted by name; sub-folders are skipped, a device,
    FIFO or socket among them is an :class:`InputError`."""
    files = []
    for entry in sorted(folder.iterdir()):
        if input_kind(entry, f"file in the {what} folder") == "file":
            files.append(entry)
    return files
