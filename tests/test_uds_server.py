"""The controller's UDS server and ISO-TP endpoint, pure (controller/runtime/uds.py, isotp.py).

Requests are encoded by udsoncan's own Request classes and our responses parsed by udsoncan's
Response classes (an independent implementation of ISO 14229-1), and the ISO-TP endpoint is
checked frame by frame against ISO 15765-2 (segmentation both ways, flow control, sequence
numbers, timeouts, overflow) and end to end against can-isotp's transport layer.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import random
from typing import Any

import pytest
import udsoncan
from udsoncan import Request, Response, services

from controller.runtime.isotp import IsoTpEndpoint, pad, stmin_s
from controller.runtime.uds import (
    DID_BOOT_COUNT,
    DID_CODING,
    DID_SOFT_RESETS,
    Action,
    UdsServer,
    coding_json,
)

CODING = {"controller": "lmpc", "config": None, "faults": [], "fault_seed": 2}


class _Json(udsoncan.DidCodec):
    """DID 0xFD10 for udsoncan: a JSON object, the rest of the response."""

    def encode(self, *value: Any) -> bytes:
        return json.dumps(value[0]).encode()

    def decode(self, payload: bytes) -> Any:
        return json.loads(payload.decode())

    def __len__(self) -> int:
        raise udsoncan.DidCodec.ReadAllRemainingData


DIDS = {DID_CODING: _Json(), DID_BOOT_COUNT: udsoncan.DidCodec(">H"),
        DID_SOFT_RESETS: udsoncan.DidCodec(">H")}


def _check(coding: dict) -> str | None:
    return None if coding.get("controller") in ("lmpc", "nmpc-rhonn", "nmpc-mf", "passive") \
        else "unknown controller"


SECRET = bytes(range(16, 48))   # a test secret (32 bytes)


def _key(seed: bytes, secret: bytes = SECRET) -> bytes:
    """The SecurityAccess key, computed here (HMAC-SHA256, first 16 bytes)."""
    return hmac.new(secret, seed, hashlib.sha256).digest()[:16]


def _unlock(server: UdsServer, now_s: float = 0.0) -> None:
    """Extended session, seed, key: the sequence a tester runs (requests by udsoncan)."""
    session = services.DiagnosticSessionControl.make_request(0x03).get_payload()
    assert _parsed(server.handle(session, moving=False, now_s=now_s).response).positive
    seed_req = services.SecurityAccess.make_request(
        0x01, services.SecurityAccess.Mode.RequestSeed).get_payload()
    seed = _parsed(server.handle(seed_req, moving=False, now_s=now_s).response).data[1:]
    key_req = services.SecurityAccess.make_request(
        0x02, services.SecurityAccess.Mode.SendKey, data=_key(seed)).get_payload()
    assert _parsed(server.handle(key_req, moving=False, now_s=now_s).response).positive


def _server(bench: bool = False, unlocked: bool = True) -> UdsServer:
    """A server with the test secret; ``unlocked``: in the extended session, security
    access granted (what a reset or a coding write needs)."""
    server = UdsServer(CODING, boot_count=7, check_coding=_check, bench=bench, secret=SECRET,
                       random_bytes=random.Random(5).randbytes)
    if unlocked:
        _unlock(server)
    return server


def _parsed(payload: bytes | None) -> Response:
    assert payload is not None
    response = Response.from_payload(payload)
    assert response.valid, payload.hex()
    return response


def _nrc(payload: bytes | None, service: int, nrc: int) -> None:
    response = _parsed(payload)
    assert not response.positive and response.service.request_id() == service
    assert response.code == nrc, (payload.hex() if payload else None)


# ---------------------------------------------------------------------- ECUReset
@pytest.mark.parametrize("kind, action", [(0x01, Action.HARD_RESET), (0x03, Action.SOFT_RESET)])
def test_ecu_reset_positive_and_suppressed(kind: int, action: Action) -> None:
    server = _server()
    reply = server.handle(services.ECUReset.make_request(kind).get_payload(), moving=False)
    assert reply.action is action
    response = _parsed(reply.response)
    assert response.positive and response.service is services.ECUReset
    services.ECUReset.interpret_response(response)
    assert response.service_data.reset_type_echo == kind
    suppressed = Request(services.ECUReset, subfunction=kind, suppress_positive_response=True)
    reply = server.handle(suppressed.get_payload(), moving=False)
    assert reply.response is None and reply.action is action  # reset still carried out


@pytest.mark.parametrize("sub", [0x02, 0x04, 0x05, 0x00, 0x7F, 0x82])
def test_ecu_reset_unsupported_sub_functions(sub: int) -> None:
    reply = _server().handle(bytes((0x11, sub)), moving=False)
    _nrc(reply.response, 0x11, 0x12)
    assert reply.action is Action.NONE


@pytest.mark.parametrize("request_", [b"\x11", b"\x11\x01\x00", b"\x11\x03\xff\xff"])
def test_ecu_reset_bad_length(request_: bytes) -> None:
    reply = _server().handle(request_, moving=False)
    _nrc(reply.response, 0x11, 0x13)
    assert reply.action is Action.NONE


def test_reset_refused_while_moving_unless_bench() -> None:
    for kind in (0x01, 0x03, 0x81):
        reply = _server().handle(bytes((0x11, kind)), moving=True)
        _nrc(reply.response, 0x11, 0x22)  # suppression never hides a negative response
        assert reply.action is Action.NONE
        assert _server(bench=True).handle(bytes((0x11, kind)), moving=True).action \
            is not Action.NONE


# ---------------------------------------------------------------------- coding
def test_coding_write_pending_until_hard_reset() -> None:
    server = _server(bench=True)   # faults: bench only
    request = services.WriteDataByIdentifier.make_request(
        DID_CODING, {"controller": "nmpc-rhonn", "faults": ["loss:5%@1s"]}, DIDS)
    reply = server.handle(request.get_payload(), moving=False)
    response = _parsed(reply.response)
    assert response.positive
    services.WriteDataByIdentifier.interpret_response(response)
    assert response.service_data.did_echo == DID_CODING
    # active coding unchanged (0xFD10 reads it), the merged coding pending
    read = server.handle(services.ReadDataByIdentifier.make_request(
        DID_CODING, DIDS).get_payload(), moving=False)
    response = _parsed(read.response)
    services.ReadDataByIdentifier.interpret_response(response, DID_CODING, DIDS)
    assert response.service_data.values[DID_CODING] == CODING
    assert server.next_coding() == {**CODING, "controller": "nmpc-rhonn",
                                    "faults": ["loss:5%@1s"]}
    # a second write merges into the pending one
    server.handle(b"\x2e\xfd\x10" + json.dumps({"fault_seed": 9}).encode(), moving=False)
    assert server.next_coding()["controller"] == "nmpc-rhonn"
    assert server.next_coding()["fault_seed"] == 9


@pytest.mark.parametrize("data", [
    b"\x2e\xfd\x10not json", b"\x2e\xfd\x10\xff\xfe", b"\x2e\xfd\x10[1, 2]",
    b'\x2e\xfd\x10{"controller": "nope"}', b'\x2e\xfd\x10{"colour": "red"}',
    b'\x2e\xfd\x10{"fault_seed": -1}', b'\x2e\xfd\x10{"faults": "loss:1%"}',
    b"\x2e\xfd\x11{}", b"\x2e\x00\x01{}", b'\x2e\xfd\x10{"controller": 5}',
    b'\x2e\xfd\x10{"config": 5}', b'\x2e\xfd\x10{"config": ["a.toml"]}'])
def test_coding_write_out_of_range(data: bytes) -> None:
    server = _server()
    _nrc(server.handle(data, moving=False).response, 0x2E, 0x31)
    assert server.pending is None


def test_coding_write_length_and_moving() -> None:
    for short in (b"\x2e", b"\x2e\xfd", b"\x2e\xfd\x10"):
        _nrc(_server().handle(short, moving=False).response, 0x2E, 0x13)
    good = b'\x2e\xfd\x10{"controller": "lmpc"}'
    _nrc(_server().handle(good, moving=True).response, 0x2E, 0x22)
    assert _parsed(_server(bench=True).handle(good, moving=True).response).positive


# ---------------------------------------------------------------------- read, tester present
def test_read_counters_and_several_dids() -> None:
    server = _server()
    server.soft_reset_done()
    server.soft_reset_done()
    request = services.ReadDataByIdentifier.make_request([DID_BOOT_COUNT, DID_SOFT_RESETS], DIDS)
    response = _parsed(server.handle(request.get_payload(), moving=True).response)
    services.ReadDataByIdentifier.interpret_response(response, [DID_BOOT_COUNT,
                                                                DID_SOFT_RESETS], DIDS)
    assert response.service_data.values[DID_BOOT_COUNT] == (7,)
    assert response.service_data.values[DID_SOFT_RESETS] == (2,)


def test_read_errors() -> None:
    _nrc(_server().handle(b"\x22\x12\x34", moving=False).response, 0x22, 0x31)
    for bad in (b"\x22", b"\x22\xfd", b"\x22\xfd\x11\x00"):
        _nrc(_server().handle(bad, moving=False).response, 0x22, 0x13)
    many = b"\x22" + b"\xfd\x10" * 200  # 200 copies of the coding: beyond 4095 bytes
    _nrc(_server().handle(many, moving=False).response, 0x22, 0x14)


def test_tester_present_and_unknown_service() -> None:
    response = _parsed(_server().handle(services.TesterPresent.make_request().get_payload(),
                                        moving=True).response)
    assert response.positive and response.service is services.TesterPresent
    assert _server().handle(b"\x3e\x80", moving=False).response is None
    _nrc(_server().handle(b"\x3e\x01", moving=False).response, 0x3E, 0x12)
    _nrc(_server().handle(b"\x3e\x00\x00", moving=False).response, 0x3E, 0x13)
    _nrc(_server().handle(b"\x3e", moving=False).response, 0x3E, 0x13)  # no sub-function
    for sid in (0x31, 0x19, 0x85):  # services udsoncan knows
        _nrc(_server().handle(bytes((sid, 0x01)), moving=False).response, sid, 0x11)
    for sid in (0x51, 0x7F, 0xBA, 0x00):  # response IDs and unassigned ones
        assert _server().handle(bytes((sid, 0x01)), moving=False).response \
            == bytes((0x7F, sid, 0x11))
    assert _server().handle(b"", moving=False).response is None


# ---------------------------------------------------------------------- ISO-TP
def _segments(message: bytes) -> list[bytes]:
    """ISO 15765-2 frames of ``message`` written out by hand (FF then CFs, 0xCC padding)."""
    if len(message) <= 7:
        return [pad(bytes((len(message),)) + message)]
    frames = [bytes((0x10 | len(message) >> 8, len(message) & 0xFF)) + message[:6]]
    for n, pos in enumerate(range(6, len(message), 7), start=1):
        frames.append(pad(bytes((0x20 | n & 0x0F,)) + message[pos:pos + 7]))
    return frames


def test_isotp_single_frame_and_padding() -> None:
    ep = IsoTpEndpoint()
    assert ep.feed(bytes.fromhex("021101cccccccccc"), 0.0) == b"\x11\x01"
    assert ep.feed(bytes.fromhex("0211"), 0.0) is None  # SF_DL beyond the frame: ignored
    assert ep.feed(bytes.fromhex("00cccccccccccccc"), 0.0) is None  # SF_DL 0: CAN FD escape
    ep.send(b"\x51\x01", 0.0)
    assert ep.due(0.0) == [bytes.fromhex("025101cccccccccc")]


def test_isotp_600_byte_coding_write_through_the_server() -> None:
    coding = {**CODING, "faults": [f"loss:{i % 50 + 1}%@{i}s" for i in range(40)]}
    payload = services.WriteDataByIdentifier.make_request(DID_CODING, coding, DIDS).get_payload()
    assert len(payload) >= 600
    ep, server = IsoTpEndpoint(), _server(bench=True)
    frames = _segments(payload)
    assert ep.feed(frames[0], 0.0) is None
    assert ep.due(0.0) == [bytes.fromhex("300000cccccccccc")]  # FC CTS, BS 0, STmin 0
    message = None
    for i, frame in enumerate(frames[1:]):
        assert message is None
        message = ep.feed(frame, 0.001 * i)
    assert message == payload
    assert _parsed(server.handle(message, moving=False).response).positive
    assert server.next_coding()["faults"] == coding["faults"]


def test_isotp_multi_frame_response_honours_flow_control() -> None:
    server = UdsServer({**CODING, "config": "x" * 100})
    response = server.handle(b"\x22\xfd\x10", moving=False).response
    assert response is not None and len(response) > 100
    ep = IsoTpEndpoint()
    ep.send(response, 0.0)
    first = ep.due(0.0)
    assert len(first) == 1 and first[0][0] >> 4 == 1
    assert ((first[0][0] & 0x0F) << 8 | first[0][1]) == len(response)
    assert ep.due(0.5) == []  # nothing before the tester's flow control
    ep.feed(bytes.fromhex("300205cccccccccc"), 0.5)  # BS 2, STmin 5 ms
    assert [f[0] for f in ep.due(0.5)] == [0x21]
    assert ep.next_release_s == pytest.approx(0.505)
    assert [f[0] for f in ep.due(0.505)] == [0x22]
    assert ep.due(1.0) == []  # block done: waits for the next flow control
    ep.feed(bytes.fromhex("300000cccccccccc"), 1.0)
    rest = ep.due(1.0)
    frames = [*first, pad(bytes((0x21,)) + response[6:13]),
              pad(bytes((0x22,)) + response[13:20]), *rest]
    assert frames == [f if i == 0 else pad(f) for i, f in enumerate(_segments(response))]
    assert [f[0] & 0x0F for f in rest] == [(3 + i) & 0x0F for i in range(len(rest))]
    joined = frames[0][2:] + b"".join(f[1:] for f in frames[1:])  # the payload reassembled
    assert joined[:len(response)] == response and set(joined[len(response):]) <= {0xCC}
    parsed = _parsed(joined[:len(response)])
    services.ReadDataByIdentifier.interpret_response(parsed, DID_CODING, DIDS)
    assert parsed.service_data.values[DID_CODING]["config"] == "x" * 100
    assert not ep.sending


def test_isotp_wrong_sequence_timeout_overflow() -> None:
    message = bytes(range(40))
    frames = _segments(message)
    ep = IsoTpEndpoint()
    ep.feed(frames[0], 0.0)
    ep.feed(frames[1], 0.1)
    assert ep.feed(frames[3], 0.2) is None and not ep.receiving  # sequence 3 after 1: abort
    assert ep.counts["aborted_rx"] == 1
    assert all(ep.feed(f, 0.3) is None for f in frames[4:])  # the rest is ignored
    # N_Cr: a consecutive frame more than 1 s after the previous one aborts
    ep.feed(frames[0], 1.0)
    assert ep.feed(frames[1], 2.5) is None and not ep.receiving
    assert ep.counts["aborted_rx"] == 2
    # a complete message in time still works on the same endpoint
    ep.feed(frames[0], 3.0)
    got = [ep.feed(f, 3.0) for f in frames[1:]]
    assert got[-1] == message and ep.counts["received"] == 1
    # 4095 bytes fit the buffer; a first frame beyond it (the 32-bit escape, here 5000
    # bytes): flow control overflow, nothing buffered
    ep.due(10.0)
    assert ep.feed(bytes.fromhex("1fffcccccccccccc"), 10.0) is None and ep.receiving
    assert ep.due(10.0) == [bytes.fromhex("300000cccccccccc")]
    assert ep.feed(bytes.fromhex("1000000013880000"), 10.0) is None
    assert ep.due(10.0) == [bytes.fromhex("320000cccccccccc")] and not ep.receiving
    small = IsoTpEndpoint(max_message=64)
    small.feed(_segments(bytes(65))[0], 0.0)
    assert small.due(0.0)[0][0] == 0x32
    # sender: no flow control within N_Bs (1 s) aborts
    ep.send(message, 20.0)
    ep.due(20.0)
    ep.poll(21.5)
    assert not ep.sending and ep.counts["aborted_tx"] == 1
    ep.send(message, 30.0)
    ep.feed(bytes.fromhex("32000000"), 30.1)  # overflow from the peer: abort
    assert not ep.sending and ep.due(31.0) == [] and ep.counts["aborted_tx"] == 2


def test_isotp_stmin_encoding() -> None:
    assert stmin_s(0) == 0.0 and stmin_s(0x7F) == pytest.approx(0.127)
    assert stmin_s(0xF1) == pytest.approx(1e-4) and stmin_s(0xF9) == pytest.approx(9e-4)
    assert stmin_s(0x80) == pytest.approx(0.127) and stmin_s(0xFA) == pytest.approx(0.127)


def test_isotp_buffer_bounds_are_checked() -> None:
    for bad in (7, 4096, 0):
        with pytest.raises(ValueError, match="max_message"):
            IsoTpEndpoint(max_message=bad)
    ep = IsoTpEndpoint(max_message=64)
    for size in (0, 65):  # nothing to send, or more than the peer's buffer may take
        with pytest.raises(ValueError, match=r"must be 1\.\.64"):
            ep.send(bytes(size), 0.0)
    assert not ep.sending and ep.due(0.0) == [] and ep.counts["sent"] == 0


def test_isotp_frames_that_are_not_iso_tp_leave_a_reception_intact() -> None:
    """An empty frame, a reserved PCI type (4..F) and a first frame cut short are ignored:
    no flow control, and the reception in progress still completes."""
    message = bytes(range(20))
    frames = _segments(message)
    ep = IsoTpEndpoint()
    ep.feed(frames[0], 0.0)
    assert ep.due(0.0) == [bytes.fromhex("300000cccccccccc")]
    for junk in (b"", bytes.fromhex("40cccccccccccccc"), bytes.fromhex("f1020304"),
                 bytes.fromhex("101400010203")):  # a FF of 6 bytes: no 6 data bytes
        assert ep.feed(junk, 0.1) is None
        assert ep.receiving and ep.due(0.1) == []
    assert ep.counts["ignored"] == 4
    assert ep.feed(frames[1], 0.2) is None and ep.feed(frames[2], 0.2) == message
    assert ep.counts["aborted_rx"] == 0


def test_isotp_first_frame_that_would_fit_a_single_frame_is_ignored() -> None:
    ep = IsoTpEndpoint()
    assert ep.feed(bytes.fromhex("1007010203040506"), 0.0) is None  # FF_DL 7 < 8
    assert not ep.receiving and ep.due(0.0) == [] and ep.counts["ignored"] == 1
    assert ep.feed(bytes.fromhex("2107cccccccccccc"), 0.0) is None  # its CF: no reception
    assert ep.counts["ignored"] == 2 and ep.counts["received"] == 0


def test_isotp_single_frame_during_a_reception_aborts_it() -> None:
    frames = _segments(bytes(range(30)))
    ep = IsoTpEndpoint()
    ep.feed(frames[0], 0.0)
    ep.feed(frames[1], 0.0)
    assert ep.feed(bytes.fromhex("023e00cccccccccc"), 0.1) == b"\x3e\x00"  # the SF wins
    assert not ep.receiving and ep.counts["aborted_rx"] == 1
    assert ep.feed(frames[2], 0.1) is None and ep.counts["received"] == 1  # rest ignored


def test_isotp_reset_drops_reception_transmission_and_queue() -> None:
    ep = IsoTpEndpoint()
    ep.send(bytes(30), 0.0)  # first frame queued, waiting for a flow control
    ep.feed(_segments(bytes(30))[0], 0.0)  # reception open, its flow control queued
    assert ep.receiving and ep.sending and ep.next_release_s == 0.0
    ep.reset()
    assert not ep.receiving and not ep.sending and ep.next_release_s is None
    assert ep.due(5.0) == []
    ep.feed(bytes.fromhex("300000cccccccccc"), 0.1)  # a flow control for the dropped message
    assert ep.due(5.0) == [] and ep.counts["ignored"] == 1
    ep.poll(10.0)  # no timeout left running either
    assert ep.counts["aborted_rx"] == 0 and ep.counts["aborted_tx"] == 0


def test_isotp_a_newer_answer_abandons_the_transmission_in_progress() -> None:
    ep = IsoTpEndpoint()
    ep.send(bytes(range(30)), 0.0)
    assert ep.due(0.0)[0][:2] == b"\x10\x1e"  # first frame out, waiting for flow control
    ep.send(b"\x7e\x00", 0.1)
    assert ep.counts["aborted_tx"] == 1
    assert ep.due(0.1) == [bytes.fromhex("027e00cccccccccc")]
    ep.feed(bytes.fromhex("300000cccccccccc"), 0.2)  # late flow control for the old message
    assert ep.due(1.0) == [] and not ep.sending and ep.counts["ignored"] == 1
    ep.send(b"\x01", 2.0)  # a queued frame not yet sent is replaced too
    ep.send(b"\x02", 2.0)
    assert ep.due(2.0) == [bytes.fromhex("0102cccccccccccc")] and ep.counts["aborted_tx"] == 2


def test_isotp_flow_control_wait_and_unexpected_flow_control() -> None:
    ep = IsoTpEndpoint()
    ep.feed(bytes.fromhex("300000cccccccccc"), 0.0)  # nothing sent: not expected
    assert ep.counts["ignored"] == 1 and ep.due(0.0) == []
    ep.send(bytes(range(20)), 0.0)
    ep.due(0.0)
    ep.feed(bytes.fromhex("30cc"), 0.5)  # too short to be a flow control: ignored
    assert ep.counts["ignored"] == 2 and ep.sending and ep.due(0.5) == []
    ep.feed(bytes.fromhex("310000cccccccccc"), 0.9)  # WAIT: N_Bs runs again from 0.9 s
    ep.poll(1.8)
    assert ep.sending and ep.counts["aborted_tx"] == 0  # 1.8 s after the FF, 0.9 s after WAIT
    ep.feed(bytes.fromhex("310000cccccccccc"), 1.8)
    ep.poll(2.9)  # 1.1 s after the last WAIT: abort
    assert not ep.sending and ep.counts["aborted_tx"] == 1
    ep.send(bytes(range(20)), 3.0)
    ep.due(3.0)
    ep.feed(bytes.fromhex("310000cccccccccc"), 3.5)
    ep.feed(bytes.fromhex("300000cccccccccc"), 4.2)  # CTS after a WAIT releases the CFs
    assert [f[0] for f in ep.due(4.2)] == [0x21, 0x22] and not ep.sending
    assert ep.counts["sent"] == 1


def test_coding_config_may_be_null_or_a_path() -> None:
    """On a bench (a production coding names packaged configurations only)."""
    for config in (None, "configs/100hz.toml"):
        server = _server(bench=True)
        data = b"\x2e\xfd\x10" + json.dumps({"config": config}).encode()
        assert _parsed(server.handle(data, moving=False).response).positive
        assert server.next_coding()["config"] == config


def test_isotp_against_can_isotp_both_ways() -> None:
    """can-isotp's transport layer (logic only, driven by hand) as the tester: a 600-byte
    request to our endpoint and a long response back, through each other's flow control."""
    import isotp

    to_server: list[bytes] = []
    to_tester: list[Any] = []
    address = isotp.Address(isotp.AddressingMode.Normal_11bits, txid=0x7E0, rxid=0x7E8)
    tester = isotp.TransportLayerLogic(
        rxfn=lambda timeout: to_tester.pop(0) if to_tester else None,
        txfn=lambda msg: to_server.append(bytes(msg.data)), address=address,
        params={"tx_padding": 0xCC, "tx_data_min_length": 8, "blocksize": 3, "stmin": 0})
    ep = IsoTpEndpoint()
    request = bytes((i * 7) & 0xFF for i in range(600))
    tester.send(request)
    now = 0.0
    got = None
    for _ in range(400):
        tester.process()
        while to_server:
            frame = to_server.pop(0)
            assert len(frame) == 8
            got = ep.feed(frame, now) or got
        to_tester.extend(isotp.CanMessage(arbitration_id=0x7E8, data=f)
                         for f in ep.due(now))
        if got is not None:
            break
        now += 0.001
    assert got == request
    answer = bytes((255 - i) & 0xFF for i in range(300))
    ep.send(answer, now)
    received = None
    for _ in range(400):
        to_tester.extend(isotp.CanMessage(arbitration_id=0x7E8, data=f) for f in ep.due(now))
        tester.process()
        while to_server:
            ep.feed(to_server.pop(0), now)
        if tester.available():
            received = tester.recv()
            break
        now += 0.001
    assert received == answer


def test_coding_json_compact_and_sorted() -> None:
    assert coding_json({"b": 1, "a": [1, 2]}) == b'{"a":[1,2],"b":1}'


def test_second_controller_starts_as_the_first() -> None:
    """A soft reset builds a second controller in the same process: it must run bit for bit
    as the first one did from its creation (no static state in the C core, no shared
    warm start)."""
    from controller.core.interfaces import ControllerInputs
    from controller.registry import make_controller

    def run(name: str) -> list[tuple]:
        ctrl = make_controller(name, None)
        inp = ControllerInputs()
        out = []
        for k in range(120):
            inp.swa_rad, inp.accel_pedal = 0.3 * math.sin(0.05 * k), 0.2
            inp.vx, inp.vy = 18.0 + 0.01 * k, 0.05 * math.sin(0.1 * k)
            inp.yaw_rate, inp.ay, inp.ax = 0.2 * math.sin(0.05 * k), 3 * math.sin(0.05 * k), 0.1
            inp.wheel_speeds[:] = inp.vx / 0.358
            o = ctrl.step(inp) if k % 5 == 0 else ctrl.allocate_only(inp)
            out.append((o.torques.tobytes(), o.delta_m, o.qp_iterations, o.yaw_rate_ref))
        return out

    for name in ("nmpc-rhonn", "nmpc-mf", "lmpc", "passive"):
        first = run(name)
        assert run(name) == first, name


def test_hard_reset_applies_the_coding_to_the_arguments() -> None:
    from controller.runtime.process import apply_coding

    argv = ["--bus", "local:x", "--controller", "lmpc", "--fault", "loss:5%", "--timing",
            "t.csv", "--config=100hz", "--fault-seed", "4", "--bench", "--fault=crc:1%"]
    coding = {"controller": "nmpc-mf", "config": None, "faults": ["burst:200ms@1s"],
              "fault_seed": 9}
    assert apply_coding(argv, coding) == [
        "--bus", "local:x", "--timing", "t.csv", "--bench", "--controller", "nmpc-mf",
        "--fault=burst:200ms@1s", "--fault-seed", "9"]
    same = apply_coding(argv, {"controller": "lmpc", "config": "100hz",
                               "faults": ["loss:5%", "crc:1%"], "fault_seed": 4})
    assert same[-8:] == ["--controller", "lmpc", "--config", "100hz", "--fault=loss:5%",
                         "--fault=crc:1%", "--fault-seed", "4"]


# ---------------------------------------------------------------------- sessions, security
WRITE = b"\x2e\xfd\x10" + json.dumps({"controller": "passive"}).encode()


def _seed(server: UdsServer, now_s: float = 0.0) -> bytes:
    reply = server.handle(b"\x27\x01", moving=False, now_s=now_s)
    return _parsed(reply.response).data[1:]


def test_a_keyless_tester_cannot_write_the_coding_or_reset() -> None:
    """Default session: 0x7F serviceNotSupportedInActiveSession; extended but locked: 0x33
    securityAccessDenied; nothing pending, no reset action; each refusal counted."""
    server = _server(unlocked=False)
    for request in (WRITE, b"\x11\x01", b"\x11\x03"):
        reply = server.handle(request, moving=False)
        _nrc(reply.response, request[0], 0x7F)
        assert reply.action is Action.NONE
    session = server.handle(b"\x10\x03", moving=False)
    response = _parsed(session.response)   # udsoncan parses P2 / P2* of ISO 14229-1:2013
    services.DiagnosticSessionControl.interpret_response(response, standard_version=2013)
    assert response.positive and response.service_data.session_echo == 0x03
    assert response.service_data.p2_server_max == 0.05
    assert response.service_data.p2_star_server_max == 5.0
    for request in (WRITE, b"\x11\x01"):
        _nrc(server.handle(request, moving=False).response, request[0], 0x33)
    assert server.pending is None
    assert server.refused == {"2E/7F": 1, "11/7F": 2, "2E/33": 1, "11/33": 1}


def test_security_access_grants_with_the_key_and_only_with_it() -> None:
    server = _server(unlocked=False)
    _nrc(server.handle(b"\x27\x01", moving=False).response, 0x27, 0x7F)  # default session
    server.handle(b"\x10\x03", moving=False)
    _nrc(server.handle(b"\x27\x02" + bytes(16), moving=False).response, 0x27, 0x24)  # no seed
    seed = _seed(server)
    assert len(seed) == 16 and seed != bytes(16)
    wrong = _key(seed, secret=bytes(32))                       # another secret's key
    _nrc(server.handle(b"\x27\x02" + wrong, moving=False).response, 0x27, 0x35)
    _nrc(server.handle(b"\x27\x02" + _key(seed), moving=False).response, 0x27, 0x24)  # used
    seed = _seed(server)
    assert _parsed(server.handle(b"\x27\x02" + _key(seed), moving=False).response).positive
    assert _seed(server) == bytes(16)                          # unlocked: a zero seed
    assert _parsed(server.handle(WRITE, moving=False).response).positive
    assert server.pending == {**CODING, "controller": "passive"}


def test_a_replayed_key_is_refused() -> None:
    """A key recorded from an earlier exchange answers that seed only: the server's next
    seed differs, so the replay is an invalid key."""
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False)
    seed = _seed(server)
    recorded = b"\x27\x02" + _key(seed)
    assert _parsed(server.handle(recorded, moving=False).response).positive
    server.handle(b"\x10\x01", moving=False)                   # session change: locked
    _nrc(server.handle(b"\x11\x01", moving=False).response, 0x11, 0x7F)
    server.handle(b"\x10\x03", moving=False)
    assert _seed(server) != seed
    _nrc(server.handle(recorded, moving=False).response, 0x27, 0x35)
    _nrc(server.handle(b"\x11\x01", moving=False).response, 0x11, 0x33)


def test_three_wrong_keys_lock_security_access_for_ten_seconds() -> None:
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False, now_s=100.0)
    for attempt, nrc in ((1, 0x35), (2, 0x35), (3, 0x36)):
        _seed(server, now_s=100.0 + attempt)
        reply = server.handle(b"\x27\x02" + bytes(16), moving=False, now_s=100.0 + attempt)
        _nrc(reply.response, 0x27, nrc)
    server.handle(b"\x10\x03", moving=False, now_s=112.9)   # S3 ended the session: again
    _nrc(server.handle(b"\x27\x01", moving=False, now_s=112.9).response, 0x27, 0x37)
    seed = _seed(server, now_s=113.1)                           # 10 s after the third key
    assert _parsed(server.handle(b"\x27\x02" + _key(seed), moving=False,
                                 now_s=113.2).response).positive


def test_the_extended_session_ends_after_s3_without_a_request() -> None:
    server = _server(unlocked=False)
    _unlock(server, now_s=50.0)
    assert server.handle(b"\x3e\x80", moving=False, now_s=54.9).response is None  # keeps it
    assert server.session == 0x03 and server.unlocked
    _nrc(server.handle(WRITE, moving=False, now_s=60.0).response, 0x2E, 0x7F)   # 5.1 s later
    assert server.session == 0x01 and not server.unlocked


def test_a_soft_reset_ends_the_session() -> None:
    server = _server()
    assert server.handle(b"\x11\x03", moving=False).action is Action.SOFT_RESET
    server.soft_reset_done()
    _nrc(server.handle(b"\x11\x03", moving=False).response, 0x11, 0x7F)


def test_the_diagnostic_secret_comes_from_env_file_or_the_public_one(tmp_path) -> None:
    from controller.runtime.uds import PUBLIC_TEST_SECRET, UdsSecretError, load_uds_secret
    assert load_uds_secret("env", {}) == (PUBLIC_TEST_SECRET, "public test secret")
    assert load_uds_secret("env", {"RHONN_UDS_SECRET": SECRET.hex()}) == (
        SECRET, "$RHONN_UDS_SECRET")
    f = tmp_path / "secret"
    f.write_text(SECRET.hex() + "\n")
    assert load_uds_secret(str(f)) == (SECRET, "file")
    f.write_text("abcd")
    with pytest.raises(UdsSecretError, match="16 bytes"):
        load_uds_secret(str(f))
    with pytest.raises(UdsSecretError, match="not hex"):
        load_uds_secret("env", {"RHONN_UDS_SECRET": "xyz"})
    assert len(set(PUBLIC_TEST_SECRET)) > 8   # not a trivial pattern


def test_a_production_coding_is_a_short_allow_list() -> None:
    """Without --bench a coding write may name the controller and a packaged configuration
    only: faults, a fault seed or a configuration file path get 0x31; a bench takes them."""
    for update in ({"faults": ["loss:5%"]}, {"fault_seed": 3}, {"config": "/tmp/x.toml"},
                   {"config": "mine.toml"}, {"controller": "lmpc", "faults": []}):
        request = b"\x2e\xfd\x10" + json.dumps(update).encode()
        _nrc(_server().handle(request, moving=False).response, 0x2E, 0x31)
        assert _parsed(_server(bench=True).handle(request, moving=False).response).positive
    for update in ({"controller": "passive"}, {"config": "100hz"}, {"config": None}):
        request = b"\x2e\xfd\x10" + json.dumps(update).encode()
        assert _parsed(_server().handle(request, moving=False).response).positive


def test_a_coding_naming_an_unreadable_file_is_refused_not_a_crash() -> None:
    """A bench coding whose config is a file that cannot be read (/proc/self/mem: EIO) is a
    coding that does not check (0x31), not an exception in the controller."""
    from can_db.codec import Codec
    from controller.runtime.process import _coding_problem

    problem = _coding_problem({"controller": "lmpc", "config": "/proc/self/mem"}, Codec())
    assert problem is not None and "Input/output error" in problem


class _Frame:
    def __init__(self, **values: float) -> None:
        self.values = values


class _Node:
    """A node whose monitor holds the given last accepted frames."""

    def __init__(self, est: dict | None, wheels: dict | None) -> None:
        frames = {"VEHICLE_EST": None if est is None else _Frame(**est),
                  "WHEEL_SPEEDS": None if wheels is None else _Frame(**wheels)}
        self.monitor = type("M", (), {"latest": staticmethod(frames.get)})()


@pytest.mark.parametrize("est, wheels, moving", [
    (None, None, True),                                      # nothing yet: fails closed
    ({"VX_EST": 0.0}, None, True),                           # no wheel speeds yet
    (None, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, True),
    ({"VX_EST": 0.0}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, False),
    ({"VX_EST": 0.2}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, True),
    ({"VX_EST": -0.2}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, True),
    ({"VX_EST": 0.1}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, False),
    ({"VX_EST": 0.0}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.5}, True),
    ({"VX_EST": 0.0}, {"WS_FL": -0.5, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, True),
    ({"VX_EST": 0.0}, {"WS_FL": 0.3, "WS_FR": 0.3, "WS_RL": 0.3, "WS_RR": 0.3}, False),
    # the km/h conversion and the limit's edge: 0.13 m/s is 0.468 km/h, 0.15 m/s 0.54 km/h;
    # 0.5/3.6 m/s is exactly 0.5 km/h (not above it); 0.45 rad/s at 0.3 m is 0.486 km/h
    ({"VX_EST": 0.13}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, False),
    ({"VX_EST": 0.15}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, True),
    ({"VX_EST": 0.5 / 3.6}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.0, "WS_RR": 0.0}, False),
    ({"VX_EST": 0.0}, {"WS_FL": 0.0, "WS_FR": 0.45, "WS_RL": 0.0, "WS_RR": 0.0}, False),
    ({"VX_EST": 0.0}, {"WS_FL": 0.0, "WS_FR": 0.0, "WS_RL": 0.5 / 3.6 / 0.3, "WS_RR": 0.0},
     False),
])
def test_the_moving_decision_from_its_frames(est: dict | None, wheels: dict | None,
                                             moving: bool) -> None:
    """0.5 km/h: VX_EST 0.2 m/s is 0.72 km/h (moving), 0.1 m/s 0.36 km/h (not); one wheel of
    0.5 rad/s at r = 0.3 m is 0.54 km/h (moving, whichever wheel), 0.3 rad/s 0.32 km/h."""
    from can_db.codec import Codec
    from controller.runtime.process import DiagLink

    link = DiagLink(Codec(), _server(), wheel_radius_m=0.3)
    assert link.moving(_Node(est, wheels)) is moving  # type: ignore[arg-type]


# ---------------------------------------------------------------------- edges of the access rules
def test_the_session_is_kept_exactly_s3_after_the_last_request() -> None:
    """S3 ends the session when more than 5 s passed: a request 5.0 s after the last one
    still finds it (and unlocked)."""
    server = _server(unlocked=False)
    _unlock(server, now_s=50.0)
    assert _parsed(server.handle(WRITE, moving=False, now_s=55.0).response).positive
    assert server.session == 0x03 and server.unlocked


@pytest.mark.parametrize(("later_s", "positive"), [(5.0, True), (5.5, False)])
def test_a_request_without_a_time_is_at_time_zero(later_s: float, positive: bool) -> None:
    """``now_s`` defaults to 0: a server unlocked by requests without a time keeps its
    session for a request at 5.0 s, not at 5.5 s (S3)."""
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False)
    seed = server.handle(b"\x27\x01", moving=False).response
    assert seed is not None
    server.handle(b"\x27\x02" + _key(seed[2:]), moving=False)
    assert server.unlocked
    reply = server.handle(WRITE, moving=False, now_s=later_s)
    if positive:
        assert _parsed(reply.response).positive
    else:
        _nrc(reply.response, 0x2E, 0x7F)


def test_the_lock_out_ends_exactly_ten_seconds_after_the_third_key_and_counts_anew() -> None:
    """A seed is refused before the lock-out's end and granted at it; the attempt count
    started again at the lock-out: three more wrong keys lock again (not four)."""
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False, now_s=100.0)
    for t in (101.0, 102.0, 103.0):
        _seed(server, now_s=t)
        server.handle(b"\x27\x02" + bytes(16), moving=False, now_s=t)
    for t in (104.0, 108.0, 112.0):  # tester present: the session stays
        server.handle(b"\x3e\x80", moving=False, now_s=t)
    _nrc(server.handle(b"\x27\x01", moving=False, now_s=112.999).response, 0x27, 0x37)
    for t, nrc in ((113.0, 0x35), (113.5, 0x35), (114.0, 0x36)):  # 103 + 10 s: granted
        _seed(server, now_s=t)
        _nrc(server.handle(b"\x27\x02" + bytes(16), moving=False, now_s=t).response, 0x27, nrc)


def test_a_seed_response_is_67_01_and_sixteen_bytes() -> None:
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False)
    response = server.handle(b"\x27\x01", moving=False).response
    assert response is not None and response[:2] == b"\x67\x01" and len(response) == 18


def test_a_one_byte_coding_write_is_checked_for_its_content_not_its_length() -> None:
    """``2E FD 10`` + one byte has the minimum length: its content is what is refused."""
    _nrc(_server().handle(b"\x2e\xfd\x10\x31", moving=False).response, 0x2E, 0x31)
    _nrc(_server().handle(b"\x2e\xfd\x10", moving=False).response, 0x2E, 0x13)


@pytest.mark.parametrize("config", ["../configs/mine", "configs\\mine", "mine.toml"])
def test_a_production_coding_names_no_configuration_file(config: str) -> None:
    """Either separator (or the .toml suffix) makes the name a path: refused without
    --bench."""
    request = b"\x2e\xfd\x10" + json.dumps({"config": config}).encode()
    _nrc(_server().handle(request, moving=False).response, 0x2E, 0x31)


def test_a_server_is_a_production_one_unless_told_it_is_a_bench() -> None:
    """Without ``bench``: resets and coding writes refused while moving, faults refused."""
    server = UdsServer(CODING, check_coding=_check, secret=SECRET)
    _unlock(server)
    _nrc(server.handle(b"\x11\x01", moving=True).response, 0x11, 0x22)
    _nrc(server.handle(b'\x2e\xfd\x10{"faults": []}', moving=False).response, 0x2E, 0x31)


def test_requests_and_refusals_are_counted_from_zero() -> None:
    server = UdsServer(CODING, secret=SECRET)
    server.handle(b"\x3e\x00", moving=False)
    server.handle(b"\x11\x01", moving=False)
    server.handle(b"\x27\x01", moving=False)
    assert server.counts == {"requests": 3, "negative": 2}


def test_a_secret_needs_sixteen_bytes() -> None:
    with pytest.raises(ValueError, match="16 bytes"):
        UdsServer(CODING, secret=bytes(15))
    assert UdsServer(CODING, secret=bytes(range(16))).session == 0x01


def test_a_security_access_request_without_a_sub_function_is_a_length_error() -> None:
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False)
    _nrc(server.handle(b"\x27", moving=False).response, 0x27, 0x13)


def test_positive_responses_byte_for_byte() -> None:
    """Each positive response is its service + 0x40 and echoes what ISO 14229-1 says: the
    write its DID, the key its sub-function, the seed of an unlocked level is zeros."""
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False)
    seed = _seed(server)
    assert server.handle(b"\x27\x02" + _key(seed), moving=False).response == b"\x67\x02"
    assert server.handle(b"\x27\x01", moving=False).response == b"\x67\x01" + bytes(16)
    assert server.handle(WRITE, moving=False).response == b"\x6e\xfd\x10"


def test_a_suppressed_key_answers_nothing_and_unlocks() -> None:
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False)
    seed = _seed(server)
    assert server.handle(b"\x27\x82" + _key(seed), moving=False).response is None
    assert server.unlocked


def test_a_granted_key_clears_the_count_of_wrong_ones() -> None:
    """Two wrong keys, then the right one: the next two wrong keys (after the session
    locked again) are invalid keys, only the third locks out."""
    server = _server(unlocked=False)
    server.handle(b"\x10\x03", moving=False)
    for _ in range(2):
        _seed(server)
        _nrc(server.handle(b"\x27\x02" + bytes(16), moving=False).response, 0x27, 0x35)
    seed = _seed(server)
    assert server.handle(b"\x27\x02" + _key(seed), moving=False).response == b"\x67\x02"
    server.handle(b"\x10\x03", moving=False)                 # a session change: locked
    for nrc in (0x35, 0x35, 0x36):
        _seed(server)
        _nrc(server.handle(b"\x27\x02" + bytes(16), moving=False).response, 0x27, nrc)


def test_a_server_started_without_a_boot_count_is_the_first_boot() -> None:
    server = UdsServer(CODING, secret=SECRET)
    assert server.handle(b"\x22\xfd\x11", moving=False).response == b"\x62\xfd\x11\x00\x01"


def test_the_servers_options_are_keyword_only() -> None:
    """A positional boot count, check or bench flag is refused: ``bench`` must be said."""
    with pytest.raises(TypeError):
        UdsServer(CODING, 3)  # type: ignore[misc]
