"""Argument checks shared by every command-line tool, run before anything starts.

A bad argument ends the program with one line on stderr and exit code 2, before any process,
server, file or directory is created:

* :class:`OneLineParser` — an ``argparse`` parser whose errors are one line (no usage dump);
* :func:`number` — an ``argparse`` type for a number in a range (with its unit in the error);
* :func:`check_out_dir` / :func:`check_out_file` — an output path that can be written.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn


class UsageError(ValueError):
    """A command-line argument that cannot be used; the message is one line."""


class HelpFormatter(argparse.RawDescriptionHelpFormatter,
                    argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the module docstring's layout and shows every flag's default (unless the help
    already names it, or there is none: None, False)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text or action.default is None or action.default is False \
                or action.default is argparse.SUPPRESS or action.default == []:
            return text
        return super()._get_help_string(action)


class OneLineParser(argparse.ArgumentParser):
    """``argparse`` parser whose errors are one line on stderr, exit code 2."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        """Print ``PROG: error: MESSAGE (see PROG --help)`` and exit 2."""
        usage_exit(self.prog, f"{message} (see {self.prog} --help)")


def usage_exit(prog: str, message: str) -> NoReturn:
    """One line on stderr, exit code 2."""
    text = " ".join(str(message).split())  # one line, whatever the message held
    sys.stderr.write(f"{prog}: error: {text}\n")
    raise SystemExit(2)


def number(kind: type = float, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, unit: str = "") -> Callable[[str], float]:
    """``argparse`` type: a finite ``kind`` (int or float) in [lo, hi] (lo excluded when
    ``lo_open``); ``unit`` is named in the error."""
    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if value != value or value in (float("inf"), float("-inf")):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        too_low = lo is not None and (value <= lo if lo_open else value < lo)
        if too_low or (hi is not None and value > hi):
            low = "" if lo is None else (f"> {lo:g}" if lo_open else f">= {lo:g}")
            high = "" if hi is None else f"<= {hi:g}"
            bounds = " and ".join(b for b in (low, high) if b)
            raise argparse.ArgumentTypeError(
                f"{text}{(' ' + unit) if unit else ''} is out of range (must be {bounds})")
        return value
    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def choice_list(choices: tuple[str, ...] | list[str], what: str) -> Callable[[str], list[str]]:
    """``argparse`` type: a comma-separated list, every item one of ``choices``."""
    def parse(text: str) -> list[str]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f"no {what} given")
        bad = [t for t in items if t not in choices]
        if bad:
            raise argparse.ArgumentTypeError(
                f"unknown {what} {', '.join(map(repr, bad))}; choose from {', '.join(choices)}")
        return items
    parse.__name__ = "list"
    return parse


def check_extra(modules: tuple[str, ...], extra: str = "harness") -> None:
    """Raise :class:`UsageError` naming the pip extra when an optional module is missing
    (the core install deploys the controller alone)."""
    import importlib.util

    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        raise UsageError(f"{', '.join(missing)} not installed: this needs the '{extra}' "
                         f"extra (pip install 'rhonn-tv[{extra}]')")


def check_port_free(port: int) -> None:
    """Raise :class:`UsageError` if a TCP port on 127.0.0.1 is taken."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError as exc:
            raise UsageError(f"--port {port}: 127.0.0.1:{port} is not free "
                             f"({exc.strerror or exc})") from None


def _existing_ancestor(path: Path) -> Path:
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_out_dir(path: str | Path, what: str = "--out") -> None:
    """Raise :class:`UsageError` unless ``path`` is a writable directory or could be created
    as one (checked without creating anything)."""
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise UsageError(f"{what} {path}: exists and is not a directory")
        base = p
    else:
        base = _existing_ancestor(p)
        if not base.is_dir():
            raise UsageError(f"{what} {path}: {base} is not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {path}: {base} is not writable")
    if str(base.absolute()).startswith(("/proc", "/sys")):
        raise UsageError(f"{what} {path}: {base} is a kernel file system, not writable")


def check_out_file(path: str | Path, what: str) -> None:
    """Raise :class:`UsageError` unless the file ``path`` can be written (its directory
    exists and is writable; an existing file must be a writable regular file)."""
    p = Path(path)
    if p.exists() and (p.is_dir() or not os.access(p, os.W_OK)):
        raise UsageError(f"{what} {path}: not a writable file")
    parent = p.absolute().parent
    if not parent.is_dir():
        raise UsageError(f"{what} {path}: directory {parent} does not exist")
    check_out_dir(parent, what)


def check_in_file(path: str | Path, what: str) -> None:
    """Raise :class:`UsageError` unless ``path`` is a readable, non-empty regular file."""
    p = Path(path)
    if not p.is_file():
        raise UsageError(f"{what} {path}: no such file")
    if not os.access(p, os.R_OK):
        raise UsageError(f"{what} {path}: not readable")
    if p.stat().st_size == 0:
        raise UsageError(f"{what} {path}: the file is empty")
