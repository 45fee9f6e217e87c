"""Hypothesis engine of ``rhonn-bench fuzz``: structured search with shrinking.

Same invariants as the numpy targets (harness/fuzz/targets.py), but the inputs are drawn by
hypothesis, which also tries boundary values on its own and shrinks a failure to a minimal
example. Runs outside pytest with ``derandomize=True`` (fixed seed from the test's source)
and no example database, so a run is reproducible and writes nothing.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from can_db.codec import Codec, Decoded
from can_db.crc import frame_crc
from can_db.monitor import RxMonitor
from controller.core.interfaces import ControllerInputs
from controller.core.params import VehicleParams
from controller.runtime.node import MONITORED
from harness.fuzz.targets import (
    ControllerTarget,
    DecoderTarget,
    Findings,
    MonitorTarget,
)

ANY = st.floats(allow_nan=True, allow_infinity=True)
FRAME = st.tuples(st.integers(0, (1 << 29) - 1), st.binary(min_size=0, max_size=64),
                  st.booleans(), st.booleans(), st.booleans(), st.booleans(), st.booleans())
INPUTS = st.tuples(*(ANY for _ in range(8)), st.lists(ANY, min_size=4, max_size=4),
                   st.booleans(), st.booleans(), st.booleans())


def _settings(examples: int) -> settings:
    return settings(max_examples=examples, derandomize=True, database=None, deadline=None,
                    phases=(Phase.explicit, Phase.generate, Phase.target, Phase.shrink),
                    suppress_health_check=list(HealthCheck), print_blob=False,
                    report_multiple_bugs=False)


class _Counter:
    def __init__(self) -> None:
        self.n = 0


def _run(name: str, test: Callable[[], None], findings: Findings) -> None:
    """Run a @given test; a failure (already shrunk) becomes one finding."""
    try:
        test()
    except Exception as exc:
        findings.add(name, "exception", f"hypothesis: {exc!r}", "(see traceback)", exc=True)


def decoder(examples: int, findings: Findings, codec: Codec) -> int:
    """Frames: any ID, length, bytes and flags (optionally with a fixed-up CRC)."""
    target, count = DecoderTarget(codec), _Counter()

    @_settings(examples)
    @given(frame=FRAME)
    def test(frame) -> None:
        count.n += 1
        fid, data, fix, ext, rtr, err, fd = frame
        data = bytearray(data)
        if fix and data:
            data[0] = frame_crc(fid, data)
        local = Findings()  # the outer report gets one (shrunk) finding, not every retry
        res = codec.decode(fid, bytes(data), is_extended_id=ext, is_remote_frame=rtr,
                           is_error_frame=err, is_fd=fd)
        if isinstance(res, Decoded):
            target._check_decoded(res, fid, frame, local)
        assert not local.items, local.items[0].message if local.items else ""

    _run("hypothesis:decoder", test, findings)
    return count.n


def monitor(examples: int, findings: Findings, codec: Codec) -> int:
    """Sequences of (message, counter, values, damage, time) through one RxMonitor."""
    target, count = MonitorTarget(codec), _Counter()
    item = st.tuples(st.sampled_from(target.names), st.integers(0, 15),
                     st.floats(-1.0, 1.0), st.integers(-1, 63), ANY)

    @_settings(examples)
    @given(seq=st.lists(item, min_size=1, max_size=60))
    def test(seq) -> None:
        count.n += 1
        mon = RxMonitor(codec, MONITORED)
        local = Findings()
        for k, (name, counter, x, flip, now) in enumerate(seq):
            spec = codec.messages[name]
            values = {s.name: s.minimum + (x + 1.0) * 0.5 * (s.maximum - s.minimum)
                      for s in spec.signals}
            msg = codec.message(name, values, counter)
            if flip >= 0:
                data = bytearray(msg.data)
                data[flip // 8] ^= 1 << (flip % 8)
                msg.data = data
            mon.process(msg, now)
            ok = mon.valid(MONITORED[k % len(MONITORED)], now)
            assert isinstance(ok, bool)
            target._check(mon, k + 1, MONITORED[k % len(MONITORED)], ok, now, seq, local)
            assert not local.items, local.items[0].message if local.items else ""

    _run("hypothesis:monitor", test, findings)
    return count.n


def controller(name: str, examples: int, findings: Findings, params: VehicleParams
               ) -> int:
    """Sequences of arbitrary ControllerInputs through step()/allocate_only()."""
    count, target = _Counter(), ControllerTarget(name, params)

    @_settings(examples)
    @given(seq=st.lists(INPUTS, min_size=1, max_size=12))
    def test(seq) -> None:
        count.n += 1
        target.ctrl.reset()  # every example starts cold, like a fresh process
        target.prev[:] = 0.0
        inp: ControllerInputs = target.inp
        for case in seq:
            (inp.swa_rad, inp.accel_pedal, inp.brake_pedal, inp.yaw_rate, inp.ax, inp.ay,
             inp.vx, inp.vy) = case[:8]
            inp.wheel_speeds[:] = np.array(case[8])
            inp.stab_enable, inp.sensors_valid, use_step = case[9], case[10], case[11]
            out = target.ctrl.step(inp) if use_step else target.ctrl.allocate_only(inp)
            problem = target._check(out, inp)
            assert problem is None, problem

    _run(f"hypothesis:controller:{name}", test, findings)
    return count.n
