"""Shared pytest configuration."""

import signal
import threading

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", max_examples=100, deadline=None)
settings.load_profile("ci")


# One Ctrl-C ends the test run, with or without xdist. A terminal's Ctrl-C reaches every
# process of the run; the harness code under test turns SIGINT into an "interrupted" run (its
# own KeyboardInterrupt path), so the test that was running fails and, by default, the next
# one would start. Each process therefore notes the signal, and after the test that was
# running the session stops (an xdist worker then ends its loop, and the controller with it).
_interrupted: list[int] = []


def _note_sigint(signum: int, _frame: object) -> None:
    _interrupted.append(signum)
    raise KeyboardInterrupt


def pytest_configure(config: pytest.Config) -> None:
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _note_sigint)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    yield
    from harness.run import signals  # the harness's own handler, once a test installed it

    if _interrupted or signals.received() == signal.SIGINT:
        item.session.shouldstop = "interrupted by SIGINT (Ctrl-C)"
