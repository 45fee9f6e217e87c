"""`rhonn-bench secoc`: SecOC cost — MAC generate + verify per frame, and the loop impact.

Per frame (in one process, ``--frames`` torque frames):

* ``mac``: one truncated AES-128-CMAC over ID + payload + freshness (can_db/secoc.MacEngine);
* ``generate``: the sender's authenticator frame (freshness, MAC, CRC, alive counter);
* ``verify``: the receiver taking the data frame and its authenticator (decode, freshness
  reconstruction, MAC check, release);
* ``generate+verify``: both (target p50 ≤ 20 µs).

Per plant burst (``--frames`` bursts of DRIVER_INPUTS, MOTION_SENSORS, WHEEL_SPEEDS,
VEHICLE_EST, SYNC): ``burst sign`` = the plant's authenticators for every secured frame of the
burst (``PlantSecOc.protect``), ``burst verify`` = the controller taking the whole protected
burst until the SYNC and the frames it releases (``ControllerSecOc.feed``).

``--loop N`` also runs N interleaved pairs of lockstep dlc-paper runs over the bus, SecOC on
and off, and reports the controller's turnaround (SYNC — or, with SecOC, its authenticator —
received → last answer frame sent) p50/p99 and the loop speed of each variant, with the
on/off ratios of the medians.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from can_db.codec import Codec, Transmitter
from can_db.process.argcheck import OneLineParser, number
from can_db.secoc import ControllerSecOc, MacEngine, PlantSecOc
from can_db.secoc_keys import ci_test_keys
from harness.analysis.run_data import load_timing_csv
from harness.bench.stats import summarize_us, write_json
from harness.report.run_report import run_and_report
from harness.run.spec import RunSpec


def _micro(frames: int) -> dict[str, dict[str, float]]:
    codec = Codec()
    keys = ci_test_keys()
    plant = PlantSecOc(codec, keys, trip=1, max_age_cycles=3)
    ctrl = ControllerSecOc(codec, keys)
    ctrl.receiver.trip = 1
    engine = MacEngine(keys.ctrl_to_plant)
    tx = Transmitter(codec)
    clock = time.perf_counter_ns
    mac, gen, ver, both = [], [], [], []
    for k in range(frames):
        msg = tx.message("WHEEL_TORQUE_CMD", {"TQ_FL": 100.0 * np.sin(0.01 * k),
                                              "ECHO_CYCLE": k % 256})
        payload = bytes(msg.data)
        t0 = clock()
        engine.mac(msg.arbitration_id, payload, k << 8)
        t1 = clock()
        auth = ctrl.sender.authenticator("WHEEL_TORQUE_CMD", msg, 1, k)
        t2 = clock()
        plant.feed(msg, k)
        released = plant.feed(auth, k)
        t3 = clock()
        if released is not msg:
            raise SystemExit(f"frame {k} not verified: {plant.receiver.rejection_counts()}")
        mac.append(t1 - t0)
        gen.append(t2 - t1)
        ver.append(t3 - t2)
        both.append(t3 - t1)
    return {"mac": summarize_us(mac), "generate": summarize_us(gen),
            "verify": summarize_us(ver), "generate+verify": summarize_us(both)}


def _micro_burst(bursts: int) -> dict[str, dict[str, float]]:
    """Sign and verify one plant burst (see the module doc), µs per burst."""
    codec = Codec()
    keys = ci_test_keys()
    plant = PlantSecOc(codec, keys, trip=1)
    ctrl = ControllerSecOc(codec, keys)
    tx = Transmitter(codec)
    clock = time.perf_counter_ns
    sign, verify = [], []
    for k in range(bursts):
        s = float(np.sin(0.01 * k))
        burst = [tx.message("DRIVER_INPUTS", {"SWA": 20.0 * s, "ACCEL_PEDAL": 10.0}),
                 tx.message("MOTION_SENSORS", {"YAW_RATE": 5.0 * s, "AY": 2.0 * s}),
                 tx.message("WHEEL_SPEEDS", {"WS_FL": 50.0 + s, "WS_FR": 50.0 - s}),
                 tx.message("VEHICLE_EST", {"VX_EST": 18.0, "VY_EST": 0.1 * s}),
                 tx.message("SYNC", {"CYCLE": k, "SIM_TIME": 0.01 * k})]
        t0 = clock()
        frames = plant.protect(burst, k)
        t1 = clock()
        released = [got for got in map(ctrl.feed, frames) if got is not None]
        t2 = clock()
        if not released:
            raise SystemExit(f"burst {k} not verified: {ctrl.receiver.rejection_counts()}")
        sign.append(t1 - t0)
        verify.append(t2 - t1)
    return {"burst sign": summarize_us(sign), "burst verify": summarize_us(verify)}


def _loop(pairs: int, controller: str, rt: bool = False) -> dict[str, object]:
    out: dict[str, dict[str, list[float]]] = {
        v: {"turnaround_p50_us": [], "turnaround_p99_us": [], "realtime_factor": []}
        for v in ("on", "off")}
    for _ in range(pairs):
        for variant in ("on", "off"):
            with tempfile.TemporaryDirectory() as tmp:
                res = run_and_report(RunSpec(
                    scenario="dlc-paper", controller=controller, out_dir=Path(tmp),
                    secoc=variant == "on", secoc_keys="ci-test-key", make_plots=False,
                    make_rrd=False, rt=rt))
                summary = res.metrics.get("plant_summary", {})
                if res.reason != "finished" or not summary.get("loop_wall_s"):
                    raise SystemExit(f"run failed: {res.reason}")
                ta = load_timing_csv(Path(tmp) / "controller_timing.csv")["turnaround_us"][1:]
                out[variant]["turnaround_p50_us"].append(float(np.percentile(ta, 50)))
                out[variant]["turnaround_p99_us"].append(float(np.percentile(ta, 99)))
                out[variant]["realtime_factor"].append(summary["sim_time_s"]
                                                       / summary["loop_wall_s"])
    med = {v: {k: float(np.median(x)) for k, x in d.items()} for v, d in out.items()}
    ratios = {k: med["on"][k] / med["off"][k] for k in med["on"]}
    return {"controller": controller, "pairs": pairs, "runs": out, "median": med,
            "ratio_on_off": ratios}


def main(argv: list[str]) -> int:
    parser = OneLineParser(prog="rhonn-bench secoc", description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=number(int, lo=1), default=20_000, metavar="N",
                        help="frames to time")
    parser.add_argument("--loop", type=number(int, lo=0), default=0, metavar="N",
                        help="also run N on/off pairs of lockstep dlc-paper runs")
    parser.add_argument("--controller", default="nmpc-rhonn", help="for --loop")
    parser.add_argument("--rt", action="store_true",
                        help="--loop runs as `rhonn-bench loop --rt` does: SCHED_FIFO, all on "
                             "the last CPU unless $RHONN_RT_CPUS says")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.rt and "RHONN_RT_CPUS" not in os.environ:
        os.environ["RHONN_RT_CPUS"] = str(max(os.sched_getaffinity(0)))
    result: dict[str, object] = {"per_frame": _micro(args.frames), "frames": args.frames,
                                 "per_burst": _micro_burst(args.frames)}
    for name, st in result["per_frame"].items():  # type: ignore[union-attr]
        print(f"secoc {name:<16} p50 {st['p50_us']:6.1f} µs  p99 {st['p99_us']:6.1f} µs")
    for name, st in result["per_burst"].items():  # type: ignore[union-attr]
        print(f"secoc {name:<16} p50 {st['p50_us']:6.1f} µs  p99 {st['p99_us']:6.1f} µs "
              "(per burst)")
    if args.loop > 0:
        loop = _loop(args.loop, args.controller, args.rt)
        result["loop"] = loop
        med, ratio = loop["median"], loop["ratio_on_off"]
        for v in ("on", "off"):
            m = med[v]  # type: ignore[index]
            print(f"loop SecOC {v:<3}: turnaround p50 {m['turnaround_p50_us']:.0f} µs, "
                  f"p99 {m['turnaround_p99_us']:.0f} µs, {m['realtime_factor']:.1f}x real "
                  f"time (medians of {args.loop} runs)")
        print("on/off ratio: " + ", ".join(f"{k} {v:.2f}" for k, v in ratio.items()))
    write_json(args.json, result)
    return 0
