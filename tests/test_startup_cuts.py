"""What keeps the processes' start short: the hub does not import python-can, a process
parses the DBC and generates its pack/unpack functions once, and the start-up profiler
(harness/tools/startup_profile.py) measures a real process start."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import can
import pytest

from can_db import codegen
from can_db.codec import Codec, default_dbc_path
from can_db.transport import localbus, wire
from harness.tools import startup_profile
from harness.tools.startup_profile import Variant

HEAVY = ("can", "cantools", "numpy", "asammdf", "pandas")


def _imported_by(module: str) -> list[str]:
    """The HEAVY packages that importing ``module`` loads in a fresh interpreter."""
    code = (f"import json, sys, {module}; "
            f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                         text=True, timeout=60).stdout
    return json.loads(out)


def test_the_hub_process_imports_no_can_library() -> None:
    """The hub forwards bytes: python-can (whose import loads asammdf, pandas and numpy for
    its MF4 format) is not in its process; a node's module does load it."""
    assert _imported_by("can_db.transport.hub") == []
    assert "can" in _imported_by("can_db.transport.localbus")


def test_the_hub_and_the_nodes_share_one_wire_format() -> None:
    """localbus re-exports the wire module's names; its errors stay python-can errors that
    are also the wire's ChannelError."""
    for name in ("HEADER", "FLAG_CONTROL", "CTRL_HELLO", "CTRL_WELCOME", "MAX_PACKET",
                 "DEFAULT_QUEUE_KIB", "control_packet", "count_records"):
        assert getattr(localbus, name) is getattr(wire, name)
    with pytest.raises(localbus.LocalBusError, match="bad rhonncan channel") as info:
        localbus.check_channel("no spaces")
    assert isinstance(info.value, can.CanInitializationError)
    assert isinstance(info.value, wire.ChannelError)
    with pytest.raises(wire.ChannelError, match="bad rhonncan channel"):
        wire.check_channel("no/slash")


def test_codecs_of_one_process_share_the_parse_and_the_generated_functions() -> None:
    first, second = Codec(), Codec()
    assert first.database is second.database
    assert first._encoders.keys() == second._encoders.keys()
    for name, (_, enc, _) in first._encoders.items():
        assert second._encoders[name][1] is enc
    # the shared functions still encode the same frames
    name = next(iter(first.messages))
    assert first.encode(name, {}, 3) == second.encode(name, {}, 3)


def test_an_edited_dbc_is_parsed_again(tmp_path: Path) -> None:
    """The parse is keyed by the file's content: the same path with other bytes is a new
    database (tests and tools write DBC variants)."""
    path = tmp_path / "edited.dbc"
    text = default_dbc_path().read_text(encoding="cp1252")
    path.write_text(text, encoding="cp1252")
    original = Codec(path)
    path.write_text(text.replace("VERSION \"", "VERSION \"x", 1), encoding="cp1252")
    edited = Codec(path)
    assert edited.database is not original.database
    assert edited.database.version != original.database.version


def test_generated_functions_are_keyed_by_their_text_not_their_numbers() -> None:
    """0.0 and -0.0 are equal table entries but different code (the sign of a zero result):
    each gets its own function."""
    row = ("S", 0, 0xFF, 0, 0, 1.0, 0.0, -1.0, 300.0)
    negative_zero = (*row[:6], -0.0, *row[7:])
    assert row == negative_zero
    plain, signed = codegen.make_decoder([row]), codegen.make_decoder([negative_zero])
    assert plain is not signed
    assert plain is codegen.make_decoder([row])


def test_variant_specs() -> None:
    assert Variant.parse("cut=/tmp/tree,-asammdf,-pandas") == Variant(
        "cut", "/tmp/tree", ("asammdf", "pandas"))
    assert Variant.parse("installed=") == Variant("installed", None, ())
    for bad in ("noequals", "=dir", "x=dir,asammdf", "x=dir,-"):
        with pytest.raises(ValueError):
            Variant.parse(bad)


def test_the_profiler_measures_a_real_hub_start(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Starts of the hub, with and without python-can marked absent: a table row per
    variant, import costs from -X importtime, the JSON with the same rows."""
    out = tmp_path / "profile.json"
    assert startup_profile.main(["--repeat", "1", "--only", "hub", "--json", str(out),
                                 "--variant", "here=", "--variant", "nocan=,-can"]) == 0
    table = capsys.readouterr().out
    assert "hub [here]" in table and "hub [nocan]" in table
    rows = json.loads(out.read_text())["rows"]
    assert [r["process"] for r in rows] == ["hub [here]", "hub [nocan]"]
    for row in rows:
        assert row["n"] == 1 and row["failed"] == 0
        assert 0.0 < row["total_s"]["median"] <= row["total_s"]["max"] < 30.0
        assert 0.0 < row["imports_s"]["median"] < row["total_s"]["max"] + 1.0
        names = [name for name, _ in row["top_imports_s"]]
        assert len(names) == 10 and "can" not in names  # measured; python-can is not there
