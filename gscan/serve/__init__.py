"""The HTTP pose-estimation service (`gscan serve`): templates kept warm, frames posted as multipart.

    gscan.serve(templates, host="127.0.0.1", port=8765, on_ready=None)   blocks until interrupted
    load_service(templates) -> Service;  create_app(service) -> the FastAPI application (tests, embedding)
    load_depth_camera(depth_K, T_color_depth) -> the service's depth camera (depth not registered to colour)

`gscan.serve` is both this package and the function that starts the service (the package is callable, so the
name means the same whichever of the two was imported first).

The contract (endpoints, fields, errors) is in `gscan.serve.service`; `gscan.serve.api` is the HTTP layer
(FastAPI, imported only when an application is made); `gscan.client` is the Python client.
"""
import sys
import types
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from gscan.serve.decode import RequestError, decode_frame
from gscan.serve.server import load_depth_camera, load_service, template_name
from gscan.serve.server import serve as _serve
from gscan.serve.service import ServeParams, Service


def create_app(service: Service) -> Any:
    """The ASGI application of a Service (gscan.serve.api.create_app)."""
    from gscan.serve.api import create_app as _create_app

    return _create_app(service)


__all__ = ["RequestError", "ServeParams", "Service", "create_app", "decode_frame", "load_depth_camera", "load_service",
           "serve", "template_name"]


class _ServeModule(types.ModuleType):
    """This package, callable: `gscan.serve(templates, ...)` starts the service (gscan.serve.server.serve)."""

    def __call__(self, templates: Sequence[str | Path], host: str = "127.0.0.1", port: int = 8765,
                 on_ready: Callable[[str], None] | None = None, params: ServeParams | None = None,
                 depth_intrinsics: str | Path | None = None, depth_to_color: str | Path | None = None) -> None:
        _serve(templates, host=host, port=port, on_ready=on_ready, params=params, depth_intrinsics=depth_intrinsics,
               depth_to_color=depth_to_color)


sys.modules[__name__].__class__ = _ServeModule
serve = sys.modules[__name__]  # `from gscan.serve import serve`, `gscan.serve`: the same callable

