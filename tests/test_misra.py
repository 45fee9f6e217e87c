"""MISRA C:2012 gate of the C core (controller/native/misra_check.py, docs/misra.md).

cppcheck's MISRA add-on over controller/native/src; every violation must be in the recorded
baseline (controller/native/misra_baseline.txt, reasons per rule in docs/misra.md). Skipped
only when cppcheck is not installed (.ci/run installs it).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.append(str(REPO / "controller" / "native"))
import misra_check  # noqa: E402

needs_cppcheck = pytest.mark.skipif(shutil.which("cppcheck") is None,
                                    reason="cppcheck not installed (apt-get install -y cppcheck)")


@needs_cppcheck
@pytest.mark.timeout(600)
def test_the_core_has_no_misra_violation_beyond_the_deviation_list() -> None:
    found = misra_check.core_violations()
    new = misra_check.new_violations(misra_check.count(found), misra_check.read_baseline())
    assert not new, f"new MISRA C:2012 violations {{(rule, file): (found, accepted)}}: {new}"


def test_every_baselined_rule_has_its_reason_in_the_deviation_list() -> None:
    doc = (REPO / "docs" / "misra.md").read_text()
    rules = {rule for rule, _name in misra_check.read_baseline()}
    missing = sorted(r for r in rules if f"| {r} |" not in doc)
    assert not missing, f"rules in the baseline without a row in docs/misra.md: {missing}"


@needs_cppcheck
@pytest.mark.timeout(300)
def test_a_planted_violation_is_reported_as_new(tmp_path) -> None:
    """A copy of one module with a goto (a rule the core does not break) and an octal
    constant added: the gate names both, with their file."""
    src = tmp_path / "src"
    src.mkdir()
    for h in (REPO / "controller" / "native" / "src").glob("*.h"):
        shutil.copy(h, src)
    text = (REPO / "controller" / "native" / "src" / "pedal_map.c").read_text()
    text += ("\nint rh_planted(int a);\nint rh_planted(int a)\n{\n    if (a > 0) {\n"
             "        goto done;\n    }\n    a = 010;\ndone:\n    return a;\n}\n")
    (src / "pedal_map.c").write_text(text)
    found = misra_check.run_misra([src / "pedal_map.c"], [src])
    new = misra_check.new_violations(misra_check.count(found), misra_check.read_baseline())
    assert ("15.1", "pedal_map.c") in new and ("7.1", "pedal_map.c") in new, new
