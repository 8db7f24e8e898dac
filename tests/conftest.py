"""Shared fixtures.

Test data: the tests that render views of real scanned objects or read real RGB-D frames use the shared test
data, a folder that is not part of the repository: `../shared/data` beside the repository root, or the folder
named by the environment variable GSCAN_TEST_DATA. It holds `meshes/` (21 textured household objects from
Google Scanned Objects, CC-BY 4.0, via a MuJoCo conversion) and `real/` (Open3D's RGB-D test frames, 7-Scenes
"redkitchen" Kinect v1 frames with ground-truth camera poses, two YCB-Video frames with object poses); its
README.md names each source and licence. Those tests fail (never skip) when it is missing. Everything else
uses the bundled sample (gscan/sample/) or renders its own data.

Files: every test writes into its pytest temporary folder only (kept for failed tests alone, see
pyproject.toml); Hypothesis keeps its files there too.

Hypothesis runs derandomized by default: every run draws the same examples, so a red CI is a reproducible
failure, not an unlucky draw. `HYPOTHESIS_PROFILE=explore python -m pytest` draws new examples each run.
"""
from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import settings

settings.register_profile("deterministic", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("GSCAN_TEST_DATA") or ROOT.parent / "shared" / "data")


@pytest.hookimpl(trylast=True)  # after pytest's own tmpdir plugin has attached its factory to the config
def pytest_configure(config: pytest.Config) -> None:
    """Hypothesis's own files (its example database, the constants it caches while drawing examples) go into the
    run's temporary folder, not into .hypothesis/ in the working directory: the `tmp_path_factory` fixture's
    folder, reached through the config before any test runs."""
    from hypothesis.configuration import set_hypothesis_home_dir

    factory = getattr(config, "_tmp_path_factory", None)
    if factory is not None:
        set_hypothesis_home_dir(factory.getbasetemp() / "hypothesis")
    # pytest-xdist hands the files out in collection order (see below), not largest file first
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files with the most long (slow or browser) tests run first, then the larger files: pytest-xdist's
    `--dist loadfile` gives each worker the next whole file as it frees up, and a long file begun last keeps one
    worker busy while the other has nothing left. A file's own tests keep their order."""
    def long(item: pytest.Item) -> bool:
        return item.get_closest_marker("slow") is not None or item.get_closest_marker("browser") is not None

    files: dict[str, list[pytest.Item]] = {}
    for item in items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)
    order = sorted(files.values(), key=lambda its: (-sum(map(long, its)), -len(its)))
    items[:] = [item for its in order for item in its]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared test data (see the module docstring): meshes/ and real/."""
    if not (SHARED_DATA / "meshes").is_dir():
        pytest.fail(f"shared test data not found at {SHARED_DATA}: the tests that use real objects and frames read "
                    "../shared/data beside the repository, or the folder GSCAN_TEST_DATA names (README, Test data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def meshes_dir(shared_data: Path) -> Path:
    return shared_data / "meshes"


@pytest.fixture(scope="session")
def real_dir(shared_data: Path) -> Path:
    return shared_data / "real"


def _made_once(tmp_path_factory: pytest.TempPathFactory, key: str, name: str, make: Callable[[Path], None]) -> Path:
    """The file `name` that `make(path)` writes, made once per run: under pytest-xdist every worker is a session of
    its own, so the first worker that asks for `key` makes it in the run's temporary folder (the workers' common
    parent) while holding a lock there, and the others wait for it and read the same file. `make` raises (or fails
    an assertion) when what it made is wrong: nothing is recorded then, and the next test that asks makes it
    again. The tests only read the file (those that change one change a copy)."""
    import fcntl

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, which holds each worker's
    done = root / f"{key}.path"  # written once `make` has returned
    with open(root / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if done.is_file():
            return Path(done.read_text())
        out = Path(tempfile.mkdtemp(prefix=key, dir=root)) / name
        make(out)
        done.write_text(str(out))
    return out


@pytest.fixture(scope="session")
def sample_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The bundled sample (gscan.demo.SAMPLES / "capture") scanned by the real pipeline (`gscan.scan`), once per
    run (`_made_once`)."""
    def make(out: Path) -> None:
        import gscan
        from gscan.demo import SAMPLES

        res = gscan.scan(SAMPLES / "capture", out)
        assert res.registered == res.frames == 30

    return _made_once(tmp_path_factory, "sample_template", "sample.gscan", make)


@pytest.fixture(scope="session")
def cad_template(meshes_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Callable[[str, int], Path]:
    """(mesh, views) -> the CAD template `gscan.template_from_mesh` renders of the shared mesh meshes/MESH with
    that many views, MESH.gscan, made once per run (`_made_once`): several files estimate against the same one."""
    def get(mesh: str, n_views: int) -> Path:
        def make(out: Path) -> None:
            from gscan.scanning.cad import template_from_mesh

            template_from_mesh(meshes_dir / mesh / "model_0.obj", out, n_views=n_views)

        return _made_once(tmp_path_factory, f"cad-{mesh}-{n_views}", f"{mesh}.gscan", make)

    return get
