"""Checks of a bus log before it is replayed: is it one whole run?

A replay compares the torque frames a fresh controller produces with the recorded ones; its
answer is only as good as the log. :func:`check_log` names every reason the answer would be
partial, in one line each:

* **truncated file**: a BLF whose header gives a larger file size than the file has (its
  writer did not finish, or the file was cut), an ASC without its closing
  ``End TriggerBlock`` line;
* **several runs in one capture**: the plant's simulated time (SYNC ``SIM_TIME``) goes back
  and it is not a plant restart within one run (:func:`_new_run_at` tells them apart);
* **a capture that starts inside a run**: its first SYNC is not the run's first cycle, so
  the controller's learned state at that point is not in the log;
* **torque frames outside the run**: frames echoing a cycle whose SYNC is not in the log;
* **a log cut short**: a log in a run's directory holds fewer frames than that run's
  recorder wrote (``bus_frames_recorded`` in the ``metrics.json`` beside it), e.g. an ASC
  cut and closed again with ``End TriggerBlock``. A log copied out of its run directory
  has no such record: a cut at a cycle's end then passes, and the replay answers for the
  cycles the log holds.

The replay itself then counts the torque frames it compared against those in the log.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import can

from can_db.codec import Codec, Decoded

ASC_END = "End TriggerBlock"


def check_file_complete(path: Path) -> list[str]:
    """Problems of the file itself (not of its frames): truncation."""
    suffix = path.suffix.lower()
    if suffix == ".blf":
        try:
            with can.BLFReader(str(path)) as reader:
                declared = int(reader.file_size)
        except Exception:  # unreadable header: the frame reader reports it
            return []
        actual = path.stat().st_size
        if declared != actual:
            return [f"the file is truncated or was not closed: its header gives {declared} "
                    f"bytes, the file has {actual}"]
    elif suffix == ".asc":
        with path.open("rb") as fh:
            fh.seek(max(0, path.stat().st_size - 256))
            tail = fh.read().decode(errors="replace").strip().splitlines()
        if not tail or tail[-1].strip() != ASC_END:
            return [f"the file is truncated or was not closed: it does not end with "
                    f"'{ASC_END}'"]
    return []


def check_run_record(path: Path) -> list[str]:
    """A log cut short: fewer frames than its run recorded (``metrics.json`` beside it);
    nothing to say for a log without that record."""
    metrics = path.parent / "metrics.json"
    try:
        recorded = int(json.loads(metrics.read_text())["bus_frames_recorded"])
    except (OSError, ValueError, KeyError, TypeError):
        return []
    try:
        with can.LogReader(str(path)) as reader:
            held = sum(1 for _ in reader)
    except Exception:  # an unreadable log: the frame reader reports it
        return []
    if held < recorded:
        return [f"it holds {held} frames, fewer than the {recorded} its run recorded "
                f"({metrics}): the log was cut short"]
    return []


def _syncs(frames: list[can.Message], codec: Codec) -> list[tuple[int, int, float]]:
    """(frame index, CYCLE, SIM_TIME s) of every well-formed SYNC."""
    sync_id = codec.messages["SYNC"].frame_id
    out = []
    for i, msg in enumerate(frames):
        if msg.arbitration_id != sync_id:
            continue
        got = codec.decode_message(msg)
        if isinstance(got, Decoded):
            out.append((i, int(got.values["CYCLE"]), float(got.values["SIM_TIME"])))
    return out


def _first_after(frames: list[can.Message], index: int, frame_id: int, codec: Codec
                 ) -> Decoded | None:
    """The first well-formed frame of ``frame_id`` after position ``index``."""
    for msg in frames[index + 1:]:
        if msg.arbitration_id == frame_id:
            got = codec.decode_message(msg)
            if isinstance(got, Decoded):
                return got
    return None


def _new_run_at(frames: list[can.Message], reset_at: int, before_at: int,
                codec: Codec) -> bool:
    """At a SYNC whose simulated time went back (``reset_at``; the SYNC before it at
    ``before_at``): True for another run, False for a plant restart within the run. With
    SecOC the plant's trip tells (+1 at every plant start, persisted in the run's directory:
    a restarted plant has a higher trip, another run's starts again). Without it, the
    controller: a process that carries on across a plant restart continues its alive
    counter, a new run's starts at 0 (a continuing one reaches 0 too, one time in 16: then
    the log is refused, on the safe side)."""
    auth_id = codec.messages["SYNC_AUTH"].frame_id
    before = _first_after(frames, before_at, auth_id, codec)
    after = _first_after(frames, reset_at, auth_id, codec)
    if before is not None and after is not None:
        return int(after.values["TRIP"]) <= int(before.values["TRIP"])
    first_answer = _first_after(frames, reset_at, codec.messages["WHEEL_TORQUE_CMD"].frame_id,
                                codec)
    return first_answer is not None and first_answer.counter == 0


def check_frames(frames: list[can.Message], codec: Codec) -> list[str]:
    """Problems of the frame sequence."""
    problems: list[str] = []
    syncs = _syncs(frames, codec)
    if not syncs:
        return ["it holds no well-formed SYNC frame (no plant cycle to replay)"]
    first_index, first_cycle, first_time = syncs[0]
    if first_cycle != 0:
        problems.append(f"the capture starts inside a run: its first SYNC is cycle "
                        f"{first_cycle} ({first_time:.2f} s), not the run's first cycle, so "
                        "the controller's state at that point is not in the log")
    for (before_at, _, t_prev), (index, cycle, t) in itertools.pairwise(syncs):
        if t < t_prev - 1e-9 and _new_run_at(frames, index, before_at, codec):
            problems.append(f"it holds more than one run: at frame {index} the simulated time "
                            f"goes back from {t_prev:.2f} s to {t:.2f} s (cycle {cycle}) and "
                            "another run starts there; replay one run per log (each run's "
                            "directory has its own bus log)")
            break
    # torque frames that answer a cycle the log does not hold
    torque_id = codec.messages["WHEEL_TORQUE_CMD"].frame_id
    echoes = {c % 256 for _, c, _ in syncs}
    outside = 0
    for msg in frames[:first_index]:
        if msg.arbitration_id == torque_id:
            outside += 1
    for msg in frames[first_index:]:
        if msg.arbitration_id != torque_id:
            continue
        got = codec.decode_message(msg)
        if isinstance(got, Decoded) and int(got.values["ECHO_CYCLE"]) not in echoes:
            outside += 1
    if outside:
        problems.append(f"{outside} torque frame(s) answer a cycle whose SYNC is not in the "
                        "log (frames from outside the run)")
    return problems
