"""Package layering (docs/layout.md): parse the imports of every module of presim/ and fail on an
import between sub-packages that the table below does not allow (upward imports, sibling imports,
the product importing presim.testing), and on any import cycle between modules.

``ALLOWED`` is the table of docs/layout.md ("Who may import whom"); change both together.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "presim"

# Sub-package -> sub-packages it may import. Root modules (presim/*.py and the package __init__) are
# the base: everybody may import them and they import only each other (see _unit / _violations).
_ALL = {"formats", "sensors", "imaging", "capture", "align", "photometric", "depth", "synthesis", "evaluation",
        "sim", "datasets", "outputs", "pose", "api", "cli", "testing"}
ALLOWED: dict[str, set[str]] = {
    "formats": set(),
    "sensors": set(),
    "imaging": set(),
    "capture": {"formats", "sensors"},
    "align": {"formats", "capture"},
    "photometric": {"formats", "capture"},
    "depth": {"formats", "capture"},
    "synthesis": {"formats", "imaging", "sensors", "capture", "photometric"},
    "evaluation": {"formats", "sensors", "imaging", "capture", "photometric", "depth", "synthesis"},
    "sim": {"formats", "sensors", "capture", "synthesis"},
    "datasets": {"formats", "sensors", "capture", "synthesis"},
    "outputs": {"formats", "sensors", "capture", "sim"},
    "pose": {"formats", "capture", "datasets"},
    "api": {"formats", "sensors", "capture", "align", "synthesis", "sim"},
    "cli": _ALL - {"cli", "testing"},
    "testing": _ALL - {"testing"},
}
ROOT = "<root>"  # presim/__init__.py and presim/*.py

# KNOWN EXCEPTIONS -- imports that break the table and are accepted for a stated reason. Each entry:
# (importing module, imported sub-package); test_known_exceptions_are_still_needed fails once an
# entry is obsolete.
KNOWN_EXCEPTIONS: set[tuple[str, str]] = {
    # presim/__init__.py re-exports the public API (presim/api/) lazily, in a module __getattr__: the
    # package's front door names it, and nothing is imported until a user asks for it.
    ("presim", "api"),
}


def _module_name(path: Path, pkg: Path = PKG) -> str:
    rel = path.relative_to(pkg.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _unit(module: str, pkg: Path = PKG) -> str:
    """Layering unit of a dotted module name: its sub-package, or ROOT for presim and presim/*.py
    (``presim/__main__.py``, ``python -m presim``, belongs to ``cli``)."""
    parts = module.split(".")
    if module == "presim.__main__":
        return "cli"
    if len(parts) >= 2 and (pkg / parts[1]).is_dir():
        return parts[1]
    return ROOT


def imported_modules(source: str, module: str, is_package: bool, pkg: Path = PKG) -> list[tuple[str, int]]:
    """``(absolute presim module name, line)`` of every import in ``source``, at any depth (lazy
    imports inside functions count), relative imports resolved, plus
    ``importlib.import_module("presim...")`` with a literal name."""
    out = []
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod == "presim":
                # `from presim import x`: a sub-package / root module named x, else a name of presim/__init__.
                for a in node.names:
                    is_mod = (pkg / a.name).is_dir() or (pkg / f"{a.name}.py").is_file()
                    out.append((f"presim.{a.name}" if is_mod else "presim", node.lineno))
            else:
                out.append((mod, node.lineno))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == "import_module" and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            out.append((node.args[0].value, node.lineno))
    return [(m, ln) for m, ln in out if m == "presim" or m.startswith("presim.")]


def _violations(pkg: Path = PKG) -> tuple[list[tuple[str, str, int, str]], list[str]]:
    """``([(importing module, imported unit, line, imported module)], [unknown sub-packages])``."""
    bad, unknown = [], set()
    for path in sorted(pkg.rglob("*.py")):
        module = _module_name(path, pkg)
        src_unit = _unit(module, pkg)
        if src_unit != ROOT and src_unit not in ALLOWED:
            unknown.add(src_unit)
            continue
        for target, line in imported_modules(path.read_text(), module, path.name == "__init__.py", pkg):
            dst_unit = _unit(target, pkg)
            if dst_unit == src_unit or dst_unit == ROOT:
                continue
            if src_unit == ROOT or dst_unit not in ALLOWED.get(src_unit, set()):
                bad.append((module, dst_unit, line, target))
    return bad, sorted(unknown)


def test_every_sub_package_is_in_the_table():
    _, unknown = _violations()
    assert not unknown, (f"sub-packages {unknown} are not in docs/layout.md's table: add them there and to "
                         f"ALLOWED in tests/test_layering.py")


def test_no_import_breaks_the_layering():
    bad, _ = _violations()
    bad = [b for b in bad if (b[0], b[1]) not in KNOWN_EXCEPTIONS]
    lines = [f"{m.replace('.', '/')}.py:{ln}: imports {t} ({d} is not allowed; docs/layout.md)" for m, d, ln, t in bad]
    assert not bad, "\n".join(lines)


def test_known_exceptions_are_still_needed():
    bad, _ = _violations()
    found = {(b[0], b[1]) for b in bad}
    obsolete = sorted(KNOWN_EXCEPTIONS - found)
    assert not obsolete, f"remove {obsolete} from KNOWN_EXCEPTIONS in tests/test_layering.py (fixed)"


def test_product_never_imports_testing():
    bad, _ = _violations()
    assert not [b for b in bad if b[1] == "testing"]
    assert "testing" not in set().union(*(v for k, v in ALLOWED.items() if k != "testing"))


@pytest.fixture()
def toy_pkg(tmp_path) -> Path:
    """A tiny presim/ tree with one upward, one sibling, one relative-upward and one testing import."""
    pkg = tmp_path / "presim"
    files = {
        "__init__.py": "",
        "geometry.py": "import numpy as np\n",
        "capture/__init__.py": "",
        "capture/scene.py": "from presim.geometry import look_at\nfrom presim.capture import store\n",
        "capture/store.py": "def f():\n    from presim.sim.robot import load_robot  # lazy, upward\n",
        "sim/__init__.py": "",
        "sim/robot.py": "from presim.capture.scene import Scene\nfrom presim import datasets\n",
        "datasets/__init__.py": "",
        "datasets/gen.py": "from ..synthesis import renderer\nfrom presim.testing.steps import x\n",
        "synthesis/__init__.py": "from . import renderer\n",
        "synthesis/renderer.py": "import importlib\nm = importlib.import_module('presim.depth.refine')\n",
        "depth/__init__.py": "",
        "testing/__init__.py": "from presim.cli import main\n",
        "cli/__init__.py": "from presim.datasets.gen import y\n",
    }
    for name, text in files.items():
        (pkg / name).parent.mkdir(parents=True, exist_ok=True)
        (pkg / name).write_text(text)
    return pkg


def test_checker_finds_each_kind_of_bad_import(toy_pkg):
    bad, unknown = _violations(toy_pkg)
    got = sorted((m, d, ln) for m, d, ln, _ in bad)
    assert got == [
        ("presim.capture.store", "sim", 2),        # lazy import inside a function, upward
        ("presim.datasets.gen", "testing", 2),     # product -> testing
        ("presim.sim.robot", "datasets", 2),       # sibling, via `from presim import datasets`
        ("presim.synthesis.renderer", "depth", 2),  # importlib with a literal name
    ], got
    # Allowed and not reported: capture -> root (geometry), within capture, sim -> capture,
    # datasets -> synthesis (relative `..`), synthesis/__init__ -> its own module, testing/cli -> anything.
    assert unknown == []
    (toy_pkg / "newpkg").mkdir()
    (toy_pkg / "newpkg" / "__init__.py").write_text("")
    assert _violations(toy_pkg)[1] == ["newpkg"]


# ---- import cycles between modules ----------------------------------------------------------------

# KNOWN CYCLES -- strongly connected sets of modules accepted for a stated reason; each entry is the
# exact set, and test_known_cycles_are_still_present fails once one is gone.
KNOWN_CYCLES: dict[frozenset[str], str] = {}


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def module_imports(source: str, module: str, is_package: bool, modules: set[str]) -> list[tuple[str, int]]:
    """``(presim module, line)`` of every import that runs when ``module`` (or a function of it) runs:
    module-level and function-local imports alike; ``if TYPE_CHECKING:`` blocks are skipped (they
    never run). ``from pkg import name`` names the sub-module ``pkg.name`` when there is one, else
    ``pkg``; a dotted name that is not a module resolves to its longest module prefix."""
    tree = ast.parse(source)
    skip = {id(n) for blk in ast.walk(tree) if isinstance(blk, ast.If) and _is_type_checking(blk)
            for stmt in blk.body for n in ast.walk(stmt)}
    package = module if is_package else module.rpartition(".")[0]
    out = []

    def add(name: str, line: int) -> None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        if name and name != module:
            out.append((name, line))

    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "presim":
                    add(a.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "presim":
                continue
            for a in node.names:
                add(f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod, node.lineno)
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == "import_module" and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
              and node.args[0].value.startswith("presim")):
            add(node.args[0].value, node.lineno)
    return out


def import_graph(pkg: Path = PKG) -> dict[str, dict[str, int]]:
    """Module -> {imported presim module: first line of such an import} for every module of ``pkg``."""
    paths = {_module_name(p, pkg): p for p in sorted(pkg.rglob("*.py"))}
    modules = set(paths)
    graph: dict[str, dict[str, int]] = {}
    for m, p in paths.items():
        edges = graph.setdefault(m, {})
        for target, line in module_imports(p.read_text(), m, p.name == "__init__.py", modules):
            edges.setdefault(target, line)
    return graph


def import_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected sets of more than one module (Tarjan), each sorted; sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
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
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _describe(cycle: list[str], graph: dict[str, dict[str, int]], pkg: Path = PKG) -> str:
    members = set(cycle)
    lines = [f"  {m.replace('.', '/')}.py:{ln}: imports {t}" for m in cycle
             for t, ln in sorted(graph[m].items()) if t in members]
    return "import cycle between " + ", ".join(cycle) + ":\n" + "\n".join(lines)


@functools.lru_cache(maxsize=1)
def _presim_graph() -> dict[str, dict[str, int]]:
    return import_graph()


def test_no_import_cycle():
    graph = _presim_graph()
    cycles = [c for c in import_cycles(graph) if frozenset(c) not in KNOWN_CYCLES]
    assert not cycles, ("\n".join(_describe(c, graph) for c in cycles)
                        + "\nbreak it: move the shared names to a module both may import (docs/layout.md)")


def test_known_cycles_are_still_present():
    found = {frozenset(c) for c in import_cycles(_presim_graph())}
    gone = [sorted(c) for c in KNOWN_CYCLES if c not in found]
    assert not gone, f"remove {gone} from KNOWN_CYCLES in tests/test_layering.py (fixed)"


def test_cycle_finder_sees_lazy_imports_and_skips_type_checking(tmp_path):
    """A toy package: a -> b at module level, b -> a inside a function (a cycle); c -> d and d -> c
    only under ``if TYPE_CHECKING`` (not a cycle); e -> f via ``from presim.p import f`` and f -> e
    via a relative import (a cycle)."""
    pkg = tmp_path / "presim"
    files = {
        "__init__.py": "",
        "a.py": "from presim.b import x\n",
        "b.py": "def g():\n    import presim.a\n",
        "c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from presim.d import D\n",
        "d.py": "import typing\nif typing.TYPE_CHECKING:\n    from presim.c import C\n",
        "p/__init__.py": "",
        "p/e.py": "from presim.p import f\n",
        "p/f.py": "from .e import y\n",
    }
    for name, text in files.items():
        (pkg / name).parent.mkdir(parents=True, exist_ok=True)
        (pkg / name).write_text(text)
    graph = import_graph(pkg)
    assert import_cycles(graph) == [["presim.a", "presim.b"], ["presim.p.e", "presim.p.f"]]
    assert graph["presim.b"] == {"presim.a": 2}
    assert "presim/b.py:2: imports presim.a" in _describe(["presim.a", "presim.b"], graph, pkg)


def test_no_private_name_is_imported_from_another_module():
    """``from presim.x import _name``: a private name belongs to its module (issue 41)."""
    bad = []
    for path in sorted(PKG.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("presim"):
                bad += [f"{path.relative_to(PKG.parent)}:{node.lineno} {a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


def test_synthesis_functions_take_at_most_12_positional_parameters():
    """Kernels take named tuples or small dataclasses instead of long argument lists (issue 41)."""
    bad = []
    for path in sorted((PKG / "synthesis").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = len(node.args.posonlyargs) + len(node.args.args)
                if n > 12:
                    bad.append(f"{path.name}:{node.lineno} {node.name} ({n})")
    assert not bad, "\n".join(bad)
