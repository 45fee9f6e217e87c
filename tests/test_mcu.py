"""The C core on a Cortex-M4F under QEMU (harness/bench/mcu/, controller/native/mcu).

Full core (the default case of `rhonn-bench mcu`): nmpc-rhonn's rh_ctrl_init / rh_ctrl_step as
deployed (-DRH_FLOAT32, OSQP generated for the configured QP shape only, N 3 without rate rows,
-DRH_N_MAX=3, OSQP in float with -DOSQP_USE_FLOAT), cross-compiled at -Os, 300 recorded
closed-loop steps (harness.bench.controller_step.recorded_inputs, rounded to float32) on QEMU's
MPS2 AN386; outputs read back as float32 bit patterns. Bounds (derivations and measurements
in mcu.full_core_case), per real output j, relative to S_j = max over the sequence of
|reference_j|:

* vs the float32 numpy reference (UD EKF): ≤ 1e-4 · S_j (measured 4.3e-6; the host float32
  C core itself is 9.8e-6 from it on this sequence; its own test bound is 2e-4);
* vs the host float32 C core (same sources and precision; newlib vs glibc maths, OSQP float
  vs double): ≤ 5e-5 · S_j (measured 7.7e-6);
* QP status and fallback equal at every step; iteration counts differing on ≤ 3 % of the
  steps (measured: none);
* the memory targets: core + generated OSQP text+rodata ≤ 64 kB (measured 37.6 kB linked at -Os),
  data+bss with the controller state (sizeof(rh_ctrl_t)) ≤ 16 kB (measured 8.8 kB); no
  software double-precision call left in the float OSQP build.

Demo case: rh_rhonn_xi / phi / bilinear of src/rhonn.c, 60 steps, |err| ≤ 16·eps32·M per output,
M = the same computation on absolute values (tanhf of newlib vs numpy's float32 tanh).

CMAC case: the node's AES-128-CMAC (controller/native/node/node_cmac.c) on 20 seeded 18-byte
SecOC MAC inputs, every tag exact against the ``cryptography`` package.

Skipped only when the cross toolchain, newlib or qemu-system-arm is absent (apt-get install
-y gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm).
"""

from __future__ import annotations

import os
import subprocess
import sys
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from harness.bench import mcu
from harness.bench.controller_step import set_toml_keys
from harness.bench.mcu.cmac_case import cmac_case

REPO = Path(__file__).resolve().parents[1]
MISSING = mcu.missing_tools()
needs_toolchain = pytest.mark.skipif(MISSING is not None, reason=f"MCU toolchain: {MISSING}")


@needs_toolchain
@pytest.mark.timeout(120)
def test_demo_case_runs_on_the_cortex_m4f_and_matches_the_float32_reference(tmp_path) -> None:
    case = mcu.demo_case(n_steps=60, seed=1)
    res = mcu.run_mcu(case, opts=("Os",), out_dir=tmp_path, timeout_s=45.0)
    r = res["levels"]["Os"]
    assert r["ok"], (r["max_abs_err"], r["max_err_over_bound"], r["worst_at"])
    assert r["max_err_over_bound"] <= 1.0
    # the figures are there and plausible
    assert 0 < r["flash_core_bytes"] < 4096 and r["ram_core_bytes"] == 0  # no mutable globals
    assert 0 < r["stack_measured_max_bytes"] <= r["stack_static_path"]["bytes"] + 256
    assert r["stack_static_path"]["path"][0] == "mcu_case_step"
    if "insns_per_step_median" in r:  # needs a host cc for the QEMU plugin
        assert 100 < r["insns_per_step_median"] <= r["insns_per_step_max"] < 100_000
    assert not r["soft_double_helpers"]


@needs_toolchain
@pytest.mark.timeout(120)
def test_cmac_case_runs_on_the_cortex_m4f_and_every_tag_equals_cryptography(tmp_path) -> None:
    """The node's AES-128-CMAC on the M4F (harness.bench.mcu.cmac_case): 20 seeded 18-byte
    SecOC MAC inputs, every tag byte equal to the ``cryptography`` package's."""
    case = cmac_case(n_steps=20, seed=3)
    res = mcu.run_mcu(case, opts=("Os",), out_dir=tmp_path, timeout_s=45.0)
    r = res["levels"]["Os"]
    assert r["ok"] and r["bitexact_fraction"] == 1.0, (r["max_abs_err"], r["worst_at"])
    assert r["ram_core_bytes"] == 0 and r["flash_core_bytes"] > 1024  # the table is const
    if "insns_per_step_median" in r:  # one CMAC a step: every step takes the same path
        assert r["insns_per_step_median"] == r["insns_per_step_max"] > 0


@needs_toolchain
@pytest.mark.timeout(90)
def test_full_core_on_the_cortex_m4f_matches_the_references_within_the_stated_bounds(
        tmp_path) -> None:
    """The packaged nmpc-rhonn (envelope rows: N + 2 decisions, 6N + 2 rows) with OSQP in
    float, as deployed: OSQP solves the QPs where a row binds, the closed forms the others.
    On the bench's recording the packaged envelope binds on no step after the start-up
    (whose box is collapsed: a closed form), so the envelope is tightened here (yaw margin
    0.9, rear slip factor 0.5) until OSQP runs on a few steps (two: 95 and 190 iterations)."""
    config = tmp_path / "tight.toml"
    text = resources.files("controller").joinpath("config/default.toml").read_text()
    config.write_text(set_toml_keys(text, "[handling]", "yaw_margin = 0.9\nrear_slip_factor = 0.5"))
    case = mcu.full_core_case(n_steps=300, config=config)
    assert case.notes["qp_shape"] == "N 3, rate + envelope rows"
    assert "OSQP_USE_FLOAT" in case.defines and "RH_N_MAX=3" in case.defines
    res = mcu.run_mcu(case, opts=("Os",), out_dir=tmp_path, timeout_s=45.0)
    r = res["levels"]["Os"]
    names = res["output_names"]
    dm = np.asarray(case.expected)[:, names.index("delta_m")]
    assert np.abs(dm).max() > 100.0                       # the MPC acted (N m)
    iters = np.asarray(case.expected)[:, names.index("qp_iterations")]
    assert 0 < np.count_nonzero(iters) < len(iters)        # OSQP ran where a row binds
    # (b) against the float32 numpy reference, per real output
    assert r["ok"], (r["vs_expected"]["rel_err_per_output"], r["worst_at"])
    assert r["vs_expected"]["max_rel_err"] <= mcu.FULL_CORE_BOUND
    # (a) against the host float32 C core, when it is built here
    if "host C float32" in r["vs_others"]:
        host = r["vs_others"]["host C float32"]
        assert host["max_rel_err"] <= mcu.HOST_C_BOUND, host["rel_err_per_output"]
    # (c) QP status / fallback equal; iterations nearly always
    for cmp_ in (r["vs_expected"], *r["vs_others"].values()):
        mism = {names[j]: n for j, n in cmp_["int_mismatch_steps"].items()}
        assert mism["qp_status"] == 0 and mism["fallback"] == 0, mism
        assert mism["qp_iterations"] <= mcu.ITER_MISMATCH_FRACTION * res["steps"], mism
    # the memory targets, the controller state counted in RAM
    assert set(r["state_symbols"]) == {"ctrl"} and r["state_bytes"] > 4000
    assert 0 < r["flash_core_total_bytes"] <= mcu.FLASH_TARGET_BYTES
    assert r["ram_core_total_bytes"] <= mcu.RAM_TARGET_BYTES
    assert r["linked"]["lib"]["text"] > 0 and r["linked"]["newlib"]["text"] > 0
    assert not r.get("lib_soft_double_callers")          # OSQP really runs in float
    assert 0 < r["stack_measured_max_bytes"] < 4096
    assert r["stack_static_path"]["path"][:2] == ["mcu_case_step", "rh_ctrl_step"]
    if "insns_per_step_median" in r:
        assert 10_000 < r["insns_per_step_median"] <= r["insns_per_step_p99"] \
            <= r["insns_per_step_max"] < 2_000_000


@needs_toolchain
@pytest.mark.timeout(180)
def test_envelope_shape_on_the_cortex_m4f_with_osqp_in_double(tmp_path) -> None:
    """The packaged nmpc-rhonn (envelope rows: N + 2 decisions, 6N + 2 rows) in the generated
    static-memory OSQP on the M4F, OSQP in double: within the stated bounds of the float32
    reference and the host C core, QP status and fallback equal at every step."""
    case = mcu.full_core_case(n_steps=120, osqp="double")
    assert case.notes["qp_shape"] == "N 3, rate + envelope rows"
    res = mcu.run_mcu(case, opts=("Os",), out_dir=tmp_path, timeout_s=120.0)
    r = res["levels"]["Os"]
    names = res["output_names"]
    assert r["ok"], (r["vs_expected"]["rel_err_per_output"], r["worst_at"])
    assert r["vs_expected"]["max_rel_err"] <= mcu.FULL_CORE_BOUND
    for cmp_ in (r["vs_expected"], *r["vs_others"].values()):
        mism = {names[j]: n for j, n in cmp_["int_mismatch_steps"].items()}
        assert mism["qp_status"] == 0 and mism["fallback"] == 0, mism
    if "host C float32" in r["vs_others"]:
        assert r["vs_others"]["host C float32"]["max_rel_err"] <= mcu.HOST_C_BOUND


def test_without_the_toolchain_the_command_names_what_is_missing_and_exits_2(tmp_path) -> None:
    env = dict(os.environ, PATH=str(tmp_path))  # nothing on PATH: no cross gcc, no qemu
    res = subprocess.run([sys.executable, "-m", "harness.bench.cli", "mcu"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=60)
    lines = (res.stdout + res.stderr).strip().splitlines()
    assert res.returncode == 2
    assert len(lines) == 1, lines
    assert "arm-none-eabi-gcc" in lines[0] and "qemu-system-arm" in lines[0]
    assert mcu.APT_LINE in lines[0]
    assert mcu.APT_LINE == ("apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi "
                            "qemu-system-arm")
