"""Per-cycle numeric logs that cost one ``write(2)`` of packed doubles per row, turned into
the CSV file the readers know when the writer closes.

Why: formatting a 62-column truth line with ``%.9g`` took ≈ 20 µs per lockstep cycle in the
plant process (measured in situ; 7 µs of it formatting on hot caches), which is ≈ 5 % of a
cycle. Packing the row is ≈ 0.4 µs; the formatting moves to the end of the run.

A row file ``NAME.csv.rows`` (:func:`rows_path`) is::

    RHONNROWS 1\\n
    <one printf format per column, comma-separated>\\n
    <column names, comma-separated>\\n
    <rows of little-endian float64, ``len(columns)`` each>

Every row is written with one ``write(2)`` to an unbuffered descriptor, so a writer killed
with SIGKILL leaves every finished row on disk (a torn last row is dropped on reading).
:meth:`RowLog.close` writes ``NAME.csv`` — each row ``fmt % values`` joined by commas, the
same bytes a line-by-line CSV writer with those formats gives — and removes the row file;
:func:`finish_rows` does the same for the file of a writer that was killed, and
:func:`read_rows` reads a row file (complete or still growing) into column arrays.
"""

from __future__ import annotations

import os
import struct
import sys
from pathlib import Path

import numpy as np

MAGIC = b"RHONNROWS 1\n"
SUFFIX = ".rows"


def rows_path(csv_path: str | Path) -> Path:
    """The row file that becomes ``csv_path`` when its writer closes."""
    return Path(str(csv_path) + SUFFIX)


class RowLog:
    """Writer of one row file (see the module docstring). ``formats``: printf format per
    column (``%.9g``, ``%.3f``, ``%d``…; a ``%d`` column holds integers stored as doubles,
    exact below 2**53)."""

    def __init__(self, csv_path: str | Path, columns: list[str] | tuple[str, ...],
                 formats: list[str] | tuple[str, ...]) -> None:
        if len(columns) != len(formats):
            raise ValueError(f"{len(columns)} columns but {len(formats)} formats")
        self.csv_path = Path(csv_path)
        self.path = rows_path(csv_path)
        self.columns = tuple(columns)
        self._pack = struct.Struct(f"<{len(columns)}d").pack
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        header = ",".join(formats) + "\n" + ",".join(columns) + "\n"
        os.write(self._fd, MAGIC + header.encode())
        self.rows = 0

    def write(self, values: tuple[float, ...] | list[float]) -> None:
        """Append one row (``len(columns)`` numbers, in column order)."""
        fd = self._fd
        if fd is not None:
            os.write(fd, self._pack(*values))
            self.rows += 1

    def close(self) -> None:
        """Write the CSV and remove the row file (idempotent)."""
        if self._fd is None:
            return
        os.close(self._fd)
        self._fd = None
        finish_rows(self.csv_path)


def _parse(raw: bytes) -> tuple[list[str], list[str], np.ndarray] | None:
    """(formats, columns, rows (n, ncol)) of a row file's bytes; None if not one (yet)."""
    if not raw.startswith(MAGIC):
        return None
    rest = raw[len(MAGIC):]
    first = rest.find(b"\n")
    second = rest.find(b"\n", first + 1) if first >= 0 else -1
    if second < 0:
        return None
    formats = rest[:first].decode().split(",")
    columns = rest[first + 1:second].decode().split(",")
    body = rest[second + 1:]
    width = 8 * len(columns)
    whole = len(body) // width * width  # a torn last row (killed mid-write) is dropped
    data = np.frombuffer(body[:whole], dtype="<f8").reshape(-1, len(columns))
    return formats, columns, data


def read_rows(path: str | Path) -> dict[str, np.ndarray]:
    """Column arrays of a row file; ``{}`` when it is missing or not a row file."""
    try:
        raw = Path(path).read_bytes()
    except OSError:
        return {}
    parsed = _parse(raw)
    if parsed is None:
        return {}
    _, columns, data = parsed
    return {c: data[:, i].copy() for i, c in enumerate(columns)}


def csv_text(formats: list[str], columns: list[str], data: np.ndarray) -> str:
    """The CSV text (header + one line per row) of rows ``data`` with ``formats``."""
    line = ",".join(formats) + "\n"
    body = "".join(line % tuple(row) for row in data.tolist())
    return ",".join(columns) + "\n" + body


def finish_rows(csv_path: str | Path) -> bool:
    """Turn ``csv_path``'s row file into ``csv_path`` (written to a temporary name, then
    renamed; the row file is removed after). False when there is no row file."""
    src = rows_path(csv_path)
    try:
        raw = src.read_bytes()
    except OSError:
        return False
    parsed = _parse(raw)
    if parsed is None:
        return False
    formats, columns, data = parsed
    dst = Path(csv_path)
    tmp = dst.with_name(dst.name + ".tmp")
    try:
        tmp.write_text(csv_text(formats, columns, data))
    except OSError:  # disk full, file too large: the row file stays, readable as it is
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, dst)
    src.unlink(missing_ok=True)
    return True


def finish_all(directory: str | Path,
               failed: dict[str, str] | None = None) -> list[Path]:
    """:func:`finish_rows` for every row file in ``directory`` (the files of writers that
    were killed); returns the CSV files written. A CSV that cannot be written (disk full)
    leaves its row file, and its name and the error go into ``failed`` when given (raised
    otherwise)."""
    done = []
    for src in sorted(Path(directory).glob(f"*{SUFFIX}")):
        csv_path = Path(str(src)[: -len(SUFFIX)])
        try:
            if finish_rows(csv_path):
                done.append(csv_path)
        except OSError as exc:
            if failed is None:
                raise
            failed[csv_path.name] = f"{type(exc).__name__}: {exc}"
    return done


class RowTail:
    """The rows appended to a growing row file since the last call, as column arrays.
    Follows the file when it is replaced (a new inode: a restarted writer); keeps reading a
    file its writer has finished and removed (the open descriptor still holds the rows)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fh = None
        self._inode: int | None = None
        self._buf = b""
        self.columns: list[str] | None = None
        self.opened = False  # a row file was seen at least once

    def _open_if_new(self) -> None:
        try:
            inode = os.stat(self.path).st_ino
        except OSError:
            return  # not there (yet, or finished and removed): keep what is open
        if inode != self._inode:
            if self._fh is not None:
                self._fh.close()
            self._fh = open(self.path, "rb")  # noqa: SIM115 - closed in close()
            self._inode, self._buf, self.columns = inode, b"", None
            self.opened = True

    def rows(self) -> dict[str, np.ndarray]:
        """New whole rows as column arrays (empty dict when nothing new)."""
        self._open_if_new()
        if self._fh is None:
            return {}
        self._buf += self._fh.read()
        if self.columns is None:
            parsed = _parse(self._buf)
            if parsed is None:
                return {}
            _, self.columns, _ = parsed
            self._buf = self._buf[self._buf.index(b"\n", len(MAGIC)) + 1:]
            self._buf = self._buf[self._buf.index(b"\n") + 1:]
        width = 8 * len(self.columns)
        whole = len(self._buf) // width * width
        if whole == 0:
            return {}
        data = np.frombuffer(self._buf[:whole], dtype="<f8").reshape(-1, len(self.columns))
        self._buf = self._buf[whole:]
        return {c: data[:, i].copy() for i, c in enumerate(self.columns)}

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def main(argv: list[str] | None = None) -> int:
    """``python -m can_db.process.rowlog FILE.csv.rows…``: turn the row files a killed writer left
    into their CSV files."""
    paths = sys.argv[1:] if argv is None else argv
    if not paths:
        print("usage: python -m can_db.process.rowlog FILE.csv.rows...", file=sys.stderr)
        return 2
    code = 0
    for name in paths:
        csv_path = name[: -len(SUFFIX)] if name.endswith(SUFFIX) else name
        if finish_rows(csv_path):
            print(f"{csv_path}: written")
        else:
            print(f"{name}: not a row file", file=sys.stderr)
            code = 1
    return code


if __name__ == "__main__":
    raise SystemExit(main())
