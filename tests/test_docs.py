"""The documentation: the site builds with every link and anchor resolved, the README stays a
short entry point whose links exist, and no development history sits outside CHANGELOG.md
and the decision records."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250
HISTORY = re.compile(r"session [0-9]|issue[- ]?[0-9]+", re.IGNORECASE)
HISTORY_ALLOWED = ("CHANGELOG.md", "docs/decisions/")


def _tracked_files() -> list[str]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout
    return [f for f in out.splitlines() if (ROOT / f).is_file()]


def test_the_site_builds_with_every_link_resolved(tmp_path: Path) -> None:
    # mkdocs.yml sets strict and turns every unresolved link, anchor and nav entry into a
    # warning, so a broken link fails the build (not with -q: it hides the warnings).
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                           "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "performance" / "index.html").is_file()


def test_the_readme_is_short_and_its_links_exist() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_MAX_LINES
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if not re.match(r"[a-z]+://", link)]
    assert local, "the README links to the docs"
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, missing


def test_the_readme_test_command_is_what_ci_runs() -> None:
    readme = (ROOT / "README.md").read_text()
    lines = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    tests = [line for line in lines if line.startswith(".venv/bin/python -m pytest")]
    assert len(tests) == 1  # the suite; the SocketCAN check (docs/vcan.md) runs after it
    assert f"```bash\n{tests[0]}\n```" in readme


def test_no_development_history_outside_the_changelog_and_decisions() -> None:
    hits = []
    for name in _tracked_files():
        if name.startswith(HISTORY_ALLOWED) or name == "tests/test_docs.py":
            continue
        if HISTORY.search(name):
            hits.append(f"{name}: file name")
            continue
        try:
            text = (ROOT / name).read_text()
        except UnicodeDecodeError:
            continue
        for lineno, line in enumerate(text.splitlines(), 1):
            if HISTORY.search(line):
                hits.append(f"{name}:{lineno}: {line.strip()[:100]}")
    assert not hits, "\n".join(hits)


def test_the_history_check_can_fail() -> None:
    assert HISTORY.search("as measured in session 4")
    assert HISTORY.search("guards (issue 12)")
    assert HISTORY.search("docs/benchmark-issue12.md")
    assert not HISTORY.search("the session's engine; an issue with the bus")
