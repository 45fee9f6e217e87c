"""Hypothesis engine of ``rhonn-bench fuzz``: structured search with shrinking.

Same invariants and oracles as the numpy targets (harness/fuzz/targets.py, oracle.py), but
the inputs are drawn by hypothesis, which also tries boundary values on its own and shrinks
a failure to a minimal example. Runs outside pytest with ``derandomize=True`` (fixed seed
from the test's source) and no example database, so a run is reproducible and writes
nothing.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from can_db.codec import Codec
from can_db.monitor import RxMonitor
from controller.core.interfaces import ControllerInputs
from controller.core.params import VehicleParams
from harness.fuzz.oracle import FrameOracle, MessageInfo, MonitorOracle
from harness.fuzz.targets import (
    NO_FLAGS,
    ControllerTarget,
    DecoderTarget,
    Findings,
    FrameMaker,
    MonitorTarget,
)

ANY = st.floats(allow_nan=True, allow_infinity=True)
INTACT = st.just(-1)
FLIP = st.one_of(INTACT, INTACT, INTACT, st.integers(0, 63))  # -1: no bit flipped
STEP = st.one_of(st.just(1), st.just(1), st.integers(0, 15))  # alive counter step
INPUTS = st.tuples(*(ANY for _ in range(8)), st.lists(ANY, min_size=4, max_size=4),
                   st.booleans(), st.booleans(), st.booleans())


def _settings(examples: int) -> settings:
    return settings(max_examples=examples, derandomize=True, database=None, deadline=None,
                    phases=(Phase.explicit, Phase.generate, Phase.target, Phase.shrink),
                    suppress_health_check=list(HealthCheck), print_blob=False,
                    report_multiple_bugs=False)


class _Counter:
    """Examples run, and the example at which the first failure came (before shrinking)."""

    def __init__(self) -> None:
        self.n = 0
        self.first: int | None = None


class MismatchError(AssertionError):
    """A disagreement with the oracle (or a broken invariant) of one kind."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(f"{kind}: {message}")
        self.kind = kind


def _fail_on(local: Findings, count: _Counter) -> None:
    """Raise the first of ``local``'s findings as a MismatchError (remembering the example)."""
    if local.items:
        if count.first is None:
            count.first = count.n
        raise MismatchError(local.items[0].kind, local.items[0].message)


def _run(name: str, test: Callable[[], None], findings: Findings, count: _Counter) -> None:
    """Run a @given test; a failure (already shrunk) becomes one finding, of the mismatch's
    kind (else "exception"), dated at the example that first failed."""
    try:
        test()
    except Exception as exc:
        findings.cases[name] = count.first if count.first is not None else count.n
        findings.add(name, exc.kind if isinstance(exc, MismatchError) else "exception",
                     f"hypothesis: {exc!r}", "(see traceback)", exc=True)


def _raws(info: MessageInfo, xs: list[float]) -> dict[str, int]:
    """Raw values from positions in the valid range (0..1; outside: out of range, kept
    within what the field can hold)."""
    return {s.name: min(s.raw_hi, max(s.raw_lo, s.valid_lo + round(
        x * (s.valid_hi - s.valid_lo)))) for s, x in zip(info.signals, xs, strict=False)}


def decoder(examples: int, findings: Findings, codec: Codec,
            oracle: FrameOracle | None = None) -> int:
    """Frames: a message's signals at any position around their range (encoded by the
    oracle), or a known or any ID with 8 or any number of bytes, any flags, the CRC field
    optionally made correct by the oracle (crcmod); every verdict compared with the oracle's."""
    target, count = DecoderTarget(codec, oracle), _Counter()
    orc = target.oracle
    ids = st.one_of(st.sampled_from(target.ids), st.integers(0, (1 << 29) - 1))
    flags = st.lists(st.booleans(), min_size=4, max_size=4)
    raw_frame = st.tuples(st.sampled_from(sorted(orc.messages)),
                          st.lists(st.floats(-0.5, 1.5), min_size=8, max_size=8),
                          st.integers(0, 15), FLIP)
    byte_frame = st.tuples(ids, st.one_of(st.binary(min_size=8, max_size=8),
                                          st.binary(min_size=0, max_size=64)),
                           st.booleans(), flags)

    @_settings(examples)
    @given(case=st.one_of(raw_frame, byte_frame))
    def test(case) -> None:
        count.n += 1
        if isinstance(case[0], str):
            name, xs, counter, flip = case
            info = orc.messages[name]
            fid, data, fl = info.frame_id, orc.encode(name, _raws(info, xs), counter), NO_FLAGS
            if flip >= 0:
                data = FrameMaker.flip_bit(data, flip)
        else:
            fid, data, fix, f4 = case
            fl = (f4[0], f4[1], f4[2], f4[3])
            info = orc.by_id.get(fid)
            if fix and info is not None and len(data) == info.length:
                data = orc.protect(info, data)
        local = Findings()  # the outer report gets one (shrunk) finding, not every retry
        target.check(fid, data, fl, local)
        _fail_on(local, count)

    _run("hypothesis:decoder", test, findings, count)
    return count.n


def monitor(examples: int, findings: Findings, codec: Codec,
            oracle: FrameOracle | None = None) -> int:
    """Sequences of (message, counter step, values, bit flip, time step, probe delay, odd
    time) through one RxMonitor, each frame made by the oracle; every verdict and every
    stream's validity after each frame compared with the oracle's."""
    target, count = MonitorTarget(codec, oracle), _Counter()
    orc = target.oracle
    item = st.tuples(st.sampled_from(target.names), STEP,
                     st.floats(-0.25, 1.25), FLIP, st.floats(0.0, 0.08),
                     st.floats(0.0, 0.06), st.one_of(st.none(), ANY))

    @_settings(examples)
    @given(seq=st.lists(item, min_size=1, max_size=60))
    def test(seq) -> None:
        count.n += 1
        mon = RxMonitor(codec, target.monitored)
        mor = MonitorOracle(orc, target.monitored)
        senders = dict.fromkeys(target.names, 0)
        local = Findings()
        t = 0.0
        for name, step, x, flip, dt, probe, odd in seq:
            info = orc.messages[name]
            senders[name] = (senders[name] + step) % 16
            data = orc.encode(name, _raws(info, [x] * len(info.signals)), senders[name])
            if flip >= 0:
                data = FrameMaker.flip_bit(data, flip)
            t += dt
            now = t if odd is None else odd
            target._one(mon, mor, (info.frame_id, data, NO_FLAGS), now, local)
            target._probe(mon, mor, now + probe, local)
            _fail_on(local, count)

    _run("hypothesis:monitor", test, findings, count)
    return count.n


def controller(name: str, examples: int, findings: Findings, params: VehicleParams
               ) -> int:
    """Sequences of arbitrary ControllerInputs through step()/allocate_only()."""
    count, target = _Counter(), ControllerTarget(name, params)

    @_settings(examples)
    @given(seq=st.lists(INPUTS, min_size=1, max_size=12))
    def test(seq) -> None:
        count.n += 1
        target.reset()  # every example starts cold, like a fresh process
        inp: ControllerInputs = target.inp
        for case in seq:
            (inp.swa_rad, inp.accel_pedal, inp.brake_pedal, inp.yaw_rate, inp.ax, inp.ay,
             inp.vx, inp.vy) = case[:8]
            inp.wheel_speeds[:] = np.array(case[8])
            inp.stab_enable, inp.sensors_valid, use_step = case[9], case[10], case[11]
            out = target.ctrl.step(inp) if use_step else target.ctrl.allocate_only(inp)
            problem = target._check(out, inp)
            assert problem is None, problem

    _run(f"hypothesis:controller:{name}", test, findings, count)
    return count.n
