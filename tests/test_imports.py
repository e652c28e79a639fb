"""The import graph of ``services/``: no cycles, one module per wire dependency, runtime apart.

Every module under ``services/`` is parsed with :mod:`ast` (nothing is imported). Each ``import``
statement counts, wherever it sits: at the top, inside a function (a lazy import is still a
dependency when it runs) or under ``if TYPE_CHECKING:``. An edge goes to the module named, or, for
``from package import name`` where ``package.name`` is a module, to that submodule. The implicit
import of a module's parent packages is not an edge (every module would depend on its package's
``__init__``).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SERVICES = REPO / "services"
# Packages whose modules the deployed services run; none may reach the evaluation code.
RUNTIME_PACKAGES = ("common", "tracker", "kinematics", "detector", "robot_bridge", "synthetic")
# Modules that are entry points or tools above the runtime packages, never imported by them.
NOT_RUNTIME = ("services.evaluation", "services.demo", "services.cli", "services.__main__")

Graph = Mapping[str, set[str]]


def module_name(path: Path, root: Path) -> str:
    """Dotted name of the module at ``path`` below ``root`` (the directory holding the package)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules_under(package_dir: Path) -> dict[str, Path]:
    """Every module of the package at ``package_dir``: dotted name -> file."""
    root = package_dir.parent
    return {module_name(p, root): p for p in sorted(package_dir.rglob("*.py"))}


def imported_names(path: Path, module: str, known: Iterable[str] = ()) -> set[str]:
    """Absolute names of the modules that ``module`` (source at ``path``) imports.

    Relative imports are resolved against ``module``; ``from a import b`` gives ``a.b`` when that is
    one of the ``known`` modules, else ``a``.
    """
    known = set(known)
    is_package = path.name == "__init__.py"
    package = module.split(".") if is_package else module.split(".")[:-1]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                names.add(sub if sub in known else source)
    return names


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """Edges between the modules of one package: module -> the package's modules it imports."""
    modules = modules_under(package_dir)
    return {m: {n for n in imported_names(p, m, modules) if n in modules and n != m}
            for m, p in modules.items()}


def find_cycle(graph: Graph) -> list[str] | None:
    """One import cycle ``[a, b, ..., a]`` of ``graph``, or None if it has none (iterative DFS)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    for start in sorted(graph):
        if state.get(start):
            continue
        path = [start]
        todo = [iter(sorted(graph.get(start, ())))]
        state[start] = 1
        while todo:
            nxt = next(todo[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                todo.pop()
            elif state.get(nxt) == 1:
                return [*path[path.index(nxt):], nxt]
            elif not state.get(nxt):
                state[nxt] = 1
                path.append(nxt)
                todo.append(iter(sorted(graph.get(nxt, ()))))
    return None


def reachable(graph: Graph, start: str) -> set[str]:
    """Every module that importing ``start`` can reach through the graph (``start`` excluded)."""
    seen: set[str] = set()
    todo = [start]
    while todo:
        for nxt in graph.get(todo.pop(), ()):
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    return seen


def importers_of(top_level: str) -> set[str]:
    """The ``services`` modules that import the third-party package ``top_level`` directly."""
    return {m for m, p in modules_under(SERVICES).items()
            if any(n.split(".")[0] == top_level for n in imported_names(p, m))}


# --- the helpers on small graphs and packages -------------------------------------------------


def test_find_cycle_reports_a_cycle_and_only_a_real_one() -> None:
    assert find_cycle({}) is None
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None  # a diamond is no cycle
    cycle = find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}})
    assert cycle is not None and cycle[0] == cycle[-1] and sorted(cycle[:-1]) == ["a", "b", "c"]
    assert find_cycle({"x": {"x"}}) == ["x", "x"]
    # a cycle that the first start in order does not reach, behind an edge to a missing module
    assert find_cycle({"a": {"zz"}, "m": {"n"}, "n": {"m"}}) == ["m", "n", "m"]


def test_import_graph_resolves_relative_lazy_and_submodule_imports(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "from pkg.sub import b\nimport zenoh\n",
        "sub/__init__.py": "from . import c\n",
        "sub/b.py": "def f():\n    from ..a import f\n",
        "sub/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.sub.b import g\n",
        "d.py": "from pkg import sub\nfrom pkg.sub import missing_name\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    graph = import_graph(pkg)
    assert graph == {"pkg": set(), "pkg.a": {"pkg.sub.b"}, "pkg.sub": {"pkg.sub.c"},
                     "pkg.sub.b": {"pkg.a"}, "pkg.sub.c": {"pkg.sub.b"}, "pkg.d": {"pkg.sub"}}
    assert find_cycle(graph) == ["pkg.a", "pkg.sub.b", "pkg.a"]
    assert "zenoh" in imported_names(pkg / "a.py", "pkg.a")


# --- the services package ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(SERVICES)


def test_every_module_is_in_the_graph(graph: dict[str, set[str]]) -> None:
    assert {"services.common.bus", "services.tracker.tracker", "services.evaluation.pipeline",
            "services.robot_bridge.factory"} <= set(graph)
    assert "services.robot_bridge.backend" in graph["services.robot_bridge.factory"]


def test_no_import_cycles_among_services_modules(graph: dict[str, set[str]]) -> None:
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or ())


def test_only_bus_imports_zenoh_and_only_protocol_imports_msgpack() -> None:
    assert importers_of("zenoh") == {"services.common.bus"}
    assert importers_of("msgpack") == {"services.common.protocol"}


@pytest.mark.parametrize("package", RUNTIME_PACKAGES)
def test_runtime_packages_never_reach_evaluation_or_entry_points(
        graph: dict[str, set[str]], package: str) -> None:
    prefix = f"services.{package}"
    modules = [m for m in graph if m == prefix or m.startswith(prefix + ".")]
    assert modules, f"no modules under {prefix}"
    for module in modules:
        bad = sorted(n for n in reachable(graph, module)
                     if any(n == x or n.startswith(x + ".") for x in NOT_RUNTIME))
        assert not bad, f"{module} imports (directly or through others) {bad}"
