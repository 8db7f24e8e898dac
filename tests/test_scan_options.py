"""gscan.scanning.options.ScanOptions: the depth camera of unregistered depth is one value (a DepthCamera)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gscan.io.camera import DepthCamera, load_depth_camera
from gscan.scanning.options import ScanOptions


def test_scan_options_hold_a_depth_camera_value(tmp_path: Path):
    """The option is the camera's value (what a resumed scan compares, `DepthCamera.to_dict`), not its files."""
    np.savetxt(tmp_path / "depth_K.txt", [[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
    cam = load_depth_camera(tmp_path / "depth_K.txt")
    opts = ScanOptions(depth_camera=cam)
    assert opts.depth_camera == cam and ScanOptions().depth_camera is None
    assert DepthCamera.from_dict(json.loads(json.dumps(opts.depth_camera.to_dict()))) == cam
    with pytest.raises(TypeError, match="must be a DepthCamera"):
        ScanOptions(depth_camera=tmp_path / "depth_K.txt")  # type: ignore[arg-type]
