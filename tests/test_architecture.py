"""The layers of lmpromp_ppl (docs/architecture.md): no import against the layer order, no import cycle.

Every ``import`` and ``from ... import`` of every module is read, at module
level and inside functions, from the source (``ast``), so an import that runs
only in some code path counts too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "lmpromp_ppl"

#: Layer of each part of the package, lowest first (docs/architecture.md).
LAYERS = {
    "lmpromp_ppl._config": 0, "lmpromp_ppl._keys": 0, "lmpromp_ppl._progress": 0, "lmpromp_ppl.errors": 0,
    "lmpromp_ppl.outputs": 0, "lmpromp_ppl.basis": 0,
    "lmpromp_ppl.data": 1,
    "lmpromp_ppl.models": 2,
    "lmpromp_ppl.inference": 3,
    "lmpromp_ppl.results": 4, "lmpromp_ppl.quantities": 4, "lmpromp_ppl.predict": 4,
    "lmpromp_ppl.diagnostics": 5,
    "lmpromp_ppl.api": 6, "lmpromp_ppl": 6,
    "lmpromp_ppl.reports": 7, "lmpromp_ppl.reproduce": 7, "lmpromp_ppl.calibration": 7, "lmpromp_ppl.bench": 7,
    "lmpromp_ppl.cli": 8,
}
NAMES = ["base", "data", "models", "inference", "results", "diagnostics", "api", "reports and experiments", "cli"]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer(module: str) -> int:
    """The layer of the longest registered prefix of ``module``."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        prefix = ".".join(parts[:n])
        if prefix in LAYERS:
            return LAYERS[prefix]
    raise KeyError(module)


def imports(path: Path, modules: set[str]) -> set[str]:
    """The package modules ``path`` imports (``from a import b`` counts b when b is a module)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("lmpromp_ppl")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("lmpromp_ppl"):
                continue
            found.add(target)
            found |= {f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in modules}
    return {m for m in found if m in modules and m != name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    paths = sorted(ROOT.rglob("*.py"))
    modules = {module_name(p) for p in paths}
    return {module_name(p): imports(p, modules) for p in paths}


def test_every_module_has_a_layer(graph):
    for module in graph:
        layer(module)


def _violations(graph: dict[str, set[str]]) -> list[str]:
    """Imports of a higher layer (a package may import its own submodules, and the root re-exports)."""
    return [
        f"{m} ({NAMES[layer(m)]}) imports {t} ({NAMES[layer(t)]})"
        for m, targets in graph.items() for t in sorted(targets)
        if layer(t) > layer(m) and not (m == "lmpromp_ppl" or t.startswith(m + "."))
    ]


def test_no_import_against_the_layer_order(graph):
    violations = _violations(graph)
    assert not violations, "\n".join(violations)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), ignoring package parents.

    ``import a.b`` runs ``a/__init__.py``; a package importing its own submodules
    (re-exports) and the submodules importing siblings is not a cycle of the code.
    """
    edges = {m: {t for t in ts if not t.startswith(m + ".") and not m.startswith(t + ".")} for m, ts in graph.items()}
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in edges:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles(graph):
    cycles = _cycles(graph)
    assert not cycles, cycles


def test_the_checks_see_a_violation_and_a_cycle(graph):
    """The checks are not vacuous: a made-up upward import and a made-up cycle are found."""
    upward = dict(graph, **{"lmpromp_ppl.data.core": graph["lmpromp_ppl.data.core"] | {"lmpromp_ppl.cli._common"}})
    assert _violations(upward) == ["lmpromp_ppl.data.core (data) imports lmpromp_ppl.cli._common (cli)"]
    looped = dict(graph, **{"lmpromp_ppl.models.hyper": graph["lmpromp_ppl.models.hyper"] | {"lmpromp_ppl.models.lmpromp"}})
    assert ["lmpromp_ppl.models.hyper", "lmpromp_ppl.models.lmpromp"] in _cycles(looped)
    # function-level imports are read: the API imports the engines inside functions
    assert "lmpromp_ppl.inference.cavi" in graph["lmpromp_ppl.api"]
