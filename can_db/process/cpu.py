"""A CPU of its own for one process (the HIL bench's device under test), and keeping it awake.

* :func:`choose_cpu` turns ``"auto"`` or a CPU number into a CPU of this process's
  affinity set that leaves at least one CPU for everything else (``CpuChoiceError``, a
  one-line reason, otherwise).
* :func:`pin_all_threads` sets the affinity of every thread of this process (threads
  started later inherit it from the thread that starts them).
* :class:`KeepAwake` runs ``python -m can_db.process.cpu --spin CPU``: a ``SCHED_IDLE`` busy loop
  pinned to that CPU. The kernel preempts it the moment the pinned process becomes
  runnable, so it takes only time nobody else wants; what it buys is that the CPU never
  goes idle. On this KVM guest an idle vCPU halts at once (``haltpoll.guest_halt_poll_ns=0``
  on the kernel command line), and code that ran before a halt runs slowly after it (the
  compiled MPC step on the bench: p50 82 µs after a 1 ms sleep, 21.7 µs after a 0.2 ms busy
  spin; which cache or predictor state the host takes was not isolated). Measured on
  dlc-paper with nmpc-rhonn (MPC update in the controller process, mean per run, 2 runs
  each, same code and minutes): alone on a CPU that may halt 33.7 / 38.5 µs, alone with the
  spinner 29.9 / 29.9 µs (41–50 µs sharing the CPUs with plant, hub and harness). A Linux
  target would use ``isolcpus`` and ``idle=poll`` instead; the spinner needs no privileges.
  ``rhonn-bench mpc-update`` measures both layouts.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys

from can_db.process.parent import die_with_parent


class CpuChoiceError(ValueError):
    """The requested CPU cannot be given to one process alone (one line, for the user)."""


def allowed_cpus() -> set[int]:
    """The CPUs this process may run on (all CPUs where affinity is not supported)."""
    if hasattr(os, "sched_getaffinity"):
        return set(os.sched_getaffinity(0))
    return set(range(os.cpu_count() or 1))


def choose_cpu(text: str | int, allowed: set[int] | None = None,
               leave_one: bool = True) -> int:
    """CPU number for ``text`` (``"auto"``: the highest allowed CPU) out of ``allowed``
    (default: this process's CPUs); with ``leave_one`` it must leave at least one of them
    for the other processes. Raises CpuChoiceError otherwise."""
    cpus = allowed_cpus() if allowed is None else set(allowed)
    if not hasattr(os, "sched_setaffinity"):
        raise CpuChoiceError("a CPU of its own needs CPU affinity (Linux); not available here")
    if leave_one and len(cpus) < 2:
        raise CpuChoiceError(f"a CPU of its own needs at least 2 usable CPUs, this process "
                             f"has {sorted(cpus)}")
    if text == "auto":
        return max(cpus)
    try:
        cpu = int(text)
    except (TypeError, ValueError):
        raise CpuChoiceError(f"CPU must be 'auto' or a CPU number, not {text!r}") from None
    if cpu not in cpus:
        raise CpuChoiceError(f"CPU {cpu} is not one of the usable CPUs {sorted(cpus)}")
    return cpu


def pin_all_threads(cpus: set[int]) -> None:
    """Set the CPU affinity of every thread of this process to ``cpus`` (Linux)."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        tids = [0]
    for tid in tids:
        with contextlib.suppress(ProcessLookupError):  # a thread that just ended
            os.sched_setaffinity(tid, cpus)


class KeepAwake:
    """The SCHED_IDLE spinner of one CPU as a child process (see the module docstring);
    it dies with its parent (PR_SET_PDEATHSIG) and on ``stop()``."""

    def __init__(self, cpu: int) -> None:
        self.cpu = cpu
        self.proc = subprocess.Popen([sys.executable, "-m", "can_db.process.cpu", "--spin",
                                      str(cpu)], stdin=subprocess.DEVNULL,
                                     preexec_fn=die_with_parent)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stop(self) -> None:
        """End the spinner (SIGKILL: it holds nothing that needs flushing)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=5.0)


def _spin(cpu: int) -> int:
    os.sched_setaffinity(0, {cpu})
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError) as exc:  # without SCHED_IDLE it would compete: stop
        print(f"can_db.process.cpu: no SCHED_IDLE ({exc}); not spinning", file=sys.stderr)
        return 1
    while True:  # runs only when nothing else on this CPU wants to
        pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m can_db.process.cpu", description=__doc__)
    parser.add_argument("--spin", type=int, required=True, metavar="CPU",
                        help="keep CPU awake with a SCHED_IDLE busy loop until killed")
    return _spin(parser.parse_args(argv).spin)


if __name__ == "__main__":
    sys.exit(main())
