"""The documents stay within the repository: every link of every Markdown file names a file or folder that is in
the repository, and the README links every page of docs/."""
from __future__ import annotations

import re
from pathlib import Path

from tests.conftest import ROOT

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")  # [text](target) and ![alt](target)


def _documents() -> list[Path]:
    skip = {".venv", "build", "node_modules", "demo-output"}
    return sorted(p for p in ROOT.rglob("*.md")
                  if not any(part.startswith(".") or part in skip for part in p.relative_to(ROOT).parts[:-1]))


def test_every_link_names_a_file_in_the_repository():
    docs = _documents()
    assert ROOT / "README.md" in docs and len(docs) >= 5
    broken = []
    for doc in docs:
        for target in LINK.findall(doc.read_text(encoding="utf-8")):
            if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):  # a URL or an anchor
                continue
            path = (doc.parent / target.split("#", 1)[0]).resolve()
            if not path.is_relative_to(ROOT) or not path.exists():
                broken.append(f"{doc.relative_to(ROOT)}: {target}")
    assert not broken, broken


def test_the_readme_links_every_page_of_docs():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    linked = {(ROOT / t.split("#", 1)[0]).resolve() for t in LINK.findall(readme)}
    pages = set((ROOT / "docs").glob("*.md"))
    assert pages and pages <= linked, sorted(str(p.relative_to(ROOT)) for p in pages - linked)


# a commit hash: a word of 7 to 40 hexadecimal digits holding both a digit and a letter (plain numbers and hex-only
# English words like "defaced" are not hashes)
HASH = re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")
# a count of tests ("847 tests", "1,024 passing tests"): it changes with every change, so no document states one
TEST_COUNT = re.compile(r"\b\d[\d,]*\s+(?:[a-z-]+\s+)?tests\b", re.IGNORECASE)
# a dotted path into the package, `gscan.scanning.api` or `gscan.Estimator.from_path` (not a file name `x.gscan`)
MODULE_PATH = re.compile(r"(?<![\w./-])gscan(?:\.[A-Za-z_]\w*)+")


def test_benchmarks_and_readme_name_no_commit():
    """Figures carry the command and the date that made them; trees are named in words (git keeps history)."""
    assert HASH.findall("at ee0fe3f and cd2eb65, 0123456789abcdef0123456789abcdef01234567")
    assert not HASH.findall("400349 keypoints, defaced, 2026-11-28, 0.650")
    found = {name: sorted(set(HASH.findall((ROOT / name).read_text(encoding="utf-8"))))
             for name in ("BENCHMARKS.md", "README.md")}
    assert not any(found.values()), found


def test_readme_states_no_test_count():
    assert TEST_COUNT.search("the whole test suite, 847 tests, 15-18 minutes")
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert not TEST_COUNT.findall(text), TEST_COUNT.findall(text)


def _resolves(path: str) -> bool:
    """`path` names a module of this tree, or an attribute of one (a class, a function, a method)."""
    import importlib

    parts = path.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:n]))
        except ModuleNotFoundError as e:
            if e.name is not None and not path.startswith(e.name):
                raise  # a module that exists failed to import: not a wrong name in the documents
            continue
        for attr in parts[n:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_every_module_path_in_the_documents_exists():
    """Every `gscan.xxx.yyy` the README, docs/ and BENCHMARKS.md name is a module or an attribute in this tree."""
    assert MODULE_PATH.findall("`gscan.scan(src)`, OBJ.gscan, demo-output/sample.gscan") == ["gscan.scan"]
    assert not _resolves("gscan.scan.pipeline") and not _resolves("gscan.serve.server")
    assert _resolves("gscan.scanning.pipeline") and _resolves("gscan.Estimator.from_path")
    missing = []
    for doc in [ROOT / "README.md", ROOT / "BENCHMARKS.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for path in sorted(set(MODULE_PATH.findall(doc.read_text(encoding="utf-8")))):
            if not _resolves(path):
                missing.append(f"{doc.relative_to(ROOT)}: {path}")
    assert not missing, missing
