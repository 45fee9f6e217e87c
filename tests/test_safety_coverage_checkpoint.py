"""Checkpoints with a small stand-in controller: every refusal reason of a restore, the
header checks, the durability helper and the manager's counters (fast, no MPC)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from controller.registry import make_controller
from controller.runtime import checkpoint as ck
from controller.runtime.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    HEADER_KEY,
    CheckpointManager,
    RestoreResult,
    config_hash,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from tests.helpers_durable import record_durable_calls

HASH = "0123456789abcdef"


class Model:
    """Adaptive model stand-in: records whether its pending prediction was dropped."""

    def __init__(self) -> None:
        self.forgotten = 0

    def forget_record(self) -> None:
        self.forgotten += 1


class Tiny:
    """A Checkpointable with one array, one scalar and one array a cold start holds NaN in."""

    name = "tiny"
    ts = 0.05

    def __init__(self) -> None:
        self.model = Model()
        self.reset()

    def reset(self) -> None:
        self.w = np.zeros(3)
        self.gain = 0.0
        self.pending = np.full(2, np.nan)
        self.resets = getattr(self, "resets", -1) + 1

    def get_state(self) -> dict[str, np.ndarray | float]:
        return {"w": self.w.copy(), "gain": self.gain, "pending": self.pending.copy()}

    def set_state(self, d: dict[str, np.ndarray | float]) -> None:
        self.w = np.array(d["w"])
        self.gain = d["gain"]
        self.pending = np.array(d["pending"])


def learned() -> Tiny:
    t = Tiny()
    t.w = np.array([1.0, -2.5, 3.25])
    t.gain = 0.125
    t.pending = np.array([np.nan, 4.0])
    return t


def write_npz(path: Path, header: object | None, arrays: dict[str, np.ndarray]) -> None:
    """A checkpoint-like file written by hand (header: JSON-able, or None for none)."""
    data = dict(arrays)
    if header is not None:
        data[HEADER_KEY] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with path.open("wb") as fh:
        np.savez(fh, **data)


def good_header(**over: object) -> dict[str, object]:
    h: dict[str, object] = {"format": FORMAT, "version": FORMAT_VERSION, "controller": "tiny",
                            "config_hash": HASH, "steps": 7, "scalars": ["gain"]}
    h.update(over)
    return h


def good_arrays() -> dict[str, np.ndarray]:
    return {"w": np.array([1.0, 2.0, 3.0]), "gain": np.array(0.5),
            "pending": np.array([np.nan, 1.0])}


# ------------------------------------------------------------------------ round trip
def test_round_trip_restores_arrays_scalars_and_steps(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    src = learned()
    save_checkpoint(path, src, cfg_hash=HASH, steps=42)
    header, data = read_checkpoint(path)
    assert header == {"format": FORMAT, "version": FORMAT_VERSION, "controller": "tiny",
                      "config_hash": HASH, "steps": 42, "scalars": ["gain"]}
    assert set(data) == {"w", "gain", "pending"}
    assert all(a.dtype == np.float64 for a in data.values())
    dst = Tiny()
    result = load_checkpoint(path, dst, cfg_hash=HASH)
    assert result == RestoreResult(True, f"restored {path} (42 MPC steps learned)", 42)
    assert dst.w.tolist() == [1.0, -2.5, 3.25]
    assert type(dst.gain) is float and dst.gain == 0.125
    assert np.isnan(dst.pending[0]) and dst.pending[1] == 4.0
    assert dst.model.forgotten == 1                     # the pending prediction is dropped
    assert not list(tmp_path.glob("*.tmp"))


def test_the_config_hash_is_not_checked_when_not_given(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned(), cfg_hash="other", steps=1)
    assert load_checkpoint(path, Tiny()).restored
    assert load_checkpoint(path, Tiny(), cfg_hash="other").restored
    r = load_checkpoint(path, Tiny(), cfg_hash=HASH)
    assert not r.restored and "config hash 'other', expected '0123456789abcdef'" in r.reason


def test_a_controller_without_an_adaptive_model_restores_too(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned(), cfg_hash=HASH, steps=0)
    plain = Tiny()
    plain.model = None  # type: ignore[assignment]
    assert load_checkpoint(path, plain, cfg_hash=HASH).restored
    odd = Tiny()
    odd.model = type("M", (), {"forget_record": 5})()  # type: ignore[assignment]
    assert load_checkpoint(path, odd, cfg_hash=HASH).restored   # not callable: skipped


def test_the_reserved_header_key_cannot_be_a_state_key(tmp_path: Path) -> None:
    t = Tiny()
    t.get_state = lambda: {HEADER_KEY: 1.0}  # type: ignore[method-assign]
    with pytest.raises(ValueError, match="reserved"):
        save_checkpoint(tmp_path / "c.npz", t, cfg_hash=HASH, steps=0)
    assert not list(tmp_path.iterdir())


def test_a_failed_write_removes_its_temp_file_and_keeps_the_old_checkpoint(tmp_path: Path
                                                                           ) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned(), cfg_hash=HASH, steps=3)
    old = path.read_bytes()

    def boom(tmp: Path) -> None:
        assert tmp.exists() and tmp.name.startswith(".c.npz.") and tmp.suffix == ".tmp"
        assert tmp.parent == path.parent    # same directory: the rename is atomic
        raise KeyboardInterrupt   # any BaseException

    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, Tiny(), cfg_hash=HASH, steps=4, _before_replace=boom)
    assert path.read_bytes() == old and sorted(tmp_path.iterdir()) == [path]


def test_a_checkpoint_in_the_working_directory(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    save_checkpoint("c.npz", learned(), cfg_hash=HASH, steps=2)
    assert load_checkpoint("c.npz", Tiny(), cfg_hash=HASH).steps == 2


def test_config_hash_names_controller_and_configuration() -> None:
    h = config_hash("nmpc-rhonn")
    assert len(h) == 16 and int(h, 16) >= 0
    assert config_hash("nmpc-rhonn") == h           # deterministic
    assert config_hash("lmpc") != h                 # the name is part of it


def test_config_hash_ignores_the_order_of_tables_and_keys(tmp_path: Path) -> None:
    """The same configuration written in another order is the same configuration: its
    checkpoints stay valid."""
    text = (Path(ck.__file__).parents[1] / "config" / "default.toml").read_text()
    head, *tables = text.split("\n[")
    reordered = tmp_path / "reordered.toml"
    reordered.write_text(head + "".join("\n[" + t for t in reversed(tables)))
    same = tmp_path / "same.toml"
    same.write_text(text)
    assert config_hash("nmpc-rhonn", reordered) == config_hash("nmpc-rhonn", same)
    changed = tmp_path / "changed.toml"
    changed.write_text(text.replace("ts_s = 0.05", "ts_s = 0.04", 1))
    assert config_hash("nmpc-rhonn", changed) != config_hash("nmpc-rhonn", same)


def test_keyword_only_parameters_stay_keyword_only(tmp_path: Path) -> None:
    """cfg_hash and steps are keywords: a positional call cannot swap them."""
    with pytest.raises(TypeError):
        save_checkpoint(tmp_path / "c.npz", Tiny(), HASH, 3)  # type: ignore[misc]
    with pytest.raises(TypeError):
        load_checkpoint(tmp_path / "c.npz", Tiny(), HASH)  # type: ignore[misc]
    with pytest.raises(TypeError):
        CheckpointManager(tmp_path / "c.npz", Tiny(), HASH, 5)  # type: ignore[misc]
    assert not list(tmp_path.iterdir())


def test_restore_result_has_a_fixed_set_of_fields() -> None:
    r = RestoreResult(True, "ok", 3)
    with pytest.raises(AttributeError):
        r.extra = 1  # type: ignore[attr-defined]


def test_pickled_arrays_are_never_loaded(tmp_path: Path) -> None:
    """Object arrays need pickle, and unpickling runs code: the file is unreadable."""
    path = tmp_path / "c.npz"
    arrays = {**good_arrays(), "w": np.array([1.0, "x", None], dtype=object)}
    data = {**arrays, HEADER_KEY: np.frombuffer(json.dumps(good_header()).encode(),
                                                dtype=np.uint8)}
    with path.open("wb") as fh:
        np.savez(fh, **data)
    r = load_checkpoint(path, Tiny(), cfg_hash=HASH)
    assert not r.restored and "unreadable" in r.reason and "allow_pickle" in r.reason


# ------------------------------------------------------------------ refusal reasons
@pytest.mark.parametrize(("header", "arrays", "words"), [
    (good_header(format="other"), good_arrays(), "format 'other' version 1"),
    (good_header(version=FORMAT_VERSION + 1), good_arrays(), f"version {FORMAT_VERSION + 1}"),
    (good_header(controller="lmpc"), good_arrays(), "controller 'lmpc', expected 'tiny'"),
    (good_header(config_hash="ffff"), good_arrays(), "config hash 'ffff'"),
    (good_header(), {**good_arrays(), "extra": np.zeros(1)}, "unexpected ['extra']"),
    (good_header(), {k: v for k, v in good_arrays().items() if k != "w"}, "missing ['w']"),
    (good_header(), {**good_arrays(), "w": np.zeros(4)}, "w: shape (4,), expected (3,)"),
    (good_header(), {**good_arrays(), "w": np.zeros(3, dtype=np.float32)},
     "w: dtype float32, expected float64"),
    (good_header(), {**good_arrays(), "w": np.array([0.0, -np.inf, 0.0])},
     "w: infinite values"),
    (good_header(), {**good_arrays(), "w": np.array([0.0, np.nan, 0.0])}, "w: NaN values"),
    (good_header(steps=-1), good_arrays(), "bad step count -1"),
    (good_header(steps="7"), good_arrays(), "bad step count '7'"),
    (good_header(steps=None), good_arrays(), "bad step count None"),
])
def test_a_mismatched_checkpoint_is_ignored_with_its_reason(tmp_path: Path, header: dict,
                                                            arrays: dict, words: str) -> None:
    path = tmp_path / "c.npz"
    write_npz(path, header, arrays)
    ctrl = Tiny()
    result = load_checkpoint(path, ctrl, cfg_hash=HASH)
    assert not result.restored and result.steps == 0
    assert words in result.reason and "ignored" in result.reason
    assert result.reason.endswith("; cold start")
    assert ctrl.w.tolist() == [0.0] * 3 and ctrl.model.forgotten == 0


def test_a_matching_hand_written_checkpoint_is_restored(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    write_npz(path, good_header(steps=0), good_arrays())
    ctrl = Tiny()
    result = load_checkpoint(path, ctrl, cfg_hash=HASH)
    assert result.restored and result.steps == 0 and ctrl.gain == 0.5


@pytest.mark.parametrize(("header_bytes", "words"), [
    (None, "no header"),
    (np.frombuffer(b"[1, 2]", dtype=np.uint8), "header is not an object"),
    (np.frombuffer(b"{not json", dtype=np.uint8), "JSONDecodeError"),
    (np.zeros(3, dtype=np.float64), "no header"),
    (np.zeros((2, 2), dtype=np.uint8), "no header"),
])
def test_a_missing_or_malformed_header_is_unreadable(tmp_path: Path, header_bytes, words: str
                                                     ) -> None:
    path = tmp_path / "c.npz"
    data = good_arrays()
    if header_bytes is not None:
        data[HEADER_KEY] = header_bytes
    with path.open("wb") as fh:
        np.savez(fh, **data)
    with pytest.raises(ValueError):
        read_checkpoint(path)
    result = load_checkpoint(path, Tiny(), cfg_hash=HASH)
    assert not result.restored and "unreadable" in result.reason and words in result.reason


def test_garbage_and_absent_files_give_a_cold_start(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    path.write_bytes(b"not a zip")
    r = load_checkpoint(path, Tiny())
    assert not r.restored and r.reason.startswith(f"unreadable checkpoint {path}")
    r = load_checkpoint(tmp_path / "absent.npz", Tiny())
    assert r == RestoreResult(False, f"no checkpoint at {tmp_path / 'absent.npz'}: cold start")
    buf = io.BytesIO()
    np.savez(buf, w=np.zeros(3))
    path.write_bytes(buf.getvalue()[:-20])     # truncated zip
    assert "unreadable" in load_checkpoint(path, Tiny()).reason


def test_a_controller_that_cannot_describe_its_state_gets_a_cold_start(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned(), cfg_hash=HASH, steps=1)
    ctrl = Tiny()

    def broken() -> dict:
        raise RuntimeError("state unavailable")

    ctrl.get_state = broken  # type: ignore[method-assign]
    r = load_checkpoint(path, ctrl, cfg_hash=HASH)
    assert not r.restored and "cannot check: RuntimeError: state unavailable" in r.reason


def test_a_rejected_state_resets_the_controller(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned(), cfg_hash=HASH, steps=1)
    ctrl = Tiny()

    def refuse(d: dict) -> None:
        ctrl.w = np.ones(3)
        raise ValueError("nope")

    ctrl.set_state = refuse  # type: ignore[method-assign]
    r = load_checkpoint(path, ctrl, cfg_hash=HASH)
    assert not r.restored and "rejected by the controller (ValueError: nope)" in r.reason
    assert ctrl.w.tolist() == [0.0] * 3 and ctrl.resets == 1 and ctrl.model.forgotten == 0


# ------------------------------------------------------------------------ the manager
def test_manager_default_period_is_one_second_of_controller_time(tmp_path: Path) -> None:
    mgr = CheckpointManager(tmp_path / "c.npz", Tiny(), HASH)
    assert mgr.every_steps == 20
    assert CheckpointManager(tmp_path / "c.npz", Tiny(), HASH, every_steps=3).every_steps == 3
    assert CheckpointManager(tmp_path / "c.npz", Tiny(), HASH, every_steps=0).every_steps == 20
    slow = Tiny()
    slow.ts = 2.0
    assert CheckpointManager(tmp_path / "c.npz", slow, HASH).every_steps == 1


def test_manager_saves_every_n_mpc_steps_only(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    msgs: list[str] = []
    mgr = CheckpointManager(path, learned(), HASH, every_steps=3, report=msgs.append)
    want = {"path": str(path), "restored": False, "restore_reason": None, "steps": 0,
            "saves": 0, "save_failures": 0, "last_error": None}
    summary = mgr.summary()
    assert {k: summary[k] for k in want} == want
    saved = [mgr.after_cycle(flag) for flag in
             (True, False, True, True, False, True, True, True)]
    assert saved == [False, False, False, True, False, False, False, True]
    assert mgr.steps == 6 and mgr.saves == 2 and read_checkpoint(path)[0]["steps"] == 6
    assert msgs == []


def test_manager_restore_removes_stale_temp_files_and_reports(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    save_checkpoint(path, learned(), cfg_hash=HASH, steps=9)
    stale = tmp_path / ".c.npz.abc123.tmp"
    stale.write_bytes(b"torn")
    other = tmp_path / ".d.npz.abc123.tmp"
    other.write_bytes(b"not ours")
    msgs: list[str] = []
    ctrl = Tiny()
    mgr = CheckpointManager(path, ctrl, HASH, report=msgs.append)
    result = mgr.restore()
    assert result.restored and mgr.steps == 9 and ctrl.gain == 0.125
    assert not stale.exists() and other.exists()
    assert msgs == [f"checkpoint: restored {path} (9 MPC steps learned)"]
    s = mgr.summary()
    assert s["restored"] is True and s["steps"] == 9 and s["restore_reason"] == result.reason
    assert mgr.after_cycle(True) is False and mgr.steps == 10


def test_manager_restore_in_the_working_directory(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / ".c.npz.x.tmp").write_bytes(b"")
    mgr = CheckpointManager("c.npz", Tiny(), HASH)
    assert not mgr.restore().restored
    assert not (tmp_path / ".c.npz.x.tmp").exists()
    assert mgr.summary()["restored"] is False


def test_manager_counts_and_reports_save_failures_and_keeps_going(tmp_path: Path) -> None:
    msgs: list[str] = []
    mgr = CheckpointManager(tmp_path / "absent" / "c.npz", learned(), HASH, every_steps=1,
                            report=msgs.append)
    assert mgr.after_cycle(True) is False and mgr.after_cycle(True) is False
    assert mgr.save_failures == 2 and mgr.saves == 0
    assert mgr.last_error is not None and mgr.last_error.startswith("FileNotFoundError")
    assert len(msgs) == 2 and "failed: FileNotFoundError" in msgs[0]
    assert mgr.summary()["save_failures"] == 2
    quiet = CheckpointManager(tmp_path / "absent" / "c.npz", learned(), HASH)
    assert quiet.save() is False     # the default report is silent


def test_a_blocked_manager_does_not_save_and_reports_once(tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    msgs: list[str] = []
    mgr = CheckpointManager(path, learned(), HASH, every_steps=1, report=msgs.append)
    assert mgr.blocked_by() is None                  # not blocked by default
    mgr.blocked_by = lambda: "core fault latched"
    assert mgr.after_cycle(True) is False
    assert len(msgs) == 1                            # reported at the first blocked save
    assert mgr.save() is False
    assert not path.exists() and mgr.saves == 0 and mgr.save_failures == 0
    assert mgr.blocked_saves == 2 and mgr.block_reason == "core fault latched"
    assert msgs == [f"checkpoint: not saved to {path} (core fault latched)"]
    s = mgr.summary()
    assert s["blocked_saves"] == 2 and s["block_reason"] == "core fault latched"
    mgr.blocked_by = lambda: None
    assert mgr.save() is True and path.exists() and mgr.saves == 1


def test_a_save_syncs_the_file_then_renames_then_syncs_the_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Durability: the temp file is fsynced before the rename and the directory after it,
    in that order, on every save (a save returning right after the rename would lose the
    checkpoint on a power cut)."""
    events = record_durable_calls(monkeypatch)
    controller = make_controller("passive")
    for _ in range(2):
        ck.save_checkpoint(tmp_path / "c.npz", controller, cfg_hash="h", steps=1)
    assert events == ["fsync file", "rename", "fsync dir"] * 2
