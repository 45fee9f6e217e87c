"""Logging and the options every command-line tool shares: ``--version``, ``-v``, ``-q``.

Diagnostics (what a program is doing, how long it waited, warnings) go through :mod:`logging`
to stderr with a timestamp and a level; results (KPI tables, the ``ready ...`` handshake lines
the harness waits for, file lists) stay plain ``print`` on stdout.

* ``-v/--verbose``: DEBUG, ``-q/--quiet``: WARNING, neither: INFO (or the level a parent
  program passed down in ``$RHONN_LOG_LEVEL``, so the plant and controller processes a
  harness starts follow the harness's ``-v``/``-q``);
* only the project's own loggers follow that level; other libraries log WARNING and above;
* ``--version`` prints ``PROG rhonn-tv X.Y.Z (controller core: ..., plant kernel: ...,
  python ...)`` from file and metadata look-ups alone (no numpy, no extension module);
  :func:`early_start`, called by the console scripts (:mod:`can_db.process.launch`),
  answers it before a program's heavy imports and says at once when a first start has
  caches to build.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import platform
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import psutil

ENV_LEVEL = "RHONN_LOG_LEVEL"
# the project's packages; their loggers (logging.getLogger(__name__)) and the programs' own
# loggers (named after the program, e.g. "rhonn-controller") follow -v/-q
PROJECT_LOGGERS = ("can_db", "controller", "plant_sim", "harness")
LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
DATE_FORMAT = "%Y-%m-%d %H:%M:%S"
LEVELS = {"DEBUG": logging.DEBUG, "INFO": logging.INFO, "WARNING": logging.WARNING}


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record (tests swap it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> Any:  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:  # StreamHandler.__init__ assigns it
        pass


_handler: _StderrHandler | None = None
_configured: set[str] = set()
_env_from_flag: list[bool] = []  # $RHONN_LOG_LEVEL was set here from -v/-q


def package_version() -> str:
    """The installed rhonn-tv version ("unknown" when not installed)."""
    try:
        return version("rhonn-tv")
    except PackageNotFoundError:
        return "unknown"


def _controller_core() -> str:
    """"C" when the compiled core is present (and not switched off), else "numpy"."""
    if os.environ.get("RHONN_BACKEND", "").strip() == "numpy":
        return "numpy (RHONN_BACKEND=numpy)"
    spec = importlib.util.find_spec("controller")  # a look-up; nothing is imported
    for base in (spec.submodule_search_locations or []) if spec else []:
        if any((Path(base) / "native").glob("_rhcore64*")):
            return "C"
    return "numpy (the C core is not built)"


def version_line(prog: str) -> str:
    """``PROG rhonn-tv X.Y.Z (controller core: C|numpy, plant kernel: numba|python, python
    X.Y.Z)`` — file and metadata look-ups only, so it is cheap."""
    kernel = "numba" if importlib.util.find_spec("numba") is not None else "python"
    return (f"{prog} rhonn-tv {package_version()} (controller core: {_controller_core()}, "
            f"plant kernel: {kernel}, python {platform.python_version()})")


ENTRY_POINTS = ("rhonn-harness", "rhonn-bench", "rhonn-plant", "rhonn-controller", "rhonn-bus")


# the module each entry point runs (its bytecode cache tells a first start from a later one)
ENTRY_MODULES = {"rhonn-harness": "harness/cli.py", "rhonn-bench": "harness/bench/cli.py",
                 "rhonn-plant": "plant_sim/process.py",
                 "rhonn-controller": "controller/runtime/process.py", "rhonn-bus": "can_db/cli.py"}
_noted_first_start: list[bool] = []


def _project_root() -> Path:
    return Path(__file__).resolve().parents[2]  # can_db/process/logsetup.py


def first_start_missing(prog: str) -> list[str]:
    """What a first start of ``prog`` still has to build: the project's bytecode cache and,
    for the programs that run the plant, numba's cache of the compiled vehicle step."""
    root = _project_root()
    missing = []
    module = root / ENTRY_MODULES.get(prog, "can_db/cli.py")
    if module.is_file() and not sys.dont_write_bytecode \
            and not Path(importlib.util.cache_from_source(str(module))).is_file():
        missing.append("Python bytecode caches")
    if prog in ("rhonn-harness", "rhonn-plant") and importlib.util.find_spec("numba"):
        base = os.environ.get("NUMBA_CACHE_DIR")
        where = Path(base) if base else root / "plant_sim" / "__pycache__"
        cached = where.is_dir() and any(where.rglob("kernel._advance-*.nbi"))
        if not cached:
            missing.append("the numba-compiled vehicle step")
    return missing


def early_start(prog: str) -> None:
    """Called by the console scripts (:mod:`can_db.process.launch`) before a program's heavy
    imports:

    * ``ENTRY_POINT --version``: print the version line and exit 0 (no numpy, scipy or
      python-can import, which take seconds on a cold start);
    * a first start after install (no bytecode or numba cache yet) with stderr on a terminal:
      one INFO line at once saying what the wait is for, instead of a minute of silence (not
      with -q or --help; not into pipes and files, where a bad argument's error must stay
      the only line).

    Any other command line passes through untouched.
    """
    if prog not in ENTRY_POINTS:
        return
    argv = sys.argv[1:]
    if argv == ["--version"]:
        print(version_line(prog), flush=True)
        raise SystemExit(0)
    quiet = {"-q", "--quiet", "-h", "--help"} & set(argv) \
        or os.environ.get(ENV_LEVEL, "").strip().upper() == "WARNING"
    if quiet or _noted_first_start or not sys.stderr.isatty():
        return
    _noted_first_start.append(True)
    missing = first_start_missing(prog)
    if missing:
        record = logging.LogRecord(prog, logging.INFO, __file__, 0,
                                   "first start after install: building %s (up to about a "
                                   "minute; later starts take seconds) ...",
                                   (" and ".join(missing),), None)
        sys.stderr.write(logging.Formatter(LOG_FORMAT, DATE_FORMAT).format(record) + "\n")
        sys.stderr.flush()


class _VersionAction(argparse.Action):
    """``--version``: the version line on stdout, exit 0 (built only when asked)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS,
                 default: Any = argparse.SUPPRESS, help: str | None = None,
                 prog: str = "") -> None:
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)
        self.version_prog = prog

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        print(version_line(self.version_prog or parser.prog.split()[0]), flush=True)
        parser.exit(0)


def add_logging_options(parser: argparse.ArgumentParser, *, top: bool = True) -> None:
    """``-v/--verbose`` and ``-q/--quiet`` (and ``--version`` when ``top``).

    A program with commands adds them to the top parser (``top=True``) and to every command's
    parser (``top=False``), so both ``PROG -v COMMAND`` and ``PROG COMMAND -v`` work.
    """
    if top:
        parser.add_argument("--version", action=_VersionAction,
                            help="print the program, package and backend versions and exit")
    group = parser.add_mutually_exclusive_group()
    # a command's copy must not overwrite the top parser's value with its default
    default: Any = False if top else argparse.SUPPRESS
    group.add_argument("-v", "--verbose", action="store_true", default=default,
                       help="diagnostics down to DEBUG on stderr")
    group.add_argument("-q", "--quiet", action="store_true", default=default,
                       help="only warnings and errors on stderr (results still on stdout)")


def level_of(verbose: bool = False, quiet: bool = False) -> int:
    """The log level of ``-v``/``-q``; without either, ``$RHONN_LOG_LEVEL`` or INFO."""
    if verbose:
        return logging.DEBUG
    if quiet:
        return logging.WARNING
    return LEVELS.get(os.environ.get(ENV_LEVEL, "").strip().upper(), logging.INFO)


def setup_logging(prog: str, verbose: bool = False, quiet: bool = False) -> logging.Logger:
    """Configure logging for the program ``prog`` and return its logger.

    Idempotent (a ``main`` called twice in one process keeps one handler). An explicit
    ``-v``/``-q`` is passed down to child processes through ``$RHONN_LOG_LEVEL``.
    """
    global _handler
    if not (verbose or quiet) and _env_from_flag:
        # a second main() in one process (tests) without -v/-q: not the first one's level
        os.environ.pop(ENV_LEVEL, None)
        _env_from_flag.clear()
    level = level_of(verbose, quiet)
    if verbose or quiet:
        os.environ[ENV_LEVEL] = logging.getLevelName(level)
        _env_from_flag.append(True)
    root = logging.getLogger()
    if _handler is None:
        _handler = _StderrHandler()
        _handler.setFormatter(logging.Formatter(LOG_FORMAT, DATE_FORMAT))
    if _handler not in root.handlers:
        root.addHandler(_handler)
    if root.level == logging.NOTSET or root.level > logging.WARNING:
        root.setLevel(logging.WARNING)  # other libraries: warnings and errors
    for name in (*PROJECT_LOGGERS, prog, *_configured):
        logging.getLogger(name).setLevel(level)
    _configured.add(prog)
    log = logging.getLogger(prog)
    log.debug("log level %s; %s", logging.getLevelName(level), " ".join(sys.argv))
    return log


def process_age_s() -> float:
    """Wall-clock seconds since this process started (its imports included), s."""
    return max(0.0, time.time() - psutil.Process().create_time())


def logging_args(args: argparse.Namespace) -> tuple[bool, bool]:
    """``(verbose, quiet)`` of parsed options (False where the option is absent)."""
    return bool(getattr(args, "verbose", False)), bool(getattr(args, "quiet", False))
