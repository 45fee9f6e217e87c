"""Processor in the loop: a firmware ELF on QEMU's MPS2 AN386, its UART0 carrying SLCAN.

:class:`PilLink` boots ``qemu-system-arm`` with UART0 on a TCP socket that QEMU itself binds
on 127.0.0.1 with port 0 (the kernel picks a free port, QEMU prints it; no port is guessed,
so no other process can take it in between), opens python-can's ``slcan`` interface on
``socket://127.0.0.1:PORT`` (pyserial's socket URL) and exposes ``send`` / ``recv``. The
firmware's semihosting output goes to ``guest.txt`` in the work folder, QEMU's own messages
to ``qemu.txt``. QEMU waits for the connection before it starts the guest (``wait=on``), so
no byte of the firmware is lost.

A lost link (QEMU exited, was killed or the firmware faulted) raises :class:`PilLinkError`
naming QEMU's exit status and the tails of both logs; :meth:`PilLink.close` stops QEMU
(SIGTERM, then SIGKILL after a grace period), and QEMU dies with this process (it is started
with the parent-death signal), so no QEMU is left behind.

:class:`PilBridge` forwards frames both ways between the project's bus (any
:func:`can_db.transport.bus.open_bus` spec, e.g. ``local:NAME``) and a :class:`PilLink`, so
the plant and the tools on the bus see the firmware as one more node.
"""

from __future__ import annotations

import contextlib
import importlib.util
import re
import subprocess
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType

import can
from can.interfaces.slcan import slcanBus

from can_db.process.parent import die_with_parent
from can_db.transport.bus import open_bus

QEMU = "qemu-system-arm"
QEMU_BOARD_ARGS: tuple[str, ...] = (
    "-M",
    "mps2-an386",
    "-cpu",
    "cortex-m4",
    "-nographic",
    "-monitor",
    "none",
)
START_TIMEOUT_S = 20.0  # wall s for QEMU to listen and the firmware to answer V
STOP_GRACE_S = 5.0  # wall s between SIGTERM and SIGKILL
POLL_S = 0.02  # wall s between looks at QEMU's message file while it starts
EXIT_SETTLE_S = 1.0  # wall s a lost link waits for QEMU's exit status
_LISTENING = re.compile(r"waiting for connection on: \S*tcp:127\.0\.0\.1:(\d+)")


class PilLinkError(RuntimeError):
    """QEMU or the SLCAN link failed (the message says how, with QEMU's status and logs)."""


def _tail(path: Path, n_chars: int = 1500) -> str:
    try:
        return path.read_text(errors="replace")[-n_chars:].strip()
    except OSError:
        return ""


class PilLink:
    """QEMU running a PIL firmware, and python-can's slcan bus on its UART0.

    ``elf``: the firmware; ``work_dir``: where the logs go (``guest.txt``, ``qemu.txt``);
    ``qemu_extra``: further QEMU arguments (e.g. the instruction-count plugin);
    ``start_timeout_s``: wall s for QEMU to listen and the firmware to answer ``V``.
    Use as a context manager, or call :meth:`start` and :meth:`close`.
    """

    def __init__(
        self,
        elf: str | Path,
        work_dir: str | Path,
        *,
        qemu_extra: Sequence[str] = (),
        start_timeout_s: float = START_TIMEOUT_S,
    ) -> None:
        self.elf = Path(elf)
        self.work_dir = Path(work_dir)
        self.qemu_extra = tuple(qemu_extra)
        self.start_timeout_s = start_timeout_s
        self.guest_log = self.work_dir / "guest.txt"
        self.qemu_log = self.work_dir / "qemu.txt"
        self.port: int | None = None
        self.version: tuple[int | None, int | None] = (None, None)
        self._proc: subprocess.Popen[bytes] | None = None
        self._bus: can.BusABC | None = None
        self._stopping = False

    # -- start and stop -------------------------------------------------------------------

    def qemu_command(self) -> list[str]:
        """The QEMU command line (UART0 on a loopback socket QEMU binds, port 0)."""
        return [
            QEMU,
            *QEMU_BOARD_ARGS,
            "-chardev",
            "socket,id=pil,host=127.0.0.1,port=0,server=on,wait=on",
            "-serial",
            "chardev:pil",
            "-chardev",
            f"file,id=shout,path={self.guest_log}",
            "-semihosting-config",
            "enable=on,target=native,chardev=shout",
            *self.qemu_extra,
            "-kernel",
            str(self.elf),
        ]

    def start(self) -> PilLink:
        """Boot QEMU, connect the slcan bus, open the channel and ask the firmware's version;
        PilLinkError (QEMU stopped) if any of it fails within ``start_timeout_s``."""
        if not self.elf.is_file():
            raise PilLinkError(f"firmware {self.elf} not found")
        if importlib.util.find_spec("serial") is None:
            raise PilLinkError(
                "python-can's slcan interface needs pyserial: pip install 'rhonn-tv[pil]'"
            )
        self.work_dir.mkdir(parents=True, exist_ok=True)
        self.guest_log.unlink(missing_ok=True)
        deadline = time.monotonic() + self.start_timeout_s
        with open(self.qemu_log, "wb") as err:
            try:
                self._proc = subprocess.Popen(
                    self.qemu_command(),
                    stdin=subprocess.DEVNULL,
                    stdout=err,
                    stderr=err,
                    preexec_fn=die_with_parent,
                )
            except OSError as exc:
                raise PilLinkError(f"cannot start {QEMU}: {exc}") from exc
        try:
            self.port = self._wait_listening(deadline)
            bus = slcanBus(channel=f"socket://127.0.0.1:{self.port}", sleep_after_open=0.0)
            self._bus = bus
            self.version = bus.get_version(max(deadline - time.monotonic(), 0.1))
        except BaseException as exc:
            why = self.failure(exc)
            self._close_quietly()
            if isinstance(exc, PilLinkError | can.CanError | OSError):
                raise PilLinkError(f"PIL link did not start: {why}") from exc
            raise
        if self.version == (None, None):
            why = self.failure(None)
            self._close_quietly()
            raise PilLinkError(
                f"PIL firmware did not answer V within {self.start_timeout_s:g} s: {why}"
            )
        return self

    def _wait_listening(self, deadline: float) -> int:
        """The port QEMU bound (from its "waiting for connection" message)."""
        assert self._proc is not None
        while time.monotonic() < deadline:
            m = _LISTENING.search(_tail(self.qemu_log, 4000))
            if m:
                return int(m.group(1))
            if self._proc.poll() is not None:
                raise PilLinkError("QEMU exited before it listened")
            time.sleep(POLL_S)
        raise PilLinkError(f"QEMU did not listen within {self.start_timeout_s:g} s")

    def close(self, grace_s: float = STOP_GRACE_S) -> int | None:
        """Close the channel (C), disconnect, stop QEMU (SIGTERM, SIGKILL after ``grace_s``);
        QEMU's exit code (None if it never started). Raises PilLinkError if QEMU had already
        exited on its own with a failure (non-zero) before the close."""
        self._stopping = True
        exited_before = self._proc.poll() if self._proc is not None else None
        if self._bus is not None:
            with contextlib.suppress(can.CanError, OSError):
                self._bus.shutdown()  # sends C, closes the socket; a dead peer is no error here
            self._bus = None
        if self._proc is None:
            return None
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=grace_s)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=grace_s)
        code = self._proc.returncode
        if exited_before is not None and exited_before != 0:
            raise PilLinkError(
                f"QEMU had exited with {exited_before} before the close: {self.failure(None)}"
            )
        return code

    def _close_quietly(self) -> None:
        """Close after a failed start (the start's error is the one to report)."""
        with contextlib.suppress(PilLinkError):
            self.close()

    def __enter__(self) -> PilLink:
        return self.start() if self._proc is None else self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is None:
            self.close()
        else:  # the first error is the one to see
            with contextlib.suppress(PilLinkError):
                self.close()

    # -- state ------------------------------------------------------------------------------

    @property
    def qemu_returncode(self) -> int | None:
        """QEMU's exit code, None while it runs (or before it started)."""
        return None if self._proc is None else self._proc.poll()

    @property
    def qemu_pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def bus(self) -> can.BusABC:
        """The python-can slcan bus (PilLinkError when the link is not up)."""
        if self._bus is None:
            raise PilLinkError("PIL link is not started (or closed)")
        return self._bus

    def failure(self, exc: BaseException | None) -> str:
        """Why the link is down: QEMU's status, the error, the tails of the logs."""
        if exc is not None and self._proc is not None and self._proc.poll() is None:
            # the socket's end of stream comes as the process exits: give the exit a moment
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._proc.wait(timeout=EXIT_SETTLE_S)
        code = self.qemu_returncode
        state = (
            "QEMU not started"
            if self._proc is None
            else "QEMU still running"
            if code is None
            else f"QEMU exited with code {code}"
            + (f" (killed by signal {-code})" if code < 0 else "")
        )
        parts = [state]
        if exc is not None:
            cause = exc.__cause__
            parts.append(f"{type(exc).__name__}: {exc}" + (f" ({cause})" if cause else ""))
        guest, qemu = _tail(self.guest_log, 600), _tail(self.qemu_log, 600)
        if guest:
            parts.append(f"guest: {guest}")
        if qemu:
            parts.append(f"qemu: {qemu}")
        return "; ".join(parts)

    # -- frames -----------------------------------------------------------------------------

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to the firmware; PilLinkError if the link is lost."""
        try:
            self.bus.send(msg, timeout)
        except (can.CanError, OSError) as exc:
            raise PilLinkError(f"PIL link lost while sending: {self.failure(exc)}") from exc

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame from the firmware, None after ``timeout`` wall s; PilLinkError if
        the link is lost (QEMU gone: the socket reports end of stream)."""
        try:
            return self.bus.recv(timeout)
        except (can.CanError, OSError) as exc:
            raise PilLinkError(f"PIL link lost while receiving: {self.failure(exc)}") from exc

    def raw_line(self, line: bytes, timeout_s: float = 5.0) -> bytes:
        """Write ``line`` as it is (no checks: malformed input for tests) and return the
        firmware's answer up to and including its '\\r' or '\\a'. Only while no frame is in
        flight: the answer is read from the serial stream directly, past python-can."""
        bus = self.bus
        port = bus.serialPortOrig  # type: ignore[attr-defined]
        answer = bytearray()
        deadline = time.monotonic() + timeout_s
        try:
            port.write(line)
            while time.monotonic() < deadline:
                b = port.read(1)
                answer += b
                if b in (b"\r", b"\a"):
                    return bytes(answer)
        except Exception as exc:  # pyserial raises SerialException (an OSError) and others
            raise PilLinkError(f"PIL link lost: {self.failure(exc)}") from exc
        raise PilLinkError(
            f"no answer to {line!r} within {timeout_s:g} s "
            f"(got {bytes(answer)!r}): {self.failure(None)}"
        )


class PilBridge:
    """Frames both ways between the project's bus (``bus_spec`` for
    :func:`can_db.transport.bus.open_bus`, e.g. ``local:NAME``) and a started
    :class:`PilLink`, one thread per direction. A thread that fails stores the error and
    stops the bridge; :meth:`check` and :meth:`stop` raise it (PilLinkError for the link).
    ``poll_s``: how long each direction's recv waits before it looks at the stop flag, wall s.
    """

    def __init__(self, link: PilLink, bus_spec: str, poll_s: float = 0.05) -> None:
        self.link = link
        self.bus_spec = bus_spec
        self.poll_s = poll_s
        self.to_firmware = 0
        self.from_firmware = 0
        self.error: BaseException | None = None
        self._bus: can.BusABC | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> PilBridge:
        self._bus = open_bus(self.bus_spec)
        self._threads = [
            threading.Thread(target=self._run, args=(d,), name=f"pil-bridge-{d}", daemon=True)
            for d in ("down", "up")
        ]
        for t in self._threads:
            t.start()
        return self

    def _run(self, direction: str) -> None:
        assert self._bus is not None
        try:
            while not self._stop.is_set():
                if direction == "down":  # project bus → firmware
                    msg = self._bus.recv(self.poll_s)
                    if msg is not None:
                        self.link.send(msg)
                        self.to_firmware += 1
                else:  # firmware → project bus
                    msg = self.link.recv(self.poll_s)
                    if msg is not None:
                        self._bus.send(msg)
                        self.from_firmware += 1
        except BaseException as exc:  # kept for check()/stop(); the other side stops too
            if not self._stop.is_set():
                self.error = exc
            self._stop.set()

    def check(self) -> None:
        """Raise the error that stopped a direction, if any."""
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        """Stop both directions and close the project-bus side (the link stays open)."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        self.check()

    def __enter__(self) -> PilBridge:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is None:
            self.stop()
        else:
            with contextlib.suppress(BaseException):
                self.stop()
