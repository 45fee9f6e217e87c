"""Controller configurations of runs: a packaged or given TOML with per-run key overrides.

A run's ``controller_overrides`` (harness/run/spec.py) are ``("SECTION.KEY", value)`` pairs;
a bare ``KEY`` means ``references.KEY``. The file the controller process loads is the base
TOML (the packaged default.toml, or the run's ``controller_config``) with each overridden key
replaced in its section (or added to it), written once under a name that is the hash of its
text, so equal configurations share one file and a changed base never reuses a stale one.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

DEFAULT_SECTION = "references"


def base_config_text(config: str | None) -> str:
    """The TOML text of ``config`` (a path, or a packaged name such as ``100hz``); the
    packaged default.toml when None."""
    if config is None:
        return resources.files("controller").joinpath("config/default.toml").read_text()
    path = Path(config)
    if path.is_file():
        return path.read_text()
    return resources.files("controller").joinpath(f"config/{config}.toml").read_text()


def overridden_text(base: str, overrides: dict[str, Any]) -> str:
    """``base`` with each ``SECTION.KEY`` (bare KEY: [references]) set to its value."""
    over: dict[str, dict[str, Any]] = {}
    for k, v in overrides.items():
        section, _, key = k.rpartition(".")
        over.setdefault(section or DEFAULT_SECTION, {})[key] = v
    out: list[str] = []
    section = ""
    seen: set[str] = set()
    for line in base.splitlines():
        m = re.match(r"^\[([^\]]+)\]", line)
        if m:
            section = m.group(1)
            seen.add(section)
            out.append(line)
            out += [f"{k} = {_toml_value(v)}" for k, v in over.get(section, {}).items()]
            continue
        km = re.match(r"^(\w+)\s*=", line)
        if km and km.group(1) in over.get(section, {}):
            continue
        out.append(line)
    for name, keys in over.items():  # a section the base does not have
        if name not in seen:
            out += ["", f"[{name}]", *(f"{k} = {_toml_value(v)}" for k, v in keys.items())]
    return "\n".join(out) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def config_file(config: str | None, overrides: dict[str, Any], folder: Path) -> str | None:
    """The file a controller loads for ``config`` with ``overrides`` (``config`` itself when
    there are none), written in ``folder`` under the hash of its text."""
    if not overrides:
        return config
    text = overridden_text(base_config_text(config), overrides)
    path = folder / f"ctrl-{hashlib.sha256(text.encode()).hexdigest()[:16]}.toml"
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        tmp.replace(path)  # another worker writing the same file writes the same bytes
    return str(path)


def mpc_period_s(config: str | None, overrides: dict[str, Any]) -> float | None:
    """The MPC period Ts (s, ``[controller] ts_s``) of the configuration a run's controller
    loads (``config`` with ``overrides``); None if it cannot be read or sets none."""
    try:
        text = overridden_text(base_config_text(config), overrides)
        ts = tomllib.loads(text).get("controller", {}).get("ts_s")
    except (OSError, ValueError, TypeError):  # tomllib.TOMLDecodeError is a ValueError
        return None
    return float(ts) if isinstance(ts, int | float) and ts > 0 else None
