"""SecOC keys and the trip counter: where the secrets and the persisted freshness live.

Keys: one 128-bit key per direction (controller → plant, plant → controller), from a TOML key
file that is refused when group or others have any permission on it, from two environment
variables, or — for CI and simulation only — the public test key below. Key bytes never
appear in a repr, a log line or an error message.

The trip counter is the freshness master's (the plant's) start counter, persisted so that a
restarted plant never reuses a freshness value (can_db/secoc.py explains the freshness).
"""

from __future__ import annotations

import os
import stat
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

TRIP_BITS = 20  # width of the trip counter on the wire (SYNC_AUTH.TRIP)
ENV_CTRL_TO_PLANT = "RHONN_SECOC_KEY_CTRL_TO_PLANT"
ENV_PLANT_TO_CTRL = "RHONN_SECOC_KEY_PLANT_TO_CTRL"
TEST_KEY_SOURCE = "ci-test-key"

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


class TripCounter:
    """The freshness master's trip counter, persisted so a restarted plant never reuses a FV.

    ``path`` None: the trip is always 1 (a restarted plant would repeat freshness values, so
    its new frames would be refused as stale: persistence is what makes restarts work).
    The file is a single decimal number, replaced atomically.
    """

    def __init__(self, path: str | Path | None) -> None:
        self.path = Path(path) if path else None
        self.value = 1

    def next_trip(self) -> int:
        """Increment (and persist) the trip counter at start; returns the new trip."""
        if self.path is None:
            return self.value
        previous = 0
        try:
            previous = int(self.path.read_text().strip())
        except FileNotFoundError:
            previous = 0
        except (OSError, ValueError) as exc:
            raise SecOcKeyError(f"SecOC trip counter {self.path}: unreadable "
                                f"({type(exc).__name__}); refusing to guess") from None
        self.value = previous + 1
        if self.value >= 1 << TRIP_BITS:
            raise SecOcKeyError("SecOC trip counter exhausted: rotate the keys")
        tmp = self.path.with_suffix(self.path.suffix + ".tmp")
        tmp.write_text(f"{self.value}\n")
        os.replace(tmp, self.path)
        return self.value
