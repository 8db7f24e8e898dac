"""Every benchmark in bench/ still imports after a restructure: its module body runs (not its main), and every
import statement in it, also those inside functions, names a module and names that exist.

The benchmarks are checked one after another in one fresh interpreter, as `python bench/x.py` from the repository
root would see them (bench/ and the repository on sys.path; benchmarks import each other by file name: bench/real.py
runs bench/peers.py's odometry chain). Between two benchmarks sys.path is restored and the modules loaded from
bench/ are dropped, so each benchmark imports its siblings afresh; the heavy libraries are imported once."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.conftest import ROOT

BENCHES = sorted((ROOT / "bench").glob("*.py"))

# run in a fresh interpreter with the benchmarks' paths as arguments; prints {stem: [broken import, ...]} as JSON,
# a module body that raises counted as broken
CHECK = r"""
import ast, importlib, importlib.util, json, sys, traceback
from pathlib import Path


def check(path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    spec.loader.exec_module(module)  # the module body; __name__ is not "__main__", so main() does not run
    broken = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                try:
                    importlib.import_module(alias.name)
                except ImportError as e:
                    broken.append(f"line {node.lineno}: import {alias.name}: {e}")
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module != "__future__":
            try:
                source = importlib.import_module(node.module)
            except ImportError as e:
                broken.append(f"line {node.lineno}: from {node.module}: {e}")
                continue
            for alias in node.names:
                if alias.name == "*" or hasattr(source, alias.name):
                    continue
                try:  # a submodule not imported by its package
                    importlib.import_module(f"{node.module}.{alias.name}")
                except ImportError:
                    broken.append(f"line {node.lineno}: {node.module} has no {alias.name}")
    return broken


out = {}
for arg in sys.argv[1:]:
    path = Path(arg)
    saved_path = list(sys.path)
    sys.path[:0] = [str(path.parent), str(path.parents[1])]  # as `python bench/x.py` from the repository root
    try:
        out[path.stem] = check(path)
    except BaseException:  # a module body that raises or exits
        out[path.stem] = [traceback.format_exc(limit=-3)]
    sys.path[:] = saved_path
    for name, mod in list(sys.modules.items()):  # the benchmarks and siblings loaded from bench/
        if Path(getattr(mod, "__file__", None) or "/").parent == path.parent:
            del sys.modules[name]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def broken(tmp_path_factory) -> dict[str, list[str]]:
    """Benchmark stem -> its broken imports (empty: all import)."""
    r = subprocess.run([sys.executable, "-c", CHECK, *map(str, BENCHES)], capture_output=True, text=True,
                       timeout=600, cwd=tmp_path_factory.mktemp("bench_imports"))
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.splitlines()[-1])


def test_bench_holds_the_benchmarks():
    assert {p.stem for p in BENCHES} >= {"estimate", "match", "peers", "real", "recall", "scan", "speed"}


@pytest.mark.parametrize("path", BENCHES, ids=[p.stem for p in BENCHES])
def test_benchmark_imports(path, broken):
    assert broken[path.stem] == [], f"{path.name}:\n" + "\n".join(broken[path.stem])
