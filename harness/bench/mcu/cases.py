"""The cases of `rhonn-bench mcu`: the rhonn.c kernel demo and the full controller step
(:func:`full_core_case`), its bounds and the replay of a host controller on recorded inputs."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from controller.core.interfaces import ControllerInputs
from controller.core.model.rhonn import MONO_INDEX, PHI_SUBSETS, TFAC_INDEX
from controller.core.registry import load_controller_config
from controller.native import osqp_gen
from controller.native.backend import core_module
from controller.native.build_tools import SRC_DIR
from controller.native.config import ctrl_config
from controller.registry import make_controller
from harness.bench.controller_step import recorded_inputs, set_toml_keys
from harness.bench.mcu.case import (
    MCU_DIR,
    McuCase,
    c_float_array,
    ctrl_layouts,
    ctrl_step_case,
)
from harness.bench.mcu.layout import FlatLayout

EPS32 = float(np.finfo(np.float32).eps)


def rhonn_demo_reference(inputs: np.ndarray, mu: np.ndarray, beta: np.ndarray,
                         W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 numpy reference of the demo step (xi, phi, bilinear C) in the C operation order,
    and the magnitude M (same computation on absolute values, float64) for the bound."""
    def forward(x: np.ndarray, mu_: np.ndarray, beta_: np.ndarray, W_: np.ndarray,
                dtype: type, absval: bool) -> np.ndarray:
        x = x.astype(dtype)
        xi = mu_.astype(dtype) * np.tanh(beta_.astype(dtype) * x)
        if absval:
            xi = np.abs(xi)
        phi = np.empty((x.shape[0], len(PHI_SUBSETS)), dtype=dtype)
        for k, s in enumerate(PHI_SUBSETS):  # left-to-right products, as rh_rhonn_phi
            p = xi[:, s[0]]
            for j in s[1:]:
                p = p * xi[:, j]
            phi[:, k] = p
        a, d = xi[:, 0], xi[:, 3]
        t = np.stack([np.ones_like(a), a, d, a * d], axis=1)
        w = np.abs(W_).astype(dtype) if absval else W_.astype(dtype)
        C = np.zeros((x.shape[0], 12), dtype=dtype)
        for i in range(3):
            w4 = np.zeros((4, 4), dtype=dtype)
            for k in range(len(PHI_SUBSETS)):
                w4[MONO_INDEX[k], TFAC_INDEX[k]] = w[i * 15 + k]
            for m in range(4):
                s_ = np.zeros(x.shape[0], dtype=dtype)
                for f in range(4):  # s += w4[m][f] * t[f], f = 0..3, as rh_rhonn_bilinear
                    s_ = s_ + w4[m, f] * t[:, f]
                C[:, i * 4 + m] = s_
        return np.concatenate([phi, C], axis=1)

    ref = forward(inputs, mu, beta, W, np.float32, False)
    mag = forward(inputs, mu, beta, W, np.float64, True)
    return ref, mag


def demo_case(n_steps: int = 200, seed: int = 0) -> McuCase:
    """The rhonn.c kernels alone: per step, ξ = μ tanh(β x) of the
    recorded x = [Vx, Vy, ωr, δw], φ(ξ) (15) and the bilinear coefficients C (12) of a fixed
    W, i.e. rh_rhonn_xi, rh_rhonn_phi and rh_rhonn_bilinear of src/rhonn.c. Inputs: a smooth
    seeded random manoeuvre (Vx 5–35 m/s, |Vy| ≤ 2 m/s, |ωr| ≤ 1 rad/s, |δw| ≤ 0.1 rad)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps) * 0.01
    ph = rng.uniform(0, 2 * np.pi, 4)
    x = np.stack([20 + 15 * np.sin(0.3 * t + ph[0]), 2.0 * np.sin(1.7 * t + ph[1]),
                  1.0 * np.sin(2.3 * t + ph[2]), 0.1 * np.sin(3.1 * t + ph[3])], axis=1)
    x = (x + rng.normal(0, 1e-3, x.shape)).astype(np.float32)
    mu = np.ones(4, dtype=np.float32)
    beta = np.array([1 / 30, 1 / 3, 1 / 0.6, 1 / 0.15], dtype=np.float32)
    W = rng.normal(0, 0.05, 45).astype(np.float32)
    ref, mag = rhonn_demo_reference(x, mu, beta, W)
    names = [f"phi{k}" for k in range(15)] + [f"C{i}{m}" for i in range(3) for m in range(4)]
    config = ('#include "rh_real.h"\n' + c_float_array("MCU_W", W) + c_float_array("MCU_MU", mu)
              + c_float_array("MCU_BETA", beta))
    return McuCase(
        name="rhonn-demo (xi, phi, bilinear of src/rhonn.c)",
        adapter=MCU_DIR / "cases" / "rhonn_demo.c", sources=["rhonn.c"], config_c=config,
        inputs=x, expected=ref, tolerance=16 * EPS32 * mag + 1e-30,
        bound_text="|err| <= 16 eps32 M, M = the same computation on |operands| (tanhf of "
                   "newlib vs numpy float32 tanh, each within a few ulp; products and sums "
                   "in the C order)", output_names=names)


# Bound of the MCU outputs vs the float32 numpy reference, per real output, relative to that
# output's largest magnitude over the sequence (see full_core_case for the derivation).
FULL_CORE_BOUND = 1e-4
# Bound of the MCU outputs vs the host's float32 C core, same scale (see full_core_case).
HOST_C_BOUND = 5e-5
# QP iteration counts may differ on at most this fraction of the steps (status and fallback
# must not differ; see full_core_case).
ITER_MISMATCH_FRACTION = 0.03


def _ctrl_inputs(row: np.ndarray, lay_in: FlatLayout) -> ControllerInputs:
    """ControllerInputs of an rh_inputs_t vector: its fields that ControllerInputs has (the
    ``<array>_usable`` flags are C's own), flags as bools."""
    fields = set(ControllerInputs.__slots__)
    values = {k: bool(v) if isinstance(v, int) else v
              for k, v in lay_in.unpack(row).items() if k in fields}
    return ControllerInputs(**values)


def replay_outputs(controller: Any, X: np.ndarray, defines: Sequence[str] = ()) -> np.ndarray:
    """Outputs (steps, n_out) as rh_outputs_t vectors of ``controller`` stepped on ``X``
    (steps, n_in), rh_inputs_t vectors (:func:`ctrl_layouts` of ``defines``)."""
    lay_in, lay_out = ctrl_layouts(defines)
    return np.array([lay_out.pack(controller.step(_ctrl_inputs(x, lay_in))) for x in X],
                    dtype=np.float64)


def qp_shape(cfg: Any, name: str = "nmpc-rhonn") -> tuple[int, int]:
    """(N, shape) of controller ``name``'s QP (osqp_gen BOX / RATE / ENVELOPE): the one OSQP
    shape the MCU build needs."""
    h = cfg.handling
    if (h.envelope if name == "nmpc-rhonn" else h.baselines_envelope):
        return int(cfg.mpc.horizon), osqp_gen.ENVELOPE
    rate = float(cfg.mpc.rate_limit_nm_per_s) > 0.0
    return int(cfg.mpc.horizon), osqp_gen.RATE if rate else osqp_gen.BOX


def full_core_case(n_steps: int = 300, name: str = "nmpc-rhonn", osqp: str = "float",
                   config: str | Path | None = None) -> McuCase:
    """The whole controller step (rh_ctrl_init / rh_ctrl_step of include/rhonn_core.h) as
    deployed: the core in float (-DRH_FLOAT32), OSQP's generated solver for the configured QP
    shape only (N and rate rows of ``config``, None → default.toml: N 3, no rate rows), the
    core built with -DRH_N_MAX=N, OSQP in float (``osqp="float"``, -DOSQP_USE_FLOAT) or in
    double (``osqp="double"``, software-emulated on the M4F's single-precision FPU).

    Inputs: the recorded closed-loop sequence (harness.bench.controller_step.recorded_inputs:
    the numpy reference in float64 on the bench plant, 65 km/h, μ 0.35, DLC steering), rounded
    to float32 (every side gets exactly the MCU's inputs). References, on those inputs, with
    ``precision = "float32"`` and the UD EKF:

    * expected: the float32 numpy reference (backend "numpy"), the oracle;
    * others["host C float32"]: the float32 C core on the host (controller.native._rhcore32,
      same sources, OSQP in double), when it is built.

    Bounds, per real output j, relative to the output's largest magnitude over the
    sequence, S_j = max_k |ref_j(k)| (the scale of tests/test_native_core.py):

    (a) MCU vs the host float32 C core: |err_j| ≤ HOST_C_BOUND = 5e-5 · S_j. Same sources,
        same precision; the differences are newlib's tanhf/expf/sqrtf/sinf vs glibc's (each
        within a few ulp) and, in the float-OSQP build, the QP solved in float to
        eps_abs = eps_rel = 1e-5 instead of double. Measured on this sequence (Os and O2
        alike) with the paper's QP shape (rate rows): 7.7e-6 (OSQP float), 1.3e-6 (OSQP
        double, libm only). With the envelope shape (N + 2 decisions, 6N + 2 rows, the
        packaged nmpc-rhonn; -Os): 2.3e-6 with OSQP in float, 1.8e-6 in double. OSQP only
        solves the QPs where a row binds (``[mpc] unconstrained_first``); with every QP
        handed to OSQP the float solver does not hold these bounds on the envelope shape
        (6.9e-4 of ΔM's scale, the iteration count apart at 199 of 300 steps: it does not
        reach eps = 1e-5 on the slack-priced problem as the double one does).
    (b) MCU vs the float32 numpy reference (the oracle): |err_j| ≤ FULL_CORE_BOUND = 1e-4 ·
        S_j. Measured here (paper's QP shape): 4.3e-6 (OSQP float), 9.8e-6 (OSQP double);
        the envelope shape: 4.4e-6 (OSQP float), 3.1e-6 (OSQP double).
    (c) QP status and fallback flags equal at every step; iteration counts may differ on at
        most ITER_MISMATCH_FRACTION = 3 % of the steps (a residual sitting at the 1e-5
        threshold can stop the float solver one termination check, 5 iterations, earlier or
        later). Measured: no step differs, in either variant, against either reference."""
    if osqp not in ("float", "double"):
        raise ValueError(f"osqp must be 'float' or 'double', not {osqp!r}")
    tmp = Path(tempfile.mkdtemp(prefix="rhonn-mcu-case-"))
    atexit.register(shutil.rmtree, tmp, True)
    if config is None:
        text = resources.files("controller").joinpath("config/default.toml").read_text()
    else:
        text = Path(config).read_text()
    text = set_toml_keys(text, "[mpc]", 'precision = "float32"')
    text = set_toml_keys(text, "[rhonn.ekf]", 'form = "ud"')
    path32 = tmp / "float32.toml"
    path32.write_text(text)
    cfg = load_controller_config(path32)

    n, rate = qp_shape(cfg, name)
    defines = [f"RH_N_MAX={n}", *(["OSQP_USE_FLOAT"] if osqp == "float" else [])]
    lay_in, lay_out = ctrl_layouts(defines)
    rec = recorded_inputs(name, steps=n_steps, config=config)
    X = np.array([lay_in.pack(inp) for inp in rec], np.float32)
    exp = replay_outputs(make_controller(name, path32, backend="numpy"), X, defines)
    others: dict[str, np.ndarray] = {}
    notes: dict[str, Any] = {}
    if core_module(True) is not None:
        others["host C float32"] = replay_outputs(
            make_controller(name, path32, backend="native"), X, defines).astype(np.float32)
    else:
        notes["host C float32"] = "not built on this host (no comparison)"

    gen = osqp_gen.generate(tmp / "osqp", [(n, rate)])
    # OSQP in float: its unsuffixed constants (1e-6, 0.5, ...) as float too, else every
    # expression they appear in is promoted to software double (all fit a float: 1e-20..1e30)
    lib_flags = ["-fsingle-precision-constant"] if osqp == "float" else []
    scale = np.array([max(float(np.nanmax(np.abs(c))) if np.isfinite(c).any() else 0.0, 1e-12)
                      for c in exp.T])
    tol = FULL_CORE_BOUND * scale
    tol[list(lay_out.int_columns)] = np.inf
    notes.update({"qp_shape": f"N {n}, {('box', 'rate rows', 'rate + envelope rows')[rate]}",
                  "osqp_precision": osqp, "defines": defines, "osqp_flags": lib_flags,
                  "reference": "numpy float32 (UD EKF), same float32 inputs"})
    case = ctrl_step_case(
        ctrl_config(name, cfg), X, exp.astype(np.float32), tol,
        sources=sorted(p.name for p in SRC_DIR.glob("*.c")),
        lib_sources=osqp_gen.osqp_sources(gen), include_dirs=osqp_gen.osqp_include_dirs(gen),
        defines=defines, lib_flags=lib_flags,
        bound_text=f"|err| <= {FULL_CORE_BOUND:g} x max|ref| per real output vs the float32 "
                   f"numpy reference, {HOST_C_BOUND:g} x max|ref| vs the host float32 C core; "
                   "QP status/fallback equal, iterations differing on <= "
                   f"{100 * ITER_MISMATCH_FRACTION:g} % of steps",
        name=f"{name} full step, core float32, OSQP {osqp} "
             f"(N={n}{('', ', rate', ', rate + envelope')[rate]})")
    case.others = others
    case.notes = notes
    return case


def full_core_case_osqp_double(n_steps: int = 300, name: str = "nmpc-rhonn") -> McuCase:
    """:func:`full_core_case` with OSQP in double (software floating point on the M4F)."""
    return full_core_case(n_steps, name, osqp="double")
