"""The package's import graph: data flows one way through the stages, and no modules import each other in a cycle.

Every `import` and `from ... import` statement of every module under gscan/ counts, wherever it stands: at
module level, inside a function, under `if TYPE_CHECKING:`. `from gscan.a import b` depends on `gscan.a` and,
when `b` is a module, on `gscan.a.b`. A module may import modules of its own or an earlier stage; within a
stage the imports must not form a cycle. A module whose stage is not listed fails the test: place it.
"""
from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

PACKAGE = ROOT / "gscan"

# earliest first; a module belongs to the longest prefix listed
STAGES: list[tuple[str, ...]] = [
    ("gscan.errors", "gscan.progress", "gscan._lazy", "gscan._version", "gscan.threads", "gscan.settings",
     "gscan.signals"),
    ("gscan.geometry",),
    ("gscan.io",),
    ("gscan.capture",),  # records captures from a camera or a recording (input, like io)
    ("gscan.features",),
    ("gscan.matching",),
    ("gscan.registration",),
    ("gscan.template",),
    ("gscan.synth",),
    ("gscan.scanning",),
    ("gscan.estimate",),
    ("gscan.evaluate",),
    ("gscan.exporters",),
    ("gscan.viewer",),
    ("gscan.service", "gscan.ros2", "gscan.batch", "gscan.client", "gscan.demo"),
    ("gscan.cli", "gscan"),  # the command line, and the package's public API (gscan/__init__.py)
]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def stage_of(module: str) -> int | None:
    best, best_len = None, -1
    for k, prefixes in enumerate(STAGES):
        for pre in prefixes:
            if (module == pre or module.startswith(pre + ".")) and len(pre) > best_len:
                best, best_len = k, len(pre)
    return best


def imports_of(module: str, source: str, is_pkg: bool, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported gscan module, line) for every import statement of the module's source, at any depth."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for a in node.names:
                name = a.name
                while name and name not in modules:  # `import gscan.a.b` imports gscan.a.b
                    name = name.rpartition(".")[0]
                if name:
                    out.append((name, node.lineno))
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the module's package
                base = module.split(".") if is_pkg else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            if src in modules:
                out.append((src, node.lineno))
            for a in node.names:
                if f"{src}.{a.name}" in modules:
                    out.append((f"{src}.{a.name}", node.lineno))
    return out


def import_graph() -> dict[str, list[tuple[str, int]]]:
    modules = all_modules()
    return {m: [(t, line) for t, line in imports_of(m, p.read_text(encoding="utf-8"), p.name == "__init__.py", modules)
                if t != m] for m, p in modules.items()}


def cycles(graph: dict[str, list[tuple[str, int]]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w, _ in graph.get(v, []):
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
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_every_module_has_a_stage():
    unplaced = [m for m in all_modules() if stage_of(m) is None]
    assert not unplaced, f"modules without a stage (add them to STAGES in {Path(__file__).name}): {unplaced}"


def test_no_stage_imports_a_later_one():
    graph = import_graph()
    bad = []
    for m, targets in graph.items():
        for t, line in targets:
            sm, st = stage_of(m), stage_of(t)
            if sm is not None and st is not None and st > sm:
                bad.append(f"{all_modules()[m].relative_to(ROOT)}:{line}: {m} imports the later stage {t}")
    assert not bad, "\n".join(bad)


def test_no_import_cycle():
    found = cycles(import_graph())
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_the_graph_walk_sees_what_it_must():
    """The walk finds imports inside functions and under TYPE_CHECKING, resolves `from pkg import module` and
    relative imports, and the checks fail on a later-stage import and on a cycle."""
    src = ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from gscan.viewer.app import ViewerApp\n"
           "def f():\n    from gscan.exporters import bop\n    from . import camera\n"
           "    import gscan.scanning.pipeline\n")
    got = {t for t, _ in imports_of("gscan.io._graph_probe", src, False, all_modules())}
    assert got == {"gscan.viewer.app", "gscan.exporters", "gscan.exporters.bop", "gscan.io", "gscan.io.camera",
                   "gscan.scanning.pipeline"}
    assert stage_of("gscan.io.camera") < stage_of("gscan.viewer.app")
    assert cycles({"a": [("b", 1)], "b": [("c", 1)], "c": [("a", 1)], "d": [("a", 1)]}) == [["a", "b", "c"]]
    assert cycles({"a": [("b", 1)], "b": []}) == []


def test_registration_sees_no_scan_template_or_command_line():
    """Sequence registration takes its own settings and a small frame interface: no module of gscan.registration
    imports gscan.scanning (ScanConfig, ScanOptions), gscan.template (TemplateDB) or gscan.cli, at any depth."""
    banned = ("gscan.scanning", "gscan.template", "gscan.cli")
    bad = [f"{all_modules()[m].relative_to(ROOT)}:{line}: {m} imports {t}"
           for m, targets in import_graph().items() if m == "gscan.registration" or m.startswith("gscan.registration.")
           for t, line in targets if any(t == b or t.startswith(b + ".") for b in banned)]
    assert not bad, "\n".join(bad)
