"""Imports run one way: the layer table of the package (README "Layout", davis_rig/__init__.py) as data.

Every ``davis_rig`` module is read with :mod:`ast` (nothing is imported): its imports at module level and inside
functions count, and so do the module paths of its lazy-export tables. A module may import its own package and the
packages of earlier layers. A package in no layer, an import of a later layer or of another package of the same
layer, and an import cycle between modules each fail the suite, naming the offending imports.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "davis_rig"

#: The layers, bottom first: top-level packages (or modules) of ``davis_rig``. A layer may import every earlier
#: layer; the packages of one layer do not import each other. ``__init__`` is the package root (``__version__``).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("__init__", "errors"),
    ("types", "_lazy", "stop"),
    ("protocol",),
    ("usb",),
    ("device",),
    ("session",),
    ("events",),
    ("models",),
    ("labelers", "metrics"),
    ("evaluation",),
    ("scene",),
    ("training",),
    ("attack",),
    ("attack_aps", "controls"),
    ("interop", "viewer"),
    ("cli",),
)
LAYER_OF = {name: i for i, layer in enumerate(LAYERS) for name in layer}


class Import(NamedTuple):
    """One reference of a module to another ``davis_rig`` module."""

    target: str  #: the imported module (``pkg.name`` when that is a module, else ``pkg``)
    line: int
    lazy: bool  #: a key of a lazy-export table (loaded on attribute access, not while the module is imported)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


#: Every module of the package: Python files, and C extension modules by their source (``_decode_kernel.c``),
#: which import nothing of the package.
MODULES = {_module_name(p): p for p in sorted([*PACKAGE.rglob("*.py"), *PACKAGE.rglob("*.c")])}


def _top(module: str) -> str:
    """The layer entry of a ``davis_rig`` module: its top-level package or module (``__init__`` for the root)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _source_of(module: str, node: ast.ImportFrom) -> str:
    """The absolute module an ``ImportFrom`` of ``module`` reads from (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = module.split(".") if MODULES[module].name == "__init__.py" else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(module: str) -> tuple[Import, ...]:
    """Every reference of ``module`` to a ``davis_rig`` module, wherever it stands in the file."""
    return _imports_in(module, MODULES[module])


@functools.cache
def _imports_in(module: str, path: Path) -> tuple[Import, ...]:
    if path.suffix != ".py":
        return ()
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [Import(alias.name, node.lineno, False) for alias in node.names
                      if alias.name.split(".")[0] == "davis_rig"]
        elif isinstance(node, ast.ImportFrom):
            source = _source_of(module, node)
            if source.split(".")[0] == "davis_rig":
                found += [Import(f"{source}.{alias.name}" if f"{source}.{alias.name}" in MODULES else source,
                                 node.lineno, False) for alias in node.names]
        elif isinstance(node, ast.Dict):
            found += [Import(key.value, key.lineno, True) for key in node.keys
                      if isinstance(key, ast.Constant) and isinstance(key.value, str) and key.value in MODULES]
    return tuple(found)


def upward_imports() -> list[str]:
    """Every import against :data:`LAYERS`, as ``"file:line: a imports b, but 'pkg' may import only [...]"``."""
    problems = []
    for module, path in MODULES.items():
        own = _top(module)
        below = sorted(name for name, i in LAYER_OF.items() if i < LAYER_OF.get(own, -1))
        for imp in imports_of(module):
            other = _top(imp.target)
            if other != own and other in LAYER_OF and own in LAYER_OF and LAYER_OF[other] >= LAYER_OF[own]:
                where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
                problems.append(f"{where}:{imp.line}: {module} imports {imp.target}, but {own!r} may import only "
                                f"{below}")
    return problems


def import_cycles() -> list[list[str]]:
    """Cycles of the module import graph (imports at module level and in functions; lazy-export tables are not
    imports at import time): the strongly connected components of more than one module (Tarjan, iterative)."""
    graph = {m: sorted({i.target for i in imports_of(m) if not i.lazy and i.target in MODULES and i.target != m})
             for m in MODULES}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []
    for start in graph:
        if start in index:
            continue
        index[start] = low[start] = len(index)
        stack.append(start)
        work = [(start, iter(graph[start]))]
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    work.append((child, iter(graph[child])))
                elif child in stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = stack[stack.index(node):]
                del stack[stack.index(node):]
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def test_every_package_has_a_layer():
    unplaced = sorted({_top(m) for m in MODULES} - set(LAYER_OF))
    assert not unplaced, f"davis_rig packages in no layer (place them in LAYERS of {Path(__file__).name}): {unplaced}"


def test_no_upward_import():
    problems = upward_imports()
    assert not problems, "imports against the layer order:\n" + "\n".join(problems)


def test_no_import_cycle():
    cycles = import_cycles()
    assert not cycles, "import cycles between modules:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_package_docstring_lists_the_layers_in_order():
    doc = (PACKAGE / "__init__.py").read_text(encoding="utf-8")
    listed = [name for line in doc.splitlines() if line.startswith("- ``")
              for name in re.findall(r"``(\w+)``", line.split(":")[0])]
    assert listed == [name for layer in LAYERS for name in layer if name not in ("__init__", "_lazy")]


@pytest.mark.parametrize(("source", "named"), [
    ("from davis_rig.cli.common import run_main\n", "imports davis_rig.cli.common"),
    ("def later():\n    from davis_rig.attack import optimize\n", "imports davis_rig.attack.optimize"),
    ("import davis_rig.device.camera\n", None),  # device is below scene: allowed
    ("from ..training import synthetic\n", "imports davis_rig.training.synthetic"),
    ('TABLE = {"davis_rig.attack.optimize": ("optimize_texture",)}\n', "imports davis_rig.attack.optimize"),
])
def test_an_upward_import_is_named(tmp_path, monkeypatch, source, named):
    """The check itself, on a probe module placed in ``scene``: a later layer's import, at module level, in a
    function, relative or in a lazy table, fails with its line and target; an earlier layer's passes."""
    probe = tmp_path / "probe.py"
    probe.write_text(source, encoding="utf-8")
    monkeypatch.setitem(MODULES, "davis_rig.scene.probe", probe)
    problems = [p for p in upward_imports() if "davis_rig.scene.probe " in p]
    if named is None:
        assert problems == []
    else:
        assert len(problems) == 1 and named in problems[0] and "'scene' may import only" in problems[0], problems


def test_a_cycle_is_named(tmp_path, monkeypatch):
    first, second = tmp_path / "first.py", tmp_path / "second.py"
    first.write_text("from davis_rig.events import second\n", encoding="utf-8")
    second.write_text("def later():\n    from davis_rig.events import first\n", encoding="utf-8")
    monkeypatch.setitem(MODULES, "davis_rig.events.first", first)
    monkeypatch.setitem(MODULES, "davis_rig.events.second", second)
    assert ["davis_rig.events.first", "davis_rig.events.second"] in import_cycles()
