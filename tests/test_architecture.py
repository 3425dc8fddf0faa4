"""The house rules of DESIGN.md read from the code's own imports: data flows one way, no import cycles.

Every ``import terralod...`` / ``from terralod... import`` in ``src/terralod`` counts, wherever it sits
(module level, inside a function, under ``TYPE_CHECKING``): a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "terralod"

#: The shared base: pure math, kernels, the heightfield and its measured error. It imports no stage.
BASE = {"terralod.errors", "terralod.kernels", "terralod.tiles", "terralod.fill", "terralod.heightfield",
        "terralod.error", "terralod.output"}  # fmt: skip
#: Stages, in the order data flows (DESIGN.md): a stage may import stages to its left and the base.
STAGES = ["terralod.io", "terralod.fractal", "terralod.store_epochs", "terralod.store", "terralod.pyramid",
          "terralod.tin", "terralod.integrity", "terralod.runtime", "terralod.terrain", "terralod.render", "terralod.change",
          "terralod.export", "terralod.site", "terralod.serve", "terralod.warmup", "terralod.cli"]  # fmt: skip


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    name = ".".join(rel.parts)
    return name[: -len(".__init__")] if name.endswith(".__init__") else name


@functools.cache
def _imports() -> dict[str, set[str]]:
    """{module: terralod modules it imports} over every source file (parsed once per session: read only)."""
    out: dict[str, set[str]] = {}
    for f in sorted(SRC.rglob("*.py")):
        mod = _module_name(f)
        deps = out.setdefault(mod, set())
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.ImportFrom)
                and node.level == 0
                and (node.module or "").startswith("terralod")
            ):
                deps.add(node.module)  # type: ignore[arg-type]
            elif isinstance(node, ast.ImportFrom) and node.level > 0:
                pytest.fail(f"{mod}: relative import (the house uses absolute terralod.* imports)")
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name.startswith("terralod"))
    return out


def _unit(mod: str) -> str:
    """The module or sub-package a module belongs to (``terralod.runtime.select`` → ``terralod.runtime``)."""
    return ".".join(mod.split(".")[:2])


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
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
        for w in graph.get(v, ()):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _unit_graph() -> dict[str, set[str]]:
    g: dict[str, set[str]] = {}
    for mod, deps in _imports().items():
        a = _unit(mod)
        if a in ("terralod", "terralod.__main__"):
            continue  # the package facade re-exports the API; __main__ runs the CLI
        for d in deps:
            b = _unit(d)
            if b != a and b != "terralod":
                g.setdefault(a, set()).add(b)
    return g


def test_no_import_cycles_between_modules() -> None:
    graph = {m: {d for d in deps if d != m} for m, deps in _imports().items()}
    # a package's own __init__ importing its submodules is how packages re-export; drop those edges
    graph = {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}
    assert _cycles(graph) == []


def test_no_import_cycles_between_packages() -> None:
    assert _cycles(_unit_graph()) == []


def test_data_flows_one_way() -> None:
    """The base imports no stage; a stage imports only stages before it; nothing imports the CLI."""
    bad = []
    for a, deps in _unit_graph().items():
        for b in deps:
            if a in BASE and b not in BASE:
                bad.append(f"{a} (base) imports the stage {b}")
            elif a in STAGES and b in STAGES and STAGES.index(b) > STAGES.index(a):
                bad.append(f"{a} imports {b}, a later stage")
            elif a not in BASE and a not in STAGES:
                bad.append(f"{a}: not placed in DESIGN.md's flow (add it to BASE or STAGES here)")
    assert bad == []


def test_the_named_rules_of_design_md() -> None:
    g = _unit_graph()
    assert "terralod.pyramid" not in g.get("terralod.store", set()), "the store never imports the builder"
    assert "terralod.render" not in g.get("terralod.runtime", set()), "the runtime never imports the renderer"
    kernels = {d for m, deps in _imports().items() if m.startswith("terralod.kernels") for d in deps}
    assert all(d.startswith("terralod.kernels") for d in kernels), "kernels import only kernels"


def test_numba_only_in_kernels() -> None:
    """Every numba kernel lives in terralod.kernels (one decorator, one cache, one warm-up): no module
    outside it imports numba, wherever the import sits."""
    bad = []
    for f in sorted(SRC.rglob("*.py")):
        mod = _module_name(f)
        if mod == "terralod.kernels" or mod.startswith("terralod.kernels."):
            continue
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            bad += [f"{mod} imports {n}" for n in names if n == "numba" or n.startswith("numba.")]
    assert bad == []
