"""Check a :class:`RunSpec` before anything starts: no process, server, file or directory is
created for a run that cannot work. Every problem is one :class:`UsageError` line naming the
option (or the scenario file and key) and the problem.

One mechanism for every front end: ``rhonn-harness run`` and ``compare`` call
:func:`check_run_config` on the config they built; a campaign calls it on every distinct
run of its matrix (harness/campaign/task.py, ``check_runs``) before its first run starts.
Values are held to the same ranges as the command-line flags (the ``argparse`` types of
:mod:`can_db.process.argcheck`), so a config built in Python meets the same checks as one
typed by a user.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import tempfile
from pathlib import Path
from typing import Any

from can_db.codec import Codec
from can_db.faults import FaultInjector, FaultSpecError, parse_fault, parse_faults
from can_db.process.argcheck import UsageError, check_out_dir, check_port_free, number
from can_db.process.cpu import CpuChoiceError, choose_cpu
from can_db.secoc_keys import SecOcKeyError, load_keys, resolve_key_source
from can_db.transport.check import check_bus
from controller.core.config_schema import CONFIG_LOAD_ERRORS, config_error_line
from controller.core.registry import CONTROLLER_NAMES, load_controller_config
from harness.run.bus_logger import LOG_FORMATS
from harness.run.controller_config import config_file
from harness.run.hil_bench import check_target, route_frame_faults
from harness.run.spec import GRPC_PORT_OFFSET, RunSpec
from plant_sim.run_options import (
    DURATION_MAX_S,
    MU_MAX,
    SPEED_MAX_KMH,
    check_scenario,
    parse_params,
)
from plant_sim.scenario import ScenarioError, check_scenario_ref

MODES = ("lockstep", "realtime")
CONTROLLER_MODES = ("lockstep", "freerun")


def check_controller_config(config: str | None) -> None:
    """The controller TOML loads (exists, is TOML, known keys, right types)."""
    if config is None:
        return
    try:
        load_controller_config(config)
    except CONFIG_LOAD_ERRORS as exc:
        raise UsageError(config_error_line(config, exc)) from None


def check_faults(cfg: RunSpec) -> None:
    """Every ``--fault`` parses, names real messages/signals and suits the mode."""
    try:
        faults = parse_faults(list(cfg.faults))
        if cfg.kill_controller_at_s is not None:
            faults.append(parse_fault(f"kill-controller@{cfg.kill_controller_at_s}s"))
        FaultInjector(Codec(), faults)
        route_frame_faults(faults, Codec(), lockstep=cfg.mode == "lockstep")
    except FaultSpecError as exc:
        raise UsageError(f"bad --fault: {exc}") from None


def check_rerun_live(web_port: int) -> None:
    """Both ports of the live viewer are free on 127.0.0.1 and the rerun CLI is there."""
    if importlib.util.find_spec("rerun") is None:
        raise UsageError("--rerun-live needs rerun-sdk: pip install 'rhonn-tv[harness]'")
    if web_port + GRPC_PORT_OFFSET > 65535:
        raise UsageError(f"--rerun-port {web_port}: must be <= {65535 - GRPC_PORT_OFFSET}")
    for port in (web_port, web_port + GRPC_PORT_OFFSET):
        check_port_free(port)


def _in_range(flag: str, value: Any, check: Any) -> None:
    """``value`` passes the ``argparse`` type ``check`` of ``flag`` (as if typed)."""
    try:
        check(str(value))
    except argparse.ArgumentTypeError as exc:
        raise UsageError(f"{flag}: {exc}") from None


def plant_params(cfg: RunSpec) -> dict[str, Any]:
    """``cfg.params`` as the plant process receives them: written as ``--param KEY=VALUE``
    (harness/run/runner.py) and read back by its parser (numbers from text, JSON lists)."""
    items = []
    for key, value in cfg.params:
        text = json.dumps(value) if isinstance(value, list | tuple) else value
        items.append(f"{key}={text}")
    return parse_params(items)


def check_secoc(cfg: RunSpec) -> None:
    """The SecOC key source loads (a key file: exists, mode 600, both keys); keys given
    with SecOC off are an error (they would be ignored)."""
    if not cfg.secoc:
        if cfg.secoc_keys is not None:
            raise UsageError("--secoc-keys is given with --no-secoc (no keys are used)")
        return
    try:
        load_keys(resolve_key_source(cfg.secoc_keys))
    except SecOcKeyError as exc:
        raise UsageError(f"--secoc-keys: {exc}") from None


def check_run_config(cfg: RunSpec, *, bus: bool = True) -> None:
    """Raise UsageError for the first thing in ``cfg`` that cannot work.

    ``bus``: also check that the bus is there (skip for configs checked long before their
    run, e.g. a batch).
    """
    if cfg.controller not in CONTROLLER_NAMES:
        raise UsageError(f"unknown controller {cfg.controller!r}; choose from "
                         f"{', '.join(CONTROLLER_NAMES)}")
    try:
        check_scenario_ref(cfg.scenario)
    except ScenarioError as exc:
        raise UsageError(str(exc)) from None
    for flag, value, choices in (("--mode", cfg.mode, MODES),
                                 ("--controller-mode", cfg.controller_mode, CONTROLLER_MODES),
                                 ("--log-format", cfg.log_format, LOG_FORMATS)):
        if value not in choices:
            raise UsageError(f"{flag}: {value!r} is not one of {', '.join(choices)}")
    for flag, value, check in (
            ("--mu", cfg.mu, number(lo=0.0, hi=MU_MAX, lo_open=True)),
            ("--speed", cfg.speed_kmh, number(lo=0.0, hi=SPEED_MAX_KMH, unit="km/h")),
            ("--duration", cfg.duration_s, number(lo=0.0, hi=DURATION_MAX_S, lo_open=True,
                                                  unit="s")),
            ("--seed", cfg.seed, number(int, lo=0))):
        if value is not None:
            _in_range(flag, value, check)
    check_scenario(cfg.scenario, cfg.mu, cfg.speed_kmh, plant_params(cfg), cfg.seed,
                   dict(cfg.vehicle))
    check_controller_config(cfg.controller_config)
    if cfg.controller_overrides:  # the merged file must load too (written to a scratch dir)
        with tempfile.TemporaryDirectory() as scratch:
            check_controller_config(config_file(cfg.controller_config,
                                                dict(cfg.controller_overrides), Path(scratch)))
    check_faults(cfg)
    check_secoc(cfg)
    try:
        check_target(cfg)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    check_out_dir(cfg.out_dir)
    if cfg.rerun_live:
        check_rerun_live(cfg.rerun_port)
    if cfg.controller_cpu is not None:
        if cfg.rt:  # the recorder would have no CPU beside the loop (harness/run/bus_logger.py)
            raise UsageError("--controller-cpu is not combined with the SCHED_FIFO loop (rt)")
        try:
            choose_cpu(cfg.controller_cpu)
        except CpuChoiceError as exc:
            raise UsageError(f"--controller-cpu: {exc}") from None
    if bus:
        check_bus(cfg.bus)
