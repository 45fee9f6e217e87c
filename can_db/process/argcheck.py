"""Argument checks shared by every command-line tool, run before anything starts.

A bad argument ends the program with one line on stderr and exit code 2, before any process,
server, file or directory is created:

* :class:`OneLineParser` — an ``argparse`` parser whose errors are one line (no usage dump);
* :func:`number` — an ``argparse`` type for a number in a range (with its unit in the error);
* :func:`check_out_dir` / :func:`check_out_file` — an output path that can be written;
* :func:`seed_spec` / :func:`add_jobs_option` — ``--seeds SPEC`` and ``--jobs N``, the same
  meaning in every command that has them.

Conventions of every entry point (docs/cli.md): errors are ``PROG [COMMAND]: error: MESSAGE``
on stderr with exit code 2; metavars name the unit or kind (``--duration S``, ``--speed KMH``,
``--mu MU``, ``--jobs N``, ``--seeds SPEC``); ``--seeds SPEC`` is a list of seeds (``0,3,7``,
``1-5``, ``1-3,9``; a bare ``5`` is the one seed 5); parallelism is ``--jobs N``.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import socket
import sys
from collections.abc import Callable, Iterable
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


# metavars by what the value is (docs/cli.md): files, directories, bus specs, lists
METAVARS = {
    "bus": "SPEC", "out": "DIR", "json": "FILE", "md": "FILE", "config": "FILE",
    "trace": "FILE", "summary": "FILE", "timing": "FILE", "rerun": "FILE",
    "checkpoint": "FILE", "secoc_state": "FILE", "secoc_keys": "SRC", "scheduler": "ADDRESS",
    "sections": "LIST", "messages": "LIST", "port": "PORT", "dashboard": "PORT",
}


def default_metavar(dest: str, kind: object = None) -> str | None:
    """The conventional metavar of an option: by name (``METAVARS``), else by unit suffix
    (``_ms`` → MS, ``_s`` → S), else ``N`` for an integer; None: argparse's own."""
    if dest in METAVARS:
        return METAVARS[dest]
    if dest.endswith("_ms"):
        return "MS"
    if dest.endswith("_s") or dest == "timeout":
        return "S"
    if kind is int or getattr(kind, "__name__", "") == "int":
        return "N"
    return None


class OneLineParser(argparse.ArgumentParser):
    """``argparse`` parser whose errors are one line on stderr, exit code 2, and whose
    options get the conventional metavar (:func:`default_metavar`) unless they name one."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def add_argument(self, *args, **kwargs):  # type: ignore[override]
        """``argparse``'s, with the conventional metavar for a value option without one."""
        options = [a for a in args if isinstance(a, str) and a.startswith("--")]
        if options and "metavar" not in kwargs and "choices" not in kwargs \
                and kwargs.get("action") in (None, "store", "append"):
            dest = kwargs.get("dest") or options[0][2:].replace("-", "_")
            metavar = default_metavar(dest, kwargs.get("type"))
            if metavar is not None:
                kwargs["metavar"] = metavar
        return super().add_argument(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        """Print ``PROG: error: MESSAGE (see PROG --help)`` and exit 2."""
        usage_exit(self.prog, f"{message} (see {self.prog} --help)")

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        """As ``argparse``, but an unrecognised argument after a command is reported by that
        command's parser (``PROG COMMAND: error: ...``), as every other error of it is."""
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:
            owner: argparse.ArgumentParser = self
            for action in self._actions:
                if isinstance(action, argparse._SubParsersAction):
                    owner = action.choices.get(getattr(parsed, action.dest, None), self)
            owner.error(f"unrecognized arguments: {' '.join(extras)}")
        return parsed


def error_line(prog: str, message: str) -> int:
    """Write ``PROG: error: MESSAGE`` as one line on stderr; return exit code 2 (for a
    command that reports bad input found while it works and returns its exit code)."""
    text = " ".join(str(message).split())  # one line, whatever the message held
    sys.stderr.write(f"{prog}: error: {text}\n")
    return 2


def usage_exit(prog: str, message: str) -> NoReturn:
    """One line on stderr, exit code 2."""
    raise SystemExit(error_line(prog, message))


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


SEEDS_MAX = 10_000  # more seeds than any study runs: a typo such as 1-100000 is caught early


def seed_spec(text: str) -> tuple[int, ...]:
    """``argparse`` type of ``--seeds SPEC``: comma-separated seeds (integers >= 0) and
    inclusive ranges ``A-B``, in the order given: ``"0,3,7"`` → (0, 3, 7), ``"1-5"`` →
    (1, 2, 3, 4, 5), ``"5"`` → (5,). A seed given twice is an error."""
    hint = "(SPEC: seeds >= 0 and ranges A-B, comma-separated, e.g. 0,3,7 or 1-5)"
    items = [t.strip() for t in str(text).split(",")]
    if not any(items):
        raise argparse.ArgumentTypeError(f"no seeds given {hint}")
    seeds: list[int] = []
    for item in items:
        lo_text, dash, hi_text = item.partition("-")
        try:
            lo = int(lo_text)
            hi = int(hi_text) if dash else lo
        except ValueError:
            raise argparse.ArgumentTypeError(f"{item!r} is not a seed or range {hint}") from None
        if lo < 0 or hi < lo:
            raise argparse.ArgumentTypeError(f"{item!r} is not a seed or range {hint}")
        if len(seeds) + hi - lo + 1 > SEEDS_MAX:
            raise argparse.ArgumentTypeError(f"{text!r}: more than {SEEDS_MAX} seeds")
        seeds.extend(range(lo, hi + 1))
    seen: set[int] = set()
    twice = sorted({s for s in seeds if s in seen or seen.add(s)})
    if twice:
        raise argparse.ArgumentTypeError(
            f"seed {', '.join(map(str, twice))} given twice in {text!r}")
    return tuple(seeds)


seed_spec.__name__ = "seed spec"  # argparse names the type in its messages


def seed_text(seeds: Iterable[int]) -> str:
    """The seeds written as ``--seeds`` takes them, the inverse of :func:`seed_spec`: a run
    of consecutive rising seeds as a range, ``(1, 2, 3, 4, 5)`` → ``1-5``, ``(0, 3, 7)`` →
    ``0,3,7``, ``(4,)`` → ``4`` (for reports, instead of a Python list)."""
    runs: list[list[int]] = []
    for seed in seeds:
        if runs and seed == runs[-1][1] + 1:
            runs[-1][1] = seed
        else:
            runs.append([seed, seed])
    return ",".join(f"{lo}-{hi}" if hi > lo else str(lo) for lo, hi in runs)

JOBS_MAX = 64


class _DeprecatedAlias(argparse.Action):
    """A hidden old spelling of an option: stores into the new option's dest and prints one
    ``PROG: warning: ...`` line on stderr."""

    def __init__(self, option_strings: list[str], dest: str, new: str = "", **kwargs) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.new = new

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> None:
        sys.stderr.write(f"{parser.prog}: warning: {option_string} is deprecated, "
                         f"use {self.new}\n")
        setattr(namespace, self.dest, values)


def add_jobs_option(parser: argparse.ArgumentParser, default: int, help: str,
                    deprecated: tuple[str, ...] = ()) -> None:
    """``--jobs N`` (1 .. JOBS_MAX parallel runs), plus hidden ``deprecated`` spellings of it
    that still work with a one-line warning."""
    kind = number(int, lo=1, hi=JOBS_MAX)
    parser.add_argument("--jobs", type=kind, default=default, metavar="N", help=help)
    for old in deprecated:
        parser.add_argument(old, dest="jobs", type=kind, action=_DeprecatedAlias,
                            new="--jobs", help=argparse.SUPPRESS)


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
    exists and is writable; an existing file must be a writable regular file). An empty
    path (``--trace=``) is refused: it would silently mean "no file"."""
    if not str(path):
        raise UsageError(f"{what}: empty path (give a file)")
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
