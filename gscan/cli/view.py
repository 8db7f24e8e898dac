"""`gscan view`: a template (views, matches, pose graph) in the web browser, optionally with a query frame."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from gscan.cli.estimate import load_query_frame
from gscan.cli.output import UsageError, line, say


def view(
    template: Path = typer.Argument(..., help="template database"),
    host: str = typer.Option("127.0.0.1", "--host", help="address to bind"),
    port: int = typer.Option(8080, "--port", min=1, max=65535, help="port to serve on"),
    color: Path | None = typer.Option(None, "--color", help="show this frame with the estimated pose"),
    depth: Path | None = typer.Option(None, "--depth", help="depth of --color"),
    intrinsics: Path | None = typer.Option(None, "--intrinsics", help="intrinsics of --color"),
    depth_scale: float = typer.Option(0.001, "--depth-scale", help="metres per raw depth unit"),
    pose: Path | None = typer.Option(
        None, "--pose", help='T_cam_obj of --color\'s frame instead of estimating it: {"T": 4x4} or a bare 4x4 list'),
    estimate: Path | None = typer.Option(
        None, "--estimate", help="an estimate result (`gscan estimate --json`, with --all: every instance) to draw: "
        "each pose found, and the refused ones in a panel; with --color/--depth/--intrinsics, in that frame"),
    token: str | None = typer.Option(None, "--token", help="serve only browsers that open the URL with "
                                     "?token=TOKEN (1-256 of A-Z a-z 0-9 . _ ~ -)"),
) -> None:
    """Browse a template (views, matches, pose graph) in the web browser."""
    from gscan.viewer.access import check_token, is_loopback
    from gscan.viewer.app import run_viewer

    if token is not None:
        check_token(token)
    elif not is_loopback(host):
        say(("warning:", "yellow"), f" --host {host} is not a loopback address: every image of {template.name} "
            "is served without authentication to anyone who can reach this port; pass --token to require one")

    frame = T_cam_obj = instances = None
    if pose is not None and color is None:
        raise UsageError(pose, "--pose places a query frame: it needs --color, --depth and --intrinsics")
    if pose is not None and estimate is not None:
        raise UsageError(estimate, "--estimate and --pose both give the frame's poses: pass one")
    if estimate is not None:
        from gscan.viewer.instances import read_estimate_result

        instances = read_estimate_result(estimate, template.stem)
    if color is not None or depth is not None or intrinsics is not None:
        if color is None or depth is None or intrinsics is None:
            raise UsageError(None, "--color, --depth and --intrinsics go together")
        frame = load_query_frame(color, depth, intrinsics, depth_scale, None)
        if instances is None:
            T_cam_obj = _query_pose(template, frame, pose)
    run_viewer(template, host=host, port=port, scene_frame=frame, T_cam_obj=T_cam_obj, token=token,
               instances=instances, on_ready=lambda url: say("viewer ready at ", (url, "bold"), " (Ctrl+C to stop)"))


def _query_pose(template: Path, frame: Any, pose: Path | None) -> Any:
    """The query frame's T_cam_obj: read from `pose`, else estimated (its outcome said on a line)."""
    if pose is not None:
        from gscan.io import read_pose_file

        return read_pose_file(pose)
    from gscan.estimate.estimator import Estimator

    result = Estimator.from_path(template).estimate(frame)
    found = f"view {result.view}" if result.T_cam_obj is not None else f"not found ({result.reason})"
    line(f"estimate: {found}")
    return result.T_cam_obj
