"""Compiled kernels of the controller hot path, beside the readable numpy reference.

Every kernel here computes the same numbers as a plain numpy/Python method elsewhere in
``controller.core`` (the reference, named in each kernel's docstring); tests compare the
two on recorded inputs (≤ 1e-9) and the reference stays the specification.

The kernels are compiled with numba (``@njit(cache=True)``). Selection is by config
(``[mpc] kernels = "numba" | "numpy"``); if numba cannot be imported, ``AVAILABLE`` is
False and every caller keeps the numpy reference path (no error: the controller is the
same, only slower). ``warm_up()`` compiles (or loads from numba's on-disk cache) every
kernel for both precisions; the controller factory calls it before a controller exists,
so a process reports ready only with compiled kernels.

Cache: numba writes its cache next to these sources (``__pycache__``) or, when that is
not writable, to its per-user cache directory; ``NUMBA_CACHE_DIR`` overrides both. A
fresh clone compiles once (a few seconds per precision) and loads from the cache after.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

try:  # numba is optional: without it the numpy reference path is used
    from numba import njit as _njit

    AVAILABLE = True
except Exception:  # pragma: no cover - exercised only on machines without numba
    AVAILABLE = False
    _njit = None

KERNEL_CHOICES = ("numba", "numpy")
PRECISIONS = ("float64", "float32")


def njit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit(cache=True)`` when numba is importable, else the function unchanged."""
    if _njit is None:
        return fn
    return _njit(cache=True, nogil=True)(fn)


def use_kernels(choice: str) -> bool:
    """True when the compiled kernels should run for config value ``choice``.

    Raises ValueError for a value outside KERNEL_CHOICES (a typo must not pass)."""
    if choice not in KERNEL_CHOICES:
        raise ValueError(f"mpc.kernels must be one of {KERNEL_CHOICES}, not {choice!r}")
    return choice == "numba" and AVAILABLE


def dtype_of(precision: str) -> Any:
    """numpy dtype for config value ``precision`` ("float64" | "float32")."""
    import numpy as np

    if precision not in PRECISIONS:
        raise ValueError(f"mpc.precision must be one of {PRECISIONS}, not {precision!r}")
    return np.float32 if precision == "float32" else np.float64
