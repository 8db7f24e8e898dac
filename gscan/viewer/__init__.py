"""The web viewer of a template database (viser, imported only when a server starts): `serve` returns a running
`ViewerApp` (one class owning its scene and GUI), `run_viewer` serves until Ctrl+C (`gscan view`).

- app: `serve`, `run_viewer`, `ViewerApp`, `PortInUseError`, `check_port`
- data: `ViewerOptions`, `ViewerData`, `load_viewer_data` (numpy only)
"""
from __future__ import annotations

from gscan.viewer.app import PortInUseError, ViewerApp, check_port, run_viewer, serve
from gscan.viewer.data import ViewerData, ViewerOptions, load_viewer_data

__all__ = ["PortInUseError", "ViewerApp", "ViewerData", "ViewerOptions", "check_port", "load_viewer_data",
           "run_viewer", "serve"]
