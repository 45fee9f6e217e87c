"""Name → controller, with the backend chosen once per controller.

``make_controller(name, config)`` builds the C core (controller/native, built at install)
when it is available and runs this configuration, else the numpy reference
(controller/core), saying why once on the log. The choice: ``[controller] backend`` in the
TOML (auto | native | numpy), overridden by ``RHONN_BACKEND`` or the ``backend`` argument;
"native" makes an unavailable core an error instead of a fallback.
"""

from __future__ import annotations

from pathlib import Path

from controller.core.interfaces import Controller
from controller.core.registry import (
    CONTROLLER_NAMES,
    ESTIMATOR_NAMES,
    build_reference,
    load_controller_config,
    make_estimator,
)
from controller.native.backend import (
    core_module,
    note_numpy,
    requested_backend,
    unavailable_reason,
)
from controller.native.config import NotSupportedError
from controller.native.controller import NativeController

__all__ = ["CONTROLLER_NAMES", "ESTIMATOR_NAMES", "make_controller", "make_estimator"]


def make_controller(name: str, config: str | Path | None = None,
                    backend: str | None = None) -> Controller:
    """Build controller ``name`` (see CONTROLLER_NAMES) from a TOML configuration (None →
    the packaged default.toml) on the chosen backend (see the module docstring)."""
    if name not in CONTROLLER_NAMES:
        raise ValueError(f"unknown controller {name!r}; choose from {CONTROLLER_NAMES}")
    cfg = load_controller_config(config)
    env = requested_backend()
    choice = backend or (env if env != "auto" else cfg.backend)
    if choice != "numpy":
        float32 = cfg.mpc.precision == "float32"
        module = core_module(float32)
        reason = unavailable_reason(float32)
        if module is not None:
            try:
                return NativeController(name, cfg, module)
            except NotSupportedError as exc:
                reason = f"the C core does not run this configuration: {exc}"
        if choice == "native":
            raise RuntimeError(f"backend \"native\": {reason}")
        note_numpy(str(reason))
    return build_reference(name, cfg)
