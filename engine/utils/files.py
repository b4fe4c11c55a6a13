"""Reading a file a user or a peer names, bounded and without blocking.

:func:`read_regular_file` opens without blocking (a FIFO does not wait for a
writer) and without following a final symbolic link through a loop, checks the
open descriptor (a regular file, at most ``max_bytes``) and only then reads, so a
directory, a FIFO, a device, a symbolic-link loop or a huge file is refused in one
line before a byte is read.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

__all__ = ["file_kind", "read_regular_file"]


def file_kind(mode: int) -> str:
    """What a ``st_mode`` is, in words (``"a directory"``, ``"a FIFO"``, ...)."""
    for test, word in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return word
    return "not a file"


def read_regular_file(path: str | Path, max_bytes: int, *, error: type[Exception] = ValueError,
                      what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` bytes.

    Args:
        path: the file.
        max_bytes: the largest size read, bytes.
        error: the exception class raised (e.g. ``ConfigError``).
        what: what the file should be, for the message (``"a PLY file"``).

    Raises:
        error: ``"<path>: ..."``: missing or unreadable, a symbolic-link loop, not a
            regular file (which kind it is), or larger than ``max_bytes``.
    """
    path = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise error(f"{path}: a symbolic-link loop, not {what}") from None
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{path}: not a regular file ({file_kind(st.st_mode)}); expected "
                        f"{what}")
        if st.st_size > max_bytes:
            raise error(f"{path}: {st.st_size} bytes exceeds the size limit of {max_bytes} "
                        f"bytes for {what}")
        with os.fdopen(fd, "rb", closefd=False) as f:
            blob = f.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    finally:
        os.close(fd)
    if len(blob) > max_bytes:
        raise error(f"{path}: grew past the size limit of {max_bytes} bytes for {what}")
    return blob
