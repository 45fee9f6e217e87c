"""Scalar attributes that a compiled step can keep in one of its float64 array slots.

``Slot`` is a data descriptor for a plain attribute (a counter, a flag, a float) of a
controller part. Unbound, the value lives in the instance ``__dict__`` as before (same
object, same type). ``bind_slots`` moves it into element ``i`` of a float64 array that a
compiled kernel reads and writes in place (mpc/compiled.py): the attribute then reads
``kind(buf[i])`` and assignments store into ``buf[i]``, so get_state/set_state, reset,
counters and tests keep the same attribute API while the compiled step needs no Python
write-back. ``unbind_slots`` moves the values back (as ``kind(value)``).

Values must be exact in float64: ints below 2**53, bools, floats (a float32 value is
widened exactly; it reads back as a Python float while bound).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

_BUF = "_slot_buf"


class Slot:
    """Descriptor for one scalar attribute; ``kind`` converts a slot value back (int,
    bool, float or e.g. an IntEnum)."""

    __slots__ = ("key", "kind", "name")

    def __init__(self, kind: Callable[[Any], Any] = float) -> None:
        self.kind = kind
        self.name = ""
        self.key = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name
        self.key = "_slot_" + name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        d = obj.__dict__
        i = d.get(self.key)
        if i is None:
            try:
                return d[self.name]
            except KeyError:
                raise AttributeError(self.name) from None
        return self.kind(d[_BUF][i])

    def __set__(self, obj: Any, value: Any) -> None:
        d = obj.__dict__
        i = d.get(self.key)
        if i is None:
            d[self.name] = value
        else:
            d[_BUF][i] = value


def bind_slots(obj: Any, buf: np.ndarray, where: Iterable[tuple[str, int]]) -> None:
    """Keep attributes ``name`` of ``obj`` in ``buf[i]`` (float64) from now on, holding
    their current values. Every name must be a ``Slot`` of type(obj)."""
    d = obj.__dict__
    for name, i in where:
        s = type(obj).__dict__.get(name) or next(
            (c.__dict__[name] for c in type(obj).__mro__ if name in c.__dict__), None)
        if not isinstance(s, Slot):
            raise TypeError(f"{type(obj).__name__}.{name} is not a Slot")
        value = getattr(obj, name)
        if s.key in d and d[_BUF] is not buf:
            raise ValueError(f"{type(obj).__name__}.{name} is bound to another buffer")
        d[_BUF] = buf
        d.pop(name, None)
        buf[i] = value
        d[s.key] = i


def unbind_slots(obj: Any) -> None:
    """Move every bound Slot attribute of ``obj`` back into its ``__dict__``."""
    d = obj.__dict__
    buf = d.get(_BUF)
    if buf is None:
        return
    for c in type(obj).__mro__:
        for name, s in c.__dict__.items():
            if isinstance(s, Slot) and s.key in d:
                d[name] = s.kind(buf[d.pop(s.key)])
    del d[_BUF]
