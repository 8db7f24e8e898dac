"""Output paths: checked before any work, so that an output that cannot be written fails at once, on
one line naming it, instead of after a long run (or as an internal error)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from gscan.errors import InputError


def check_output_path(path: str | Path) -> None:
    """InputError naming `path` when it cannot be created: a folder on its way is a file, or the nearest
    existing folder takes no new file (permissions, a read-only or virtual file system: tried with a
    probe file, removed at once). Folders still missing are made later, by the writer."""
    path = Path(path)
    for d in path.absolute().parents:  # nearest first
        if d.exists():
            if not d.is_dir():
                raise InputError(path, f"cannot be created: {d} is a file, not a folder")
            try:
                fd, probe = tempfile.mkstemp(prefix=".gscan-probe-", dir=d)
                os.close(fd)
                os.unlink(probe)
            except OSError as e:
                raise InputError(path, f"cannot be created: folder {d} takes no new file ({e.strerror or e})") from None
            return


def missing_folders(path: str | Path) -> list[Path]:
    """The folders on `path`'s way that do not exist yet, deepest first: what a failed writer removes."""
    p = Path(path)
    return [d for d in (p.parent, *p.parent.parents) if not d.exists()]


def remove_empty_folders(folders: list[Path]) -> None:
    """Remove those of `folders` (deepest first) that exist and are empty; never raises."""
    for d in folders:
        try:
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
        except OSError:
            pass
