"""`rhonn-harness paper` and `benchmark` show their campaign's progress on stderr whether or
not it is a terminal (a tqdm bar on one, else a plain line at most every 10 s:
harness/campaign/runner.py, shown across processes for `campaign` in tests/test_campaign.py),
and not with -q. Before, `benchmark` with stderr redirected to a file printed nothing for
its whole campaign. The studies themselves are replaced here: what is tested is the choice
the command line makes."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from harness import cli


def _progress_asked(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, command: str, *flags: str
) -> bool:
    seen: dict[str, Any] = {}

    def fake_benchmark(
        out: Path,
        sections: Any,
        engine: Any = None,
        progress: Any = None,
        bar: bool = True,
        a_deg: float | None = None,
    ) -> dict[str, Any]:
        seen["progress"] = bar
        return {}

    def fake_paper(
        out: Path,
        jobs: int = 2,
        quick: bool = False,
        engine: Any = None,
        resume: bool = False,
        progress: bool = True,
    ) -> dict[str, Any]:
        seen["progress"] = progress
        return {"meta": {"runs": 0, "wall_time_s": 0.0}}

    monkeypatch.setattr(cli, "run_benchmark", fake_benchmark)
    monkeypatch.setattr(cli, "run_paper", fake_paper)
    assert cli.main([command, "--out", str(tmp_path / command), "--quick", *flags]) == 0
    return seen["progress"]


@pytest.mark.parametrize("command", ["benchmark", "paper"])
def test_progress_off_a_terminal_and_not_with_quiet(
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    command: str,
) -> None:
    assert not sys.stderr.isatty()  # captured by pytest: as a file or a pipe would be
    assert _progress_asked(monkeypatch, tmp_path, command) is True
    assert _progress_asked(monkeypatch, tmp_path, command, "-q") is False
    assert _progress_asked(monkeypatch, tmp_path, command) is True
