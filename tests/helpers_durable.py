"""Records the order of a durable write's system calls (fsync of a file or a directory,
rename) for the tests of can_db/process/durable.py and of the checkpoints that use it."""

from __future__ import annotations

import os
import stat

import pytest


def record_durable_calls(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Patch ``os.fsync`` and ``os.replace`` to log "fsync file" / "fsync dir" / "rename"
    (and still do them); returns the list the calls are appended to."""
    events: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append("fsync dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "fsync file")
        real_fsync(fd)

    def replace(src: object, dst: object) -> None:
        events.append("rename")
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return events
