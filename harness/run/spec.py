"""One description of a closed-loop run: :class:`RunSpec`.

``rhonn-harness run`` and ``compare``, the paper study, the stability benchmark and campaigns all
describe a run with it. It holds *what* runs (scenario, controller, overrides, faults, seed —
these decide the outcome and enter :meth:`RunSpec.key`) and *how* it is run and recorded (bus,
output directory, plots, recordings, time-outs, CPU layout — these do not change what the run
computes and stay out of the key).

Speeds in km/h, friction dimensionless, durations in simulated s unless named ``wall``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from plant_sim.scenario import is_scenario_file

# the live rerun view's data (gRPC) port = its web viewer port (``rerun_port``) + this
# (9090 → rerun's usual 9876)
GRPC_PORT_OFFSET = 786


def _frozen_value(value: Any) -> Any:
    """A hashable form of a parameter value (lists become tuples, at any depth)."""
    if isinstance(value, list | tuple):
        return tuple(_frozen_value(v) for v in value)
    return value


def _json_value(value: Any) -> Any:
    """The JSON form of a parameter value (tuples become lists, at any depth)."""
    if isinstance(value, tuple):
        return [_json_value(v) for v in value]
    return value


def _pairs(value: Any) -> tuple[tuple[str, Any], ...]:
    """A mapping (or pairs) as sorted, hashable ``(key, value)`` pairs."""
    items = value.items() if isinstance(value, dict) else (value or ())
    return tuple(sorted((str(k), _frozen_value(v)) for k, v in items))


@dataclass(frozen=True)
class RunSpec:
    """One closed-loop run.

    ``params`` (scenario overrides, ``--param``), ``vehicle`` (plant overrides, ``--vehicle``)
    and ``info`` are kept as sorted pairs and ``faults``/``post``/extra arguments as tuples, so
    equal runs compare and hash equal; a dict or list given for them is converted. Read them
    with ``dict(spec.params)``.
    """

    scenario: str
    controller: str
    out_dir: Path | None = None  # the run's directory (campaigns: :meth:`run_dir`)
    group: str = ""  # the campaign matrix or study a run belongs to
    seed: int = 0
    mu: float | None = None
    speed_kmh: float | None = None
    duration_s: float | None = None
    params: tuple[tuple[str, Any], ...] = ()
    vehicle: tuple[tuple[str, float], ...] = ()  # plant_sim/overrides.py
    faults: tuple[str, ...] = ()  # --fault specs, see can_db/faults.py
    controller_config: str | None = None
    # ("SECTION.KEY", value) on top of controller_config (harness/run/controller_config.py)
    controller_overrides: tuple[tuple[str, Any], ...] = ()
    mode: str = "lockstep"  # lockstep | realtime
    controller_mode: str = "lockstep"  # lockstep (sync-driven) | freerun
    kill_controller_at_s: float | None = None  # simulated s (same as fault kill-controller@T)
    controller_extra_args: tuple[str, ...] = ()
    plant_extra_args: tuple[str, ...] = ()  # e.g. ("--lost-after", "100")
    secoc: bool = True  # authenticated SYNC/torque/status frames (can_db/secoc.py)
    post: tuple[str, ...] = ()  # post-processing steps of a campaign run (campaign/task.py)
    info: tuple[tuple[str, Any], ...] = ()  # free data for a post step
    # the plant's hold of the last torque command without a fresh one, ms (None: its default,
    # 30 ms); the same rule in lockstep and real time (PlantNode, plant_sim/node.py)
    command_hold_ms: float | None = None
    # where the controller runs: "host" (the Python controller process) or "m4f" (the node
    # as Cortex-M4F firmware on QEMU, bridged to the bus: harness/bench/mcu/pil_node.py)
    target: str = "host"
    # --- how the run is carried out and recorded (not in the key)
    bus: str = "auto"
    wall_timeout_s: float = 600.0
    # lockstep: the plant's wall-clock wait for each cycle's answer, ms (None: the plant's
    # default, 200 ms); raise it on slow machines (emulators, loaded CI) to avoid time-outs
    lockstep_wait_ms: float | None = None
    bus_start_timeout_s: float = 10.0  # a started hub or bus server must be up by then, wall s
    make_plots: bool = True
    make_rrd: bool = True
    rt: bool = False  # plant, controller, hub and recorder ask for SCHED_FIFO (process/rt.py)
    log_format: str = "blf"  # bus log: blf | asc | mf4 (see harness/run/bus_logger.py)
    rerun_live: bool = False  # stream to a rerun web viewer on 127.0.0.1 during the run
    rerun_port: int = 9090  # web viewer port of --rerun-live
    secoc_keys: str | None = None  # env | ci-test-key | KEYFILE; None: env if set, else test key
    # HIL layout: the controller alone on this CPU ("auto": the highest), kept awake
    # (can_db/process/cpu.py); harness, recorder, hub and plant on the others. None: all share.
    controller_cpu: str | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise the given forms once, here
        set_(self, "params", _pairs(self.params))
        set_(self, "vehicle", tuple(sorted((str(k), float(v)) for k, v in
                                           (dict(self.vehicle) or {}).items())))
        set_(self, "info", _pairs(self.info))
        set_(self, "controller_overrides", _pairs(self.controller_overrides))
        for name in ("faults", "post", "controller_extra_args", "plant_extra_args"):
            set_(self, name, tuple(getattr(self, name) or ()))
        if self.out_dir is not None and not isinstance(self.out_dir, Path):
            set_(self, "out_dir", Path(self.out_dir))

    # ------------------------------------------------------------------ identity
    def identity(self) -> dict[str, Any]:
        """Everything that decides the run's outcome (the hashed configuration). Fields at
        their defaults that campaigns never set stay out, so the keys of such runs do not
        depend on them."""
        cfg_sha = None
        if self.controller_config:
            try:
                cfg_sha = hashlib.sha256(Path(self.controller_config).read_bytes()).hexdigest()
            except OSError:
                cfg_sha = "unreadable"
        ident: dict[str, Any] = {
            "scenario": self.scenario, "controller": self.controller, "seed": self.seed,
            "mu": self.mu, "speed_kmh": self.speed_kmh, "duration_s": self.duration_s,
            "params": [[k, _json_value(v)] for k, v in self.params],
            "faults": list(self.faults), "controller_config": self.controller_config,
            "controller_config_sha256": cfg_sha, "mode": self.mode,
            "controller_mode": self.controller_mode, "post": list(self.post),
            "info": [[k, _json_value(v)] for k, v in self.info]}
        if self.vehicle:
            ident["vehicle"] = [list(v) for v in self.vehicle]
        for name in ("kill_controller_at_s", "controller_extra_args", "plant_extra_args",
                     "controller_overrides"):
            if getattr(self, name):
                ident[name] = _json_value(getattr(self, name))
        if not self.secoc:
            ident["secoc"] = False
        if self.command_hold_ms is not None:
            ident["command_hold_ms"] = self.command_hold_ms
        if self.target != "host":
            ident["target"] = self.target
        if is_scenario_file(self.scenario):  # a scenario file: its content decides the run too
            try:
                ident["scenario_sha256"] = hashlib.sha256(
                    Path(self.scenario).read_bytes()).hexdigest()
            except OSError:
                ident["scenario_sha256"] = "unreadable"
        return ident

    def key(self) -> str:
        """16 hex digits of the SHA-256 of :meth:`identity` as canonical JSON."""
        text = json.dumps(self.identity(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def run_dir(self, root: Path) -> Path:
        """Where a campaign run's files go: ROOT/runs/<group>/<key>."""
        return Path(root) / "runs" / (self.group or "runs") / self.key()

    # ------------------------------------------------------------------ transport
    def to_json(self) -> dict[str, Any]:
        """Plain JSON-able dict (for a worker and a manifest); :meth:`from_json` inverts it."""
        d = asdict(self)
        for name in ("params", "vehicle", "info", "controller_overrides"):
            d[name] = [[k, _json_value(v)] for k, v in getattr(self, name)]
        for name in ("faults", "post", "controller_extra_args", "plant_extra_args"):
            d[name] = list(getattr(self, name))
        d["out_dir"] = None if self.out_dir is None else str(self.out_dir)
        return d

    @staticmethod
    def from_json(d: dict[str, Any]) -> RunSpec:
        """Inverse of :meth:`to_json` (unknown keys are an error: a TypeError)."""
        known = {f.name for f in fields(RunSpec)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise TypeError(f"RunSpec: unknown field(s) {', '.join(unknown)}")
        return RunSpec(**d)
