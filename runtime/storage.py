"""Writing files without losing the last good copy, and storage faults as one clear line.

A full disk (ENOSPC, EDQUOT), a read-only file system (EROFS) or a folder the process may not write (EACCES, EPERM)
is not a bug to show as a traceback: :class:`StorageError` names the path and the errno, and every process turns it
into one line on stderr and exit code :data:`EXIT_STORAGE` (protocol/cli.py, deploy/run_local.py).
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from pathlib import Path

#: The exit code of a process stopped by a storage fault (documented with the others in the README).
EXIT_STORAGE = 5
#: The errnos that mean "this storage cannot take the write", as opposed to a bug.
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM})


class StorageError(OSError):
    """A write refused by the storage; ``str()`` is the one line to print."""

    def __str__(self) -> str:
        name = errno.errorcode.get(self.errno or 0, str(self.errno))
        return f"cannot write {self.filename}: {self.strerror} ({name})"


def is_storage_fault(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in STORAGE_ERRNOS


@contextlib.contextmanager
def storage_errors(path: Path | str) -> Iterator[None]:
    """Turn a storage fault inside the block into a StorageError naming ``path`` (or the file the OS named)."""
    try:
        yield
    except StorageError:
        raise
    except OSError as err:
        if err.errno not in STORAGE_ERRNOS:
            raise
        raise StorageError(err.errno, err.strerror, str(err.filename or path)) from err


def atomic_write(path: Path, data: bytes, tmp: Path | None = None) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder (written, fsynced, renamed over
    ``path``, the folder fsynced): a reader sees the old file or the new one, never a part. On a failure the
    temporary file is removed, ``path`` is left as it was, and a storage fault raises StorageError."""
    tmp = tmp or path.with_name(path.name + ".tmp")
    with storage_errors(path):
        try:
            with tmp.open("wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    return path
