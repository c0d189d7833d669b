"""The package's layers: data flows one way, io -> spectra -> models -> fitting / uncertainty /
diagnosis -> figures -> api -> pipeline -> cli, and no import cycle joins two components.

Every ``import`` of an armfit module is read from the source with :mod:`ast`, at module
level and inside functions alike (a function-local import is still a dependency).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "armfit"

#: Layer of each component (a top-level module or subpackage of armfit). A module may
#: import from its own layer or below, never from above; the package itself
#: (armfit/__init__.py, the public facade) is imported by nobody inside the package.
LAYERS: dict[str, int] = {
    "_version": 0, "constants": 0, "errors": 0, "data": 0, "workers": 0, "noise": 0,
    "io": 1,
    "spectra": 2,
    "models": 3,
    "fitting": 4, "uncertainty": 4, "diagnosis": 4, "simulation": 4, "tables": 4,
    "loop": 4, "blocklsq": 4,
    "figures": 5, "adopt": 5,
    "api": 6,
    "pipeline": 7,
    "cli": 8,
    "armfit": 9,
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[str, int]]:
    """(imported armfit module, line) for every import statement in ``path``."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "armfit"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "armfit":
                continue
            # ``from armfit import figures`` imports the module armfit.figures
            for a in node.names:
                sub = f"{mod}.{a.name}"
                out.append((sub if _is_module(sub) else mod, node.lineno))
    return out


def _is_module(name: str) -> bool:
    rel = Path(*name.split(".")[1:])
    return (ROOT / rel).with_suffix(".py").is_file() or (ROOT / rel / "__init__.py").is_file()


def _component(module: str) -> str:
    parts = module.split(".")
    return "armfit" if len(parts) == 1 else parts[1].removesuffix(".py")


def _graph() -> dict[str, list[tuple[str, str, int]]]:
    """{module: [(imported module, file, line)]} over every module of the package."""
    graph = {}
    for path in sorted(ROOT.rglob("*.py")):
        graph[_module_name(path)] = [(m, str(path.relative_to(ROOT.parent)), line)
                                     for m, line in _imports(path)]
    return graph


def test_every_component_has_a_layer():
    unknown = sorted({_component(m) for m in _graph()} - set(LAYERS))
    assert not unknown, f"give these components a layer in LAYERS: {unknown}"


def test_imports_go_down_the_layers_only():
    upward = []
    for module, edges in _graph().items():
        here = LAYERS.get(_component(module))
        for target, file, line in edges:
            there = LAYERS.get(_component(target))
            if here is None or there is None:
                continue
            if there > here or (target == "armfit" and module != "armfit"):
                upward.append(f"{file}:{line}: {module} imports {target}")
    assert not upward, "imports against the layers:\n" + "\n".join(upward)


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle_between_components():
    edges: dict[str, set[str]] = {}
    for module, targets in _graph().items():
        a = _component(module)
        for target, _, _ in targets:
            b = _component(target)
            if a != b:
                edges.setdefault(a, set()).add(b)
    assert _cycles(edges) == []


def test_the_cycle_finder_finds_a_planted_cycle():
    # io -> uncertainty -> io, as the package once had through a function-local import
    assert _cycles({"io": {"uncertainty"}, "uncertainty": {"io", "models"}}) == [
        ["io", "uncertainty"]]
    assert _cycles({"a": {"b"}, "b": {"c"}}) == []


@pytest.mark.parametrize("source, expected", [
    ("def f():\n    from armfit.uncertainty import WuWeight\n", ["armfit.uncertainty"]),
    ("from armfit import figures\n", ["armfit.figures"]),
    ("from . import atomic\n", ["armfit.io.atomic"]),
])
def test_imports_inside_functions_and_relative_ones_are_read(tmp_path, monkeypatch, source,
                                                             expected):
    path = ROOT / "io" / "trials.py"  # a module path inside the package, for `package`
    monkeypatch.setattr(Path, "read_text", lambda self, encoding=None: source)
    assert [m for m, _ in _imports(path)] == expected
