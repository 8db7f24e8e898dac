"""Every third-party module that gscan, its tests and its tools import is declared in pyproject.toml.

A module imported but not declared installs on the developer's machine (where it came with something else) and
fails on a user's. The imports are read from the source with `ast` (every `import` statement, also those inside
functions; not those under `if TYPE_CHECKING:`, which only the type checker runs); the standard library
(`sys.stdlib_module_names`), gscan itself and the modules of the folder being walked are left out; an import
name is mapped to the distributions that provide it (`importlib.metadata.packages_distributions()`, else the
name itself).

- gscan/: each import is a `dependencies` entry; one that only an optional extra provides (ray: the batch extra)
  or whose entry has an environment marker (pyrealsense2: x86-64 only) is imported inside a function, so that
  `import gscan` works without it, except in the extra's own package (gscan/ros2 for the ros2 extra: its modules
  load only after `gscan.ros2.require_rclpy()`). The test extra's packages are not gscan's; an extra that names
  another (`gscan[ros2]`) declares that one's packages too.
- tests/, bench/, web/, samples/: `dependencies` or the test extra.
"""
from __future__ import annotations

import ast
import functools
import importlib.metadata
import re
import sys
from dataclasses import dataclass
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - the test extra's tomli (pytest's own dependency there)
    import tomli as tomllib

from tests.conftest import ROOT

# every wheel of OpenCV provides cv2: an import of cv2 is declared by any of them
ALIKE = {"cv2": {"opencv-python", "opencv-python-headless", "opencv-contrib-python",
                 "opencv-contrib-python-headless"}}
TOOL_FOLDERS = ("tests", "bench", "web", "samples")  # code that runs with the test extra installed


@dataclass(frozen=True)
class Import:
    module: str  # the top-level name imported ("cv2" for `from cv2 import imread`)
    path: Path
    line: int
    lazy: bool  # inside a function: imported when it is called, not when its module is


@dataclass(frozen=True)
class Declared:
    required: frozenset[str]  # normalised names of `dependencies` entries without an environment marker
    conditional: frozenset[str]  # `dependencies` entries with a marker (installed on some machines only)
    extras: dict[str, frozenset[str]]  # optional extra -> the names it declares


def normalise(name: str) -> str:
    """A distribution's name as PEP 503 compares it ("PyYAML" -> "pyyaml", "mcap_ros2" -> "mcap-ros2")."""
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement_name(req: str) -> str:
    """The distribution a PEP 508 requirement names ("numpy>=1.24" -> "numpy")."""
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
    assert m, f"not a requirement: {req!r}"
    return normalise(m.group(1))


def declared(pyproject: dict) -> Declared:
    deps = pyproject["project"].get("dependencies", [])
    extras = pyproject["project"].get("optional-dependencies", {})
    named = {k: frozenset(requirement_name(r) for r in v) for k, v in extras.items()}

    def expanded(names: frozenset[str]) -> frozenset[str]:  # "gscan[ros2]" in an extra: the ros2 extra's names
        own = [r for v in extras.values() for r in v if requirement_name(r) == "gscan"]
        inner = {m.group(1) for r in own for m in [re.search(r"\[([^\]]+)\]", r)] if m}
        return names | frozenset().union(*(named.get(x, frozenset()) for x in inner)) if "gscan" in names else names

    return Declared(frozenset(requirement_name(r) for r in deps if ";" not in r),
                    frozenset(requirement_name(r) for r in deps if ";" in r),
                    {k: expanded(v) for k, v in named.items()})


def _type_checking_only(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports(path: Path) -> list[Import]:
    """The absolute imports of the Python file `path` (not `__future__`, not under `if TYPE_CHECKING:`)."""
    found: list[Import] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        if isinstance(node, ast.If) and _type_checking_only(node):
            for child in node.orelse:
                visit(child, lazy)
            return
        if isinstance(node, ast.Import):
            found.extend(Import(a.name.split(".")[0], path, node.lineno, lazy) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and node.module != "__future__":
            found.append(Import(node.module.split(".")[0], path, node.lineno, lazy))
        inner = lazy or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        for child in ast.iter_child_nodes(node):
            visit(child, inner)

    visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), False)
    return found


def local_names(folder: Path) -> set[str]:
    """Modules a file under `folder` imports by its own name: the folder's package name and its .py files and
    packages at any depth (bench/real.py imports `peers`, bench/peers.py)."""
    names = {folder.name}
    for p in folder.rglob("*"):
        if p.suffix == ".py":
            names.add(p.stem)
        elif p.is_dir() and (p / "__init__.py").is_file():
            names.add(p.name)
    return names


def third_party(found: list[Import], local: set[str]) -> list[Import]:
    skip = set(sys.stdlib_module_names) | {"gscan"} | local
    return [i for i in found if i.module not in skip]


@functools.cache
def _installed() -> dict[str, list[str]]:
    return importlib.metadata.packages_distributions()  # reads every installed distribution's files: once


def providers(module: str) -> set[str]:
    """The distributions that may provide the import name `module` (normalised)."""
    installed = _installed().get(module, [module])
    return {normalise(d) for d in installed} | ALIKE.get(module, set())


def problems(found: list[Import], decl: Declared, library: bool) -> list[str]:
    """One message per import that `decl` does not declare: for the library (`library`) against `dependencies`,
    imported lazily where only an optional extra or a marked entry provides it; for tools against `dependencies`
    and the test extra."""
    out = []
    optional = decl.conditional | frozenset().union(*(v for k, v in decl.extras.items() if k != "test"))
    for i in found:
        where = f"{i.path.relative_to(ROOT) if i.path.is_relative_to(ROOT) else i.path}:{i.line}: {i.module}"
        dists = providers(i.module)
        if dists & decl.required:
            continue
        if library:
            if not dists & optional:
                out.append(f"{where}: not in pyproject's dependencies ({', '.join(sorted(dists))})")
            elif not i.lazy and not any(dists & v and i.path.is_relative_to(ROOT / "gscan" / k)
                                        for k, v in decl.extras.items()):
                out.append(f"{where}: optional ({', '.join(sorted(dists & optional))}) but imported at module level")
        elif not dists & (decl.conditional | decl.extras.get("test", frozenset())):
            out.append(f"{where}: neither a dependency nor in the test extra ({', '.join(sorted(dists))})")
    return out


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _library_imports() -> list[Import]:
    return third_party([i for p in sorted((ROOT / "gscan").rglob("*.py")) for i in imports(p)], set())


def test_library_imports_are_declared():
    found = _library_imports()
    assert {i.module for i in found} >= {"numpy", "cv2", "open3d", "ray"}  # the walk sees gscan's imports
    assert problems(found, declared(_pyproject()), library=True) == []


def test_tool_imports_are_declared():
    decl = declared(_pyproject())
    local = set().union(*(local_names(ROOT / f) for f in TOOL_FOLDERS))  # tests import web/ and bench/ modules
    found = third_party([i for f in TOOL_FOLDERS for p in sorted((ROOT / f).rglob("*.py")) for i in imports(p)], local)
    assert {i.module for i in found} >= {"pytest", "hypothesis", "numpy"}
    assert problems(found, decl, library=False) == []


def test_an_undeclared_or_eager_optional_import_is_found(tmp_path: Path):
    """The check fails where it must: on gscan's own imports against a pyproject without one of its
    dependencies (rich), and on synthetic modules that import an optional extra's package (ray) or a marked
    dependency (pyrealsense2) at module level, a test-only package (pytest) in the library, or import what
    nothing declares."""
    pyproject = _pyproject()
    reqs = pyproject["project"]["dependencies"]
    pyproject["project"]["dependencies"] = [r for r in reqs if requirement_name(r) != "rich"]
    assert len(pyproject["project"]["dependencies"]) == len(reqs) - 1
    missing = problems(_library_imports(), declared(pyproject), library=True)
    assert missing and all(m.endswith(": rich: not in pyproject's dependencies (rich)") for m in missing), missing

    decl = declared(_pyproject())
    src = tmp_path / "mod.py"
    src.write_text("import ray\nimport pyrealsense2 as rs\nfrom pytest import approx\nimport nosuchpackage_x\n"
                   "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import nosuchpackage_y\n"
                   "def f():\n    import ray\n    import pyrealsense2\n")
    found = third_party(imports(src), set())
    assert [(i.module, i.lazy) for i in found] == [("ray", False), ("pyrealsense2", False), ("pytest", False),
                                                   ("nosuchpackage_x", False), ("ray", True), ("pyrealsense2", True)]
    msgs = problems(found, decl, library=True)
    assert [m.split(": ", 2)[1:] for m in msgs] == [
        ["ray", "optional (ray) but imported at module level"],
        ["pyrealsense2", "optional (pyrealsense2) but imported at module level"],
        ["pytest", "not in pyproject's dependencies (pytest)"],
        ["nosuchpackage_x", "not in pyproject's dependencies (nosuchpackage-x)"]], msgs
    tool_msgs = problems(found, decl, library=False)  # tools: pytest and ray are the test extra's
    assert [m.split(": ", 2)[1] for m in tool_msgs] == ["nosuchpackage_x"], tool_msgs


def test_an_import_name_maps_to_its_distribution():
    assert normalise("PyYAML") == "pyyaml" and requirement_name("mcap-ros2-support>=0.5") == "mcap-ros2-support"
    assert requirement_name("pyrealsense2>=2.54; platform_machine == 'x86_64'") == "pyrealsense2"
    assert "pyyaml" in providers("yaml") and "pillow" in providers("PIL")
    assert "opencv-python-headless" in providers("cv2")
