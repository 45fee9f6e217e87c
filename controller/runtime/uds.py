"""The controller's UDS (ISO 14229-1) server: pure request → response logic, no I/O.

Services (docs/diagnostics.md):

* 0x11 ECUReset, sub-function 0x01 hardReset or 0x03 softReset (bit 0x80 suppresses the
  positive response ``51 <sub>``); the reset itself is the caller's :class:`Action`.
* 0x2E WriteDataByIdentifier, DID 0xFD10 "controller coding": a UTF-8 JSON object
  ``{"controller", "config", "faults", "fault_seed"}`` (keys optional, a missing key keeps
  its value), kept pending until the next hard reset (``6E FD 10``).
* 0x22 ReadDataByIdentifier: 0xFD10 the active coding (JSON), 0xFD11 the boot counter,
  0xFD12 the soft resets since boot (2 bytes each, big-endian); several DIDs in one request.
* 0x3E TesterPresent, sub-function 0x00 (``7E 00``; bit 0x80 suppresses).

Negative responses ``7F <service> <NRC>``: 0x11 serviceNotSupported, 0x12
subFunctionNotSupported, 0x13 incorrectMessageLengthOrInvalidFormat, 0x14 responseTooLong,
0x22 conditionsNotCorrect (a reset or a coding write while the vehicle moves, unless the
server runs on a bench), 0x31 requestOutOfRange (unknown DID, coding that does not check).
The checks run in the order of ISO 14229-1's NRC handling (length, sub-function or DID,
conditions, data). A suppressed positive response never suppresses a negative one.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

# service identifiers (requests; a positive response is SID + 0x40)
ECU_RESET = 0x11
READ_DID = 0x22
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
NRC_REQUEST_OUT_OF_RANGE = 0x31

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


class UdsServer:
    """Answers UDS requests (see the module doc).

    ``coding``: the active controller coding (DID 0xFD10); ``boot_count``: this process's
    boot counter (DID 0xFD11); ``check_coding``: returns why a merged coding cannot run
    (unknown controller, config that does not load, bad fault spec) or None; ``bench``: the
    harness says this is a bench, resets and coding writes are allowed while moving.
    """

    def __init__(self, coding: dict, *, boot_count: int = 1,
                 check_coding: CodingCheck | None = None, bench: bool = False) -> None:
        self.coding = dict(coding)
        # written coding: active after the next hard reset, or after a soft reset when it
        # keeps the controller (controller/runtime/process.py)
        self.pending: dict | None = None
        self.boot_count = boot_count
        self.soft_resets = 0
        self.bench = bench
        self._check = check_coding
        self.counts = {"requests": 0, "negative": 0}

    def next_coding(self) -> dict:
        """The coding a hard reset starts with: the pending one, else the active one."""
        return dict(self.pending if self.pending is not None else self.coding)

    def handle(self, request: bytes, moving: bool) -> UdsReply:
        """The reply to one complete request; ``moving``: the vehicle moves (from the last
        valid VEHICLE_EST / wheel speeds)."""
        if not request:
            return UdsReply(None)
        self.counts["requests"] += 1
        sid = request[0]
        if sid == ECU_RESET:
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
        return reply

    def soft_reset_done(self) -> None:
        """Count a completed soft reset (DID 0xFD12)."""
        self.soft_resets = (self.soft_resets + 1) & 0xFFFF

    # ------------------------------------------------------------------ services
    def _ecu_reset(self, request: bytes, moving: bool) -> UdsReply:
        if len(request) < 2:
            return negative(ECU_RESET, NRC_BAD_LENGTH)
        sub = request[1] & ~SUPPRESS
        if sub not in (HARD_RESET, SOFT_RESET):
            return negative(ECU_RESET, NRC_SUBFUNCTION_NOT_SUPPORTED)
        if len(request) != 2:
            return negative(ECU_RESET, NRC_BAD_LENGTH)
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
