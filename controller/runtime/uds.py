"""The controller's UDS (ISO 14229-1) server: pure request → response logic, no I/O.

Services (docs/diagnostics.md):

* 0x11 ECUReset, sub-function 0x01 hardReset or 0x03 softReset (bit 0x80 suppresses the
  positive response ``51 <sub>``); the reset itself is the caller's :class:`Action`.
* 0x2E WriteDataByIdentifier, DID 0xFD10 "controller coding": a UTF-8 JSON object
  ``{"controller", "config", "faults", "fault_seed"}`` (keys optional, a missing key keeps
  its value), kept pending until the next hard reset (``6E FD 10``). Without ``bench`` only
  PRODUCTION_KEYS, the configuration by packaged name.
* 0x22 ReadDataByIdentifier: 0xFD10 the active coding (JSON), 0xFD11 the boot counter,
  0xFD12 the soft resets since boot (2 bytes each, big-endian); several DIDs in one request.
* 0x3E TesterPresent, sub-function 0x00 (``7E 00``; bit 0x80 suppresses).
* 0x10 DiagnosticSessionControl, 0x01 default or 0x03 extended session (``50 <sub>`` and the
  P2 / P2* timing); the extended session falls back to the default one after S3 (5 s)
  without a request, and every session change locks the security access again.
* 0x27 SecurityAccess, level 1: 0x01 requestSeed (``67 01`` + 16 random bytes; zeros when
  already unlocked), 0x02 sendKey (``67 02``) with key = HMAC-SHA256(secret, seed)[:16]; the
  secret is the diagnostic secret of the process, never the SecOC key. A seed answers one
  key; three wrong keys lock the service for 10 s.

ECUReset and WriteDataByIdentifier change what the controller does: they are accepted only
in the extended session with the security access unlocked; in the default session they get
0x7F serviceNotSupportedInActiveSession, locked 0x33 securityAccessDenied.

Negative responses ``7F <service> <NRC>``: 0x11 serviceNotSupported, 0x12
subFunctionNotSupported, 0x13 incorrectMessageLengthOrInvalidFormat, 0x14 responseTooLong,
0x22 conditionsNotCorrect (a reset or a coding write while the vehicle moves, unless the
server runs on a bench), 0x24 requestSequenceError (a key without a seed), 0x31
requestOutOfRange (unknown DID, coding that does not check), 0x33 securityAccessDenied, 0x35
invalidKey, 0x36 exceededNumberOfAttempts, 0x37 requiredTimeDelayNotExpired, 0x7F
serviceNotSupportedInActiveSession.
The checks run in the order of ISO 14229-1's NRC handling (length, sub-function or DID,
conditions, data). A suppressed positive response never suppresses a negative one.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

# service identifiers (requests; a positive response is SID + 0x40)
SESSION_CONTROL = 0x10
ECU_RESET = 0x11
READ_DID = 0x22
SECURITY_ACCESS = 0x27
WRITE_DID = 0x2E
TESTER_PRESENT = 0x3E
NEGATIVE = 0x7F
SUPPRESS = 0x80  # suppressPosRspMsgIndicationBit of a sub-function byte

HARD_RESET = 0x01
SOFT_RESET = 0x03

# negative response codes (ISO 14229-1 annex A)
NRC_SERVICE_NOT_SUPPORTED = 0x11
NRC_SUBFUNCTION_NOT_SUPPORTED = 0x12
NRC_BAD_LENGTH = 0x13
NRC_RESPONSE_TOO_LONG = 0x14
NRC_CONDITIONS_NOT_CORRECT = 0x22
NRC_SEQUENCE_ERROR = 0x24
NRC_REQUEST_OUT_OF_RANGE = 0x31
NRC_SECURITY_DENIED = 0x33
NRC_INVALID_KEY = 0x35
NRC_ATTEMPTS_EXCEEDED = 0x36
NRC_DELAY_NOT_EXPIRED = 0x37
NRC_NOT_IN_SESSION = 0x7F

DEFAULT_SESSION = 0x01
EXTENDED_SESSION = 0x03
REQUEST_SEED = 0x01
SEND_KEY = 0x02
SEED_BYTES = 16
P2_MS = 50          # the server's response time (P2), ms
P2_STAR_MS = 5000   # its extended response time (P2*), ms (a reset answers once done)
S3_S = 5.0          # a non-default session ends after this long without a request, s
MAX_ATTEMPTS = 3    # wrong keys before the lock-out
LOCKOUT_S = 10.0    # SecurityAccess refused this long after MAX_ATTEMPTS wrong keys, s
PUBLIC_TEST_SECRET = hashlib.sha256(b"rhonn-tv public diagnostic test secret").digest()[:16]
"""The diagnostic secret of a controller started without one: published (tests, benches), so
it protects nothing; a vehicle sets its own (``--uds-secret FILE`` / $RHONN_UDS_SECRET)."""

DID_CODING = 0xFD10
DID_BOOT_COUNT = 0xFD11
DID_SOFT_RESETS = 0xFD12
CODING_KEYS = ("controller", "config", "faults", "fault_seed")
MAX_RESPONSE = 4095  # the ISO-TP message limit, bytes
MOVING_KMH = 0.5  # above this speed the vehicle moves: no reset, no coding write, km/h


class Action(Enum):
    """What the caller does after sending the response."""

    NONE = "none"
    SOFT_RESET = "soft_reset"
    HARD_RESET = "hard_reset"


@dataclass(frozen=True, slots=True)
class UdsReply:
    """A request's outcome: the response bytes (None: suppressed, or no request at all)
    and the action the caller takes."""

    response: bytes | None
    action: Action = Action.NONE


CodingCheck = Callable[[dict], str | None]


class UdsSecretError(ValueError):
    """The diagnostic secret cannot be read (one line, for the command line)."""


def load_uds_secret(source: str, environ: dict[str, str] | None = None) -> tuple[bytes, str]:
    """(secret, where it came from) of ``source``: "env" ($RHONN_UDS_SECRET as hex when set,
    else the public test secret), "public" (the public test secret), or a file holding the
    secret as hex (at least 32 hex digits, i.e. 16 bytes)."""
    def from_hex(text: str, where: str) -> bytes:
        try:
            secret = bytes.fromhex(text.strip())
        except ValueError:
            raise UdsSecretError(f"{where}: not hex digits") from None
        if len(secret) < 16:
            raise UdsSecretError(f"{where}: needs at least 16 bytes (32 hex digits)")
        return secret

    if source == "public":
        return PUBLIC_TEST_SECRET, "public test secret"
    if source == "env":
        text = (environ if environ is not None else os.environ).get(
            "RHONN_UDS_SECRET")
        if not text:
            return PUBLIC_TEST_SECRET, "public test secret"
        return from_hex(text, "$RHONN_UDS_SECRET"), "$RHONN_UDS_SECRET"
    try:
        with open(source, encoding="ascii") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise UdsSecretError(f"--uds-secret {source}: {getattr(exc, 'strerror', exc)}") from None
    return from_hex(text, f"--uds-secret {source}"), "file"


def security_key(secret: bytes, seed: bytes) -> bytes:
    """The SecurityAccess key for ``seed``: HMAC-SHA256(secret, seed), first 16 bytes."""
    return hmac.new(secret, seed, hashlib.sha256).digest()[:SEED_BYTES]


def negative(service: int, nrc: int) -> UdsReply:
    """The negative response ``7F <service> <nrc>``."""
    return UdsReply(bytes((NEGATIVE, service, nrc)))


def coding_json(coding: dict) -> bytes:
    """The DID 0xFD10 representation of ``coding``: compact UTF-8 JSON, keys sorted."""
    return json.dumps(coding, sort_keys=True, separators=(",", ":")).encode()


def merge_coding(base: dict, update: dict) -> dict:
    """``base`` with the keys of ``update`` that a coding knows (a missing key keeps its
    value)."""
    return {**base, **{k: update[k] for k in CODING_KEYS if k in update}}


def check_coding_types(coding: dict) -> str | None:
    """Why ``coding`` is not a well-typed coding object (None: it is)."""
    if not isinstance(coding, dict):
        return "not a JSON object"
    unknown = sorted(set(coding) - set(CODING_KEYS))
    if unknown:
        return f"unknown key(s) {unknown}"
    if "controller" in coding and not isinstance(coding["controller"], str):
        return "controller: not a string"
    if "config" in coding and not (coding["config"] is None or isinstance(coding["config"], str)):
        return "config: not a string or null"
    if "faults" in coding and not (isinstance(coding["faults"], list)
                                   and all(isinstance(f, str) for f in coding["faults"])):
        return "faults: not a list of strings"
    seed = coding.get("fault_seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        return "fault_seed: not an integer >= 0"
    return None


PRODUCTION_KEYS = ("controller", "config")
"""What a production coding (a controller started without --bench) may write: the controller
and a packaged configuration by name. Fault injection (faults, fault_seed) and configuration
files by path are bench-only."""


def production_problem(update: dict) -> str | None:
    """Why a coding write is refused on a production controller (None: allowed)."""
    extra = sorted(k for k in update if k not in PRODUCTION_KEYS)
    if extra:
        return f"{', '.join(extra)}: bench only"
    config = update.get("config")
    if isinstance(config, str) and ("/" in config or "\\" in config or config.endswith(".toml")):
        return "config: a packaged configuration name only (a file path is bench only)"
    return None


class UdsServer:
    """Answers UDS requests (see the module doc).

    ``coding``: the active controller coding (DID 0xFD10); ``boot_count``: this process's
    boot counter (DID 0xFD11); ``check_coding``: returns why a merged coding cannot run
    (unknown controller, config that does not load, bad fault spec) or None; ``bench``: the
    harness says this is a bench, resets and coding writes are allowed while moving;
    ``secret``: the diagnostic secret the SecurityAccess key is derived from (16+ bytes);
    ``random_bytes``: the seed source (tests inject a seeded one).
    """

    def __init__(self, coding: dict, *, boot_count: int = 1,
                 check_coding: CodingCheck | None = None, bench: bool = False,
                 secret: bytes = PUBLIC_TEST_SECRET,
                 random_bytes: Callable[[int], bytes] = secrets.token_bytes) -> None:
        if len(secret) < 16:
            raise ValueError("the diagnostic secret needs at least 16 bytes")
        self.coding = dict(coding)
        # written coding: active after the next hard reset, or after a soft reset when it
        # keeps the controller (controller/runtime/process.py)
        self.pending: dict | None = None
        self.boot_count = boot_count
        self.soft_resets = 0
        self.bench = bench
        self._check = check_coding
        self._secret = bytes(secret)
        self._random = random_bytes
        self.session = DEFAULT_SESSION
        self.unlocked = False
        self._seed: bytes | None = None    # the seed that the next key must answer
        self._failed_keys = 0
        self._locked_until = -1.0         # SecurityAccess refused before this time, s
        self._last_request = 0.0          # time of the last request, s (S3)
        self.counts = {"requests": 0, "negative": 0}
        self.refused: dict[str, int] = {}  # negative responses by "service/NRC", hex

    def next_coding(self) -> dict:
        """The coding a hard reset starts with: the pending one, else the active one."""
        return dict(self.pending if self.pending is not None else self.coding)

    def handle(self, request: bytes, moving: bool, now_s: float = 0.0) -> UdsReply:
        """The reply to one complete request; ``moving``: the vehicle moves (from the last
        valid VEHICLE_EST / wheel speeds); ``now_s``: the caller's monotonic time, s (the
        S3 session timeout and the key lock-out)."""
        if not request:
            return UdsReply(None)
        self.expire(now_s)
        self._last_request = now_s
        self.counts["requests"] += 1
        sid = request[0]
        if sid == SESSION_CONTROL:
            reply = self._session_control(request)
        elif sid == SECURITY_ACCESS:
            reply = self._security_access(request, now_s)
        elif sid in (ECU_RESET, WRITE_DID) and (refusal := self._protected(sid)):
            reply = refusal
        elif sid == ECU_RESET:
            reply = self._ecu_reset(request, moving)
        elif sid == READ_DID:
            reply = self._read(request)
        elif sid == WRITE_DID:
            reply = self._write(request, moving)
        elif sid == TESTER_PRESENT:
            reply = self._tester_present(request)
        else:
            reply = negative(sid, NRC_SERVICE_NOT_SUPPORTED)
        if reply.response is not None and reply.response[0] == NEGATIVE:
            self.counts["negative"] += 1
            key = f"{reply.response[1]:02X}/{reply.response[2]:02X}"
            self.refused[key] = self.refused.get(key, 0) + 1
        return reply

    def expire(self, now_s: float) -> None:
        """S3: back to the default session (locked) after S3_S without a request."""
        if self.session != DEFAULT_SESSION and now_s - self._last_request > S3_S:
            self._enter(DEFAULT_SESSION)

    def _enter(self, session: int) -> None:
        self.session = session
        self.unlocked = False
        self._seed = None

    def _protected(self, sid: int) -> UdsReply | None:
        """The refusal of a behaviour-changing service outside an unlocked extended session
        (None: allowed)."""
        if self.session == DEFAULT_SESSION:
            return negative(sid, NRC_NOT_IN_SESSION)
        if not self.unlocked:
            return negative(sid, NRC_SECURITY_DENIED)
        return None

    def soft_reset_done(self) -> None:
        """Count a completed soft reset (DID 0xFD12); the ECU is back in the default session,
        locked."""
        self.soft_resets = (self.soft_resets + 1) & 0xFFFF
        self._enter(DEFAULT_SESSION)

    # ------------------------------------------------------------------ services
    @staticmethod
    def _sub_function(request: bytes, service: int, allowed: tuple[int, ...]) -> int | UdsReply:
        """The sub-function of a two-byte request (suppress bit cleared), or its negative
        response in ISO 14229-1's order: length, sub-function, exact length."""
        if len(request) < 2:
            return negative(service, NRC_BAD_LENGTH)
        sub = request[1] & ~SUPPRESS
        if sub not in allowed:
            return negative(service, NRC_SUBFUNCTION_NOT_SUPPORTED)
        if len(request) != 2:
            return negative(service, NRC_BAD_LENGTH)
        return sub

    def _session_control(self, request: bytes) -> UdsReply:
        sub = self._sub_function(request, SESSION_CONTROL, (DEFAULT_SESSION, EXTENDED_SESSION))
        if isinstance(sub, UdsReply):
            return sub
        self._enter(sub)
        if request[1] & SUPPRESS:
            return UdsReply(None)
        return UdsReply(bytes((SESSION_CONTROL + 0x40, sub)) + P2_MS.to_bytes(2, "big")
                        + (P2_STAR_MS // 10).to_bytes(2, "big"))

    def _security_access(self, request: bytes, now_s: float) -> UdsReply:
        if len(request) < 2:
            return negative(SECURITY_ACCESS, NRC_BAD_LENGTH)
        sub = request[1] & ~SUPPRESS
        if sub not in (REQUEST_SEED, SEND_KEY):
            return negative(SECURITY_ACCESS, NRC_SUBFUNCTION_NOT_SUPPORTED)
        if self.session == DEFAULT_SESSION:
            return negative(SECURITY_ACCESS, NRC_NOT_IN_SESSION)
        if sub == REQUEST_SEED:
            if len(request) != 2:
                return negative(SECURITY_ACCESS, NRC_BAD_LENGTH)
            if now_s < self._locked_until:
                return negative(SECURITY_ACCESS, NRC_DELAY_NOT_EXPIRED)
            if self.unlocked:   # ISO 14229-1: an unlocked level answers a seed of zeros
                return UdsReply(bytes((SECURITY_ACCESS + 0x40, REQUEST_SEED))
                                + bytes(SEED_BYTES))
            self._seed = self._random(SEED_BYTES)
            return UdsReply(bytes((SECURITY_ACCESS + 0x40, REQUEST_SEED)) + self._seed)
        if len(request) != 2 + SEED_BYTES:
            return negative(SECURITY_ACCESS, NRC_BAD_LENGTH)
        if self._seed is None:
            return negative(SECURITY_ACCESS, NRC_SEQUENCE_ERROR)
        seed, self._seed = self._seed, None          # a seed answers one key
        if not hmac.compare_digest(request[2:], security_key(self._secret, seed)):
            self._failed_keys += 1
            if self._failed_keys >= MAX_ATTEMPTS:
                self._failed_keys = 0
                self._locked_until = now_s + LOCKOUT_S
                return negative(SECURITY_ACCESS, NRC_ATTEMPTS_EXCEEDED)
            return negative(SECURITY_ACCESS, NRC_INVALID_KEY)
        self._failed_keys = 0
        self.unlocked = True
        return UdsReply(None if request[1] & SUPPRESS
                        else bytes((SECURITY_ACCESS + 0x40, SEND_KEY)))

    def _ecu_reset(self, request: bytes, moving: bool) -> UdsReply:
        sub = self._sub_function(request, ECU_RESET, (HARD_RESET, SOFT_RESET))
        if isinstance(sub, UdsReply):
            return sub
        if moving and not self.bench:
            return negative(ECU_RESET, NRC_CONDITIONS_NOT_CORRECT)
        action = Action.HARD_RESET if sub == HARD_RESET else Action.SOFT_RESET
        response = None if request[1] & SUPPRESS else bytes((ECU_RESET + 0x40, sub))
        return UdsReply(response, action)

    def _read(self, request: bytes) -> UdsReply:
        if len(request) < 3 or len(request) % 2 != 1:
            return negative(READ_DID, NRC_BAD_LENGTH)
        out = bytearray((READ_DID + 0x40,))
        for i in range(1, len(request), 2):
            did = int.from_bytes(request[i:i + 2], "big")
            if did == DID_CODING:
                data = coding_json(self.coding)
            elif did == DID_BOOT_COUNT:
                data = (self.boot_count & 0xFFFF).to_bytes(2, "big")
            elif did == DID_SOFT_RESETS:
                data = self.soft_resets.to_bytes(2, "big")
            else:
                return negative(READ_DID, NRC_REQUEST_OUT_OF_RANGE)
            out += did.to_bytes(2, "big") + data
        if len(out) > MAX_RESPONSE:
            return negative(READ_DID, NRC_RESPONSE_TOO_LONG)
        return UdsReply(bytes(out))

    def _write(self, request: bytes, moving: bool) -> UdsReply:
        if len(request) < 4:
            return negative(WRITE_DID, NRC_BAD_LENGTH)
        did = int.from_bytes(request[1:3], "big")
        if did != DID_CODING:
            return negative(WRITE_DID, NRC_REQUEST_OUT_OF_RANGE)
        if moving and not self.bench:
            return negative(WRITE_DID, NRC_CONDITIONS_NOT_CORRECT)
        try:
            update = json.loads(request[3:].decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            return negative(WRITE_DID, NRC_REQUEST_OUT_OF_RANGE)
        if check_coding_types(update) is not None:
            return negative(WRITE_DID, NRC_REQUEST_OUT_OF_RANGE)
        if not self.bench and production_problem(update) is not None:
            return negative(WRITE_DID, NRC_REQUEST_OUT_OF_RANGE)
        coding = merge_coding(self.next_coding(), update)
        if self._check is not None and self._check(coding) is not None:
            return negative(WRITE_DID, NRC_REQUEST_OUT_OF_RANGE)
        self.pending = coding
        return UdsReply(bytes((WRITE_DID + 0x40,)) + request[1:3])

    def _tester_present(self, request: bytes) -> UdsReply:
        if len(request) < 2:
            return negative(TESTER_PRESENT, NRC_BAD_LENGTH)
        if request[1] & ~SUPPRESS != 0x00:
            return negative(TESTER_PRESENT, NRC_SUBFUNCTION_NOT_SUPPORTED)
        if len(request) != 2:
            return negative(TESTER_PRESENT, NRC_BAD_LENGTH)
        return UdsReply(None if request[1] & SUPPRESS else bytes((TESTER_PRESENT + 0x40, 0x00)))
