"""An output never lands on an input of the same command (issue "Hostile input, round three", item 1).

Every writing command is run through the real command line with its output drawn relative to one of its
inputs: the input itself, its parent folder, a path inside it, a link to it (refused: exit 2, one line naming
both, no input file changed, whatever --force says), or a sibling (allowed: it works).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gscan import synth
from gscan.io.output import check_not_input

ROOT = Path(__file__).resolve().parents[1]
INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240
TIMEOUT_S = 300
REFUSED = ("equal", "parent", "child", "symlink")


def _gscan(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gscan.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=TIMEOUT_S, cwd=ROOT, check=False)


def _tree_hash(root: Path) -> dict[str, str]:
    """Every file under `root` (links not followed) by its path and content hash."""
    out = {}
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            p = Path(dirpath, f)
            if not p.is_symlink():
                out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The inputs every example copies: a capture, a CAD template of it and its textured mesh."""
    from gscan.scanning.cad import template_from_mesh

    base = tmp_path_factory.mktemp("inputs")
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, base / "cap", 6, mode="static", elevations_deg=(40.0,), intr=INTR)
    synth.save_textured_mesh(mesh, base / "box" / "box.obj")
    template_from_mesh(base / "box" / "box.obj", base / "t.gscan", n_views=6)
    return base


def _workspace(base: Path, w: Path) -> None:
    """The inputs of every command under `w`: cap/, t.gscan, box/box.obj, caps/box0/ (batch), temps/box0.gscan
    with scenes/box0/ (batch-eval) and rec.bag (capture --from; not a real recording)."""
    shutil.copytree(base / "cap", w / "cap")
    shutil.copy(base / "t.gscan", w / "t.gscan")
    shutil.copytree(base / "box", w / "box")
    shutil.copytree(base / "cap", w / "caps" / "box0")
    (w / "temps").mkdir()
    shutil.copy(base / "t.gscan", w / "temps" / "box0.gscan")
    shutil.copytree(base / "cap", w / "scenes" / "box0")
    (w / "rec.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(64))


@dataclass(frozen=True)
class Command:
    name: str
    argv: Callable[[Path, Path], list[str | Path]]  # (workspace, output) -> arguments
    anchors: tuple[str, ...]  # the inputs (relative to the workspace) an output is drawn against
    out_name: str  # a new output's name
    force: bool = True  # has --force
    cheap: bool = True  # a sibling output is run for real (else: checked by the library's check alone)
    inputs: Callable[[Path], list[Path]] = lambda w: []  # the inputs for the library check of a sibling


COMMANDS = [
    Command("scan", lambda w, o: ["scan", w / "cap", "-o", o], ("cap", "cap/cam_K.txt"), "o.gscan",
            inputs=lambda w: [w / "cap"]),
    Command("track", lambda w, o: ["track", w / "t.gscan", w / "cap", "-o", o], ("cap", "t.gscan"), "poses"),
    Command("export", lambda w, o: ["export", w / "t.gscan", "--format", "json", "-o", o], ("t.gscan",), "o.json"),
    Command("export-bop", lambda w, o: ["export", w / "t.gscan", "--format", "bop", "-o", o], ("t.gscan",), "bop"),
    Command("eval", lambda w, o: ["eval", w / "t.gscan", w / "cap", "-o", o, "--no-icp"], ("cap", "t.gscan"),
            "r.csv"),
    Command("template-from-mesh", lambda w, o: ["template-from-mesh", w / "box" / "box.obj", "-o", o, "--views", "4"],
            ("box/box.obj",), "m.gscan"),
    Command("batch", lambda w, o: ["batch", w / "caps", "-o", o], ("caps", "caps/box0"), "temps-out", cheap=False,
            inputs=lambda w: [w / "caps" / "box0"]),
    Command("batch-eval", lambda w, o: ["batch-eval", w / "temps", w / "scenes", "-o", o],
            ("temps", "scenes", "temps/box0.gscan", "scenes/box0"), "r.csv", cheap=False,
            inputs=lambda w: [w / "temps", w / "scenes"]),
    Command("capture", lambda w, o: ["capture", "--from", w / "rec.bag", "--no-preview", "-o", o], ("rec.bag",),
            "capture", force=False, cheap=False, inputs=lambda w: [w / "rec.bag"]),
]


def _output(w: Path, anchor: str, relation: str, name: str) -> Path:
    a = w / anchor
    if relation == "equal":
        return a
    if relation == "parent":
        return a.parent
    if relation == "child":
        # a batch's templates folder directly in its captures folder is allowed (it is no capture): go deeper
        return a / "sub" / name if anchor == "caps" else a / name
    if relation == "symlink":
        link = w / "link"
        link.symlink_to(a)
        return link
    return w / "side" / name


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cmd=st.sampled_from(COMMANDS), relation=st.sampled_from(REFUSED), data=st.data(), force=st.booleans())
def test_an_output_on_an_input_is_refused(base: Path, cmd: Command, relation: str, data: st.DataObject,
                                          force: bool):
    anchor = data.draw(st.sampled_from(cmd.anchors))
    with tempfile.TemporaryDirectory() as d:
        w = Path(d)
        _workspace(base, w)
        out = _output(w, anchor, relation, cmd.out_name)
        before = _tree_hash(w)
        proc = _gscan(*cmd.argv(w, out), *(["--force"] if force and cmd.force else []))
        detail = f"{cmd.name} {relation} {anchor}: rc {proc.returncode}\n{proc.stderr[-2000:]}"
        assert proc.returncode == 2, detail
        lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
        assert len(lines) == 1 and "input" in lines[0] and str(out) in lines[0], detail
        assert "--force" not in lines[0], detail
        assert _tree_hash(w) == before, detail


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c.name)
def test_a_sibling_output_works(base: Path, tmp_path: Path, cmd: Command):
    """A new output beside the inputs: the command writes it (the batches, whose runtime takes long to start,
    and capture, which needs a camera recording, are checked by the library's rule alone: test_batch.py and
    test_capture.py run them)."""
    _workspace(base, tmp_path)
    out = _output(tmp_path, cmd.anchors[0], "sibling", cmd.out_name)
    if not cmd.cheap:
        check_not_input(out, cmd.inputs(tmp_path))
        return
    before = _tree_hash(tmp_path)
    proc = _gscan(*cmd.argv(tmp_path, out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert out.exists()
    after = _tree_hash(tmp_path)
    assert {k: v for k, v in after.items() if not k.startswith("side")} == before


def test_track_onto_its_capture_is_refused_with_force(base: Path, tmp_path: Path):
    """`gscan track T CAPTURE -o CAPTURE --force` once replaced the capture by pose files: refused, naming both."""
    _workspace(base, tmp_path)
    before = _tree_hash(tmp_path)
    proc = _gscan("track", tmp_path / "t.gscan", tmp_path / "cap", "-o", tmp_path / "cap", "--force")
    assert proc.returncode == 2, proc.stderr
    assert f"error: {tmp_path / 'cap'}: is the input {tmp_path / 'cap'}" in proc.stderr
    assert "--force" not in proc.stderr
    assert _tree_hash(tmp_path) == before


def test_check_not_input_relations(tmp_path: Path):
    """The library rule: equal, containing, inside and linked outputs refused; siblings and (with inside_ok)
    an output inside an input folder allowed."""
    from gscan.errors import InputError

    inp = tmp_path / "in"
    (inp / "a").mkdir(parents=True)
    (tmp_path / "ln").symlink_to(inp)
    for out, how in ((inp, "is the input"), (tmp_path, "contains the input"), (inp / "a" / "x", "lies inside"),
                     (tmp_path / "ln", "is the input"), (tmp_path / "ln" / "a", "lies inside")):
        with pytest.raises(InputError, match=how):
            check_not_input(out, [None, inp])
    check_not_input(tmp_path / "side", [inp])
    check_not_input(inp / "templates", [inp], inside_ok=True)
    with pytest.raises(InputError, match="contains"):
        check_not_input(tmp_path, [inp], inside_ok=True)


def test_demo_into_its_bundled_sample_is_refused(tmp_path: Path):
    """`gscan demo -o` inside the bundled sample it scans (directly or through a link): refused, the sample kept."""
    from gscan.demo import SAMPLES

    before = _tree_hash(SAMPLES)
    (tmp_path / "link").symlink_to(SAMPLES / "capture")
    for out in (SAMPLES / "capture", tmp_path / "link"):
        proc = _gscan("demo", "--no-view", "-o", out)
        assert proc.returncode == 2, proc.stderr
        assert "lies inside the input" in proc.stderr and str(SAMPLES) in proc.stderr
    assert _tree_hash(SAMPLES) == before
