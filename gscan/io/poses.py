"""Pose files, each read into [4 x 4] rigid transforms (metres): a text matrix, a JSON matrix, an Open3D
trajectory log, a TUM ground-truth line. Every reader raises InputError naming the file, also for a
matrix that is not a rigid transform (`check_rigid`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gscan.errors import InputError, not_a_file
from gscan.geometry.transforms import MAX_TRANSLATION_M, is_rigid, nearest_rigid
from gscan.io.output import describe_os_error


def check_rigid(T: np.ndarray, path: Path) -> np.ndarray:
    """T [4 x 4] with its rotation projected onto the nearest rotation (`nearest_rigid`); InputError naming
    `path` unless T is finite, its rotation orthonormal (to the tolerance of `is_rigid`) with det +1, its
    last row 0 0 0 1 and its translation within MAX_TRANSLATION_M."""
    if not is_rigid(T, max_translation=np.inf):
        raise InputError(path, "pose is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    if np.abs(T[:3, 3]).max() > MAX_TRANSLATION_M:
        raise InputError(path, f"pose translation {np.abs(T[:3, 3]).max():g} m is beyond {MAX_TRANSLATION_M:g} m "
                         "(poses are in metres)")
    return nearest_rigid(T)


def read_pose_txt(path: Path) -> np.ndarray:
    """[4 x 4] pose from a text file of 4 (or 3) rows of 4 numbers."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise InputError(path, f"cannot read the pose file ({describe_os_error(e)})") from None
    except UnicodeDecodeError:
        raise InputError(path, "malformed pose file (not UTF-8 text): expected a 4x4 matrix") from None
    try:
        T = np.array([[float(x) for x in line.replace(",", " ").split()]
                      for line in text.splitlines() if line.strip()], dtype=np.float64)
    except ValueError as e:
        raise InputError(path, f"malformed pose file ({e.__class__.__name__}): expected a 4x4 matrix") from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(path, f"malformed pose file: expected a 4x4 matrix of numbers, got shape {T.shape}")
    return check_rigid(T, path)


def read_pose_file(path: str | Path) -> np.ndarray:
    """[4 x 4] pose from a JSON file: `{"T": [[4x4]]}` or a bare 4x4 list (metres)."""
    path = Path(path)
    if not path.is_file():
        raise not_a_file(path, "pose file")
    try:
        d = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise InputError(path, f"malformed pose JSON ({e.__class__.__name__})") from None
    try:
        T = np.asarray(d["T"] if isinstance(d, dict) else d, dtype=np.float64)
    except (KeyError, TypeError, ValueError, OverflowError):
        raise InputError(path, 'expected {"T": [[4x4]]} or a bare 4x4 list') from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(path, f"expected a finite 4x4 matrix, got shape {T.shape}")
    return check_rigid(T, path)


def read_open3d_log(path: Path) -> list[tuple[int, np.ndarray]]:
    """Open3D trajectory .log: per entry a line "i j n" then 4 rows of a 4x4 pose -> [(i, T [4 x 4])]."""
    try:
        lines = [ln.split() for ln in path.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read trajectory log ({e.__class__.__name__})") from None
    if len(lines) % 5:
        raise InputError(path, f"malformed Open3D log: {len(lines)} non-empty lines is not a multiple of 5")
    out = []
    for k in range(0, len(lines), 5):
        try:
            idx = int(lines[k][0])
            T = np.array([[float(x) for x in row] for row in lines[k + 1:k + 5]], dtype=np.float64)
        except (ValueError, IndexError):
            raise InputError(path, f"malformed Open3D log entry at line {k + 1}") from None
        if len(lines[k]) != 3 or T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(path, f"malformed Open3D log entry at line {k + 1}: expected 'i j n' and a 4x4 matrix")
        out.append((idx, check_rigid(T, path)))
    return out


def tum_pose(vals: list[str], path: Path) -> np.ndarray:
    """[4 x 4] from the fields after the timestamp of a TUM ground-truth line: tx ty tz qx qy qz qw."""
    from scipy.spatial.transform import Rotation

    try:
        tx, ty, tz, qx, qy, qz, qw = (float(v) for v in vals[:7])
        if len(vals) < 7:
            raise ValueError
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
    except ValueError:
        raise InputError(path, "malformed ground truth line: expected 'timestamp tx ty tz qx qy qz qw'") from None
    T[:3, 3] = (tx, ty, tz)
    return T
