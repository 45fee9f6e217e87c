"""Durable file replacement (can_db/process/durable.py): the order of the syncs and the
rename, a failed write leaving the old file and no temp file, and the directory fsync's
tolerance of file systems that refuse it."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

import pytest

from can_db.process.durable import fsync_dir, replace_durably
from tests.helpers_durable import record_durable_calls


def test_a_replacement_syncs_the_file_then_renames_then_syncs_the_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    events = record_durable_calls(monkeypatch)
    replace_durably(tmp_path / "f", lambda fh: fh.write(b"one\n"))
    assert events == ["fsync file", "rename", "fsync dir"]
    assert (tmp_path / "f").read_bytes() == b"one\n"
    assert [p.name for p in tmp_path.iterdir()] == ["f"]  # no temp file left


def test_the_hook_sees_the_whole_temp_file_before_the_rename(tmp_path: Path) -> None:
    seen: list[tuple[str, bytes, bool]] = []
    target = tmp_path / "f"
    target.write_bytes(b"old\n")
    replace_durably(target, lambda fh: fh.write(b"new\n"), before_replace=lambda tmp: seen.append(
        (tmp.name, tmp.read_bytes(), target.read_bytes() == b"old\n")))
    assert seen == [(seen[0][0], b"new\n", True)] and seen[0][0].startswith(".f.")
    assert seen[0][0].endswith(".tmp") and target.read_bytes() == b"new\n"


def test_a_failed_write_keeps_the_old_file_and_removes_the_temp_file(tmp_path: Path) -> None:
    target = tmp_path / "f"
    target.write_bytes(b"old\n")

    def full_disk(fh: BinaryIO) -> None:
        fh.write(b"ne")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        replace_durably(target, full_disk)
    assert target.read_bytes() == b"old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["f"]


def test_a_relative_path_is_replaced_in_the_working_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    replace_durably("rel", lambda fh: fh.write(b"x"))
    assert (tmp_path / "rel").read_bytes() == b"x"


def test_a_directory_in_the_way_is_an_oserror(tmp_path: Path) -> None:
    (tmp_path / "d").mkdir()
    with pytest.raises(OSError):
        replace_durably(tmp_path / "d", lambda fh: fh.write(b"x"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


# ------------------------------------------------------------------- directory fsync
def test_directory_fsync_skips_directories_that_cannot_be_opened(tmp_path: Path) -> None:
    fsync_dir(tmp_path / "absent")          # no exception


def test_directory_fsync_failure_is_ignored_and_the_descriptor_closed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[int] = []
    closed: list[int] = []
    real_open, real_close = os.open, os.close

    def spy_open(path: str | os.PathLike[str], flags: int) -> int:
        fd = real_open(path, flags)
        opened.append(fd)
        return fd

    def spy_close(fd: int) -> None:
        closed.append(fd)
        real_close(fd)

    def no_fsync(fd: int) -> None:
        raise OSError(22, "fsync not supported")

    monkeypatch.setattr(os, "open", spy_open)
    monkeypatch.setattr(os, "close", spy_close)
    monkeypatch.setattr(os, "fsync", no_fsync)
    fsync_dir(tmp_path)
    assert len(opened) == 1 and closed == opened


def test_directory_fsync_syncs_the_directory(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[int] = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd)))
    fsync_dir(tmp_path)
    assert len(synced) == 1


def test_the_temp_file_and_the_synced_directory_are_the_targets(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The temp file is written beside the target (so the rename is atomic, one file system)
    and the directory fsynced is the target's, not the working directory."""
    target = tmp_path / "sub" / "f"
    target.parent.mkdir()
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    dirs: list[tuple[int, int]] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            dirs.append((st.st_dev, st.st_ino))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    temps: list[Path] = []
    replace_durably(target, lambda fh: fh.write(b"x"), before_replace=temps.append)
    assert [t.parent for t in temps] == [target.parent]
    st = os.stat(target.parent)
    assert dirs == [(st.st_dev, st.st_ino)]
    assert list(elsewhere.iterdir()) == []


def test_the_hook_is_keyword_only(tmp_path: Path) -> None:
    """``before_replace`` is a test hook: never taken from a third positional argument."""
    with pytest.raises(TypeError):
        replace_durably(tmp_path / "f", lambda fh: fh.write(b"x"),
                        lambda tmp: None)  # type: ignore[misc]
    assert not (tmp_path / "f").exists()
