"""Every benchmark in bench/ still imports after a restructure: its module body runs (not its main), and every
import statement in it, also those inside functions, names a module and names that exist.

Each benchmark is checked in its own interpreter: benchmarks put bench/ or the repository on sys.path and import
each other by file name (bench/real.py runs bench/peers.py's odometry chain)."""
from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import ROOT

BENCHES = sorted((ROOT / "bench").glob("*.py"))

# run in a fresh interpreter with the benchmark's path as argv[1]; prints one line per broken import
CHECK = r"""
import ast, importlib, importlib.util, sys
from pathlib import Path

path = Path(sys.argv[1])
sys.path[:0] = [str(path.parent), str(path.parents[1])]  # as `python bench/x.py` from the repository root
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
print("\n".join(broken))
sys.exit(1 if broken else 0)
"""


def test_bench_holds_the_benchmarks():
    assert {p.stem for p in BENCHES} >= {"estimate", "match", "peers", "real", "recall", "scan", "speed"}


@pytest.mark.parametrize("path", BENCHES, ids=[p.stem for p in BENCHES])
def test_benchmark_imports(path, tmp_path):
    r = subprocess.run([sys.executable, "-c", CHECK, str(path)], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path)
    assert r.returncode == 0, f"{path.name}:\n{r.stdout}{r.stderr[-3000:]}"
