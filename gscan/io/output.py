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
