"""OSQP's generated C solver (``OSQP.codegen``), built locally and called through a C shim.

The Python osqp path (``LinearizedMpc`` with ``qp_backend = "osqp"``) spends most of a
round in the wrapper; the generated code runs the same ADMM on a workspace that is a set
of C globals. This module

1. generates the code of a set-up OSQP problem (``parameters="matrices"``: q, l, u and the
   values of P and A may change; the sparsity may not), in a temporary folder;
2. compiles it with the system C compiler (``$CC``, else ``cc``; flags ``CFLAGS`` below,
   no -ffast-math) together with ``SHIM_C``: plain functions that update q / l / u / P_x,
   warm start, solve and copy x and y into buffers bound once (no pybind11, no network;
   the generated setup.py / CMakeLists.txt / bindings.cpp are not used);
3. caches the library under ``cache_dir()`` keyed by a SHA-256 of the generated sources
   (generation dates removed), the shim, the compiler's ``--version`` and the flags; the
   file is written under a temporary name and renamed into place (``os.replace``), so
   processes that build at the same time do not see half-written files;
4. loads a **private copy per solver instance**: the generated workspace is a C global, so
   two instances must not share one loaded library. Each instance copies the cached file
   to a uniquely named file, ``dlopen``s it (RTLD_LOCAL; a distinct file, so the dynamic
   loader maps a new copy with its own globals — glibc would return the already-loaded
   object for the same path or the same inode) and removes the copy at once (the mapping
   stays valid). All symbols but the shim's are hidden (``-fvisibility=hidden``), so no
   copy can bind to another copy's globals. Cost: ≈ 1 ms and ≈ 60 kB per instance, unmapped
   (``dlclose``) when the instance is garbage collected.

Availability: ``$RHONN_NO_CC=1``, no compiler, or a failed generation/compile/load raise
``EmbeddedBuildError`` with the reason; the caller (``LinearizedMpc``) falls back to the
Python osqp path. Nothing here runs inside ``step()``: the build happens at construction.

Numba: ``EmbeddedOsqp.round_wap()`` is a first-class-function object (numba's wrapper
address protocol) for the shim's ``rh_round(flags)``; a ``@njit`` function can take it as
an argument and call it, so a compiled step kernel can run pre-QP → solve → post in one
call. The buffers it updates are the numpy arrays bound at construction.

Algorithm: OSQP 1.1's embedded mode 2 runs the same iteration as the library (update_data_mat
re-scales and re-factors, adaptive ρ by iteration count is kept); what it leaves out is
polishing, time limits and printing, all off in ``QpConfig``. Whether the numbers are the
same is tested (tests/test_osqp_embedded.py), not assumed.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import re
import shutil
import subprocess
import tempfile
import threading
import uuid
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

PREFIX = "rh_"
CFLAGS = ("-O3", "-fPIC", "-shared", "-fvisibility=hidden", "-std=gnu99", "-w")
BACKENDS = ("auto", "osqp", "embedded")
OSQP_INFTY = 1e30
STATUS_SHIFT = 64   # rh_round returns iterations * STATUS_SHIFT + status_val (status < 64)

# The shim: functions with default visibility; everything generated stays hidden.
SHIM_C = r"""
#include "osqp.h"
#include "types.h"
#include "algebra_matrix.h"
#include "@PREFIX@workspace.h"
#define RH_API __attribute__((visibility("default")))

static const OSQPFloat *g_q, *g_l, *g_u, *g_px;
static OSQPFloat *g_x, *g_y;

static void copy_out(OSQPFloat *x, OSQPFloat *y) {
  OSQPInt i, n = @PREFIX@solver.work->data->n, m = @PREFIX@solver.work->data->m;
  for (i = 0; i < n; i++) x[i] = @PREFIX@solver.solution->x[i];
  for (i = 0; i < m; i++) y[i] = @PREFIX@solver.solution->y[i];
}

/* dims[0] = n, dims[1] = m, dims[2] = nnz(P), dims[3] = nnz(A), dims[4] = sizeof(OSQPInt) */
RH_API void rh_dims(long long *dims) {
  OSQPSolver *s = &@PREFIX@solver;
  dims[0] = s->work->data->n;
  dims[1] = s->work->data->m;
  dims[2] = OSQPMatrix_get_nz(s->work->data->P);
  dims[3] = OSQPMatrix_get_nz(s->work->data->A);
  dims[4] = (long long)sizeof(OSQPInt);
}

/* Bind the buffers rh_round reads (q n, l m, u m, P_x nnz(P)) and writes (x n, y m). */
RH_API void rh_bind(const double *q, const double *l, const double *u, const double *px,
                    double *x, double *y) {
  g_q = q; g_l = l; g_u = u; g_px = px; g_x = x; g_y = y;
}

/* One round on the bound buffers: update q (and l, u when flags & 1), update P_x, solve,
   copy x and y out. Returns iterations * 64 + status_val; the same call sequence as the
   Python extension's update_data_vec / update_data_mat / solve. */
RH_API long long rh_round(int flags) {
  OSQPSolver *s = &@PREFIX@solver;
  if (flags & 1) osqp_update_data_vec(s, g_q, g_l, g_u);
  else osqp_update_data_vec(s, g_q, OSQP_NULL, OSQP_NULL);
  osqp_update_data_mat(s, g_px, OSQP_NULL, OSQPMatrix_get_nz(s->work->data->P),
                       OSQP_NULL, OSQP_NULL, 0);
  osqp_solve(s);
  copy_out(g_x, g_y);
  return (long long)s->info->iter * 64 + (long long)s->info->status_val;
}

/* Wrapper-style calls (NULL = leave as is). */
RH_API int rh_update(const double *q, const double *l, const double *u, const double *px) {
  OSQPSolver *s = &@PREFIX@solver;
  int e = 0;
  if (q || l || u) e = (int)osqp_update_data_vec(s, q, l, u);
  if (px) e |= (int)osqp_update_data_mat(s, px, OSQP_NULL,
                                          OSQPMatrix_get_nz(s->work->data->P),
                                          OSQP_NULL, OSQP_NULL, 0) << 4;
  return e;
}

RH_API long long rh_solve(double *x, double *y) {
  OSQPSolver *s = &@PREFIX@solver;
  osqp_solve(s);
  copy_out(x, y);
  return (long long)s->info->iter * 64 + (long long)s->info->status_val;
}

RH_API int rh_warm_start(const double *x, const double *y) {
  return (int)osqp_warm_start(&@PREFIX@solver, x, y);
}
""".replace("@PREFIX@", PREFIX)

_SHIM_FUNCS = ("rh_dims", "rh_bind", "rh_round", "rh_update", "rh_solve", "rh_warm_start")
_DATE_LINE = re.compile(rb"This file was autogenerated by OSQP on [^\n]*")
_lock = threading.Lock()
_built: dict[str, Path] = {}        # problem key → cached library (this process)
_cc_version: dict[str, str] = {}


class EmbeddedBuildError(RuntimeError):
    """The generated solver cannot be used here (the message says why)."""


def cache_dir() -> Path:
    """``$RHONN_CACHE_DIR/osqp``, else ``$XDG_CACHE_HOME/rhonn-tv/osqp`` (``~/.cache``)."""
    base = os.environ.get("RHONN_CACHE_DIR")
    if base:
        return Path(base) / "osqp"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "rhonn-tv" / "osqp"


def compiler() -> str:
    """Path of the C compiler (``$CC`` or ``cc``); EmbeddedBuildError when none is usable
    or ``$RHONN_NO_CC=1``."""
    if os.environ.get("RHONN_NO_CC", "") not in ("", "0"):
        raise EmbeddedBuildError("RHONN_NO_CC is set")
    cc = os.environ.get("CC") or "cc"
    path = shutil.which(cc)
    if path is None:
        raise EmbeddedBuildError(f"no C compiler ({cc!r} not found)")
    if path not in _cc_version:
        try:
            out = subprocess.run([path, "--version"], capture_output=True, text=True,
                                 timeout=30, check=True).stdout
        except (OSError, subprocess.SubprocessError) as exc:
            raise EmbeddedBuildError(f"C compiler {path} does not run: {exc}") from exc
        _cc_version[path] = out
    return path


def problem_key(P: Any, q: np.ndarray, A: Any, lo: np.ndarray, hi: np.ndarray,
                settings: dict[str, Any]) -> str:
    """SHA-256 of everything the generated code depends on at setup (data, sparsity,
    settings, osqp version); the in-process memo of built libraries uses it."""
    import osqp

    h = hashlib.sha256(str(getattr(osqp, "__version__", "")).encode())
    for M in (P, A):
        for arr in (M.indptr, M.indices, M.data):
            h.update(np.ascontiguousarray(arr).tobytes())
        h.update(repr(M.shape).encode())
    for v in (q, lo, hi):
        h.update(np.ascontiguousarray(v, dtype=float).tobytes())
    h.update(repr(sorted(settings.items())).encode())
    return h.hexdigest()


def build(P: Any, q: np.ndarray, A: Any, lo: np.ndarray, hi: np.ndarray,
          settings: dict[str, Any]) -> Path:
    """Path of the compiled library for this problem (generated, compiled and cached on
    first use). P: upper-triangular CSC (n, n); A: CSC (m, n); settings: OSQP setup()
    keywords. Raises EmbeddedBuildError with the reason when it cannot be built."""
    cc = compiler()
    key = problem_key(P, q, A, lo, hi, settings) + cc
    with _lock:
        hit = _built.get(key)
        if hit is not None and hit.exists():
            return hit
        lib = _generate_and_compile(P, q, A, lo, hi, settings, cc)
        _built[key] = lib
        return lib


def _generate_and_compile(P: Any, q: np.ndarray, A: Any, lo: np.ndarray, hi: np.ndarray,
                          settings: dict[str, Any], cc: str) -> Path:
    import osqp

    with tempfile.TemporaryDirectory(prefix="rhonn-osqpgen-") as tmp:
        src = Path(tmp) / "gen"
        try:
            solver = osqp.OSQP()
            solver.setup(P, q, A, lo, hi, **settings)
            solver.codegen(str(src), parameters="matrices", prefix=PREFIX, compile=False,
                           force_rewrite=True)
        except Exception as exc:   # osqp raises plain ValueError/RuntimeError here
            raise EmbeddedBuildError(f"OSQP code generation failed: {exc}") from exc
        (src / "rh_shim.c").write_text(SHIM_C)
        files = sorted([*src.glob("src/*.c"), src / f"{PREFIX}workspace.c", src / "rh_shim.c"])
        headers = sorted([*src.glob("inc/**/*.h"), *src.glob("*.h")])
        h = hashlib.sha256()
        for f in [*files, *headers]:
            h.update(str(f.relative_to(src)).encode())
            h.update(_DATE_LINE.sub(b"", f.read_bytes()))
        h.update(_cc_version[cc].encode())
        h.update(cc.encode())
        h.update(" ".join(CFLAGS).encode())
        out_dir = cache_dir()
        target = out_dir / f"osqp-{h.hexdigest()[:32]}.so"
        if target.exists():
            return target
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp_lib = out_dir / f".{target.name}.{os.getpid()}.{uuid.uuid4().hex}"
        cmd = [cc, *CFLAGS, f"-I{src / 'inc' / 'public'}", f"-I{src / 'inc' / 'private'}",
               f"-I{src}", *map(str, files), "-o", str(tmp_lib), "-lm"]
        try:
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        except (OSError, subprocess.SubprocessError) as exc:
            raise EmbeddedBuildError(f"C compiler failed to run: {exc}") from exc
        if res.returncode != 0:
            tmp_lib.unlink(missing_ok=True)
            msg = (res.stderr or res.stdout).strip().splitlines()[-1:] or ["?"]
            raise EmbeddedBuildError(f"compile failed ({cc}): {msg[0]}")
        os.replace(tmp_lib, target)
        return target


def _load_private_copy(lib: Path) -> ctypes.CDLL:
    """dlopen a fresh copy of ``lib`` (own globals = own OSQP workspace)."""
    tmp_dir = Path(tempfile.gettempdir()) / f"rhonn-osqp-{os.getuid()}"
    tmp_dir.mkdir(mode=0o700, exist_ok=True)
    copy = tmp_dir / f"{uuid.uuid4().hex}.so"   # a name never loaded before in this process
    shutil.copyfile(lib, copy)
    try:
        return ctypes.CDLL(str(copy), mode=os.RTLD_LOCAL | os.RTLD_NOW)
    finally:
        copy.unlink(missing_ok=True)


class _Info:
    """``iter`` and ``status_val`` of the last solve (the extension object's ``info``)."""

    __slots__ = ("iter", "status_val")

    def __init__(self) -> None:
        self.iter = 0
        self.status_val = 11   # OSQP_UNSOLVED


class _Solution:
    """``x`` (n,): the buffer every solve rewrites (read it before the next solve);
    ``y`` (m,): a copy of the dual buffer ``y_buf`` (as the extension's ``solution.y``,
    which is a new array per read, so a kept ``y`` is a snapshot)."""

    __slots__ = ("x", "y_buf")

    def __init__(self, n: int, m: int) -> None:
        self.x = np.zeros(n)
        self.y_buf = np.zeros(m)

    @property
    def y(self) -> np.ndarray:
        return self.y_buf.copy()


class _Result:
    __slots__ = ("info", "x", "y")


_DP = ctypes.c_void_p


class EmbeddedOsqp:
    """One generated OSQP solver (its own copy of the library and workspace).

    Offers the subset of ``osqp.OSQP`` and of its extension object that ``LinearizedMpc``
    uses: ``update(q=, Px=, l=, u=)``, ``solve(raise_error=)``, ``warm_start(x=, y=)``,
    ``update_data_vec(q, l, u)``, ``update_data_mat(P_x, P_i, A_x, A_i)``, ``solve()``,
    ``info``, ``solution`` and ``_solver`` (itself); plus the fast ``round(bounds)`` on
    buffers bound once with ``bind()``."""

    def __init__(self, lib_path: Path) -> None:
        lib = _load_private_copy(lib_path)
        for name in _SHIM_FUNCS:
            if not hasattr(lib, name):
                raise EmbeddedBuildError(f"{lib_path.name} lacks {name}")
        lib.rh_dims.argtypes = [_DP]
        lib.rh_dims.restype = None
        lib.rh_bind.argtypes = [_DP] * 6
        lib.rh_bind.restype = None
        lib.rh_round.argtypes = [ctypes.c_int]
        lib.rh_round.restype = ctypes.c_longlong
        lib.rh_update.argtypes = [_DP] * 4
        lib.rh_update.restype = ctypes.c_int
        lib.rh_solve.argtypes = [_DP, _DP]
        lib.rh_solve.restype = ctypes.c_longlong
        lib.rh_warm_start.argtypes = [_DP, _DP]
        lib.rh_warm_start.restype = ctypes.c_int
        self._lib = lib
        dims = np.zeros(5, np.int64)
        lib.rh_dims(dims.ctypes.data)
        self.n, self.m, self.nnz_p, self.nnz_a = (int(v) for v in dims[:4])
        self.info = _Info()
        self.solution = _Solution(self.n, self.m)
        self._round = lib.rh_round
        self._bound: tuple[np.ndarray, ...] = ()

    def __del__(self) -> None:
        """Unmap this instance's library copy (nothing else holds its addresses: the numba
        function object of round_wap() keeps this instance alive)."""
        lib = getattr(self, "_lib", None)
        if lib is not None:
            self._lib = None
            try:
                import _ctypes

                _ctypes.dlclose(lib._handle)
            except Exception:   # pragma: no cover - interpreter shutdown or no dlclose
                pass

    @property
    def _solver(self) -> EmbeddedOsqp:
        """The object with the extension-style calls (this one)."""
        return self

    # ---------------------------------------------------------------- fast path
    def bind(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, px: np.ndarray) -> None:
        """Bind the float64 buffers ``round`` reads: q (n,), l, u (m,), P_x (nnz(P),) in the
        CSC order of the set-up P. They are kept referenced here (and must not be
        reallocated by the caller: write into them in place)."""
        arrs = tuple(self._check(a, k, name) for a, k, name in (
            (q, self.n, "q"), (lo, self.m, "l"), (hi, self.m, "u"), (px, self.nnz_p, "P_x")))
        self._bound = (*arrs, self.solution.x, self.solution.y_buf)
        self._lib.rh_bind(*(a.ctypes.data for a in self._bound))

    def round(self, bounds: bool) -> tuple[int, int]:
        """update q (+ l, u when ``bounds``) and P_x from the bound buffers, solve;
        returns (iterations, OSQP status_val); x and y are in ``solution``."""
        it, st = divmod(self._round(1 if bounds else 0), STATUS_SHIFT)
        self.info.iter = it
        self.info.status_val = st
        return it, st

    def round_address(self) -> int:
        """Address of ``long long rh_round(int flags)`` (valid while this object lives)."""
        return ctypes.cast(self._round, ctypes.c_void_p).value or 0

    def round_wap(self) -> Any:
        """``rh_round`` as a numba first-class function ``int64(int32)`` (wrapper address
        protocol): pass it to an ``@njit`` function and call it there. Requires bind()."""
        from numba import types

        owner = self

        class _RoundWap(types.WrapperAddressProtocol):
            def __wrapper_address__(self) -> int:
                return owner.round_address()

            def signature(self) -> Any:
                return types.int64(types.int32)

        return _RoundWap()

    # ---------------------------------------------------------------- extension-style
    @staticmethod
    def _check(a: Any, size: int, name: str) -> np.ndarray:
        arr = np.ascontiguousarray(a, dtype=np.float64)
        if arr.shape != (size,):
            raise ValueError(f"{name}: expected shape ({size},), got {arr.shape}")
        return arr

    def update_data_vec(self, q: Any, l: Any, u: Any) -> int:  # noqa: E741 (OSQP's names)
        """osqp_update_data_vec (None = unchanged)."""
        return self.update(q=q, l=l, u=u)

    def update_data_mat(self, P_x: Any, P_i: Any = None, A_x: Any = None,
                        A_i: Any = None) -> int:
        """osqp_update_data_mat for all of P_x (partial updates and A are not offered)."""
        if P_i is not None or A_x is not None or A_i is not None:
            raise NotImplementedError("only a full P_x update is offered")
        return self.update(Px=P_x)

    def update(self, q: Any = None, l: Any = None, u: Any = None,  # noqa: E741
               Px: Any = None) -> int:
        """Like ``osqp.OSQP.update`` for q, l, u and all of P_x; returns OSQP's exit flags
        (bit 0–3: vectors, bit 4+: matrix)."""
        if l is not None:   # as osqp.OSQP.update: bounds clipped to ±OSQP_INFTY (1e30)
            l = np.maximum(l, -OSQP_INFTY)  # noqa: E741
        if u is not None:
            u = np.minimum(u, OSQP_INFTY)
        args = [None if a is None else self._check(a, k, name) for a, k, name in (
            (q, self.n, "q"), (l, self.m, "l"), (u, self.m, "u"), (Px, self.nnz_p, "Px"))]
        return int(self._lib.rh_update(*(None if a is None else a.ctypes.data
                                          for a in args)))

    def solve(self, raise_error: bool = False) -> Any:
        """Solve; returns an object with ``x``, ``y`` (copies) and ``info`` (iter,
        status_val) like ``osqp.OSQP.solve``. ``raise_error`` is accepted and ignored."""
        sol = self.solution
        it, st = divmod(int(self._lib.rh_solve(sol.x.ctypes.data, sol.y_buf.ctypes.data)),
                        STATUS_SHIFT)
        self.info.iter, self.info.status_val = it, st
        res = _Result()
        res.x, res.y = sol.x.copy(), sol.y
        info = _Info()
        info.iter, info.status_val = it, st
        res.info = info
        return res

    def warm_start(self, x: Any = None, y: Any = None) -> None:
        """osqp_warm_start with x (n,) and/or y (m,) in unscaled units."""
        xa = None if x is None else self._check(x, self.n, "x")
        ya = None if y is None else self._check(y, self.m, "y")
        self._lib.rh_warm_start(None if xa is None else xa.ctypes.data,
                                None if ya is None else ya.ctypes.data)


def make_solver(P: Any, q: np.ndarray, A: Any, lo: np.ndarray, hi: np.ndarray,
                settings: dict[str, Any]) -> EmbeddedOsqp:
    """Build (or take from the cache) and load a private generated solver for this
    problem. Raises EmbeddedBuildError with the reason."""
    try:
        lib = build(P, q, A, lo, hi, settings)
    except OSError as exc:   # e.g. a cache or temporary directory that cannot be written
        raise EmbeddedBuildError(f"cannot build: {exc}") from exc
    try:
        return EmbeddedOsqp(lib)
    except OSError as exc:
        raise EmbeddedBuildError(f"cannot load {lib}: {exc}") from exc


_warned: set[str] = set()


def note_fallback(reason: str) -> None:
    """One log line per process and reason: the Python osqp path is used instead."""
    if reason not in _warned:
        _warned.add(reason)
        log.warning("qp_backend auto: generated OSQP solver not used (%s); "
                    "using the Python osqp path", reason)
