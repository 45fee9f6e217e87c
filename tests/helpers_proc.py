"""Helpers for cross-process tests: spawning children and checking none are left behind."""

from __future__ import annotations

import os
import subprocess
import sys

import psutil

from can_db.server import die_with_parent


def spawn(*args: str, **kwargs: object) -> subprocess.Popen[str]:
    """Start ``python -m ...`` with this interpreter; it dies if the test process dies."""
    return subprocess.Popen([sys.executable, *args], text=True,  # type: ignore[call-overload]
                            preexec_fn=die_with_parent, **kwargs)


def live_children() -> list[psutil.Process]:
    """Descendant processes of this test process that are still running (not zombies)."""
    out = []
    for proc in psutil.Process(os.getpid()).children(recursive=True):
        try:
            if proc.status() != psutil.STATUS_ZOMBIE:
                out.append(proc)
        except psutil.NoSuchProcess:
            pass
    return out
