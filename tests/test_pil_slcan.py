"""The processor-in-the-loop transport: SLCAN over UART0 of the MPS2 AN386
(controller/native/mcu/pil/, harness/run/pil_link.py, harness/bench/mcu/pil.py).

Unit: the SLCAN codec (slcan.c) compiled for the host into a cffi API-mode module declared by
slcan.h itself (controller/native/module_ffi.py: no layout or constant written here): good,
bad, overlong and partial lines, the answers ('\\r', 'z\\r', '\\a', ...), resynchronisation, and
the frame format against python-can's own slcan line format.

End to end, across processes (QEMU running the echo firmware, python-can's slcan interface
on QEMU's loopback socket, a local bus hub): 100 seeded frames echoed and checked, malformed
lines answered with '\\a' and the link in step afterwards, the bridge to the project's bus,
a killed QEMU reported as such, no QEMU left behind when its parent dies, and the link's
instructions per frame from the QEMU plugin. Skipped only when the cross toolchain, newlib or
qemu-system-arm is absent (the detection of tests/test_mcu.py).
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import can
import psutil
import pytest

from can_db.transport.bus import open_bus
from can_db.transport.hub import LocalHub
from controller.native.build_tools import NATIVE_DIR
from controller.native.module_ffi import build_module
from harness.bench import mcu
from harness.bench.mcu.pil import (
    build_pil_firmware,
    echo_answer,
    frame_instructions,
    measure_echo,
    random_frames,
    slcan_line,
)
from harness.run.pil_link import PilBridge, PilLink, PilLinkError

REPO = Path(__file__).resolve().parents[1]
PIL_DIR = NATIVE_DIR / "mcu" / "pil"
MISSING = mcu.missing_tools()
needs_toolchain = pytest.mark.skipif(MISSING is not None, reason=f"MCU toolchain: {MISSING}")

# --- the codec on the host --------------------------------------------------------------


@pytest.fixture(scope="module")
def slcan(tmp_path_factory: pytest.TempPathFactory) -> ModuleType:
    """slcan.c through a cffi API-mode module declared by slcan.h: the compiler fixes every
    field offset, and the SLCAN_* macros and enums are the module's constants."""
    return build_module(
        ["slcan.c"],
        tmp_path_factory.mktemp("slcan"),
        name="slcan_test",
        src_dir=PIL_DIR,
        macro_prefixes=("SLCAN_",),
    )


def frame_data(slcan: ModuleType, frame: Any, n: int | None = None) -> bytes:
    """The first ``n`` (default all) data bytes of an ``slcan_frame_t *``."""
    return bytes(slcan.ffi.unpack(frame.data, len(frame.data) if n is None else n))


class Adapter:
    """The codec fed byte by byte, collecting answers, events and frames."""

    def __init__(self, slcan: ModuleType) -> None:
        self.ffi = slcan.ffi
        self.lib = slcan.lib
        self.s = self.ffi.new("slcan_t *")
        self.lib.slcan_init(self.s)

    def feed(self, data: bytes) -> list[tuple[int, bytes, Any]]:
        """(event, answer, ``slcan_frame_t *`` or None) for each line completed by ``data``."""
        lib = self.lib
        out = []
        reply = self.ffi.new("char[]", lib.SLCAN_OUT_MAX)
        n = self.ffi.new("size_t *")
        for b in data:
            f = self.ffi.new("slcan_frame_t *")
            ev = lib.slcan_feed(self.s, b, f, reply, n)
            assert ev != lib.SLCAN_EV_NONE or n[0] == 0
            if ev != lib.SLCAN_EV_NONE:
                assert n[0] == len(self.ffi.string(reply)) and 0 < n[0] < lib.SLCAN_OUT_MAX
                out.append(
                    (ev, self.ffi.unpack(reply, n[0]), f if ev == lib.SLCAN_EV_FRAME else None)
                )
        return out

    def one(self, line: bytes) -> tuple[int, bytes, Any]:
        res = self.feed(line)
        assert len(res) == 1, res
        return res[0]


def opened(slcan: ModuleType) -> Adapter:
    a = Adapter(slcan)
    assert a.one(b"O\r")[:2] == (slcan.lib.SLCAN_EV_OPEN, b"\r")
    return a


def test_frame_lines_are_parsed_and_answered_z(slcan: ModuleType) -> None:
    lib = slcan.lib
    a = opened(slcan)
    ev, ans, f = a.one(b"t12321122\r")
    assert (ev, ans) == (lib.SLCAN_EV_FRAME, b"z\r")
    assert f is not None and (f.id, f.extended, f.rtr, f.dlc) == (0x123, 0, 0, 2)
    assert frame_data(slcan, f, 2) == b"\x11\x22"
    ev, ans, f = a.one(b"T1fffFFFF8a1b2c3d4e5f60718\r")  # both cases of hex, the longest line
    assert (ev, ans) == (lib.SLCAN_EV_FRAME, b"Z\r")
    assert f is not None and (f.id, f.extended, f.dlc) == (0x1FFFFFFF, 1, 8)
    assert frame_data(slcan, f) == bytes.fromhex("a1b2c3d4e5f60718")
    ev, ans, f = a.one(b"t7FF0\r")
    assert (ev, ans) == (lib.SLCAN_EV_FRAME, b"z\r")
    assert f is not None and (f.id, f.dlc) == (0x7FF, 0)
    ev, ans, f = a.one(b"r1238\r")
    assert (ev, ans) == (lib.SLCAN_EV_FRAME, b"z\r")
    assert f is not None and (f.rtr, f.dlc) == (1, 8)
    ev, ans, f = a.one(b"R000000013\r")
    assert (ev, ans) == (lib.SLCAN_EV_FRAME, b"Z\r") and f is not None
    assert (f.id, f.extended, f.rtr, f.dlc) == (1, 1, 1, 3)
    assert a.s.errors == 0 and a.s.lines == 6


def test_commands_get_the_lawicel_answers(slcan: ModuleType) -> None:
    lib = slcan.lib
    a = Adapter(slcan)
    assert a.one(b"V\r")[1] == b"V1001\r"
    assert a.one(b"N\r")[1] == b"NRH01\r"
    assert a.one(b"S4\r")[:2] == (lib.SLCAN_EV_COMMAND, b"\r") and a.s.bitrate_code == 4
    assert a.one(b"s031C\r")[:2] == (lib.SLCAN_EV_COMMAND, b"\r")
    assert a.one(b"Z0\r")[:2] == (lib.SLCAN_EV_COMMAND, b"\r")
    assert a.one(b"\r")[:2] == (lib.SLCAN_EV_COMMAND, b"\r")  # empty line: a no-op
    assert a.one(b"F\r")[1] == b"F00\r"
    assert a.one(b"O\r")[:2] == (lib.SLCAN_EV_OPEN, b"\r") and a.s.mode == lib.SLCAN_OPEN
    assert lib.slcan_is_open(a.s) == 1
    assert a.one(b"C\r")[:2] == (lib.SLCAN_EV_CLOSE, b"\r") and a.s.mode == lib.SLCAN_CLOSED
    assert lib.slcan_is_open(a.s) == 0
    assert a.one(b"L\r")[:2] == (lib.SLCAN_EV_OPEN, b"\r")
    assert a.s.mode == lib.SLCAN_LISTEN_ONLY
    assert lib.slcan_is_open(a.s) == 1
    assert a.s.errors == 0


def test_python_can_open_sequence_with_a_bitrate_opens_the_channel(slcan: ModuleType) -> None:
    """slcanBus(bitrate=500000) writes C, S6, an empty data-bitrate line, O
    (can/interfaces/slcan.py set_bitrate); only the C of a closed channel is refused."""
    a = Adapter(slcan)
    answers = [ans for _, ans, _ in a.feed(b"C\rS6\r\rO\r")]
    assert answers == [b"\a", b"\r", b"\r", b"\r"]
    assert a.s.mode == slcan.lib.SLCAN_OPEN and a.s.bitrate_code == 6


def test_a_frame_while_the_channel_is_closed_is_refused(slcan: ModuleType) -> None:
    lib = slcan.lib
    line = b"t1230"  # a good frame line
    a = Adapter(slcan)
    assert a.one(line + b"\r")[:2] == (lib.SLCAN_EV_ERROR, b"\a")
    assert a.one(b"L\r")[0] == lib.SLCAN_EV_OPEN
    assert a.one(line + b"\r")[:2] == (lib.SLCAN_EV_ERROR, b"\a")  # listen only: no frames in
    assert a.s.errors == 2


@pytest.mark.parametrize(
    "line",
    [
        b"t8000",
        b"t12",
        b"t123",
        b"t1239" + b"00" * 9,
        b"t1232001122",
        b"t1232001",
        b"t12X0",
        b"t1231GG",
        b"T2000000000",
        b"T1234567",
        b"r1239",
        b"r12310",
        b"R1234567",
        b"x1230",
        b"O",
        b"S6",
        b"s031C",
        b"Z0",
        b"Z1",
        b"V1",
        b"F0",
        b"C1",
        b"t12 0",
        b"t123\x000",
        b"t1\t230",
        b"?",
    ],
)
def test_bad_lines_get_bel_and_change_nothing(slcan: ModuleType, line: bytes) -> None:
    """Malformed frames, out-of-range identifiers and DLCs, wrong lengths, unknown commands,
    control bytes, and commands in the wrong channel state (O, S, s, Z0 while open)."""
    lib = slcan.lib
    a = opened(slcan)
    before = (a.s.mode, a.s.bitrate_code)
    assert a.one(line + b"\r")[:2] == (lib.SLCAN_EV_ERROR, b"\a")
    assert (a.s.mode, a.s.bitrate_code) == before and a.s.errors == 1
    # the next good line is understood: the codec is in step
    ev, ans, f = a.one(b"t0011FF\r")
    assert (ev, ans) == (lib.SLCAN_EV_FRAME, b"z\r") and f is not None and f.data[0] == 0xFF


def test_close_while_closed_and_bad_bitrate_are_refused(slcan: ModuleType) -> None:
    lib = slcan.lib
    a = Adapter(slcan)
    assert a.one(b"C\r")[:2] == (lib.SLCAN_EV_ERROR, b"\a")
    assert a.one(b"S9\r")[:2] == (lib.SLCAN_EV_ERROR, b"\a")
    assert a.s.bitrate_code == 6


def test_an_overlong_line_is_dropped_whole_with_one_bel_then_resync(slcan: ModuleType) -> None:
    lib = slcan.lib
    line_max = lib.SLCAN_LINE_MAX
    assert len(slcan.ffi.new("slcan_t *").line) == line_max  # the buffer the codec fills
    a = opened(slcan)
    longest = b"T1FFFFFFF8" + b"AB" * 8
    assert len(longest) == line_max
    assert a.one(longest + b"\r")[0] == lib.SLCAN_EV_FRAME
    for extra in (1, 2, 300):
        junk = b"t" + b"1" * (line_max - 1 + extra)
        assert a.feed(junk) == []  # nothing answered before the '\r'
        assert a.s.overlong == 1
        assert a.one(b"\r")[:2] == (lib.SLCAN_EV_ERROR, b"\a")  # exactly one answer
        ev, ans, f = a.one(b"t1232BEEF\r")
        assert (ev, ans) == (lib.SLCAN_EV_FRAME, b"z\r") and f is not None and f.id == 0x123
    assert a.s.overlong_lines == 3 and a.s.errors == 3
    assert a.one(b"F\r")[1] == b"F08\r"  # the lost-line flag, cleared when read
    assert a.one(b"F\r")[1] == b"F00\r"


def test_partial_lines_wait_for_their_end_and_crlf_is_accepted(slcan: ModuleType) -> None:
    lib = slcan.lib
    a = opened(slcan)
    stream = b"t1232AABB\r\nt4560\r\n"
    events = []
    for b in stream:  # one byte at a time: nothing before each '\r'
        events += a.feed(bytes([b]))
        if bytes([b]) != b"\r":
            assert len(events) in (0, 1, 2)
    assert [(e[0], e[1]) for e in events] == [
        (lib.SLCAN_EV_FRAME, b"z\r"),
        (lib.SLCAN_EV_FRAME, b"z\r"),
    ]
    assert [e[2].id for e in events if e[2] is not None] == [0x123, 0x456]
    assert a.s.errors == 0
    # a '\n' that starts a line is no '\r\n'
    assert a.one(b"\n\r")[:2] == (lib.SLCAN_EV_ERROR, b"\a")


def test_format_matches_python_can_and_round_trips(slcan: ModuleType) -> None:
    ffi, lib = slcan.ffi, slcan.lib
    rng = random.Random(7)
    a = opened(slcan)
    out = ffi.new("char[]", lib.SLCAN_OUT_MAX)
    for k in range(300):
        ext = k % 3 == 0
        rtr = k % 7 == 0
        dlc = rng.randrange(9)
        ident = rng.randrange(1 << 29) if ext else rng.randrange(1 << 11)
        data = bytes(rng.randrange(256) for _ in range(0 if rtr else dlc))
        f = ffi.new(
            "slcan_frame_t *",
            {"id": ident, "extended": int(ext), "rtr": int(rtr), "dlc": dlc, "data": list(data)},
        )
        n = lib.slcan_format(f, out)
        # python-can's slcan interface writes exactly this (can/interfaces/slcan.py send)
        msg = can.Message(
            arbitration_id=ident, is_extended_id=ext, is_remote_frame=rtr, dlc=dlc, data=data
        )
        if rtr:
            want = f"R{ident:08X}{dlc:d}" if ext else f"r{ident:03X}{dlc:d}"
        else:
            want = (
                f"T{ident:08X}{dlc:d}" if ext else f"t{ident:03X}{dlc:d}"
            ) + msg.data.hex().upper()
        assert ffi.string(out) == want.encode() + b"\r" and n == len(want) + 1
        ev, _, back = a.one(ffi.string(out))
        assert ev == lib.SLCAN_EV_FRAME and back is not None
        assert (back.id, back.extended, back.rtr, back.dlc) == (ident, int(ext), int(rtr), dlc)
        assert frame_data(slcan, back, len(data)) == data


@pytest.mark.parametrize(
    ("ident", "ext", "dlc"), [(0x800, 0, 0), (0x20000000, 1, 0), (0x123, 0, 9)]
)
def test_format_refuses_invalid_frames(slcan: ModuleType, ident: int, ext: int, dlc: int) -> None:
    ffi, lib = slcan.ffi, slcan.lib
    out = ffi.new("char[]", b"x" * (lib.SLCAN_OUT_MAX - 1))
    f = ffi.new("slcan_frame_t *", {"id": ident, "extended": ext, "dlc": dlc})
    assert lib.slcan_format(f, out) == 0 and ffi.string(out) == b""


def test_frame_instructions_attributes_marker_pairs_to_frames() -> None:
    # baseline pairs of 5, then: O\r (2 bytes), one frame "t1230\r" (6 bytes + its tx pair)
    marks = [0, 5, 10, 15, 20, 25, 30, 35]
    costs = [11, 12, 20, 21, 22, 23, 24, 25, 100]  # O, \r, the 6 bytes, the tx pair
    t = 100
    for c in costs:
        marks += [t, t + 5 + c]
        t += 1000
    assert frame_instructions(marks, [b"O\r", b"t1230\r"]) == [sum(costs[2:])]
    with pytest.raises(mcu.case.McuError, match="baseline"):
        frame_instructions([0, 5, 10, 16, 20, 25, 30, 35], [])
    with pytest.raises(mcu.case.McuError, match="more"):
        frame_instructions(marks, [b"O\r", b"t1230\r", b"t1230\r"])


# --- end to end on QEMU -----------------------------------------------------------------


@pytest.fixture(scope="module")
def echo_elf(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if MISSING is not None:
        pytest.skip(f"MCU toolchain: {MISSING}")
    return build_pil_firmware(tmp_path_factory.mktemp("pil-echo"), insn_marks=False)


def _check_answer(msg: can.Message, got: can.Message | None) -> None:
    want = echo_answer(msg)
    assert got is not None, f"no answer to {msg}"
    assert (got.arbitration_id, got.is_extended_id, got.dlc, bytes(got.data)) == (
        want.arbitration_id,
        want.is_extended_id,
        want.dlc,
        bytes(want.data),
    )


@needs_toolchain
@pytest.mark.timeout(120)
def test_echo_firmware_answers_100_frames_over_python_can_slcan(
    echo_elf: Path, tmp_path: Path
) -> None:
    frames = random_frames(100, seed=3)
    assert {f.dlc for f in frames} == set(range(9))
    with PilLink(echo_elf, tmp_path) as link:
        assert link.version == (10, 1)  # the firmware's V answer
        assert link.port is not None and 0 < link.port < 65536
        for msg in frames[:50]:  # one by one
            link.send(msg)
            _check_answer(msg, link.recv(10.0))
        for msg in frames[50:]:  # a burst, then the answers
            link.send(msg)
        for msg in frames[50:]:
            _check_answer(msg, link.recv(10.0))
        assert link.recv(0.2) is None  # nothing more than asked
        ext = can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, data=b"\xff")
        link.send(ext)
        got = link.recv(10.0)
        assert got is not None and got.is_extended_id and got.arbitration_id == 0
        assert bytes(got.data) == b"\x00"
        pid = link.qemu_pid
    assert link.qemu_returncode == 0  # stopped by SIGTERM, cleanly
    assert pid is not None and not psutil.pid_exists(pid)
    assert "PIL echo ready" in link.guest_log.read_text()


@needs_toolchain
@pytest.mark.timeout(120)
def test_malformed_lines_get_bel_and_the_link_resyncs(echo_elf: Path, tmp_path: Path) -> None:
    with PilLink(echo_elf, tmp_path) as link:
        assert link.raw_line(b"tXYZ\r") == b"\a"
        assert link.raw_line(b"t12391122334455667788\r") == b"\a"  # DLC 9
        assert link.raw_line(b"t" + b"7" * 200 + b"\r") == b"\a"  # overlong: one answer
        assert link.raw_line(b"F\r") == b"F08\r"  # the lost-line flag
        assert link.raw_line(b"O\r") == b"\a"  # already open
        msg = can.Message(arbitration_id=0x321, is_extended_id=False, data=b"\x10\x20")
        link.send(msg)  # in step again
        _check_answer(msg, link.recv(10.0))
        assert link.raw_line(b"C\r") == b"\r"
        link.send(msg)  # closed: refused
        assert link.recv(0.5) is None
        assert link.raw_line(b"O\r") == b"\r"
        link.send(msg)
        _check_answer(msg, link.recv(10.0))


@needs_toolchain
@pytest.mark.timeout(120)
def test_a_killed_qemu_is_a_clear_error_on_the_host(echo_elf: Path, tmp_path: Path) -> None:
    link = PilLink(echo_elf, tmp_path).start()
    msg = can.Message(arbitration_id=0x10, is_extended_id=False, data=b"\x01")
    link.send(msg)
    _check_answer(msg, link.recv(10.0))
    assert link.qemu_pid is not None
    os.kill(link.qemu_pid, signal.SIGKILL)
    with pytest.raises(PilLinkError, match=r"QEMU exited with code -9 \(killed by signal 9\)"):
        for _ in range(50):  # the end of stream comes with the next read
            link.recv(0.2)
    with pytest.raises(PilLinkError, match="before the close"):
        link.close()


@needs_toolchain
@pytest.mark.timeout(60)
def test_missing_firmware_and_a_faulting_firmware_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(PilLinkError, match="not found"):
        PilLink(tmp_path / "none.elf", tmp_path).start()
    # a firmware whose main returns at once: QEMU exits (semihosting) before any answer
    main = tmp_path / "quit.c"
    main.write_text("void mcu_mark(void);\nvoid mcu_mark(void) {}\nint main(void) { return 3; }\n")
    elf = build_pil_firmware(tmp_path / "quit", main=main, insn_marks=False)
    link = PilLink(elf, tmp_path / "run", start_timeout_s=10.0)
    with pytest.raises(PilLinkError, match=r"did not start|did not answer") as err:
        link.start()
    assert "QEMU exited with code 1" in str(err.value)
    assert link.qemu_returncode == 1


_ORPHAN_SCRIPT = """
import sys, time
from harness.run.pil_link import PilLink
link = PilLink(sys.argv[1], sys.argv[2]).start()
print(link.qemu_pid, flush=True)
time.sleep(60)
"""


@needs_toolchain
@pytest.mark.timeout(120)
def test_qemu_dies_with_the_process_that_started_it(echo_elf: Path, tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", _ORPHAN_SCRIPT, str(echo_elf), str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
    )
    qemu_pid: int | None = None
    try:
        assert proc.stdout is not None
        qemu_pid = int(proc.stdout.readline())
        assert psutil.Process(qemu_pid).name().startswith("qemu-system")
        proc.kill()
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        while not _gone(qemu_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(qemu_pid), "QEMU outlived the process that started it"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        if qemu_pid is not None and not _gone(qemu_pid):
            os.kill(qemu_pid, signal.SIGKILL)  # leave nothing behind when the test fails


def _gone(pid: int) -> bool:
    """The process has exited (a zombie waiting for its new parent to reap it counts)."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


@needs_toolchain
@pytest.mark.timeout(120)
def test_bridge_puts_the_firmware_on_the_project_bus(echo_elf: Path, tmp_path: Path) -> None:
    frames = random_frames(20, seed=11)
    with (
        LocalHub("pil-unit") as hub,
        PilLink(echo_elf, tmp_path) as link,
        PilBridge(link, hub.spec) as bridge,
    ):
        node = open_bus(hub.spec, autostart=False)
        try:
            for msg in frames:
                node.send(msg)
                got = node.recv(10.0)  # a local bus node does not see its own frames
                _check_answer(msg, got)
        finally:
            node.shutdown()
        bridge.check()
    # counted after the bridge stopped (a direction counts a frame once its send returned)
    assert (bridge.to_firmware, bridge.from_firmware) == (20, 20)
    assert bridge.error is None


@needs_toolchain
@pytest.mark.timeout(180)
def test_instructions_per_frame_from_the_qemu_plugin(tmp_path: Path) -> None:
    res = measure_echo(tmp_path, n_frames=27, seed=5)
    by_dlc = res["insns_per_frame_by_dlc"]
    assert sorted(by_dlc) == list(range(9))
    # every data byte adds two characters each way: strictly more work per DLC step
    steps = [by_dlc[d + 1] - by_dlc[d] for d in range(8)]
    assert all(s > 0 for s in steps), by_dlc
    assert (
        100
        < res["insns_per_frame_min"]
        <= res["insns_per_frame_median"]
        <= res["insns_per_frame_max"]
        < 10_000
    )
    assert (
        slcan_line(can.Message(arbitration_id=0x12, is_extended_id=False, data=b"\x0a"))
        == b"t01210A\r"
    )
