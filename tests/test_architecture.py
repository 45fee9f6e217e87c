"""The layout's rules, read from the code with the AST (docs/architecture.md):

* dependencies point one way: can_db ← controller, can_db ← plant_sim, everything ← harness;
* controller never imports plant_sim or harness (it is deployed alone);
* the harness never imports the plant's process module (plant_sim.node and
  plant_sim.run_options are what it uses);
* controller.core never imports controller.runtime (the algorithm has no I/O);
* inside can_db: process plumbing (can_db.process) ← transport (can_db.transport) ← the CAN
  layer (codec, CRC, monitor, SecOC, faults) ← its CLI; plumbing and transport know no frame;
* no import circle between modules anywhere in the project;
* the harness's subpackages form a declared order (``HARNESS_ORDER``) and every import goes
  down it; no import circle between folders (packages) anywhere in the project;
* imports inside function bodies only for optional third-party packages (not in
  ``[project] dependencies``): never for project modules, the standard library or the core
  dependencies, so a module's dependencies are all on its first lines.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import tomllib
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


MODULES = _modules()
GRAPH = {m: _imports(p, MODULES) for m, p in MODULES.items()}


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
    # the harness starts the plant process and uses the plant's node and run options, never
    # the process module itself (its main, its loops)
    ("harness", ("plant_sim.process",)),
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


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of ``graph``: its strongly connected components (Tarjan) of more than
    one node."""
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
        for w in sorted(graph.get(v, ())):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def test_no_import_circle() -> None:
    assert _circles(GRAPH) == []


# --- folders and function-level imports -------------------------------------------------------

# The harness's subpackages, each with the subpackages it may import (its own always). ``run``
# starts processes and knows nothing else of the harness; analysis reads what a run wrote; viz
# draws analysis results; report carries out one run and writes its report (run → KPIs →
# plots → recording); campaigns run many runs and summarise them; the paper is campaigns and
# their tables; bench, fuzz and tools are leaves beside each other; the command line sits on top.
_FIVE = ("run", "analysis", "viz", "report", "campaign", "paper")
HARNESS_ORDER: dict[str, tuple[str, ...]] = {
    "run": (),
    "analysis": ("run",),
    "viz": ("analysis", "run"),
    "report": ("viz", "analysis", "run"),
    "campaign": ("report", "viz", "analysis", "run"),
    "paper": ("campaign", "report", "viz", "analysis", "run"),
    "bench": _FIVE,
    "fuzz": _FIVE,
    "tools": _FIVE,
    "cli": (*_FIVE, "bench", "fuzz", "tools"),
}


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The longest project module that prefixes ``name`` (None: not a project module)."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in modules:
            return ".".join(parts[:k])
    return None


def _sites(path: Path) -> list[tuple[int, str, tuple[str, ...], bool]]:
    """Every import statement of ``path`` (one per name of ``import a, b``): (line, the module
    it names, the names it may load - a ``from`` import's names may be modules -, inside a
    function body)."""
    found: list[tuple[int, str, tuple[str, ...], bool]] = []

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend((child.lineno, a.name, (a.name,), in_function) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = "." * child.level + (child.module or "")
                names = (base, *(f"{base}.{a.name}" for a in child.names if child.module))
                found.append((child.lineno, base, names, in_function))
            walk(child, in_function or isinstance(
                child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda))

    walk(ast.parse(path.read_text(), str(path)), False)
    return found


def _folder(module: str) -> str:
    """The package a module lives in (a package's ``__init__`` lives in the package itself)."""
    return module if MODULES[module].name == "__init__.py" else module.rpartition(".")[0]


def _folder_edges() -> list[tuple[str, int, str, str]]:
    """Imports that cross folders, from every file:
    (importing file, line, importing module, imported module)."""
    edges = []
    for m, path in MODULES.items():
        for line, _, names, _ in _sites(path):
            for d in {_resolve(n, MODULES) for n in names} - {None}:
                if _folder(d) != _folder(m):
                    edges.append((_rel(path), line, m, d))
    return edges


def _harness_layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "harness" and len(parts) > 1 else None


def _harness_back_arrows(edges: list[tuple[str, int, str, str]]) -> list[str]:
    """The edges from a harness subpackage to one it may not import (``HARNESS_ORDER``; the
    ``harness`` package itself is no layer: importing it from below is a back arrow too)."""
    bad: list[tuple[str, int, str]] = []
    for path, line, m, d in edges:
        src, dst = _harness_layer(m), _harness_layer(d)
        if src is None or d.split(".")[0] != "harness" or src == dst:
            continue
        if dst not in HARNESS_ORDER.get(src, ()):
            bad.append((path, line, d))
    return [f"{p}:{n} imports {x}" for p, n, x in sorted(set(bad))]


def test_harness_order_is_declared_for_every_subpackage() -> None:
    layers = {_harness_layer(m) for m in MODULES} - {None}
    assert layers == set(HARNESS_ORDER), layers ^ set(HARNESS_ORDER)
    # the order has no circle of its own: each layer may import only layers listed before it
    seen: set[str] = set()
    for layer, below in HARNESS_ORDER.items():
        assert set(below) <= seen, layer
        seen.add(layer)


def test_harness_imports_go_down_the_order() -> None:
    bad = _harness_back_arrows(_folder_edges())
    assert not bad, "back arrows:\n" + "\n".join(bad)


def test_no_import_circle_between_folders() -> None:
    graph: dict[str, set[str]] = {}
    for _, _, m, d in _folder_edges():
        graph.setdefault(_folder(m), set()).add(_folder(d))
    assert _circles(graph) == []


def _core_distributions() -> set[str]:
    """The normalised names of ``[project] dependencies`` in pyproject.toml."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = (re.match(r"[A-Za-z0-9._-]+", r).group(0) for r in project["dependencies"])
    return {re.sub(r"[-_.]+", "-", n).lower() for n in names}


def _function_import_violations() -> list[str]:
    """``path:line imports X`` for every import statement inside a function body (at any depth)
    of a project module, ``X`` a project module, a relative import, the standard library or a
    core dependency. (``importlib.import_module`` of a computed name, the commands' dispatch,
    is no import statement and not seen.)"""
    core = _core_distributions()
    distributions = importlib.metadata.packages_distributions()
    bad: list[tuple[str, int, str]] = []
    for _, path in sorted(MODULES.items()):
        for line, name, _, in_function in _sites(path):
            top = name.split(".")[0]
            dists = {re.sub(r"[-_.]+", "-", d).lower() for d in distributions.get(top, ())}
            # an optional package that is not installed has no distribution: it is optional
            if in_function and (name.startswith(".") or top in PACKAGES
                                or top in sys.stdlib_module_names or dists & core):
                bad.append((_rel(path), line, name))
    return [f"{p}:{n} imports {x}" for p, n, x in sorted(set(bad))]


def test_imports_inside_functions_only_for_optional_packages() -> None:
    bad = _function_import_violations()
    print("\n".join(bad))
    assert not bad, f"{len(bad)} imports inside functions:\n" + "\n".join(bad)


def test_the_folder_checkers_see_a_violation(tmp_path: Path) -> None:
    """The folder and function-level rules can fail: an edge up the order or sideways between
    leaves is a back arrow, two folders that import each other are a circle, and an import in a
    function nested in a method is found at its line, a module-level one is not inside one."""
    assert _harness_back_arrows([("harness/run/x.py", 3, "harness.run.x", "harness.viz.plots")])
    assert _harness_back_arrows([("harness/fuzz/x.py", 3, "harness.fuzz.x", "harness.tools.y")])
    assert not _harness_back_arrows([("harness/viz/x.py", 3, "harness.viz.x",
                                      "harness.run.signals")])
    assert _circles({"a": {"a.b"}, "a.b": {"a"}}) == [["a", "a.b"]]
    assert _circles({"a": {"a.b"}, "a.b": {"c"}}) == []
    sample = tmp_path / "sample.py"
    sample.write_text("import os\n"
                      "class C:\n"
                      "    def f(self):\n"
                      "        def g():\n"
                      "            from harness.run import procs\n"
                      "        return lambda: g()\n")
    assert _sites(sample) == [(1, "os", ("os",), False),
                              (5, "harness.run", ("harness.run", "harness.run.procs"), True)]
    assert {"numpy", "python-can", "cantools"} <= _core_distributions()
    assert "matplotlib" not in _core_distributions()
