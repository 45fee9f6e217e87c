"""SecOC receiver and endpoints at their edges: the freshness value's fields, the receiver's
initial state, the forward window's last cycle, the held queue's evictions, non-data frames
on deferred IDs, the counters a summary reports, trip 0 (the smallest freshness values) and
the observer's labels."""

from __future__ import annotations

import logging

import can
import pytest

from can_db.codec import Codec, Decoded, Transmitter
from can_db.secoc import (
    CTRL_SECURED,
    CYCLE_BITS,
    FV_LO_BITS,
    HISTORY,
    MAC_BITS,
    SECURED,
    ControllerSecOc,
    PlantSecOc,
    SecOcObserver,
    SecOcReceiver,
    _Stream,
    freshness,
    fv_cycle,
)
from can_db.secoc_keys import SecOcKeys, ci_test_keys
from tests.test_secoc_unit import KEY_A, deliver, keys, pair, sensor_burst, sync, torque

CODEC = Codec()


def name_of(msg: can.Message) -> str:
    return CODEC.by_id[msg.arbitration_id].name


def fv_lo_of(auth: can.Message) -> int:
    decoded = CODEC.decode_message(auth)
    assert isinstance(decoded, Decoded)
    return int(decoded.values["FV_LO"])


# ------------------------------------------------------------------------ freshness value
def test_the_freshness_value_is_trip_cycle_and_index_each_cut_to_its_field() -> None:
    """FV = trip (20 bits) << 32 | cycle (24 bits) << 8 | index (8 bits): a field's excess
    bits are dropped, never carried into the next field."""
    assert freshness(5, 0x123456, 0xAB) == 0x0000_0005_1234_56AB
    assert freshness(0xFFFFF, 0xFFFFFF, 0xFF) == 0x000F_FFFF_FFFF_FFFF
    assert freshness(5, 3, 200) == (5 << 32) | (3 << 8) | 200
    assert freshness((1 << 20) | 5, (1 << 24) | 0x10, (1 << 8) | 7) == (5 << 32) | (0x10 << 8) | 7
    # an even trip: a cycle carry into bit 32 would show
    assert freshness(6, (1 << 24) | 0x10, 7) == (6 << 32) | (0x10 << 8) | 7
    assert freshness(1 << 21, 1 << 25, 1 << 9) == 0
    assert fv_cycle(freshness(7, 0xABCDEF, 9)) == 0xABCDEF


def test_the_field_widths_are_the_wires() -> None:
    """The MAC, FV_LO and cycle widths are the DBC signals' (every authenticator's MAC and
    FV_LO, the SYNC's CYCLE)."""
    db = CODEC.database
    for auth in SECURED.values():
        signals = {s.name: s.length for s in db.get_message_by_name(auth).signals}
        assert signals["MAC"] == MAC_BITS == 32, auth
        if auth != "SYNC_AUTH":
            assert signals["FV_LO"] == FV_LO_BITS == 20, auth
    assert db.get_message_by_name("SYNC").get_signal_by_name("CYCLE").length == CYCLE_BITS


def test_a_trip_beyond_the_wire_is_sent_and_used_as_its_low_20_bits() -> None:
    plant = PlantSecOc(CODEC, keys(), trip=(1 << 20) + 5)
    ctrl = ControllerSecOc(CODEC, keys())
    frames = plant.protect([Transmitter(CODEC).message("SYNC", {"CYCLE": 3})], 3)
    decoded = CODEC.decode_message(frames[1])
    assert isinstance(decoded, Decoded) and decoded.values["TRIP"] == 5
    assert ctrl.feed(frames[0]) is None and ctrl.feed(frames[1]) is frames[0]
    assert ctrl.trip == 5


def test_before_its_first_sync_the_controller_answers_with_the_freshness_of_cycle_zero() -> None:
    """The node answers cycle -1 before any SYNC: its authenticator carries cycle 0 (FV_LO 0),
    not the 24-bit wrap of -1."""
    ctrl = ControllerSecOc(CODEC, keys())
    ctx = Transmitter(CODEC)
    _, auth = ctrl.protect([torque(ctx, 0)], -1)
    assert fv_lo_of(auth) == 0
    _, auth = ctrl.protect([torque(ctx, 0)], -1)
    assert fv_lo_of(auth) == 1  # the second frame of cycle 0: index 1


def test_the_frames_of_one_id_in_one_cycle_are_indexed_0_1_2() -> None:
    ctrl = ControllerSecOc(CODEC, keys())
    ctx = Transmitter(CODEC)
    lows = [fv_lo_of(ctrl.protect([torque(ctx, 7)], 7)[1]) for _ in range(3)]
    assert lows == [(7 << 8) | 0, (7 << 8) | 1, (7 << 8) | 2]
    assert fv_lo_of(ctrl.protect([torque(ctx, 8)], 8)[1]) == 8 << 8  # a new cycle: index 0
    assert ctrl.summary()["authenticators_sent"] == 4


# ----------------------------------------------------------------------- receiver's state
def test_a_new_receivers_counters_start_at_zero() -> None:
    plant, ctrl, _, _ = pair()
    for summary in (plant.summary(), ctrl.summary()):
        assert summary["enabled"] is True
        assert summary["evicted_unverified"] == 0 and summary["rejected"] == {}
        assert summary["rejected_by_frame"] == {} and summary["authenticators_sent"] == 0
        assert set(summary["accepted"].values()) == {0}
    assert ctrl.summary()["resyncs"] == 0
    assert plant.receiver.accepted == ctrl.receiver.accepted == 0
    assert ctrl.trip == 0 and ctrl.summary()["trip"] == 0  # no SYNC yet


def test_a_receiver_given_a_trip_answers_for_cycle_zero_until_told_a_cycle() -> None:
    """A receiver's cycle is 0 until set: with the trip known, the controller's command of
    cycle 0 verifies; one of cycle 1 is not yet answerable (its freshness reconstructs a
    whole FV_LO range back), so its MAC fails."""
    rx = SecOcReceiver(CODEC, KEY_A, CTRL_SECURED)
    rx.trip = 5
    ctrl = ControllerSecOc(CODEC, keys())
    ctrl.receiver.trip = 5
    ctx = Transmitter(CODEC)
    tq, auth = ctrl.protect([torque(ctx, 0)], 0)
    assert rx.feed(tq) is None and rx.feed(auth) is tq
    tq, auth = ctrl.protect([torque(ctx, 1)], 1)
    assert rx.feed(tq) is None and rx.feed(auth) is None
    assert rx.rejection_counts() == {"bad_mac": 1}


def test_the_accepted_total_counts_every_pair_once() -> None:
    """``accepted`` is the sum of the per-frame counts: frames released on their
    authenticator's arrival, with their SYNC, and the plant's commands."""
    plant, ctrl, ptx, ctx = pair()
    deliver(ctrl, plant.protect(sensor_burst(ptx, 0), 0))  # released with the SYNC
    assert ctrl.receiver.accepted == 5
    deliver(ctrl, plant.protect(sensor_burst(ptx, 1), 1))  # the trip known: early
    assert ctrl.receiver.accepted == 10
    assert ctrl.receiver.accepted == sum(ctrl.summary()["accepted"].values())
    for cycle in (1, 2):
        for m in ctrl.protect([torque(ctx, cycle)], cycle):
            plant.feed(m, cycle)
    assert plant.receiver.accepted == 2 == plant.summary()["accepted"]["WHEEL_TORQUE_CMD"]


def test_syncs_of_one_trip_are_no_resynchronisation() -> None:
    plant, ctrl, ptx, _ = pair()
    for cycle in range(4):
        sync(plant, ptx, ctrl, cycle)
    assert ctrl.receiver.resyncs == 0 and ctrl.summary()["resyncs"] == 0
    restarted = PlantSecOc(CODEC, keys(), trip=6)
    sync(restarted, Transmitter(CODEC), ctrl, 0)
    sync(restarted, Transmitter(CODEC), ctrl, 1)
    assert ctrl.receiver.resyncs == 1 and ctrl.trip == 6


def test_the_history_forgets_exactly_its_oldest_freshness_value() -> None:
    """The replay memory of an ID is the last 4096 accepted freshness values (a FV_LO range
    of cycles), no more and no other: the oldest is forgotten first."""
    stream = _Stream()
    for fv in range(4096 + 2):
        stream.remember(fv)
    assert HISTORY == 4096
    assert list(stream.history) == list(range(2, 4096 + 2))
    assert stream.seen == set(range(2, 4096 + 2))
    assert stream.last_fv == 4096 + 1


# ------------------------------------------------------------------------- forward window
def test_a_command_is_accepted_up_to_exactly_the_window_and_not_a_cycle_later() -> None:
    """At the plant's cycle c + 10 a command answering cycle c is fresh (window of 10
    cycles); at c + 11 it is stale."""
    for late, accepted in ((10, True), (11, False)):
        plant, ctrl, ptx, ctx = pair()
        sync(plant, ptx, ctrl, 22)
        tq, auth = ctrl.protect([torque(ctx, 22)], 22)
        plant.feed(tq, 22 + late)
        assert (plant.feed(auth, 22 + late) is tq) is accepted, late
        assert plant.receiver.rejection_counts() == ({} if accepted else {"stale_freshness": 1})


@pytest.mark.parametrize(("ahead", "early"), [(1, True), (10, True), (11, False)])
def test_sensor_frames_are_released_early_up_to_ten_cycles_after_the_last_sync(
    ahead: int, early: bool
) -> None:
    """With the trip known, a sensor frame up to 10 cycles after the last authentic SYNC is
    released when its authenticator arrives; a later one waits for its own SYNC."""
    plant, ctrl, ptx, _ = pair()
    deliver(ctrl, plant.protect(sensor_burst(ptx, 20), 20))
    burst = plant.protect(sensor_burst(ptx, 20 + ahead), 20 + ahead)
    assert ctrl.feed(burst[2]) is None
    assert (ctrl.feed(burst[3]) is burst[2]) is early
    # the wheel speeds, the estimate and the SYNC; the motion frame too when it waited
    assert len(deliver(ctrl, burst[4:])) == (3 if early else 4)
    assert ctrl.receiver.rejection_counts() == {}


def test_after_its_first_sync_the_next_burst_is_released_early() -> None:
    plant, ctrl, ptx, _ = pair()
    deliver(ctrl, plant.protect(sensor_burst(ptx, 0), 0))
    burst = plant.protect(sensor_burst(ptx, 1), 1)
    assert ctrl.feed(burst[0]) is None and ctrl.feed(burst[1]) is burst[0]


@pytest.mark.parametrize(("delay", "accepted"), [(9, True), (10, True), (11, False), (12, False)])
def test_a_held_back_sensor_frame_is_fresh_for_exactly_ten_cycles(
    delay: int, accepted: bool
) -> None:
    """An attacker holds back a genuine MOTION_SENSORS of cycle 21 (and its authenticator)
    and delivers it after the SYNC of cycle 21 + delay: released up to 10 cycles, stale
    (never released to the node) from 11."""
    plant, ctrl, ptx, _ = pair()
    deliver(ctrl, plant.protect(sensor_burst(ptx, 20), 20))
    held: list[can.Message] = []
    for cycle in range(21, 21 + delay + 1):
        burst = plant.protect(sensor_burst(ptx, cycle), cycle)
        if cycle == 21:
            held = burst[2:4]
        deliver(ctrl, burst[:2] + burst[4:])
    assert ctrl.feed(held[0]) is None
    assert (ctrl.feed(held[1]) is held[0]) is accepted
    expected = {} if accepted else {"MOTION_SENSORS": {"stale_freshness": 1}}
    assert ctrl.receiver.rejections_by_frame() == expected


def test_the_last_index_of_a_cycle_is_inside_both_windows() -> None:
    """The 256th frame of an ID in one cycle (index 255): a sensor frame 10 cycles after
    the last SYNC is released early, a command of the plant's current cycle is accepted."""
    plant, ctrl, ptx, ctx = pair()
    deliver(ctrl, plant.protect(sensor_burst(ptx, 0), 0))
    driver = plant.protect([ptx.message("DRIVER_INPUTS", {}) for _ in range(256)], 10)
    assert fv_lo_of(driver[-1]) == (10 << 8) | 255
    assert ctrl.feed(driver[-2]) is None and ctrl.feed(driver[-1]) is driver[-2]
    commands = ctrl.protect([torque(ctx, 0) for _ in range(256)], 0)
    assert fv_lo_of(commands[-1]) == 255
    assert plant.feed(commands[-2], 0) is None and plant.feed(commands[-1], 0) is commands[-2]


# ----------------------------------------------------------------------------- evictions
def test_unauthenticated_commands_pushed_out_are_counted_one_by_one() -> None:
    plant, ctrl, ptx, _ = pair()
    sync(plant, ptx, ctrl, 0)
    rogue = Transmitter(CODEC)
    for k in range(16 + 3):  # 16 kept per ID (module doc)
        plant.feed(torque(rogue, 0, tq=float(k)), 0)
    summary = plant.summary()
    assert summary["evicted_unverified"] == 3 == plant.receiver.evicted
    assert summary["rejected_by_frame"] == {"WHEEL_TORQUE_CMD": {"unauthenticated": 3}}
    assert summary["pending"]["WHEEL_TORQUE_CMD"] == 16


def test_the_held_queue_counts_the_kind_of_the_frame_it_pushes_out() -> None:
    """Before the first SYNC the controller holds a sensor ID's data frames and
    authenticators (32 in all); the oldest is pushed out by a new one and counted as what it
    is: a data frame ``unauthenticated``, an authenticator ``unchecked_auth``."""
    plant, ctrl, ptx, _ = pair()
    frames = []
    held = 32  # 16 data frames and 16 authenticators (module doc)
    for cycle in range(held):
        burst = plant.protect(sensor_burst(ptx, cycle), cycle)
        frames += burst[2:4]  # MOTION_SENSORS and its authenticator; no SYNC delivered
    assert [name_of(m) for m in frames[:2]] == ["MOTION_SENSORS", "MOTION_SENSORS_AUTH"]
    for m in frames[:held]:
        assert ctrl.feed(m) is None
    assert ctrl.summary()["pending"]["MOTION_SENSORS"] == 16
    assert ctrl.summary()["pending_authenticators"]["MOTION_SENSORS"] == 16
    assert ctrl.receiver.rejection_counts() == {}
    ctrl.feed(frames[held])  # pushes out the oldest: a data frame
    assert ctrl.receiver.rejections_by_frame() == {"MOTION_SENSORS": {"unauthenticated": 1}}
    ctrl.feed(frames[held + 1])  # pushes out the oldest: an authenticator
    assert ctrl.receiver.rejections_by_frame() == {
        "MOTION_SENSORS": {"unauthenticated": 1, "unchecked_auth": 1}
    }
    assert ctrl.receiver.evicted == 2


def test_held_data_frames_and_authenticators_are_told_apart() -> None:
    plant, ctrl, ptx, _ = pair()
    burst = plant.protect(sensor_burst(ptx, 3), 3)
    extra = plant.protect(sensor_burst(ptx, 4), 4)
    for m in [*burst[:8], extra[2]]:  # no SYNC: 5 data frames, 4 authenticators held
        ctrl.feed(m)
    sec = ctrl.summary()
    assert sec["received"] == {
        "SYNC": 0,
        "DRIVER_INPUTS": 1,
        "MOTION_SENSORS": 2,
        "WHEEL_SPEEDS": 1,
        "VEHICLE_EST": 1,
    }
    assert sec["authenticators_received"] == {
        "SYNC": 0,
        "DRIVER_INPUTS": 1,
        "MOTION_SENSORS": 1,
        "WHEEL_SPEEDS": 1,
        "VEHICLE_EST": 1,
    }
    assert sec["pending"] == {
        "SYNC": 0,
        "DRIVER_INPUTS": 1,
        "MOTION_SENSORS": 2,
        "WHEEL_SPEEDS": 1,
        "VEHICLE_EST": 1,
    }
    assert sec["pending_authenticators"] == {
        "SYNC": 0,
        "DRIVER_INPUTS": 1,
        "MOTION_SENSORS": 1,
        "WHEEL_SPEEDS": 1,
        "VEHICLE_EST": 1,
    }


@pytest.mark.parametrize("flag", ["is_remote_frame", "is_error_frame", "is_extended_id"])
def test_a_non_data_frame_on_a_deferred_id_is_neither_held_nor_counted(flag: str) -> None:
    """Each flag on its own: on the sensor ID the frame goes to the E2E layer at once (which
    counts it as not_data_frame), on its authenticator ID it is dropped; neither is a
    received secured frame, held, or passed on as a CRC fault."""
    plant, ctrl, ptx, _ = pair()
    burst = plant.protect(sensor_burst(ptx, 1), 1)
    data, auth = burst[2], burst[3]
    flags = {"is_extended_id": False, flag: True}
    bad_data = can.Message(arbitration_id=data.arbitration_id, data=data.data, **flags)
    bad_auth = can.Message(arbitration_id=auth.arbitration_id, data=auth.data, **flags)
    assert ctrl.feed(bad_data) is bad_data
    assert ctrl.feed(bad_auth) is None
    sec = ctrl.summary()
    assert (
        sec["received"]["MOTION_SENSORS"] == sec["authenticators_received"]["MOTION_SENSORS"] == 0
    )
    assert sec["pending"]["MOTION_SENSORS"] == sec["pending_authenticators"]["MOTION_SENSORS"] == 0
    assert sec["to_e2e"]["MOTION_SENSORS"] == 0 and sec["rejected"] == {}


@pytest.mark.parametrize("flag", ["is_remote_frame", "is_error_frame", "is_extended_id"])
def test_a_non_data_frame_on_a_command_id_goes_to_the_e2e_layer_uncounted(flag: str) -> None:
    plant, ctrl, ptx, ctx = pair()
    sync(plant, ptx, ctrl, 0)
    tq, _ = ctrl.protect([torque(ctx, 0)], 0)
    bad = can.Message(
        arbitration_id=tq.arbitration_id, data=tq.data, **{"is_extended_id": False, flag: True}
    )
    assert plant.feed(bad, 0) is bad
    assert plant.summary()["received"]["WHEEL_TORQUE_CMD"] == 0
    assert plant.summary()["pending"]["WHEEL_TORQUE_CMD"] == 0


def test_a_short_sensor_frame_goes_to_the_e2e_layer_at_once() -> None:
    plant, ctrl, ptx, _ = pair()
    burst = plant.protect(sensor_burst(ptx, 2), 2)
    short = can.Message(
        arbitration_id=burst[2].arbitration_id, data=bytes(burst[2].data)[:7], is_extended_id=False
    )
    assert ctrl.feed(short) is short
    sec = ctrl.summary()
    assert sec["to_e2e"]["MOTION_SENSORS"] == 1 and sec["pending"]["MOTION_SENSORS"] == 0


def test_a_corrupted_sync_held_before_the_genuine_one_does_not_hide_it() -> None:
    """A SYNC that does not decode (bad CRC) waits with the genuine SYNC of the cycle; the
    genuine one's authenticator still finds and releases it."""
    plant, ctrl, ptx, _ = pair()
    frames = plant.protect([ptx.message("SYNC", {"CYCLE": 4, "SIM_TIME": 0.04})], 4)
    bad = bytearray(frames[0].data)
    bad[0] ^= 0xFF
    corrupted = can.Message(
        arbitration_id=frames[0].arbitration_id, data=bytes(bad), is_extended_id=False
    )
    assert ctrl.feed(corrupted) is None
    assert ctrl.feed(frames[0]) is None
    assert ctrl.feed(frames[1]) is frames[0]
    assert ctrl.trip == 5 and ctrl.receiver.rejection_counts() == {"unauthenticated": 1}


def test_the_first_rejection_of_a_kind_is_a_warning_the_rest_are_counted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    plant, ctrl, ptx, _ = pair()
    sync(plant, ptx, ctrl, 0)
    _, auth = ctrl.protect([torque(Transmitter(CODEC), 0)], 0)
    with caplog.at_level(logging.WARNING, logger="can_db.secoc"):
        for _ in range(3):
            plant.feed(auth, 0)  # nothing pending: orphan_auth
    warnings = [r.getMessage() for r in caplog.records if r.name == "can_db.secoc"]
    assert len(warnings) == 1
    assert "WHEEL_TORQUE_CMD" in warnings[0] and "orphan_auth" in warnings[0]
    assert plant.receiver.rejection_counts() == {"orphan_auth": 3}


# ------------------------------------------------------------------------------- trip 0
def test_on_trip_zero_the_first_command_has_the_smallest_freshness_and_is_accepted() -> None:
    """Trip 0, cycle 0, index 0 is FV 0: above a new receiver's "nothing accepted yet"."""
    plant = PlantSecOc(CODEC, keys(), trip=0)
    ctrl = ControllerSecOc(CODEC, keys())
    sync(plant, Transmitter(CODEC), ctrl, 0)
    assert ctrl.trip == 0
    ctx = Transmitter(CODEC)
    for sub in range(2):  # FV 0, then FV 1
        tq, auth = ctrl.protect([torque(ctx, 0, tq=float(sub))], 0)
        assert fv_lo_of(auth) == sub
        assert plant.feed(tq, 0) is None and plant.feed(auth, 0) is tq
    assert plant.receiver.rejection_counts() == {}


def test_on_trip_zero_a_late_sensor_frame_of_cycle_zero_is_released_on_arrival() -> None:
    """The SYNC of cycle 0 arrives before the cycle's driver frame: the frame (FV 0) is then
    verified and released when its authenticator arrives."""
    plant = PlantSecOc(CODEC, keys(), trip=0)
    ctrl = ControllerSecOc(CODEC, keys())
    burst = plant.protect(sensor_burst(Transmitter(CODEC), 0), 0)
    assert [name_of(m) for m in deliver(ctrl, burst[8:])] == ["SYNC"]
    assert ctrl.feed(burst[0]) is None
    assert ctrl.feed(burst[1]) is burst[0]
    assert ctrl.receiver.rejection_counts() == {}


def test_on_trip_zero_an_authenticator_without_a_freshness_value_is_held_not_checked() -> None:
    """With trip 0 the early window's bound is below 2**20: a (forged) FV_LO of 0xFFFFF has
    no freshness value at or below it (it would be -1), so the authenticator is held, not
    checked (an FV below zero has no 8-byte form to MAC), and judged with the next SYNC."""
    plant = PlantSecOc(CODEC, keys(), trip=0)
    ctrl = ControllerSecOc(CODEC, keys())
    ptx = Transmitter(CODEC)
    assert len(deliver(ctrl, plant.protect(sensor_burst(ptx, 0), 0))) == 5
    burst = plant.protect(sensor_burst(ptx, 1), 1)
    forged = Transmitter(CODEC).message("DRIVER_INPUTS_AUTH", {"FV_LO": 0xFFFFF, "MAC": 1.0})
    assert ctrl.feed(burst[0]) is None
    assert ctrl.feed(forged) is None
    assert [name_of(m) for m in deliver(ctrl, burst[1:])] == [
        "DRIVER_INPUTS",
        "MOTION_SENSORS",
        "WHEEL_SPEEDS",
        "VEHICLE_EST",
        "SYNC",
    ]
    assert ctrl.receiver.rejection_counts() == {"orphan_auth": 1}


def test_on_trip_zero_a_command_authenticator_without_a_freshness_value_is_a_bad_mac() -> None:
    """The plant on trip 0 at cycle 3: a forged FV_LO of 0xFFFFF has no freshness value at
    or below the plant's bound (it would be -1): no MAC is computed, the authenticator is
    refused as not verifying and the pending command stays pending."""
    plant = PlantSecOc(CODEC, keys(), trip=0)
    ctrl = ControllerSecOc(CODEC, keys())
    sync(plant, Transmitter(CODEC), ctrl, 3)
    tq, auth = ctrl.protect([torque(Transmitter(CODEC), 3)], 3)
    forged = Transmitter(CODEC).message("WHEEL_TORQUE_AUTH", {"FV_LO": 0xFFFFF, "MAC": 1.0})
    assert plant.feed(tq, 3) is None
    assert plant.feed(forged, 3) is None
    assert plant.receiver.rejection_counts() == {"bad_mac": 1}
    assert plant.feed(auth, 3) is tq


# ------------------------------------------------------------------------------- labels
def test_the_summary_names_the_keys_source_and_marks_the_public_test_key() -> None:
    plant = PlantSecOc(CODEC, ci_test_keys(), trip=1)
    assert plant.summary()["keys"] == "ci-test-key (PUBLIC, simulation only)"
    ctrl = ControllerSecOc(CODEC, SecOcKeys(KEY_A, KEY_A, "/etc/rhonn/keys.toml"))
    assert ctrl.summary()["keys"] == "/etc/rhonn/keys.toml"


def test_the_observer_returns_the_sensor_frame_an_authenticator_released() -> None:
    plant, _, ptx, _ = pair()
    obs = SecOcObserver(CODEC, keys())
    for m in plant.protect(sensor_burst(ptx, 0), 0):
        obs.observe(m)
    burst = plant.protect(sensor_burst(ptx, 1), 1)
    assert obs.observe(burst[0]) == ("pending", None)
    assert obs.observe(burst[1]) == ("pending", burst[0])


def test_the_observer_names_exactly_the_reason_of_a_rejection() -> None:
    plant, ctrl, ptx, ctx = pair()
    obs = SecOcObserver(CODEC, keys())
    for m in plant.protect([ptx.message("SYNC", {"CYCLE": 1})], 1):
        obs.observe(m)
        ctrl.feed(m)
    tq, auth = ctrl.protect([torque(ctx, 1)], 1)
    assert obs.observe(auth) == ("REJECTED orphan_auth", None)
    forged = bytearray(auth.data)
    forged[6] ^= 0x01  # a MAC bit, CRC made right again
    CODEC.seal(auth.arbitration_id, forged)
    forged_auth = can.Message(
        arbitration_id=auth.arbitration_id, data=bytes(forged), is_extended_id=False
    )
    assert obs.observe(tq) == ("pending", None)
    assert obs.observe(forged_auth) == ("REJECTED bad_mac", None)
    assert obs.observe(auth) == ("authenticated 0x080", tq)
    assert obs.observe(auth) == ("REJECTED orphan_auth", None)


def test_the_options_of_the_receiver_the_plant_and_the_observer_are_keyword_only() -> None:
    with pytest.raises(TypeError):
        SecOcReceiver(CODEC, KEY_A, CTRL_SECURED, 10)  # type: ignore[misc]
    with pytest.raises(TypeError):
        PlantSecOc(CODEC, keys(), 1, 10)  # type: ignore[misc]
    with pytest.raises(TypeError):
        SecOcObserver(CODEC, keys(), 10)  # type: ignore[misc]
