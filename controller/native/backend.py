"""Which backend runs a controller: the C core (built at install) or the numpy reference.

``core_module(float32)`` is the extension module of that precision, or None when it was not
built (no C compiler at install, ``RHONN_NO_CC=1``) or ``RHONN_BACKEND=numpy`` asks for the
reference; ``unavailable_reason`` says why, once per process, on the log.
"""

from __future__ import annotations

import importlib
import logging
import os
from types import ModuleType

log = logging.getLogger(__name__)
BACKENDS = ("auto", "native", "numpy")
_MODULES = {False: "controller.native._rhcore64", True: "controller.native._rhcore32"}
_noted: set[str] = set()


def core_module(float32: bool) -> ModuleType | None:
    """The built core of that precision, or None (see unavailable_reason)."""
    try:
        return importlib.import_module(_MODULES[float32])
    except ImportError:
        return None


def unavailable_reason(float32: bool) -> str | None:
    """Why the C core cannot run here (None when it can)."""
    if core_module(float32) is None:
        return ("the C core is not built (no C compiler at install, or RHONN_NO_CC=1); "
                "reinstall with a C compiler to get it")
    return None


def requested_backend() -> str:
    """``RHONN_BACKEND`` (auto | native | numpy), default auto."""
    b = os.environ.get("RHONN_BACKEND", "auto").strip() or "auto"
    if b not in BACKENDS:
        raise ValueError(f"RHONN_BACKEND={b!r}: choose one of {BACKENDS}")
    return b


def note_numpy(reason: str) -> None:
    """One log line per process and reason: the numpy reference runs instead of the core."""
    if reason not in _noted:
        _noted.add(reason)
        log.warning("controller backend: numpy reference (%s)", reason)
