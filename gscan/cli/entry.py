"""`main`, the `gscan` command: the process set up before any command module loads (OpenCV's log level, the
thread rule of gscan.threads), then the typer application run with its errors mapped to exit codes: 0 ok,
2 bad input (one line naming the file), 1 internal error, 130 interrupted."""
from __future__ import annotations

import errno
import os
import sys
from typing import NoReturn

import typer

from gscan.cli.output import err, error_line, interrupt_said, plain, printable
from gscan.errors import GscanError

try:  # typer >= 0.2x vendors click as typer._click; older releases use click itself
    from typer._click import exceptions as _cx
except ImportError:  # pragma: no cover - depends on the installed typer
    import click.exceptions as _cx  # type: ignore[no-redef]


def _setup_process() -> None:
    """What must hold before a command imports numpy, numba and OpenCV."""
    from gscan.threads import one_blas_thread

    if sys.stdout is None:  # started with stdout closed (`gscan ... >&-`): what it prints goes nowhere
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - lives as long as the process
    # OpenCV's own log lines ("[ERROR:0@0.1] global grfmt_png.cpp ... readHeader") would precede the one
    # error line gscan prints for an undecodable image; it is read when cv2 is first imported
    os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
    # every command is a process gscan owns: one BLAS / OpenMP / numba thread unless the environment names a count,
    # read by those libraries when they load
    one_blas_thread()


def main() -> None:
    """Console entry point: maps errors to exit codes (2 bad input, 1 internal)."""
    _setup_process()
    try:
        from gscan.cli.application import app

        rc = app(standalone_mode=False)
        if rc == 130 and not interrupt_said():  # typer turns Ctrl+C into exit code 130 without a word
            err.print("interrupted")
        sys.exit(rc if isinstance(rc, int) else 0)
    except _cx.NoArgsIsHelpError as e:  # bare `gscan` or a bare group: show the help
        sys.stdout.write(e.ctx.get_help() + "\n" if e.ctx else "")
        sys.exit(0)
    except _cx.UsageError as e:  # a wrong option value or a missing argument: one line, exit 2
        cmd = e.ctx.command_path if e.ctx else "gscan"
        plain(printable(f"error: {cmd}: {e.format_message()} (see `{cmd} --help`)"))
        sys.exit(2)
    except typer.Abort:
        err.print("aborted")
        sys.exit(130)
    except GscanError as e:  # InputError and the other deliberate errors: bad input
        plain(error_line(e))
        sys.exit(2)
    except KeyboardInterrupt:
        err.print("interrupted")
        sys.exit(130)
    except OSError as e:
        # the file system refused a write the library does not own (numba's kernel cache on first use, a
        # temporary file): disk full, quota, file size limit or a read-only file system, named as the writers
        # name it; any other OSError is an internal error
        if e.errno not in _RESOURCE_ERRNOS or os.environ.get("GSCAN_DEBUG"):
            _internal_error(e)
        from gscan.io.output import describe_os_error

        plain(printable(f"error: {e.filename or 'writing a file'}: {describe_os_error(e)}"))
        sys.exit(2)
    except Exception as e:  # noqa: BLE001 - the last resort: one line, exit 1
        _internal_error(e)


_RESOURCE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


def _internal_error(e: Exception) -> NoReturn:
    """Exit 1 with one line naming the unexpected error (its traceback with GSCAN_DEBUG=1)."""
    if os.environ.get("GSCAN_DEBUG"):
        raise e
    msg = " ".join(f"{e.__class__.__name__}: {e}".split())
    err.print(printable(f"internal error: {msg} (set GSCAN_DEBUG=1 for the traceback)"), markup=False,
              soft_wrap=True)
    sys.exit(1)
