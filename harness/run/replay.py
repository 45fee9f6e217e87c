"""Deterministic replay: feed a recorded bus log to a fresh controller node offline.

Only the plant's frames are replayed (in recorded order); the torque frames the node produces
are compared byte for byte with the ones recorded in the log.

The controller is read from the log (CTRL_STATUS.CONTROLLER_ID) unless one is named. A log
may hold several controller processes (a ``restart-controller`` fault): a new process shows
as a torque frame whose alive counter starts again at 0 out of sequence. The log is then
split there and each part is replayed by its own fresh node from the plant burst the new
process answered first, and each part is replayed up to its process's last recorded torque
frame (a killed process answers nothing after it). A restart that restored a learned-state
checkpoint cannot match a cold start; that part then reports DIFFERENT. A counter that starts
again at 0 only because the frame before it was lost on the bus (a ``loss`` fault) is no
restart: a part is split there only when one node replaying across the point does not
reproduce the recorded frames.

Recorded and replayed torque frames are matched in order, a recorded one to the next equal
replayed one: an answer that is not in the log (dropped on the bus by an injected fault, its
alive counter skipped in the log) is counted as ``lost_in_log``, not as a difference; every
recorded frame must still be reproduced byte for byte, counters and MACs included.

A log of a SecOC run (it holds SYNC_AUTH frames) is replayed with SecOC: the node verifies the
recorded SYNC authenticators as it did live, the recorded torque frames count only when their
authenticator verifies (a rogue node's frames in the log are left out), and the replayed
torque authenticators (MACs) must match the recorded ones as well.

The log is checked first (harness/run/log_check.py): a truncated file, a log with fewer
frames than its run recorded, several runs in one capture, a capture that starts inside a
run or torque frames from outside it are refused
(:class:`PartialLogError`); and the answer is BIT-IDENTICAL only when every torque frame of
the log was compared.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import can

from can_db.codec import Codec, Decoded
from can_db.process.argcheck import UsageError
from can_db.secoc import PLANT_SECURED, SECURED, ControllerSecOc, SecOcObserver
from can_db.secoc_keys import SecOcKeys
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import CONTROLLER_IDS, ControllerNode
from harness.run.log_check import check_file_complete, check_frames, check_run_record


class PartialLogError(UsageError):
    """The log is not one whole run (harness/run/log_check.py): a replay would answer only
    part of it."""


PLANT_FRAMES = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")
ID_TO_CONTROLLER = {v: k for k, v in CONTROLLER_IDS.items()}


@dataclass
class SegmentResult:
    """One controller process's part of the log."""

    controller: str
    first_frame: int  # index of the segment's first frame in the log
    recorded: int
    replayed: int
    identical: int
    first_mismatch: int | None
    secured: bool = False  # SecOC log: authenticators compared too
    # replayed answers whose frame the log lacks (lost on the bus: its counter skipped there)
    lost_in_log: int = 0

    @property
    def bit_identical(self) -> bool:
        """Every recorded torque frame was reproduced exactly, and every other replayed
        answer is one the log lacks (lost on the bus)."""
        return (self.recorded == self.identical > 0
                and self.replayed == self.identical + self.lost_in_log)


@dataclass
class ReplayResult:
    """Comparison of replayed and recorded torque frames over all segments."""

    controller: str
    segments: list[SegmentResult] = field(default_factory=list)
    secured: bool = False  # SecOC log: torque frames and their MACs were compared
    # torque frames in the log (SecOC: those whose authenticator verifies); more than
    # ``recorded``: some were not compared, and the answer is partial
    torque_frames_in_log: int = 0

    @property
    def recorded(self) -> int:
        return sum(s.recorded for s in self.segments)

    @property
    def replayed(self) -> int:
        return sum(s.replayed for s in self.segments)

    @property
    def identical(self) -> int:
        return sum(s.identical for s in self.segments)

    @property
    def lost_in_log(self) -> int:
        return sum(s.lost_in_log for s in self.segments)

    @property
    def first_mismatch(self) -> int | None:
        """Index (over all recorded torque frames) of the first differing one."""
        offset = 0
        for s in self.segments:
            if s.first_mismatch is not None:
                return offset + s.first_mismatch
            offset += s.recorded
        return None

    @property
    def uncompared(self) -> int:
        """Torque frames of the log that no segment compared (0 for a whole answer)."""
        return max(0, self.torque_frames_in_log - self.recorded)

    @property
    def bit_identical(self) -> bool:
        """Every segment reproduced exactly, and every torque frame of the log compared."""
        return (bool(self.segments) and all(s.bit_identical for s in self.segments)
                and self.uncompared == 0)


def read_log(log_path: str | Path) -> list[can.Message]:
    """Every frame of a bus log (.blf/.asc/.mf4/...); UsageError if it cannot be read."""
    path = Path(log_path)
    if not path.is_file():
        raise UsageError(f"bus log {path}: no such file")
    if path.stat().st_size == 0:
        raise UsageError(f"bus log {path}: the file is empty")
    try:
        frames = [m for m in can.LogReader(str(path)) if not m.is_error_frame]
    except ValueError as exc:  # python-can: unknown suffix
        raise UsageError(f"bus log {path}: {exc}") from None
    except Exception as exc:  # a corrupt file raises whatever its parser meets
        raise UsageError(f"bus log {path}: not a readable log ({type(exc).__name__}: "
                         f"{exc})") from None
    if not frames:
        raise UsageError(f"bus log {path}: holds no CAN frames")
    return frames


def genuine_frames(frames: list[can.Message], codec: Codec,
                   keys: SecOcKeys | None) -> set[int] | None:
    """``id()`` of every frame whose authenticator verifies (None without keys: no SecOC)."""
    if keys is None:
        return None
    observer = SecOcObserver(codec, keys)
    genuine: set[int] = set()
    for msg in frames:
        _, released = observer.observe(msg)
        if released is not None:
            genuine.add(id(released))
    return genuine


def split_at_restarts(frames: list[can.Message], codec: Codec,
                      genuine: set[int] | None = None) -> list[int]:
    """Start index of each controller process's part of ``frames`` (the first is 0).

    A new process's first torque frame has alive counter 0 out of sequence; its part starts
    right after the SYNC preceding the SYNC it answers (so it gets that whole burst).
    ``genuine``: a SecOC log's authenticated frames (:func:`genuine_frames`): only those count.
    """
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    sync_id = codec.messages["SYNC"].frame_id
    starts = [0]
    last_alive: int | None = None
    syncs: list[int] = []  # indices of SYNC frames seen so far
    for i, msg in enumerate(frames):
        if msg.arbitration_id == sync_id:
            syncs.append(i)
        elif msg.arbitration_id == torque_id and (genuine is None or id(msg) in genuine):
            dec = codec.decode_message(msg)
            if not isinstance(dec, Decoded):
                continue
            if last_alive is not None and dec.counter == 0 and last_alive != 15:
                # the SYNC this frame answers is the last one seen; start after the one before
                start = syncs[-2] + 1 if len(syncs) >= 2 else 0
                if start > starts[-1]:
                    starts.append(start)
            last_alive = dec.counter
    return starts


def controller_in(frames: list[can.Message], codec: Codec) -> str | None:
    """The controller named by the first valid CTRL_STATUS.CONTROLLER_ID in ``frames``."""
    status_id = codec.messages["CTRL_STATUS"].frame_id
    for msg in frames:
        if msg.arbitration_id == status_id:
            dec = codec.decode_message(msg)
            if isinstance(dec, Decoded):
                return ID_TO_CONTROLLER.get(int(dec.values["CONTROLLER_ID"]))
    return None


def _replay_segment(frames: list[can.Message], first: int, name: str, config: str | None,
                    codec: Codec, keys: SecOcKeys | None = None) -> SegmentResult:
    """Replay one controller process's part; with ``keys`` (a SecOC log) the node runs SecOC,
    recorded torque frames count only when their authenticator verifies, and the replayed
    authenticators (MACs) are compared too."""
    names = PLANT_FRAMES + (tuple(SECURED[n] for n in PLANT_SECURED) if keys is not None
                            else ())
    plant_ids = {codec.messages[n].frame_id for n in names}
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    torque_auth_id = codec.messages["WHEEL_TORQUE_AUTH"].frame_id
    secoc = ControllerSecOc(codec, keys) if keys is not None else None
    observer = SecOcObserver(codec, keys) if keys is not None else None
    node = ControllerNode(make_controller(name, config), load_vehicle_params(), codec=codec,
                          secoc=secoc)
    # The process answered nothing after its last recorded torque frame (killed, or the log
    # ends): replay the plant frames up to there only (with SecOC: up to its authenticator).
    last_id = torque_auth_id if keys is not None else torque_id
    last = max((i for i, m in enumerate(frames) if m.arbitration_id == last_id), default=-1)
    frames = frames[:last + 1]
    recorded: list[bytes] = []
    replayed: list[bytes] = []
    last_auth = b""
    for msg in frames:
        if observer is not None:
            _, released = observer.observe(msg)
            if msg.arbitration_id == torque_auth_id:
                last_auth = bytes(msg.data)
            if released is not None and released.arbitration_id == torque_id:
                recorded.append(bytes(released.data) + last_auth)
        elif msg.arbitration_id == torque_id:
            recorded.append(bytes(msg.data))
        if msg.arbitration_id in plant_ids:
            out = node.on_frame_lockstep(msg)
            if out:
                replayed.extend(_torque_records(out, torque_id, torque_auth_id,
                                                secured=keys is not None))
    identical, mismatch, lost = match_in_order(recorded, replayed)
    return SegmentResult(name, first, len(recorded), len(replayed), identical, mismatch,
                         lost_in_log=lost)


#: Replayed answers one recorded frame may be ahead of: fewer than the 16 values of the alive
#: counter, so a skipped stretch of the log is never mistaken for another cycle's frame.
LOST_RUN_MAX = 15


def match_in_order(recorded: list[bytes], replayed: list[bytes]
                   ) -> tuple[int, int | None, int]:
    """(identical, index of the first recorded frame not reproduced or None, replayed
    answers skipped as lost in the log). Each recorded frame is looked for among the next
    ``LOST_RUN_MAX + 1`` replayed ones; the replayed frames passed over are answers the log
    lacks. Payloads hold the echoed cycle and the alive counter (and, secured, the MAC), so
    an equal payload is the same answer."""
    identical, mismatch, lost, j = 0, None, 0, 0
    for i, rec in enumerate(recorded):
        window = replayed[j:j + LOST_RUN_MAX + 1]
        k = window.index(rec) if rec in window else None
        if k is None:
            if mismatch is None:
                mismatch = i
            j += 1  # the answer to this cycle differs: compare the next one with the next
            continue
        identical += 1
        lost += k
        j += k + 1
    # answers after the last recorded one: the part ends at its last torque frame or
    # authenticator in the log, so these answered cycles whose frames the log lacks
    trailing = len(replayed) - j
    if 0 < trailing <= LOST_RUN_MAX and identical:
        lost += trailing
    return identical, mismatch, lost


def log_is_secured(log_path: str | Path) -> bool:
    """True when the log holds SYNC authenticators (a SecOC run)."""
    auth_id = Codec().messages["SYNC_AUTH"].frame_id
    return any(msg.arbitration_id == auth_id for msg in read_log(log_path))


def replay_log(log_path: str | Path, controller_name: str | None = None,
               config: str | None = None, keys: SecOcKeys | None = None) -> ReplayResult:
    """Replay ``log_path`` in lockstep mode, split at controller restarts.

    ``controller_name``: None → read from each part's CTRL_STATUS.CONTROLLER_ID.
    """
    codec = Codec()
    frames = read_log(log_path)
    problems = check_file_complete(Path(log_path)) + check_run_record(Path(log_path)) \
        + check_frames(frames, codec)
    if problems:
        raise PartialLogError(f"bus log {log_path}: not replayed, the answer would be partial: "
                              + "; ".join(problems))
    genuine = genuine_frames(frames, codec, keys)  # SecOC log: only authenticated ones count
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    in_log = sum(1 for m in frames if m.arbitration_id == torque_id
                 and (genuine is None or id(m) in genuine))

    def replay_part(first: int, end: int) -> SegmentResult:
        part = frames[first:end]
        name = controller_name or controller_in(part, codec)
        if name is None:
            raise UsageError(f"bus log {log_path}: no valid CTRL_STATUS frame names the "
                             "controller; give --controller")
        return _replay_segment(part, first, name, config, codec, keys)

    # a counter back at 0 is a restart only if one node cannot replay across it (the frame
    # with counter 15 may just be lost on the bus)
    candidates = split_at_restarts(frames, codec, genuine)
    starts = [0]
    for cand, end in itertools.pairwise([*candidates[1:], len(frames)]):
        if not replay_part(starts[-1], end).bit_identical:
            starts.append(cand)
    segments = [replay_part(first, end)
                for first, end in itertools.pairwise([*starts, len(frames)])]
    return ReplayResult(controller_name or segments[0].controller, segments,
                        secured=keys is not None, torque_frames_in_log=in_log)


def _torque_records(frames: list[can.Message], torque_id: int, auth_id: int, *,
                    secured: bool) -> list[bytes]:
    """Torque payloads (followed by their authenticator's payload when ``secured``)."""
    out: list[bytes] = []
    for i, frame in enumerate(frames):
        if frame.arbitration_id != torque_id:
            continue
        data = bytes(frame.data)
        if secured:
            nxt = frames[i + 1] if i + 1 < len(frames) else None
            data += bytes(nxt.data) if nxt is not None and nxt.arbitration_id == auth_id \
                else b""
        out.append(data)
    return out
