"""gscan command line (typer). The only package that prints or exits.

Exit codes: 0 ok, 2 bad input (one line naming the file), 1 internal error.
`--json` prints exactly one JSON object on stdout, built by the library's result types (`to_json()`); progress
and logs go to stderr.

- entry: `main` (the `gscan` command): the process set up, then the application run, errors to exit codes
- application: the typer `app`, its global options, every command registered
- output: printing (`say`, `line`, `print_json`, `error_line`), poses as text
- choices: the choice types, made from the library's lists
- imports: the rule for imports in the command modules (heavy modules inside the command functions)
- scan (scan, template-from-mesh, config dump), estimate (estimate, track), template (info, poses, grasp add /
  list, export), view, service (serve), ros2 (the ROS 2 node), batch (eval, batch, batch-eval), capture, demo: the
  commands

Importing this package loads `main` alone: the application and its commands load when `main` has set the process
up, or on first use of the names below (PEP 562); the library a command runs loads inside the command.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

from gscan._lazy import lazy_exports
from gscan.cli.entry import main

_EXPORTS = {
    "app": "gscan.cli.application", "ExportFormat": "gscan.cli.choices", "ScanFormat": "gscan.cli.choices",
    "ScanMode": "gscan.cli.choices",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:
    from gscan.cli.application import app
    from gscan.cli.choices import ExportFormat, ScanFormat, ScanMode

__all__ = ["ExportFormat", "ScanFormat", "ScanMode", "app", "main"]
