"""The controller fuzz target's slew check starts again with the controller: a sequence that
ends braking and the next one, cold, driving may not read as one 200 N·m jump
(harness/fuzz/targets.py ControllerTarget.reset, used by the random and the hypothesis pass)."""

from __future__ import annotations

from controller.core.params import load_vehicle_params
from harness.fuzz.targets import ControllerTarget


def _drive(target: ControllerTarget, accel: float, brake: float, steps: int) -> str | None:
    inp = target.inp
    inp.vx, inp.vy, inp.yaw_rate, inp.swa_rad, inp.ax, inp.ay = 20.0, 0.0, 0.0, 0.0, 0.0, 0.0
    inp.wheel_speeds[:] = 20.0 / 0.358
    inp.accel_pedal, inp.brake_pedal = accel, brake
    inp.stab_enable = inp.sensors_valid = True
    problem = None
    for _ in range(steps):
        problem = problem or target._check(target.ctrl.step(inp), inp)
    return problem


def test_a_cold_sequence_is_checked_against_a_cold_controller() -> None:
    target = ControllerTarget("lmpc", load_vehicle_params())
    assert _drive(target, 0.0, 1.0, 3) is None          # braking: every wheel −100 N·m per cycle
    assert min(target.last_cmd) < -150.0
    target.reset()
    assert _drive(target, 1.0, 0.0, 1) is None          # driving from a cold controller: +100
    # the controller alone reset, the check would compare with the braking answer
    _drive(target, 0.0, 1.0, 3)
    target.ctrl.reset()
    assert "moved" in (_drive(target, 1.0, 0.0, 1) or "")
