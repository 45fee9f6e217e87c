"""The mutation run's module list (harness/tools/mutation.py) names files that exist: a test
file listed but absent would measure a module against fewer tests than the docs claim."""

from __future__ import annotations

from pathlib import Path

import pytest

from harness.tools.mutation import TARGETS

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_every_mutation_target_and_its_tests_exist(name: str) -> None:
    target = TARGETS[name]
    assert (ROOT / target.path).is_file(), target.path
    missing = [t for t in target.tests if not (ROOT / t.split("::")[0]).is_file()]
    assert not missing, f"{name}: {missing}"
