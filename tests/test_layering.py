"""The package's layers (docs/design.md §7): every import points down, and no import goes in a circle.

Every ``.py`` under ``warpnerf/`` and ``kernels/`` (shipped as ``warpnerf.kernels``) is read with ``ast``
(nothing is imported), and every import in it is collected: top level and inside functions; only imports
under ``if TYPE_CHECKING:`` are left out (they never run). Then

1. no module imports from a higher layer than its own (:data:`LAYERS`);
2. the kernels import neither torch nor any of warpnerf but ``warpnerf.kernels`` itself;
3. the module import graph (every import that runs, function-level ones included) has no cycle;
4. an import inside a function says why on its line (or the line before): ``# lazy: ...`` to keep
   ``warpnerf --help`` fast, ``# optional extra``, ...; anything else belongs at the top of the module.

The checks are plain functions over ``{module: source}``, so the last tests plant violations in small
made-up packages and make sure each check catches them.
"""

from __future__ import annotations

import ast
import pathlib
from dataclasses import dataclass

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

# docs/design.md §7, lowest first; a module's layer is that of the longest name here that is it or a
# package holding it
LAYERS = {
    "warpnerf": 1,  # base: the package root (__version__), device and openmp, the kernels
    "warpnerf.device": 1,
    "warpnerf.openmp": 1,
    "warpnerf.kernels": 1,
    "warpnerf.ops": 2,
    "warpnerf.geometry": 3,
    "warpnerf.data": 4,
    "warpnerf.model": 5,
    "warpnerf.train": 6,
    "warpnerf.runs": 7,
    "warpnerf.outputs": 8,
    "warpnerf.studies": 9,
    "warpnerf.cli": 10,
}


@dataclass(frozen=True)
class Import:
    module: str  # the importing module
    target: str  # dotted name imported (a module where one by that name exists)
    line: int
    in_function: bool
    commented: bool  # a '#' comment on the import's lines or on the line before


def package_sources(root: pathlib.Path = ROOT) -> dict[str, tuple[str, str]]:
    """``{module name: (path, source)}`` of the package: warpnerf/ and kernels/ (as warpnerf.kernels)."""
    out = {}
    for base, prefix in ((root / "warpnerf", ["warpnerf"]), (root / "kernels", ["warpnerf", "kernels"])):
        for path in sorted(base.rglob("*.py")):
            parts = prefix + list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = (str(path.relative_to(root)), path.read_text(encoding="utf-8"))
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def collect_imports(module: str, source: str, is_package: bool, known: set[str]) -> list[Import]:
    """Every import of ``module`` that runs: relative ones resolved, ``from a import b`` naming the
    module ``a.b`` where there is one, else ``a``."""
    lines = source.splitlines()
    package = module if is_package else module.rpartition(".")[0]
    found: list[Import] = []

    def commented(node: ast.stmt) -> bool:
        span = lines[node.lineno - 1: node.end_lineno]
        before = lines[node.lineno - 2].strip() if node.lineno >= 2 else ""
        return any("#" in text for text in span) or before.startswith("#")

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                for other in child.orelse:  # 'else:' of a TYPE_CHECKING block runs
                    visit(other, in_function)
                continue
            if isinstance(child, ast.Import):
                for alias in child.names:
                    found.append(Import(module, alias.name, child.lineno, in_function, commented(child)))
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[: len(base) - (child.level - 1)]
                    source_module = ".".join(base + ([child.module] if child.module else []))
                else:
                    source_module = child.module or ""
                targets = dict.fromkeys(f"{source_module}.{a.name}" if f"{source_module}.{a.name}" in known
                                        else source_module for a in child.names)
                found.extend(Import(module, t, child.lineno, in_function, commented(child)) for t in targets)
            else:
                inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
                visit(child, inner)

    visit(ast.parse(source), False)
    return found


def all_imports(sources: dict[str, tuple[str, str]]) -> list[Import]:
    known = set(sources)
    out = []
    for module, (path, source) in sources.items():
        out += collect_imports(module, source, path.endswith("__init__.py"), known)
    return out


def layer_of(module: str, layers: dict[str, int] = LAYERS) -> int | None:
    """The layer of a warpnerf module (None outside the package, or for a module no layer holds: the
    package root counts only for itself, so a new top-level module has to be placed here)."""
    if module == "warpnerf":
        return layers["warpnerf"]
    parts = module.split(".")
    for n in range(len(parts), 1, -1):
        name = ".".join(parts[:n])
        if name in layers:
            return layers[name]
    return None


def upward_imports(imports: list[Import], layers: dict[str, int] = LAYERS) -> list[str]:
    out = []
    for imp in imports:
        src, dst = layer_of(imp.module, layers), layer_of(imp.target, layers)
        if dst is not None and src is not None and dst > src:
            out.append(f"{imp.module}:{imp.line} imports {imp.target} (layer {src} -> layer {dst})")
    return out


def kernel_violations(imports: list[Import]) -> list[str]:
    out = []
    for imp in imports:
        if not imp.module.startswith("warpnerf.kernels"):
            continue
        top = imp.target.split(".")[0]
        if top == "torch" or (top == "warpnerf" and not imp.target.startswith("warpnerf.kernels")):
            out.append(f"{imp.module}:{imp.line} imports {imp.target} (kernels: Warp only, no torch, no warpnerf)")
    return out


def find_cycles(imports: list[Import], modules: set[str]) -> list[list[str]]:
    """One cycle (as a path that returns to its start) per strongly connected component of the graph."""
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for imp in imports:
        if imp.target in modules:
            graph[imp.module].add(imp.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def strongconnect(v: str) -> None:  # Tarjan, recursive: the graph has ~100 nodes
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strongconnect(w)
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
            if len(comp) > 1 or v in graph[v]:
                components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)

    cycles = []
    for comp in components:  # a shortest way round, from the component's first module back to it
        members, start = set(comp), comp[0]
        if start in graph[start]:
            cycles.append([start, start])
            continue
        prev: dict[str, str | None] = {start: None}
        queue, last = [start], None
        while last is None:  # an SCC of two or more modules always leads back to start
            v = queue.pop(0)
            for w in sorted(graph[v] & members):
                if w == start:
                    last = v
                    break
                if w not in prev:
                    prev[w] = v
                    queue.append(w)
        path = [last]
        while prev[path[-1]] is not None:
            path.append(prev[path[-1]])
        cycles.append(path[::-1] + [start])
    return cycles


def uncommented_function_imports(imports: list[Import]) -> list[str]:
    return [f"{imp.module}:{imp.line} imports {imp.target} inside a function without a '# why' comment"
            for imp in imports if imp.in_function and not imp.commented]


# --- the package ----------------------------------------------------------------------------------

SOURCES = package_sources()
IMPORTS = all_imports(SOURCES)


def test_every_module_has_a_layer():
    assert [m for m in SOURCES if layer_of(m) is None] == [], "place new modules in a layer's package (LAYERS)"
    assert "warpnerf.kernels.hashgrid" in SOURCES and "warpnerf.cli" in SOURCES  # the walk found both trees


def test_no_module_imports_from_a_higher_layer():
    bad = upward_imports(IMPORTS)
    assert not bad, "imports from a higher layer:\n" + "\n".join(bad)


def test_kernels_import_only_warp_and_each_other():
    bad = kernel_violations(IMPORTS)
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    cycles = find_cycles(IMPORTS, set(SOURCES))
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_function_level_imports_say_why():
    bad = uncommented_function_imports(IMPORTS)
    assert not bad, "\n".join(bad)


# --- the checks catch what they are for -----------------------------------------------------------

PLANTED = {
    "warpnerf": ("warpnerf/__init__.py", ""),
    "warpnerf.kernels": ("kernels/__init__.py", ""),
    "warpnerf.kernels.k": ("kernels/k.py", "import warp as wp\nimport torch\nfrom warpnerf.ops import launch\n"),
    "warpnerf.ops": ("warpnerf/ops/__init__.py", ""),
    "warpnerf.ops.launch": ("warpnerf/ops/launch.py", "from warpnerf.kernels import k\n"),
    "warpnerf.model": ("warpnerf/model/__init__.py", ""),
    "warpnerf.model.field": ("warpnerf/model/field.py",
                             "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from warpnerf.train import trainer\n"
                             "def f():\n    from warpnerf.train.config import X\n"),
    "warpnerf.train": ("warpnerf/train/__init__.py", ""),
    "warpnerf.train.trainer": ("warpnerf/train/trainer.py", "from . import tasks\n"),
    "warpnerf.train.tasks": ("warpnerf/train/tasks.py",
                             "def hook():\n    from warpnerf.train.trainer import Trainer  # lazy: a cycle\n"),
    "warpnerf.train.config": ("warpnerf/train/config.py", "X = 1\n"),
}


def test_the_checks_catch_planted_violations():
    imports = all_imports(PLANTED)
    # an import inside a function, not under TYPE_CHECKING, from layer 5 (model) up to layer 6 (train)
    assert upward_imports(imports) == ["warpnerf.kernels.k:3 imports warpnerf.ops.launch (layer 1 -> layer 2)",
                                       "warpnerf.model.field:5 imports warpnerf.train.config (layer 5 -> layer 6)"]
    assert kernel_violations(imports) == [
        "warpnerf.kernels.k:2 imports torch (kernels: Warp only, no torch, no warpnerf)",
        "warpnerf.kernels.k:3 imports warpnerf.ops.launch (kernels: Warp only, no torch, no warpnerf)"]
    # a same-layer cycle through a (commented) function-level import, and one across layers
    cycles = find_cycles(imports, set(PLANTED))
    assert sorted(cycles) == [["warpnerf.kernels.k", "warpnerf.ops.launch", "warpnerf.kernels.k"],
                              ["warpnerf.train.tasks", "warpnerf.train.trainer", "warpnerf.train.tasks"]]
    assert uncommented_function_imports(imports) == [
        "warpnerf.model.field:5 imports warpnerf.train.config inside a function without a '# why' comment"]


@pytest.mark.parametrize("source, expected", [
    ("def f():\n    import os  # stdlib\n", True),
    ("def f():\n    # optional extra\n    import viser\n", True),
    ("def f():\n    from warpnerf.ops import (\n        launch,  # lazy: warp\n    )\n", True),
    ("def f():\n    x = 1\n    import os\n", False),
])
def test_a_comment_on_the_line_or_the_line_before_counts(source, expected):
    (imp,) = collect_imports("warpnerf.m", source, False, {"warpnerf.ops.launch"})
    assert imp.in_function and imp.commented is expected
