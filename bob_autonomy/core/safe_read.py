"""Reading small settings files (parameters, configuration, scenarios) that may be hostile or broken.

`read_small_file(path, max_bytes)` returns the bytes of a regular file no larger than `max_bytes`, and
otherwise raises `UnreadableFileError` saying why in words a log can carry: not a regular file (a directory, a
FIFO that would block a plain `open().read()` forever, a device), too large (checked before reading and
again while reading, so a file that grows cannot exhaust memory), or an OSError (permissions, I/O). A
missing file raises FileNotFoundError, because callers treat "absent" differently from "broken".

`describe_parse_error(exc)` turns what a parser of hostile text can raise (RecursionError for deep
nesting, MemoryError, UnicodeDecodeError, ValueError, ...) into one short line.
"""

from __future__ import annotations

import os
import stat

__all__ = ["MAX_SETTINGS_FILE_BYTES", "UnreadableFileError", "describe_parse_error", "read_small_file"]

MAX_SETTINGS_FILE_BYTES = 1 << 20  # 1 MiB: far above any real parameter, config or scenario file


class UnreadableFileError(ValueError):
    """A file that cannot be used at all; str() is the problem, without the path (callers add it)."""


def read_small_file(path: str | os.PathLike[str], max_bytes: int = MAX_SETTINGS_FILE_BYTES) -> bytes:
    """The contents of the regular file `path` (at most `max_bytes` bytes).

    FileNotFoundError when it does not exist; UnreadableFileError for anything else that stops it being read.
    The file is opened non-blocking so that a FIFO put in its place cannot hang the caller.
    """
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise UnreadableFileError(f"cannot be opened: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            kind = "a directory" if stat.S_ISDIR(info.st_mode) else "a pipe, socket or device"
            raise UnreadableFileError(f"is not a regular file but {kind}")
        if info.st_size > max_bytes:
            raise UnreadableFileError(f"is {info.st_size:,} bytes long; at most {max_bytes:,} are accepted")
        chunks: list[bytes] = []
        size = 0
        while True:
            chunk = os.read(fd, min(65536, max_bytes + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
            if size > max_bytes:
                raise UnreadableFileError(f"is more than {max_bytes:,} bytes long (it grew while being read)")
        return b"".join(chunks)
    except OSError as exc:
        raise UnreadableFileError(f"cannot be read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def describe_parse_error(exc: BaseException) -> str:
    """One line saying why a parser failed on some text (for messages that also name the file)."""
    if isinstance(exc, RecursionError):
        return "nested too deeply to parse"
    if isinstance(exc, MemoryError):
        return "too large to parse in memory"
    if isinstance(exc, UnicodeDecodeError):
        return f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})"
    text = str(exc)
    if len(text) > 300:
        text = text[:300] + "..."
    return text or type(exc).__name__
