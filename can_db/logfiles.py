"""Bus log files: the MF4 layout, the crash-safe frame file an MF4 is built from, the time
base of BLF/ASC/MF4 logs, and a conversion between them that keeps it.

**Time base.** Every log has a start (wall clock, Unix s) and frame times counted from it;
the recorder also writes a one-line note saying what the times mean (simulated time in
lockstep, receive time in realtime). Where each format keeps them:

* BLF: the file header's start time + a global marker event at the start (the note).
* ASC: ``Begin Triggerblock <date>`` (the start, local time, ms) + a comment event (the note).
* MF4: the MDF header ``start_time`` + the MDF header comment (the note); the channel times
  are zero-based (0 s = the start).

``python -m can.logconvert`` reads frames only and an ASC input with relative times, so it
drops the note everywhere and, from an ASC input, the start (a converted log begins on
1 Jan 1970); :func:`convert` keeps both.

**MF4 layout** (:func:`write_mf4`): one channel group per DBC message, named by the message
(``acq_name``), holding one channel per signal named ``MESSAGE.SIGNAL`` (e.g.
``MOTION_SENSORS.YAW_RATE``): the raw integer with the DBC's linear conversion and unit (a
value-table conversion for signals with a value table, e.g. ``CTRL_STATUS.MODE``). A signal
whose name is unique in the DBC also gets its bare name as display name, so
``mdf.get('YAW_RATE')`` finds it; names shared by several messages (``ALIVE``, ``CRC8``…)
are only reachable as ``MESSAGE.SIGNAL``. Beside them, the raw frames are kept in the ASAM
bus-logging group ``CAN_DataFrame`` (python-can's MF4Reader, replay and asammdf's bus
logging tools read it). The DBC is attached to the file, not to that group: asammdf decodes a
group whose channel carries a DBC again on opening, which would put every signal in the file
twice.

**Crash safety.** The recorder does not keep an MF4 open: it appends each frame as a packed
record to ``bus.mf4.frames`` (:class:`FrameFile`: the line ``RHONNFRAMES 1``, a JSON line
with the start and the note, then per frame ``<dIBBB`` = time s, id, flags, DLC, payload
length, followed by the payload; buffered and written with one ``write(2)`` every 0.2 s) and
builds ``bus.mf4`` from it when it stops (:func:`finish_mf4`), then removes the frame file.
A harness killed with SIGKILL leaves the frame file with every flushed frame;
``rhonn-bus recover RUN_DIR`` (:func:`recover`) builds the MF4 from it. This is the scheme of
the row logs (can_db/process/rowlog.py), chosen over an MF4 appended in chunks because such a
file still needs its data-block links and sizes written at the end to be readable, and
asammdf offers no writer that keeps a partial file valid.
"""

from __future__ import annotations

import json
import os
import re
import struct
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import can
import cantools
import numpy as np
from can.io import blf

if TYPE_CHECKING:
    from cantools.database.can import Message as DbcMessage
    from cantools.database.can import Signal as DbcSignal

FRAMES_SUFFIX = ".frames"
FRAMES_MAGIC = b"RHONNFRAMES 1\n"
_RECORD = struct.Struct("<dIBBB")  # time from the start s, id, flags, DLC, payload bytes
_EXT, _RTR, _ERR, _FD, _BRS, _ESI, _TX = (1 << i for i in range(7))
FLUSH_BYTES = 1 << 16  # the frame file's buffer is written at this size at the latest
NOTE_PREFIX = "rhonn-tv bus log;"  # start of the recorder's time-base note
LOG_SUFFIXES = (".blf", ".asc", ".mf4")
HEADER_LINES = 6  # an ASC header: date, base, internal events, Begin Triggerblock, ...

_RAW_FIELDS = (  # ASAM MDF bus logging, the fields python-can's MF4 reader reads
    ("BusChannel", "<u1"), ("ID", "<u4"), ("IDE", "<u1"), ("DLC", "<u1"), ("DataLength", "<u1"),
    ("DataBytes", "(64,)u1"), ("Dir", "<u1"), ("EDL", "<u1"), ("BRS", "<u1"), ("ESI", "<u1"))
_RAW_GROUPS = {  # group -> its fields (a remote frame has no payload)
    "CAN_DataFrame": _RAW_FIELDS, "CAN_ErrorFrame": _RAW_FIELDS,
    "CAN_RemoteFrame": tuple(f for f in _RAW_FIELDS
                             if f[0] in ("BusChannel", "ID", "IDE", "DLC", "DataLength", "Dir")),
}


class LogFileError(Exception):
    """A log file that cannot be read or written; the message is one line."""


def dbc_bytes() -> bytes:
    """The project's DBC file."""
    return resources.files("can_db").joinpath("rhonn_tv.dbc").read_bytes()


def frames_path(mf4_path: str | Path) -> Path:
    """The frame file that becomes ``mf4_path`` when its writer stops."""
    return Path(str(mf4_path) + FRAMES_SUFFIX)


# ----------------------------------------------------------------------------- frame file

def _flags(msg: can.Message) -> int:
    return ((_EXT if msg.is_extended_id else 0) | (_RTR if msg.is_remote_frame else 0)
            | (_ERR if msg.is_error_frame else 0) | (_FD if msg.is_fd else 0)
            | (_BRS if msg.bitrate_switch else 0) | (_ESI if msg.error_state_indicator else 0)
            | (0 if msg.is_rx else _TX))


def _pack(msg: can.Message, t_s: float) -> bytes:
    data = bytes(msg.data or b"")
    return _RECORD.pack(t_s, msg.arbitration_id, _flags(msg), msg.dlc, len(data)) + data


class FrameFile:
    """Append-only frame file of an MF4 being recorded (see the module docstring).

    ``start_s``: the log's start, wall clock Unix s; ``note``: the time-base note. Frames are
    buffered and written with one ``write(2)`` per :meth:`flush` (or every
    :data:`FLUSH_BYTES`), so a killed writer leaves every flushed frame on disk (a torn last
    record is dropped on reading).
    """

    def __init__(self, path: str | Path, start_s: float, note: str) -> None:
        self.path = Path(path)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        head = json.dumps({"start_s": start_s, "note": note}).encode() + b"\n"
        os.write(self._fd, FRAMES_MAGIC + head)
        self._buf = bytearray()

    def add(self, msg: can.Message, t_s: float) -> None:
        """Append ``msg`` at ``t_s`` seconds after the start."""
        self._buf += _pack(msg, t_s)
        if len(self._buf) >= FLUSH_BYTES:
            self.flush()

    def flush(self) -> None:
        """Write the buffered frames to the file."""
        if self._fd is not None and self._buf:
            os.write(self._fd, self._buf)
            self._buf.clear()

    def close(self) -> None:
        """Flush and close (idempotent)."""
        if self._fd is not None:
            self.flush()
            os.close(self._fd)
            self._fd = None


@dataclass
class BusLog:
    """A log read back: its start (wall clock Unix s), its time-base note (None if it has
    none) and its frames with times counted from the start, s."""

    start_s: float
    note: str | None
    frames: list[can.Message] = field(default_factory=list)


@dataclass
class Frames:
    """Frames as columns (what an MF4 is built from without one object per frame):
    ``t`` s from the start, ``arb`` id, ``flags`` (``_EXT``…), ``dlc``, ``length`` payload
    bytes, ``data`` (n, 64) payloads, ``channel`` bus channel numbers."""

    t: np.ndarray
    arb: np.ndarray
    flags: np.ndarray
    dlc: np.ndarray
    length: np.ndarray
    data: np.ndarray
    channel: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    def take(self, mask: np.ndarray) -> Frames:
        """The frames where ``mask`` is true."""
        return Frames(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))

    @classmethod
    def of(cls, messages: list[can.Message]) -> Frames:
        """Columns of python-can messages (``timestamp``: s from the start)."""
        return cls(
            t=np.array([m.timestamp for m in messages], dtype="<f8"),
            arb=np.array([m.arbitration_id for m in messages], dtype="u4"),
            flags=np.array([_flags(m) for m in messages], dtype="u1"),
            dlc=np.array([m.dlc for m in messages], dtype="u1"),
            length=np.array([len(m.data or b"") for m in messages], dtype="u1"),
            data=_payloads([bytes(m.data or b"") for m in messages]),
            channel=np.array([can.util.channel2int(m.channel) or 0 for m in messages],
                             dtype="u1"))

    def messages(self) -> list[can.Message]:
        """python-can messages of the columns."""
        out = []
        for t, arb, flags, dlc, length, data, channel in zip(
                self.t.tolist(), self.arb.tolist(), self.flags.tolist(), self.dlc.tolist(),
                self.length.tolist(), self.data, self.channel.tolist(), strict=True):
            out.append(can.Message(
                timestamp=t, arbitration_id=arb, data=data[:length].tobytes(),
                is_extended_id=bool(flags & _EXT), is_remote_frame=bool(flags & _RTR),
                is_error_frame=bool(flags & _ERR), is_fd=bool(flags & _FD),
                bitrate_switch=bool(flags & _BRS), error_state_indicator=bool(flags & _ESI),
                is_rx=not flags & _TX, dlc=dlc, channel=channel, check=False))
        return out


def _payloads(payloads: list[bytes]) -> np.ndarray:
    """(n, 64) array of payloads padded with zeros."""
    if not payloads:
        return np.zeros((0, 64), dtype="u1")
    return np.frombuffer(b"".join(d.ljust(64, b"\0") for d in payloads),
                         dtype="u1").reshape(-1, 64).copy()


def read_frame_columns(path: str | Path) -> tuple[float, str | None, Frames]:
    """(start wall clock Unix s, note, frames) of a frame file, complete or left by a
    killed writer (a torn last record is dropped)."""
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise LogFileError(f"{path}: {exc.strerror or exc}") from None
    end = raw.find(b"\n", len(FRAMES_MAGIC))
    if not raw.startswith(FRAMES_MAGIC) or end < 0:
        raise LogFileError(f"{path}: not a frame file")
    head = json.loads(raw[len(FRAMES_MAGIC):end])
    rows, payloads = [], []
    pos, size, unpack = end + 1, _RECORD.size, _RECORD.unpack_from
    while pos + size <= len(raw):
        row = unpack(raw, pos)
        length = row[4]
        if pos + size + length > len(raw):
            break  # torn last record
        rows.append(row)
        payloads.append(raw[pos + size:pos + size + length])
        pos += size + length
    cols = np.array(rows, dtype="f8").reshape(-1, 5)
    frames = Frames(t=cols[:, 0].copy(), arb=cols[:, 1].astype("u4"),
                    flags=cols[:, 2].astype("u1"), dlc=cols[:, 3].astype("u1"),
                    length=cols[:, 4].astype("u1"), data=_payloads(payloads),
                    channel=np.zeros(len(rows), dtype="u1"))
    return float(head["start_s"]), head.get("note"), frames


def read_frame_file(path: str | Path) -> BusLog:
    """The frames of a frame file (complete, or left by a killed writer)."""
    start_s, note, frames = read_frame_columns(path)
    return BusLog(start_s, note, frames.messages())


# ----------------------------------------------------------------------------- MF4

def _int_dtype(bits: int, signed: bool) -> np.dtype:
    for width in (8, 16, 32, 64):
        if bits <= width:
            return np.dtype(f"{'i' if signed else 'u'}{width // 8}")
    return np.dtype("i8" if signed else "u8")


def _conversion(sig: DbcSignal) -> dict | None:
    """asammdf conversion of a cantools signal: value table, linear, or none."""
    choices = sig.choices or {}
    if choices and sig.scale == 1 and sig.offset == 0:
        conv: dict = {"default": b""}
        for i, (value, text) in enumerate(sorted(choices.items())):
            conv[f"val_{i}"], conv[f"text_{i}"] = int(value), str(text).encode()
        return conv
    if sig.scale != 1 or sig.offset != 0:
        return {"a": float(sig.scale), "b": float(sig.offset)}
    return None


def _raw_records(kind: str, f: Frames) -> np.ndarray:
    """The ASAM bus-logging records of frames ``f`` for group ``kind`` (CAN_DataFrame…)."""
    fields = _RAW_GROUPS[kind]
    raw = np.zeros(len(f), dtype=[(f"{kind}.{n}", t) for n, t in fields])
    names = {n for n, _ in fields}
    ext = (f.flags & _EXT).astype(bool)
    fd = (f.flags & _FD).astype(bool)
    dlc_code = np.array([can.util.len2dlc(n) for n in f.length.tolist()], dtype="u1")
    columns = {
        "BusChannel": f.channel,
        "ID": f.arb | (ext.astype("u4") << 31),  # the ASAM bus-logging flag of an extended id
        "IDE": ext,
        "DLC": np.where(fd, dlc_code, f.dlc),
        "DataLength": f.length,
        "DataBytes": f.data,
        "Dir": (f.flags & _TX).astype(bool),
        "EDL": fd,
        "BRS": (f.flags & _BRS).astype(bool),
        "ESI": (f.flags & _ESI).astype(bool),
    }
    for name in names:
        raw[f"{kind}.{name}"] = columns[name]
    return raw


def _decode_raw(msg: DbcMessage, f: Frames) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(times, raw integer per signal) of the frames ``f`` of DBC message ``msg`` (cantools),
    the frames cantools cannot decode left out. Little-endian integer signals of a frame of
    the message's length are cut from the payload as a 64-bit word in one numpy step (what
    cantools does frame by frame); anything else goes through cantools."""
    simple = msg.length <= 8 and not msg.is_multiplexed() and all(
        s.byte_order == "little_endian" and not s.is_float for s in msg.signals)
    if simple:
        ok = f.length == msg.length
        word = np.ascontiguousarray(f.data[ok, :8]).view("<u8").ravel()
        columns = {}
        for sig in msg.signals:
            raw = (word >> np.uint64(sig.start)) & np.uint64((1 << sig.length) - 1)
            if sig.is_signed:  # two's complement of sig.length bits
                value = raw.astype("i8")
                value[value >= 1 << (sig.length - 1)] -= 1 << sig.length
                raw = value
            columns[sig.name] = raw.astype(_int_dtype(sig.length, sig.is_signed))
        return f.t[ok], columns
    times, rows = [], []
    for t, payload, length in zip(f.t.tolist(), f.data, f.length.tolist(), strict=True):
        try:
            rows.append(msg.decode(payload[:length].tobytes(), decode_choices=False,
                                   scaling=False))
        except Exception:  # malformed (fuzzing): kept in CAN_DataFrame only
            continue
        times.append(t)
    return np.array(times, dtype="<f8"), {
        s.name: np.array([r[s.name] for r in rows], dtype=_int_dtype(s.length, s.is_signed))
        for s in msg.signals}


def write_mf4(path: str | Path, frames: Iterable[can.Message] | Frames, start_s: float,
              note: str | None) -> int:
    """Write an MF4 in the layout of the module docstring; frame times: s from ``start_s``
    (wall clock Unix s). Returns the number of frames written."""
    from asammdf import MDF, Signal
    from asammdf.blocks.v4_blocks import SourceInformation
    from asammdf.blocks.v4_constants import BUS_TYPE_CAN, SOURCE_BUS

    cols = frames if isinstance(frames, Frames) else Frames.of(list(frames))
    mdf = MDF(version="4.10")
    mdf.header.start_time = datetime.fromtimestamp(start_s, tz=UTC)
    if note:
        mdf.header.comment = note
    dbc = dbc_bytes()
    mdf.attach(dbc, file_name="rhonn_tv.dbc", comment="DBC of the decoded channel groups",
               embedded=True)
    error = (cols.flags & _ERR).astype(bool)
    remote = (cols.flags & _RTR).astype(bool) & ~error
    data_mask = ~error & ~remote
    source = SourceInformation(source_type=SOURCE_BUS, bus_type=BUS_TYPE_CAN)
    for kind, mask in (("CAN_DataFrame", data_mask), ("CAN_ErrorFrame", error),
                       ("CAN_RemoteFrame", remote)):
        if mask.any() or kind == "CAN_DataFrame":
            mine = cols.take(mask)
            mdf.append(Signal(name=kind, samples=_raw_records(kind, mine), timestamps=mine.t,
                              source=source),
                       acq_name="CAN", comment=f"raw {kind} records (ASAM bus logging)")
    data = cols.take(data_mask & ~(cols.flags & _EXT).astype(bool))  # the DBC's are 11-bit

    db = cantools.database.load_string(dbc.decode(), database_format="dbc")
    counts: dict[str, int] = {}
    for msg in db.messages:
        for sig in msg.signals:
            counts[sig.name] = counts.get(sig.name, 0) + 1
    for msg in db.messages:
        times, columns = _decode_raw(msg, data.take(data.arb == msg.frame_id))
        if not len(times):
            continue
        signals = []
        for sig in msg.signals:
            signals.append(Signal(
                samples=columns[sig.name], timestamps=times,
                name=f"{msg.name}.{sig.name}", unit=sig.unit or "",
                conversion=_conversion(sig), comment=sig.comment or "",
                display_names={sig.name: "signal"} if counts[sig.name] == 1 else None))
        comment = f"{msg.name} 0x{msg.frame_id:03X}" + (f": {msg.comment}" if msg.comment else "")
        mdf.append(signals, acq_name=msg.name, comment=comment)
    path = Path(path)
    tmp = path.with_name(path.stem + ".tmp.mf4")  # asammdf gives a saved file .mf4
    mdf.save(tmp, overwrite=True, compression=2)
    mdf.close()
    os.replace(tmp, path)
    return len(cols)


def finish_mf4(mf4_path: str | Path) -> bool:
    """Build ``mf4_path`` from its frame file and remove the frame file; False when there
    is no frame file."""
    src = frames_path(mf4_path)
    if not src.exists():
        return False
    start_s, note, frames = read_frame_columns(src)
    write_mf4(mf4_path, frames, start_s, note)
    src.unlink(missing_ok=True)
    return True


def recover(target: str | Path) -> list[Path]:
    """:func:`finish_mf4` for a run directory (every ``*.mf4.frames`` in it), an MF4 path or
    a frame file path; returns the MF4 files written."""
    target = Path(target)
    if target.is_dir():
        sources = sorted(target.glob(f"*.mf4{FRAMES_SUFFIX}"))
    elif target.name.endswith(FRAMES_SUFFIX):
        sources = [target]
    else:
        sources = [frames_path(target)]
    done = []
    for src in sources:
        mf4 = Path(str(src)[: -len(FRAMES_SUFFIX)])
        if finish_mf4(mf4):
            done.append(mf4)
    return done


# ----------------------------------------------------------------------------- reading logs

def _blf_note(path: Path) -> str | None:
    """The recorder's note: the first global marker of a BLF whose text is one."""
    with can.BLFReader(str(path)) as reader:  # leaves the file after its header
        f = reader.file
        for _ in range(4):  # the note is the first event: in the first container
            head = f.read(blf.OBJ_HEADER_BASE_STRUCT.size)
            if len(head) < blf.OBJ_HEADER_BASE_STRUCT.size:
                return None
            sig, _, _, size, obj_type = blf.OBJ_HEADER_BASE_STRUCT.unpack(head)
            if sig != b"LOBJ":
                return None
            body = f.read(size - len(head))
            f.read(size % 4)
            if obj_type != blf.LOG_CONTAINER:
                continue
            method, _ = blf.LOG_CONTAINER_STRUCT.unpack_from(body)
            data = body[blf.LOG_CONTAINER_STRUCT.size:]
            if method == blf.ZLIB_DEFLATE:
                data = zlib.decompressobj().decompress(data)
            pos = 0
            while pos + blf.OBJ_HEADER_BASE_STRUCT.size <= len(data):
                sig, _, version, size, obj_type = blf.OBJ_HEADER_BASE_STRUCT.unpack_from(data, pos)
                if sig != b"LOBJ" or size <= 0:
                    break
                if obj_type == blf.GLOBAL_MARKER:
                    at = pos + blf.OBJ_HEADER_BASE_STRUCT.size + (
                        blf.OBJ_HEADER_V1_STRUCT.size if version == 1
                        else blf.OBJ_HEADER_V2_STRUCT.size)
                    fields = blf.GLOBAL_MARKER_STRUCT.unpack_from(data, at)
                    at += blf.GLOBAL_MARKER_STRUCT.size
                    text = data[at:at + fields[4]].decode("latin-1")
                    if text.startswith(NOTE_PREFIX):
                        return text
                pos += size + size % 4
            return None
    return None


def _asc_note(path: Path) -> str | None:
    with open(path, encoding="latin-1") as f:
        for _, line in zip(range(50), f, strict=False):
            parts = line.strip().split(" ", 1)
            if len(parts) == 2 and parts[1].startswith(NOTE_PREFIX):
                return parts[1]
    return None


def _mdf_comment(comment: str) -> str | None:
    """The text of an MDF header comment (plain or ``<HDcomment><TX>…</TX>``)."""
    found = re.search(r"<TX>(.*?)</TX>", comment, re.S)
    text = found.group(1) if found else comment
    return text.strip() or None


def read_log(path: str | Path) -> BusLog:
    """Frames of a BLF, ASC or MF4 log or a frame file, times counted from the log's start;
    :class:`LogFileError` (one line) when it cannot be read."""
    path = Path(path)
    if not path.exists():
        hint = ""
        if frames_path(path).exists():
            hint = (f" (its writer did not finish: `rhonn-bus recover {path.parent}` builds it "
                    f"from {frames_path(path).name})")
        raise LogFileError(f"{path}: no such file{hint}")
    suffix = path.suffix.lower()
    try:
        if path.name.endswith(FRAMES_SUFFIX):
            return read_frame_file(path)
        if suffix == ".blf":
            with can.BLFReader(str(path)) as reader:
                start = float(reader.start_timestamp)
                frames = list(reader)
            note = _blf_note(path)
        elif suffix == ".asc":
            with can.ASCReader(str(path), relative_timestamp=False) as reader:
                frames = list(reader)
                start = float(reader.start_time)
            note = _asc_note(path)
        elif suffix == ".mf4":
            from asammdf import MDF

            with MDF(path) as mdf:
                start = mdf.header.start_time.timestamp()
                note = _mdf_comment(mdf.header.comment or "")
            with can.MF4Reader(str(path)) as reader:
                frames = list(reader)
        else:
            raise LogFileError(f"{path}: use a .blf, .asc or .mf4 log (or a .mf4.frames file)")
    except LogFileError:
        raise
    except Exception as exc:  # python-can/asammdf parse errors have many types
        raise LogFileError(f"{path}: cannot read it as {suffix[1:].upper()}: {exc}") from None
    for m in frames:
        m.timestamp -= start
    return BusLog(start, note, frames)


def set_asc_date(path: str | Path, start_s: float) -> None:
    """Put ``start_s`` (wall clock Unix s, shown in local time) into an ASC file's header: the
    ``date …`` line (python-can's ASCWriter writes the time the file was opened there) and the
    ``Begin Triggerblock …`` line, both with three millisecond digits as CANoe writes them
    (python-can drops the leading zeros, so its own reader takes 25 ms for 250 ms)."""
    dt = datetime.fromtimestamp(start_s)
    stamp = f"{dt.strftime('%a %b %d %H:%M:%S')}.{dt.microsecond // 1000:03d} {dt.year}"
    with open(path, "r+b") as f:
        head = [f.readline() for _ in range(HEADER_LINES)]
        new = list(head)
        for i, line in enumerate(head):
            for key in (b"date ", b"Begin Triggerblock "):
                if line.startswith(key):
                    end = b"\r\n" if line.endswith(b"\r\n") else b"\n"
                    new[i] = key + stamp.encode("ascii") + end
        if new == head:
            return
        if [len(x) for x in new] == [len(x) for x in head]:
            f.seek(0)  # the same lengths: in place
            f.write(b"".join(new))
            return
        rest = f.read()
        f.seek(0)
        f.write(b"".join(new) + rest)
        f.truncate()


def write_log(path: str | Path, log: BusLog) -> int:
    """Write ``log`` as BLF, ASC or MF4 by suffix with its start and note; returns the
    number of frames written."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".mf4":
        return write_mf4(path, log.frames, log.start_s, log.note)
    if suffix == ".blf":
        writer: can.io.generic.MessageWriter = can.BLFWriter(str(path))
    elif suffix == ".asc":
        writer = can.ASCWriter(str(path))
    else:
        raise LogFileError(f"{path}: use a .blf, .asc or .mf4 output")
    with writer:
        # the first event fixes the file's start (BLF header, ASC Begin Triggerblock)
        writer.log_event(log.note or f"{NOTE_PREFIX} converted from a log without a note",
                         log.start_s)
        for m in log.frames:
            out = can.Message(
                timestamp=log.start_s + m.timestamp, arbitration_id=m.arbitration_id,
                data=m.data, is_extended_id=m.is_extended_id, is_remote_frame=m.is_remote_frame,
                is_error_frame=m.is_error_frame, is_fd=m.is_fd, bitrate_switch=m.bitrate_switch,
                error_state_indicator=m.error_state_indicator, is_rx=m.is_rx, dlc=m.dlc,
                channel=m.channel, check=False)
            writer.on_message_received(out)
    if suffix == ".asc":
        set_asc_date(path, log.start_s)
    return len(log.frames)


def convert(src: str | Path, dst: str | Path) -> int:
    """Convert a bus log between BLF, ASC and MF4 (or a frame file to any of them),
    keeping its start and time-base note; returns the number of frames."""
    if Path(src).resolve() == Path(dst).resolve():
        raise LogFileError(f"{dst}: the output must differ from the input")
    return write_log(dst, read_log(src))

