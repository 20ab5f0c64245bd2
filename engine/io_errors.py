"""Writes that fail because the disk is full: one message for every writer, and a test hook that makes them fail.

A run writes `metrics.jsonl`, TensorBoard events, checkpoints, logs and recorded episodes under its run directory.
When the file system there is full (ENOSPC), over quota (EDQUOT) or failing (EIO), every writer raises or logs the
same kind of error, `DiskFullError`, whose message names the path and what is left on its file system:

    no space left on device writing /run/x/metrics.jsonl (12.0 KiB free of 30.0 MiB)

so that a long-running process can say so in one line and wait for space (`deploy.runtime.runloop`) instead of
dying with a traceback that the full disk then cuts short. `writing(path)` turns such an error, raised directly or
as the cause of another (orbax and tensorstore wrap it, or only say it in words: `os_error_code='28'`), into a
`DiskFullError` for `path`; `append_whole` appends a record to a file whole or not at all, so that a retried write
never duplicates nor garbles a line.

Test hook. A file system that fills up cannot be made without mounting one, which a CI machine may not allow, so
the writers also ask `check_space(path, nbytes)` before they write: `limit_writes(directory, max_bytes)` makes it
raise ENOSPC for a write under `directory` once the files there plus the write would pass `max_bytes` (as a
file system of that size would), and `disk_usage` reports that file system's figures; `lift_write_limits()` frees
the space again. A child process is limited by the environment variable `IMPULSE_TEST_DISK_LIMIT=DIR:BYTES`, read
when this module is first imported. Without a limit `check_space` returns at once and nothing else changes. It sits
in the engine, the lowest room, because every room that writes files uses it (the engine imports nothing of ours).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

DISK_FULL_ERRNOS = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
                    errno.EIO: "input/output error"}
"""The errors that say the disk cannot take the write (as opposed to a wrong path or permission), and how the
message says each."""
LIMIT_ENV = "IMPULSE_TEST_DISK_LIMIT"
"""`DIR:BYTES`: the test hook's limit for a child process (see the module docstring)."""
_OS_ERROR_CODE = re.compile(r"os_error_code='?(\d+)")
_LIMITS: dict[Path, int] = {}


class DiskFullError(OSError):
    """A write to `path` failed because its file system is full, over quota or failing (`errno`). `str()` is the
    one-line message: what went wrong, the path, and the free space of its file system."""

    def __init__(self, path: str | Path, code: int = errno.ENOSPC) -> None:
        super().__init__(code, os.strerror(code), str(path))
        self.path = Path(path)
        self.message = disk_full_message(path, code)

    def __str__(self) -> str:
        return self.message

    def __reduce__(self) -> tuple:
        return type(self), (self.path, self.errno)


class Usage(NamedTuple):
    total: int
    free: int


def disk_usage(path: str | Path) -> Usage | None:
    """Total and free bytes of the file system that holds `path` (the nearest folder above it that exists); the
    test hook's figures where a limit covers it; None if it cannot be read."""
    path = Path(path).absolute()
    limited = _limit_for(path)
    if limited is not None:
        root, limit = limited
        return Usage(limit, max(limit - _bytes_under(root), 0))
    for folder in (path, *path.parents):
        try:
            usage = shutil.disk_usage(folder)
        except OSError:
            continue
        return Usage(usage.total, usage.free)
    return None


def size_text(nbytes: int) -> str:
    """`nbytes` for a person: `512 B`, `12.0 KiB`, `30.0 MiB`, `1.5 GiB`."""
    if nbytes < 1024:
        return f"{nbytes} B"
    value = float(nbytes)
    for unit in ("KiB", "MiB", "GiB", "TiB"):
        value /= 1024
        if value < 1024 or unit == "TiB":
            break
    return f"{value:.1f} {unit}"


def disk_full_message(path: str | Path, code: int = errno.ENOSPC) -> str:
    """`no space left on device writing PATH (12.0 KiB free of 30.0 MiB)`: the one line every writer says."""
    what = DISK_FULL_ERRNOS.get(code, os.strerror(code).lower())
    usage = disk_usage(path)
    room = "" if usage is None else f" ({size_text(usage.free)} free of {size_text(usage.total)})"
    return f"{what} writing {path}{room}"


def disk_full_code(err: BaseException | None) -> int | None:
    """The errno (one of `DISK_FULL_ERRNOS`) that says `err`, or one of its causes, failed for lack of disk; None
    for any other error. Libraries that wrap the OS error in their own (tensorstore's `ValueError`) say it in
    words (`os_error_code='28'`, `No space left on device`), which count too."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, OSError) and err.errno in DISK_FULL_ERRNOS:
            return err.errno
        text = str(err)
        match = _OS_ERROR_CODE.search(text)
        if match and int(match.group(1)) in DISK_FULL_ERRNOS:
            return int(match.group(1))
        for code in (errno.ENOSPC, errno.EDQUOT):
            if os.strerror(code) in text:
                return code
        err = err.__cause__ or err.__context__
    return None


def disk_full_error(path: str | Path, err: BaseException | None) -> DiskFullError | None:
    """`err` as a `DiskFullError` for `path` (itself if it is one already), or None if it is another error."""
    if isinstance(err, DiskFullError):
        return err
    code = disk_full_code(err)
    return None if code is None else DiskFullError(path, code)


@contextmanager
def writing(path: str | Path) -> Iterator[None]:
    """Raise a failure of the writes inside for lack of disk as `DiskFullError` for `path` (from the original);
    any other error passes unchanged."""
    try:
        yield
    except Exception as err:
        full = disk_full_error(path, err)
        if full is None or full is err:
            raise
        raise full from err


def append_whole(fd: int, data: bytes) -> None:
    """Append `data` to the file open as `fd` (opened with O_APPEND) whole or not at all: a write that fails part
    way (a full disk takes what fits) is cut off again, so the file ends where it ended before and the same data
    can be written again later without a duplicate or a garbled record. Raises the OSError of the failed write."""
    start = os.fstat(fd).st_size
    view = memoryview(data)
    try:
        while view:
            written = os.write(fd, view)
            view = view[written:]
    except OSError:
        try:
            os.ftruncate(fd, start)  # freeing blocks needs no space
        except OSError:
            pass
        raise


# -- the test hook -----------------------------------------------------------------------------------------------


def limit_writes(directory: str | Path, max_bytes: int) -> None:
    """Test hook: from now on, `check_space` refuses writes under `directory` (ENOSPC) once the files there would
    hold more than `max_bytes`, and `disk_usage` reports `max_bytes` in all with what is left free."""
    _LIMITS[Path(directory).absolute()] = int(max_bytes)


def lift_write_limits() -> None:
    """Test hook: the disk is freed; `check_space` refuses nothing again."""
    _LIMITS.clear()


def check_space(path: str | Path, nbytes: int) -> None:
    """What every writer calls before writing `nbytes` to (or under) `path`: nothing, unless the test hook limits
    that folder and the write would pass its limit, which raises `OSError(ENOSPC)` as a full disk would."""
    if not _LIMITS:
        return
    limited = _limit_for(Path(path).absolute())
    if limited is not None and _bytes_under(limited[0]) + nbytes > limited[1]:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def _limit_for(path: Path) -> tuple[Path, int] | None:
    for root, limit in _LIMITS.items():
        if path == root or root in path.parents:
            return root, limit
    return None


def _bytes_under(root: Path) -> int:
    total = 0
    for folder, _, files in os.walk(root):
        for name in files:
            try:
                total += os.lstat(os.path.join(folder, name)).st_size
            except OSError:
                pass
    return total


def _limit_from_environment() -> None:
    value = os.environ.get(LIMIT_ENV)
    if not value:
        return
    directory, _, nbytes = value.rpartition(":")
    if directory and nbytes.isdigit():
        limit_writes(directory, int(nbytes))


_limit_from_environment()
