"""The package's layers: data flows one way, io -> spectra -> models -> fitting / uncertainty /
diagnosis -> figures -> api -> report -> pipeline -> cli, and no import cycle joins two
components; no function is longer than 100 lines, and every module names its public API
(``__all__``).

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
LAYERS: dict[str, float] = {
    "_version": 0, "_lazy": 0, "constants": 0, "errors": 0, "data": 0, "workers": 0, "noise": 0,
    "memory": 0, "_scipy": 0, "_slsqp": 0, "_trf": 0, "_order": 0, "_pool": 0,
    "_server_exit": 0, "_student": 0, "_shared": 0, "_lapack": 0,
    "io": 1,
    "spectra": 2, "feedback": 2,
    "models": 3,
    "fitting": 4, "uncertainty": 4, "diagnosis": 4, "simulation": 4, "tables": 4,
    "loop": 4, "blocklsq": 4, "multilsq": 4,
    "figures": 5, "adopt": 5, "export": 5,
    "api": 6,
    "report": 6.5,        # report.md from the typed results; the pipeline imports it
    "htmlreport": 6.5,    # report.html from report.md
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


# ---------------------------------------------------------------------------
# No private multiprocessing API, no names rebound on the package
# ---------------------------------------------------------------------------

def _is_private(name: str) -> bool:
    """``_x`` is private; ``__x__`` (a dunder) is not."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _module_named(node: ast.AST) -> str | None:
    """The module an expression names by its dotted name as a string: the argument of
    ``sys.modules[...]``, ``sys.modules.get(...)`` or ``importlib.import_module(...)``."""
    def const(n):
        return n.value if isinstance(n, ast.Constant) and isinstance(n.value, str) else None
    if isinstance(node, ast.Subscript) and ast.unparse(node.value) == "sys.modules":
        return const(node.slice)
    if isinstance(node, ast.Call) and node.args:
        fn = ast.unparse(node.func)
        if fn in ("sys.modules.get", "importlib.import_module", "import_module",
                  "__import__"):
            return const(node.args[0])
    return None


class _Names(ast.NodeVisitor):
    """The names a module binds to a module object of ``root`` (the dotted module name,
    or None for a name of a module outside ``root``): by import, or by assignment from
    ``sys.modules``/``import_module`` or from another such name."""

    def __init__(self, root: str):
        self.root = root
        self.bound: dict[str, str] = {}

    def of(self, node: ast.AST) -> str | None:
        """The module of ``root`` that ``node`` evaluates to, if it is one."""
        if isinstance(node, ast.Name):
            return self.bound.get(node.id)
        named = _module_named(node)
        if named is not None and named.split(".")[0] == self.root:
            return named
        if isinstance(node, ast.Attribute) and not _is_private(node.attr):
            base = self.of(node.value)      # a private attribute is reported itself
            if base is not None:
                return f"{base}.{node.attr}"
        return None

    def visit_Import(self, node: ast.Import) -> None:
        for a in node.names:
            if a.name.split(".")[0] == self.root:
                if a.asname:
                    self.bound[a.asname] = a.name
                else:
                    self.bound[a.name.split(".")[0]] = self.root

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level == 0 and node.module and node.module.split(".")[0] == self.root:
            for a in node.names:
                self.bound[a.asname or a.name] = f"{node.module}.{a.name}"

    def visit_Assign(self, node: ast.Assign | ast.NamedExpr) -> None:
        mod = self.of(node.value)
        targets = node.targets if isinstance(node, ast.Assign) else [node.target]
        for t in targets:
            if isinstance(t, ast.Name) and mod is not None:
                self.bound[t.id] = mod

    visit_NamedExpr = visit_Assign


def _private_multiprocessing(source: str) -> list[str]:
    """Every use of a private name of :mod:`multiprocessing` in ``source``: an import of
    one (``from multiprocessing.util import _exit_function``, ``import
    multiprocessing._x``), an attribute ``_x`` read from a multiprocessing module object
    (however the name was bound: import, ``sys.modules``, ``import_module``), or
    ``getattr(<that object>, "_x")``. Returns "line: code" strings."""
    tree = ast.parse(source)
    names = _Names("multiprocessing")
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom | ast.Assign | ast.NamedExpr):
            names.visit(node)
    found = []
    for node in ast.walk(tree):
        bad = False
        if isinstance(node, ast.Import):
            bad = any(a.name.split(".")[0] == "multiprocessing"
                      and any(_is_private(p) for p in a.name.split(".")) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                and node.module.split(".")[0] == "multiprocessing":
            bad = any(_is_private(p) for p in node.module.split(".")) or \
                any(_is_private(a.name) for a in node.names)
        elif isinstance(node, ast.Attribute):
            bad = _is_private(node.attr) and names.of(node.value) is not None
        elif isinstance(node, ast.Call) and ast.unparse(node.func) in ("getattr", "hasattr",
                                                                      "setattr") \
                and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) \
                and isinstance(node.args[1].value, str):
            bad = _is_private(node.args[1].value) and names.of(node.args[0]) is not None
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and node.value.split(".")[0] == "multiprocessing":
            bad = any(_is_private(p) for p in node.value.split("."))   # sys.modules["..."]
        if bad:
            found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


def _package_rebinding(source: str) -> list[str]:
    """Every statement of ``source`` that binds or deletes a name on the ``armfit``
    package object from outside it: ``setattr(package, ...)``/``delattr``, ``package.x
    = ...`` (also augmented, annotated, deleted), ``vars(package)[...] = ...`` or
    ``package.__dict__[...] = ...``, where ``package`` is ``sys.modules["armfit"]``,
    ``sys.modules.get("armfit")``, ``import_module("armfit")``, ``import armfit`` (as
    any name) or a name assigned one of these. Returns "line: code" strings."""
    tree = ast.parse(source)
    names = _Names("armfit")
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom | ast.Assign | ast.NamedExpr):
            names.visit(node)

    def package(node: ast.AST) -> bool:
        return names.of(node) == "armfit"

    def target(t: ast.AST) -> bool:
        if isinstance(t, ast.Attribute):
            return package(t.value)
        if isinstance(t, ast.Subscript):
            v = t.value
            return (isinstance(v, ast.Attribute) and v.attr == "__dict__"
                    and package(v.value)) or (isinstance(v, ast.Call)
                                              and ast.unparse(v.func) == "vars"
                                              and len(v.args) == 1 and package(v.args[0]))
        if isinstance(t, ast.Tuple | ast.List):
            return any(target(e) for e in t.elts)
        return False

    found = []
    for node in ast.walk(tree):
        bad = False
        if isinstance(node, ast.Call) and ast.unparse(node.func) in ("setattr", "delattr") \
                and node.args:
            bad = package(node.args[0])
        elif isinstance(node, ast.Assign):
            bad = any(target(t) for t in node.targets)
        elif isinstance(node, ast.AugAssign | ast.AnnAssign):
            bad = target(node.target)
        elif isinstance(node, ast.Delete):
            bad = any(target(t) for t in node.targets)
        if bad:
            found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


def _scan(check) -> list[str]:
    return [f"{path.relative_to(ROOT.parent)}:{hit}" for path in sorted(ROOT.rglob("*.py"))
            for hit in check(path.read_text(encoding="utf-8"))]


def test_no_module_uses_a_private_name_of_multiprocessing():
    """Only multiprocessing's public API (private names change between Python versions
    without notice): none of the package's modules touches one."""
    assert _scan(_private_multiprocessing) == []


def test_no_module_rebinds_a_name_of_the_package():
    """The package's names are what armfit/__init__.py says (its lazy exports): no
    module binds a name on the package object from outside."""
    assert _scan(_package_rebinding) == []


#: Code the checks above must catch, with the lines they report (the first two are
#: what armfit.workers.stop_workers and armfit.cli.entry._exit_now once did).
PRIVATE_MP = [
    ('fs = sys.modules.get("multiprocessing.forkserver")\n'
     'server = getattr(fs, "_forkserver", None)\n',
     ["2: getattr(fs, '_forkserver', None)"]),
    ('mp_util = sys.modules.get("multiprocessing.util")\n'
     'getattr(mp_util, "_exit_function", lambda: None)()\n',
     ["2: getattr(mp_util, '_exit_function', lambda: None)"]),
    ("import multiprocessing as mp\nmp.util._exit_function()\n",
     ["2: mp.util._exit_function"]),
    ("import multiprocessing.forkserver\nmultiprocessing.forkserver._forkserver._stop()\n",
     ["2: multiprocessing.forkserver._forkserver"]),
    ("from multiprocessing import util\nutil._run_finalizers()\n",
     ["2: util._run_finalizers"]),
    ("from multiprocessing.util import _exit_function\n",
     ["1: from multiprocessing.util import _exit_function"]),
    ("import multiprocessing\nmultiprocessing.active_children()\nobj._private\n", []),
    ('sys.modules["multiprocessing.forkserver"]._forkserver\n',
     ["1: sys.modules['multiprocessing.forkserver']._forkserver"]),
]

REBINDING = [
    ('package = sys.modules.get("armfit")\nsetattr(package, "diagnose", f)\n',
     ["2: setattr(package, 'diagnose', f)"]),
    ('sys.modules["armfit"].x = 1\n', ["1: sys.modules['armfit'].x = 1"]),
    ("import armfit.spectra\narmfit.estimate = None\n", ["2: armfit.estimate = None"]),
    ("import armfit as pkg\nvars(pkg)['run'] = None\n", ["2: vars(pkg)['run'] = None"]),
    ("import armfit.spectra as sp\nsp.x = 1\nglobals()['y'] = 2\n", []),
]


@pytest.mark.parametrize("source, expected", PRIVATE_MP)
def test_the_multiprocessing_check_finds_private_names(source, expected):
    assert _private_multiprocessing(source) == expected


@pytest.mark.parametrize("source, expected", REBINDING)
def test_the_rebinding_check_finds_names_bound_on_the_package(source, expected):
    assert _package_rebinding(source) == expected


# ---------------------------------------------------------------------------
# Size of functions, and every module's public names
# ---------------------------------------------------------------------------

#: The longest a function or method of the package may be, in lines (``end_lineno -
#: lineno + 1`` of its ``def``, body, docstring and comments included).
MAX_FUNCTION_LINES = 100


def _long_functions(source: str, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """"name: lines" of every function or method of ``source`` (nested ones included)
    longer than ``limit`` lines."""
    return [f"{node.name}: {node.end_lineno - node.lineno + 1}"
            for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            and node.end_lineno - node.lineno + 1 > limit]


def _declares_all(source: str) -> bool:
    """Whether ``source`` binds ``__all__`` at module level."""
    for node in ast.parse(source).body:
        targets = (node.targets if isinstance(node, ast.Assign)
                   else [node.target] if isinstance(node, ast.AnnAssign | ast.AugAssign)
                   else [])
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            return True
    return False


def test_no_function_is_longer_than_100_lines():
    """A long function is split into well-named parts (report.md's renderer, once 195
    lines, is a function per section)."""
    assert _scan(_long_functions) == []


def test_the_length_check_counts_every_line_of_a_function():
    # a def line, a docstring of 2 lines and 98 statements: 101 lines; one fewer: 100
    body = '    """Two\n    lines."""\n' + "    x = 1\n" * 98
    assert _long_functions("def f():\n" + body) == ["f: 101"]
    assert _long_functions("def f():\n" + body[:-len("    x = 1\n")]) == []
    nested = "class A:\n    async def m(self):\n" + "        x = 1\n" * 100
    assert _long_functions(nested) == ["m: 101"]


def test_every_module_declares_its_public_names():
    missing = [str(path.relative_to(ROOT.parent)) for path in sorted(ROOT.rglob("*.py"))
               if not _declares_all(path.read_text(encoding="utf-8"))]
    assert missing == []


@pytest.mark.parametrize("module", ["pipeline.py", "report.py"])
def test_the_pipeline_and_the_report_declare_their_public_names(module):
    assert _declares_all((ROOT / module).read_text(encoding="utf-8"))


@pytest.mark.parametrize("source, expected", [
    ("__all__ = ['f']\n", True),
    ("__all__: list[str] = []\n", True),
    ("x = 1\ndef f():\n    __all__ = ['f']\n", False),   # not at module level
    ("ALL = ['f']\n", False),
])
def test_the_all_check_reads_module_level_bindings(source, expected):
    assert _declares_all(source) is expected


#: Names every module of a kind defines by protocol: each subcommand module's click
#: ``command`` (loaded lazily by name, armfit.cli.main) and each effect file's ``EFFECTS``
#: list (the built-in library is loaded like a user's file, armfit.models.effects).
PROTOCOL_NAMES = {"command", "EFFECTS"}


def test_no_public_name_is_defined_in_two_modules():
    """One name, one object: a public class, function or constant is defined in one
    module only (an engine function is not named like the API stage above it)."""
    where: dict[str, list[str]] = {}
    for path in sorted(ROOT.rglob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                names = [node.name]
            elif isinstance(node, ast.Assign):
                names = [t.id for t in node.targets if isinstance(t, ast.Name)]
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                names = [node.target.id]
            else:
                continue
            for name in names:
                if not name.startswith("_") and name not in PROTOCOL_NAMES:
                    where.setdefault(name, []).append(_module_name(path))
    assert {n: m for n, m in where.items() if len(m) > 1} == {}
