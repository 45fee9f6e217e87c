"""A plant run's options as the command line and the harness check them: scenario overrides
(``--param``), the scenario argument, and the whole scenario set-up checked once before
anything starts, each problem one line (UsageError)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from can_db.process.argcheck import UsageError
from plant_sim.overrides import apply_vehicle_overrides
from plant_sim.params import load_vehicle_params
from plant_sim.scenario import ScenarioError, check_scenario_ref, load_scenario, scenario_source
from plant_sim.scenario_schema import DURATION_MAX_S, MU_MAX, SPEED_MAX_KMH
from plant_sim.simulation import Simulation

__all__ = ["DURATION_MAX_S", "MU_MAX", "SPEED_MAX_KMH", "check_scenario", "parse_params",
           "scenario_arg"]


def parse_params(items: list[str]) -> dict[str, Any]:
    """``--param KEY=VALUE`` items as a dict (numbers as float, a value in brackets as a JSON
    list, e.g. ``steps=[[8,0.3]]``); UsageError if malformed."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--param needs KEY=VALUE, got {item!r}")
        if value.strip().startswith("["):
            try:
                out[key.strip()] = json.loads(value)
            except ValueError:
                raise UsageError(f"--param {key.strip()}: not a JSON list: {value!r}") from None
            continue
        try:
            out[key.strip()] = float(value)
        except ValueError:
            out[key.strip()] = value
    return out


def scenario_arg(text: str) -> str:
    """``argparse`` type of a scenario: a packaged name, or a path to a scenario file
    (anything containing '/' or ending in .toml; child processes inherit the working
    directory, so a relative path names the same file). The file's content is checked by
    :func:`check_scenario`, so its errors name the file as the user wrote it."""
    try:
        check_scenario_ref(text)
    except ScenarioError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def check_scenario(name: str, mu: float | None, speed_kmh: float | None,
                   params: dict[str, Any], seed: int = 0,
                   vehicle: dict[str, float] | None = None) -> Simulation:
    """Load the scenario (a packaged name or a file) with its overrides, apply the plant
    overrides and build the simulation once (nothing runs); any problem is a one-line
    UsageError naming the file or option, the key and the problem."""
    try:
        scenario = load_scenario(name, mu=mu, speed_kmh=speed_kmh, **params)
    except ScenarioError as exc:
        raise UsageError(str(exc)) from None
    try:
        car = apply_vehicle_overrides(load_vehicle_params(), vehicle or {})
    except ValueError as exc:
        raise UsageError(f"--vehicle: {exc}") from None
    try:
        return Simulation(scenario, params=car, seed=seed)
    except (KeyError, ValueError, TypeError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        raise UsageError(f"{scenario_source(name)}: {msg}") from None
