"""Shared fixtures. Tests that need ../shared/data fail (never skip) when it is missing.

Hypothesis runs derandomized by default: every run draws the same examples, so a red CI is a reproducible
failure, not an unlucky draw. `HYPOTHESIS_PROFILE=explore python -m pytest` draws new examples each run.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

settings.register_profile("deterministic", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "meshes").is_dir():
        pytest.fail(f"shared test data not found at {SHARED_DATA} (tests read ../shared/data beside the project)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def meshes_dir(shared_data: Path) -> Path:
    return shared_data / "meshes"


@pytest.fixture(scope="session")
def real_dir(shared_data: Path) -> Path:
    return shared_data / "real"


@pytest.fixture(scope="session")
def sample_template(tmp_path_factory) -> Path:
    """The bundled sample (gscan.demo.SAMPLES / "capture") scanned by the real pipeline, once per session."""
    from gscan.demo import SAMPLES
    from gscan.scan.pipeline import ScanOptions, run_scan

    out = tmp_path_factory.mktemp("sample") / "sample.gscan"
    res = run_scan(ScanOptions(input_dir=SAMPLES / "capture", output=out))
    assert res.registered == res.frames == 30
    return out
