"""Exceptions shared by the library; the CLI maps them to exit codes.

`InputError` is bad input (exit code 2): its message is one line and names the file.
"""
from __future__ import annotations

from pathlib import Path


class GscanError(Exception):
    """Base class of every error gscan raises on purpose."""


class InputError(GscanError):
    """Bad input: a missing, corrupt or inconsistent file. The CLI exits with code 2.

    Args:
        path: the offending file or folder.
        reason: what is wrong with it, one line.
    """

    def __init__(self, path: str | Path | None, reason: str):
        self.path = None if path is None else Path(path)
        self.reason = " ".join(str(reason).split())
        super().__init__(f"{self.path}: {self.reason}" if self.path is not None else self.reason)
