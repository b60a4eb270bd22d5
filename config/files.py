"""Read an input file given by a user: regular files only, size bounded.

One implementation for every file the CLI and the service read on a user's say-so
(project and scenario YAML, survey CSV, plan JSON): a FIFO, a device (``/dev/zero``) or a
directory is refused before it is read, and a file longer than the bound is refused
after reading at most one byte more than the bound, so no input hangs the reader or
exhausts memory.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

MIB = 1024 * 1024


class InputFileError(Exception):
    """The file cannot be used as input; the message is one line naming the file.

    Scenarios: missing, unreadable (permissions), not a regular file (FIFO, device,
    directory, socket), longer than the bound.
    """


def file_kind(mode: int) -> str:
    """What a file that is not a regular file is, for a message ("a directory", ...)."""
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def read_input_file(path: str | Path, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``max_bytes`` of them."""
    p = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO without a writer returns at once instead of waiting.
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise InputFileError(f"{p}: file not found") from None
    except OSError as exc:
        raise InputFileError(f"{p}: cannot read: {exc.strerror}") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise InputFileError(f"{p}: {file_kind(mode)}, expected a regular file")
        chunks: list[bytes] = []
        size = 0
        while size <= max_bytes:
            chunk = os.read(fd, min(MIB, max_bytes + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise InputFileError(f"{p}: cannot read: {exc.strerror}") from None
    finally:
        os.close(fd)
    if size > max_bytes:
        raise InputFileError(f"{p}: longer than {max_bytes} bytes, the limit for this file")
    return b"".join(chunks)


def read_text_file(
    path: str | Path, max_bytes: int, encoding: str = "utf-8", hint: str = ""
) -> str:
    """:func:`read_input_file`, decoded; text that is not UTF-8 is an :class:`InputFileError`
    naming the first bad byte (and ``hint``, what the user can do about it)."""
    data = read_input_file(path, max_bytes)
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        tail = f"; {hint}" if hint else ""
        raise InputFileError(f"{Path(path)}: not UTF-8 text (byte {exc.start}){tail}") from None
