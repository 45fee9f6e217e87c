"""The layout's rules, read from the code with the AST (DESIGN.md §2):

* dependencies point one way: can_db ← controller, can_db ← plant_sim, everything ← harness;
* controller never imports plant_sim or harness (it is deployed alone);
* controller.core never imports controller.runtime (the algorithm has no I/O);
* inside can_db: process plumbing (can_db.process) ← transport (can_db.transport) ← the CAN
  layer (codec, CRC, monitor, SecOC, faults) ← its CLI; plumbing and transport know no frame;
* no import circle between modules anywhere in the project.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("can_db", "controller", "plant_sim", "harness")
# can_db's own modules above its transport: the frame layer and its command line
CAN_LAYER = tuple(f"can_db.{p.stem}" for p in (ROOT / "can_db").glob("*.py")
                  if p.stem != "__init__")


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """Project modules that ``path`` imports (also lazily, inside functions)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            # resolve to the longest project module that prefixes the name
            parts = name.split(".")
            for k in range(len(parts), 0, -1):
                cand = ".".join(parts[:k])
                if cand in modules:
                    found.add(cand)
                    break
    return found


GRAPH = {m: _imports(p, _modules()) for m, p in _modules().items()}


def _violations(src_prefix: str, forbidden: tuple[str, ...]) -> list[str]:
    return sorted(f"{m} -> {d}" for m, deps in GRAPH.items()
                  if m == src_prefix or m.startswith(src_prefix + ".")
                  for d in deps if any(d == f or d.startswith(f + ".") for f in forbidden))


@pytest.mark.parametrize(("src", "forbidden"), [
    ("can_db", ("controller", "plant_sim", "harness")),
    ("controller", ("plant_sim", "harness")),
    ("plant_sim", ("controller", "harness")),
    ("controller.core", ("controller.runtime",)),
    ("can_db.process", ("can_db.transport", *CAN_LAYER)),
    ("can_db.transport", CAN_LAYER),
])
def test_dependency_direction(src: str, forbidden: tuple[str, ...]) -> None:
    assert _violations(src, forbidden) == []


def test_the_checker_sees_a_violation() -> None:
    """The rules above can fail: the runtime does import the core, the CAN layer's CLI does
    import the transport, and the transport does import the plumbing."""
    assert _violations("controller.runtime", ("controller.core",))
    assert _violations("can_db.cli", ("can_db.transport",))
    assert _violations("can_db.transport", ("can_db.process",))
    assert "can_db.codec" in CAN_LAYER and "can_db.secoc" in CAN_LAYER


def test_no_import_circle() -> None:
    # Tarjan's strongly connected components; a component of more than one module is a circle
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH.get(v, ()):
            if w == v:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(comp))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    assert circles == []
