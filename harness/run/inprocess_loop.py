"""The closed loop without sockets: PlantNode and ControllerNode exchanging real frames.

Same frames, codec, monitors and node logic as the cross-process lockstep run, so its torque
frames are bit-identical to a lockstep bus run with the same seed — only the sockets and the
process boundaries are missing. Used for tuning and unit-speed experiments; the published
results always come from the cross-process runs (``rhonn-harness run``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from can_db.codec import Decoded
from controller.core.params import load_vehicle_params
from controller.registry import make_controller
from controller.runtime.node import ControllerNode
from plant_sim.node import TORQUE_FRAME, PlantNode
from plant_sim.overrides import apply_vehicle_overrides
from plant_sim.params import load_vehicle_params as load_plant_params
from plant_sim.scenario import load_scenario
from plant_sim.simulation import Simulation


def exchange_cycle(plant: PlantNode, node: ControllerNode) -> Decoded | None:
    """One lockstep cycle without sockets: the plant's burst to the node, the node's answer
    back to the plant; the decoded torque command, or None if there was none."""
    answer = None
    for frame in plant.burst():
        out = node.on_frame_lockstep(frame)
        if out is not None:
            answer = out
    command = None
    for frame in answer or ():
        got = plant.receive(frame, plant.sim.time_s)
        # receive() also returns CTRL_STATUS (for the lost-torque-frame check of the lockstep
        # run); only the torque frame is a command.
        if got is not None and got.name == TORQUE_FRAME:
            command = got
    return command


@dataclass
class InProcessResult:
    """Truth columns (arrays at the 10 ms cycle) and the node's per-cycle ΔM and references.

    model_err_rms: per cycle, the learned model's filtered RMS one-step yaw-rate prediction
    error, rad/s (the confidence gate's signal; NaN for a controller without a learned model).
    """

    truth: dict[str, np.ndarray]
    delta_m: np.ndarray
    yaw_rate_ref: np.ndarray
    beta_ref: np.ndarray
    spun: bool
    model_err_rms: np.ndarray


def run_in_process(scenario: str, controller: str, *, mu: float | None = None,
                   speed_kmh: float | None = None, seed: int = 0, config: str | None = None,
                   duration_s: float | None = None, vehicle: dict[str, float] | None = None,
                   **params: object) -> InProcessResult:
    """Run ``scenario`` with ``controller`` in lockstep, in this process.

    vehicle: plant parameter overrides (plant_sim/overrides.py), e.g. {"mass_scale": 1.15}.
    """
    plant_params = apply_vehicle_overrides(load_plant_params(), vehicle or {})
    sim = Simulation(load_scenario(scenario, mu=mu, speed_kmh=speed_kmh, **params),
                     params=plant_params, seed=seed)
    plant = PlantNode(sim)
    node = ControllerNode(make_controller(controller, config), load_vehicle_params())
    rows = [sim.truth_row()]
    dms, rrefs, brefs, errs = [], [], [], []
    model = getattr(node.controller, "model", None)
    has_err = hasattr(model, "err_ms")
    while not sim.finished and (duration_s is None or sim.time_s < duration_s - 1e-9):
        command = exchange_cycle(plant, node)
        out_rec = node.record.outputs
        dms.append(float(node.torques[1] + node.torques[3] - node.torques[0] - node.torques[2]))
        rrefs.append(out_rec.yaw_rate_ref)
        brefs.append(out_rec.beta_ref)
        errs.append(math.sqrt(model.err_ms) if has_err else math.nan)
        plant.advance(command)
        rows.append(sim.truth_row())
    truth = {k: np.array([r[k] for r in rows]) for k in sim.trace_columns}
    return InProcessResult(truth, np.array(dms), np.array(rrefs), np.array(brefs),
                           bool(sim.spun), np.array(errs))
