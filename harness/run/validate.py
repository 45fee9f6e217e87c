"""Check a :class:`RunConfig` before anything starts: no process, server, file or directory is
created for a run that cannot work. Every problem is one :class:`UsageError` line."""

from __future__ import annotations

from can_db.codec import Codec
from can_db.faults import FaultInjector, FaultSpecError, parse_fault, parse_faults
from can_db.process.argcheck import UsageError, check_out_dir, check_port_free
from can_db.process.cpu import CpuChoiceError, choose_cpu
from can_db.transport.check import check_bus
from controller.core.config_schema import CONFIG_LOAD_ERRORS, config_error_line
from controller.core.registry import CONTROLLER_NAMES, load_controller_config
from harness.run.runner import RunConfig, _route_frame_faults
from plant_sim.process import check_scenario


def check_controller_config(config: str | None) -> None:
    """The controller TOML loads (exists, is TOML, known keys, right types)."""
    if config is None:
        return
    try:
        load_controller_config(config)
    except CONFIG_LOAD_ERRORS as exc:
        raise UsageError(config_error_line(config, exc)) from None


def check_faults(cfg: RunConfig) -> None:
    """Every ``--fault`` parses, names real messages/signals and suits the mode."""
    try:
        faults = parse_faults(list(cfg.faults))
        if cfg.kill_controller_at_s is not None:
            faults.append(parse_fault(f"kill-controller@{cfg.kill_controller_at_s}s"))
        FaultInjector(Codec(), faults)
        _route_frame_faults(faults, Codec(), lockstep=cfg.mode == "lockstep")
    except FaultSpecError as exc:
        raise UsageError(f"bad --fault: {exc}") from None


def check_rerun_live(web_port: int) -> None:
    """Both ports of the live viewer are free on 127.0.0.1 and the rerun CLI is there."""
    import importlib.util

    from harness.viz.rerun_live import GRPC_PORT_OFFSET

    if importlib.util.find_spec("rerun") is None:
        raise UsageError("--rerun-live needs rerun-sdk: pip install 'rhonn-tv[harness]'")
    if web_port + GRPC_PORT_OFFSET > 65535:
        raise UsageError(f"--rerun-port {web_port}: must be <= {65535 - GRPC_PORT_OFFSET}")
    for port in (web_port, web_port + GRPC_PORT_OFFSET):
        check_port_free(port)


def check_run_config(cfg: RunConfig, *, bus: bool = True) -> None:
    """Raise UsageError for the first thing in ``cfg`` that cannot work.

    ``bus``: also check that the bus is there (skip for configs checked long before their
    run, e.g. a batch).
    """
    if cfg.controller not in CONTROLLER_NAMES:
        raise UsageError(f"unknown controller {cfg.controller!r}; choose from "
                         f"{', '.join(CONTROLLER_NAMES)}")
    if cfg.duration_s is not None and not cfg.duration_s > 0:
        raise UsageError(f"--duration {cfg.duration_s} s: must be > 0")
    check_scenario(cfg.scenario, cfg.mu, cfg.speed_kmh, dict(cfg.params), cfg.seed)
    check_controller_config(cfg.controller_config)
    check_faults(cfg)
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
