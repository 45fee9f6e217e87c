"""core/slots.py: a Slot attribute reads and writes its array element while bound and its
instance dict otherwise, with the same values and kinds (the compiled step's bound state,
mpc/compiled.py, is tested against the generic step in test_compiled_step.py)."""

from __future__ import annotations

import enum

import numpy as np
import pytest

from controller.core.slots import Slot, bind_slots, unbind_slots


class _Status(enum.IntEnum):
    A = 0
    B = 4


class _Part:
    count = Slot(int)
    level = Slot(float)
    flag = Slot(bool)
    status = Slot(_Status)

    def __init__(self) -> None:
        self.count = 3
        self.level = np.float32(0.1)
        self.flag = True
        self.status = _Status.B
        self.other = "plain"


def test_unbound_keeps_the_object_itself() -> None:
    p = _Part()
    assert type(p.level) is np.float32 and p.level == np.float32(0.1)
    assert p.count == 3 and p.flag is True and p.status is _Status.B
    with pytest.raises(AttributeError):
        _ = _Part.__new__(_Part).count
    assert not hasattr(_Part.__new__(_Part), "level")


def test_bound_reads_and_writes_the_array() -> None:
    p = _Part()
    buf = np.zeros(10)
    bind_slots(p, buf, [("count", 2), ("level", 5), ("flag", 7), ("status", 9)])
    assert buf[2] == 3.0 and buf[5] == float(np.float32(0.1)) and buf[7] == 1.0
    assert buf[9] == 4.0
    assert p.count == 3 and type(p.count) is int
    assert p.level == float(np.float32(0.1)) and type(p.level) is float
    assert p.flag is True and p.status is _Status.B
    buf[2] += 1.0          # what a kernel does
    buf[7] = 0.0
    buf[9] = 0.0
    assert p.count == 4 and p.flag is False and p.status is _Status.A
    p.count += 10
    p.level = float("nan")
    assert buf[2] == 14.0 and np.isnan(buf[5])
    assert "count" not in p.__dict__ and p.other == "plain"
    unbind_slots(p)
    assert p.count == 14 and type(p.count) is int and np.isnan(p.level)
    assert p.flag is False and p.status is _Status.A
    p.count = 1
    assert buf[2] == 14.0   # unbound again: the array is no longer written


def test_bind_rejects_a_plain_attribute() -> None:
    p = _Part()
    with pytest.raises(TypeError):
        bind_slots(p, np.zeros(2), [("other", 0)])


def test_unbound_access_is_a_plain_attribute_and_binding_switches_the_class() -> None:
    p = _Part()
    assert type(p) is _Part and "count" in p.__dict__   # the instance dict answers
    buf = np.zeros(10)
    bind_slots(p, buf, [("count", 2)])
    assert isinstance(p, _Part) and type(p) is not _Part and type(p).__name__ == "_Part"
    bind_slots(p, buf, [("level", 5)])                   # more names, same buffer
    assert p.count == 3 and buf[5] == float(np.float32(0.1))
    with pytest.raises(ValueError, match="another buffer"):
        bind_slots(p, np.zeros(10), [("flag", 7)])
    with pytest.raises(ValueError, match="two elements"):
        bind_slots(p, buf, [("count", 3)])
    q = _Part()
    bind_slots(q, np.zeros(10), [("count", 2)])
    q.count = 8
    assert p.count == 3                                  # each instance its own buffer
    unbind_slots(p)
    assert type(p) is _Part and p.count == 3 and p.level == float(np.float32(0.1))
    unbind_slots(p)                                      # unbinding twice is harmless
    assert type(p) is _Part
