"""`gscan serve`: pose estimation over HTTP with the templates kept warm."""
from __future__ import annotations

from pathlib import Path

import typer

from gscan.cli.output import say, setup_logging
from gscan.cli.texts import DEPTH_TO_COLOR_HELP, ESTIMATE_CONFIG_HELP


def serve(
    templates: list[Path] = typer.Argument(..., metavar="OBJ.gscan...", help="template databases to serve"),
    host: str = typer.Option("127.0.0.1", "--host", help="address to bind (0.0.0.0: every interface)"),
    port: int = typer.Option(8765, "--port", min=0, max=65535, help="port to serve on (0: a free one)"),
    depth_intrinsics: Path | None = typer.Option(
        None, "--depth-intrinsics", help="depth not registered to colour: the depth camera's cam_K.txt or Open3D "
        "intrinsics JSON, for the requests that name none (a request's depth_intrinsics field overrides it)"),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    config: Path | None = typer.Option(None, "--config", help=ESTIMATE_CONFIG_HELP),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log requests' details to stderr"),
) -> None:
    """Serve pose estimation over HTTP with the templates kept warm (OpenAPI page at /docs)."""
    setup_logging(verbose)
    from gscan.estimate.settings import load_estimate_params
    from gscan.io.camera import depth_camera_of
    from gscan.service.params import ServeParams
    from gscan.service.server import serve as run_service

    # the estimators' settings: the file's `estimate:` section (a bad key: exit 2 before any template loads)
    params = ServeParams(estimate=load_estimate_params(config))
    depth_camera = depth_camera_of(depth_intrinsics, depth_to_color)

    def ready(url: str) -> None:
        say("serving ", (", ".join(t.name for t in templates), "bold"), " at ", (url, "bold"),
            f" (API at {url}/docs; Ctrl+C to stop)"
            + (f"; depth camera {depth_intrinsics}" if depth_intrinsics is not None else ""))

    run_service(templates, host=host, port=port, on_ready=ready, params=params, depth_camera=depth_camera)
