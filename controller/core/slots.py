"""Scalar attributes that a compiled step can keep in one of its float64 array slots.

``Slot`` declares a plain attribute (a counter, a flag, a float) of a controller part.
Unbound, the value lives in the instance ``__dict__`` as before (same object, same type),
and reading or writing it costs what a plain attribute costs: ``Slot`` is a non-data
descriptor, so the instance dict answers first. ``bind_slots`` moves the values into
elements of a float64 array that a compiled kernel reads and writes in place
(mpc/compiled.py) and switches the instance to a subclass of its class whose data
descriptors read ``kind(buf[i])`` and store assignments into ``buf[i]``; get_state /
set_state, reset, counters and tests keep the same attribute API while the compiled step
needs no Python write-back. ``unbind_slots`` moves the values back (as ``kind(value)``)
and restores the class. (Declaring data descriptors on the class itself cost ≈ 90 ns per
unbound access, measured on the passive controller's allocator: 7.1–7.4 → 7.9–8.3 µs.)

While bound, ``type(obj)`` is that subclass (``isinstance`` holds); code that checks
``type(x) is C`` must do it on unbound parts (mpc/compiled.py builds before binding).
Values must be exact in float64: ints below 2**53, bools, floats (a float32 value is
widened exactly; it reads back as a Python float while bound).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

_BUF = "_slot_buf"
_BASE = "_slot_base"     # on a bound subclass: the class it was made from


class Slot:
    """Declares one scalar attribute; ``kind`` converts a slot value back (int, bool,
    float or e.g. an IntEnum)."""

    __slots__ = ("kind", "name")

    def __init__(self, kind: Callable[[Any], Any] = float) -> None:
        self.kind = kind
        self.name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        raise AttributeError(self.name)   # unbound and never set (the dict answers first)


class _BoundSlot:
    """The bound form of a Slot on a bound subclass: element ``i`` of the instance's
    buffer."""

    __slots__ = ("i", "kind")

    def __init__(self, kind: Callable[[Any], Any], i: int) -> None:
        self.kind = kind
        self.i = i

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        return self.kind(obj.__dict__[_BUF][self.i])

    def __set__(self, obj: Any, value: Any) -> None:
        obj.__dict__[_BUF][self.i] = value


_SUBCLASSES: dict[tuple[type, frozenset[tuple[str, int]]], type] = {}


def _slot_of(cls: type, name: str) -> Slot:
    s = next((c.__dict__[name] for c in cls.__mro__ if name in c.__dict__), None)
    if not isinstance(s, Slot):
        raise TypeError(f"{cls.__name__}.{name} is not a Slot")
    return s


def _bound_class(base: type, where: frozenset[tuple[str, int]]) -> type:
    """The subclass of ``base`` with bound descriptors for ``where`` (cached)."""
    key = (base, where)
    sub = _SUBCLASSES.get(key)
    if sub is None:
        attrs: dict[str, Any] = {n: _BoundSlot(_slot_of(base, n).kind, i) for n, i in where}
        attrs[_BASE] = base
        attrs["__module__"] = base.__module__
        attrs["__qualname__"] = base.__qualname__
        attrs["__doc__"] = base.__doc__
        sub = type(base.__name__, (base,), attrs)
        _SUBCLASSES[key] = sub
    return sub


def _bound_where(obj: Any) -> frozenset[tuple[str, int]]:
    """The (name, index) pairs ``obj`` is bound with (empty when unbound)."""
    cls = type(obj)
    if _BASE not in cls.__dict__:
        return frozenset()
    return frozenset((n, d.i) for n, d in cls.__dict__.items() if isinstance(d, _BoundSlot))


def bind_slots(obj: Any, buf: np.ndarray, where: Iterable[tuple[str, int]]) -> None:
    """Keep attributes ``name`` of ``obj`` in ``buf[i]`` (float64) from now on, holding
    their current values. Every name must be a ``Slot`` of type(obj)."""
    d = obj.__dict__
    base = type(obj).__dict__.get(_BASE, type(obj))
    new = frozenset(where)
    for name, _ in new:
        _slot_of(base, name)
    old = _bound_where(obj)
    if old and d[_BUF] is not buf:
        raise ValueError(f"{base.__name__} is bound to another buffer")
    if len({n for n, _ in old | new}) != len(old | new):
        raise ValueError(f"{base.__name__}: a name bound to two elements")
    values = [(name, i, getattr(obj, name)) for name, i in new]
    for name, i, value in values:
        buf[i] = value
        d.pop(name, None)
    d[_BUF] = buf
    obj.__class__ = _bound_class(base, old | new)


def unbind_slots(obj: Any) -> None:
    """Move every bound Slot attribute of ``obj`` back into its ``__dict__``."""
    cls = type(obj)
    base = cls.__dict__.get(_BASE)
    if base is None:
        return
    d = obj.__dict__
    buf = d[_BUF]
    for name, i in _bound_where(obj):
        d[name] = _slot_of(base, name).kind(buf[i])
    del d[_BUF]
    obj.__class__ = base
