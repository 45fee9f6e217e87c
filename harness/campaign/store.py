"""Campaign results on disk: one Parquet part per finished run, written atomically.

``DIR/parts/<key>.parquet`` exists if and only if the run with that key has finished (its
row, failed or not, is complete): it is written to a temporary name and renamed, so a
campaign killed at any moment (SIGKILL included) leaves either the whole row or nothing.
``--resume`` runs exactly the keys without a part. :meth:`ResultStore.consolidate` writes
``DIR/results.parquet`` (every row, one table).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from harness.campaign.task import KPI_FLAGS, KPI_FLOATS

SCHEMA = pa.schema(
    [("key", pa.string()), ("group", pa.string()), ("scenario", pa.string()),
     ("controller", pa.string()), ("seed", pa.int64()), ("mu", pa.float64()),
     ("speed_kmh", pa.float64()), ("duration_s", pa.float64()), ("params", pa.string()),
     ("faults", pa.string()), ("controller_config", pa.string()), ("mode", pa.string()),
     ("status", pa.string()), ("reason", pa.string()), ("error", pa.string()),
     ("run_dir", pa.string()), ("host", pa.string()), ("worker_pid", pa.int64()),
     ("started_at", pa.float64()), ("task_wall_s", pa.float64()), ("run_wall_s", pa.float64()),
     ("loop_wall_s", pa.float64()), ("bench", pa.string())]
    + [(k, pa.float64()) for k in KPI_FLOATS] + [(k, pa.bool_()) for k in KPI_FLAGS]
    + [("post", pa.string()), ("config", pa.string())])


def _table(rows: list[dict[str, Any]]) -> pa.Table:
    cols = {f.name: [r.get(f.name) for r in rows] for f in SCHEMA}
    return pa.Table.from_pydict(cols, schema=SCHEMA)


class ResultStore:
    """The Parquet results of one campaign directory."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.parts = self.root / "parts"

    def has_results(self) -> bool:
        """Any finished run recorded here."""
        return self.parts.is_dir() and any(self.parts.glob("*.parquet"))

    def write(self, row: dict[str, Any]) -> Path:
        """Record one finished run (atomically)."""
        self.parts.mkdir(parents=True, exist_ok=True)
        path = self.parts / f"{row['key']}.parquet"
        tmp = self.parts / f".{row['key']}.{os.getpid()}.tmp"
        pq.write_table(_table([row]), tmp)
        os.replace(tmp, path)
        return path

    def rows(self) -> dict[str, dict[str, Any]]:
        """Every recorded row by key (unreadable parts are skipped and reported as missing)."""
        out: dict[str, dict[str, Any]] = {}
        if not self.parts.is_dir():
            return out
        for path in sorted(self.parts.glob("*.parquet")):
            try:
                for row in pq.read_table(path).to_pylist():
                    out[row["key"]] = row
            except (OSError, pa.ArrowException):
                continue
        return out

    def drop(self, key: str) -> None:
        """Forget a recorded run (``--retry-failed``)."""
        (self.parts / f"{key}.parquet").unlink(missing_ok=True)

    def consolidate(self) -> Path:
        """Write DIR/results.parquet from every part; returns its path."""
        rows = sorted(self.rows().values(), key=lambda r: (r["group"], r["key"]))
        path = self.root / "results.parquet"
        tmp = self.root / ".results.parquet.tmp"
        pq.write_table(_table(rows), tmp)
        os.replace(tmp, path)
        return path
