"""Shared pytest configuration."""

import signal
import threading

import pytest
from hypothesis import HealthCheck, settings

from harness.run import signals as harness_signals

settings.register_profile(
    "ci", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", max_examples=100, deadline=None)
settings.load_profile("ci")


# One Ctrl-C (SIGINT) ends the test run, with or without xdist. A run started in the
# background by a non-interactive shell inherits SIGINT as ignored, and Python keeps it so:
# no process of the run would react. The harness code under test also turns SIGINT into an
# "interrupted" run, so the test that was running fails and the next one would start. Each
# process therefore sets its own handler and notes the signal, and after the test that was
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
    # the harness's own handler notes it instead, once a test installed it
    if _interrupted or harness_signals.received() == signal.SIGINT:
        item.session.shouldstop = "interrupted by SIGINT (Ctrl-C)"
