"""First contact: the README's install command in a fresh virtual environment, and `pip install .` of a clean
copy of the repository, each followed by the demo; the README's Python quick-start.

Both install into a new venv that sees the running environment's packages (a .pth line; the dependencies are
not downloaded again: the CI run has just installed them, through the same scripts/setup.sh), so what is
tested is gscan's own install: its setup script, its build, its package data and its entry point."""
from __future__ import annotations

import os
import re
import shutil
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from gscan.demo import FIRST_RUN
from tests.conftest import ROOT

# what a clean clone holds that an install needs (the tests, benchmarks and documents are not needed)
SOURCE = ("pyproject.toml", "README.md", "gscan", "samples", "scripts")
DEMO_LINES = ("30/30 frames registered", "held-back frames: 4/4 found")


def _clean_copy(dst: Path) -> Path:
    """The repository's installable files copied to `dst`, without caches or build output."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc", "*.egg-info", "build")
    dst.mkdir(parents=True)
    for name in SOURCE:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dst / name, ignore=ignore)
        else:
            shutil.copy2(src, dst / name)
    return dst


def _venv_seeing_this_environment(path: Path) -> Path:
    """A fresh venv at `path` whose interpreter also finds the running environment's installed packages."""
    subprocess.run([sys.executable, "-m", "venv", str(path)], check=True, capture_output=True, timeout=300)
    py = path / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *site.getsitepackages()}
    (Path(purelib) / "_gscan_test_deps.pth").write_text("\n".join(sorted(p for p in ours if os.path.isdir(p))) + "\n")
    return py


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV", "GSCAN_"))}
    env.update(PIP_DISABLE_PIP_VERSION_CHECK="1", **extra)
    return env


def _readme_commands() -> list[str]:
    """The shell commands of the README's two commands (the first two bash blocks of "Two commands")."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Two commands", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, flags=re.DOTALL)[:2]
    return [ln.split("#")[0].strip() for b in blocks for ln in b.splitlines() if ln.strip() and not ln.startswith("#")]


def test_readme_commands_are_the_setup_script():
    """The README's two commands are scripts/setup.sh (install and demo) and scripts/setup.sh --test, the
    command .ci/run runs."""
    assert _readme_commands() == ["bash scripts/setup.sh", "bash scripts/setup.sh --test"]
    assert "scripts/setup.sh --test" in (ROOT / ".ci" / "run").read_text()


@pytest.mark.slow
def test_readme_install_command_in_a_fresh_venv(tmp_path: Path):
    """README command 1 on a clean copy: system packages checked (none missing here), the venv reused, gscan
    installed into it (editable), `gscan demo` run; --no-view is passed on to the demo. The copy holds no compiled
    kernels (numba caches them beside the sources): that first demo says once that it compiles them, and leaves
    every kernel module compiled (scan and estimator), as a new process of the venv reads numba's cache: the
    demo's own condition for saying it (`gscan.demo.kernels_cached`, tests/test_demo.py) is then false, so the
    next demo says nothing. (A second demo is not run: what it would add, the demo's results from cached kernels,
    is what tests/test_demo.py checks on the bundled sample in the suite, which runs on the kernels CI compiled.)
    This is the suite's run of the `gscan demo` command: its summary lines, whatever the terminal width (the lines
    are not wrapped; whitespace is joined in case a terminal does), and its template in the output folder."""
    src = _clean_copy(tmp_path / "src")
    venv = tmp_path / "venv"
    _venv_seeing_this_environment(venv)
    command = _readme_commands()[0].split() + ["--no-view"]
    r = subprocess.run(command, cwd=src, capture_output=True, text=True, timeout=900,
                       env=_env(GSCAN_VENV=str(venv)))
    assert r.returncode == 0, r.stderr[-3000:]
    out = " ".join(r.stderr.split())
    assert all(line in out for line in DEMO_LINES), r.stderr[-3000:]
    assert out.count(FIRST_RUN) == 1, r.stderr[-3000:]
    assert (src / "demo-output" / "sample.gscan").is_file()
    cached = subprocess.run([str(venv / "bin" / "python"), "-c", "import gscan.demo as d; print(d.__file__); "
                             "print(d.kernels_cached())"], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                            env=_env())
    assert cached.returncode == 0, cached.stderr[-3000:]
    module, compiled = cached.stdout.split()
    assert Path(module).is_relative_to(src) and compiled == "True", cached.stdout  # the copy's kernels, all compiled
    v = subprocess.run([str(venv / "bin" / "gscan"), "--version"], capture_output=True, text=True, timeout=120)
    assert v.returncode == 0 and v.stdout.startswith("gscan "), v.stderr


def _package_files(package: Path) -> dict[str, bytes]:
    """Relative path -> bytes of every file of a `gscan` package folder (its modules and package data), without
    the caches (__pycache__: compiled bytecode and numba's kernels)."""
    return {str(f.relative_to(package)): f.read_bytes() for f in sorted(package.rglob("*"))
            if f.is_file() and "__pycache__" not in f.relative_to(package).parts}


@pytest.mark.slow
def test_wheel_install_holds_the_whole_package_and_finds_its_sample_from_another_folder(tmp_path: Path):
    """`pip install .` (a built wheel, not editable) of a clean copy; the copy is deleted. The installed package
    holds every module and data file of the checkout's, byte for byte (a module or sample file left out of the
    wheel fails here), and from another folder the entry point runs and the demo finds its bundled sample in the
    installed package. The demo itself runs in the README command's test above (a clean copy, kernels compiled
    from scratch) and in tests/test_demo.py; run here too it would compile every kernel again for the same code."""
    src = _clean_copy(tmp_path / "src")
    py = _venv_seeing_this_environment(tmp_path / "venv")
    r = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-compile", str(src)], capture_output=True,
                       text=True, timeout=900, env=_env())
    assert r.returncode == 0, r.stderr[-3000:]
    shutil.rmtree(src)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    where = subprocess.run([str(py), "-c", "import gscan.demo as d; print(d.__file__); print(d.SAMPLES)"],
                           cwd=elsewhere, capture_output=True, text=True, timeout=120, env=_env())
    module, samples = where.stdout.split()
    assert Path(module).is_relative_to(tmp_path / "venv") and Path(samples).is_relative_to(tmp_path / "venv")
    installed, ours = _package_files(Path(module).parent), _package_files(ROOT / "gscan")
    assert sorted(set(ours) - set(installed)) == [], "left out of the wheel"
    assert [f for f in ours if installed[f] != ours[f]] == []
    assert (Path(samples) / "capture" / "cam_K.txt").is_file()
    assert len(list((Path(samples) / "heldout" / "rgb").iterdir())) == 4
    for args in (["--version"], ["demo", "--help"]):
        r = subprocess.run([str(tmp_path / "venv" / "bin" / "gscan"), *args], cwd=elsewhere, capture_output=True,
                           text=True, timeout=120, env=_env())
        assert r.returncode == 0, r.stderr[-3000:]
    assert not (elsewhere / "demo-output").exists()


def test_readme_quickstart_runs_without_the_repository(sample_template: Path, tmp_path: Path):
    """The README's Python block, run in a folder holding only the demo's template (demo-output/sample.gscan),
    needs nothing beside the installed package: the bundled sample and no shared data."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Python quick-start", 1)[1].split("\n## ", 1)[0]
    code = re.findall(r"```python\n(.*?)```", section, flags=re.DOTALL)[0]
    assert "shared" not in code
    (tmp_path / "demo-output").mkdir()
    shutil.copy(sample_template, tmp_path / "demo-output" / "sample.gscan")
    env = _env(PYTHONPATH=str(ROOT))  # this checkout's gscan, as an installed one would be found
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                       env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    pose = r.stdout.split("]]")[-2]  # the last print: the held-back frame's T_cam_obj, then its reason
    assert "None" not in pose and r.stdout.split()[-1] == "None", r.stdout  # found: a pose and no reason


def _fake_system(tmp_path: Path, uid: int, installed: set[str], sudo: bool) -> tuple[dict[str, str], Path]:
    """A PATH of stand-ins for id, dpkg-query, apt-get and (optionally) sudo that log their calls, plus the few
    real tools the script needs; no other program is reachable."""
    bin_dir, log = tmp_path / "bin", tmp_path / "calls.log"
    bin_dir.mkdir(parents=True)
    for tool in ("bash", "dirname", "env"):
        (bin_dir / tool).symlink_to(shutil.which(tool))
    scripts = {
        "id": f'[ "$1" = "-u" ] && echo {uid}',
        "dpkg-query": 'for a; do p="$a"; done; case " $FAKE_INSTALLED " in *" $p "*) printf "install ok installed";; '
                      '*) echo "dpkg-query: no packages found matching $p" >&2; exit 1;; esac',
        "apt-get": f'echo "apt-get $*" >> {log}',
    }
    if sudo:
        scripts["sudo"] = f'echo "sudo $1" >> {log}; exec "$@"'
    for name, body in scripts.items():
        (bin_dir / name).write_text(f"#!{shutil.which('bash')}\n{body}\n")
        (bin_dir / name).chmod(0o755)
    env = {"PATH": str(bin_dir), "FAKE_INSTALLED": " ".join(sorted(installed)), "PYTHON": sys.executable,
           "HOME": str(tmp_path)}
    return env, log


SYSTEM_PACKAGES = {"libusb-1.0-0", "libgl1", "libegl1", "libx11-6", "libgomp1", "python3-venv"}


@pytest.mark.parametrize("uid, sudo, expected", [
    (0, False, ["apt-get update -qq", "apt-get install -y -qq --no-install-recommends libgl1 libgomp1"]),
    (1000, True, ["sudo env", "apt-get update -qq", "sudo env",
                  "apt-get install -y -qq --no-install-recommends libgl1 libgomp1"]),
    (1000, False, None),
])
def test_setup_installs_missing_system_packages_with_sudo_only_when_not_root(tmp_path: Path, uid: int, sudo: bool,
                                                                               expected: list[str] | None):
    """scripts/setup.sh --system: as root apt-get runs itself; as a user through sudo; a user without sudo gets one
    line naming the missing packages and exit 2. Only the missing packages are installed."""
    env, log = _fake_system(tmp_path, uid, SYSTEM_PACKAGES - {"libgl1", "libgomp1"}, sudo)
    r = subprocess.run(["bash", str(ROOT / "scripts" / "setup.sh"), "--system"], capture_output=True, text=True,
                       timeout=60, env=env)
    calls = log.read_text().splitlines() if log.exists() else []
    if expected is None:
        assert r.returncode == 2 and calls == [], (r.stderr, calls)
        assert "missing system packages: libgl1 libgomp1" in r.stderr and "apt-get install libgl1 libgomp1" in r.stderr
    else:
        assert r.returncode == 0, r.stderr
        assert calls == expected
    env, log = _fake_system(tmp_path / "all", uid, SYSTEM_PACKAGES | {"chromium", "fonts-dejavu-core"}, sudo)
    r = subprocess.run(["bash", str(ROOT / "scripts" / "setup.sh"), "--system", "--test"], capture_output=True,
                       text=True, timeout=60, env=env)
    assert r.returncode == 0 and not log.exists(), r.stderr  # nothing missing: no apt-get, no sudo


@pytest.mark.parametrize("failing", [None, "ruff", "mypy", "gscan.cli"])
def test_setup_test_runs_ruff_and_mypy_before_the_tests_and_stops_when_one_fails(tmp_path: Path,
                                                                                   failing: str | None):
    """scripts/setup.sh --test (what .ci/run runs) lints with ruff, type-checks with mypy and, beside them, compiles
    the numeric kernels with `gscan demo --no-view` (into a temporary folder it removes), then runs pytest on every
    core with the given arguments; a failing step fails the run (non-zero exit, one line naming it) before the
    tests. The venv's interpreter is a stand-in that logs its calls and fails as `failing` says."""
    venv, log = tmp_path / "venv", tmp_path / "calls.log"
    (venv / "bin").mkdir(parents=True)
    stub = venv / "bin" / "python"
    stub.write_text(f'#!{shutil.which("bash")}\necho "$*" >> {log}\n[ "$2" = "{failing}" ] && exit 1\nexit 0\n')
    stub.chmod(0o755)
    r = subprocess.run(["bash", str(ROOT / "scripts" / "setup.sh"), "--test", "-x", "tests/test_config.py"],
                       capture_output=True, text=True, timeout=60,
                       env=_env(GSCAN_NO_APT="1", GSCAN_VENV=str(venv), PYTHON=sys.executable))
    lines = log.read_text().splitlines()
    # the demo runs in the background: its call is logged among the checks', in no fixed order
    demo = [line for line in lines if line.startswith("-m gscan.cli ")]
    # the other pyrealsense2 versions the recording tests record with, each into a folder of its own
    sdks = [c for c in lines if c.startswith("-m pip install") and "--target" in c]
    assert [c.split()[-1] for c in sdks] == ["pyrealsense2==2.57.7.10387", "pyrealsense2==2.58.4.10922"], sdks
    calls = [c.split()[:2] for c in lines if not c.startswith("-m gscan.cli ") and c not in sdks]
    ran = [["-m", "pip"], ["-m", "ruff"], ["-m", "mypy"], ["-m", "pytest"]]
    assert len(demo) <= 1 and all(d.split()[2:5] == ["demo", "--no-view", "--output"] for d in demo), demo
    warm = [Path(d.split()[5]).parent for d in demo]
    assert not any(w.exists() for w in warm), warm  # its temporary folder is gone, also after a failure
    if failing is None:
        assert r.returncode == 0, r.stderr
        assert calls == ran and lines[-1] == "-m pytest -q -n auto --dist loadfile -x tests/test_config.py"
        assert len(demo) == 1 and lines.index(demo[0]) < len(lines) - 1  # compiled before the tests
    else:
        last = r.stderr.strip().splitlines()[-1]
        name = "gscan demo" if failing == "gscan.cli" else failing
        assert r.returncode == 1 and last.startswith(f"setup: error: {name}") and "failed" in last, r.stderr
        if failing == "gscan.cli":  # the checks ran to the end, the tests did not
            assert len(demo) == 1 and calls == ran[:3]
        else:
            assert calls == ran[: ran.index(["-m", failing]) + 1]  # nothing after the failing check
