"""The scenario file schema: every key a scenario TOML may hold, with its type, unit, default
and range, and the check that holds a file (packaged or a user's) to it.

A scenario file has top-level keys (:data:`TOP`) and three tables: ``[course]`` (its ``type``
selects the keys of :data:`COURSE_TYPES`), ``[road]`` (:data:`ROAD`; friction patches, a
split-μ and friction steps in time) and ``[driver]`` (:data:`DRIVER`, the fields of
:class:`plant_sim.driver.DriverSpec`). Unknown keys are errors (a typo must not pass
silently); numbers may be written as TOML integers or floats; every number is finite.

:func:`check_spec` raises :class:`SpecError` (the dotted key and the problem) for the first
thing wrong; :func:`normalise` gives the spec with every number a float. ``python -m
plant_sim.scenario_schema`` prints the key tables of docs/scenarios.md.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import Any

from plant_sim.driver import SPEED_MODES, STEER_MODES

MU_MAX = 1.5  # highest road friction coefficient accepted (dry asphalt is ≈ 1.0–1.2)
SPEED_MAX_KMH = 250.0  # highest initial speed accepted, km/h
DURATION_MAX_S = 3600.0  # longest simulated run accepted, s
COURSE_KINDS = ("iso3888_1", "iso3888_2", "straight", "curve", "circle")


class _Required:
    def __repr__(self) -> str:
        return "required"


REQUIRED: Any = _Required()  # the default of a key a file must give


@dataclass(frozen=True, slots=True)
class Key:
    """One key: ``kind`` is number | text | choice | table | tables | steps.

    number: finite, in [lo, hi] (lo excluded when ``lo_open``); choice: one of ``choices``;
    table: a TOML table with the keys ``keys``; tables: a list of such tables; steps: a list
    of [t_s, mu] pairs or {t_s, mu} tables. ``default`` is :data:`REQUIRED` for a key a file
    must give, None for an optional key without a value of its own.
    """

    name: str
    kind: str
    default: Any = REQUIRED
    unit: str = "-"
    doc: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple[str, ...] = ()
    keys: tuple[Key, ...] = ()

    def range_text(self) -> str:
        """The accepted values in words (for errors and the docs)."""
        if self.kind == "choice":
            return ", ".join(self.choices)
        if self.kind == "text":
            return "any text"
        if self.kind != "number":
            return "see below" if self.keys else "see the meaning"
        low = "" if self.lo is None else (f"> {self.lo:g}" if self.lo_open else f">= {self.lo:g}")
        high = "" if self.hi is None else f"<= {self.hi:g}"
        return " and ".join(b for b in (low, high) if b) or "any"


class SpecError(ValueError):
    """A scenario spec that breaks the schema: ``key`` (dotted, '' for the whole file) and
    ``problem``; str() is ``key: problem`` on one line."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"{key}: {problem}" if key else problem)
        self.key = key
        self.problem = problem


def _num(name: str, default: Any, unit: str, doc: str, lo: float | None = None,
         hi: float | None = None, lo_open: bool = False) -> Key:
    return Key(name, "number", default, unit, doc, lo, hi, lo_open)


def _mu(name: str, default: Any, doc: str) -> Key:
    return _num(name, default, "-", doc, 0.0, MU_MAX, lo_open=True)


_DIRECTION = Key("direction", "choice", "left", "-", "side the course turns to",
                 choices=("left", "right"))
_HALF_WIDTH = _num("half_width_m", 1.75, "m", "half the lane width (boundaries in the plots)",
                   0.0, 50.0, lo_open=True)
_LANE_LEAD_IN = _num("lead_in_m", 20.0, "m", "straight before the first gate", 0.0, 1000.0)
_LANE_RUN_OUT = _num("run_out_m", 60.0, "m", "path after the last gate", 0.0, 1000.0)

TOP: tuple[Key, ...] = (
    Key("description", "text", "", "-", "one line shown in reports"),
    _num("duration_s", REQUIRED, "s", "simulated time; the run ends earlier at the end of "
         "the path, at standstill or when the car leaves the test area", 0.0, DURATION_MAX_S,
         lo_open=True),
    _num("speed_kmh", REQUIRED, "km/h", "initial speed", 0.0, SPEED_MAX_KMH),
    _num("stab_enable_after_s", 0.0, "s", "the stability function is enabled from this time",
         0.0, DURATION_MAX_S),
)

COURSE_TYPE = Key("type", "choice", REQUIRED, "-", "the course geometry", choices=COURSE_KINDS)
COURSE_TYPES: dict[str, tuple[Key, ...]] = {
    "iso3888_1": (_LANE_LEAD_IN, _LANE_RUN_OUT),
    "iso3888_2": (_LANE_LEAD_IN, _LANE_RUN_OUT),
    "straight": (
        _num("length_m", REQUIRED, "m", "length of the road after x = 0", 0.0, 100_000.0,
             lo_open=True),
        _num("lead_in_m", 0.0, "m", "road before x = 0 (the car starts there)", 0.0, 10_000.0),
        _HALF_WIDTH,
    ),
    "curve": (
        _num("radius_m", REQUIRED, "m", "radius of the arc", 0.0, 100_000.0, lo_open=True),
        _num("arc_deg", REQUIRED, "deg", "heading change of the curve, clothoids included",
             0.0, 360.0, lo_open=True),
        _num("straight_in_m", REQUIRED, "m", "straight before the curve", 0.0, 10_000.0),
        _num("clothoid_m", REQUIRED, "m", "length of each clothoid (entry and exit)", 0.0,
             10_000.0),
        _num("straight_out_m", REQUIRED, "m", "straight after the curve", 0.0, 10_000.0),
        _DIRECTION, _HALF_WIDTH,
    ),
    "circle": (
        _num("radius_m", REQUIRED, "m", "radius of the circle", 0.0, 100_000.0, lo_open=True),
        _num("laps", REQUIRED, "-", "laps of the circle", 0.0, 1000.0, lo_open=True),
        _num("lead_in_m", 30.0, "m", "straight before the circle (a short clothoid joins "
             "them)", 0.0, 10_000.0),
        _DIRECTION, _HALF_WIDTH,
    ),
}

PATCH: tuple[Key, ...] = (
    _num("x0", None, "m", "lower x edge (omitted: unbounded)"),
    _num("x1", None, "m", "upper x edge (omitted: unbounded)"),
    _num("y0", None, "m", "lower y edge (omitted: unbounded)"),
    _num("y1", None, "m", "upper y edge (omitted: unbounded)"),
    _mu("mu", REQUIRED, "friction inside the rectangle"),
)
SPLIT: tuple[Key, ...] = (
    _num("y_line", 0.0, "m", "the line y = y_line dividing the road"),
    _mu("mu_left", REQUIRED, "friction where y >= y_line"),
    _mu("mu_right", REQUIRED, "friction where y < y_line"),
    _num("x0", None, "m", "split starts at this x (omitted: unbounded)"),
    _num("x1", None, "m", "split ends at this x (omitted: unbounded)"),
)
ROAD: tuple[Key, ...] = (
    _mu("mu", REQUIRED, "base road friction (patches override it)"),
    Key("patches", "tables", None, "-", "rectangles x0 <= x < x1, y0 <= y < y1 with their own "
        "mu; later ones override earlier ones", keys=PATCH),
    Key("split", "table", None, "-", "split-μ: left and right of a line y = y_line, from x0 "
        "to x1", keys=SPLIT),
    Key("steps", "steps", None, "s, -", "friction steps in time: [[t_s, mu], ...] (t_s >= 0, "
        "increasing); from t_s the base is mu and every patch keeps its ratio to it"),
)

DRIVER: tuple[Key, ...] = (
    Key("steer", "choice", REQUIRED, "-", "lateral: path follower or a steering robot",
        choices=STEER_MODES),
    Key("speed", "choice", REQUIRED, "-", "longitudinal: hold a speed, coast (pedals "
        "released) or brake", choices=SPEED_MODES),
    _num("preview_time_s", 0.8, "s", "path: preview time", 0.0, 10.0, lo_open=True),
    _num("preview_min_m", 6.0, "m", "path: shortest preview distance", 0.0, 1000.0),
    _num("steer_gain", 1.0, "-", "path: gain on the pure-pursuit wheel angle", 0.0, 10.0,
         lo_open=True),
    _num("neuromuscular_lag_s", 0.10, "s", "path: first-order lag of the hands", 0.0, 10.0),
    _num("swa_rate_limit_degps", 600.0, "deg/s", "path: steering-wheel rate limit", 0.0,
         10_000.0, lo_open=True),
    _num("max_swa_deg", 540.0, "deg", "largest steering-wheel angle", 0.0, 1080.0,
         lo_open=True),
    _num("target_speed_kmh", None, "km/h", "hold: target speed (omitted: the initial speed)",
         0.0, SPEED_MAX_KMH),
    _num("speed_ramp_kmhps", 0.0, "km/h/s", "hold: the target changes at this rate", -100.0,
         100.0),
    _num("speed_kp", 0.6, "1/(m/s)", "hold: pedal per m/s of speed error", 0.0, 100.0),
    _num("speed_ki", 0.15, "1/m", "hold: pedal per m of integrated speed error", 0.0, 100.0),
    _num("amplitude_deg", 180.0, "deg", "sine_dwell, step: steering-wheel amplitude", 0.0,
         1080.0),
    Key("direction", "choice", "left", "-", "robots: side of the first steering lobe",
        choices=("left", "right")),
    _num("start_s", 1.0, "s", "robots: steering starts at this time", 0.0, DURATION_MAX_S),
    _num("frequency_hz", 0.7, "Hz", "sine_dwell: sine frequency", 0.0, 10.0, lo_open=True),
    _num("dwell_s", 0.5, "s", "sine_dwell: dwell at the second peak", 0.0, 10.0),
    _num("steer_rate_degps", 13.5, "deg/s", "ramp: steering-wheel rate", 0.0, 10_000.0),
    _num("step_rate_degps", 500.0, "deg/s", "step: steering-wheel rate of the step", 0.0,
         10_000.0, lo_open=True),
    _num("brake_pedal", 1.0, "-", "brake: pedal position, 0 .. 1", 0.0, 1.0),
    _num("brake_start_s", 1.0, "s", "brake: the pedal is applied from this time", 0.0,
         DURATION_MAX_S),
    _num("pedal_rate_per_s", 4.0, "1/s", "pedal rate limit (full travel per s)", 0.0, 1000.0,
         lo_open=True),
)

TABLES: dict[str, tuple[Key, ...]] = {"road": ROAD, "driver": DRIVER}


def _hint(name: str, known: list[str], prefix: str = "") -> str:
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    if close:
        return f"; did you mean {prefix + close[0]!r}?"
    return f"; known: {', '.join(prefix + k for k in known)}"


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _show(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else repr(value)


def check_value(key: Key, value: Any, where: str) -> Any:
    """``value`` checked against ``key``; returns it normalised (numbers as float).
    ``where``: the dotted key named in the error."""
    if key.kind == "number":
        if not _is_number(value):
            raise SpecError(where, f"must be a number ({key.unit}), got {value!r}")
        if not math.isfinite(value):
            raise SpecError(where, f"must be a finite number, got {value!r}")
        too_low = key.lo is not None and (value <= key.lo if key.lo_open else value < key.lo)
        if too_low or (key.hi is not None and value > key.hi):
            raise SpecError(where, f"must be {key.range_text()}, got {_show(value)}")
        return float(value)
    if key.kind == "text":
        if not isinstance(value, str):
            raise SpecError(where, f"must be a text string, got {value!r}")
        return value
    if key.kind == "choice":
        if value not in key.choices:
            raise SpecError(where, f"must be one of {', '.join(key.choices)}, got {value!r}")
        return value
    if key.kind == "table":
        return check_table(key.keys, value, where)
    if key.kind == "tables":
        if not isinstance(value, list):
            raise SpecError(where, f"must be a list of tables, got {value!r}")
        return [check_table(key.keys, v, f"{where}[{i}]") for i, v in enumerate(value)]
    if key.kind == "steps":
        return _check_steps(value, where)
    raise AssertionError(f"schema kind {key.kind!r}")


def _check_steps(value: Any, where: str) -> list[list[float]]:
    if not isinstance(value, list | tuple):  # tuples: overrides given from Python
        raise SpecError(where, f"must be a list of [t_s, mu] pairs, got {value!r}")
    t_key = _num("t_s", REQUIRED, "s", "", 0.0, DURATION_MAX_S)
    mu_key = _mu("mu", REQUIRED, "")
    out: list[list[float]] = []
    for i, step in enumerate(value):
        at = f"{where}[{i}]"
        if isinstance(step, dict):
            check_table((t_key, mu_key), step, at)
            pair = [step["t_s"], step["mu"]]
        elif isinstance(step, list | tuple) and len(step) == 2:
            pair = list(step)
        else:
            raise SpecError(at, f"must be a [t_s, mu] pair, got {step!r}")
        t, mu = check_value(t_key, pair[0], f"{at}.t_s"), check_value(mu_key, pair[1], f"{at}.mu")
        if out and t < out[-1][0]:
            raise SpecError(at, f"t_s must not decrease: {t:g} s after {out[-1][0]:g} s")
        out.append([t, mu])
    return out


def check_table(keys: tuple[Key, ...], value: Any, where: str) -> dict[str, Any]:
    """A table checked against ``keys`` (unknown and missing keys, each value); returns it
    normalised."""
    if not isinstance(value, dict):
        raise SpecError(where, f"must be a table, got {value!r}")
    by_name = {k.name: k for k in keys}
    prefix = f"{where}." if where else ""
    for name in value:
        if name not in by_name:
            raise SpecError("", f"unknown key {prefix + name!r}"
                                + _hint(name, list(by_name), prefix))
    out: dict[str, Any] = {}
    for key in keys:
        if key.name in value:
            out[key.name] = check_value(key, value[key.name], prefix + key.name)
        elif key.default is REQUIRED:
            raise SpecError("", f"missing key {prefix + key.name!r}")
    return out


def course_keys(kind: str) -> tuple[Key, ...]:
    """The keys of a ``[course]`` table of type ``kind`` (``type`` first)."""
    return (COURSE_TYPE, *COURSE_TYPES[kind])


def check_spec(spec: dict[str, Any]) -> dict[str, Any]:
    """A whole scenario spec checked against the schema (raises :class:`SpecError`);
    returns it normalised (every number a float, only the keys it gives)."""
    tables = {"course": None, **TABLES}
    for name in spec:
        if name not in tables and name not in {k.name for k in TOP}:
            known = [k.name for k in TOP] + [f"[{t}]" for t in tables]
            raise SpecError("", f"unknown key {name!r}" + _hint(name, known))
    out = check_table(TOP, {k: v for k, v in spec.items() if k not in tables}, "")
    for name in tables:
        if name not in spec:
            raise SpecError("", f"missing table [{name}]")
    course = spec["course"]
    if not isinstance(course, dict):
        raise SpecError("course", f"must be a table, got {course!r}")
    if "type" not in course:
        raise SpecError("", "missing key 'course.type'")
    kind = check_value(COURSE_TYPE, course["type"], "course.type")
    out["course"] = check_table(course_keys(kind), course, "course")
    for name, keys in TABLES.items():
        out[name] = check_table(keys, spec[name], name)
    return out


def key_homes(spec: dict[str, Any]) -> dict[str, list[tuple[str, Key]]]:
    """Where a parameter override of each name goes in ``spec``: name -> [(table or '' for
    the top level, Key)]. Every place the spec already gives the name; a name it does not
    give goes to the first table whose schema has it (driver, road, course, top level)."""
    kind = spec.get("course", {}).get("type")
    course = COURSE_TYPES.get(kind, ()) if isinstance(kind, str) else ()
    order = [("driver", DRIVER), ("road", ROAD), ("course", course), ("", TOP)]
    homes: dict[str, list[tuple[str, Key]]] = {}
    for table, keys in order:
        given = spec if not table else spec.get(table, {})
        for key in keys:
            if isinstance(given, dict) and key.name in given:
                homes.setdefault(key.name, []).append((table, key))
    for table, keys in order:
        for key in keys:
            homes.setdefault(key.name, [(table, key)])
    return homes


def markdown_tables() -> str:
    """The key tables of docs/scenarios.md (generated from this schema)."""
    def rows(keys: tuple[Key, ...], prefix: str = "") -> list[str]:
        out = []
        for k in keys:
            default = ("**required**" if k.default is REQUIRED else
                       "—" if k.default is None else f"`{_toml(k.default)}`")
            kind = {"number": "number", "text": "string", "choice": "string",
                    "table": "table", "tables": "list of tables", "steps": "list"}[k.kind]
            out.append(f"| `{prefix}{k.name}` | {kind} | {k.unit} | {default} | "
                       f"{k.range_text()} | {k.doc} |")
        return out

    head = ["| key | type | unit | default | range | meaning |",
            "|---|---|---|---|---|---|"]
    parts = ["### Top level", "", *head, *rows(TOP), "",
             "### `[course]`", "", *head, *rows((COURSE_TYPE,))]
    for kind, keys in COURSE_TYPES.items():
        parts += ["", f"`type = \"{kind}\"`:", "", *head, *rows(keys)]
    parts += ["", "### `[road]`", "", *head, *rows(ROAD), "", "Each of `patches`:", "",
              *head, *rows(PATCH), "", "`split`:", "", *head, *rows(SPLIT), "",
              "### `[driver]`", "", *head, *rows(DRIVER)]
    return "\n".join(parts) + "\n"


def _toml(value: Any) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    return f"{value:g}" if isinstance(value, float) else str(value)


if __name__ == "__main__":
    print(markdown_tables(), end="")
