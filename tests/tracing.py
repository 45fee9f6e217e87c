"""Keeping allocation measurements to the code under test.

tracemalloc counts the allocations of every thread of the process. Two others run in a test
process: coverage's tracer under ``pytest --cov`` (its per-frame bookkeeping) and, under
pytest-xdist, the worker's message thread (execnet), which allocates whenever the controller
sends it work. ``coverage_paused`` stops every coverage measurement for the block (or the
decorated test) and restarts them after; ``other_threads_held`` keeps the GIL with the
measuring thread for the block, so no other Python thread runs in it.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

# s; longer than any measured block, so the interpreter never hands the GIL over in one
HOLD_SWITCH_INTERVAL_S = 60.0


@contextmanager
def coverage_paused() -> Iterator[None]:
    """Stop the running coverage measurement (if any) for the duration of the block."""
    try:
        import coverage
    except ImportError:  # coverage is in the test extra; a bare install has none
        yield
        return
    # Every started instance, oldest first: an xdist worker is itself a child process, so
    # `patch = ["subprocess"]` starts one at its start-up besides pytest-cov's own, and each
    # traces (Coverage.current() is only the newest). Stopped newest first, as they stack.
    running = list(getattr(coverage.Coverage, "_instances", []))
    if not running and coverage.Coverage.current() is not None:
        running = [coverage.Coverage.current()]
    for cov in reversed(running):
        cov.stop()
    try:
        yield
    finally:
        for cov in running:
            cov.start()


@contextmanager
def other_threads_held() -> Iterator[None]:
    """Let no other Python thread run during the block (unless the block itself blocks or
    releases the GIL): the interpreter's switch interval is raised for its duration."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(HOLD_SWITCH_INTERVAL_S)
    try:
        yield
    finally:
        sys.setswitchinterval(before)
