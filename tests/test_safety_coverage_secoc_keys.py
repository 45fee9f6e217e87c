"""SecOC keys and the trip counter: every refusal path, without key bytes in any message."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from can_db.secoc_keys import (
    ENV_CTRL_TO_PLANT,
    ENV_PLANT_TO_CTRL,
    TEST_KEY_SOURCE,
    TRIP_BITS,
    SecOcKeyError,
    SecOcKeys,
    TripCounter,
    ci_test_keys,
    load_keys,
    resolve_key_source,
)

KEY_A = bytes(range(16))
KEY_B = bytes(range(16, 32))


def key_file(path: Path, text: str, mode: int = 0o600) -> Path:
    path.write_text(text)
    os.chmod(path, mode)
    return path


@pytest.mark.parametrize(("a", "b", "name"), [(b"\x00" * 15, KEY_B, "ctrl_to_plant"),
                                              (KEY_A, b"\x00" * 17, "plant_to_ctrl"),
                                              (b"", KEY_B, "ctrl_to_plant")])
def test_keys_must_be_128_bit(a: bytes, b: bytes, name: str) -> None:
    with pytest.raises(SecOcKeyError, match=f"{name} must be 128 bit"):
        SecOcKeys(a, b)


def test_the_public_test_key_is_recognised() -> None:
    keys = ci_test_keys()
    assert keys.is_test_key and keys.source == TEST_KEY_SOURCE
    assert len(keys.ctrl_to_plant) == len(keys.plant_to_ctrl) == 16
    assert keys.ctrl_to_plant != keys.plant_to_ctrl
    assert not SecOcKeys(KEY_A, KEY_B).is_test_key
    assert load_keys(TEST_KEY_SOURCE) == keys


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o610, 0o601, 0o620, 0o602])
def test_any_group_or_other_permission_is_refused(tmp_path: Path, mode: int) -> None:
    path = key_file(tmp_path / "k.toml",
                    f'ctrl_to_plant = "{KEY_A.hex()}"\nplant_to_ctrl = "{KEY_B.hex()}"\n', mode)
    with pytest.raises(SecOcKeyError, match=f"mode {mode:o}") as exc:
        load_keys(str(path))
    assert KEY_A.hex() not in str(exc.value)


def test_owner_only_key_file_loads_with_its_path_as_source(tmp_path: Path) -> None:
    path = key_file(tmp_path / "k.toml",
                    f'ctrl_to_plant = "{KEY_A.hex()}"\nplant_to_ctrl = " {KEY_B.hex()} "\n',
                    0o400)
    keys = load_keys(str(path))
    assert (keys.ctrl_to_plant, keys.plant_to_ctrl, keys.source) == (KEY_A, KEY_B, str(path))


@pytest.mark.parametrize(("text", "words"), [
    ("ctrl_to_plant = [", "unreadable (TOMLDecodeError)"),
    (f'plant_to_ctrl = "{KEY_B.hex()}"\n', "missing ctrl_to_plant"),
    (f'ctrl_to_plant = "{KEY_A.hex()}"\n', "missing plant_to_ctrl"),
    (f'ctrl_to_plant = "{KEY_A.hex()}"\nplant_to_ctrl = "xyz"\n', "plant_to_ctrl: not a hex"),
])
def test_malformed_key_files_are_refused_with_a_reason(tmp_path: Path, text: str, words: str
                                                       ) -> None:
    path = key_file(tmp_path / "k.toml", text)
    with pytest.raises(SecOcKeyError) as exc:
        load_keys(str(path))
    assert words in str(exc.value) and str(path) in str(exc.value)
    assert KEY_A.hex() not in str(exc.value) and KEY_B.hex() not in str(exc.value)


def test_a_binary_key_file_is_unreadable(tmp_path: Path) -> None:
    path = tmp_path / "k.toml"
    path.write_bytes(b"\xff\xfe\x00garbage")
    os.chmod(path, 0o600)
    with pytest.raises(SecOcKeyError, match="unreadable"):
        load_keys(str(path))


def test_a_directory_is_no_key_file(tmp_path: Path) -> None:
    d = tmp_path / "dir"
    d.mkdir(mode=0o700)
    with pytest.raises(SecOcKeyError, match="unreadable"):
        load_keys(str(d))


def test_environment_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV_CTRL_TO_PLANT, KEY_A.hex())
    monkeypatch.delenv(ENV_PLANT_TO_CTRL, raising=False)
    with pytest.raises(SecOcKeyError, match=f"not set: {ENV_PLANT_TO_CTRL} \\(set both"):
        load_keys("env")
    monkeypatch.setenv(ENV_PLANT_TO_CTRL, KEY_B.hex()[:-2])
    with pytest.raises(SecOcKeyError, match="120 bit, expected 128"):
        load_keys("env")
    monkeypatch.setenv(ENV_PLANT_TO_CTRL, KEY_B.hex())
    keys = load_keys("env")
    assert (keys.ctrl_to_plant, keys.plant_to_ctrl, keys.source) == (KEY_A, KEY_B, "env")


def test_key_source_resolution(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_CTRL_TO_PLANT, raising=False)
    monkeypatch.delenv(ENV_PLANT_TO_CTRL, raising=False)
    assert resolve_key_source(None) == TEST_KEY_SOURCE
    assert resolve_key_source("") == TEST_KEY_SOURCE
    assert resolve_key_source("/etc/keys.toml") == "/etc/keys.toml"
    monkeypatch.setenv(ENV_CTRL_TO_PLANT, KEY_A.hex())
    assert resolve_key_source(None) == "env"  # one variable: refused by load_keys, not the
    with pytest.raises(SecOcKeyError, match=f"not set: {ENV_PLANT_TO_CTRL} "):  # test key
        load_keys(resolve_key_source(None))
    monkeypatch.setenv(ENV_PLANT_TO_CTRL, KEY_B.hex())
    assert resolve_key_source(None) == "env"
    assert resolve_key_source("ci-test-key") == TEST_KEY_SOURCE
    monkeypatch.delenv(ENV_CTRL_TO_PLANT)
    assert resolve_key_source(None) == "env"
    with pytest.raises(SecOcKeyError, match=f"not set: {ENV_CTRL_TO_PLANT} "):
        load_keys(resolve_key_source(None))
    monkeypatch.delenv(ENV_PLANT_TO_CTRL)
    assert resolve_key_source(None) == TEST_KEY_SOURCE


# ------------------------------------------------------------------------- trip counter
def test_trip_counter_increments_and_persists(tmp_path: Path) -> None:
    path = tmp_path / "trip"
    assert [TripCounter(path).next_trip() for _ in range(3)] == [1, 2, 3]
    assert path.read_text() == "3\n"
    assert not (tmp_path / "trip.tmp").exists()
    counter = TripCounter(str(path))
    assert counter.value == 1 and counter.next_trip() == 4 and counter.value == 4


def test_trip_counter_without_a_file_is_always_one() -> None:
    counter = TripCounter(None)
    assert counter.path is None
    assert [counter.next_trip() for _ in range(3)] == [1, 1, 1]


def test_trip_counter_refuses_to_wrap(tmp_path: Path) -> None:
    path = tmp_path / "trip"
    path.write_text(f"{(1 << TRIP_BITS) - 2}\n")
    assert TripCounter(path).next_trip() == (1 << TRIP_BITS) - 1   # the last one
    with pytest.raises(SecOcKeyError, match="exhausted"):
        TripCounter(path).next_trip()
    assert path.read_text() == f"{(1 << TRIP_BITS) - 1}\n"       # not advanced


def test_unreadable_trip_counter_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "trip"
    path.mkdir()
    with pytest.raises(SecOcKeyError, match=r"unreadable \(IsADirectoryError\)"):
        TripCounter(path).next_trip()


def test_no_key_bytes_in_the_repr_and_keys_are_immutable() -> None:
    keys = SecOcKeys(KEY_A, KEY_B, "somewhere")
    text = repr(keys)
    assert "somewhere" in text
    for key in (KEY_A, KEY_B):
        assert repr(key) not in text and key.hex() not in text
    with pytest.raises(AttributeError):
        keys.ctrl_to_plant = KEY_B  # type: ignore[misc]


def test_the_trip_counter_width_is_the_wire_width() -> None:
    from can_db.codec import Codec

    signal = Codec().database.get_message_by_name("SYNC_AUTH").get_signal_by_name("TRIP")
    assert TRIP_BITS == signal.length == 20
