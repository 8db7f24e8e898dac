"""View names are data (GitHub issue 21): whatever a template calls its views, every export writes inside its
output folder, file names made from names are unique and safe, and the names themselves round-trip as data."""
from __future__ import annotations

import itertools
import json
import os
import unicodedata
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gscan.exporters import FORMATS, export
from gscan.exporters.common import MAX_STEM_BYTES, safe_file_names
from gscan.features import Features
from gscan.geometry.mesh import MeshData
from gscan.io.camera import Intrinsics
from gscan.template.db import Edge, TemplateDB, View

INTR = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)
# names that were written outside the output, or that a file system or terminal takes for something else
NASTY = ["../../escaped", "/etc/passwd", "..", ".", "", "a/b", "a\\b", "nul\x00byte", "\x1b[31mred", "line\nbreak",
         "\u202eevil.png", ".hidden", "x" * 300, "é" * 200, "Frame", "frame", "e\u0301", "\u00e9", "con", "a:b*c?"]


BIDI = set("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def _tiny_template(path: Path, names: list[str]) -> None:
    """A complete template: one registered keyframe view per name (32 x 24 images, a mask, 4 keypoints), an
    accepted edge between consecutive views, a tetrahedron mesh and a cloud."""
    rng = np.random.default_rng(0)
    with TemplateDB.create(path, meta={"descriptor": {"kind": "rootsift"}}) as db:
        for i, name in enumerate(names):
            T = np.eye(4)
            T[:3, 3] = [0.01 * i, 0.0, -0.3]
            color = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
            depth = np.full((24, 32), 0.3, np.float32)
            mask = np.zeros((24, 32), bool)
            mask[6:18, 8:24] = True
            px = rng.uniform(0, 31, (4, 2)).astype(np.float32)
            pts = rng.normal(0, 0.02, (4, 3)).astype(np.float32)
            desc = rng.random((4, 128)).astype(np.float32)
            db.add_view(View(name, INTR, T, color, depth, mask, keyframe=True, quality=1.0, input_index=i),
                        Features(pixels=px, points=pts, descriptors=desc, kind="rootsift",
                                 scales=np.ones(4, np.float32)))
        for a, b in itertools.pairwise(names):
            db.add_edge(Edge(a, b, np.eye(4), np.array([[0, 0], [1, 1]]), 0.1, 0.001, 0.9, "sequential", True))
        V = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], float)
        db.set_mesh(MeshData(vertices=V, triangles=np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
                             vertex_colors=np.full((4, 3), 200, np.uint8)))
        db.set_cloud(V, np.full((4, 3), 100, np.uint8))
        db.mark_complete()


def _files_under(root: Path) -> set[Path]:
    return {Path(d) / f for d, _, fs in os.walk(root) for f in fs}


def _key(s: str) -> str:
    return unicodedata.normalize("NFC", s).casefold()


def _check_exports(tmp: Path, names: list[str]) -> None:
    """Every format exported from a template of `names`: nothing outside the output, safe unique image names,
    the names themselves kept as data."""
    work = tmp / "work"
    work.mkdir()
    db = work / "t.gscan"
    _tiny_template(db, names)
    before = _files_under(tmp)
    outs = {fmt: work / "out" / (f"x.{fmt}" if fmt in ("ply", "obj", "glb", "json") else fmt) for fmt in FORMATS}
    for fmt, out in outs.items():
        export(db, fmt, out)
    written = _files_under(tmp) - before
    for f in written:  # every file inside its format's output, none a link
        owner = next(o for o in outs.values() if f == o or o in f.parents)
        assert not f.is_symlink() and f.resolve().is_relative_to(owner.resolve()), f
    assert {f.name for f in work.iterdir()} == {"t.gscan", "out"}  # no temporary sibling left
    images = sorted(p.name for p in (outs["colmap"] / "images").iterdir())
    stems = safe_file_names(names)
    assert images == sorted(f"{s}.png" for s in stems) and len(images) == len(names)
    assert len({_key(s) for s in stems}) == len(names)  # unique where case or normalisation is ignored
    for s in stems:
        assert "/" not in s and "\\" not in s and "\x00" not in s and s not in (".", "..") and not s.startswith(".")
        assert len(s.encode("utf-8")) <= MAX_STEM_BYTES
        assert not any(unicodedata.category(c) in ("Cc", "Cs", "Zl", "Zp") or c in BIDI for c in s), s
    for name, s in zip(names, stems, strict=True):  # a name already safe is kept
        if (name and name.isprintable() and not name.startswith(".") and "/" not in name and "\\" not in name
                and len(name.encode()) <= MAX_STEM_BYTES and _key(name) not in {_key(n) for n in names if n != name}):
            assert s == name
    doc = json.loads(outs["json"].read_text(encoding="utf-8"))
    assert [v["name"] for v in doc["views"]] == names  # the names themselves are data and round-trip
    assert list(json.loads((outs["bop"] / "gscan_views.json").read_text(encoding="utf-8")).values()) == names
    fp = yaml.safe_load((outs["foundationpose"] / "ob_0000001" / "select_frames.yml").read_text(encoding="utf-8"))
    assert fp == names


def test_nasty_names_through_every_export(tmp_path: Path):
    """Separators, `..`, absolute paths, NUL, escape sequences, line breaks, bidi overrides, overlong names,
    names equal but for case or Unicode normalisation: COLMAP's images get safe unique names; the names stay
    as they are where they are data (JSON, BOP's gscan_views.json, FoundationPose's select_frames.yml)."""
    _check_exports(tmp_path, NASTY)


def test_safe_names_are_kept(tmp_path: Path):
    """Names that are already file names are not changed: exports made before keep their file names."""
    names = ["000000", "frame 0001", "view_é", "IMG-3.jpg", "x" * MAX_STEM_BYTES]
    assert safe_file_names(names) == names
    assert safe_file_names(["a", "A"])[0] == "a" and safe_file_names(["a", "A"])[1] != "A"


_NAME = st.one_of(
    st.text(max_size=40),
    st.text(alphabet=st.sampled_from(list("./\\\x00\x1b\n\r\t \u202eaAe\u0301\u00e9")), max_size=12),
    st.sampled_from(NASTY),
    st.text(min_size=150, max_size=300),
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                   HealthCheck.too_slow])
@given(names=st.lists(_NAME, min_size=1, max_size=4, unique=True))
def test_random_view_names_through_every_export(tmp_path_factory, names):
    """Property: any unicode view names (separators, control characters, any length) through every export stay
    inside the output and map to unique, safe file names."""
    try:
        [n.encode("utf-8") for n in names]
    except UnicodeEncodeError:  # SQLite stores text as UTF-8: such a name cannot be a view's
        return
    _check_exports(tmp_path_factory.mktemp("names"), names)


@pytest.mark.parametrize("name", NASTY)
def test_safe_name_is_deterministic(name: str):
    assert safe_file_names([name]) == safe_file_names([name])
