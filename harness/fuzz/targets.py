"""Fuzz targets for ``rhonn-bench fuzz``: adversarial case generators and invariant checks.

Every target is a class with ``run(rng, n, findings)``: it draws ``n`` cases from the seeded
numpy generator ``rng``, exercises the code under test and appends a ``Finding`` for every
exception or broken invariant. Values come from ``adversarial()``: mostly plausible ranges,
some 100× beyond, and the special floats below (NaN, ±inf, ±0, ±1e308, subnormals...).
"""

from __future__ import annotations

import math
import traceback
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from can_db.codec import Codec, Decoded, Rejected, Rejection
from can_db.crc import frame_crc
from can_db.monitor import RxMonitor
from controller.core.interfaces import ControllerInputs, ControllerOutputs, QpStatus
from controller.core.params import VehicleParams, load_vehicle_params
from controller.registry import make_controller
from controller.runtime.envelope import SafetyEnvelope, load_envelope_config
from controller.runtime.node import MONITORED, ControllerNode, Mode

NAN, INF = math.nan, math.inf
SPECIALS = np.array([NAN, INF, -INF, 0.0, -0.0, 1e308, -1e308, 5e-324, -5e-324, 1e-300,
                     1e300, 2.0 ** 53, -(2.0 ** 53), 1e9, -1e9, 1.0, -1.0])
FINITE_SPECIALS = SPECIALS[np.isfinite(SPECIALS)]
MAX_FINDINGS_PER_TARGET = 20   # per kind; keeps the report readable (counts stay complete)
QP_STATUSES = {int(s) for s in QpStatus}


@dataclass
class Finding:
    """One exception or broken invariant, with what is needed to reproduce it."""

    target: str
    kind: str        # "exception" | "invariant"
    message: str
    case: str        # repr of the input (truncated)
    traceback: str = ""


class Findings:
    """Counts every finding; keeps the first few per target and kind in full."""

    def __init__(self) -> None:
        self.items: list[Finding] = []
        self.counts: dict[str, int] = {}
        self._kept: dict[tuple[str, str], int] = {}

    def add(self, target: str, kind: str, message: str, case: Any, exc: bool = False
            ) -> None:
        self.counts[target] = self.counts.get(target, 0) + 1
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
class DecoderTarget:
    """Codec.decode on arbitrary IDs, lengths, bytes and flags (half with a valid CRC so the
    signal decoder is reached). Invariants: returns Decoded or Rejected; a Decoded frame
    has finite values within the DBC limits and re-encodes to the same values."""

    name = "decoder"

    def __init__(self, codec: Codec) -> None:
        self.codec = codec
        self.ids = np.array(sorted(codec.by_id), dtype=np.int64)

    def run(self, rng: np.random.Generator, n: int, findings: Findings) -> None:
        codec = self.codec
        kind = rng.random(n)
        known = self.ids[rng.integers(0, len(self.ids), n)]
        ids = np.where(kind < 0.6, known, np.where(kind < 0.8, rng.integers(0, 0x800, n),
                                                   rng.integers(0, 1 << 29, n)))
        lengths = np.where(rng.random(n) < 0.85, 8, rng.integers(0, 65, n))
        payload = rng.integers(0, 256, (n, 64), dtype=np.uint8)
        fix_crc = rng.random(n) < 0.5
        flags = rng.random((n, 4)) < 0.03
        for k in range(n):
            fid, ln = int(ids[k]), int(lengths[k])
            data = bytearray(payload[k, :ln].tobytes())
            if fix_crc[k] and ln:
                data[0] = frame_crc(fid, data)
            ext, rtr, err, fd = (bool(v) for v in flags[k])
            case = (hex(fid), bytes(data).hex(), ext, rtr, err, fd)
            try:
                res = codec.decode(fid, bytes(data), is_extended_id=ext, is_remote_frame=rtr,
                                   is_error_frame=err, is_fd=fd)
            except Exception as exc:
                findings.add(self.name, "exception", repr(exc), case, exc=True)
                continue
            if isinstance(res, Rejected):
                if not isinstance(res.reason, Rejection):
                    findings.add(self.name, "invariant", "bad rejection reason", case)
                continue
            if not isinstance(res, Decoded):
                findings.add(self.name, "invariant", f"returned {type(res)}", case)
                continue
            self._check_decoded(res, fid, case, findings)

    def _check_decoded(self, res: Decoded, fid: int, case: Any, findings: Findings) -> None:
        spec = self.codec.messages.get(res.name)
        if spec is None or spec.frame_id != fid or not 0 <= res.counter < 16:
            findings.add(self.name, "invariant", "decoded under a wrong name/ID/counter", case)
            return
        for sig in spec.signals:
            v = res.values.get(sig.name)
            if v is None or not math.isfinite(v) or not (
                    sig.minimum - 1e-9 <= v <= sig.maximum + 1e-9):
                findings.add(self.name, "invariant", f"{sig.name} = {v} out of range", case)
                return
        try:
            again = self.codec.decode(fid, self.codec.encode(res.name, res.values,
                                                              res.counter)[0])
        except Exception as exc:
            findings.add(self.name, "exception", f"re-encode: {exc!r}", case, exc=True)
            return
        if not isinstance(again, Decoded) or again.values != res.values:
            findings.add(self.name, "invariant", "decode(encode(x)) != x", case)


# ----------------------------------------------------------------------- monitor
class MonitorTarget:
    """RxMonitor.process on streams of frames with counter sequences (in order, jumps,
    frozen, random), corrupted frames, and arbitrary times (backwards, jumps, NaN, ±inf).
    Invariants: never raises; every frame is accounted for exactly once (accepted, ignored or
    rejected); fault levels stay in range; ``valid`` is a bool, False for a stream never
    accepted or counter-faulted, and for finite times False once the timeout has passed."""

    name = "monitor"

    def __init__(self, codec: Codec) -> None:
        self.codec = codec
        self.names = [*MONITORED, "WHEEL_TORQUE_CMD"]  # one message the node ignores

    def run(self, rng: np.random.Generator, n: int, findings: Findings) -> None:
        codec = self.codec
        mon = RxMonitor(codec, MONITORED)
        counters = dict.fromkeys(self.names, 0)
        t = 0.0
        processed = 0
        pick = rng.integers(0, len(self.names), n)
        policy = rng.random(n)
        tkind = rng.random(n)
        dts = rng.uniform(0.0, 0.012, n)
        vals = rng.uniform(-1.0, 1.0, (n, 8))
        corrupt = rng.random(n)
        for k in range(n):
            name = self.names[int(pick[k])]
            # alive counter: mostly +1, else a jump, a repeat or anything
            p = policy[k]
            c = counters[name]
            c = (c + 1) % 16 if p < 0.85 else (c if p < 0.9 else int(rng.integers(0, 16)))
            counters[name] = c
            spec = codec.messages[name]
            values = {s.name: float(s.minimum + (vals[k, i % 8] + 1.0) * 0.5
                                    * (s.maximum - s.minimum))
                      for i, s in enumerate(spec.signals)}
            msg = codec.message(name, values, c)
            if corrupt[k] < 0.05:   # damaged on the wire
                data = bytearray(msg.data)
                data[int(rng.integers(0, 8))] ^= 1 << int(rng.integers(0, 8))
                msg.data = data
            elif corrupt[k] < 0.07:
                msg = can.Message(arbitration_id=int(rng.integers(0, 0x800)),
                                  data=rng.integers(0, 256, int(rng.integers(0, 9)),
                                                    dtype=np.uint8).tobytes(),
                                  is_extended_id=False)
            tk = tkind[k]  # the clock: mostly forward, sometimes back or a jump ...
            if tk < 0.95:
                t += dts[k]
            elif tk < 0.97:
                t -= float(rng.uniform(0.0, 1.0))
            elif tk < 0.99:
                t += float(rng.uniform(0.0, 10.0))
            # ... and once in a while a special value (NaN, ±inf, ±1e308...) for one frame
            t_now = t if tk < 0.995 else float(SPECIALS[int(rng.integers(0, len(SPECIALS)))])
            case = (name, bytes(msg.data).hex(), hex(msg.arbitration_id), t_now)
            try:
                mon.process(msg, t_now)
                processed += 1
                probe = self.names[int(pick[k]) % len(MONITORED)]
                ok = mon.valid(probe, t_now)
                all_ok = mon.all_valid(MONITORED, t_now)
            except Exception as exc:
                findings.add(self.name, "exception", repr(exc), case, exc=True)
                mon = RxMonitor(codec, MONITORED)
                processed = 0
                continue
            if not isinstance(ok, bool) or not isinstance(all_ok, bool):
                findings.add(self.name, "invariant", "valid() not a bool", case)
            self._check(mon, processed, probe, ok, t_now, case, findings)

    def _check(self, mon: RxMonitor, processed: int, probe: str, ok: bool, now: float,
               case: Any, findings: Findings) -> None:
        counts = mon.counts
        rejected = sum(v for k, v in counts.items() if k != Rejection.TIMEOUT.value)
        accepted = sum(s.accepted for s in mon.streams.values())
        if rejected - counts[Rejection.COUNTER_JUMP.value] + accepted + mon.ignored \
                != processed:
            findings.add(self.name, "invariant", "a frame was not accounted for", case)
        st = mon.streams[probe]
        if not 0 <= st.counter_fault_level <= mon.counter_fault_limit:
            findings.add(self.name, "invariant", "counter fault level out of range", case)
        if ok and (st.last_rx_s is None
                   or st.counter_fault_level >= mon.counter_fault_limit):
            findings.add(self.name, "invariant", "valid without a healthy frame", case)
        if ok and math.isfinite(now) and st.last_rx_s is not None \
                and math.isfinite(st.last_rx_s) and now - st.last_rx_s > st.timeout_s + 1e-9:
            findings.add(self.name, "invariant", "valid after its timeout", case)


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
    limit at ω_i; ΔM = T2 + T4 − T1 − T3; ΔM = 0 when sensors are invalid or stabilisation
    is disabled; a valid QP status; and the output envelope holds on the sequence."""

    def __init__(self, name: str, params: VehicleParams) -> None:
        self.name = f"controller:{name}"
        self.ctrl = make_controller(name)
        self.p = params
        self.env = SafetyEnvelope(load_envelope_config(), params.peak_torque_nm,
                                  params.peak_power_w, 0.01)
        self.inp = ControllerInputs()
        self.prev = np.zeros(4)
        self.env_out = np.zeros(4)

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
                self.ctrl.reset()
                self.prev[:] = 0.0
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
                continue
            problem = self._check(out, inp)
            if problem:
                findings.add(self.name, "invariant", problem, (use_step, inp, out))

    def _check(self, out: ControllerOutputs, inp: ControllerInputs) -> str | None:
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
        if (not inp.sensors_valid or not inp.stab_enable) and out.delta_m != 0.0:
            return f"delta_m {out.delta_m} while invalid/disabled"
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
