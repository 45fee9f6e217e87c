"""Are two bus logs the same run? Frames compared by id and data, in order, time stamps aside.

Two kinds of field differ between any two runs, however deterministic, and are set aside:

* a wall-clock measurement, CTRL_STATUS.COMPUTE_TIME (the controller's step time, µs). It
  changes CTRL_STATUS's CRC8, and through the payload the MAC of its SecOC authenticator;
* the SecOC trip: each run is a trip of its own (the plant's persisted trip counter, +1 at
  every run's start, can_db/secoc_keys.py), carried in SYNC_AUTH.TRIP and covered by every
  authenticator's MAC (the MAC is over the full freshness value, trip included).

Frames with such fields (CTRL_STATUS and every authenticator) are compared by their other
decoded values — alive counters and FV_LO (cycle and index) included; every other frame
byte for byte. Whether each log's MACs verify is the replay's check (``rhonn-harness
replay``), which reads the trip from the log.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can

from can_db.codec import Codec, Decoded
from can_db.secoc import SECURED

# per frame name: the decoded signals that depend on the wall clock (directly or via the MAC)
WALL_CLOCK_FIELDS = {"CTRL_STATUS": ("COMPUTE_TIME",), "CTRL_STATUS_AUTH": ("MAC",)}
# per authenticator: the decoded signals that depend on the run's SecOC trip
TRIP_FIELDS = {name: (("TRIP", "MAC") if name == "SYNC_AUTH" else ("MAC",))
               for name in SECURED.values()}
SET_ASIDE = {**TRIP_FIELDS, **WALL_CLOCK_FIELDS}


def comparable(msg: can.Message, codec: Codec) -> Any:
    """A frame as compared: ``(id, data)``, or for a frame with wall-clock or trip fields
    ``(id, counter, the other decoded values)``."""
    spec = codec.by_id.get(msg.arbitration_id)
    skip = SET_ASIDE.get(spec.name) if spec is not None else None
    if skip is None:
        return msg.arbitration_id, bytes(msg.data)
    decoded = codec.decode_message(msg)
    if not isinstance(decoded, Decoded):  # a damaged frame: compared as it is
        return msg.arbitration_id, bytes(msg.data)
    values = tuple(sorted((k, v) for k, v in decoded.values.items() if k not in skip))
    return msg.arbitration_id, decoded.counter, values


def log_frames(path: Path, codec: Codec | None = None) -> list[Any]:
    """The comparable frames of a bus log (BLF, ASC or MF4 via python-can), in order."""
    codec = codec or Codec()
    with can.LogReader(str(path)) as reader:
        return [comparable(m, codec) for m in reader
                if not m.is_error_frame and not m.is_remote_frame]


def first_difference(a: Path, b: Path) -> str | None:
    """None if the two logs hold the same frames; else where and how they first differ."""
    fa, fb = log_frames(a), log_frames(b)
    for i, (x, y) in enumerate(zip(fa, fb, strict=False)):
        if x != y:
            return f"frame {i}: {x!r} != {y!r}"
    if len(fa) != len(fb):
        return f"{len(fa)} frames != {len(fb)} frames"
    return None
