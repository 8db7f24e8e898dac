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
