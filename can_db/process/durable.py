"""Durable file replacement: a crash at any moment leaves the old file or the new one.

The steps (POSIX): write a temp file in the same directory (``.NAME.*.tmp``), fsync it,
``os.replace`` it over the target, fsync the directory. Without the first fsync a crash after
the rename can leave an empty or torn file under the target's name (the data was still in
the page cache); without the directory fsync the rename itself may not survive a power loss.
Used by the controller's checkpoints and the plant's SecOC trip counter.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (POSIX); silently skipped where directories
    cannot be opened or synced (some file systems refuse either: the rename still happened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def replace_durably(path: str | Path, write: Callable[[BinaryIO], None], *,
                    before_replace: Callable[[Path], None] | None = None) -> None:
    """Write ``path`` through ``write(fh)`` so that it is either the old file or the whole new
    one, and durable once this returns. Raises OSError (disk full, no permission, a directory
    in the way) with any previous file untouched and the temp file removed.
    ``before_replace`` is a test hook called with the fsynced temp file before the rename."""
    path = Path(path)
    directory = path.parent if str(path.parent) else Path(".")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        if before_replace is not None:
            before_replace(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    fsync_dir(directory)
