"""Injected core faults (``--fault core-exception[:D][@T]``, can_db/faults.py).

:class:`FaultyCore` wraps the controller core the node steps. While a ``core-exception``
window is open (simulated time T ≤ t < T + D, or t ≥ T without a duration) its ``step`` and
``allocate_only`` raise :class:`InjectedCoreError` from inside the call the node makes, so the
exception travels the same path a bug in the core would: through the node's handler in
``ControllerNode._run_controller`` (controller/runtime/node.py), which selects FAULT and the
safe torques. Nothing here touches the node's mode or outputs.

The simulated time is read through ``clock`` (the node binds it to the SIM_TIME of the SYNC
being answered), so a lockstep run with a core fault is as reproducible as one without.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from can_db.faults import FaultSpec
from controller.core.interfaces import Controller, ControllerInputs, ControllerOutputs


class InjectedCoreError(RuntimeError):
    """Raised by :class:`FaultyCore` inside the core's step (an injected fault)."""


class FaultyCore:
    """A controller core that raises while a ``core-exception`` fault is active.

    Every other attribute (``name``, ``ts`` in s, ``model``, ``backend``, ``reset`` …) is the
    wrapped core's, so the node and the checkpointing see the core they would see without it.
    """

    def __init__(self, core: Controller, faults: list[FaultSpec],
                 clock: Callable[[], float] | None = None) -> None:
        self._core = core
        # (start, end) windows in simulated s; end is inf without a duration
        self._windows = [(f.at_s, f.at_s + f.amount) for f in faults if f.is_core_fault]
        self._clock = clock or (lambda: 0.0)
        self.raised = 0  # exceptions raised so far

    def bind(self, clock: Callable[[], float]) -> None:
        """Read the simulated time (s) from ``clock`` from now on."""
        self._clock = clock

    def __getattr__(self, name: str) -> Any:
        return getattr(self._core, name)

    def _check(self, where: str) -> None:
        now = self._clock()
        for start, end in self._windows:
            if start - 1e-9 <= now < end - 1e-9:
                self.raised += 1
                raise InjectedCoreError(f"core-exception injected in {where} at "
                                        f"t = {now:.3f} s")

    def step(self, inputs: ControllerInputs) -> ControllerOutputs:
        """The core's full step, or InjectedCoreError inside an active window."""
        self._check("step")
        return self._core.step(inputs)

    def allocate_only(self, inputs: ControllerInputs) -> ControllerOutputs:
        """The core's re-allocation, or InjectedCoreError inside an active window."""
        self._check("allocate_only")
        return self._core.allocate_only(inputs)


def core_faults(faults: list[FaultSpec]) -> list[FaultSpec]:
    """The faults of ``faults`` that :class:`FaultyCore` carries out."""
    return [f for f in faults if f.is_core_fault]
