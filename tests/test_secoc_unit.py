"""SecOC unit tests (in-process): MAC, freshness, receiver verdicts, keys, trip counter."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import can
import pytest
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC
from hypothesis import given, settings
from hypothesis import strategies as st

from can_db.codec import Codec, Decoded, Transmitter
from can_db.crc import frame_crc
from can_db.faults import FaultInjector, parse_faults
from can_db.secoc import (
    FV_LO_BITS,
    HISTORY,
    ControllerSecOc,
    MacEngine,
    PlantSecOc,
    SecOcObserver,
    freshness,
    reconstruct,
)
from can_db.secoc_keys import (
    ENV_CTRL_TO_PLANT,
    ENV_PLANT_TO_CTRL,
    SecOcKeyError,
    SecOcKeys,
    TripCounter,
    ci_test_keys,
    load_keys,
)

CODEC = Codec()
KEY_A = bytes(range(16))
KEY_B = bytes(range(16, 32))


def keys() -> SecOcKeys:
    return SecOcKeys(KEY_A, KEY_B, "test")


def torque(tx: Transmitter, cycle: int, tq: float = 10.0) -> can.Message:
    return tx.message("WHEEL_TORQUE_CMD", {"TQ_FL": tq, "TQ_FR": -tq, "ECHO_CYCLE": cycle % 256})


def test_cmac_of_the_library_matches_rfc4493_example_2() -> None:
    c = CMAC(algorithms.AES(bytes.fromhex("2b7e151628aed2a6abf7158809cf4f3c")))
    c.update(bytes.fromhex("6bc1bee22e409f96e93d7e117393172a"))
    assert c.finalize().hex() == "070a16b46b4d4144f79bdd9dd04a287c"


def test_mac_is_the_truncated_cmac_over_id_payload_and_full_freshness() -> None:
    payload, fv = bytes(range(8)), freshness(3, 1234, 1)
    c = CMAC(algorithms.AES(KEY_A))
    c.update((0x80).to_bytes(2, "big") + payload + fv.to_bytes(8, "big"))
    assert MacEngine(KEY_A).mac(0x80, payload, fv) == int.from_bytes(c.finalize()[:4], "big")
    engine = MacEngine(KEY_A)
    base = engine.mac(0x80, payload, fv)
    assert engine.mac(0x81, payload, fv) != base  # ID covered
    assert engine.mac(0x80, payload, fv + (1 << 32)) != base  # trip (beyond FV_LO) covered
    assert engine.mac(0x80, bytes([1]) + payload[1:], fv) != base  # CRC byte covered


def test_reconstruction_picks_the_largest_value_not_above_the_bound() -> None:
    upper = freshness(2, 4096 + 5, 255)
    for cycle in (4096 + 5, 4096 + 1, 4096, 4095, 4096 + 5 - 4095):
        fv = freshness(2, cycle)
        assert reconstruct(fv & ((1 << FV_LO_BITS) - 1), upper) == fv


def pair() -> tuple[PlantSecOc, ControllerSecOc, Transmitter, Transmitter]:
    plant = PlantSecOc(CODEC, keys(), trip=5)
    ctrl = ControllerSecOc(CODEC, keys())
    return plant, ctrl, Transmitter(CODEC), Transmitter(CODEC)


def sync(plant: PlantSecOc, ptx: Transmitter, ctrl: ControllerSecOc, cycle: int) -> None:
    frames = plant.protect([ptx.message("SYNC", {"CYCLE": cycle, "SIM_TIME": cycle / 100})],
                           cycle)
    assert ctrl.feed(frames[0]) is None  # held until its authenticator verifies
    released = ctrl.feed(frames[1])
    assert released is not None and released.arbitration_id == frames[0].arbitration_id


def test_authentic_command_is_released_only_by_its_authenticator() -> None:
    plant, ctrl, ptx, ctx = pair()
    sync(plant, ptx, ctrl, 0)
    assert ctrl.trip == 5
    tq, auth = ctrl.protect([torque(ctx, 0)], 0)
    assert plant.feed(tq, 0) is None
    assert plant.feed(auth, 0) is tq
    assert plant.receiver.rejection_counts() == {}
    # the same pair again: a replay
    assert plant.feed(tq, 0) is None and plant.feed(auth, 0) is None
    assert plant.receiver.rejection_counts() == {"replay": 1}


def test_forged_and_corrupted_frames_are_rejected_by_reason() -> None:
    plant, ctrl, ptx, ctx = pair()
    sync(plant, ptx, ctrl, 10)
    tq, auth = ctrl.protect([torque(ctx, 10)], 10)
    # MAC bit flipped (CRC recomputed: well formed)
    bad = bytearray(auth.data)
    bad[5] ^= 0x10
    bad[0] = frame_crc(auth.arbitration_id, bad)
    assert plant.feed(tq, 10) is None
    assert plant.feed(can.Message(arbitration_id=auth.arbitration_id, data=bytes(bad),
                                  is_extended_id=False), 10) is None
    assert plant.receiver.counts["bad_mac"] == 1
    # payload bit flipped
    flipped = bytearray(tq.data)
    flipped[3] ^= 0x01
    flipped[0] = frame_crc(tq.arbitration_id, flipped)
    plant2, _, _, _ = pair()
    plant2.feed(can.Message(arbitration_id=tq.arbitration_id, data=bytes(flipped),
                            is_extended_id=False), 10)
    assert plant2.feed(auth, 10) is None and plant2.receiver.counts["bad_mac"] == 1
    # the genuine authenticator still releases the genuine (pending) frame
    assert plant.feed(auth, 10) is tq
    # an authenticator with nothing to authenticate
    assert plant.feed(auth, 10) is None and plant.receiver.counts["orphan_auth"] == 1


def test_stale_freshness_older_than_the_forward_window_or_the_last_accepted() -> None:
    plant, ctrl, ptx, ctx = pair()
    sync(plant, ptx, ctrl, 20)
    old = ctrl.protect([torque(ctx, 20)], 20)  # never delivered in time
    sync(plant, ptx, ctrl, 21)
    new = ctrl.protect([torque(ctx, 21)], 21)
    for m in new:
        plant.feed(m, 21)
    for m in old:  # authentic, not a replay, but older than the last accepted
        plant.feed(m, 21)
    assert plant.receiver.rejection_counts() == {"stale_freshness": 1}
    late = ctrl.protect([torque(ctx, 22)], 22)
    for m in late:  # authentic and newer, but 11 cycles old at the plant (window: 10)
        plant.feed(m, 33)
    assert plant.receiver.counts["stale_freshness"] == 2
    assert plant.receiver.accepted_by_frame["WHEEL_TORQUE_CMD"] == 1


def test_unauthenticated_frame_is_dropped_and_the_genuine_one_kept() -> None:
    plant, ctrl, ptx, ctx = pair()
    sync(plant, ptx, ctrl, 3)
    rogue = torque(Transmitter(CODEC), 3, tq=450.0)
    tq, auth = ctrl.protect([torque(ctx, 3)], 3)
    plant.feed(rogue, 3)  # arrives first, same ID, correct CRC and counter
    plant.feed(tq, 3)
    assert plant.feed(auth, 3) is tq
    assert plant.receiver.rejection_counts() == {"unauthenticated": 1}


def test_freerun_frames_of_one_cycle_get_distinct_freshness() -> None:
    plant, ctrl, ptx, ctx = pair()
    sync(plant, ptx, ctrl, 7)
    first = ctrl.protect([torque(ctx, 7)], 7)
    second = ctrl.protect([torque(ctx, 7, tq=11.0)], 7)
    released = [plant.feed(m, 7) for m in first + second]
    assert released[1] is first[0] and released[3] is second[0]


def test_plant_restart_resynchronises_through_the_authenticated_sync(tmp_path: Path) -> None:
    state = tmp_path / "trip"
    trips = [TripCounter(state).next_trip() for _ in range(2)]
    assert trips == [1, 2] and state.read_text().strip() == "2"
    ctrl = ControllerSecOc(CODEC, keys())
    old_plant = PlantSecOc(CODEC, keys(), trip=trips[0])
    sync(old_plant, Transmitter(CODEC), ctrl, 500)
    new_plant = PlantSecOc(CODEC, keys(), trip=trips[1])  # cycles start again at 0
    sync(new_plant, Transmitter(CODEC), ctrl, 0)
    assert ctrl.trip == 2 and ctrl.receiver.resyncs == 1
    ctx = Transmitter(CODEC)
    tq, auth = ctrl.protect([torque(ctx, 0)], 0)
    new_plant.feed(tq, 0)
    assert new_plant.feed(auth, 0) is tq
    # an old-trip SYNC replayed afterwards is refused
    replayed = old_plant.protect([Transmitter(CODEC).message("SYNC", {"CYCLE": 501})], 501)
    assert ctrl.feed(replayed[0]) is None and ctrl.feed(replayed[1]) is None
    assert ctrl.receiver.rejection_counts() == {"stale_freshness": 1}


def test_restarted_controller_is_accepted_without_any_state() -> None:
    plant, ctrl, ptx, ctx = pair()
    for cycle in range(5):
        sync(plant, ptx, ctrl, cycle)
        for m in ctrl.protect([torque(ctx, cycle)], cycle):
            plant.feed(m, cycle)
    fresh = ControllerSecOc(CODEC, keys())
    sync(plant, ptx, fresh, 5)
    tq, auth = fresh.protect([torque(Transmitter(CODEC), 5)], 5)
    plant.feed(tq, 5)
    assert plant.feed(auth, 5) is tq


def test_wrong_key_never_verifies() -> None:
    plant = pair()[0]
    intruder = ControllerSecOc(CODEC, SecOcKeys(KEY_B, KEY_B, "x"))
    intruder.receiver.trip = 5
    for m in intruder.protect([torque(Transmitter(CODEC), 0)], 0):
        plant.feed(m, 0)
    assert plant.receiver.rejection_counts() == {"bad_mac": 1}


def test_observer_labels_frames() -> None:
    plant, ctrl, ptx, ctx = pair()
    obs = SecOcObserver(CODEC, keys())
    burst = plant.protect([ptx.message("DRIVER_INPUTS", {}),
                           ptx.message("SYNC", {"CYCLE": 1})], 1)
    labels = [obs.observe(m)[0] for m in burst]
    for m in burst:
        ctrl.feed(m)
    out = ctrl.protect([torque(ctx, 1)], 1)
    labels += [obs.observe(m)[0] for m in out]
    # the driver frame and its authenticator wait for the SYNC of their burst
    assert labels == ["pending", "pending", "pending", "authenticated 0x10F", "pending",
                      "authenticated 0x080"]
    assert obs.observe(out[1])[0].startswith("REJECTED")


# ------------------------------------------------------------------------------------- keys
def write_key_file(path: Path, mode: int) -> Path:
    path.write_text(f'ctrl_to_plant = "{KEY_A.hex()}"\nplant_to_ctrl = "{KEY_B.hex()}"\n')
    os.chmod(path, mode)
    return path


def test_key_file_readable_by_others_is_refused(tmp_path: Path) -> None:
    path = write_key_file(tmp_path / "keys.toml", 0o644)
    with pytest.raises(SecOcKeyError, match="group/others") as exc:
        load_keys(str(path))
    assert KEY_A.hex() not in str(exc.value)
    os.chmod(path, stat.S_IRUSR | stat.S_IWUSR)
    loaded = load_keys(str(path))
    assert loaded.ctrl_to_plant == KEY_A and loaded.plant_to_ctrl == KEY_B
    assert KEY_A.hex() not in repr(loaded) and str(list(KEY_A)) not in repr(loaded)


def test_bad_key_files_and_variables_give_one_line_errors(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    short = tmp_path / "short.toml"
    short.write_text('ctrl_to_plant = "00ff"\nplant_to_ctrl = "00ff"\n')
    os.chmod(short, 0o600)
    with pytest.raises(SecOcKeyError, match="expected 128"):
        load_keys(str(short))
    with pytest.raises(SecOcKeyError, match="No such file"):
        load_keys(str(tmp_path / "missing.toml"))
    monkeypatch.delenv(ENV_CTRL_TO_PLANT, raising=False)
    monkeypatch.delenv(ENV_PLANT_TO_CTRL, raising=False)
    with pytest.raises(SecOcKeyError, match="not set"):
        load_keys("env")
    monkeypatch.setenv(ENV_CTRL_TO_PLANT, KEY_A.hex())
    monkeypatch.setenv(ENV_PLANT_TO_CTRL, "zz" * 16)
    with pytest.raises(SecOcKeyError, match="not a hex"):
        load_keys("env")
    monkeypatch.setenv(ENV_PLANT_TO_CTRL, KEY_B.hex())
    assert load_keys("env").plant_to_ctrl == KEY_B
    assert ci_test_keys().is_test_key and not load_keys("env").is_test_key


def test_corrupt_trip_counter_is_refused(tmp_path: Path) -> None:
    state = tmp_path / "trip"
    state.write_text("garbage\n")
    with pytest.raises(SecOcKeyError, match="refusing"):
        TripCounter(state).next_trip()
    assert TripCounter(None).next_trip() == 1


# ------------------------------------------------------------------------------ bit flips
@pytest.mark.parametrize(("spec", "frame"), [("mac-flip:100%", "WHEEL_TORQUE_AUTH"),
                                             ("payload-flip:100%", "WHEEL_TORQUE_CMD")])
def test_flip_faults_keep_e2e_valid_but_break_the_mac(spec: str, frame: str) -> None:
    plant, ctrl, ptx, ctx = pair()
    sync(plant, ptx, ctrl, 0)
    frames = ctrl.protect([torque(ctx, 0)], 0)
    injector = FaultInjector(CODEC, parse_faults([spec]), seed=1)
    out = injector.apply(frames, 0.0)
    changed = [m for m, o in zip(frames, out, strict=True) if bytes(m.data) != bytes(o.data)]
    assert [CODEC.by_id[m.arbitration_id].name for m in changed] == [frame]
    assert all(isinstance(CODEC.decode_message(m), Decoded) for m in out)  # CRC still valid
    assert [plant.feed(m, 0) for m in out] == [None, None]
    assert plant.receiver.rejection_counts() == {"bad_mac": 1}


def test_harness_refuses_bad_keys_with_one_line(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    from harness.cli import main

    path = write_key_file(tmp_path / "keys.toml", 0o640)
    with pytest.raises(SystemExit) as info:  # argparse-style usage error: exit 2
        main(["run", "dlc-paper", "--controller", "lmpc", "--out", str(tmp_path / "run"),
              "--secoc-keys", str(path)])
    code = info.value.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "group/others" in err
    assert KEY_A.hex() not in err and not (tmp_path / "run" / "bus.blf").exists()


@given(st.lists(st.tuples(st.sampled_from([0x080, 0x081, 0x090, 0x092, 0x10F, 0x110, 0x7FF]),
                          st.binary(min_size=0, max_size=8), st.booleans()),
                max_size=60))
@settings(max_examples=200, deadline=None)
def test_random_frames_never_raise_and_never_verify(frames: list[tuple[int, bytes, bool]]
                                                    ) -> None:
    plant, ctrl, _, _ = pair()
    ctrl.receiver.trip = 5
    for k, (fid, data, remote) in enumerate(frames):
        msg = can.Message(arbitration_id=fid, data=data, is_extended_id=False,
                          is_remote_frame=remote)
        out_p, out_c = plant.feed(msg, k), ctrl.feed(msg)
        # released: only frames the receiver does not secure, or a remote frame of a data ID
        # (left to the E2E layer, which rejects it)
        for out, data_ids, auth_ids in ((out_p, {0x080, 0x090}, {0x081, 0x092}),
                                        (out_c, {0x10F}, {0x110})):
            if out is not None:
                assert fid not in auth_ids and (fid not in data_ids or remote)
    assert plant.receiver.accepted == 0 and ctrl.receiver.accepted == 0


# ------------------------------------------------------------- driver and sensor frames
def sensor_burst(ptx: Transmitter, cycle: int, yaw: float = 3.0) -> list[can.Message]:
    """A plant burst: driver and sensor frames, SYNC last."""
    return [ptx.message("DRIVER_INPUTS", {"SWA": 15.0, "STAB_ENABLE": 1.0}),
            ptx.message("MOTION_SENSORS", {"YAW_RATE": yaw, "AY": 1.0}),
            ptx.message("WHEEL_SPEEDS", {"WS_FL": 50.0, "WS_FR": 50.0}),
            ptx.message("VEHICLE_EST", {"VX_EST": 18.0}),
            ptx.message("SYNC", {"CYCLE": cycle, "SIM_TIME": cycle / 100})]


def deliver(ctrl: ControllerSecOc, frames: list[can.Message]) -> list[can.Message]:
    """Feed ``frames``; the frames the node would process, released data first."""
    out: list[can.Message] = []
    for m in frames:
        got = ctrl.feed(m)
        if got is not None:
            out += [*ctrl.released_data, got]
    return out


def test_sensor_frames_are_released_with_their_authentic_sync() -> None:
    plant, ctrl, ptx, _ = pair()
    for cycle in range(3):
        burst = plant.protect(sensor_burst(ptx, cycle), cycle)
        assert len(burst) == 10  # every frame followed by its authenticator
        names = [CODEC.by_id[m.arbitration_id].name for m in deliver(ctrl, burst)]
        assert names == ["DRIVER_INPUTS", "MOTION_SENSORS", "WHEEL_SPEEDS", "VEHICLE_EST",
                         "SYNC"], cycle
    assert ctrl.receiver.rejection_counts() == {}
    assert ctrl.summary()["accepted"]["MOTION_SENSORS"] == 3


def test_forged_sensor_frame_is_dropped_and_counted_per_frame() -> None:
    """A rogue's MOTION_SENSORS (valid CRC16 and counter, no key) with a forged
    authenticator never reaches the node; the genuine frame of the cycle does."""
    plant, ctrl, ptx, _ = pair()
    rogue = Transmitter(CODEC)
    burst = plant.protect(sensor_burst(ptx, 7), 7)
    forged = rogue.message("MOTION_SENSORS", {"YAW_RATE": -90.0})
    forged_auth = rogue.message("MOTION_SENSORS_AUTH", {"FV_LO": float(7 << 8), "MAC": 1234.0})
    out = deliver(ctrl, [forged, forged_auth, *burst])
    motions = [m for m in out if CODEC.by_id[m.arbitration_id].name == "MOTION_SENSORS"]
    assert len(motions) == 1 and bytes(motions[0].data) == bytes(burst[2].data)
    assert ctrl.summary()["rejected_by_frame"] == {
        "MOTION_SENSORS": {"bad_mac": 1, "unauthenticated": 1}}
    # a forged frame alone (no authenticator): dropped at its burst's SYNC
    out = deliver(ctrl, [rogue.message("DRIVER_INPUTS", {"ACCEL_PEDAL": 100.0}),
                         *plant.protect(sensor_burst(ptx, 8), 8)])
    assert sum(CODEC.by_id[m.arbitration_id].name == "DRIVER_INPUTS" for m in out) == 1
    assert ctrl.summary()["rejected_by_frame"]["DRIVER_INPUTS"] == {"unauthenticated": 1}


def test_controller_summary_accounts_for_every_secured_frame_received() -> None:
    """Received = accepted + rejected + pending, per data frame and per authenticator: a
    genuine burst, a forged pair, and a forged pair still held when the counts are read."""
    plant, ctrl, ptx, _ = pair()
    rogue = Transmitter(CODEC)
    forged = [rogue.message("MOTION_SENSORS", {"YAW_RATE": -90.0}),
              rogue.message("MOTION_SENSORS_AUTH", {"FV_LO": float(7 << 8), "MAC": 1234.0})]
    deliver(ctrl, [*forged, *plant.protect(sensor_burst(ptx, 7), 7), *forged])
    sec = ctrl.summary()
    assert sec["received"]["MOTION_SENSORS"] == sec["authenticators_received"][
        "MOTION_SENSORS"] == 3
    assert sec["accepted"]["MOTION_SENSORS"] == 1
    assert sec["rejected_by_frame"]["MOTION_SENSORS"] == {"bad_mac": 1, "unauthenticated": 1}
    # the second pair, held for its SYNC: one data frame, one authenticator
    assert sec["pending"]["MOTION_SENSORS"] == sec["pending_authenticators"][
        "MOTION_SENSORS"] == 1
    assert sec["pending"]["DRIVER_INPUTS"] == 0
    assert_frames_add_up(sec)


def assert_frames_add_up(sec: dict) -> None:
    """Per secured data frame, every data frame and every authenticator received is counted
    once: accepted, rejected by a reason of its kind, pending, or passed to the E2E layer."""
    for name, received in sec["received"].items():
        r = sec["rejected_by_frame"].get(name, {})
        pairs = sec["accepted"][name] + r.get("replay", 0) + r.get("stale_freshness", 0)
        assert received == pairs + r.get("unauthenticated", 0) + sec["pending"][name] \
            + sec["to_e2e"][name], (name, sec)
        assert sec["authenticators_received"][name] == pairs + r.get("bad_mac", 0) \
            + r.get("orphan_auth", 0) + r.get("unchecked_auth", 0) \
            + sec["pending_authenticators"][name], (name, sec)


def test_counters_add_up_with_a_wrong_key() -> None:
    """A controller with another key than the plant's: 300 SYNC received are 300 bad_mac
    authenticators plus 300 data frames (unauthenticated or still pending), not 600
    rejections of 300 frames; the held driver and sensor authenticators are unchecked_auth."""
    plant, _, ptx, _ = pair()
    wrong = ControllerSecOc(CODEC, SecOcKeys(b"\x01" * 16, b"\x02" * 16, "test"))
    for cycle in range(300):
        deliver(wrong, plant.protect(sensor_burst(ptx, cycle), cycle))
    sec = wrong.summary()
    r = sec["rejected_by_frame"]
    assert sec["received"]["SYNC"] == sec["authenticators_received"]["SYNC"] == 300
    assert r["SYNC"]["bad_mac"] == 300
    assert r["SYNC"]["unauthenticated"] + sec["pending"]["SYNC"] == 300
    assert r["DRIVER_INPUTS"]["unauthenticated"] + sec["pending"]["DRIVER_INPUTS"] == 300
    assert r["DRIVER_INPUTS"]["unchecked_auth"] \
        + sec["pending_authenticators"]["DRIVER_INPUTS"] == 300
    assert_frames_add_up(sec)


def test_replayed_sensor_frames_are_rejected() -> None:
    plant, ctrl, ptx, _ = pair()
    old = plant.protect(sensor_burst(ptx, 3), 3)
    assert len(deliver(ctrl, old)) == 5
    new = plant.protect(sensor_burst(ptx, 4), 4)
    # the recorded data frames and authenticators of cycle 3 replayed before cycle 4's burst
    out = deliver(ctrl, old[:8] + new)
    assert len(out) == 5 and [bytes(m.data) for m in out] == [bytes(m.data) for m in new[::2]]
    assert ctrl.receiver.rejection_counts() == {"replay": 4}


def test_payload_changed_with_valid_crc_fails_the_mac() -> None:
    plant, ctrl, ptx, _ = pair()
    burst = plant.protect(sensor_burst(ptx, 2), 2)
    changed = bytearray(burst[2].data)
    changed[4] ^= 0x01  # a yaw-rate bit
    CODEC.seal(burst[2].arbitration_id, changed)
    assert isinstance(CODEC.decode(burst[2].arbitration_id, bytes(changed)), Decoded)
    burst[2] = can.Message(arbitration_id=burst[2].arbitration_id, data=bytes(changed),
                           is_extended_id=False)
    out = deliver(ctrl, burst)
    assert [CODEC.by_id[m.arbitration_id].name for m in out] == [
        "DRIVER_INPUTS", "WHEEL_SPEEDS", "VEHICLE_EST", "SYNC"]
    # its authenticator fails (bad_mac), the changed frame is dropped at the SYNC
    assert ctrl.summary()["rejected_by_frame"] == {
        "MOTION_SENSORS": {"bad_mac": 1, "unauthenticated": 1}}


def test_burst_of_a_lost_sync_is_verified_with_the_next_sync() -> None:
    """Frames whose SYNC was lost wait (bounded) and verify with the next authentic SYNC:
    both cycles' frames are released, in order, none counted as an attack."""
    plant, ctrl, ptx, _ = pair()
    first = plant.protect(sensor_burst(ptx, 10), 10)
    second = plant.protect(sensor_burst(ptx, 11), 11)
    out = deliver(ctrl, first[:8] + second)  # SYNC 10 and its authenticator lost
    names = [CODEC.by_id[m.arbitration_id].name for m in out]
    assert names.count("MOTION_SENSORS") == 2 and names[-1] == "SYNC"
    assert ctrl.receiver.rejection_counts() == {}


def test_plant_restart_sensor_frames_verify_with_the_new_trip() -> None:
    plant, ctrl, ptx, _ = pair()
    assert len(deliver(ctrl, plant.protect(sensor_burst(ptx, 500), 500))) == 5
    restarted = PlantSecOc(CODEC, keys(), trip=6)
    out = deliver(ctrl, restarted.protect(sensor_burst(Transmitter(CODEC), 0), 0))
    assert len(out) == 5 and ctrl.trip == 6 and ctrl.receiver.resyncs == 1
    assert ctrl.receiver.rejection_counts() == {}


def test_corrupted_sensor_frame_goes_to_the_e2e_layer_as_a_fault() -> None:
    """A sensor frame with a bad CRC is handed on at once (the rx monitor rejects it as
    bad_crc, a fault), not held to fail its MAC as if it were an attack."""
    plant, ctrl, ptx, _ = pair()
    burst = plant.protect(sensor_burst(ptx, 4), 4)
    bad = bytearray(burst[2].data)
    bad[0] ^= 0xFF
    corrupted = can.Message(arbitration_id=burst[2].arbitration_id, data=bytes(bad),
                            is_extended_id=False)
    assert ctrl.feed(corrupted) is corrupted
    out = deliver(ctrl, [*burst[:2], *burst[3:]])
    assert "MOTION_SENSORS" not in [CODEC.by_id[m.arbitration_id].name for m in out]
    assert ctrl.receiver.rejection_counts() == {"orphan_auth": 1}


def test_with_a_known_trip_sensor_frames_are_released_before_their_sync() -> None:
    """Once a SYNC has told the trip, a sensor frame is released when its authenticator
    arrives (not inside the SYNC's turnaround); a forged one still waits and is counted."""
    plant, ctrl, ptx, _ = pair()
    deliver(ctrl, plant.protect(sensor_burst(ptx, 20), 20))
    burst = plant.protect(sensor_burst(ptx, 21), 21)
    rogue = Transmitter(CODEC)
    forged = [rogue.message("MOTION_SENSORS", {"YAW_RATE": 50.0}),
              rogue.message("MOTION_SENSORS_AUTH", {"FV_LO": float(21 << 8), "MAC": 7.0})]
    early = [got for m in [*forged, *burst[:8]] if (got := ctrl.feed(m)) is not None]
    assert [bytes(m.data) for m in early] == [bytes(m.data) for m in burst[:8:2]]
    assert ctrl.feed(burst[8]) is None and ctrl.feed(burst[9]) is burst[8]  # the SYNC
    assert ctrl.released_data == []
    assert ctrl.summary()["rejected_by_frame"] == {
        "MOTION_SENSORS": {"bad_mac": 1, "unauthenticated": 1}}


def test_history_forgets_the_oldest_and_a_wrapped_replay_fails_its_mac() -> None:
    """The receiver remembers the last HISTORY (4096) accepted freshness values per ID, the
    oldest forgotten first: a replay of a remembered frame is a ``replay``. A frame 4096
    cycles old has the same FV_LO as the current cycle's (20 bits = 12 bits of cycle and 8
    of index), so its freshness reconstructs to the current cycle and its MAC fails."""
    plant, ctrl, _ptx, ctx = pair()
    sync(plant, _ptx, ctrl, 0)
    first = ctrl.protect([torque(ctx, 0)], 0)
    assert plant.feed(first[0], 0) is None and plant.feed(first[1], 0) is first[0]
    recent = first
    for cycle in range(1, HISTORY + 1):
        recent = ctrl.protect([torque(ctx, cycle)], cycle)
        plant.feed(recent[0], cycle)
        assert plant.feed(recent[1], cycle) is recent[0]
    stream = plant.receiver.streams[first[0].arbitration_id]
    assert len(stream.history) == HISTORY and len(stream.seen) == HISTORY
    for msg in recent:
        plant.feed(msg, HISTORY)
    for msg in first:
        plant.feed(msg, HISTORY)
    assert first[0].arbitration_id == recent[0].arbitration_id
    assert plant.receiver.rejection_counts() == {"replay": 1, "bad_mac": 1}


def test_non_data_frames_on_a_deferred_id_go_to_the_e2e_layer() -> None:
    """A remote, error or extended-ID frame on a held sensor ID is handed on at once (the
    rx monitor rejects it as not_data_frame); on that ID's authenticator ID it is dropped."""
    _plant, ctrl, _ptx, _ = pair()
    sensors = CODEC.messages["MOTION_SENSORS"].frame_id
    auth = CODEC.messages["MOTION_SENSORS_AUTH"].frame_id
    remote = can.Message(arbitration_id=sensors, is_remote_frame=True, is_extended_id=False)
    extended = can.Message(arbitration_id=auth, data=bytes(8), is_extended_id=True)
    assert ctrl.feed(remote) is remote
    assert ctrl.feed(extended) is None
    assert ctrl.receiver.rejection_counts() == {}


