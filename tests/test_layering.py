"""The package's import graph: no cycles, no upward arrows (physics ← drivers ← control ←
bench ← gui/cli). Static, from the sources: module-level and function-level imports alike."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ROOTS = {  # source folder → the package it installs as (pyproject's package-dir)
    REPO / "smabench": "smabench",
    REPO / "drivers": "smabench.drivers",
    REPO / "firmware" / "hardware": "smabench.hardware",
    REPO / "sessions" / "samples": "smabench.samples",
}


def import_graph() -> dict[str, set[str]]:
    files: dict[str, Path] = {}
    for base, pkg in ROOTS.items():
        for f in base.rglob("*.py"):
            parts = [p for p in f.relative_to(base).with_suffix("").parts if p != "__init__"]
            files[".".join([pkg, *parts])] = f
    graph: dict[str, set[str]] = {}
    for mod, f in files.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module:
                deps.add(node.module)
                deps |= {f"{node.module}.{a.name}" for a in node.names}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
        graph[mod] = {d for d in deps if d in files and d != mod}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_no_upward_imports():
    allowed = {  # a layer may import itself and what is listed
        "smabench.physics": ("smabench.physics",),
        "smabench.hardware": ("smabench.hardware",),
        "smabench.drivers": ("smabench.drivers", "smabench.physics", "smabench.hardware"),
        "smabench.control": ("smabench.control", "smabench.physics", "smabench.hardware",
                             "smabench.commands", "smabench.protocols", "smabench.settings"),
        # the bench runtime: below the GUI, the CLI's commands, the calibration commands and the
        # analysis (it reads the calibration store, never the commands that write it)
        "smabench.bench": ("smabench.bench", "smabench.control", "smabench.physics",
                           "smabench.hardware", "smabench.drivers", "smabench.commands",
                           "smabench.protocols", "smabench.settings", "smabench.sessions",
                           "smabench.calibration_store", "smabench.argtypes", "smabench.tasks",
                           "smabench"),  # the last: the package's own __init__ (its version)
    }  # fmt: skip

    def within(dep: str, ok: tuple[str, ...]) -> bool:
        return any(dep == x or (x != "smabench" and dep.startswith(x + ".")) for x in ok)

    wrong = [
        f"{mod} imports {dep}"
        for mod, deps in import_graph().items()
        for layer, ok in allowed.items()
        if mod == layer or mod.startswith(layer + ".")
        for dep in deps
        if not within(dep, ok)
    ]
    assert wrong == []
