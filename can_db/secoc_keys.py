"""SecOC keys and the trip counter: where the secrets and the persisted freshness live.

Keys: one 128-bit key per direction (controller → plant, plant → controller), from a TOML key
file that is refused when group or others have any permission on it, from two environment
variables, or — for CI and simulation only — the public test key below. Key bytes never
appear in a repr, a log line or an error message.

The trip counter is the freshness master's (the plant's) start counter, like a vehicle's
ignition-cycle counter: +1 at every start, persisted durably in the node's state directory, so
a restarted plant never reuses a freshness value and frames recorded in an earlier trip are
stale in every later one (can_db/secoc.py explains the freshness). A counter file that cannot
be read or advanced stops the start (:class:`TripCounterError`): a counter that silently
starts again at 1 would let a recording of an earlier trip replay into this one.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import stat
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from can_db.process.durable import replace_durably

TRIP_BITS = 20  # width of the trip counter on the wire (SYNC_AUTH.TRIP)
ENV_CTRL_TO_PLANT = "RHONN_SECOC_KEY_CTRL_TO_PLANT"
ENV_PLANT_TO_CTRL = "RHONN_SECOC_KEY_PLANT_TO_CTRL"
TEST_KEY_SOURCE = "ci-test-key"
ENV_STATE_DIR = "RHONN_STATE_DIR"  # the nodes' state directories (the trip counter), not secret
TRIP_FILE = "secoc_trip"  # the trip counter's file name in a node's state directory

# --------------------------------------------------------------------------------------------
# CI / SIMULATION TEST KEYS ONLY. They are public (they are in this file): anyone can forge
# frames with them. Never use them outside tests and simulation runs.
_CI_TEST_KEY_CTRL_TO_PLANT = bytes.fromhex("0f1e2d3c4b5a69788796a5b4c3d2e1f0")
_CI_TEST_KEY_PLANT_TO_CTRL = bytes.fromhex("f0e1d2c3b4a5968778695a4b3c2d1e0f")
# --------------------------------------------------------------------------------------------


class SecOcKeyError(ValueError):
    """Keys missing, malformed or kept in an unsafe file (message never contains key bytes)."""


@dataclass(frozen=True)
class SecOcKeys:
    """One 128-bit key per direction. ``repr`` never shows the key bytes."""

    ctrl_to_plant: bytes = field(repr=False)
    plant_to_ctrl: bytes = field(repr=False)
    source: str = ""

    def __post_init__(self) -> None:
        for name in ("ctrl_to_plant", "plant_to_ctrl"):
            if len(getattr(self, name)) != 16:
                raise SecOcKeyError(f"SecOC key {name} must be 128 bit (16 bytes)")

    @property
    def is_test_key(self) -> bool:
        """True for the public CI test key (simulation only)."""
        return self.ctrl_to_plant == _CI_TEST_KEY_CTRL_TO_PLANT


def ci_test_keys() -> SecOcKeys:
    """The public CI test keys (clearly not secret; tests and simulation only)."""
    return SecOcKeys(_CI_TEST_KEY_CTRL_TO_PLANT, _CI_TEST_KEY_PLANT_TO_CTRL, TEST_KEY_SOURCE)


def _parse_hex_key(text: str, what: str) -> bytes:
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise SecOcKeyError(f"{what}: not a hex string") from None
    if len(key) != 16:
        raise SecOcKeyError(f"{what}: {len(key) * 8} bit, expected 128 (32 hex digits)")
    return key


def load_keys(source: str) -> SecOcKeys:
    """Keys from ``source``: ``env`` (the two RHONN_SECOC_KEY_* variables, 32 hex digits
    each), ``ci-test-key`` (public test key), or the path of a TOML key file with
    ``ctrl_to_plant = "<hex>"`` and ``plant_to_ctrl = "<hex>"``; the file is refused when its
    group or others have any permission (like ssh does). Errors raise SecOcKeyError."""
    if source == TEST_KEY_SOURCE:
        return ci_test_keys()
    if source == "env":
        missing = [v for v in (ENV_CTRL_TO_PLANT, ENV_PLANT_TO_CTRL) if not os.environ.get(v)]
        if missing:
            raise SecOcKeyError(f"SecOC key variable(s) not set: {', '.join(missing)} "
                                "(set both RHONN_SECOC_KEY_* variables, or neither for the "
                                "public test key)")
        return SecOcKeys(_parse_hex_key(os.environ[ENV_CTRL_TO_PLANT], ENV_CTRL_TO_PLANT),
                         _parse_hex_key(os.environ[ENV_PLANT_TO_CTRL], ENV_PLANT_TO_CTRL),
                         "env")
    path = Path(source)
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise SecOcKeyError(f"SecOC key file {path}: {exc.strerror}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SecOcKeyError(f"SecOC key file {path} is accessible by group/others "
                            f"(mode {stat.S_IMODE(mode):o}); chmod 600 it")
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SecOcKeyError(f"SecOC key file {path}: unreadable ({type(exc).__name__})") \
            from None
    try:
        return SecOcKeys(_parse_hex_key(str(data["ctrl_to_plant"]), f"{path}: ctrl_to_plant"),
                         _parse_hex_key(str(data["plant_to_ctrl"]), f"{path}: plant_to_ctrl"),
                         str(path))
    except KeyError as exc:
        raise SecOcKeyError(f"SecOC key file {path}: missing {exc.args[0]}") from None


def resolve_key_source(requested: str | None) -> str:
    """The key source a run uses: the requested one, else ``env`` when a RHONN_SECOC_KEY_*
    variable is set, else the public CI test key (simulation). One variable without the other
    is ``env`` too, so :func:`load_keys` refuses it naming the missing one: a half-set pair is
    a mistake, never a silent fall-back to the public key."""
    if requested:
        return requested
    if os.environ.get(ENV_CTRL_TO_PLANT) or os.environ.get(ENV_PLANT_TO_CTRL):
        return "env"
    return TEST_KEY_SOURCE


def key_kind(keys: SecOcKeys) -> str:
    """Where ``keys`` came from, in a user's words: ``file``, ``env`` or ``public test key``."""
    if keys.source == TEST_KEY_SOURCE:
        return "public test key"
    return "env" if keys.source == "env" else "file"


def secoc_state_text(keys: SecOcKeys | None) -> str:
    """The SecOC part of a process's ready line: ``SecOC on (key: KIND)`` or ``SecOC off``
    (``keys`` None: the frames are not authenticated)."""
    return f"SecOC on (key: {key_kind(keys)})" if keys is not None else "SecOC off"


class TripCounterError(SecOcKeyError):
    """The persisted trip counter cannot be read, is corrupt, or cannot be advanced: the
    freshness master must not start (a counter that starts again would accept recordings of
    earlier trips)."""


def state_dir(node: str) -> Path:
    """The node's state directory (persistent, not secret): ``$RHONN_STATE_DIR/NODE``, else
    ``$XDG_STATE_HOME/rhonn-tv/NODE``, else ``~/.local/state/rhonn-tv/NODE``."""
    root = os.environ.get(ENV_STATE_DIR)
    if root:
        return Path(root) / node
    xdg = os.environ.get("XDG_STATE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".local" / "state"
    return base / "rhonn-tv" / node


def default_trip_file(node: str = "plant") -> Path:
    """Where a node keeps its SecOC trip counter unless told otherwise (``--secoc-state``)."""
    return state_dir(node) / TRIP_FILE


@contextlib.contextmanager
def _exclusive(path: Path) -> Iterator[None]:
    """Hold an exclusive lock beside ``path`` (``.NAME.lock``): two plants that start at once
    on one counter file (parallel campaign workers) read, advance and write it one after the
    other and get different trips. The counter file itself cannot carry the lock: it is
    replaced by a rename, so each writer would lock another inode."""
    fd = os.open(path.parent / f".{path.name}.lock", os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


class TripCounter:
    """The freshness master's trip counter, persisted so that every start has a trip above
    every earlier one: frames recorded in an earlier trip are stale in every later one.

    The file holds one decimal number, the last trip used, and is replaced durably
    (can_db/process/durable.py) under a lock. Missing: this is the first trip (1), and the file
    is created with its directory. Unreadable, corrupt (not a whole number >= 1 within the
    wire's TRIP_BITS), exhausted or not writable: :class:`TripCounterError`; the caller
    refuses to start rather than reuse freshness values. ``path`` None (in-process loops and
    unit tests only, no process uses it): always trip 1, nothing persisted.
    """

    def __init__(self, path: str | Path | None) -> None:
        self.path = Path(path) if path else None
        self.value = 1
        self.created = False  # True when this start created the file (trip 1)

    def next_trip(self) -> int:
        """Advance (and persist) the trip counter at start; returns the new trip."""
        if self.path is None:
            return self.value
        path = self.path
        try:
            path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
            with _exclusive(path):
                previous = self._read(path)
                value = previous + 1
                if value >= 1 << TRIP_BITS:
                    raise TripCounterError(f"SecOC trip counter {path} exhausted "
                                           f"({previous}): rotate the keys, then remove it")
                replace_durably(path, lambda fh: fh.write(f"{value}\n".encode()))
        except OSError as exc:
            raise TripCounterError(f"SecOC trip counter {path}: cannot write "
                                   f"({exc.strerror or type(exc).__name__}); {_REFUSAL}") \
                from None
        self.value, self.created = value, previous == 0
        return value

    @staticmethod
    def _read(path: Path) -> int:
        """The last trip used (0: no file yet); TripCounterError if the file is not one."""
        try:
            text = path.read_text(encoding="ascii")
        except FileNotFoundError:
            return 0
        except (OSError, UnicodeDecodeError) as exc:
            raise TripCounterError(f"SecOC trip counter {path}: unreadable "
                                   f"({type(exc).__name__}); {_REFUSAL}") from None
        digits = text.removesuffix("\n")
        # only what this class writes: digits and one newline ("", "-3", " 7", "0x5" are not)
        if not digits.isdigit() or not digits.isascii() or int(digits) < 1 \
                or int(digits) >= 1 << TRIP_BITS:
            raise TripCounterError(f"SecOC trip counter {path}: corrupt ({text[:20]!r} is "
                                   f"not a trip 1 .. {(1 << TRIP_BITS) - 1}); {_REFUSAL}")
        return int(digits)


# why a counter that cannot be used stops the start, in the user's words (one line)
_REFUSAL = ("refusing to start: a counter that starts again would accept recordings of "
            "earlier trips (restore the file, or rotate the keys and remove it)")
