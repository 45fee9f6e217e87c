"""One Ctrl-C ends the test command (tests/conftest.py), with two xdist workers as the README
runs it, although the code under test swallows KeyboardInterrupt (as the harness does: a
SIGINT becomes an "interrupted" run, and the test goes on).

Cross-process: a pytest session on two workers in its own process group, its tests each
catching KeyboardInterrupt; SIGINT to the whole group, as a terminal sends it. The session is
started with SIGINT ignored, as a job started in the background by a non-interactive shell
(a CI script, `cmd &`) inherits it: Python then never raises KeyboardInterrupt by itself, and
without the conftest's handler the run went on (measured: still running 60 s after the
signal, against 6 s with it)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SWALLOWING_TESTS = '''
import os
import time

def swallow(seconds):
    """Like the harness: a KeyboardInterrupt ends the work early, not the caller."""
    try:
        time.sleep(seconds)
    except KeyboardInterrupt:
        pass

''' + "\n".join(f"def test_{i}():\n    with open(os.environ['STARTED'], 'a') as f:\n"
                f"        f.write('started {i}\\n')\n    swallow(3)\n" for i in range(20))


def test_one_sigint_ends_a_two_worker_run_whose_tests_swallow_it(tmp_path: Path) -> None:
    (tmp_path / "test_swallow.py").write_text(SWALLOWING_TESTS)
    log, started = tmp_path / "out.txt", tmp_path / "started.txt"
    started.touch()
    with log.open("w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "pytest", "-q", "-s", "-n", "2", "-p", "tests.conftest",
             "-p", "no:cacheprovider", "--rootdir", str(tmp_path), str(tmp_path)],
            cwd=REPO, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
            env={**os.environ, "PYTHONPATH": str(REPO), "STARTED": str(started)})
    try:
        deadline = time.monotonic() + 120
        while started.read_text().count("started") < 2 and time.monotonic() < deadline:
            time.sleep(0.2)  # both workers are inside a test
        assert started.read_text().count("started") >= 2, log.read_text()
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=60)  # 20 tests of 3 s on 2 workers would take 30 s more
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    text = log.read_text()
    # the tests that were running (at most one more each, started as the signal came)
    assert started.read_text().count("started") <= 4, (started.read_text(), text)
    assert proc.returncode != 0, text
