"""``DIR/RUN_IN_PROGRESS``: a run directory that a harness is writing, or was writing when it was
killed.

:func:`claim` writes the marker (JSON: pid, the process start time, start time UTC, command)
when a run starts; :func:`touch` refreshes its modification time while the run goes (about
once a second), so after a SIGKILL the marker's time says when the harness stopped;
:func:`release` removes it at any end the harness lives to see (finished, failed, interrupted).
A marker whose process is gone is *stale*: :func:`stale_note` gives the one line that
``rhonn-harness run``, ``replay`` and the analysis loader print when they meet it::

    DIR holds an incomplete run (harness killed at about 2026-01-01 10:00:03 UTC, pid 1234,
    started 2026-01-01 10:00:00 UTC): rhonn-harness run ...; its files end where it stopped

A marker whose process is alive means another harness writes into DIR: :func:`claim` refuses
(:class:`RunDirBusyError`, one line).

Studies (``paper``, ``benchmark``, ``campaign``, ``rhonn-bench soak``) stopped by SIGINT or
SIGTERM leave ``DIR/INTERRUPTED`` (:func:`mark_interrupted`): what was finished is kept, the
rest is missing; a complete study removes it.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import psutil

MARKER = "RUN_IN_PROGRESS"
INTERRUPTED = "INTERRUPTED"  # a study's output directory cut short by a signal
TOUCH_EVERY_S = 1.0  # wall s between refreshes of the marker's modification time
_noted: set[Path] = set()  # directories whose stale marker was already reported here


class RunDirBusyError(ValueError):
    """Another live harness process is writing into the run directory."""


def _utc(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _own_start() -> float:
    return psutil.Process().create_time()


def read(out_dir: Path) -> dict[str, Any] | None:
    """The marker's content (plus ``touched_s``: its modification time, epoch s), or None."""
    path = Path(out_dir) / MARKER
    try:
        data = dict(json.loads(path.read_text()))
        data["touched_s"] = path.stat().st_mtime
    except (OSError, ValueError, TypeError):
        return None if not path.exists() else {"pid": None, "touched_s": path.stat().st_mtime}
    return data


def _alive(info: dict[str, Any]) -> bool:
    """True while the process that wrote the marker runs (same pid and same start time)."""
    pid = info.get("pid")
    if not isinstance(pid, int):
        return False
    try:
        start = psutil.Process(pid).create_time()
    except (psutil.NoSuchProcess, psutil.AccessDenied, ValueError):
        return False
    expected = info.get("pid_start")
    return expected is None or abs(start - float(expected)) < 1.0  # else a reused pid


def stale_note(out_dir: Path) -> str | None:
    """One line if ``out_dir`` holds the marker of a harness that is gone, else None."""
    info = read(out_dir)
    if info is None or _alive(info):
        return None
    started = info.get("started_utc", "?")
    command = info.get("command") or "?"
    return (f"{out_dir} holds an incomplete run (harness killed at about "
            f"{_utc(info['touched_s'])}, pid {info.get('pid')}, started {started}): "
            f"{command}; its files end where it stopped")


def report_stale(out_dir: Path) -> str | None:
    """Print :func:`stale_note` on stderr (once per directory and process); return it."""
    note = stale_note(out_dir)
    key = Path(out_dir).resolve()
    if note is not None and key not in _noted:
        _noted.add(key)
        print(note, file=sys.stderr, flush=True)
    return note


def busy_note(out_dir: Path) -> str | None:
    """One line if another live harness process is writing into ``out_dir``, else None."""
    info = read(out_dir)
    if info is None or not _alive(info) or info.get("pid") == os.getpid():
        return None
    return (f"{out_dir} is in use by a running harness (pid {info['pid']}, "
            f"started {info.get('started_utc', '?')})")


def claim(out_dir: Path, command: str | None = None) -> Path:
    """Write the marker of this process into ``out_dir``; report a stale one first.

    Raises :class:`RunDirBusyError` if a live harness holds the directory."""
    out_dir = Path(out_dir)
    busy = busy_note(out_dir)
    if busy is not None:
        raise RunDirBusyError(f"{busy}: choose another --out")
    info = read(out_dir)
    if info is not None and info.get("pid") != os.getpid():
        report_stale(out_dir)
    path = out_dir / MARKER
    now = time.time()
    path.write_text(json.dumps({
        "pid": os.getpid(), "pid_start": _own_start(), "started_utc": _utc(now),
        "command": command if command is not None else " ".join(sys.argv)}) + "\n")
    return path


def mark_interrupted(out_dir: Path, signum: int | None, note: str) -> Path:
    """``out_dir/INTERRUPTED``: a study output that a signal cut short (JSON: the signal, when,
    the command and ``note``: what is there and how to finish). Returns its path."""
    path = Path(out_dir) / INTERRUPTED
    name = signal.Signals(signum).name if signum else "SIGINT"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"signal": name, "at_utc": _utc(time.time()),
                                "command": " ".join(sys.argv), "note": note}, indent=1,
                               ensure_ascii=False) + "\n")
    return path


def clear_interrupted(out_dir: Path) -> None:
    """Remove ``out_dir/INTERRUPTED`` (the output is complete)."""
    with contextlib.suppress(OSError):
        (Path(out_dir) / INTERRUPTED).unlink()


def touch(path: Path) -> None:
    """Refresh the marker's modification time (the harness is still alive)."""
    with contextlib.suppress(OSError):
        os.utime(path)


def release(path: Path) -> None:
    """Remove the marker (the run ended and its files are complete as far as it got)."""
    with contextlib.suppress(OSError):
        path.unlink()
