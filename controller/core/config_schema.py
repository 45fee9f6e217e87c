"""One typed schema for every controller configuration table.

Each section of a controller TOML maps onto a ``@dataclass`` whose annotated fields are the
schema: ``build_section`` checks every key against the fields, every value against the field's
type, and raises :class:`ConfigError` — one line naming the file, the section and the key —
for an unknown key or a wrong type. Cross-field rules stay with each dataclass (its
``from_dict``). Stdlib only, on purpose: the controller core is deployed alone on an ECU-like
target, and a flat schema of numbers, strings and short tuples does not need pydantic or
msgspec (both were considered; neither is needed to give the one-line errors asked for).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value that cannot be used. ``str()`` is one line:
    ``FILE: [section] key: what is wrong``."""

    def __init__(self, section: str, key: str, message: str, source: str = "") -> None:
        self.section, self.key, self.message, self.source = section, key, message, source
        super().__init__(self._line())

    def _line(self) -> str:
        where = " ".join(x for x in (f"[{self.section}]" if self.section else "", self.key) if x)
        parts = [x for x in (self.source, where, self.message) if x]
        return ": ".join(parts)

    def with_source(self, source: str) -> ConfigError:
        """The same error, naming the file it came from."""
        return ConfigError(self.section, self.key, self.message, source)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, section: str, key: str) -> Any:
    """``value`` converted to the annotated type ``tp`` or ConfigError."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        for option in typing.get_args(tp):
            try:
                return _coerce(value, option, section, key)
            except ConfigError:
                continue
        raise ConfigError(section, key, f"expected {_type_name(tp)}, got {value!r}")
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            out = float(value)
            if math.isnan(out):
                raise ConfigError(section, key, "NaN is not a value")
            return out
    elif tp is str:
        if isinstance(value, str):
            return value
    elif origin is tuple:
        args = typing.get_args(tp)
        if isinstance(value, list | tuple):
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(_coerce(v, args[0], section, key) for v in value)
            if len(value) != len(args):
                raise ConfigError(section, key, f"expected {len(args)} entries, got {len(value)}")
            return tuple(_coerce(v, a, section, key) for v, a in zip(value, args, strict=True))
    elif origin is dict or tp is dict:
        if isinstance(value, Mapping):
            return dict(value)
    elif dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if isinstance(value, Mapping):
            return build_section(tp, value, f"{section}.{key}")
    else:  # a type the schema does not know: pass through unchecked rather than guess
        return value
    raise ConfigError(section, key, f"expected {_type_name(tp)}, got {type(value).__name__} "
                                    f"{value!r}")


def build_section(cls: type[T], table: Mapping[str, Any], section: str) -> T:
    """Instance of dataclass ``cls`` from a TOML ``table``: defaults for missing keys,
    ConfigError for an unknown key or a value of the wrong type."""
    if not isinstance(table, Mapping):
        raise ConfigError(section, "", f"expected a table, got {type(table).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in table.items():
        if key not in known:
            raise ConfigError(section, key, f"unknown key (known: {', '.join(sorted(known))})")
        kwargs[key] = _coerce(value, hints[key], section, key)
    return cls(**kwargs)


def require_positive(cfg: object, section: str, keys: tuple[str, ...]) -> None:
    """ConfigError naming the first of ``keys`` whose value in ``cfg`` is not a finite
    number > 0."""
    for key in keys:
        if not 0.0 < getattr(cfg, key) < math.inf:
            raise ConfigError(section, key, "must be a finite number > 0")


def require_nonnegative(cfg: object, section: str, keys: tuple[str, ...]) -> None:
    """ConfigError naming the first of ``keys`` whose value (or any entry of a tuple value)
    in ``cfg`` is not a finite number >= 0."""
    for key in keys:
        value = getattr(cfg, key)
        for v in value if isinstance(value, tuple) else (value,):
            if not 0.0 <= v < math.inf:
                raise ConfigError(section, key, "must be a finite number >= 0")


def require_band(cfg: object, section: str, lo: str, hi: str) -> None:
    """ConfigError unless 0 <= cfg.lo < cfg.hi (a ramp's start and end)."""
    if not getattr(cfg, hi) > getattr(cfg, lo) >= 0.0:
        raise ConfigError(section, hi, f"needs 0 <= {lo} < {hi}")


def merge_tables(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Deep merge: tables merge key by key, any other value in ``override`` replaces."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge_tables(out[key], value)
        else:
            out[key] = value
    return out


# What loading a controller config can raise for a bad file (ConfigError is a ValueError).
CONFIG_LOAD_ERRORS = (FileNotFoundError, KeyError, ValueError, TypeError)


def config_error_line(config: object, exc: BaseException) -> str:
    """One line for a command-line user about a config that could not be loaded."""
    if isinstance(exc, ConfigError):  # already names the file, the section and the key
        return f"--config: {exc}"
    if isinstance(exc, FileNotFoundError):
        return f"--config {config}: {exc.args[-1] if exc.args else exc}"
    msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
    return f"--config {config}: {msg}"

