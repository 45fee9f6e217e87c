"""Back-to-back tests of the node logic in C (controller/native/node/node_logic.c) against
the Python node (controller/runtime/node.py ControllerNode), frame for frame.

Both nodes run the same C core (the installed ``_rhcore64`` / ``_rhcore32`` extension: the
Python node through its NativeController, the C node through ``rh_ctrl_step`` of the same
library on its own ``rh_ctrl_t`` initialised from the same configuration). Every frame the
plant sends goes to the Python node as a CAN frame and to the C node as the event the frame
layer makes of it (the Python codec's decode: decoded values, or the rejection reason).
After every frame the two answer alike (answered or not), and after every answer these are
equal: the physical values of the three frames the Python node encodes, the mode, fault
bits, QP status, the torques, the controller outputs held, the core inputs, the monitor
(counts by reason, per-stream state), the frozen-signal monitor, the envelope's counters,
the fault state, the rx drops and overload cycles, and the cores' step counts and held ΔM.

Bounds: none. The node computes in double in both builds and converts to real_t only at
the core's boundary, as the Python binding does, so the float32 core gets bit-identical
inputs and returns bit-identical outputs; every comparison is exact (NaN equal to NaN), in
the double and the ``-DRH_FLOAT32`` build.

Sequences: named scenarios (good cycles, timeouts of each stream, every rejection reason,
NaN/inf/out-of-range values, frozen sensors, sensor-invalid cycles, STAB_ENABLE off,
driver lost → ramp-down and back, an injected core fault → FAULT latched with ramp-down
while the driver frame is lost, a plant restart, burst overflow → RX_OVERLOAD, a rejected
SYNC) and seeded random fault mixes, lockstep and free-running.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from types import ModuleType
from typing import Any

import can
import numpy as np
import pytest

from can_db.codec import Codec, Decoded, Rejected
from can_db.faults import FaultSpec, parse_fault
from can_db.secoc import PENDING, ControllerSecOc, PlantSecOc
from can_db.secoc_keys import load_keys
from controller.core.params import load_vehicle_params
from controller.core.registry import ControllerConfig, load_controller_config
from controller.native.backend import core_module
from controller.native.config import ctrl_config
from controller.native.controller import NativeController
from controller.runtime.core_fault import FaultyCore
from controller.runtime.node import BURST_FULL, ControllerNode, Fault, Mode
from tests import native_node_logic as lay
from tests.recorded import config_file

pytestmark = pytest.mark.skipif(
    core_module(False) is None or core_module(True) is None,
    reason="the C core is not built (no C compiler at install)",
)

PARAMS = load_vehicle_params()
SYNC_ID = 0x10F
RX_DECODED, RX_REJECTED, RX_IGNORED = 0, 1, 2


@pytest.fixture(scope="module")
def libs(tmp_path_factory) -> dict[bool, lay.NodeLib]:
    """The node library per build (False: double, True: RH_FLOAT32)."""
    out = {}
    for f32 in (False, True):
        out[f32] = lay.build(tmp_path_factory.getbasetemp() / "native_node", core_module(f32), f32)
    return out


@pytest.fixture(scope="module")
def configs(tmp_path_factory) -> dict[bool, ControllerConfig]:
    """The packaged configuration (double) and its float32 variant (UD EKF, as deployed)."""
    tmp = tmp_path_factory.mktemp("node_cfg")
    return {
        False: load_controller_config(None),
        True: load_controller_config(config_file(tmp, 'precision = "float32"', 'form = "ud"')),
    }


class InjectingCodec(Codec):
    """The DBC codec, with decoded values injected for chosen frames (NaN, inf, huge: values
    no DBC frame can carry, which the C node's API accepts and must survive)."""

    def __init__(self) -> None:
        super().__init__()
        self.injected: dict[int, tuple[can.Message, Decoded]] = {}

    def inject(self, msg: can.Message, values: dict[str, float]) -> None:
        """Decode ``msg`` with ``values`` replaced (a frame the decoder rejects stays so)."""
        d = super().decode_message(msg)
        if isinstance(d, Decoded):
            self.injected[id(msg)] = (msg, Decoded(d.name, {**d.values, **values}, d.counter))

    def decode_message(self, msg: can.Message) -> Decoded | Rejected:
        hit = self.injected.get(id(msg))
        return hit[1] if hit is not None and hit[0] is msg else super().decode_message(msg)


@dataclass
class Faults:
    """What the plant does to one cycle's frames (message names)."""

    drop: set[str] = field(default_factory=set)
    counter: dict[str, int] = field(default_factory=dict)  # alive-counter step (1 = good)
    crc: set[str] = field(default_factory=set)
    short: set[str] = field(default_factory=set)  # wrong length
    remote: set[str] = field(default_factory=set)  # not a data frame
    extended: set[str] = field(default_factory=set)  # 29-bit ID: not a data frame
    out_of_range: set[str] = field(default_factory=set)
    inject: dict[str, dict[str, float]] = field(default_factory=dict)
    extra: dict[str, int] = field(default_factory=dict)  # further frames of a message
    junk: int = 0  # unknown IDs
    foreign: int = 0  # well-formed frames not monitored
    stuck_yaw: bool = False
    stab: int = 1
    accel: float = 0.3
    brake: float = 0.0
    sync_back_s: float = 0.0  # SYNC time jumps back by this


# Raw patches that decode out of range (bit start, length, raw value): above the maximum.
OUT_OF_RANGE = {
    "DRIVER_INPUTS": (36, 10, 1023),
    "MOTION_SENSORS": (36, 14, 8191),
    "VEHICLE_EST": (20, 16, 32767),
    "WHEEL_SPEEDS": None,
    "SYNC": None,
}


class Plant:
    """Encodes plant bursts (DRIVER_INPUTS, MOTION_SENSORS, WHEEL_SPEEDS, VEHICLE_EST, SYNC)
    with seeded sensor noise, and applies a cycle's Faults."""

    def __init__(self, codec: InjectingCodec, seed: int) -> None:
        self.codec = codec
        self.rng = np.random.default_rng(seed)
        self.cycle = 0
        self.time_s = 0.0
        self.counters: dict[str, int] = {}
        self.yaw_held = 0.5

    def _values(self, f: Faults) -> dict[str, dict[str, float]]:
        n, k = self.rng.normal, self.cycle
        vx = 18.0 + 2.0 * math.sin(0.01 * k)
        yaw = self.yaw_held if f.stuck_yaw else 3.0 * math.sin(0.05 * k) + n(0, 0.1)
        return {
            "DRIVER_INPUTS": {
                "SWA": 40.0 * math.sin(0.03 * k),
                "ACCEL_PEDAL": 100 * f.accel,
                "BRAKE_PEDAL": 100 * f.brake,
                "STAB_ENABLE": f.stab,
            },
            "MOTION_SENSORS": {"YAW_RATE": yaw, "AX": n(0, 0.3), "AY": n(0, 0.5)},
            "WHEEL_SPEEDS": {f"WS_{w}": vx / 0.358 + n(0, 0.3) for w in ("FL", "FR", "RL", "RR")},
            "VEHICLE_EST": {"VX_EST": vx + n(0, 0.05), "VY_EST": n(0, 0.05)},
            "SYNC": {"CYCLE": k, "SIM_TIME": self.time_s},
        }

    def _frame(self, name: str, values: dict[str, float], f: Faults) -> can.Message:
        c = self.counters.get(name, -1)
        c = (c + f.counter.get(name, 1)) % 16
        self.counters[name] = c
        msg = self.codec.message(name, values, c)
        data = bytearray(msg.data)
        patch = OUT_OF_RANGE.get(name) if name in f.out_of_range else None
        if patch is not None:
            start, length, raw = patch
            word = int.from_bytes(data, "little")
            word = (word & ~(((1 << length) - 1) << start)) | (raw << start)
            data = bytearray(word.to_bytes(8, "little"))
            self.codec.seal(msg.arbitration_id, data)
        if name in f.crc:
            data[0] ^= 0x10
        if name in f.short:
            data = data[:7]
        msg = can.Message(
            arbitration_id=msg.arbitration_id,
            data=bytes(data),
            is_extended_id=name in f.extended,
            is_remote_frame=name in f.remote and name not in f.extended,
            dlc=len(data),
        )
        if name in f.inject:
            self.codec.inject(msg, f.inject[name])
        return msg

    def burst(self, f: Faults) -> list[can.Message]:
        """One cycle's frames, SYNC last; advances the plant by 10 ms."""
        if f.sync_back_s:
            self.time_s = max(0.0, self.time_s - f.sync_back_s)
        vals = self._values(f)
        frames = []
        for name, v in vals.items():
            if name == "SYNC":
                continue
            for _ in range(1 + f.extra.get(name, 0)):
                msg = self._frame(name, v, f)
                if name not in f.drop:
                    frames.append(msg)
        for _ in range(f.junk):
            frames.append(
                can.Message(
                    arbitration_id=int(self.rng.choice([0x7FF, 0x555, 0x12])),
                    data=bytes(self.rng.integers(0, 256, 8)),
                    is_extended_id=False,
                )
            )
        for _ in range(f.foreign):
            frames.append(self.codec.message("CTRL_STATUS", {"MODE": 1}, self.cycle % 16))
        self.rng.shuffle(frames)  # arrival order within a burst varies
        sync = self._frame("SYNC", vals["SYNC"], f)
        if "SYNC" not in f.drop:
            frames.append(sync)
        self.cycle += 1
        self.time_s = round(self.time_s + 0.01, 2)
        return frames


class Pair:
    """The Python node and the C node on the same core library, fed the same frames."""

    def __init__(
        self,
        lib: lay.NodeLib,
        name: str,
        cfg: ControllerConfig,
        module: ModuleType,
        faults: Iterable[FaultSpec] = (),
        rampdown: float = 1500.0,
        secoc: bool = False,
    ) -> None:
        self.lib, self.module = lib, module
        self.codec = InjectingCodec()
        self.core = NativeController(name, cfg, module)
        faults = list(faults)
        ctl = FaultyCore(self.core, faults) if faults else self.core
        self.faulty = ctl if faults else None
        keys = load_keys("ci-test-key") if secoc else None
        self.node = ControllerNode(
            ctl,
            PARAMS,
            codec=self.codec,
            rampdown_nm_per_s=rampdown,
            secoc=ControllerSecOc(self.codec, keys) if keys else None,
        )
        # the C node's frame layer: its own SecOC receiver, fed the same frames
        self.c_secoc = ControllerSecOc(Codec(), keys) if keys else None
        if faults:
            ctl.bind(lambda: self.node.record.sim_time_s)
        self.sent: list[tuple[str, dict[str, float]]] = []
        encode = self.node.tx.message

        def record(msg_name: str, values: dict[str, float]) -> can.Message:
            self.sent.append((msg_name, dict(values)))
            return encode(msg_name, values)

        self.node.tx.message = record  # the values the Python node hands to the encoder
        ffi = module.ffi
        self.ctrl = ffi.new("rh_ctrl_t *")
        assert module.lib.rh_ctrl_init(self.ctrl, ctrl_config(name, cfg, module)) == 0
        self.ctrl_ptr = lib.core(module, self.ctrl)
        c = lib.new("logic_config")
        lib.rh_node_logic_default_config(c)
        c.comm_period_s = self.node.comm_period_s
        c.mpc_every = self.node.mpc_every
        c.controller_id = self.node.controller_id
        c.peak_torque_nm, c.peak_power_w = PARAMS.peak_torque_nm, PARAMS.peak_power_w
        for k, v in asdict(self.node.envelope.cfg).items():
            setattr(c.envelope, k, v)
        c.fault.rampdown_nm_per_s = rampdown
        c.fault.n_windows = len(faults)
        for k, spec in enumerate(faults):
            c.fault.window_start_s[k], c.fault.window_duration_s[k] = spec.at_s, spec.amount
        self.st = lib.new("logic")
        assert lib.rh_node_logic_init(self.st, c) == 0
        self.answers: list[Any] = []

    # ------------------------------------------------------------------ feeding
    def event(self, msg: can.Message) -> Any:
        """The frame layer's event for ``msg`` (the codec's verdict)."""
        d = self.codec.decode_message(msg)
        ev = self.lib.new("rx")
        if isinstance(d, Rejected):
            ev.kind, ev.reason = RX_REJECTED, lay.REASON_LIST.index(d.reason)
            spec = self.codec.by_id.get(d.frame_id)
            ev.stream = (
                lay.STREAM_NAMES.index(spec.name)
                if spec is not None and spec.name in lay.STREAM_NAMES
                else -1
            )
        elif d.name in lay.STREAM_NAMES:
            ev.kind, ev.stream = RX_DECODED, lay.STREAM_NAMES.index(d.name)
            ev.frame.counter = d.counter
            for k, g in enumerate(self.codec.messages[d.name].signals):
                ev.frame.values[k] = d.values[g.name]
        else:
            ev.kind, ev.stream = RX_IGNORED, -1
        return ev

    def lockstep(self, frames: list[can.Message]) -> int:
        """Feed one burst to both nodes; the number of answers (equal on both sides)."""
        answered = 0
        for msg in frames:
            out_py = self.node.on_frame_lockstep(msg)
            ev = self.event(msg)
            if msg.arbitration_id == SYNC_ID:
                tx = self.lib.new("tx")
                r = self.lib.rh_node_logic_sync(
                    self.st,
                    self.ctrl_ptr,
                    ev,
                    self.lib.NULL,
                    0,
                    tx,
                )
                assert r == (1 if out_py is not None else 0)
                if out_py is not None:
                    answered += 1
                    self.check_answer(tx)
                self.check_state()
            else:
                assert out_py is None
                assert self.lib.rh_node_logic_rx(self.st, ev) == 0
                for k, slot in enumerate(self.node._burst.values()):
                    assert self.st.burst_n[k] == len(slot)
        return answered

    def lockstep_secoc(self, frames: list[can.Message]) -> int:
        """Feed one SecOC-protected burst: the Python node verifies inside; the C node gets
        what its frame layer (a second ControllerSecOc) releases: a SYNC with its burst's
        verified frames (``released``) and the eviction total. The number of answers."""
        assert self.c_secoc is not None
        answered, st = 0, self.st
        for msg in frames:
            out_py = self.node.on_frame_lockstep(msg)
            verified = self.c_secoc.feed(msg)
            if verified is None:
                assert out_py is None
                continue
            if verified.arbitration_id != SYNC_ID:
                assert out_py is None
                assert self.lib.rh_node_logic_rx(st, self.event(verified)) == 0
                continue
            released = [self.event(m) for m in self.c_secoc.released_data]
            arr = self.lib.rx_array(released)
            self.lib.rh_node_logic_set_secoc_evicted(st, self.c_secoc.receiver.evicted)
            tx = self.lib.new("tx")
            ev = self.event(verified)
            r = self.lib.rh_node_logic_sync(st, self.ctrl_ptr, ev, arr, len(released), tx)
            assert r == (1 if out_py is not None else 0)
            if out_py is not None:
                answered += 1
                self.check_answer(tx)
            self.check_state()
        return answered

    def accept(self, msg: can.Message, now: float) -> None:
        """Free-running: a frame on arrival at ``now`` s."""
        self.node.on_frame(msg, now)
        ev = self.event(msg)
        assert self.lib.rh_node_logic_accept(self.st, ev, now) == 0

    def tick(self, now: float) -> None:
        """Free-running: one answer at ``now`` s on both nodes."""
        self.node.tick(now)
        tx = self.lib.new("tx")
        self.lib.rh_node_logic_tick(self.st, self.ctrl_ptr, now, tx)
        self.check_answer(tx)
        self.check_state()

    # ------------------------------------------------------------------ checks
    def check_answer(self, tx: Any) -> None:
        """The three frames' physical values equal those the Python node encoded."""
        self.answers.append(tx)
        sent = dict(self.sent[-3:])
        assert list(sent) == ["WHEEL_TORQUE_CMD", "CTRL_STATUS", "CTRL_REFS"]
        w, s, r = sent["WHEEL_TORQUE_CMD"], sent["CTRL_STATUS"], sent["CTRL_REFS"]
        assert [w["TQ_FL"], w["TQ_FR"], w["TQ_RL"], w["TQ_RR"]] == list(tx.tq_nm)
        assert w["ECHO_CYCLE"] == s["ECHO_CYCLE"] == r["ECHO_CYCLE"] == tx.echo_cycle
        assert (
            s["MODE"],
            s["FAULT_BITS"],
            s["QP_STATUS"],
            s["QP_ITER"],
            s["COMPUTE_TIME"],
            s["CONTROLLER_ID"],
        ) == (
            tx.mode,
            tx.fault_bits,
            tx.qp_status,
            tx.qp_iter,
            tx.compute_time_us,
            tx.controller_id,
        )
        assert all(
            map(
                lay.same,
                (r["DELTA_M"], r["YAW_RATE_REF"], r["BETA_REF"]),
                (tx.delta_m_nm, tx.yaw_rate_ref_deg_s, tx.beta_ref_deg),
            )
        )
        rec = self.node.record
        assert (rec.cycle, rec.mpc_update) == (tx.cycle, bool(tx.mpc_update))
        assert lay.same(rec.sim_time_s, tx.sim_time_s)

    def check_state(self) -> None:
        """Every piece of node state equal (module docstring)."""
        node, st = self.node, self.st
        lay.assert_same_monitor(node.monitor, st.monitor)
        lay.assert_same_plaus(node.frozen, st.plaus)
        lay.assert_same_envelope(node.envelope, st.envelope)
        assert list(st.torques) == list(node.torques)  # enveloped: never NaN
        assert list(st.env_prev) == list(node._env_prev)
        assert st.mode == int(node.mode) and st.mode_changes == node.mode_changes
        assert st.cycles_since_mpc == node._cycles_since_mpc
        assert st.plant_restarts == node.plant_restarts
        assert bool(st.fault.latched) == node.core_fault_latched
        assert st.fault.exceptions == node.controller_exceptions
        assert st.burst_drops == node.rx_drops[BURST_FULL]
        assert st.rx_overload_cycles == node.rx_overload_cycles
        assert st.drops_answered == node._drops_answered
        assert lay.same(st.last_stamp_s, node._last_stamp)
        assert bool(st.has_sync) == (node.last_sync is not None)
        if node.last_sync is not None:
            assert st.last_sync.counter == node.last_sync.counter
            assert st.last_sync.values[0] == node.last_sync.values["CYCLE"]
            assert lay.same(st.last_sync.values[1], node.last_sync.values["SIM_TIME"])
        inp, ci = node.inputs, st.inputs
        for k in ("swa_rad", "accel_pedal", "brake_pedal", "yaw_rate", "ax", "ay", "vx", "vy"):
            assert lay.same(getattr(ci, k), getattr(inp, k)), k
        assert all(map(lay.same, ci.wheel_speeds, inp.wheel_speeds))
        assert (bool(ci.stab_enable), bool(ci.sensors_valid)) == (
            inp.stab_enable,
            inp.sensors_valid,
        )
        o, co = node.record.outputs, st.out
        assert all(map(lay.same, co.torques, o.torques))
        for k in ("total_torque", "delta_m", "yaw_rate_ref", "vy_ref", "beta_ref"):
            assert lay.same(getattr(co, k), getattr(o, k)), k
        assert (co.qp_status, co.qp_iterations, bool(co.fallback)) == (
            int(o.qp_status),
            o.qp_iterations,
            bool(o.fallback),
        )
        # the cores were stepped alike (full steps, held ΔM)
        assert self.ctrl.steps == self.core._c.steps
        assert self.ctrl.dm_held == self.core._c.dm_held
        if self.faulty is not None:
            assert st.fault.injected == self.faulty.raised

    def modes(self) -> list[int]:
        return [t.mode for t in self.answers]

    def bits(self) -> int:
        """OR of every answer's fault bits."""
        out = 0
        for t in self.answers:
            out |= t.fault_bits
        return out


def pair(libs, configs, name: str, f32: bool, **kw) -> Pair:
    return Pair(libs[f32], name, configs[f32], core_module(f32), **kw)


def run(p: Pair, plant: Plant, cycles: int, faults: Faults | None = None) -> int:
    return sum(p.lockstep(plant.burst(faults or Faults())) for _ in range(cycles))


PRECISIONS = pytest.mark.parametrize("f32", [False, True], ids=["f64", "f32"])


# ------------------------------------------------------------------------ named cases
@PRECISIONS
@pytest.mark.parametrize("name", ["nmpc-rhonn", "lmpc", "nmpc-mf", "passive"])
def test_good_cycles_are_answered_alike(libs, configs, name: str, f32: bool) -> None:
    p = pair(libs, configs, name, f32)
    plant = Plant(p.codec, 1)
    assert run(p, plant, 120) == 120
    assert p.modes()[-1] == Mode.ACTIVE
    assert any(t.mpc_update for t in p.answers) and not all(t.mpc_update for t in p.answers)
    if name != "passive":
        assert any(abs(t.delta_m_nm) > 1.0 for t in p.answers)  # the controller acted


@PRECISIONS
def test_timeouts_of_each_stream_and_recovery(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 2)
    run(p, plant, 30)
    for name in ("MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST", "DRIVER_INPUTS"):
        run(p, plant, 6, Faults(drop={name}))
        run(p, plant, 15)
    run(p, plant, 5, Faults(drop={"SYNC"}))  # no SYNC: no answers
    run(p, plant, 10)
    m = p.modes()
    assert Mode.DEGRADED_SENSORS in m and Mode.DRIVER_LOST_RAMPDOWN in m
    assert m[-1] == Mode.ACTIVE
    assert p.node.monitor.counts["timeout"] == 4  # one per lost data stream (no SYNC: no answer)


@PRECISIONS
@pytest.mark.parametrize(
    "kind",
    [
        "crc",
        "short",
        "remote",
        "extended",
        "out_of_range",
        "counter_frozen",
        "counter_jump",
        "wrong_sequence",
        "junk",
        "foreign",
    ],
)
def test_rejected_frames_of_each_reason(libs, configs, kind: str, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 3)
    run(p, plant, 20)
    rng = np.random.default_rng(4)
    names = ["DRIVER_INPUTS", "MOTION_SENSORS", "VEHICLE_EST", "WHEEL_SPEEDS"]
    for k in range(60):
        name = names[k % 4] if kind != "out_of_range" else names[k % 3]
        f = Faults()
        if kind in ("crc", "short", "remote", "extended", "out_of_range"):
            getattr(f, kind).add(name)
        elif kind == "counter_frozen":
            f.counter[name] = 0
        elif kind == "counter_jump":
            f.counter[name] = int(rng.choice([2, 3]))
        elif kind == "wrong_sequence":
            f.counter[name] = int(rng.choice([5, 9, 15]))
        elif kind == "junk":
            f.junk = 3
        else:
            f.foreign = 2
        p.lockstep(plant.burst(f))
        run(p, plant, int(rng.integers(0, 3)))
    counts = p.node.monitor.counts
    expected = {
        "crc": "bad_crc",
        "short": "wrong_length",
        "remote": "not_data_frame",
        "extended": "not_data_frame",
        "out_of_range": "out_of_range",
        "counter_frozen": "counter_frozen",
        "counter_jump": "counter_jump",
        "wrong_sequence": "wrong_sequence",
        "junk": "unknown_id",
    }
    if kind == "foreign":
        assert p.node.monitor.ignored > 0
    else:
        assert counts[expected[kind]] > 0


@PRECISIONS
def test_counter_fault_level_entry_and_recovery(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "lmpc", f32)
    plant = Plant(p.codec, 5)
    run(p, plant, 20)
    run(p, plant, 6, Faults(counter={"WHEEL_SPEEDS": 0}))  # frozen counter x6: level 5
    run(p, plant, 12)
    assert p.node.monitor.counts["counter_fault"] > 0
    m = p.modes()
    # stale (frozen) frames are rejected, the level reaches the limit: invalid while it
    # stays there; each good frame lowers it by one, so the next good frame is accepted
    assert Mode.DEGRADED_SENSORS in m[-18:-12] and m[-1] == Mode.ACTIVE


@PRECISIONS
def test_nonfinite_and_huge_values_stay_safe_and_equal(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 6)
    run(p, plant, 20)
    cases = [
        ("WHEEL_SPEEDS", {"WS_FL": math.nan}),
        ("WHEEL_SPEEDS", {"WS_RR": math.inf}),
        ("VEHICLE_EST", {"VX_EST": math.nan}),
        ("VEHICLE_EST", {"VY_EST": 1e300}),
        ("MOTION_SENSORS", {"YAW_RATE": -math.inf}),
        ("DRIVER_INPUTS", {"SWA": math.nan}),
        ("DRIVER_INPUTS", {"ACCEL_PEDAL": 1e308}),
        ("DRIVER_INPUTS", {"STAB_ENABLE": math.nan}),
        ("DRIVER_INPUTS", {"BRAKE_PEDAL": -math.inf}),
        ("SYNC", {"SIM_TIME": math.nan}),
    ]
    for name, values in cases:
        for _ in range(3):
            p.lockstep(plant.burst(Faults(inject={name: values})))
        run(p, plant, 8)
    for t in p.answers:
        assert all(math.isfinite(v) and abs(v) <= PARAMS.peak_torque_nm for v in t.tq_nm)
    assert p.node.envelope.counters.nonfinite_cmd + p.node.envelope.counters.invalid_speed > 0


@PRECISIONS
def test_frozen_sensor_degrades_and_recovers(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 7)
    run(p, plant, 20)
    run(p, plant, 15, Faults(stuck_yaw=True))
    run(p, plant, 5)
    assert p.node.frozen.detections == 1
    m = p.modes()
    assert m[-6] == Mode.DEGRADED_SENSORS and m[-1] == Mode.ACTIVE
    assert p.bits() & (1 << Fault.SENSORS_INVALID)


@PRECISIONS
def test_stability_disabled_is_standby_with_zero_yaw_moment(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 8)
    run(p, plant, 30)
    run(p, plant, 20, Faults(stab=0))
    assert p.modes()[-1] == Mode.STANDBY
    assert all(t.delta_m_nm == 0.0 for t in p.answers[-15:])
    run(p, plant, 10)
    assert p.modes()[-1] == Mode.ACTIVE


@PRECISIONS
def test_driver_lost_ramps_down_and_returns(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "passive", f32, rampdown=1500.0)
    plant = Plant(p.codec, 9)
    run(p, plant, 10, Faults(accel=0.8))
    run(p, plant, 40, Faults(accel=0.8, drop={"DRIVER_INPUTS"}))
    ramp = [max(abs(v) for v in t.tq_nm) for t in p.answers[10:]]
    assert ramp[-1] == 0.0 and ramp[5] > 0.0
    assert Mode.DRIVER_LOST_RAMPDOWN in p.modes()
    run(p, plant, 5, Faults(accel=0.8))
    assert p.modes()[-1] == Mode.ACTIVE


@PRECISIONS
def test_driver_absent_from_the_start_stays_init(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 10)
    run(p, plant, 10, Faults(drop={"DRIVER_INPUTS"}))
    assert set(p.modes()) == {Mode.INIT}
    run(p, plant, 5)
    assert p.modes()[-1] == Mode.ACTIVE


@PRECISIONS
def test_core_fault_latches_fault_and_ramps_down_without_driver(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32, faults=[parse_fault("core-exception:50ms@0.3s")])
    plant = Plant(p.codec, 11)
    run(p, plant, 40)
    assert p.modes()[-1] == Mode.FAULT and p.st.fault.latched
    run(p, plant, 10, Faults(drop={"DRIVER_INPUTS"}))  # ramp-down in FAULT
    assert p.modes()[-1] == Mode.DRIVER_LOST_RAMPDOWN
    run(p, plant, 10)
    assert p.modes()[-1] == Mode.FAULT  # latched: FAULT returns with the driver frame
    last = p.answers[-1]
    assert last.qp_status == 3 and len(set(last.tq_nm)) == 1  # split evenly
    assert p.st.fault.exceptions == 1


@PRECISIONS
def test_plant_restart_forgets_the_streams(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 12)
    run(p, plant, 80)
    run(p, plant, 1, Faults(sync_back_s=0.7))
    run(p, plant, 20)
    assert p.node.plant_restarts == 1 == p.st.plant_restarts


@PRECISIONS
def test_burst_overflow_sets_rx_overload(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 13)
    run(p, plant, 10)
    run(p, plant, 3, Faults(extra={"WHEEL_SPEEDS": 4, "DRIVER_INPUTS": 3}))
    run(p, plant, 3)
    assert p.node.rx_drops[BURST_FULL] > 0 and p.node.rx_overload_cycles == 3
    assert [bool(t.fault_bits & (1 << Fault.RX_OVERLOAD)) for t in p.answers[-6:]] == [True] * 3 + [
        False
    ] * 3


@PRECISIONS
def test_rejected_sync_is_not_answered(libs, configs, f32: bool) -> None:
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 14)
    run(p, plant, 10)
    assert run(p, plant, 1, Faults(counter={"SYNC": 0})) == 0  # a repeated SYNC counter
    assert run(p, plant, 1, Faults(crc={"SYNC"})) == 0
    assert run(p, plant, 1, Faults(short={"SYNC"})) == 0
    assert run(p, plant, 1, Faults(extended={"SYNC"})) == 0
    # three SYNC counters lost: delta 4 is a wrong sequence (rejected, resynchronised)
    assert run(p, plant, 1) == 0
    assert run(p, plant, 5) == 5
    assert p.node.monitor.streams["SYNC"].rejections["wrong_sequence"] == 1


# ---------------------------------------------------------------------- random mixes
def random_faults(rng: np.random.Generator, state: dict, inject: bool = True) -> Faults:
    """A cycle's faults: long episodes (stuck sensor, stability off, driver lost, pedals)
    and single-cycle faults of every kind (``inject``: non-finite values too; the SecOC
    receiver decodes the SYNC it releases itself, past the test codec's injection)."""
    names = ["DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST"]
    for key, p_on, p_off in (
        ("stuck", 0.01, 0.08),
        ("stab_off", 0.01, 0.1),
        ("driver_lost", 0.01, 0.15),
        ("brake", 0.02, 0.1),
    ):
        if state.get(key):
            state[key] = rng.random() > p_off
        else:
            state[key] = rng.random() < p_on
    f = Faults(
        stuck_yaw=state["stuck"],
        stab=0 if state["stab_off"] else 1,
        accel=0.0 if state["brake"] else 0.3,
        brake=0.4 if state["brake"] else 0.0,
    )
    if state["driver_lost"]:
        f.drop.add("DRIVER_INPUTS")
    for _ in range(int(rng.poisson(0.6))):
        name = str(rng.choice([*names, "SYNC"]))
        kind = int(rng.integers(0, 9))
        if kind == 0:
            f.drop.add(name)
        elif kind == 1:
            f.counter[name] = int(rng.choice([0, 2, 3, 4, 7]))
        elif kind == 2:
            f.crc.add(name)
        elif kind == 3:
            f.short.add(name)
        elif kind == 4:
            (f.remote if rng.random() < 0.5 else f.extended).add(name)
        elif kind == 5 and OUT_OF_RANGE.get(name):
            f.out_of_range.add(name)
        elif kind == 6 and name != "SYNC":
            f.extra[name] = int(rng.integers(1, 5))
        elif kind == 7 and inject:
            sig = {
                "DRIVER_INPUTS": "SWA",
                "MOTION_SENSORS": "AY",
                "WHEEL_SPEEDS": "WS_FR",
                "VEHICLE_EST": "VX_EST",
                "SYNC": "SIM_TIME",
            }[name]
            f.inject[name] = {sig: float(rng.choice([math.nan, math.inf, -1e300, 0.0]))}
        else:
            f.junk, f.foreign = int(rng.integers(0, 3)), int(rng.integers(0, 2))
    if rng.random() < 0.003:
        f.sync_back_s = 1.0
    return f


@PRECISIONS
@pytest.mark.parametrize(
    "name,seed", [("nmpc-rhonn", 0), ("nmpc-rhonn", 1), ("lmpc", 2), ("passive", 3)]
)
def test_random_fault_mix_lockstep(libs, configs, name: str, seed: int, f32: bool) -> None:
    faults = [parse_fault("core-exception:20ms@4s")] if seed == 1 else []
    p = pair(libs, configs, name, f32, faults=faults)
    plant = Plant(p.codec, 100 + seed)
    rng, state = np.random.default_rng(seed), {}
    for _ in range(1200):
        p.lockstep(plant.burst(random_faults(rng, state)))
    modes = set(p.modes())
    assert {Mode.ACTIVE, Mode.DEGRADED_SENSORS, Mode.DRIVER_LOST_RAMPDOWN} <= modes
    assert sum(1 for v in p.node.monitor.counts.values() if v) >= 8
    if faults:
        assert Mode.FAULT in modes


@PRECISIONS
@pytest.mark.parametrize("seed", [0, 1])
def test_random_fault_mix_free_running(libs, configs, seed: int, f32: bool) -> None:
    """Frames arrive with jitter at monotonic times; the node ticks on its own, slightly
    slower schedule (drift: some ticks see no fresh frame, some two)."""
    p = pair(libs, configs, "nmpc-rhonn", f32)
    plant = Plant(p.codec, 200 + seed)
    rng, state = np.random.default_rng(seed), {}
    events: list[tuple[float, int, can.Message | None]] = []
    for k in range(800):
        t0 = 0.01 * k
        for msg in plant.burst(random_faults(rng, state)):
            events.append((t0 + float(rng.uniform(0.0, 0.004)), 0, msg))
        events.append((0.003 + 0.0101 * k, 1, None))
    events.sort(key=lambda e: (e[0], e[1]))
    for now, is_tick, msg in events:
        if is_tick:
            p.tick(now)
        else:
            p.accept(msg, now)
    assert {Mode.ACTIVE, Mode.DEGRADED_SENSORS} <= set(p.modes())
    assert p.bits() & (1 << Fault.SYNC_LOST)


# ------------------------------------------------------------- the C node's own guards
def test_released_frames_count_as_the_burst_would(libs, configs) -> None:
    """SecOC's released frames (rh_node_logic_sync's ``released``) are validated after the
    burst and before the SYNC: the same answers as the same frames buffered."""
    a = pair(libs, configs, "nmpc-rhonn", False)
    b = Pair(libs[False], "nmpc-rhonn", configs[False], core_module(False))
    plant_a, plant_b = Plant(a.codec, 15), Plant(b.codec, 15)
    for _ in range(50):
        a.lockstep(plant_a.burst(Faults()))
        frames = plant_b.burst(Faults())
        sorted_frames = sorted(frames[:-1], key=lambda m: m.arbitration_id)
        rel = b.lib.rx_array([b.event(m) for m in sorted_frames])
        tx = b.lib.new("tx")
        assert (
            b.lib.rh_node_logic_sync(
                b.st,
                b.ctrl_ptr,
                b.event(frames[-1]),
                rel,
                len(sorted_frames),
                tx,
            )
            == 1
        )
        assert list(tx.tq_nm) == list(a.answers[-1].tq_nm)
        assert tx.mode == a.answers[-1].mode == Mode.ACTIVE


def test_no_core_is_fault_and_bad_events_are_counted(libs, configs) -> None:
    """A core the integrator could not initialise (NULL) gives FAULT with the driver's torque
    split evenly; events the node cannot place are counted and change nothing."""
    p = pair(libs, configs, "passive", False)
    plant = Plant(p.codec, 16)
    lib, st = p.lib, p.st
    for _ in range(5):
        frames = plant.burst(Faults(accel=0.5))
        tx = lib.new("tx")
        for msg in frames[:-1]:
            lib.rh_node_logic_rx(st, p.event(msg))
        assert lib.rh_node_logic_sync(st, lib.NULL, p.event(frames[-1]), lib.NULL, 0, tx) == 1
    assert tx.mode == Mode.FAULT and st.fault.exceptions == 1
    assert list(tx.tq_nm) == [0.5 * 4 * PARAMS.peak_torque_nm / 4] * 4
    bad = [
        lib.new("rx", {"kind": 0, "stream": -1}),
        lib.new("rx", {"kind": 7, "stream": 0}),
        lib.new("rx", {"kind": 0, "stream": 4}),
        lib.new("rx", {"kind": 0, "stream": 9}),
    ]
    before = bytes(lib.ffi.buffer(lib.ffi.addressof(st, "monitor")))
    for ev in bad:
        assert lib.rh_node_logic_rx(st, ev) == -1
    assert lib.rh_node_logic_sync(st, lib.NULL, bad[0], lib.NULL, 0, tx) == -1
    assert lib.rh_node_logic_accept(st, bad[1], 0.0) == -1
    assert st.bad_events == 6 and bytes(lib.ffi.buffer(lib.ffi.addressof(st, "monitor"))) == before
    # a released frame of an unknown kind: counted, the SYNC still answered
    frames = plant.burst(Faults(accel=0.5))
    released = lib.rx_array([bad[1]])
    sync_ev = p.event(frames[-1])
    assert lib.rh_node_logic_sync(st, lib.NULL, sync_ev, released, 1, tx) == 1
    assert st.bad_events == 7


def test_invalid_config_starts_in_fault(libs) -> None:
    lib = libs[False]
    for field_name, value in (
        ("comm_period_s", 0.0),
        ("mpc_every", 0),
        ("controller_id", 16),
        ("plant_restart_backstep_s", math.nan),
    ):
        c = lib.new("logic_config")
        lib.rh_node_logic_default_config(c)
        setattr(c, field_name, value)
        st = lib.new("logic")
        assert lib.rh_node_logic_init(st, c) == -1
        assert st.fault.latched == 1
    c = lib.new("logic_config")
    lib.rh_node_logic_default_config(c)
    c.burst_bound[1] = lib.RH_NODE_BURST_MAX + 1
    assert lib.rh_node_logic_init(lib.new("logic"), c) == -1
    c.burst_bound[1] = 3
    c.envelope.clip_tol_nm = -1.0
    assert lib.rh_node_logic_init(lib.new("logic"), c) == -1


def test_default_config_matches_the_python_node(libs, configs) -> None:
    lib = libs[False]
    c = lib.new("logic_config")
    lib.rh_node_logic_default_config(c)
    node = ControllerNode(
        NativeController("nmpc-rhonn", configs[False], core_module(False)), PARAMS
    )
    assert (c.comm_period_s, c.mpc_every) == (node.comm_period_s, node.mpc_every)
    assert (c.peak_torque_nm, c.peak_power_w) == (PARAMS.peak_torque_nm, PARAMS.peak_power_w)
    assert list(c.burst_bound) == [s.maxlen for s in node._burst.values()]
    assert c.fault.rampdown_nm_per_s == node.rampdown_nm_per_s
    from controller.runtime.node import PLANT_RESTART_BACKSTEP_S

    assert c.plant_restart_backstep_s == PLANT_RESTART_BACKSTEP_S
    # the C node reads each stream's values in the DBC's signal order (node_monitor.h)
    order = {n: [g.name for g in Codec().messages[n].signals] for n in lay.STREAM_NAMES}
    assert order == {
        "DRIVER_INPUTS": ["SWA", "ACCEL_PEDAL", "BRAKE_PEDAL", "STAB_ENABLE"],
        "MOTION_SENSORS": ["YAW_RATE", "AX", "AY"],
        "WHEEL_SPEEDS": ["WS_FL", "WS_FR", "WS_RL", "WS_RR"],
        "VEHICLE_EST": ["VX_EST", "VY_EST"],
        "SYNC": ["CYCLE", "SIM_TIME"],
    }


@PRECISIONS
def test_secoc_released_frames_lost_authenticators_and_evictions(libs, configs, f32: bool) -> None:
    """With SecOC the C node gets the burst's verified frames with the SYNC (``released``)
    and the SecOC queue's eviction total; lost or forged authenticators leave frames
    unreleased (timeouts), a flood of unauthenticated SYNC frames evicts (RX_OVERLOAD)."""
    p = pair(libs, configs, "nmpc-rhonn", f32, secoc=True)
    plant = Plant(p.codec, 17)
    plant_secoc = PlantSecOc(Codec(), load_keys("ci-test-key"), trip=5)
    auth_ids = {p.codec.messages[n].frame_id for n in p.codec.messages if n.endswith("_AUTH")}
    rng, state = np.random.default_rng(17), {}
    forged = Codec().message("SYNC", {"CYCLE": 1.0, "SIM_TIME": 0.01}, 3)
    for k in range(400):
        cycle = plant.cycle
        frames = plant_secoc.protect(plant.burst(random_faults(rng, state, False)), cycle)
        kept = []
        for msg in frames:
            if msg.arbitration_id in auth_ids and rng.random() < 0.04:
                continue  # authenticator lost: its frame is never released
            if msg.arbitration_id in auth_ids and rng.random() < 0.02:
                data = bytearray(msg.data)
                data[6] ^= 0x01  # MAC bit flipped, CRC sealed again: a forgery
                Codec().seal(msg.arbitration_id, data)
                msg = can.Message(
                    arbitration_id=msg.arbitration_id, data=bytes(data), is_extended_id=False
                )
            kept.append(msg)
        if k in (100, 250):
            kept = [forged] * (PENDING + 5) + kept
        p.lockstep_secoc(kept)
    assert p.c_secoc.receiver.evicted > 0 and p.node.rx_overload_cycles >= 2
    assert p.bits() & (1 << Fault.RX_OVERLOAD)
    assert {Mode.ACTIVE, Mode.DEGRADED_SENSORS} <= set(p.modes())
    assert len(p.answers) > 300
