"""The command line's first contact: --version, --help that shows flags and whole choice lists at any terminal
width, choice values that are the library's, and human output that says what it means."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import gscan
from gscan.cli import ExportFormat, ScanFormat, ScanMode
from tests.conftest import ROOT


def _gscan(*args: str, columns: int | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if columns is not None:
        env["COLUMNS"] = str(columns)
    return subprocess.run([sys.executable, "-m", "gscan.cli", *args], capture_output=True, text=True, timeout=300,
                          cwd=ROOT, env=env)


def test_version():
    r = _gscan("--version")
    assert r.returncode == 0 and r.stdout == f"gscan {gscan.__version__}\n"
    assert re.fullmatch(r"\d+\.\d+\.\d+", gscan.__version__)


def test_choice_values_are_the_librarys():
    """The CLI's choice lists are the library's own (the contract's values)."""
    from gscan.exporters import FORMATS as EXPORT_FORMATS
    from gscan.io.layouts import FORMATS as INPUT_FORMATS
    from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT
    from gscan.scanning.options import FORMAT_CHOICES, MODE_CHOICES

    assert [f.value for f in ScanFormat] == list(FORMAT_CHOICES) == ["auto", *INPUT_FORMATS]
    assert [m.value for m in ScanMode] == list(MODE_CHOICES) == ["auto", STATIC_OBJECT, MOVING_OBJECT]
    assert [f.value for f in ExportFormat] == list(EXPORT_FORMATS)


def test_help_starts_without_the_library():
    """`gscan --help` (and `import gscan.cli`, what the console script does before `main`) loads no numpy, numba,
    OpenCV or open3d: the choice lists load when a command that has them is parsed, after `main` set the thread
    rule and OpenCV's log level. `track --help` names the library's input layouts."""
    from gscan.scanning.options import FORMAT_CHOICES

    code = ("import sys, gscan.cli\nheavy = ('numpy', 'numba', 'cv2', 'open3d')\n"
            "print(sorted(m for m in heavy if m in sys.modules))\n"
            "try:\n    gscan.cli.app(['--help'], standalone_mode=False)\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in heavy if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.splitlines()[0] == r.stdout.splitlines()[-1] == "[]", (r.stdout, r.stderr)
    assert "|".join(FORMAT_CHOICES) in _gscan("track", "--help", columns=300).stdout.split()


def test_bad_input_is_refused_before_the_heavy_libraries_load(tmp_path: Path, sample_template: Path):
    """numba, scipy and open3d cost about a CPU second to import (viser half of one, Ray and trimesh a third):
    every command refuses a bad input (a missing folder, template, mesh or query file, an output on its input, an
    exclusive option pair, a missing configuration) and answers `--help` without them (the scan opens its input
    before the pipeline loads, and open3d when its first stage begins; the estimator opens its templates and the
    query's files or sequence before its stages load, as `eval` and `serve` do; the viewer opens its template
    before its scene and server load; the batches check their inputs before Ray loads; the configuration's
    settings classes are light)."""
    code = ("import sys\nfrom gscan.cli import main\nsys.argv = ['gscan', *sys.argv[1:]]\ntry:\n    main()\n"
            "except SystemExit as e:\n    print('exit', e.code, *sorted(m for m in ('numba', 'scipy', 'open3d', "
            "'viser', 'ray', 'trimesh') if m in sys.modules))")
    out = str(tmp_path / "x.gscan")
    missing = str(tmp_path / "missing")
    query = ["--color", str(tmp_path / "c.png"), "--depth", "d.png", "--intrinsics", "K.txt"]
    estimate = ["estimate", str(tmp_path / "missing.gscan"), *query]
    for args, rc in (([*estimate], 2), ([*estimate, "--config", str(tmp_path / "missing.yaml")], 2),
                     (["eval", str(sample_template), missing, "-o", str(tmp_path / "r.csv")], 2),
                     (["serve", str(tmp_path / "missing.gscan")], 2),
                     (["batch", missing, "-o", str(tmp_path / "templates")], 2),
                     (["batch-eval", missing, missing, "-o", str(tmp_path / "r.csv")], 2),
                     (["capture", "--from", missing, "--no-preview", "-o", missing], 2),
                     (["template-from-mesh", str(tmp_path / "missing.obj"), "-o", out], 2),
                     (["estimate", str(sample_template), *query], 2),
                     (["track", str(sample_template), str(tmp_path / "missing")], 2),
                     (["track", str(tmp_path / "missing.gscan"), str(tmp_path / "missing")], 2),
                     (["view", str(tmp_path / "missing.gscan")], 2),
                     (["scan", str(tmp_path / "missing"), "-o", out], 2),
                     (["scan", str(tmp_path / "missing"), "-o", out, "--resume", "--force"], 2),
                     (["scan", str(tmp_path / "missing"), "-o", out, "--config", str(tmp_path / "missing.yaml")], 2),
                     (["scan", "--help"], 0), (["estimate", "--help"], 0)):
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120,
                           cwd=ROOT)
        assert r.stdout.splitlines()[-1].split() == ["exit", str(rc)], (args, r.stdout, r.stderr)
        assert rc == 0 or (r.stderr.startswith("error: ") and str(tmp_path) in r.stderr), (args, r.stderr)


def test_the_scan_imports_the_rest_when_its_first_stage_begins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """`ImportsAtFirstStage` (what `gscan scan` reports its stages to) imports its modules before the first stage
    runs, once, and passes every stage on."""
    from gscan.cli.imports import ImportsAtFirstStage
    from gscan.progress import StageTimer

    (tmp_path / "gscan_test_stage_import.py").write_text("LOADS = [1]\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "gscan_test_stage_import", raising=False)
    timer = StageTimer()
    progress = ImportsAtFirstStage(timer, ("gscan_test_stage_import",))
    assert "gscan_test_stage_import" not in sys.modules
    for name in ("camera", "load", "camera"):
        with progress.stage(name, total=1) as advance:
            module = sys.modules["gscan_test_stage_import"]
            advance(1)
    assert module.LOADS == [1] and sys.modules["gscan_test_stage_import"] is module
    assert sorted(timer.timings) == ["camera", "load"]


@pytest.mark.parametrize("columns", [40, 300])
@pytest.mark.parametrize("command", ["scan", "export", "estimate", "eval", "demo"])
def test_help_shows_flags_plainly_and_choice_lists_whole(command: str, columns: int):
    """At 40 or 300 columns: every option named in full, flags without a value type (typer's boxed help wrote
    `--force <bool>` and cut names and choice lists to the box)."""
    r = _gscan(command, "--help", columns=columns)
    assert r.returncode == 0, r.stderr
    assert "<bool>" not in r.stdout and "…" not in r.stdout
    words = set(r.stdout.split())
    assert "--help" in words and ("--json" in words or command == "demo")
    # the whole list as one word: <a|b> (typer >= 0.26) or [a|b]
    choices = {w.strip("<>[]") for w in words if "|" in w}
    if command == "scan":
        assert {"--force", "--no-segment", "--resume", "--obj-id"} <= words
        assert {"auto|capture|open3d|tum|bop", "auto|static-object|moving-object"} <= choices
    if command == "export":
        assert {"--force", "--keep-holes"} <= words and "bop|foundationpose|colmap|ply|obj|glb|json" in choices


def test_a_wrong_choice_names_the_option_and_the_choices(tmp_path: Path):
    r = _gscan("export", str(tmp_path / "x.gscan"), "--format", "stl", "-o", str(tmp_path / "x.stl"), columns=40)
    assert r.returncode == 2 and r.stdout == ""
    line = " ".join(r.stderr.split())
    assert "--format" in line and "'stl'" in line and all(f"'{f.value}'" in line for f in ExportFormat)


def _pose_from_line(line: str) -> np.ndarray:
    """T from `t = [x, y, z] m, R = A deg about [ax, ay, az]` (the human poses / grasp list line)."""
    import cv2

    nums = [float(x) for x in re.findall(r"[-+]?\d+\.\d+", line.split(":", 1)[1])]
    t, angle, axis = np.array(nums[:3]), np.radians(nums[3]), np.array(nums[4:7])
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0]
    T[:3, 3] = t
    return T


def test_human_poses_print_rotation_and_translation(sample_template: Path):
    """Each line holds the whole pose: rebuilt from its printed numbers, it is the stored T_obj_cam to the
    printed precision (0.1 mm; 0.01 deg and an axis to 1e-3, i.e. about 0.1 deg of rotation)."""
    from gscan.geometry.transforms import pose_error

    js = json.loads(_gscan("poses", str(sample_template), "--json").stdout)["frames"]
    r = _gscan("poses", str(sample_template), columns=40)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if re.match(r"^\d{6}: t = ", ln)]
    assert len(lines) == len(js) == 30
    for ln in lines:
        rot, trans = pose_error(_pose_from_line(ln), np.asarray(js[ln.split(":")[0]]))
        # the printed pose: 0.1 mm translation, 0.01 deg angle and a 1e-3 axis (about 0.06 deg) of rounding
        assert rot < 0.2 and trans < 1e-4, (ln, rot, trans)


def test_grasp_list_prints_the_whole_pose(sample_template: Path, tmp_path: Path):
    import shutil

    from gscan.geometry.transforms import make_T, pose_error, rotvec_to_R

    db = tmp_path / "g.gscan"
    shutil.copy(sample_template, db)
    T = make_T(rotvec_to_R(np.radians([0.0, 90.0, 0.0])), [0.01, -0.02, 0.05])
    (tmp_path / "g.json").write_text(json.dumps({"T": T.tolist()}))
    assert _gscan("grasp", "add", str(db), "--name", "top", "--pose", str(tmp_path / "g.json")).returncode == 0
    line = next(ln for ln in _gscan("grasp", "list", str(db)).stderr.splitlines() if ln.startswith("top:"))
    rot, trans = pose_error(_pose_from_line(line), T)
    # the printed pose: 0.1 mm translation, 0.01 deg angle and a 1e-3 axis (about 0.06 deg) of rounding
    assert "R = 90.00 deg" in line and rot < 0.2 and trans < 1e-4, line


def test_estimate_names_its_match_count(sample_template: Path):
    """The human line says what the number counts (the keypoint pairs of GMatch's list), which the viewer's
    edge "matches" (refined inlier pairs, hundreds) are not."""
    from gscan.demo import SAMPLES

    held = SAMPLES / "heldout"
    r = _gscan("estimate", str(sample_template), "--color", str(held / "rgb" / "000000.jpg"), "--depth",
               str(held / "depth" / "000000.png"), "--intrinsics", str(held / "cam_K.txt"), columns=40)
    assert r.returncode == 0, r.stderr
    js = json.loads(_gscan("estimate", str(sample_template), "--color", str(held / "rgb" / "000000.jpg"), "--depth",
                           str(held / "depth" / "000000.png"), "--intrinsics", str(held / "cam_K.txt"),
                           "--json").stdout)
    assert f"{js['n_matches']} matched keypoint pairs (GMatch's list)" in " ".join(r.stderr.split())


def _estimate_args(template: Path) -> list[str]:
    from gscan.demo import SAMPLES

    held = SAMPLES / "heldout"
    return ["estimate", str(template), "--color", str(held / "rgb" / "000000.jpg"), "--depth",
            str(held / "depth" / "000000.png"), "--intrinsics", str(held / "cam_K.txt"), "--json"]


def test_estimate_all_lists_each_template_and_gives_claimed_pixels_to_one(sample_template: Path, tmp_path: Path):
    """`estimate A B --all --json`: a list per template, each instance the single estimate's object plus its
    pixels; the same object under two names claims the same pixels, so one keeps the instance and the other
    lists it as refused, naming it. Several templates without --all, or --max-instances without it: exit 2."""
    import shutil

    twin = tmp_path / "twin.gscan"
    shutil.copy(sample_template, twin)
    single = json.loads(_gscan(*_estimate_args(sample_template)).stdout)
    args = _estimate_args(sample_template)
    r = _gscan(*args[:2], str(twin), *args[2:], "--all")
    assert r.returncode == 0, r.stderr
    js = json.loads(r.stdout)
    first, second = js["templates"]
    assert [first["template"], second["template"]] == [sample_template.stem, "twin"]
    assert len(first["instances"]) == 1 and first["reason"] is None and first["instances"][0]["pixels"]["count"] > 0
    inst = first["instances"][0]
    assert set(single) <= set(inst) and np.allclose(inst["T_cam_obj"], single["T_cam_obj"], atol=2e-3)
    assert second["instances"] == [] and "claimed by template " + sample_template.stem in second["refused"][0]["reason"]
    for bad in ([*args[:2], str(twin), *args[2:]], [*args, "--max-instances", "2"]):
        r = _gscan(*bad)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_config_dump_loads_back_and_its_estimate_section_reaches_estimate(sample_template: Path, tmp_path: Path):
    """`config dump` prints the scan's sections, then `estimate:`; the whole file loads back as the defaults of
    both, and an edited `estimate:` value given to `estimate --config` changes the estimate."""
    import yaml

    from gscan.estimate.estimator import EstimateParams
    from gscan.estimate.settings import load_estimate_params
    from gscan.scanning.config import ScanConfig, dump_defaults, load_config

    r = _gscan("config", "dump")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(dump_defaults())
    data = yaml.safe_load(r.stdout)
    assert list(data)[-1] == "estimate" and set(data) - {"estimate"} == set(ScanConfig.model_fields)
    path = tmp_path / "all.yaml"
    path.write_text(r.stdout)
    assert load_config(path) == ScanConfig() and load_estimate_params(path) == EstimateParams()

    plain = json.loads(_gscan(*_estimate_args(sample_template)).stdout)
    same = _gscan(*_estimate_args(sample_template), "--config", str(path))
    assert same.returncode == 0, same.stderr
    assert json.loads(same.stdout)["T_cam_obj"] == plain["T_cam_obj"] and plain["T_cam_obj"] is not None
    data["estimate"]["accept"]["min_matches"] = 1000  # no match list is that long: the object is not found
    path.write_text(yaml.safe_dump(data))
    edited = _gscan(*_estimate_args(sample_template), "--config", str(path))
    assert edited.returncode == 0, edited.stderr
    assert json.loads(edited.stdout)["T_cam_obj"] is None


@pytest.mark.parametrize("command", ["estimate", "serve"])
def test_a_bad_estimate_key_names_the_file_and_the_key(sample_template: Path, tmp_path: Path, command: str):
    path = tmp_path / "bad.yaml"
    path.write_text("estimate:\n  top_kk: 3\n")
    args = _estimate_args(sample_template) if command == "estimate" else ["serve", str(sample_template), "--port", "0"]
    r = _gscan(*args, "--config", str(path))
    assert r.returncode == 2 and r.stdout == "", r.stderr
    assert str(path) in r.stderr and "estimate.top_kk" in r.stderr
    path.write_text("estimate:\n  top_k: many\n")  # a value of the wrong type: its key named too
    r = _gscan(*args, "--config", str(path))
    assert r.returncode == 2 and "estimate.top_k" in r.stderr, r.stderr
