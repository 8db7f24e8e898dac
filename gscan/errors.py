"""Exceptions shared by the library; the CLI maps them to exit codes.

`InputError` is bad input (exit code 2): its message is one line and names the file. Library messages
describe the problem; `fix` names, as a key of `FIXES`, what the caller can change about it, and the CLI
turns that key into its own option (`--force`, `--resume`, ...), so the library never names a flag.
"""
from __future__ import annotations

import errno
import os
from pathlib import Path

# what an InputError's `fix` may name (the CLI holds the option or command of each)
FIXES = (
    "replace",        # an existing output: replace it (force=True)
    "resume",         # an existing scan output: continue it (resume=True) or replace it (force=True)
    "restart",        # a partial scan of another input or configuration: start it over (force=True)
    "finish",         # a partial template: finish the scan that wrote it (resume)
    "depth_scale",    # the depth scale
    "intrinsics",     # an intrinsics file
    "obj_id",         # the BOP object id
    "gt_capture",     # the ground-truth capture a scanned template is related to
    "port",           # the viewer's port
    "host",           # the viewer's address
    "output",         # another output (an existing one that may not be replaced)
    "roi",            # the box that shows the object in the first frame
    "mask",           # the mask that shows the object in the first frame
)


class GscanError(Exception):
    """Base class of every error gscan raises on purpose."""


class InputError(GscanError):
    """Bad input: a missing, corrupt or inconsistent file. The CLI exits with code 2.

    Args:
        path: the offending file or folder.
        reason: what is wrong with it, one line.
        fix: what the caller can change about it, one of `FIXES` (the CLI names its option).
    """

    def __init__(self, path: str | Path | None, reason: str, fix: str | None = None):
        if fix is not None and fix not in FIXES:
            raise ValueError(f"unknown fix {fix!r}; expected one of {FIXES}")
        self.path = None if path is None else Path(path)
        self.reason = " ".join(str(reason).split())
        self.fix = fix
        super().__init__(f"{self.path}: {self.reason}" if self.path is not None else self.reason)


class OutputExists(InputError):
    """An output that exists and may not be replaced (no `force`)."""

    def __init__(self, path: str | Path, reason: str = "already exists", fix: str = "replace"):
        super().__init__(path, reason, fix)


def not_a_file(path: str | Path, what: str) -> InputError:
    """The InputError for an input file `what` (e.g. "intrinsics file") that is missing or not a file."""
    path = Path(path)
    if path.is_dir():
        return InputError(path, f"is a folder; expected the {what}")
    if path.exists():
        return InputError(path, f"is not a regular file; expected the {what}")
    if path.is_symlink():
        try:
            os.stat(path)
        except OSError as e:
            if e.errno == errno.ELOOP:
                return InputError(path, f"is a loop of symbolic links; expected the {what}")
        return InputError(path, f"{what} not found (a broken symbolic link)")
    return InputError(path, f"{what} not found")
