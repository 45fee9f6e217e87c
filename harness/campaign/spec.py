"""Campaign files: TOML → a run matrix of :class:`RunSpec` plus derived-study declarations.

A campaign file (see ``harness/campaign/campaigns/*.toml`` and docs/campaigns.md)::

    [campaign]
    name = "dlc-seeds"
    seeds = [0, 1, 2]            # default for every [[matrix]] and [[study]]

    [[matrix]]                   # cartesian product of the lists
    name = "dlc"
    scenarios = ["dlc-paper"]    # packaged names or scenario files (docs/scenarios.md)
    controllers = ["nmpc-rhonn", "passive"]
    mu = [0.35]                  # friction, dimensionless (omit: the scenario's)
    speeds_kmh = [60.0, 65.0]    # entry speed, km/h (omit: the scenario's)
    duration_s = 6.0             # simulated s (omit: the scenario's)
    params = [{}, { stab_enable_after_s = "1.0" }]  # scenario override sets (--param)
    faults = [[], ["loss:10%"]]  # fault sets (--fault specs)
    vehicle = [{}, { mass_scale = 1.15 }]   # plant overrides (--vehicle; plant_sim/overrides.py)
    controller_overrides = [{}, { "mpc.horizon" = 6 }]  # "SECTION.KEY" = value (bare KEY:
                                 # [references]) on the controller config
    seed_overrides = ["rhonn.init_seed"]  # config keys set to each run's seed
    exclusive = false            # true: run after every other run, one at a time, alone

    [[study]]
    kind = "vmax"                # or "fmvss126"
    controllers = ["nmpc-rhonn"]

Every run is keyed by :func:`RunSpec.key`, a hash of everything that decides its outcome.
"""

from __future__ import annotations

import itertools
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from can_db.faults import FaultSpecError, parse_faults
from controller.core.registry import CONTROLLER_NAMES
from harness.run.spec import RunSpec
from plant_sim.overrides import apply_vehicle_overrides
from plant_sim.params import load_vehicle_params
from plant_sim.scenario import is_scenario_file, list_scenarios

KNOWN_POSTS = ("timing", "diag", "fidelity", "fmvss", "sis", "stability")
STUDY_KINDS = ("vmax", "fmvss126")


class CampaignError(ValueError):
    """A campaign file that cannot be used; the message is one line."""


@dataclass
class StudyDecl:
    """A derived study: ``kind`` vmax (bisection of the DLC entry speed, km/h) or fmvss126
    (sine-with-dwell amplitude series, deg); ``options`` holds the kind's settings."""

    name: str
    kind: str
    controllers: tuple[str, ...]
    seeds: tuple[int, ...]
    options: dict[str, Any] = field(default_factory=dict)


@dataclass
class Campaign:
    """A parsed campaign: the fixed run matrix and the derived studies."""

    name: str
    runs: list[RunSpec]
    studies: list[StudyDecl]
    source: str = ""
    # keys of the runs of ``exclusive = true`` matrices: they run last, one at a time, with
    # nothing else running (wall-clock measurements such as the controller's step time)
    exclusive: frozenset[str] = frozenset()


_CAMPAIGN_KEYS = {"name", "description", "seeds", "mode", "controller_mode", "plots", "rrd",
                  "wall_timeout_s", "duration_s"}
_MATRIX_KEYS = {"name", "scenarios", "controllers", "mu", "speeds_kmh", "duration_s", "params",
                "faults", "vehicle", "seeds", "controller_config", "post", "plots", "rrd",
                "info", "exclusive", "controller_overrides", "seed_overrides"}
_STUDY_KEYS = {"vmax": {"name", "kind", "controllers", "seeds", "scenario", "bracket_kmh",
                        "resolution_kmh", "verify_offsets_kmh", "mu", "rules", "vehicle",
                        "controller_overrides", "seed_overrides", "coast_duration", "post",
                        "info"},
               "fmvss126": {"name", "kind", "controllers", "seeds", "directions",
                            "amplitude_factors", "sis_duration_s", "duration_s"}}


def _unknown(where: str, got: dict[str, Any], allowed: set[str]) -> None:
    extra = sorted(set(got) - allowed)
    if extra:
        raise CampaignError(f"{where}: unknown key(s) {', '.join(extra)} "
                            f"(allowed: {', '.join(sorted(allowed))})")


def _list(where: str, value: Any, kind: type | tuple[type, ...], default: list[Any]
          ) -> list[Any]:
    if value is None:
        return default
    if not isinstance(value, list) or not value:
        raise CampaignError(f"{where}: expected a non-empty list, got {value!r}")
    for v in value:
        if not isinstance(v, kind) or (isinstance(v, bool) and kind is not bool):
            raise CampaignError(f"{where}: bad entry {v!r}")
    return value


def _is_file(scenario: str) -> bool:
    return is_scenario_file(scenario)


def _scenario_files(where: str, scenarios: list[str], base: Path) -> list[str]:
    """Scenario files (docs/scenarios.md) as absolute paths, relative ones to the campaign
    file's folder; packaged names as they are. Their content is checked with each run."""
    out = []
    for s in scenarios:
        if _is_file(s):
            path = Path(s) if Path(s).is_absolute() else base / s
            if not path.is_file():
                raise CampaignError(f"{where}.scenarios: no such file {s}")
            s = str(path.resolve())
        out.append(s)
    return out


def _check_names(where: str, scenarios: list[str], controllers: list[str]) -> None:
    known = list_scenarios()
    for s in scenarios:
        if s not in known and not _is_file(s):
            raise CampaignError(f"{where}: unknown scenario {s!r} (known: {', '.join(known)})")
    for c in controllers:
        if c not in CONTROLLER_NAMES:
            raise CampaignError(f"{where}: unknown controller {c!r} "
                                f"(known: {', '.join(CONTROLLER_NAMES)})")


def _vehicle_set(where: str, overrides: dict[str, Any]) -> tuple[tuple[str, float], ...]:
    """A checked, sorted plant-override set (the same rules as ``--vehicle KEY=VALUE``)."""
    try:
        out = tuple(sorted((str(k), float(v)) for k, v in overrides.items()))
        apply_vehicle_overrides(load_vehicle_params(), dict(out))
    except (TypeError, ValueError) as exc:
        raise CampaignError(f"{where}: {exc}") from exc
    return out


def _overrides(where: str, table: Any) -> dict[str, Any]:
    """A controller override table (``"SECTION.KEY" = value``; bare KEY: [references])."""
    if not isinstance(table, dict) or not all(isinstance(v, (int, float, str, bool, list))
                                              for v in table.values()):
        raise CampaignError(f"{where}: expected a table of \"SECTION.KEY\" = value")
    return dict(table)


def _seeds(where: str, value: Any, default: list[int]) -> tuple[int, ...]:
    seeds = _list(f"{where}.seeds", value, int, default)
    if len(set(seeds)) != len(seeds) or any(s < 0 for s in seeds):
        raise CampaignError(f"{where}.seeds: must be distinct non-negative integers")
    return tuple(seeds)


def _matrix_runs(i: int, m: dict[str, Any], top: dict[str, Any], base: Path) -> list[RunSpec]:
    where = f"matrix[{i}]"
    _unknown(where, m, _MATRIX_KEYS)
    name = str(m.get("name", f"matrix{i}"))
    where = f"matrix {name!r}"
    scenarios = _list(f"{where}.scenarios", m.get("scenarios"), str, [])
    controllers = _list(f"{where}.controllers", m.get("controllers"), str, [])
    if not scenarios or not controllers:
        raise CampaignError(f"{where}: needs scenarios and controllers")
    scenarios = _scenario_files(where, scenarios, base)
    _check_names(where, scenarios, controllers)
    mus = _list(f"{where}.mu", m.get("mu"), (int, float), [None])
    speeds = _list(f"{where}.speeds_kmh", m.get("speeds_kmh"), (int, float), [None])
    params = _list(f"{where}.params", m.get("params"), dict, [{}])
    faults = _list(f"{where}.faults", m.get("faults"), list, [[]])
    for fs in faults:
        if not all(isinstance(f, str) for f in fs):
            raise CampaignError(f"{where}.faults: each fault set is a list of strings")
    try:
        for fs in faults:
            parse_faults(list(fs))
    except FaultSpecError as exc:
        raise CampaignError(f"{where}.faults: {exc}") from exc
    vehicles = [_vehicle_set(f"{where}.vehicle", v)
                for v in _list(f"{where}.vehicle", m.get("vehicle"), dict, [{}])]
    posts = _list(f"{where}.post", m.get("post"), str, [])
    for p in posts:
        if p not in KNOWN_POSTS:
            raise CampaignError(f"{where}.post: unknown step {p!r} "
                                f"(known: {', '.join(KNOWN_POSTS)})")
    info = m.get("info", {})
    if not isinstance(info, dict):
        raise CampaignError(f"{where}.info: expected a table")
    seeds = _seeds(where, m.get("seeds"), list(top.get("seeds", [0])))
    overrides = [_overrides(f"{where}.controller_overrides", o) for o in _list(
        f"{where}.controller_overrides", m.get("controller_overrides"), dict, [{}])]
    by_seed = _list(f"{where}.seed_overrides", m.get("seed_overrides"), str, [])
    cfg = m.get("controller_config")
    if cfg is not None:
        path = Path(cfg) if Path(cfg).is_absolute() else (base / cfg)
        if not path.is_file():
            raise CampaignError(f"{where}.controller_config: no such file {cfg}")
        cfg = str(path.resolve())
    duration = m.get("duration_s", top.get("duration_s"))
    runs = []
    for scen, ctrl, mu, v, par, fs, veh, ov, seed in itertools.product(
            scenarios, controllers, mus, speeds, params, faults, vehicles, overrides, seeds):
        runs.append(RunSpec(
            controller_overrides={**ov, **{k: int(seed) for k in by_seed}},
            group=name, scenario=scen, controller=ctrl, seed=int(seed),
            mu=None if mu is None else float(mu), speed_kmh=None if v is None else float(v),
            duration_s=None if duration is None else float(duration),
            params=tuple(sorted((str(k), str(val)) for k, val in par.items())),
            faults=tuple(fs), vehicle=veh, controller_config=cfg,
            mode=str(top.get("mode", "lockstep")),
            controller_mode=str(top.get("controller_mode", "lockstep")),
            post=tuple(posts), info=tuple(sorted(info.items())),
            make_plots=bool(m.get("plots", top.get("plots", False))),
            make_rrd=bool(m.get("rrd", top.get("rrd", False))),
            wall_timeout_s=float(top.get("wall_timeout_s", 600.0))))
    return runs


def _study(i: int, s: dict[str, Any], top: dict[str, Any]) -> StudyDecl:
    kind = s.get("kind")
    if kind not in STUDY_KINDS:
        raise CampaignError(f"study[{i}]: kind must be one of {', '.join(STUDY_KINDS)}, "
                            f"got {kind!r}")
    _unknown(f"study[{i}]", s, _STUDY_KEYS[kind])
    name = str(s.get("name", kind))
    where = f"study {name!r}"
    controllers = _list(f"{where}.controllers", s.get("controllers"), str, [])
    if not controllers:
        raise CampaignError(f"{where}: needs controllers")
    _check_names(where, [], controllers)
    seeds = _seeds(where, s.get("seeds"), list(top.get("seeds", [0])))
    opts = {k: v for k, v in s.items() if k not in {"name", "kind", "controllers", "seeds"}}
    if kind == "vmax":
        br = opts.get("bracket_kmh", [30.0, 90.0])
        if (not isinstance(br, list) or len(br) != 2 or not all(
                isinstance(x, (int, float)) for x in br) or not 0 < br[0] < br[1]):
            raise CampaignError(f"{where}.bracket_kmh: expected [low, high] km/h, low < high")
        if float(opts.get("resolution_kmh", 0.5)) <= 0:
            raise CampaignError(f"{where}.resolution_kmh: must be > 0")
        _check_names(where, [str(opts.get("scenario", "dlc-paper"))], [])
        _vehicle_set(f"{where}.vehicle", opts.get("vehicle", {}))
        _overrides(f"{where}.controller_overrides", opts.get("controller_overrides", {}))
        for key in ("rules", "seed_overrides", "post"):
            _list(f"{where}.{key}", opts.get(key), str, [])
    else:
        for d in opts.get("directions", ["left", "right"]):
            if d not in ("left", "right"):
                raise CampaignError(f"{where}.directions: left or right, got {d!r}")
        for f in opts.get("amplitude_factors", []) or []:
            if not isinstance(f, (int, float)) or f <= 0:
                raise CampaignError(f"{where}.amplitude_factors: positive numbers, got {f!r}")
    return StudyDecl(name, kind, tuple(controllers), seeds, opts)


def parse_campaign(text: str, base: Path | None = None,
                   duration_cap_s: float | None = None,
                   seeds: list[int] | None = None) -> Campaign:
    """Parse campaign TOML text. ``base``: folder for relative paths. ``duration_cap_s``
    (simulated s) replaces every matrix run's duration (for smoke runs); ``seeds`` replaces
    the seeds of every matrix and study."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CampaignError(f"not valid TOML: {exc}") from exc
    if seeds is not None:
        _seeds("--seeds", list(seeds), [])
        for table in [doc.setdefault("campaign", {}), *doc.get("matrix", []),
                      *doc.get("study", [])]:
            if isinstance(table, dict):
                table["seeds"] = list(seeds)
    _unknown("file", doc, {"campaign", "matrix", "study"})
    top = doc.get("campaign", {})
    _unknown("[campaign]", top, _CAMPAIGN_KEYS)
    name = str(top.get("name", "campaign"))
    matrices, studies = doc.get("matrix", []), doc.get("study", [])
    if not matrices and not studies:
        raise CampaignError("no [[matrix]] and no [[study]]: nothing to run")
    base = base or Path.cwd()
    runs: list[RunSpec] = []
    alone: set[int] = set()  # indices into runs of the exclusive matrices' runs
    for i, m in enumerate(matrices):
        if not isinstance(m.get("exclusive", False), bool):
            raise CampaignError(f"matrix[{i}].exclusive: expected true or false")
        mine = _matrix_runs(i, m, top, base)
        if m.get("exclusive", False):
            alone.update(range(len(runs), len(runs) + len(mine)))
        runs += mine
    if duration_cap_s is not None:
        runs = [replace(r, duration_s=float(duration_cap_s)) for r in runs]
    exclusive = frozenset(r.key() for i, r in enumerate(runs) if i in alone)
    seen: set[str] = set()
    unique = []
    for r in runs:  # the same run in two matrices runs once
        if r.key() not in seen:
            seen.add(r.key())
            unique.append(r)
    decls = [_study(i, s, top) for i, s in enumerate(studies)]
    names = [d.name for d in decls] + [str(m.get("name", f"matrix{i}"))
                                       for i, m in enumerate(matrices)]
    if len(set(names)) != len(names):
        raise CampaignError(f"matrix/study names must be unique: {names}")
    if duration_cap_s is not None:
        for d in decls:
            d.options["duration_cap_s"] = float(duration_cap_s)
    return Campaign(name, unique, decls, text, exclusive)


def load_campaign(path: Path, duration_cap_s: float | None = None,
                  seeds: list[int] | None = None) -> Campaign:
    """Read and parse a campaign file; a missing file is a CampaignError."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise CampaignError(f"cannot read {path}: {exc.strerror}") from exc
    return parse_campaign(text, path.parent, duration_cap_s, seeds)
