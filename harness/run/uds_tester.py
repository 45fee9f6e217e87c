"""The bench's UDS tester: ISO 14229 requests to the controller over the bus.

Built on udsoncan (the client: request encoding, response parsing, negative responses) and
can-isotp (ISO 15765-2 transport, normal 11-bit addressing, frames padded to 8 bytes with
0xCC) over python-can, on the DBC's diagnostic IDs DIAG_REQ_CTRL (0x7E0) / DIAG_RESP_CTRL
(0x7E8). The tester joins the bus only inside its ``with`` block.

    with UdsTester("local:bench") as tester:
        tester.unlock()                       # extended session + SecurityAccess
        tester.write_coding({"controller": "lmpc"})
        tester.ecu_reset("hard")

The key is computed here from the seed (HMAC-SHA256 of the seed under the diagnostic secret,
first 16 bytes), independently of the server's code; the secret is the controller's
(``--uds-secret``; by default $RHONN_UDS_SECRET or the public test secret).

Services and identifiers: docs/diagnostics.md; the server: controller/runtime/uds.py.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import json
import logging
from typing import Any

import can
import isotp
import udsoncan
from udsoncan.client import Client
from udsoncan.connections import PythonIsoTpConnection
from udsoncan.exceptions import (
    ConfigError,
    InvalidResponseException,
    NegativeResponseException,
    TimeoutException,
    UnexpectedResponseException,
)

from can_db.codec import Codec
from can_db.transport.bus import open_bus
from controller.runtime.uds import load_uds_secret

DID_CODING = 0xFD10
DID_BOOT_COUNT = 0xFD11
DID_SOFT_RESETS = 0xFD12
RESET_TYPES = {"hard": 0x01, "soft": 0x03}
EXTENDED_SESSION = 0x03
SECURITY_LEVEL = 0x01
PADDING = 0xCC
READ_TIMEOUT_S = 0.005

# udsoncan and can-isotp log every frame at DEBUG and some timeouts at WARNING/ERROR: the
# tester reports through its exceptions instead
for _name in ("isotp", "UdsClient", "Connection"):
    logging.getLogger(_name).setLevel(logging.CRITICAL)


class UdsError(Exception):
    """A request without a valid answer (no response in time, malformed response, bus)."""


class UdsNegativeResponse(UdsError):  # noqa: N818 - the name ISO 14229 uses
    """The server answered ``7F <service> <nrc>``."""

    def __init__(self, service: int, nrc: int) -> None:
        super().__init__(f"negative response to service 0x{service:02X}: NRC 0x{nrc:02X}")
        self.service = service
        self.nrc = nrc


def _key_of_seed(level: int, seed: bytes, params: bytes) -> bytes:
    """udsoncan's security algorithm: the key of ``seed`` under the secret ``params``."""
    del level
    return hmac.new(params, bytes(seed), hashlib.sha256).digest()[:16]


@functools.cache
def _diag_ids() -> tuple[int, int]:
    """(request ID, response ID) of the controller's diagnostic frames in the DBC (parsed
    once per process: a bench resets between every two runs)."""
    codec = Codec()
    return codec.diagnostic["DIAG_REQ_CTRL"], codec.diagnostic["DIAG_RESP_CTRL"]


class _RawDid(udsoncan.DidCodec):
    """A DID's bytes as they are: fixed ``size`` bytes, or (None) the rest of the response."""

    def __init__(self, size: int | None) -> None:
        super().__init__()
        self._size = size

    def encode(self, *did_value: Any) -> bytes:
        value = did_value[0]
        return value.encode() if isinstance(value, str) else bytes(value)

    def decode(self, did_payload: bytes) -> bytes:
        return bytes(did_payload)

    def __len__(self) -> int:
        if self._size is None:
            raise udsoncan.DidCodec.ReadAllRemainingData
        return self._size


class UdsTester:
    """A UDS client on the controller's diagnostic IDs of ``bus_spec`` (see the module doc).
    ``timeout_s``: how long a request may wait for its response, s (P2 and P2*: a reset
    answers once its work is done)."""

    def __init__(self, bus_spec: str, timeout_s: float = 5.0,
                 secret: bytes | None = None) -> None:
        self.bus_spec = bus_spec
        self.timeout_s = float(timeout_s)
        self.secret = secret if secret is not None else load_uds_secret("env")[0]
        self.req_id, self.resp_id = _diag_ids()
        self._bus: can.BusABC | None = None
        self._stack: isotp.CanStack | None = None
        self._conn: PythonIsoTpConnection | None = None
        self._client: Client | None = None

    # ------------------------------------------------------------------ context
    def __enter__(self) -> UdsTester:
        # only the responses reach the stack (python-can's software filter)
        self._bus = open_bus(self.bus_spec,
                             can_filters=[{"can_id": self.resp_id, "can_mask": 0x7FF}])
        try:
            address = isotp.Address(isotp.AddressingMode.Normal_11bits, txid=self.req_id,
                                    rxid=self.resp_id)
            params = {"tx_padding": PADDING, "tx_data_min_length": 8, "blocksize": 0,
                      "stmin": 0, "rx_flowcontrol_timeout": 1000,
                      "rx_consecutive_frame_timeout": 1000, "max_frame_size": 4095}
            # read_timeout: the stack's reader thread polls the bus this often, s; leaving
            # the with block waits for it, so short (a bench resets between every two runs)
            self._stack = isotp.CanStack(self._bus, address=address, params=params,
                                         read_timeout=READ_TIMEOUT_S)
            self._conn = PythonIsoTpConnection(self._stack)
            config = dict(udsoncan.configs.default_client_config)
            config.update({
                "request_timeout": self.timeout_s, "p2_timeout": self.timeout_s,
                "p2_star_timeout": self.timeout_s, "use_server_timing": False,
                "data_identifiers": {DID_CODING: _RawDid(None), DID_BOOT_COUNT: _RawDid(2),
                                     DID_SOFT_RESETS: _RawDid(2)},
                "security_algo": _key_of_seed, "security_algo_params": self.secret,
            })
            self._client = Client(self._conn, config=config)
            self._client.open()
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._close()

    def _close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()
        self._stack = self._conn = None

    # ------------------------------------------------------------------ services
    def unlock(self) -> None:
        """Extended session (0x10 0x03), then SecurityAccess level 1 (seed, key): what a
        coding write or a reset needs (docs/diagnostics.md)."""
        client = self._need()
        self._call(client.change_session, EXTENDED_SESSION)
        self._call(client.unlock_security_access, SECURITY_LEVEL)

    def ecu_reset(self, kind: str, suppress: bool = False) -> bytes | None:
        """ECUReset (0x11) ``kind`` "hard" (0x01) or "soft" (0x03); the positive response's
        bytes (``51 <sub>``), None when ``suppress`` asked the server not to answer."""
        if kind not in RESET_TYPES:
            raise ValueError(f"reset kind {kind!r}: one of {sorted(RESET_TYPES)}")
        client = self._need()
        if suppress:
            with client.suppress_positive_response:
                self._call(client.ecu_reset, RESET_TYPES[kind])
            return None
        return self._payload(self._call(client.ecu_reset, RESET_TYPES[kind]))

    def write_coding(self, coding: dict[str, Any]) -> bytes:
        """WriteDataByIdentifier 0xFD10: the controller coding as UTF-8 JSON (active after
        the next hard reset); the positive response's bytes (``6E FD 10``)."""
        payload = json.dumps(coding, sort_keys=True, separators=(",", ":")).encode()
        client = self._need()
        return self._payload(self._call(client.write_data_by_identifier, DID_CODING, payload))

    def read_did(self, did: int) -> bytes:
        """ReadDataByIdentifier of one DID: its data bytes (without the DID echo)."""
        client = self._need()
        response = self._call(client.read_data_by_identifier, did)
        try:
            return bytes(response.service_data.values[did])
        except (AttributeError, KeyError) as exc:
            raise UdsError(f"DID 0x{did:04X} missing from the response") from exc

    def read_coding(self) -> dict[str, Any]:
        """The active coding (DID 0xFD10) as a dict."""
        return json.loads(self.read_did(DID_CODING).decode())

    def tester_present(self) -> bytes:
        """TesterPresent (0x3E 0x00); the positive response's bytes (``7E 00``)."""
        return self._payload(self._call(self._need().tester_present))

    # ------------------------------------------------------------------ helpers
    def _need(self) -> Client:
        if self._client is None:
            raise UdsError("UdsTester used outside its with block")
        return self._client

    @staticmethod
    def _call(fn: Any, *args: Any) -> Any:
        try:
            return fn(*args)
        except NegativeResponseException as exc:
            raise UdsNegativeResponse(exc.response.service.request_id(),
                                      int(exc.response.code)) from None
        except (TimeoutException, InvalidResponseException, UnexpectedResponseException,
                ConfigError) as exc:
            raise UdsError(f"{type(exc).__name__}: {exc}") from None
        except (can.CanError, OSError) as exc:
            raise UdsError(f"bus: {exc}") from None

    @staticmethod
    def _payload(response: Any) -> bytes:
        if response is None:
            raise UdsError("no response")
        return bytes(response.original_payload)
