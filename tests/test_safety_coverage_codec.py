"""The codec refuses a DBC whose frames lack the E2E layout it relies on."""

from __future__ import annotations

from pathlib import Path

import pytest

from can_db.codec import Codec

HEAD = 'VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A B\n\n'


def dbc(tmp_path: Path, signals: str) -> Path:
    path = tmp_path / "t.dbc"
    path.write_text(HEAD + "BO_ 256 M: 8 A\n" + signals + "\n")
    return path


@pytest.mark.parametrize(("signals", "words"), [
    (' SG_ ALIVE : 8|4@1+ (1,0) [0|15] "" B\n', "every frame needs one of"),
    (' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n', "every frame needs one of"),
    (' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n SG_ CRC16 : 8|16@1+ (1,0) [0|65535] "" B\n'
     ' SG_ ALIVE : 24|4@1+ (1,0) [0|15] "" B\n', "every frame needs one of"),
    (' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n SG_ ALIVE : 12|4@1+ (1,0) [0|15] "" B\n',
     "must be bits 0..7"),
    (' SG_ CRC16 : 0|16@1+ (1,0) [0|65535] "" B\n SG_ ALIVE : 20|4@1+ (1,0) [0|15] "" B\n',
     "must be bits 0..15"),
    (' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n SG_ ALIVE : 8|4@1+ (1,0) [0|15] "" B\n'
     ' SG_ X : 23|8@0+ (1,0) [0|255] "" B\n', "only Intel byte order"),
])
def test_a_frame_without_the_e2e_layout_is_refused(tmp_path: Path, signals: str, words: str
                                                   ) -> None:
    with pytest.raises(ValueError, match=words):
        Codec(dbc(tmp_path, signals))


def test_a_frame_with_the_e2e_layout_is_accepted(tmp_path: Path) -> None:
    codec = Codec(dbc(tmp_path, ' SG_ CRC8 : 0|8@1+ (1,0) [0|255] "" B\n'
                                ' SG_ ALIVE : 8|4@1+ (1,0) [0|15] "" B\n'
                                ' SG_ X : 12|8@1+ (1,0) [0|255] "" B\n'))
    assert list(codec.messages) == ["M"]
