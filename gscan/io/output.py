"""Outputs written safely: the one set of rules every gscan writer follows.

- An output that cannot be written fails at once, on one line naming it (`check_output`), before any work.
- A folder is never taken for a file (nor a file for a folder), and an existing output is never replaced
  without `force` (`OutputExists`; the CLI names its option).
- The new output is written into a hidden temporary sibling (same folder, so the final rename is atomic)
  and renamed into place only once it is complete (`Output`); a run that fails, or is interrupted, removes
  what it created (the sibling and the folders made for it) and leaves the old output as it was.
- Two writers of one output never write into the same file: each has its own sibling, and the last to
  finish wins with a complete output; without `force`, a writer that finds the output created meanwhile
  by another is refused (`OutputExists`).
- Temporary names stay within NAME_MAX, with room for SQLite's journal beside them, so a long output
  name works.
- An output never lands on an input of the same command (`check_not_input`): one that is, contains or lies
  inside an input is refused whatever `force` says, so no input is replaced or written into.
- An OSError of the file system is named for what it is (`write_error`): a full disk, a quota, the
  process's file size limit, a read-only file system.
"""
from __future__ import annotations

import errno
import os
import secrets
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Self  # typing.Self from Python 3.11

from gscan.errors import InputError, OutputExists

NAME_MAX = 255  # bytes of one file name (Linux, macOS)
JOURNAL_SUFFIX = "-journal"  # SQLite's rollback journal beside a database file
# every file SQLite keeps beside a database: the rollback journal, the write-ahead log and its index (shorter
# names than the journal's, so JOURNAL_SUFFIX sets the room left for them)
SQLITE_SIDECARS = (JOURNAL_SUFFIX, "-wal", "-shm")
_FREE_BYTES_FULL = 1 << 20  # a file system with less free space than this counts as full


# ------------------------------------------------------------------------------------------ checks
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
                raise InputError(path, f"cannot be created: folder {d} takes no new file ({describe_os_error(e)})"
                                 ) from None
            return


def real_path(path: str | Path) -> Path:
    """`path` absolute with every link followed (the part that exists), a loop of links left where it is met:
    what two paths are compared as."""
    path = Path(path).absolute()
    try:
        return path.resolve()
    except (OSError, RuntimeError):  # a loop of links (RuntimeError before Python 3.13)
        return Path(os.path.realpath(path))


def check_not_input(output: str | Path, inputs: Iterable[str | Path | None], *, inside_ok: bool = False) -> None:
    """InputError naming `output` and the input when the output is, contains or lies inside one of `inputs`
    (None entries skipped), compared with links followed: writing it would replace or change that input, so
    it is refused whatever `force` says (no fix is offered). `inside_ok`: an output inside an input folder is
    allowed (a batch's templates folder inside its captures folder, which it reads past)."""
    out = real_path(output)
    for inp in inputs:
        if inp is None:
            continue
        real = real_path(inp)
        if real == out:
            how = "is the input"
        elif out in real.parents:
            how = "contains the input"
        elif real in out.parents and not inside_ok:
            how = "lies inside the input"
        else:
            continue
        raise InputError(output, f"{how} {inp}: an output never replaces or goes into an input of the same "
                         "command; choose another output path")


def occupied(path: Path) -> bool:
    """Whether an output at `path` would replace something: a file, a link, or a folder that is not empty."""
    if path.is_dir() and not path.is_symlink():
        try:
            return any(path.iterdir())
        except OSError:
            return True
    return path.exists() or path.is_symlink()


def check_output(path: str | Path, *, force: bool = False, folder: bool = False, kind: str = "file path",
                 fix: str = "replace") -> None:
    """Refuse an output before any work: a folder where a file is written (or, without `force`, a file
    where a folder is), an existing output without `force` (OutputExists with `fix`), a path that cannot
    be created (`check_output_path`). `kind` says what the file is ("a .gscan file path")."""
    path = Path(path)
    if not folder and path.is_dir():
        raise InputError(path, f"output is a folder, expected a {kind}")
    if occupied(path) and not force:
        raise OutputExists(path, fix=fix)
    check_output_path(path)


def journal_fits(path: str | Path) -> bool:
    """Whether SQLite's journal beside the database `path` has a legal name (NAME_MAX bytes)."""
    return len(os.fsencode(Path(path).name + JOURNAL_SUFFIX)) <= NAME_MAX


# ------------------------------------------------------------------------------------------ errors
def describe_os_error(e: OSError) -> str:
    """What a file system error means, in words a user acts on (disk full, file size limit, ...)."""
    no = e.errno
    if no == errno.ENOSPC:
        return "no space left on the device (disk full)"
    if no == errno.EDQUOT:
        return "disk quota exceeded"
    if no == errno.EFBIG:
        return f"file too large: {file_size_limit_text()}"
    if no == errno.EROFS:
        return "read-only file system"
    if no in (errno.EACCES, errno.EPERM):
        return "permission denied"
    if no == errno.ENAMETOOLONG:
        return "file name too long"
    if no == errno.EISDIR:
        return "a folder is in the way"
    return e.strerror or str(e)


def file_size_limit_text() -> str:
    """The file size limit a write ran into: the process's (ulimit -f) when one is set, else the file system's."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if soft != resource.RLIM_INFINITY:
            return f"the process's file size limit (ulimit -f) of {soft} bytes was reached"
    except (ImportError, OSError, ValueError):
        pass
    return "the file system's file size limit was reached"


def write_failure_reason(path: str | Path) -> str | None:
    """Why writing the file `path` failed when the writer (SQLite) reports only an I/O error: the disk is
    full, or the file reached the process's file size limit; None when neither is the case."""
    path = Path(path)
    try:
        st = os.statvfs(path.parent)
        if st.f_bavail * st.f_frsize < _FREE_BYTES_FULL:
            return "no space left on the device (disk full)"
    except OSError:
        pass
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    except (ImportError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    sizes = [p.stat().st_size for p in (path, *(Path(f"{path}{x}") for x in SQLITE_SIDECARS)) if p.is_file()]
    if sizes and max(sizes) + _FREE_BYTES_FULL >= soft:
        return f"file too large: {file_size_limit_text()}"
    return None


def write_error(path: str | Path, e: OSError) -> InputError:
    """The InputError naming output `path` for an OSError met while writing it."""
    return InputError(path, f"cannot write the output: {describe_os_error(e)}")


# ------------------------------------------------------------------------------------------ names
def temp_sibling(path: str | Path, tag: str = "tmp") -> Path:
    """A new hidden name beside `path`: ".<name>.<tag>-<8 random hex>", the name shortened (whole
    characters) so that it and SQLite's journal beside it stay within NAME_MAX bytes."""
    path = Path(path)
    suffix = f".{tag}-{secrets.token_hex(4)}"
    budget = NAME_MAX - len(JOURNAL_SUFFIX) - 1 - len(suffix)
    stem = path.name
    while len(os.fsencode(stem)) > budget:
        stem = stem[:-1]
    return path.with_name(f".{stem}{suffix}")


# ------------------------------------------------------------------------------------------ removal
def remove_sqlite_sidecars(path: str | Path) -> None:
    """Remove SQLite's journal and write-ahead log beside the database `path` (`SQLITE_SIDECARS`), left by a
    writer that was killed: SQLite would replay them into whatever database next has that name, so a new file
    put there must not meet them. Never raises."""
    for x in SQLITE_SIDECARS:
        remove(Path(f"{path}{x}"))


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


def file_identity(path: str | Path) -> tuple[int, int] | None:
    """(device, inode) of the file at `path` (links not followed), None when there is none: tells whether the
    file there is still the one this process created, or another process's since."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def remove(path: Path) -> None:
    """Remove a file, a link or a folder tree if it exists; never raises."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists() or path.is_symlink():
            path.unlink()
    except OSError:
        pass


# ------------------------------------------------------------------------------------------ the writer
class Output:
    """One output file or folder, written into a temporary sibling and renamed into place on success.

        with Output(path, force=force) as out:   # checks (check_output), makes the missing folders
            write(out.tmp)                        # a hidden sibling: an empty file, or an empty folder
        # renamed into place here; an exception removes the sibling and the folders made for it,
        # and an OSError is reported as an InputError naming `path` (disk full, ...)

    `open`, `commit` and `discard` do the same steps for a writer that cannot be one `with` block.
    An InputError raised while writing that names the sibling is re-raised naming `path`.
    """

    def __init__(self, path: str | Path, *, force: bool = False, folder: bool = False, kind: str = "file path",
                 fix: str = "replace"):
        self.path = Path(path)
        self.force, self.folder, self.fix = force, folder, fix
        check_output(self.path, force=force, folder=folder, kind=kind, fix=fix)
        self.tmp: Path = temp_sibling(self.path)
        self._made: list[Path] = []
        self._open = False

    # -- steps
    def open(self) -> Path:
        """Make the missing folders and the empty sibling; returns the sibling's path."""
        self._made = missing_folders(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            while True:
                try:
                    if self.folder:
                        self.tmp.mkdir()
                    else:
                        os.close(os.open(self.tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
                    break
                except FileExistsError:  # a name drawn twice: draw another
                    self.tmp = temp_sibling(self.path)
        except OSError as e:
            remove_empty_folders(self._made)
            raise write_error(self.path, e) from None
        self._open = True
        return self.tmp

    def commit(self) -> None:
        """Rename the complete sibling into place (see the module docstring for concurrent writers)."""
        try:
            if self.folder:
                self._commit_folder()
            elif self.force:
                os.replace(self.tmp, self.path)
            else:
                self._commit_new_file()
        except BaseException as e:
            self.discard()
            if isinstance(e, OSError):
                raise write_error(self.path, e) from None
            raise
        self._open = False

    def discard(self) -> None:
        """Remove the sibling (and SQLite's journal and log beside it) and the folders made for it; never raises."""
        remove(self.tmp)
        remove_sqlite_sidecars(self.tmp)
        remove_empty_folders(self._made)
        self._open = False

    def translate(self, e: BaseException) -> BaseException:
        """The exception to report for `e` met while writing: an OSError becomes an InputError naming the
        output, an InputError naming the sibling names the output instead."""
        if isinstance(e, OSError):
            return write_error(self.path, e)
        if isinstance(e, InputError) and e.path is not None and e.path.name.startswith(self.tmp.name):
            out = type(e).__new__(type(e))
            InputError.__init__(out, self.path, e.reason, e.fix)
            return out
        return e

    # -- context manager
    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None) -> None:
        if e is None:
            self.commit()
            return
        self.discard()
        t = self.translate(e)
        if t is not e:
            raise t from None

    # -- renames
    def _commit_new_file(self) -> None:
        """Link the sibling to `path` only if nothing is there (another writer may have created it since the
        check); file systems without hard links get a rename after one more check."""
        try:
            os.link(self.tmp, self.path)
        except FileExistsError:
            raise OutputExists(self.path, "already exists (created by another process while this one wrote it)",
                               fix=self.fix) from None
        except OSError as e:
            if e.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK, errno.EXDEV):
                raise
            if occupied(self.path):
                raise OutputExists(self.path, "already exists (created by another process while this one wrote it)",
                                   fix=self.fix) from None
            os.replace(self.tmp, self.path)
            return
        remove(self.tmp)  # the output is in place: the second name goes (never raises)

    def _commit_folder(self) -> None:
        """Move the old folder (or file) aside, rename the new one into place, then delete the old one. A
        concurrent writer may swap its own in between: then this one tries again (its output is as complete)."""
        for _ in range(20):
            old = None
            if occupied(self.path):
                if not self.force:
                    raise OutputExists(self.path, "already exists (created by another process while this one "
                                       "wrote it)", fix=self.fix)
                old = temp_sibling(self.path, "old")
                try:
                    os.rename(self.path, old)
                except FileNotFoundError:  # another writer moved it away first
                    continue
            try:
                os.rename(self.tmp, self.path)
            except OSError as e:
                if old is not None:
                    try:
                        os.rename(old, self.path)  # put the old one back if the place is still free
                    except OSError:
                        remove(old)
                if e.errno in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR):
                    continue  # another writer's output landed first
                raise
            if old is not None:
                remove(old)
            return
        raise InputError(self.path, "cannot be replaced: other processes kept replacing it meanwhile")
