"""Planted missing checks: each a small mutant of the codec or the rx monitor that removes or
weakens one check; the oracle-checked fuzz targets must report a mismatch for every one
(``rhonn-bench fuzz --planted``, tests/test_fuzz_smoke.py, docs/safety/fuzz.md).

A mutant is applied with ``unittest.mock.patch`` only while its context is open; the codec
is built inside it (the range mutant changes the generated unpackers).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any
from unittest import mock

import numpy as np

import can_db.codec as codec_module
from can_db.codec import Codec
from can_db.monitor import RxMonitor
from harness.fuzz import property_pass
from harness.fuzz.oracle import FrameOracle
from harness.fuzz.targets import DecoderTarget, Findings, MonitorTarget


@contextmanager
def no_crc() -> Iterator[None]:
    """The decoder's CRC comparison removed: every frame's CRC field is taken as right
    (both profiles)."""
    with ExitStack() as stack:
        stack.enter_context(mock.patch.object(
            codec_module, "frame_crc", lambda fid, data: data[0]))
        stack.enter_context(mock.patch.object(
            codec_module, "frame_crc16", lambda fid, data: data[0] | data[1] << 8))
        yield


@contextmanager
def no_range() -> Iterator[None]:
    """The decoder's range check removed: the generated unpackers get limits of ±1e300."""
    real = codec_module.make_decoder

    def unlimited(table: tuple[tuple[Any, ...], ...]) -> Callable[[int], Any]:
        return real(tuple((*row[:-2], -1e300, 1e300) for row in table))

    with mock.patch.object(codec_module, "make_decoder", unlimited):
        yield


@contextmanager
def timeout_5_cycles() -> Iterator[None]:
    """The rx monitor's timeout at 5 cycles instead of the documented 3."""
    real = RxMonitor.__init__

    def init(self: RxMonitor, *args: Any, **kwargs: Any) -> None:
        real(self, *args, **{**kwargs, "timeout_factor": 5.0})

    with mock.patch.object(RxMonitor, "__init__", init):
        yield


@contextmanager
def no_counter() -> Iterator[None]:
    """The rx monitor's alive-counter check removed (every counter accepted)."""
    with mock.patch.object(RxMonitor, "_check_counter", lambda self, stream, counter: None):
        yield


@contextmanager
def no_window() -> Iterator[None]:
    """The CRC16 profile's counter-delta window not applied: its messages get the CRC8
    rule (any jump accepted while the fault level stays below the limit)."""
    real = RxMonitor.__init__

    def init(self: RxMonitor, *args: Any, **kwargs: Any) -> None:
        real(self, *args, **kwargs)
        for stream in self.streams.values():
            stream.window = False

    with mock.patch.object(RxMonitor, "__init__", init):
        yield


PLANTED: dict[str, Callable[[], Any]] = {
    "no_crc": no_crc,
    "no_range": no_range,
    "timeout_5_cycles": timeout_5_cycles,
    "no_counter": no_counter,
    "no_window": no_window,
}
PLANTED_TARGETS = ("decoder", "monitor", "hypothesis:decoder", "hypothesis:monitor")


@dataclass
class Detection:
    """What one target reported with one mutant in place."""

    bug: str
    target: str
    cases: int
    mismatches: int
    first_at: int | None                       # cases run when the first mismatch came
    by_kind: dict[str, int] = field(default_factory=dict)


def run_target(target: str, codec: Codec, oracle: FrameOracle, cases: int, seed: int,
               findings: Findings) -> int:
    """Run one oracle-checked target for ``cases`` cases (hypothesis: examples); returns the
    number run. Chunk j draws from ``default_rng([seed, j])``."""
    if target == "hypothesis:decoder":
        return property_pass.decoder(cases, findings, codec, oracle)
    if target == "hypothesis:monitor":
        return property_pass.monitor(cases, findings, codec, oracle)
    runner = DecoderTarget(codec, oracle) if target == "decoder" else \
        MonitorTarget(codec, oracle)
    done, chunk = 0, 0
    while done < cases:
        n = min(2_000, cases - done)
        runner.run(np.random.default_rng([seed, chunk]), n, findings)
        done, chunk = done + n, chunk + 1
    return done


def detect(bug: str | None, target: str, cases: int, seed: int = 0,
           oracle: FrameOracle | None = None) -> Detection:
    """Run ``target`` with the mutant ``bug`` in place (None: the code as it is)."""
    oracle = oracle if oracle is not None else FrameOracle()
    findings = Findings()
    with PLANTED[bug]() if bug is not None else ExitStack():
        run = run_target(target, Codec(), oracle, cases, seed, findings)
    first = findings.first_at.get(target, {})
    return Detection(bug or "none", target, run, findings.counts.get(target, 0),
                     min(first.values()) if first else None,
                     dict(findings.by_kind.get(target, {})))


def matrix(cases: int, examples: int, seed: int = 0,
           bugs: tuple[str, ...] = tuple(PLANTED)) -> list[Detection]:
    """Every planted bug against every oracle-checked target (``cases`` numpy cases,
    ``examples`` hypothesis examples each)."""
    oracle = FrameOracle()
    out = []
    for bug in bugs:
        for target in PLANTED_TARGETS:
            n = examples if target.startswith("hypothesis") else cases
            if n > 0:
                out.append(detect(bug, target, n, seed, oracle))
    return out
