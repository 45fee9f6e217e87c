"""The distributed engine: a dask.distributed client on a LocalCluster or a running scheduler.

* ``scheduler="local"``: a :class:`distributed.LocalCluster` of ``workers`` processes with one
  thread each (one closed-loop run at a time per worker), scheduler and workers bound to
  127.0.0.1, no dashboard unless ``dashboard_port`` is given (then 127.0.0.1:PORT only).
* ``scheduler="tcp://HOST:PORT"`` (or a scheduler JSON file written by
  ``dask scheduler --scheduler-file``): connect to a cluster started by hand (``dask
  scheduler`` + ``dask worker`` per machine, see docs/campaigns.md); its workers are its own.

Campaigns (harness/campaign/runner.py) are its only user: the paper study and the benchmark
run as campaigns.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.run.procs import stop_descendants

LOOPBACK = "127.0.0.1"


class EngineError(RuntimeError):
    """The engine could not start or reach its scheduler; the message is one line."""


@dataclass
class EngineConfig:
    """Where runs execute. ``workers``: LocalCluster processes (ignored for an external
    scheduler); ``dashboard_port``: None = no dashboard, else served on 127.0.0.1 only;
    ``connect_timeout_s``: seconds to wait for an external scheduler."""

    scheduler: str = "local"
    workers: int = 2
    dashboard_port: int | None = None
    connect_timeout_s: float = 20.0


class Engine:
    """A started dask client (and the LocalCluster it owns, if any). Use as a context
    manager or call :meth:`close`."""

    def __init__(self, cfg: EngineConfig) -> None:
        self.cfg = cfg
        self.cluster: Any = None
        self.client: Any = None

    def start(self) -> Engine:
        """Start the LocalCluster or connect to the scheduler."""
        # dask.distributed logs its own life (scheduler, nanny, connections) at INFO: like
        # every other library, warnings only unless -v (the worker processes inherit it)
        quiet_dask = logging.getLogger("harness").getEffectiveLevel() > logging.DEBUG
        if quiet_dask:
            os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
        from distributed import Client, LocalCluster

        if quiet_dask:
            logging.getLogger("distributed").setLevel(logging.WARNING)

        if self.cfg.workers < 1:
            raise EngineError(f"--jobs must be ≥ 1, got {self.cfg.workers}")
        if self.cfg.scheduler == "local":
            # The scheduler always serves a small HTTP app (health, metrics); without a
            # dashboard it goes to a free loopback port instead of the default 8787.
            on = self.cfg.dashboard_port is not None
            dash = f"{LOOPBACK}:{self.cfg.dashboard_port if on else 0}"
            try:
                self.cluster = LocalCluster(
                    n_workers=self.cfg.workers, threads_per_worker=1, processes=True,
                    host=LOOPBACK, scheduler_port=0, dashboard_address=dash,
                    worker_dashboard_address=None, silence_logs=logging.ERROR,
                    protocol="tcp://", scheduler_kwargs={"dashboard": on})
                self.client = Client(self.cluster, set_as_default=False)
            except KeyboardInterrupt:  # SIGINT/SIGTERM while the workers start
                self.abort()
                raise
            except Exception as exc:
                self.close()
                raise EngineError(f"cannot start a LocalCluster: {exc}") from exc
            return self
        target = self.cfg.scheduler
        kwargs: dict[str, Any] = {"timeout": self.cfg.connect_timeout_s,
                                  "set_as_default": False}
        if not target.startswith(("tcp://", "tls://", "inproc://")):
            if not Path(target).is_file():
                raise EngineError(f"--scheduler {target!r}: use local, tcp://HOST:PORT or a "
                                  "scheduler file written by `dask scheduler --scheduler-file`")
            kwargs["scheduler_file"] = target
            target = None
        try:
            self.client = Client(target, **kwargs)
        except Exception as exc:  # OSError, TimeoutError ...
            self.close()
            raise EngineError(f"cannot reach the dask scheduler {self.cfg.scheduler}: "
                              f"{type(exc).__name__}: {exc}") from exc
        try:
            self.client.wait_for_workers(1, timeout=self.cfg.connect_timeout_s)
        except Exception as exc:
            self.close()
            raise EngineError(f"the dask scheduler {self.cfg.scheduler} has no worker after "
                              f"{self.cfg.connect_timeout_s:.0f} s: start `dask worker` "
                              "processes first") from exc
        return self

    def threads(self) -> int:
        """Total worker threads (concurrent runs) the scheduler knows now."""
        try:
            return max(1, sum(self.client.nthreads().values()))
        except Exception:
            return max(1, self.cfg.workers)

    def describe(self) -> str:
        """One line for the console: where the runs go (and the dashboard, if on)."""
        where = (f"LocalCluster of {self.cfg.workers} workers on {LOOPBACK}"
                 if self.cluster is not None else f"dask scheduler {self.cfg.scheduler}")
        line = f"{where}, {self.threads()} worker threads"
        if self.cluster is not None and self.cfg.dashboard_port is not None:
            line += f", dashboard {self.client.dashboard_link}"
        return line

    def submit(self, fn: Callable[..., Any], *args: Any, priority: int = 0) -> Any:
        """A distributed.Future of ``fn(*args)`` (never deduplicated: pure=False); a higher
        ``priority`` runs before the waiting tasks of a lower one."""
        return self.client.submit(fn, *args, pure=False, priority=priority)

    def close(self) -> None:
        """Close the client, then the cluster we own (its worker processes end)."""
        if self.client is not None:
            with contextlib.suppress(Exception):
                self.client.close(timeout=10)
            self.client = None
        if self.cluster is not None:
            with contextlib.suppress(Exception):
                self.cluster.close(timeout=20)
            self.cluster = None

    def abort(self) -> None:
        """Stop at once (SIGINT/SIGTERM): our LocalCluster's processes and the bus children of
        their runs get SIGTERM (SIGKILL after 0.5 s), then client and cluster are dropped. With
        an external scheduler only the client goes (its workers are not ours)."""
        if self.cfg.scheduler == "local":  # (also while the LocalCluster is being built)
            stop_descendants(grace_s=0.5)
        if self.cluster is not None:
            # its workers are gone: no graceful close at interpreter exit (distributed's
            # atexit hook would wait up to 10 s for them)
            self.cluster.shutdown_on_close = False
        for part in (self.client, self.cluster):
            if part is not None:
                with contextlib.suppress(Exception):
                    part.close(timeout=0.5)
        self.client = self.cluster = None

    def __enter__(self) -> Engine:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
            self.abort()
        else:
            self.close()


def worker_count_hint() -> int:
    """Default LocalCluster size: the CPU count, at most 2 on a small machine."""
    return max(1, min(2, os.cpu_count() or 1))
