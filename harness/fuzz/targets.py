"""Fuzz targets for ``rhonn-bench fuzz``: adversarial case generators and invariant checks.

Every target is a class with ``run(rng, n, findings)``: it draws ``n`` cases from the seeded
numpy generator ``rng``, exercises the code under test and appends a ``Finding`` for every
exception, broken invariant or disagreement with an independent oracle. The decoder and
monitor targets are checked against harness/fuzz/oracle.py (cantools, crcmod, the DBC's
cycle times and the documented receiver rules); their frames are made by that oracle, not by
the codec under test. Values come from ``adversarial()``: mostly plausible ranges,
some 100× beyond, and the special floats below (NaN, ±inf, ±0, ±1e308, subnormals...).
"""

from __future__ import annotations

import math
import random
import traceback
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from can_db.codec import Codec, Decoded, Rejected, Rejection
from can_db.monitor import RxMonitor
from controller.core.interfaces import ControllerInputs, ControllerOutputs, QpStatus
from controller.core.params import VehicleParams, load_vehicle_params
from controller.registry import make_controller
from controller.runtime.envelope import SafetyEnvelope, load_envelope_config
from controller.runtime.node import MONITORED, ControllerNode, Mode
from harness.fuzz.oracle import (
    COUNTER_FAULT_LIMIT,
    FrameOracle,
    MessageInfo,
    MonitorOracle,
    compare,
)

NAN, INF = math.nan, math.inf
SPECIALS = np.array([NAN, INF, -INF, 0.0, -0.0, 1e308, -1e308, 5e-324, -5e-324, 1e-300,
                     1e300, 2.0 ** 53, -(2.0 ** 53), 1e9, -1e9, 1.0, -1.0])
FINITE_SPECIALS = SPECIALS[np.isfinite(SPECIALS)]
MAX_FINDINGS_PER_TARGET = 20   # per kind; keeps the report readable (counts stay complete)
QP_STATUSES = {int(s) for s in QpStatus}


@dataclass
class Finding:
    """One exception, broken invariant or oracle mismatch, with what reproduces it."""

    target: str
    kind: str        # "exception" | "invariant" | an oracle mismatch ("missed:bad_crc", ...)
    message: str
    case: str        # repr of the input (truncated)
    traceback: str = ""


class Findings:
    """Counts every finding, by target and by kind, and the case number at which each kind
    first appeared; keeps the first few per target and kind in full."""

    def __init__(self) -> None:
        self.items: list[Finding] = []
        self.counts: dict[str, int] = {}
        self.by_kind: dict[str, dict[str, int]] = {}
        self.first_at: dict[str, dict[str, int]] = {}  # kind -> cases run when first seen
        self.cases: dict[str, int] = {}                # cases run so far, per target
        self._kept: dict[tuple[str, str], int] = {}

    def tick(self, target: str) -> None:
        """One more case of ``target`` (for ``first_at``)."""
        self.cases[target] = self.cases.get(target, 0) + 1

    def add(self, target: str, kind: str, message: str, case: Any, exc: bool = False
            ) -> None:
        self.counts[target] = self.counts.get(target, 0) + 1
        kinds = self.by_kind.setdefault(target, {})
        kinds[kind] = kinds.get(kind, 0) + 1
        self.first_at.setdefault(target, {}).setdefault(kind, self.cases.get(target, 0))
        n = self._kept.get((target, kind), 0)
        if n < MAX_FINDINGS_PER_TARGET:
            self._kept[(target, kind)] = n + 1
            self.items.append(Finding(target, kind, message, repr(case)[:600],
                                      traceback.format_exc() if exc else ""))


def adversarial(rng: np.random.Generator, shape: int | tuple[int, ...], lo: float, hi: float,
                p_wide: float, p_special: float, finite_only: bool = False) -> np.ndarray:
    """Values in [lo, hi], with probability p_wide 100× wider, p_special a special float."""
    x = rng.uniform(lo, hi, shape)
    u = rng.random(shape)
    wide = u < p_wide
    x[wide] = rng.uniform(100.0 * lo - 1.0, 100.0 * hi + 1.0, int(wide.sum()))
    spec = u > 1.0 - p_special
    pool = FINITE_SPECIALS if finite_only else SPECIALS
    x[spec] = pool[rng.integers(0, len(pool), int(spec.sum()))]
    return x


def motor_limit(params: VehicleParams, w: float) -> float:
    """Independent oracle of |T| ≤ min(T_peak, P_peak/|ω|) N·m; non-finite ω → T_peak."""
    if not math.isfinite(w) or w == 0.0:
        return params.peak_torque_nm
    return min(params.peak_torque_nm, params.peak_power_w / abs(w))


# ----------------------------------------------------------------------- decoder
NO_FLAGS = (False, False, False, False)  # is_extended_id, is_remote, is_error, is_fd


def _reason(res: Rejected) -> str:
    return str(res.reason.value) if isinstance(res.reason, Rejection) else repr(res.reason)


class FrameMaker:
    """Frames for the oracle-checked targets, all made by the oracle (cantools encodes,
    crcmod protects), never by the codec under test."""

    def __init__(self, oracle: FrameOracle) -> None:
        self.oracle = oracle
        self.infos = list(oracle.messages.values())
        self.ranged = {info.name: [s for s in info.signals
                                   if s.raw_lo < s.valid_lo or s.valid_hi < s.raw_hi]
                       for info in self.infos}
        self.ranged_infos = [info for info in self.infos if self.ranged[info.name]]

    def raws(self, r: random.Random, info: MessageInfo, boundary: bool = False
             ) -> dict[str, int]:
        """In-range raw values; ``boundary``: each at a limit or one step inside."""
        if not boundary:
            return {s.name: r.randint(s.valid_lo, s.valid_hi) for s in info.signals}
        return {s.name: r.choice((s.valid_lo, s.valid_hi, min(s.valid_lo + 1, s.valid_hi),
                                  max(s.valid_hi - 1, s.valid_lo))) for s in info.signals}

    def valid(self, r: random.Random, info: MessageInfo, counter: int | None = None,
              boundary: bool = False) -> bytes:
        """A correct frame of ``info`` (random counter unless given)."""
        c = r.randrange(16) if counter is None else counter
        return self.oracle.encode(info.name, self.raws(r, info, boundary), c)

    def out_of_range(self, r: random.Random, info: MessageInfo, counter: int) -> bytes | None:
        """A correctly protected frame with one raw value outside the DBC limits (None when
        every signal of ``info`` spans its whole raw range)."""
        ranged = self.ranged[info.name]
        if not ranged:
            return None
        sig = r.choice(ranged)
        raw = self.raws(r, info)
        below = sig.raw_lo < sig.valid_lo and (sig.valid_hi == sig.raw_hi or r.random() < 0.5)
        if below:
            raw[sig.name] = r.choice((sig.valid_lo - 1, r.randint(sig.raw_lo, sig.valid_lo - 1)))
        else:
            raw[sig.name] = r.choice((sig.valid_hi + 1, r.randint(sig.valid_hi + 1, sig.raw_hi)))
        return self.oracle.encode(info.name, raw, counter)

    @staticmethod
    def flip_bit(data: bytes, bit: int) -> bytes:
        """``data`` with bit ``bit`` (0 = LSB of byte 0) flipped (CRC not recomputed)."""
        out = bytearray(data)
        out[bit // 8] ^= 1 << (bit % 8)
        return bytes(out)

    @staticmethod
    def flip(r: random.Random, data: bytes, bits: int) -> bytes:
        """``data`` with ``bits`` random bit flips (CRC not recomputed)."""
        out = bytearray(data)
        for _ in range(bits):
            i = r.randrange(8 * len(out))
            out[i // 8] ^= 1 << (i % 8)
        return bytes(out)

    def wrong_crc(self, r: random.Random, info: MessageInfo, data: bytes) -> bytes:
        """``data`` with its CRC field changed (nothing else)."""
        first, end = info.crc_bytes
        out = bytearray(data)
        k = r.randrange(first, end)
        out[k] ^= r.randint(1, 255)
        return bytes(out)

    @staticmethod
    def wrong_length(r: random.Random, data: bytes) -> bytes:
        """``data`` cut short or padded with random bytes (0..64 bytes, never its length)."""
        n = r.choice((r.randrange(len(data)), r.randint(len(data) + 1, 64)))
        return (data + bytes(r.randrange(256) for _ in range(64)))[:n]


class DecoderTarget:
    """Codec.decode against the frame oracle (harness/fuzz/oracle.py). Cases: correct frames
    (cantools + crcmod), at the range limits, with bit flips, a wrong CRC field, a raw value
    out of range (CRC correct), the wrong length, a frame sent on another message's ID,
    random bytes under a correct CRC, non-data flags, and anything at all. Invariants: never
    raises; returns Decoded or Rejected; the verdict and reason equal the oracle's; an
    accepted frame has exactly cantools' values and counter."""

    name = "decoder"

    def __init__(self, codec: Codec, oracle: FrameOracle | None = None) -> None:
        self.codec = codec
        self.oracle = oracle if oracle is not None else FrameOracle()
        self.make = FrameMaker(self.oracle)
        self.ids = sorted(self.oracle.by_id)

    def case(self, r: random.Random) -> tuple[int, bytes, tuple[bool, bool, bool, bool]]:
        """One frame: (ID, payload, flags)."""
        make, u = self.make, r.random()
        info = r.choice(make.infos)
        fid = info.frame_id
        if u < 0.25:
            return fid, make.valid(r, info), NO_FLAGS
        if u < 0.33:
            return fid, make.valid(r, info, boundary=True), NO_FLAGS
        if u < 0.43:
            return fid, make.flip(r, make.valid(r, info), r.randint(1, 3)), NO_FLAGS
        if u < 0.51:
            return fid, make.wrong_crc(r, info, make.valid(r, info)), NO_FLAGS
        if u < 0.61:
            info = r.choice(make.ranged_infos)
            return info.frame_id, make.out_of_range(r, info, r.randrange(16)) or b"", NO_FLAGS
        if u < 0.66:
            return fid, make.wrong_length(r, make.valid(r, info)), NO_FLAGS
        if u < 0.71:
            other = r.choice([i for i in make.infos if i.length == info.length])
            return other.frame_id, make.valid(r, info), NO_FLAGS
        if u < 0.79:
            raw = bytes(r.randrange(256) for _ in range(info.length))
            return fid, self.oracle.protect(info, raw), NO_FLAGS
        if u < 0.83:
            flags = [False] * 4
            flags[r.randrange(4)] = True
            return fid, make.valid(r, info), (flags[0], flags[1], flags[2], flags[3])
        w = r.random()
        fid = r.choice(self.ids) if w < 0.5 else (r.randrange(0x800) if w < 0.8
                                                  else r.randrange(1 << 29))
        n = 8 if r.random() < 0.85 else r.randint(0, 64)
        flags4 = tuple(r.random() < 0.03 for _ in range(4))
        return fid, bytes(r.randrange(256) for _ in range(n)), flags4  # type: ignore[return-value]

    def run(self, rng: np.random.Generator, n: int, findings: Findings) -> None:
        r = random.Random(int(rng.integers(0, 1 << 63)))
        for _ in range(n):
            fid, data, flags = self.case(r)
            findings.tick(self.name)
            self.check(fid, data, flags, findings)

    def check(self, fid: int, data: bytes, flags: tuple[bool, bool, bool, bool],
              findings: Findings) -> None:
        """Decode one frame and compare with the oracle."""
        ext, rtr, err, fd = flags
        case = (hex(fid), data.hex(), ext, rtr, err, fd)
        expected = self.oracle.verdict(fid, data, ext, rtr, err, fd)
        try:
            res = self.codec.decode(fid, data, is_extended_id=ext, is_remote_frame=rtr,
                                    is_error_frame=err, is_fd=fd)
        except Exception as exc:
            findings.add(self.name, "exception", repr(exc), case, exc=True)
            return
        if isinstance(res, Rejected):
            if not isinstance(res.reason, Rejection):
                findings.add(self.name, "invariant", "bad rejection reason", case)
            kind = compare(expected, False, _reason(res), False)
        elif isinstance(res, Decoded):
            kind = compare(expected, True, None, False, res.name, res.values, res.counter)
        else:
            findings.add(self.name, "invariant", f"returned {type(res)}", case)
            return
        if kind is not None:
            findings.add(self.name, kind, f"oracle {expected.reason or 'accepts'}, codec "
                         f"{_reason(res) if isinstance(res, Rejected) else 'accepts'}", case)


# ----------------------------------------------------------------------- monitor
# The plant's receiver set (PlantNode in plant_sim/node.py): the controller's frames, CRC8
# profile.
PLANT_MONITORED = ("WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS")
UNMONITORED = "SYNC_AUTH"  # a known message no receiver here monitors (must be ignored)


@dataclass
class _Sender:
    counter: int = 0
    silent: int = 0  # bus cycles of silence left


class MonitorTarget:
    """RxMonitor against the monitor oracle (harness/fuzz/oracle.py) over a simulated bus:
    every cycle (≈ 10 ms, jittered) each message sends one frame, made by the oracle, with
    counter behaviour (mostly +1; repeats, +2, any jump), damage (bit flips, wrong CRC field,
    out-of-range raw value, wrong length, non-data flags, a foreign ID), silence gaps of
    1..8 cycles (the counter held or running on), and a clock that now and then jumps, runs
    back or is NaN/±inf. After every cycle each stream's ``valid`` is probed at a random
    instant. Invariants: never raises; each ``process`` verdict (accepted, ignored, reason)
    and each ``valid`` equal the oracle's (timeout = TIMEOUT_CYCLES × the DBC cycle time);
    accepted frames carry cantools' values; jumps are counted; every frame is accounted for
    exactly once in the monitor's counts."""

    name = "monitor"

    def __init__(self, codec: Codec, oracle: FrameOracle | None = None,
                 monitored: tuple[str, ...] | None = None) -> None:
        self.codec = codec
        self.oracle = oracle if oracle is not None else FrameOracle()
        self.make = FrameMaker(self.oracle)
        self.monitored = monitored if monitored is not None else (*MONITORED,
                                                                  *PLANT_MONITORED)
        self.names = [*self.monitored, UNMONITORED]

    def run(self, rng: np.random.Generator, n: int, findings: Findings) -> None:
        r = random.Random(int(rng.integers(0, 1 << 63)))
        mon = RxMonitor(self.codec, self.monitored)
        orc = MonitorOracle(self.oracle, self.monitored)
        senders = {name: _Sender(r.randrange(16)) for name in self.names}
        t, done, processed = 0.0, 0, 0
        while done < n:
            for name in self.names:
                if done >= n:
                    break
                frame = self._frame(r, name, senders[name])
                if frame is None:
                    continue
                tf = t + r.uniform(0.0, 0.002) if r.random() > 0.002 else r.choice(SPECIAL_TIMES)
                done += 1
                findings.tick(self.name)
                try:
                    self._one(mon, orc, frame, tf, findings)
                except Exception as exc:
                    findings.add(self.name, "exception", repr(exc), (frame, tf), exc=True)
                    mon = RxMonitor(self.codec, self.monitored)  # both start afresh
                    orc = MonitorOracle(self.oracle, self.monitored)
                    processed = 0
                    continue
                processed += 1
                self._accounting(mon, processed, (frame, tf), findings)
            tp = t + r.uniform(0.0, 0.0099) if r.random() > 0.002 else r.choice(SPECIAL_TIMES)
            try:
                self._probe(mon, orc, tp, findings)
            except Exception as exc:
                findings.add(self.name, "exception", repr(exc), ("valid", tp), exc=True)
                mon = RxMonitor(self.codec, self.monitored)
                orc = MonitorOracle(self.oracle, self.monitored)
                processed = 0
            u = r.random()  # the clock: one cycle, sometimes a jump forward or back
            t += 0.01 + r.uniform(-0.001, 0.001) if u < 0.99 else (
                r.uniform(0.0, 2.0) if u < 0.997 else -r.uniform(0.0, 1.0))

    def _frame(self, r: random.Random, name: str, s: _Sender
               ) -> tuple[int, bytes, tuple[bool, bool, bool, bool]] | None:
        """This cycle's frame of ``name`` (None: silent)."""
        if s.silent > 0:
            s.silent -= 1
            if r.random() < 0.5:   # frames lost on the wire: the sender's counter runs on
                s.counter = (s.counter + 1) % 16
            return None
        if r.random() < 0.02:
            s.silent = r.randint(1, 8)
            return None
        u = r.random()
        step = 1 if u < 0.86 else (0 if u < 0.91 else (2 if u < 0.95 else r.randint(3, 15)))
        s.counter = (s.counter + step) % 16
        info = self.oracle.messages[name]
        make = self.make
        data = make.valid(r, info, s.counter)
        v = r.random()
        fid, flags = info.frame_id, NO_FLAGS
        if v < 0.03:
            data = make.flip(r, data, r.randint(1, 3))
        elif v < 0.05:
            data = make.wrong_crc(r, info, data)
        elif v < 0.07:
            data = make.out_of_range(r, info, s.counter) or data
        elif v < 0.08:
            data = make.wrong_length(r, data)
        elif v < 0.085:
            fl = [False] * 4
            fl[r.randrange(4)] = True
            flags = (fl[0], fl[1], fl[2], fl[3])
        elif v < 0.09:
            fid = r.randrange(0x800)
        return fid, data, flags

    def _one(self, mon: RxMonitor, orc: MonitorOracle,
             frame: tuple[int, bytes, tuple[bool, bool, bool, bool]], now: float,
             findings: Findings) -> None:
        """Process one frame in the monitor and the oracle; record any disagreement."""
        fid, data, (ext, rtr, err, fd) = frame
        msg = can.Message(arbitration_id=fid, data=data, is_extended_id=ext,
                          is_remote_frame=rtr, is_error_frame=err, is_fd=fd, check=False)
        expected = orc.process(fid, data, now, ext, rtr, err, fd)
        jumps = mon.counts.get(Rejection.COUNTER_JUMP.value, 0)
        res = mon.process(msg, now)
        if res is None:
            kind = compare(expected, False, None, True)
        elif isinstance(res, Rejected):
            kind = compare(expected, False, _reason(res), False)
        else:
            kind = compare(expected, True, None, False, res.name, res.values, res.counter)
            if kind is None and expected.jump and \
                    mon.counts.get(Rejection.COUNTER_JUMP.value, 0) != jumps + 1:
                kind = "uncounted:counter_jump"
        if kind is not None:
            got = "ignores" if res is None else (
                _reason(res) if isinstance(res, Rejected) else "accepts")
            findings.add(self.name, kind, f"oracle {expected.reason or 'accepts'}, monitor "
                         f"{got}", (hex(fid), data.hex(), ext, rtr, err, fd, now))

    def _probe(self, mon: RxMonitor, orc: MonitorOracle, now: float,
               findings: Findings) -> None:
        """Compare every monitored stream's ``valid`` at ``now`` with the oracle's."""
        for name in self.monitored:
            expected = orc.valid(name, now)
            got = mon.valid(name, now)
            if not isinstance(got, bool):
                findings.add(self.name, "invariant", "valid() not a bool", (name, now))
            elif expected is not None and got != expected:
                s = orc.streams[name]
                kind = ("false_invalid" if expected else
                        "missed:never_received" if s.last_rx_s is None else
                        "missed:counter_fault" if s.level >= COUNTER_FAULT_LIMIT else
                        "missed:timeout")
                findings.add(self.name, kind, f"{name} valid={got} at {now}, oracle "
                             f"{expected} (last accepted {s.last_rx_s}, timeout "
                             f"{s.timeout_s})", (name, now))

    def _accounting(self, mon: RxMonitor, processed: int, case: Any,
                    findings: Findings) -> None:
        """Every processed frame counted exactly once (accepted, ignored or rejected)."""
        counts = mon.counts
        rejected = sum(v for k, v in counts.items() if k != Rejection.TIMEOUT.value)
        accepted = sum(s.accepted for s in mon.streams.values())
        if rejected - counts.get(Rejection.COUNTER_JUMP.value, 0) + accepted + mon.ignored \
                != processed:
            findings.add(self.name, "invariant", "a frame was not accounted for", case)


SPECIAL_TIMES = (NAN, INF, -INF, 1e308, -1e308, 0.0, -0.0)


# -------------------------------------------------------------------- controllers
FIELDS = (  # name, plausible range
    ("swa_rad", -8.0, 8.0), ("accel_pedal", 0.0, 1.0), ("brake_pedal", 0.0, 1.0),
    ("yaw_rate", -2.0, 2.0), ("ax", -15.0, 15.0), ("ay", -15.0, 15.0),
    ("vx", -10.0, 60.0), ("vy", -10.0, 10.0))
MODES = ((0.0, 0.0, True), (0.1, 0.05, True), (0.05, 0.1, False))  # p_wide, p_special, finite


class ControllerTarget:
    """``step()`` and ``allocate_only()`` of one registry controller on sequences of
    adversarial inputs (reset between sequences). Invariants: never raises; every float
    output finite (the model prediction may be NaN by design); |T_i| within the motor
    limit at ω_i; ΔM = T2 + T4 − T1 − T3; the commanded ΔM is 0 when sensors are invalid or
    stabilisation is disabled; every wheel moves at most the motor torque rate × 10 ms from
    the controller's previous answer unless its motor limit cut it (the passive car: no
    slew); a valid QP status; and the output envelope holds on the sequence (it zeroes the
    applied ΔM on the frame whenever the node demands it)."""

    def __init__(self, name: str, params: VehicleParams) -> None:
        self.name = f"controller:{name}"
        self.ctrl = make_controller(name)
        self.p = params
        self.env = SafetyEnvelope(load_envelope_config(), params.peak_torque_nm,
                                  params.peak_power_w, 0.01)
        self.inp = ControllerInputs()
        self.prev = np.zeros(4)
        self.env_out = np.zeros(4)
        self.last_cmd = np.zeros(4)      # the controller's previous answer, N·m
        self.slew = 0.0 if name == "passive" else params.torque_rate_nm_per_s * 0.01

    def reset(self) -> None:
        """A cold controller and the checks' memory of it (previous output, last answer)."""
        self.ctrl.reset()
        self.prev[:] = 0.0
        self.last_cmd[:] = 0.0

    def run(self, rng: np.random.Generator, n: int, findings: Findings) -> None:
        inp = self.inp
        cols = {}
        mode_of = rng.integers(0, len(MODES), n)
        new_seq = rng.random(n) < 1.0 / 150.0
        for fname, lo, hi in FIELDS:
            cols[fname] = {m: adversarial(rng, n, lo, hi, *MODES[m]) for m in range(3)}
        ws = {m: adversarial(rng, (n, 4), -20.0, 200.0, *MODES[m]) for m in range(3)}
        flags = rng.random((n, 3))
        mode = int(mode_of[0])
        for k in range(n):
            if k == 0 or new_seq[k]:
                self.reset()
                mode = int(mode_of[k])
            for fname, _, _ in FIELDS:
                setattr(inp, fname, float(cols[fname][mode][k]))
            inp.wheel_speeds[:] = ws[mode][k]
            inp.stab_enable = bool(flags[k, 0] < 0.9)
            inp.sensors_valid = bool(flags[k, 1] < 0.9)
            use_step = bool(flags[k, 2] < 0.5)
            try:
                out = self.ctrl.step(inp) if use_step else self.ctrl.allocate_only(inp)
            except Exception as exc:
                findings.add(self.name, "exception", repr(exc), (use_step, inp), exc=True)
                self.ctrl.reset()
                self.last_cmd[:] = 0.0
                continue
            problem = self._check(out, inp, use_step)
            if problem:
                findings.add(self.name, "invariant", problem, (use_step, inp, out))

    def _check(self, out: ControllerOutputs, inp: ControllerInputs, stepped: bool = True
               ) -> str | None:
        t = out.torques
        if t.shape != (4,) or not np.all(np.isfinite(t)):
            return f"torques {t}"
        for i in range(4):
            if abs(t[i]) > motor_limit(self.p, float(inp.wheel_speeds[i])) + 1e-6:
                return f"wheel {i}: {t[i]} N·m beyond the motor limit"
        for v in (out.total_torque, out.delta_m, out.yaw_rate_ref, out.vy_ref, out.beta_ref):
            if not math.isfinite(v):
                return "non-finite scalar output"
        dm = float(t[1] + t[3] - t[0] - t[2])
        if abs(dm - out.delta_m) > 1e-6 * (1.0 + abs(dm)):
            return f"delta_m {out.delta_m} != torques' {dm}"
        # the MPC step's command (allocate_only allocates ΔM = 0 then and keeps the held one)
        held = float(getattr(self.ctrl, "dm_held", 0.0)) if stepped else 0.0
        if (not inp.sensors_valid or not inp.stab_enable) and held != 0.0:
            return f"commanded delta_m {held} while invalid/disabled"
        for i in range(4):
            lim = motor_limit(self.p, float(inp.wheel_speeds[i]))
            if self.slew > 0.0 and abs(t[i] - self.last_cmd[i]) > self.slew + 1e-3 \
                    and abs(abs(t[i]) - lim) > 1e-3:   # float32 cores: rounding
                return f"wheel {i}: moved {t[i] - self.last_cmd[i]} N·m in one cycle"
        np.copyto(self.last_cmd, t)
        if int(out.qp_status) not in QP_STATUSES or out.qp_iterations < 0:
            return "bad QP status"
        zero_dm = not (inp.sensors_valid and inp.stab_enable)
        self.env.apply(t, inp.wheel_speeds, zero_dm, self.prev, self.env_out)
        e, pv = self.env_out, self.prev
        if not np.all(np.isfinite(e)) or self.env.counters.conflicts:
            return "envelope output non-finite or in conflict"
        for i in range(4):
            if abs(e[i]) > motor_limit(self.p, float(inp.wheel_speeds[i])) + 1e-9 \
                    or abs(e[i] - pv[i]) > self.env.d_wheel + 1e-6:
                return f"envelope broken at wheel {i}"
        if abs((e[1] + e[3] - e[0] - e[2]) - (pv[1] + pv[3] - pv[0] - pv[2])) \
                > self.env.d_dm + 1e-6 or (zero_dm and (e[0] != e[1] or e[2] != e[3])):
            return "envelope ΔM broken"
        np.copyto(self.prev, e)
        return None


# --------------------------------------------------------------------------- node
class NodeTarget:
    """The whole ControllerNode (monitor → controller → envelope → frames) on adversarial
    plant bursts: random physical values (saturated by the encoder), dropped and damaged
    frames, foreign frames, counter misbehaviour, SYNC time jumps and plant restarts.
    Invariants: never raises; every answer is 3 valid frames echoing the SYNC cycle; wire
    torques within the motor limits at the node's wheel speeds, per-wheel and ΔM rate limits
    (+ the 0.5 N·m wire resolution), axle-symmetric in DEGRADED_SENSORS/STANDBY; the core
    never raised (node.controller_exceptions stays 0)."""

    PLANT = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST")

    def __init__(self, controller: str, params: VehicleParams, codec: Codec) -> None:
        self.name = f"node:{controller}"
        self.controller = controller
        self.p = params
        self.codec = codec

    def run(self, rng: np.random.Generator, n: int, findings: Findings) -> None:
        codec = self.codec
        node = ControllerNode(make_controller(self.controller), self.p, codec=codec)
        counters = dict.fromkeys((*self.PLANT, "SYNC"), 0)
        cycle, t = 0, 0.0
        prev = np.zeros(4)
        wild = rng.random(n) < 0.2
        for k in range(n):
            frames: list[can.Message] = []
            for name in self.PLANT:
                if rng.random() < 0.03:
                    continue  # dropped
                spec = codec.messages[name]
                values = {s.name: float(adversarial(rng, 1, s.minimum, s.maximum,
                                                    0.2 if wild[k] else 0.0,
                                                    0.1 if wild[k] else 0.0)[0])
                          for s in spec.signals}
                if name == "DRIVER_INPUTS":
                    values["STAB_ENABLE"] = float(rng.random() < 0.9)
                c = counters[name] = (counters[name] + (1 if rng.random() < 0.97 else
                                                        int(rng.integers(0, 16)))) % 16
                msg = codec.message(name, values, c)
                if rng.random() < 0.02:
                    data = bytearray(msg.data)
                    data[int(rng.integers(0, 8))] ^= 1 << int(rng.integers(0, 8))
                    msg.data = data
                frames.append(msg)
            if rng.random() < 0.02:
                frames.insert(int(rng.integers(0, len(frames) + 1)), can.Message(
                    arbitration_id=int(rng.integers(0, 0x800)), is_extended_id=False,
                    data=rng.integers(0, 256, 8, dtype=np.uint8).tobytes()))
            u = rng.random()
            cycle = cycle + 1 if u < 0.98 else int(rng.integers(0, 1 << 24))
            t = t + 0.01 if u < 0.97 else (0.0 if u < 0.985 else t + float(rng.uniform(0, 2)))
            counters["SYNC"] = (counters["SYNC"] + 1) % 16
            frames.append(codec.message("SYNC", {"CYCLE": float(cycle % (1 << 24)),
                                                 "SIM_TIME": t}, counters["SYNC"]))
            answer = None
            try:
                for msg in frames:
                    out = node.on_frame_lockstep(msg)
                    answer = out if out is not None else answer
            except Exception as exc:
                findings.add(self.name, "exception", repr(exc),
                             [bytes(m.data).hex() for m in frames], exc=True)
                node = ControllerNode(make_controller(self.controller), self.p, codec=codec)
                prev[:] = 0.0
                continue
            if answer is None:
                continue
            problem = self._check(node, answer, cycle, prev)
            if problem:
                findings.add(self.name, "invariant", problem,
                             [bytes(m.data).hex() for m in frames])

    def _check(self, node: ControllerNode, answer: list[can.Message], cycle: int,
               prev: np.ndarray) -> str | None:
        if node.controller_exceptions:
            node.controller_exceptions = 0
            return "the controller core raised (node FAULT mode)"
        dec = [self.codec.decode_message(m) for m in answer]
        if len(dec) != 3 or not all(isinstance(d, Decoded) for d in dec):
            return "answer frames do not decode"
        by = {d.name: d for d in dec}  # type: ignore[union-attr]
        v = by["WHEEL_TORQUE_CMD"].values
        if v["ECHO_CYCLE"] != node.record.cycle % 256:
            return "wrong echo"
        t = np.array([v["TQ_FL"], v["TQ_FR"], v["TQ_RL"], v["TQ_RR"]])
        ws = node.inputs.wheel_speeds
        for i in range(4):
            if abs(t[i]) > motor_limit(self.p, float(ws[i])) + 1e-9:
                return f"wheel {i}: {t[i]} N·m beyond the motor limit at {ws[i]} rad/s"
            if abs(t[i] - prev[i]) > node.envelope.d_wheel + 0.5:
                return f"wheel {i}: rate {t[i] - prev[i]} N·m per cycle"
        if abs((t[1] + t[3] - t[0] - t[2]) - (prev[1] + prev[3] - prev[0] - prev[2])) \
                > node.envelope.d_dm + 2.0:
            return "ΔM rate"
        if node.mode in (Mode.DEGRADED_SENSORS, Mode.STANDBY) and \
                (t[0] != t[1] or t[2] != t[3]):
            return f"yaw moment in {node.mode.name}: {t}"
        np.copyto(prev, t)
        return None


def default_params() -> VehicleParams:
    """The controller's vehicle parameters (motor limits for the oracles)."""
    return load_vehicle_params()
