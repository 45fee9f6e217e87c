"""Pausing coverage measurement around allocation measurements.

Under ``pytest --cov`` coverage's tracer runs in the test process and allocates on its own
(its per-frame bookkeeping); a test that measures the allocations of the code under test with
tracemalloc would count those too. ``coverage_paused`` stops the measurement for the block
(or the decorated test) and restarts it after; without coverage it does nothing.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def coverage_paused() -> Iterator[None]:
    """Stop the running coverage measurement (if any) for the duration of the block."""
    try:
        import coverage
    except ImportError:  # coverage is in the test extra; a bare install has none
        yield
        return
    cov = coverage.Coverage.current()
    if cov is None:
        yield
        return
    cov.stop()
    try:
        yield
    finally:
        cov.start()
