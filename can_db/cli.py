"""`rhonn-bus`: run the loopback bus server, dump decoded traffic, run the bus demo, or
decode, convert and recover bus logs.

  rhonn-bus serve [--port P]            loopback bus server on 127.0.0.1 (Ctrl-C stops it)
  rhonn-bus dump --bus SPEC [--count N] [--secoc-keys SRC]
                                        print every frame decoded and validated, marked
                                        authenticated or not (SecOC)
  rhonn-bus demo [--cycles N]           two OS processes exchange E2E frames over a fresh server
  rhonn-bus decode LOG [--messages NAME,...] [--count N]
                                        print a bus log (.blf, .asc, .mf4, .mf4.frames) decoded
                                        with the DBC: time from the log's start, message, signals
                                        with units
  rhonn-bus convert IN OUT              convert a bus log between BLF, ASC and MF4, keeping its
                                        start time and time-base note
  rhonn-bus recover RUN_DIR|FILE        build the MF4 a killed harness left as bus.mf4.frames

Bus logs, their time bases and the MF4 layout: docs/logs.md.
"""

from __future__ import annotations

import argparse
import logging
import math
import subprocess
import sys
import time
from collections import deque
from pathlib import Path
from typing import TextIO

from can_db.codec import Codec, Decoded, Rejected, Transmitter
from can_db.logfiles import (
    FRAMES_SUFFIX,
    LOG_SUFFIXES,
    LogFileError,
    convert,
    frames_path,
    read_log,
    recover,
)
from can_db.monitor import RxMonitor
from can_db.process.argcheck import (
    OneLineParser,
    UsageError,
    check_extra,
    check_in_file,
    check_out_file,
    check_port_free,
    choice_list,
    number,
    usage_exit,
)
from can_db.process.logsetup import add_logging_options, logging_args, setup_logging
from can_db.process.parent import die_with_parent
from can_db.process.stopflag import StopFlag
from can_db.secoc import SECURED, SecOcObserver
from can_db.secoc_keys import SecOcKeyError, load_keys
from can_db.transport.bus import BusDisconnected, open_bus
from can_db.transport.check import check_bus
from can_db.transport.server import BusServer, BusServerError
from can_db.transport.socketcan import CAPTURE_RCVBUF_BYTES, rx_dropped

log = logging.getLogger("rhonn-bus")
PLANT_FRAMES = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC")


def signal_formats(codec: Codec) -> dict[tuple[str, str], tuple[dict[int, str], str]]:
    """(message, signal) -> (value table, unit) from the DBC."""
    out: dict[tuple[str, str], tuple[dict[int, str], str]] = {}
    for msg in codec.database.messages:
        for sig in msg.signals:
            choices = {int(k): str(v) for k, v in (sig.choices or {}).items()}
            out[(msg.name, sig.name)] = (choices, sig.unit or "")
    return out


def format_frame(result: object,
                 formats: dict[tuple[str, str], tuple[dict[int, str], str]]) -> str:
    """One decoded frame: value-table names for enums (``MODE=ACTIVE``), units after
    physical values (``SWA=12.5 deg``); a rejected frame says why (``REJECTED unknown_id:
    ...``), in words as every line here, never as a Python object."""
    if isinstance(result, Rejected):
        return f"REJECTED {result.reason.value}: {result.detail}"
    if not isinstance(result, Decoded):  # a well-formed frame no rule here checks
        return "not checked"
    parts = []
    for name, value in result.values.items():
        choices, unit = formats.get((result.name, name), ({}, ""))
        if choices and float(value).is_integer() and int(value) in choices:
            parts.append(f"{name}={choices[int(value)]}")
        elif name == "MAC":  # a 32-bit authenticator: hex digits, as a tool shows it
            parts.append(f"{name}=0x{int(value):08X}")
        else:
            parts.append(f"{name}={value:g}" + (f" {unit}" if unit else ""))
    return f"{result.name:<16} alive={result.counter:>2} " + ", ".join(parts)


def cmd_serve(args: argparse.Namespace) -> int:
    # the handlers before the start: a signal sent as soon as the address line is read (or
    # to a server started in the background, SIGINT inherited as ignored) must stop it
    stop = StopFlag()
    server = BusServer(args.port).start()
    print(f"loopback bus server on {server.url}  (spec: {server.spec})", flush=True)
    try:
        while not stop() and server.alive():
            time.sleep(0.2)
    finally:
        server.stop()
    return 0


def _sec_label(codec: Codec, msg) -> str:
    """SecOC mark of a frame without the keys: what can be said of it."""
    spec = codec.by_id.get(msg.arbitration_id)
    name = spec.name if spec is not None else ""
    if name in SECURED or name in SECURED.values():
        return "[secured, not verified: no key]"
    return "[unsecured]"


RESOLVE_WINDOW = 64  # frames a secured frame may wait in the dump for its authenticator


class SecOcLabels:
    """The dump's SecOC marks with the keys: a secured data frame comes before its
    authenticator (the plant's driver and sensor frames even before their SYNC's), so its
    line waits until that arrives and then says ``[authenticated]`` or why not. Lines come
    out in bus order; one still unresolved ``RESOLVE_WINDOW`` frames later (or at the end)
    says ``[unverified: no authenticator seen]``."""

    def __init__(self, observer: SecOcObserver) -> None:
        self.observer = observer
        self._lines: deque[list] = deque()  # [frame, head, tail, label or None: pending]
        self._waiting: dict[int, list] = {}  # id(frame) -> its entry

    def add(self, msg, head: str, tail: str) -> list[str]:
        """Record one frame (its line: ``head [mark] tail``); returns the lines ready to
        print."""
        label, released = self.observer.observe(msg)
        receiver = self.observer.sync if self.observer.sync.is_secured(msg.arbitration_id) \
            else self.observer.ctrl
        if label == "pending" and released is not None:  # verified its frame on arrival
            label = f"authenticated 0x{released.arbitration_id:03X}"
        entry = [msg, head, tail, None if label == "pending" else f"[{label}]"]
        self._lines.append(entry)
        if entry[3] is None:
            self._waiting[id(msg)] = entry
        if released is None:
            return self._ready(len(self._lines) > RESOLVE_WINDOW)
        for frame in (released, *receiver.released_data):  # the SYNC's burst with it
            done = self._waiting.pop(id(frame), None)
            if done is not None:
                done[3] = "[authenticated]"
        if released.arbitration_id == self.observer.sync_id:
            # the burst's deferred authenticators were checked with their SYNC
            for key, waiting in list(self._waiting.items()):
                if waiting[0].arbitration_id in self.observer.sync.auth_ids:
                    waiting[3] = "[authenticator: checked with its SYNC]"
                    del self._waiting[key]
        return self._ready(len(self._lines) > RESOLVE_WINDOW)

    def _ready(self, overflow: bool) -> list[str]:
        out = []
        while self._lines and (self._lines[0][3] is not None or overflow):
            msg, head, tail, label = self._lines.popleft()
            self._waiting.pop(id(msg), None)
            out.append(f"{head} {label or '[unverified: no authenticator seen]'} {tail}")
            overflow = len(self._lines) > RESOLVE_WINDOW
        return out

    def flush(self) -> list[str]:
        """Every line still held (the dump ends)."""
        out = []
        while self._lines:
            out += self._ready(True)
        return out


FIRST_FRAME_POLL_S = 0.5  # how often the wait for the first frame wakes, s
STOP_POLL_S = 0.5  # longest wait for a frame before the stop flag is looked at again, s
DUMP_FLUSH_S = 0.2  # longest a printed frame waits in the buffer when not on a terminal, s


def _counts_text(counts: dict[str, int]) -> str:
    """Counts by reason as ``bad_mac 3, replay 1`` (``0``: none)."""
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "0"


def cmd_dump(args: argparse.Namespace) -> int:
    codec = Codec()
    formats = signal_formats(codec)
    monitor = RxMonitor(codec, codec.messages)
    observer = None
    if args.secoc_keys:
        try:
            observer = SecOcObserver(codec, load_keys(args.secoc_keys))
        except SecOcKeyError as exc:
            usage_exit("rhonn-bus dump", str(exc))
    labels = SecOcLabels(observer) if observer is not None else None
    # SIGINT and SIGTERM set the flag, whatever the inherited disposition (a dump started in
    # the background by a script has SIGINT ignored): the loop ends within STOP_POLL_S with
    # its summary line
    stop = StopFlag()
    # a capture tool, not a loop node: a receive buffer for a whole run on SocketCAN
    bus = open_bus(args.bus, rcvbuf_bytes=CAPTURE_RCVBUF_BYTES)
    log.info("dumping %s: %s, stops after %g s without a frame (once one came)", args.bus,
             f"{args.count} frames" if args.count > 0 else "every frame", args.timeout)
    print(f"ready dump on {args.bus}", flush=True)  # as the plant's and controller's lines
    # a terminal sees every frame at once; a file or pipe gets its lines in batches (a
    # flush per frame made the dump slower than the loop it watched under emulation)
    out = LineBatcher(sys.stdout, 0.0 if sys.stdout.isatty() else DUMP_FLUSH_S)
    seen = 0
    last_rx = time.monotonic()
    try:
        while (args.count <= 0 or seen < args.count) and not stop():
            # the idle time-out counts from the last frame: before the first one the dump
            # waits for as long as it takes the other nodes to start (Ctrl-C ends it)
            idle_left = args.timeout - (time.monotonic() - last_rx)
            wait = min(idle_left, DUMP_FLUSH_S) if out.pending else idle_left
            msg = bus.recv(min(max(wait, 0.0), STOP_POLL_S) if seen else FIRST_FRAME_POLL_S)
            if msg is None:
                out.flush()
                if not seen or time.monotonic() - last_rx < args.timeout:
                    continue
                print(f"no frame for {args.timeout} s", flush=True)
                break
            seen += 1
            last_rx = time.monotonic()
            decoded = format_frame(monitor.process(msg, last_rx), formats)
            if labels is None:
                out.add(f"{msg.timestamp:.6f} 0x{msg.arbitration_id:03X} "
                        f"{_sec_label(codec, msg)} {decoded}")
                continue
            lines = labels.add(msg, f"{msg.timestamp:.6f} 0x{msg.arbitration_id:03X}", decoded)
            if lines:
                out.add("\n".join(lines))
    except BusDisconnected as exc:
        out.flush()
        print(f"rhonn-bus dump: error: bus lost: {exc}", file=sys.stderr)
        return 1
    finally:
        out.flush()
        bus.shutdown()
        if labels is not None and (rest := labels.flush()):
            print("\n".join(rest), flush=True)
    secoc = ""
    if observer is not None:
        counts = observer.ctrl.rejection_counts() | observer.sync.rejection_counts()
        secoc = f"  SecOC rejections: {_counts_text(counts)}"
    # frames the dump's own socket lost (SocketCAN: the kernel's count); absent elsewhere
    dropped = rx_dropped(bus)
    lost = f"  lost (receive buffer full): {dropped}" if dropped is not None else ""
    print(f"frames: {seen}  rejections: {_counts_text(monitor.rejection_counts())}{secoc}"
          f"{lost}", flush=True)
    return 0


class LineBatcher:
    """Lines to a text stream, flushed when ``every_s`` (wall s) has passed since the last
    flush (0: at once) or when asked."""

    def __init__(self, stream: TextIO, every_s: float) -> None:
        self.stream = stream
        self.every_s = every_s
        self.pending = False
        self._last = time.monotonic()

    def add(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.pending = True
        if time.monotonic() - self._last >= self.every_s:
            self.flush()

    def flush(self) -> None:
        if self.pending:
            self.stream.flush()
            self.pending = False
        self._last = time.monotonic()


def cmd_demo_tx(args: argparse.Namespace) -> int:
    """Publish a plant-like burst every 10 ms: a 0.5 Hz steering sine at 65 km/h."""
    tx = Transmitter(Codec())
    bus = open_bus(args.bus)
    period = 0.01
    start = time.monotonic()
    try:
        for cycle in range(args.cycles):
            t = cycle * period
            swa = 60.0 * math.sin(2 * math.pi * 0.5 * t)
            vx = 65 / 3.6
            frames = {
                "DRIVER_INPUTS": {"SWA": swa, "ACCEL_PEDAL": 0.0, "BRAKE_PEDAL": 0.0,
                                  "STAB_ENABLE": 1},
                "MOTION_SENSORS": {"YAW_RATE": swa / 16 * vx / 2.67 * 0.9, "AX": 0.0,
                                   "AY": math.radians(swa / 16) * vx * vx / 2.67},
                "WHEEL_SPEEDS": {f"WS_{w}": vx / 0.358 for w in ("FL", "FR", "RL", "RR")},
                "VEHICLE_EST": {"VX_EST": vx, "VY_EST": 0.0},
                "SYNC": {"CYCLE": cycle, "SIM_TIME": t},
            }
            for name in PLANT_FRAMES:
                bus.send(tx.message(name, frames[name]))
            delay = start + (cycle + 1) * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    finally:
        bus.shutdown()
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Start a server, a receiver process and a sender process; print what arrives decoded."""
    with BusServer() as server:
        log.info("loopback bus server: %s", server.url)
        expected = args.cycles * len(PLANT_FRAMES)
        rx = subprocess.Popen(
            [sys.executable, "-m", "can_db.cli", "dump", "--bus", server.spec,
             "--count", str(expected), "--timeout", "3"],
            stdout=subprocess.PIPE, text=True, preexec_fn=die_with_parent)
        assert rx.stdout is not None
        if not rx.stdout.readline().startswith("ready"):
            rx.kill()
            print("rhonn-bus demo: error: the receiver failed to start", file=sys.stderr)
            return 1
        tx = subprocess.Popen(
            [sys.executable, "-m", "can_db.cli", "demo-tx", "--bus", server.spec,
             "--cycles", str(args.cycles)], preexec_fn=die_with_parent)
        for line in rx.stdout:
            print("  rx| " + line.rstrip(), flush=True)
        tx_code, rx_code = tx.wait(timeout=30), rx.wait(timeout=30)
    print(f"sender exit {tx_code}, receiver exit {rx_code}; {expected} frames expected")
    return 0 if tx_code == 0 and rx_code == 0 else 1


def format_values(name: str, values: dict,
                  formats: dict[tuple[str, str], tuple[dict[int, str], str]]) -> str:
    """Signals of one frame decoded by cantools (raw enum numbers): value-table names for
    enums, units after physical values."""
    parts = []
    for sig, value in values.items():
        choices, unit = formats.get((name, sig), ({}, ""))
        if choices and float(value).is_integer() and int(value) in choices:
            parts.append(f"{sig}={choices[int(value)]}")
        elif sig == "MAC":  # a 32-bit authenticator: hex digits, as the dump shows it
            parts.append(f"{sig}=0x{int(value):08X}")
        else:
            text = str(value) if isinstance(value, int) else f"{value:g}"
            parts.append(f"{sig}={text}" + (f" {unit}" if unit else ""))
    return ", ".join(parts)


def _need_asammdf(path: str) -> None:
    if path.lower().endswith(".mf4"):
        check_extra(("asammdf",))


def cmd_decode(args: argparse.Namespace) -> int:
    """Print every frame of a log decoded with the DBC (cantools), times from its start."""
    codec = Codec()
    db, formats = codec.database, signal_formats(codec)
    log = read_log(args.log)
    wanted = None
    if args.messages:
        wanted = {db.get_message_by_name(n).frame_id for n in args.messages}
    start = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(log.start_s))
    print(f"# {args.log}: {len(log.frames)} frames; t = s from the log's start, "
          f"{start}.{int(log.start_s % 1 * 1000):03d}Z (wall clock)")
    print(f"# {log.note or 'no time-base note in this log'}")
    shown = 0
    for m in log.frames:
        if wanted is not None and m.arbitration_id not in wanted:
            continue
        if args.count and shown >= args.count:
            break
        shown += 1
        head = f"{m.timestamp:12.6f} 0x{m.arbitration_id:03X}"
        if m.is_error_frame or m.is_remote_frame:
            print(f"{head} {'ERROR FRAME' if m.is_error_frame else 'REMOTE FRAME'}")
            continue
        try:
            if m.is_extended_id:  # the DBC's ids are all 11-bit
                raise KeyError(m.arbitration_id)
            spec = db.get_message_by_frame_id(m.arbitration_id)
        except KeyError:
            print(f"{head} {'(not in the DBC)':<20} data={bytes(m.data).hex(' ')}")
            continue
        try:
            values = spec.decode(bytes(m.data), decode_choices=False)
        except Exception as exc:  # cantools raises several types for a malformed payload
            print(f"{head} {spec.name:<20} cannot decode ({exc}): data={bytes(m.data).hex(' ')}")
            continue
        print(f"{head} {spec.name:<20} {format_values(spec.name, values, formats)}")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    n = convert(args.input, args.output)
    print(f"{args.output}: {n} frames written (start time and time-base note kept)")
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    done = recover(args.target)
    if not done:
        print(f"rhonn-bus recover: error: {args.target}: no bus.mf4.frames to recover",
              file=sys.stderr)
        return 1
    for path in done:
        print(f"{path}: written")
    return 0


def _check_log_name(path: str, what: str) -> None:
    """A log these commands read: .blf, .asc, .mf4, or the frame file an .mf4 writer left
    (a bad argument like any other: one line, exit code 2, not a read error)."""
    p = Path(path)
    if p.suffix.lower() in LOG_SUFFIXES or (
            p.suffix == FRAMES_SUFFIX and Path(p.stem).suffix.lower() == ".mf4"):
        return
    raise UsageError(f"{what} {path}: use a .blf, .asc or .mf4 log (or a .mf4.frames file)")


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="rhonn-bus", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("serve", help="run the loopback bus server on 127.0.0.1")
    p.add_argument("--port", type=number(int, lo=1, hi=65535), default=None,
                   help="TCP port on 127.0.0.1 (default: a free one)")
    p.set_defaults(func=cmd_serve)
    p = sub.add_parser("dump", help="print decoded, validated frames from a bus")
    p.add_argument("--bus", required=True,
                   help="local:NAME | socketcan:IFACE | remote:ws://127.0.0.1:PORT/")
    p.add_argument("--count", type=number(int, lo=0), default=0,
                   help="stop after N frames (0: never)")
    p.add_argument("--timeout", type=number(lo=0.0, lo_open=True, unit="s"), default=5.0,
                   help="stop after this idle time after a frame, s (before the first "
                        "frame it waits until Ctrl-C)")
    p.add_argument("--secoc-keys", default=None,
                   help="verify SecOC frames with these keys: env | ci-test-key | KEYFILE")
    p.set_defaults(func=cmd_dump)
    p = sub.add_parser("demo-tx", help="(demo) publish plant-like frames every 10 ms")
    p.add_argument("--bus", required=True, help="bus spec, as for dump")
    p.add_argument("--cycles", type=number(int, lo=1), default=20,
                   help="10 ms cycles to publish")
    p.set_defaults(func=cmd_demo_tx)
    p = sub.add_parser("demo", help="bus demo: two OS processes over a fresh loopback server")
    p.add_argument("--cycles", type=number(int, lo=1), default=10,
                   help="10 ms cycles to publish")
    p.set_defaults(func=cmd_demo)
    names = [m.name for m in Codec().database.messages]
    p = sub.add_parser("decode", help="print a bus log decoded with the DBC")
    p.add_argument("log", metavar="LOG", help="bus log: .blf, .asc, .mf4 or .mf4.frames")
    p.add_argument("--messages", type=choice_list(names, "message"), default=None,
                   metavar="NAME,...",
                   help="only these messages, comma-separated (e.g. MOTION_SENSORS,SYNC)")
    p.add_argument("--count", type=number(int, lo=0), default=0, metavar="N",
                   help="stop after N printed frames (0: all)")
    p.set_defaults(func=cmd_decode)
    p = sub.add_parser("convert", help="convert a bus log (BLF/ASC/MF4), keeping its time base")
    p.add_argument("input", metavar="IN", help="bus log: .blf, .asc, .mf4 or .mf4.frames")
    p.add_argument("output", metavar="OUT", help="output: .blf, .asc or .mf4")
    p.set_defaults(func=cmd_convert)
    p = sub.add_parser("recover", help="build the MF4 a killed harness left as bus.mf4.frames")
    p.add_argument("target", metavar="RUN_DIR|FILE",
                   help="run directory, bus.mf4 or bus.mf4.frames")
    p.set_defaults(func=cmd_recover)
    add_logging_options(parser)
    for command in sub.choices.values():
        add_logging_options(command, top=False)
    args = parser.parse_args(argv)
    setup_logging("rhonn-bus", *logging_args(args))
    try:
        if getattr(args, "bus", None) is not None:
            check_bus(args.bus, allow_auto=False)
        if args.command == "serve" and args.port is not None:
            check_port_free(args.port)
        if args.command == "decode":
            if not frames_path(args.log).exists():  # else read_log says how to recover it
                check_in_file(args.log, "LOG")
            _check_log_name(args.log, "LOG")
            _need_asammdf(args.log)
        if args.command == "convert":
            check_in_file(args.input, "IN")
            _check_log_name(args.input, "IN")
            check_out_file(args.output, "OUT")
            if Path(args.output).suffix.lower() not in LOG_SUFFIXES:
                raise UsageError(f"OUT {args.output}: use a .blf, .asc or .mf4 output")
            _need_asammdf(args.input)
            _need_asammdf(args.output)
        if args.command == "recover":
            check_extra(("asammdf",))
        return int(args.func(args))
    except UsageError as exc:
        sub.choices[args.command].error(str(exc))  # "rhonn-bus COMMAND: error: ..."
    except (BusDisconnected, BusServerError, LogFileError) as exc:
        print(f"rhonn-bus {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # decode piped into head: the reader has what it wanted
        sys.stderr.close()
        return 0

if __name__ == "__main__":
    raise SystemExit(main())


