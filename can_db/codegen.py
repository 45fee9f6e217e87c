"""Straight-line pack/unpack functions, one per message, generated once from the DBC specs.

The codec's generic loop spends most of its time unpacking the per-signal table and loading
its entries; a function per message with every constant written in (exact ``repr`` of each
float, so the arithmetic is the same IEEE operations in the same order as the table-driven
code) does the same work in about half the time. The functions are built with ``exec`` from
code this module writes out of the parsed DBC (names are checked identifiers, numbers are
``repr`` of ints and floats): no text from elsewhere is executed.

Encoder ``enc(values, word) -> (word, saturated)``: ``values`` maps signal names to physical
values (missing = 0.0), ``word`` holds the bits set so far (the alive counter); returns the
packed 64-bit word and the names of the saturated or non-finite signals.

Decoder ``dec(word) -> dict | int``: the physical values, or the index (in the message's
signal order) of the first signal outside its range.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

PackRow = tuple[str, float, float, float, float, int, int, int, int, float]
UnpackRow = tuple[str, int, int, int, int, float, float, float, float]


def _num(value: float) -> str:
    """Exact source text of a finite float."""
    if not math.isfinite(value):
        raise ValueError(f"non-finite constant {value!r} in the DBC tables")
    return repr(float(value))


def _check_name(name: str) -> str:
    if not name.isidentifier():
        raise ValueError(f"signal name {name!r} is not an identifier")
    return name


def make_encoder(table: Sequence[PackRow]) -> Callable[[Any, int], tuple[int, tuple[str, ...]]]:
    """The encoder of one message (see the module doc) from its pack table rows
    ``(name, min, max, offset, scale, raw_min, raw_max, mask, start, nan_phys)``."""
    lines = ["def enc(values, word):", "    get = values.get", "    saturated = ()"]
    for name, lo, hi, offset, scale, raw_min, raw_max, mask, start, nan_phys in table:
        n = repr(_check_name(name))
        lines += [
            f"    phys = get({n}, 0.0)",
            "    if phys != phys:",
            f"        saturated += ({n},)",
            f"        phys = {_num(nan_phys)}",
            f"    elif phys > {_num(hi)}:",
            f"        saturated += ({n},)",
            f"        phys = {_num(hi)}",
            f"    elif phys < {_num(lo)}:",
            f"        saturated += ({n},)",
            f"        phys = {_num(lo)}",
            f"    raw = round((phys - {_num(offset)}) / {_num(scale)})",
            f"    raw = {int(raw_max)} if raw > {int(raw_max)} else {int(raw_min)} "
            f"if raw < {int(raw_min)} else raw",
            f"    word |= (raw & {int(mask)}) << {int(start)}",
        ]
    lines.append("    return word, saturated")
    return _define("\n".join(lines), "enc")


def make_decoder(table: Sequence[UnpackRow]) -> Callable[[int], dict[str, float] | int]:
    """The decoder of one message (see the module doc) from its unpack table rows
    ``(name, start, mask, sign_bit, wrap, scale, offset, lo, hi)``."""
    lines = ["def dec(word):", "    values = {}"]
    for index, (name, start, mask, sign_bit, wrap, scale, offset, lo, hi) in enumerate(table):
        lines.append(f"    raw = (word >> {int(start)}) & {int(mask)}")
        if sign_bit:
            lines += [f"    if raw & {int(sign_bit)}:", f"        raw -= {int(wrap)}"]
        lines += [
            f"    phys = raw * {_num(scale)} + {_num(offset)}",
            f"    if not {_num(lo)} <= phys <= {_num(hi)}:",
            f"        return {index}",
            f"    values[{_check_name(name)!r}] = phys",
        ]
    lines.append("    return values")
    return _define("\n".join(lines), "dec")


@functools.lru_cache(maxsize=1024)
def _define(source: str, name: str) -> Callable[..., Any]:
    """The function ``name`` that ``source`` (generated from the DBC tables) defines, built
    once per process and source text: every codec of a process (node, injector, SecOC,
    recorder, tester, each reset) asks for the same functions, which are pure, and ``exec``
    is most of a codec's construction. Keyed by the text, not the table: ``0.0`` and
    ``-0.0`` are equal keys but different code."""
    scope: dict[str, Any] = {}
    exec(source, {"round": round}, scope)
    return scope[name]
