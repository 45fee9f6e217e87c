"""Run a campaign on the engine: submit, record, feed the studies, resume, summarise.

Every run is a task ``execute_run(spec, DIR)`` on a Dask worker. As each finishes its row is
written to ``DIR/parts/<key>.parquet`` (:mod:`harness.campaign.store`); a derived study fed
with it may ask for further runs, which are submitted at once. With ``resume`` the runs that
already have a row are not submitted again: their rows are fed to the studies as if they had
just finished. The same key asked for twice (two matrices, a study probe equal to a matrix
run) runs once. The runs of ``exclusive`` matrices wait until nothing else is left, then run one
at a time (their wall-clock measurements see no concurrent run).
"""

from __future__ import annotations

import contextlib
import json
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from harness.campaign.engine import Engine, EngineConfig
from harness.campaign.spec import Campaign, CampaignError, RunSpec
from harness.campaign.store import ResultStore
from harness.campaign.studies import make_study
from harness.campaign.summary import summarise, write_summary
from harness.campaign.task import error_row, execute_run
from harness.run import signals
from harness.viz.progress import Bar

Feed = Callable[[RunSpec, dict[str, Any]], list[RunSpec]]


class Progress:
    """Runs done / running / failed on stderr (harness/viz/progress.py: a tqdm bar on a
    terminal, else one plain line at most every ``LINE_EVERY_S``), or nothing."""

    LINE_EVERY_S = 10.0

    def __init__(self, enabled: bool, stream: TextIO | None = None) -> None:
        self.bar: Any = None
        if enabled:
            self.bar = Bar("campaign", total=0, unit="runs", stream=stream,
                           line_every_s=self.LINE_EVERY_S)

    def update(self, done: int, total: int, running: int, failed: int, cached: int) -> None:
        """Set the bar to ``done`` of ``total`` (an estimate: the runs known plus what each
        study may still ask for, so it shrinks when a study ends early)."""
        if self.bar is None:
            return
        self.bar.set(done, max(total, done),
                     f"running {running}, failed {failed}, resumed {cached}")

    def close(self) -> None:
        """End the bar's line."""
        if self.bar is not None:
            self.bar.close()


@dataclass
class CampaignResult:
    """What a campaign left: counts, the wall time (s) and the files written."""

    out: Path
    rows: dict[str, dict[str, Any]]
    executed: int
    cached: int
    wall_time_s: float
    studies: dict[str, Any] = field(default_factory=dict)
    summary: list[dict[str, Any]] = field(default_factory=list)

    @property
    def failed(self) -> list[dict[str, Any]]:
        """Rows whose status is not ok."""
        return [r for r in self.rows.values() if r.get("status") != "ok"]


class CampaignRunner:
    """One campaign into one output directory."""

    def __init__(self, campaign: Campaign, out: Path, engine: EngineConfig,
                 resume: bool = False, retry_failed: bool = False,
                 progress: bool = True) -> None:
        self.campaign, self.out = campaign, Path(out).resolve()
        self.engine_cfg, self.resume, self.retry_failed = engine, resume, retry_failed
        self.store = ResultStore(self.out)
        self.progress = Progress(progress)
        self.studies = {d.name: make_study(d) for d in campaign.studies}
        self._owners: dict[str, list[Feed]] = {}
        self._spec: dict[str, RunSpec] = {}
        self._inflight: dict[Any, str] = {}
        self._done: dict[str, dict[str, Any]] = {}
        self._inflight_keys: set[str] = set()
        self._resumed_keys: set[str] = set()
        self._reused: set[str] = set()
        self._alone: list[RunSpec] = []  # exclusive runs not yet asked for, in file order
        self.executed = self.cached = 0

    # ---------------------------------------------------------------- bookkeeping
    def _prepare(self) -> None:
        if self.store.has_results() and not self.resume:
            raise CampaignError(f"{self.out} already holds campaign results: add --resume to "
                                "finish it, or choose another --out")
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "campaign.toml").write_text(self.campaign.source)
        self._done = self.store.rows()
        if self.retry_failed:
            for key in [k for k, r in self._done.items() if r.get("status") != "ok"]:
                self.store.drop(key)
                del self._done[key]
        self._resumed_keys = set(self._done)

    def _expected(self) -> int:
        return len(self._spec) + sum(s.expected_remaining() for s in self.studies.values())

    def _finish(self, key: str, row: dict[str, Any], engine: Engine) -> None:
        """A run has just finished: record its row, then hand it to its owners."""
        self.store.write(row)
        self.executed += 1
        self._done[key] = row
        self._deliver(key, engine)

    def _deliver(self, key: str, engine: Engine) -> None:
        """Feed a known row to the studies waiting for it; submit what they ask for next."""
        spec, row = self._spec[key], self._done[key]
        for feed in self._owners.pop(key, []):
            for nxt in feed(spec, row):
                self._want(nxt, engine, feed)

    def _want(self, spec: RunSpec, engine: Engine, feed: Feed | None) -> None:
        """Ask for a run: reuse its row if it has one, else submit it (once)."""
        key = spec.key()
        self._spec.setdefault(key, spec)
        if feed is not None:
            self._owners.setdefault(key, []).append(feed)
        if key in self._done:  # finished earlier (resume, or asked for twice)
            if key not in self._reused and key in self._resumed_keys:
                self._reused.add(key)
                self.cached += 1
            self._deliver(key, engine)
            return
        if key in self._inflight_keys:
            return
        # a study's next probe waits for its last one: it goes before the waiting matrix runs,
        # so a bisection chain never idles a worker at the campaign's end
        fut = engine.submit(execute_run, spec.to_json(), str(self.out),
                            priority=1 if feed is not None else 0)
        self._inflight[fut] = key
        self._inflight_keys.add(key)
        self._as_completed.add(fut)

    def _next_alone(self, engine: Engine) -> None:
        """With nothing in flight, ask for the next exclusive run (one with a row is fed and
        the one after it asked for)."""
        while self._alone and not self._inflight:
            self._want(self._alone.pop(0), engine, None)

    # ---------------------------------------------------------------- main loop
    def run(self, engine: Engine | None = None) -> CampaignResult:
        """Run everything that is missing; write results.parquet, summary, studies.json.
        ``engine``: a started engine to use (and leave open); None: one of its own."""
        from distributed import as_completed

        t0 = time.monotonic()
        self._prepare()
        failed = 0
        try:
            with contextlib.nullcontext(engine) if engine else Engine(self.engine_cfg) as engine:
                if self.progress.bar is not None:
                    print(engine.describe(), file=sys.stderr)
                self._as_completed = as_completed(loop=engine.client.loop)
                for study in self.studies.values():
                    for spec in study.initial():
                        self._want(spec, engine, study.feed)
                for spec in self.campaign.runs:  # (in file order)
                    if spec.key() in self.campaign.exclusive:
                        self._spec.setdefault(spec.key(), spec)
                        self._alone.append(spec)
                # grouped by controller coding (stable): a worker's warm bench soft-resets
                # between runs of one group and hard-resets only between groups
                for spec in sorted(self.campaign.runs, key=_coding):
                    if spec.key() not in self.campaign.exclusive:
                        self._want(spec, engine, None)
                self._next_alone(engine)
                threads = engine.threads()
                self.progress.update(self.executed + self.cached, self._expected(),
                                     min(len(self._inflight), threads), failed, self.cached)
                for fut in self._as_completed:
                    key = self._inflight.pop(fut)
                    self._inflight_keys.discard(key)
                    try:
                        row = fut.result()
                    except Exception as exc:  # the worker died, the task was lost ...
                        row = error_row(self._spec[key], self.out,
                                        f"{type(exc).__name__}: {exc}")
                    fut.release()
                    if row.get("reason") == "interrupted":
                        # its processes got a stop signal (a terminal's Ctrl-C reaches the
                        # workers' children too): the campaign stops, the run is not recorded
                        # (--resume runs it again)
                        signals.check()
                        raise signals.Interrupted(signal.SIGINT)
                    if row.get("status") != "ok":
                        failed += 1
                    self._finish(key, row, engine)
                    self._next_alone(engine)
                    self.progress.update(self.executed + self.cached, self._expected(),
                                         min(len(self._inflight), threads), failed,
                                         self.cached)
        finally:
            self.progress.close()
        return self._report(time.monotonic() - t0)

    def _report(self, wall_s: float) -> CampaignResult:
        self.store.consolidate()
        rows = self.store.rows()
        summary = summarise(list(rows.values()))
        write_summary(self.out, summary)
        studies = {name: s.to_json() for name, s in self.studies.items()}
        meta = {"campaign": self.campaign.name, "wall_time_s": wall_s, "runs": len(rows),
                "executed": self.executed, "resumed": self.cached,
                "failed": sum(1 for r in rows.values() if r.get("status") != "ok"),
                "scheduler": self.engine_cfg.scheduler, "workers": self.engine_cfg.workers}
        (self.out / "studies.json").write_text(
            json.dumps({"meta": meta, "studies": studies}, indent=2, default=str) + "\n")
        return CampaignResult(self.out, rows, self.executed, self.cached, wall_s, studies,
                              summary)


def _coding(spec: RunSpec) -> tuple[str, ...]:
    """What decides a controller process's coding (harness/run/hil_bench.py): runs with equal
    codings follow each other on a warm bench without a hard reset."""
    return (spec.controller, spec.controller_config or "", repr(spec.controller_overrides),
            repr(spec.faults), spec.controller_mode)
