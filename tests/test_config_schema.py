"""The typed controller configuration: one-line errors naming file, section and key;
``extends``; and the packaged configs parse to the values their comments state."""

from __future__ import annotations

from pathlib import Path

import pytest

from controller.core.config_schema import ConfigError, build_section, merge_tables
from controller.core.registry import load_controller_config, load_raw_config
from controller.runtime.envelope import EnvelopeConfig


def _write(tmp_path: Path, body: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(body)
    return path


@pytest.mark.parametrize(("body", "section", "key", "fragment"), [
    ("[mpc]\nhorizn = 3\n", "mpc", "horizn", "unknown key"),
    ("[mpc]\nhorizon = \"3\"\n", "mpc", "horizon", "expected int"),
    ("[mpc]\nhorizon = true\n", "mpc", "horizon", "expected int"),
    ("[mpc]\nq_yaw = [1.0, 2.0]\n", "mpc", "q_yaw", "needs 1 or 3"),
    ("[mpcc]\nx = 1\n", "mpcc", "", "unknown section"),
    ("[rhonn.ekf]\nr = [1.0, \"x\", 3.0]\n", "rhonn.ekf", "r", "expected float"),
    ("[rhonn]\nform = \"other\"\n", "rhonn", "form", "increment"),
    ("[references]\ngrid_n = 9.5\n", "references", "grid_n", "expected int"),
    ("[allocation]\nsplit = 3\n", "allocation", "split", "expected str"),
    ("[controller]\nts_s = 0.0\n", "controller", "ts_s", "> 0"),
    ("[controller]\nts_s = nan\n", "controller", "ts_s", "NaN"),
    ("[controller]\nts_s = inf\n", "controller", "ts_s", "finite number > 0"),
    ("[mpc]\nhorizon = 50\nq_yaw = 1.0\nr_beta = 1.0\n", "mpc", "horizon", "1..20"),
    ("[mpc]\nq_yaw = -1.0\n", "mpc", "q_yaw", ">= 0"),
    ("[mpc]\nr_beta = [1.0, inf, 1.0]\n", "mpc", "r_beta", "finite number >= 0"),
    ("[mpc]\nq_yaw = 0.0\nr_beta = 0.0\n", "mpc", "q_yaw", "nothing to track"),
    ("[mpc]\ninput_reg = -1e-3\n", "mpc", "input_reg", ">= 0"),
    ("[mpc]\nfallback_decay = 1.5\n", "mpc", "fallback_decay", "[0, 1]"),
    ("[mpc]\nu_scale = 0.0\n", "mpc", "u_scale", "> 0"),
    ("[grip]\ntau_s = inf\n", "grip", "tau_s", "finite number > 0"),
])
def test_bad_values_name_file_section_and_key(tmp_path: Path, body: str, section: str,
                                              key: str, fragment: str) -> None:
    path = _write(tmp_path, body)
    with pytest.raises(ConfigError) as info:
        load_controller_config(path)
    err = info.value
    assert (err.section, err.key) == (section, key)
    line = str(err)
    assert "\n" not in line
    assert line.startswith(str(path) + ": ")
    assert fragment in line


def test_malformed_toml_is_one_line(tmp_path: Path) -> None:
    path = _write(tmp_path, "[mpc\n")
    with pytest.raises(ConfigError, match=r"not valid TOML") as info:
        load_controller_config(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_extends_overrides_only_what_differs(tmp_path: Path) -> None:
    base = load_controller_config()
    path = _write(tmp_path, 'extends = "default"\n[mpc]\nhorizon = 4\n[rhonn.ekf]\nq = 3e-6\n')
    cfg = load_controller_config(path)
    assert cfg.mpc.horizon == 4 and cfg.mpc.q_yaw == (100.0,) * 4
    assert cfg.rhonn.ekf.q == 3e-6
    # everything else is the base's
    assert cfg.rhonn.ekf.r == base.rhonn.ekf.r
    assert cfg.mpc.input_reg == base.mpc.input_reg
    assert cfg.rhonn.dm_dead_time_s == base.rhonn.dm_dead_time_s
    assert cfg.references == base.references


def test_extends_a_sibling_file_and_bounded_chain(tmp_path: Path) -> None:
    _write(tmp_path, 'extends = "default"\n[mpc]\nhorizon = 6\n', "parent.toml")
    child = _write(tmp_path, 'extends = "parent.toml"\n[mpc]\ninput_reg = 0.5\n', "child.toml")
    cfg = load_controller_config(child)
    assert (cfg.mpc.horizon, cfg.mpc.input_reg) == (6, 0.5)
    loop = _write(tmp_path, 'extends = "loop.toml"\n', "loop.toml")
    with pytest.raises(ConfigError, match="deeper"):
        load_controller_config(loop)


def test_100hz_is_default_plus_its_stated_differences() -> None:
    d_raw, _, _ = load_raw_config(None)
    h_raw, _, _ = load_raw_config("100hz")

    def flat(t: dict, prefix: str = "") -> dict:
        out = {}
        for k, v in t.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) and k != "osqp"
                       else {prefix + k: v})
        return out

    d, h = flat(d_raw), flat(h_raw)
    assert d.keys() == h.keys()
    differs = {k for k in d if d[k] != h[k]}
    assert differs == {"controller.ts_s", "mpc.horizon", "rhonn.ekf.q"}
    cfg = load_controller_config("100hz")
    assert (cfg.ts, cfg.mpc.horizon) == (0.01, 5)
    # the three settings 100hz.toml used to drop silently
    assert cfg.rhonn.dm_dead_time_s == 0.02 and cfg.rhonn.gate_warmup_s == 0.5
    assert cfg.mpc.input_reg == 0.1


def test_default_values_match_the_file() -> None:
    cfg = load_controller_config()
    assert cfg.ts == 0.05 and cfg.mpc.horizon == 3
    assert cfg.mpc.q_yaw == (100.0,) * 3 and cfg.mpc.r_beta == (1000.0,) * 3
    assert cfg.rhonn.ekf.r == (1e-4, 1e-4, 1e-5)
    assert isinstance(cfg.references.grid_n, int)


def test_envelope_uses_the_same_schema() -> None:
    with pytest.raises(ConfigError, match=r"\[envelope\] torque_rate: unknown key"):
        EnvelopeConfig.from_dict({"torque_rate": 1.0})
    with pytest.raises(ConfigError, match="expected float"):
        EnvelopeConfig.from_dict({"torque_rate_nm_per_s": "fast"})


def test_build_section_and_merge_are_generic() -> None:
    from dataclasses import dataclass

    @dataclass
    class Inner:
        a: float = 1.0
        b: tuple[int, int] = (1, 2)

    assert build_section(Inner, {"a": 2, "b": [3, 4]}, "s") == Inner(2.0, (3, 4))
    with pytest.raises(ConfigError, match="expected 2 entries"):
        build_section(Inner, {"b": [1]}, "s")
    assert merge_tables({"x": {"y": 1, "z": 2}}, {"x": {"y": 3}}) == {"x": {"y": 3, "z": 2}}


@pytest.mark.parametrize(("key", "value", "fragment"), [
    ("mass_kg", "0.0", "> 0"), ("yaw_inertia_kgm2", "inf", "finite number > 0"),
    ("wheel_radius_m", "-0.3", "> 0"), ("cf_axle_n_per_rad", "80000.0", "< 0"),
    ("torque_rate_nm_per_s", "-1.0", ">= 0"),
])
def test_a_vehicle_file_out_of_physical_range_is_refused(tmp_path: Path, key: str, value: str,
                                                        fragment: str) -> None:
    """A [controller] vehicle_file with a mass of 0 (or another value no car has) is a
    one-line refusal naming the key, not a controller that runs on it."""
    from importlib import resources

    text = resources.files("controller").joinpath("config/vehicle.toml").read_text()
    lines = [f"{key} = {value}" if ln.split("=")[0].strip() == key else ln
             for ln in text.splitlines()]
    assert lines != text.splitlines()
    _write(tmp_path, "\n".join(lines), "vehicle.toml")
    path = _write(tmp_path, '[controller]\nvehicle_file = "vehicle.toml"\n')
    with pytest.raises(ConfigError) as info:
        load_controller_config(path)
    assert (info.value.section, info.value.key) == ("vehicle", key)
    assert fragment in str(info.value)
