"""The package's layout holds: its import graph has no cycles and every layer imports only what is below it.

The graph is read from the source with ``ast``: every ``import`` and ``from ... import``, including those under
``if TYPE_CHECKING:`` and inside functions, with relative imports resolved and ``from package import name``
resolved to the submodule ``name`` when there is one (to the package's ``__init__`` otherwise).
"""

from __future__ import annotations

import ast
import functools
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "atlas_onboard"
MAX_LINES = 400


@dataclass(frozen=True)
class Import:
    """One import statement's target: ``module`` is a dotted name (inside the package or not)."""

    source: str
    module: str
    line: int


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _files() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((ROOT / PACKAGE).rglob("*.py"))}


def _is_package(files: dict[str, Path], name: str) -> bool:
    return name in files and files[name].name == "__init__.py"


def _imports(files: dict[str, Path], name: str, path: Path) -> list[Import]:
    """Every import of one module, wherever it stands in the file."""
    found: list[Import] = []
    for node in _nodes(path):
        if isinstance(node, ast.Import):
            found.extend(Import(name, alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                # relative to the importing module's package (a package's __init__ is its own package)
                base = name.split(".") if _is_package(files, name) else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.append(Import(name, sub if sub in files else target, node.lineno))
    return found


@functools.cache
def _nodes(path: Path) -> tuple[ast.AST, ...]:
    """Every node of a module's syntax tree (parsed once for all the tests)."""
    return tuple(ast.walk(ast.parse(path.read_text(), str(path))))


def _graph() -> tuple[dict[str, Path], dict[str, list[Import]]]:
    return _graph_at(ROOT)


@functools.cache
def _graph_at(root: Path) -> tuple[dict[str, Path], dict[str, list[Import]]]:
    """The package under ``root`` (the module-wide ``ROOT``), read once for all the tests."""
    files = _files()
    return files, {name: _imports(files, name, path) for name, path in files.items()}


def _inside(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each as one shortest cycle."""
    return [_shortest_cycle(edges, comp) for comp in _components(edges)]


def _components(edges: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components that hold a cycle (Tarjan), in the order found."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1 or v in edges.get(v, ()):
                components.append(comp)

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(edges) + 100))
    try:
        for v in sorted(edges):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return components


def _shortest_cycle(edges: dict[str, set[str]], comp: set[str]) -> list[str]:
    best: list[str] = []
    for start in sorted(comp):
        prev: dict[str, str] = {}
        frontier = [start]
        seen = {start}
        found = None
        while frontier and found is None:
            nxt = []
            for v in frontier:
                for w in sorted(edges.get(v, ())):
                    if w not in comp:
                        continue
                    if w == start:
                        found = v
                        break
                    if w not in seen:
                        seen.add(w)
                        prev[w] = v
                        nxt.append(w)
                if found is not None:
                    break
            frontier = nxt
        if found is None:
            continue
        path = [found]
        while path[-1] != start:
            path.append(prev[path[-1]])
        cycle = [*reversed(path), start]
        if not best or len(cycle) < len(best):
            best = cycle
    return best


def _violations(imports: dict[str, list[Import]], layer: str, allowed) -> list[str]:
    return [
        f"{imp.source}:{imp.line} imports {imp.module}"
        for name, found in imports.items()
        if _inside(name, layer)
        for imp in found
        if not allowed(imp.module)
    ]


def test_no_import_cycles():
    """Each strongly connected group of modules is reported with one shortest cycle through it."""
    files, imports = _graph()
    edges = {name: {imp.module for imp in found if imp.module in files} for name, found in imports.items()}
    lines = []
    for comp in _components(edges):
        cycle = _shortest_cycle(edges, comp)
        rest = sorted(comp - set(cycle))
        lines.append(" -> ".join(cycle) + (f"  (and through {', '.join(rest)})" if rest else ""))
    assert not lines, "import cycles:\n" + "\n".join(lines)


def test_every_import_of_the_package_names_one_of_its_modules():
    """A module moved or renamed leaves no import of its old name behind (in a function, say)."""
    files, imports = _graph()
    bad = [
        f"{imp.source}:{imp.line} imports {imp.module}"
        for found in imports.values()
        for imp in found
        if _inside(imp.module, PACKAGE) and imp.module not in files
    ]
    assert not bad, "\n".join(bad)


def test_core_imports_only_stdlib_numpy_scipy():
    """The one error hierarchy (``errors``) sits below every layer, the core included; it imports only the
    standard library, so the core stays pure through it."""
    _, imports = _graph()
    core, errors = f"{PACKAGE}.core", f"{PACKAGE}.errors"

    def stdlib(module: str) -> bool:
        return module.split(".", maxsplit=1)[0] in sys.stdlib_module_names

    def allowed(module: str) -> bool:
        top = module.split(".", maxsplit=1)[0]
        return _inside(module, core) or module == errors or top in {"numpy", "scipy"} or stdlib(module)

    bad = _violations(imports, core, allowed) + _violations(imports, errors, stdlib)
    assert not bad, "\n".join(bad)


def test_mavlink_knows_nothing_of_node_publisher_schedule_detector():
    _, imports = _graph()
    forbidden = [f"{PACKAGE}.{n}" for n in ("node", "core.publisher", "detector", "service")]

    def allowed(module: str) -> bool:
        return not any(_inside(module, f) for f in forbidden)

    bad = _violations(imports, f"{PACKAGE}.mavlink", allowed)
    assert not bad, "\n".join(bad)


def test_detector_knows_nothing_of_mapping_sim_or_the_node():
    _, imports = _graph()
    above = [f"{PACKAGE}.{n}" for n in ("mapping", "sim", "node", "listener", "publisher", "schedule")]
    bad = _violations(imports, f"{PACKAGE}.detector", lambda m: not any(_inside(m, a) for a in above))
    assert not bad, "\n".join(bad)


def test_only_the_simulator_imports_the_simulator():
    _, imports = _graph()
    sim = f"{PACKAGE}.sim"
    bad = [
        f"{imp.source}:{imp.line} imports {imp.module}"
        for name, found in imports.items()
        if not _inside(name, sim)
        for imp in found
        if _inside(imp.module, sim)
    ]
    assert not bad, "\n".join(bad)


def test_unused_import_waivers_only_in_package_init_files():
    bad = [
        f"{path.relative_to(ROOT)}:{n}"
        for path in _files().values()
        if path.name != "__init__.py"
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if "noqa: F401" in line
    ]
    assert not bad, "re-exports outside a package's __init__.py:\n" + "\n".join(bad)


def test_no_module_over_400_lines():
    long = {
        str(path.relative_to(ROOT)): n
        for path in _files().values()
        if (n := len(path.read_text().splitlines())) > MAX_LINES
    }
    assert not long, long


def test_no_getattr_with_a_literal_name():
    """``getattr(x, "name", default)`` looks up by duck typing what a declared type should say."""
    bad = []
    for path in _files().values():
        for node in _nodes(path):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "getattr"
                and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant)
                and isinstance(node.args[1].value, str)
            ):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno} getattr(..., {node.args[1].value!r})")
    assert not bad, "\n".join(bad)


def test_argument_parsing_and_printing_only_in_the_command_line():
    """argparse and print() belong to ``cli/`` (and the simulator's own commands, which reach the command line
    through entry points): the library's functions return what they found and raise what went wrong."""
    allowed = {f"{PACKAGE}.sim.command", f"{PACKAGE}.sim.demo"}
    bad = []
    for name, path in _files().items():
        if _inside(name, f"{PACKAGE}.cli") or name in allowed:
            continue
        for node in _nodes(path):
            if isinstance(node, ast.Import | ast.ImportFrom):
                modules = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                if "argparse" in modules:
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno} imports argparse")
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("print", "input"):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno} calls {node.func.id}()")
    assert not bad, "\n".join(bad)


def test_the_apriltag_library_detector_is_made_only_by_the_backend():
    """pupil-apriltags can corrupt the heap when one of its detectors is destroyed after finding tags: the
    process aborts later, anywhere. Only ``detector.backends`` makes them (kept for the process's life), in
    the package, its tests and its benchmarks alike."""
    owner = ROOT / PACKAGE / "detector" / "backends.py"
    bad = []
    for path in sorted(
        [*(ROOT / PACKAGE).rglob("*.py"), *(ROOT / "tests").rglob("*.py"), *(ROOT / "benchmarks").rglob("*.py")]
    ):
        if path == owner:
            continue
        for node in _nodes(path):
            named = (
                [a.name for a in node.names]
                if isinstance(node, ast.ImportFrom) and node.module == "pupil_apriltags"
                else []
            )
            called = isinstance(node, ast.Attribute) and node.attr == "Detector" and isinstance(node.value, ast.Name)
            if "Detector" in named or (called and node.value.id == "pupil_apriltags"):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not bad, "\n".join(bad)


def test_no_attribute_forwarding():
    """``__getattr__`` hands on whatever is asked: composition says what an object offers."""
    bad = [
        f"{path.relative_to(ROOT)}:{node.lineno}"
        for path in _files().values()
        for node in _nodes(path)
        if isinstance(node, ast.FunctionDef) and node.name in ("__getattr__", "__getattribute__")
    ]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(
    ("edges", "expected"),
    [
        ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
        ({"a": {"b"}, "b": {"a"}}, [["a", "b", "a"]]),
        ({"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}, [["a", "b", "c", "a"]]),
        ({"a": {"a"}}, [["a", "a"]]),
    ],
)
def test_cycle_finder(edges, expected):
    assert _cycles(edges) == expected


def test_imports_resolved_relative_and_under_type_checking(tmp_path, monkeypatch):
    pkg = tmp_path / PACKAGE
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from .b import B\n")
    (pkg / "sub" / "b.py").write_text("B = 1\n")
    (pkg / "a.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from .sub import b\n"
        "def f():\n    from .sub import B\n    import numpy.linalg\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    _, imports = _graph()
    expected = {"typing", f"{PACKAGE}.sub.b", f"{PACKAGE}.sub", "numpy.linalg"}
    assert {i.module for i in imports[f"{PACKAGE}.a"]} == expected
    assert {i.module for i in imports[f"{PACKAGE}.sub"]} == {f"{PACKAGE}.sub.b"}
