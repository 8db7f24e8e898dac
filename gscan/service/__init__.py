"""The HTTP pose-estimation service (`gscan serve`): templates kept warm, frames posted as multipart.

    serve(templates, host="127.0.0.1", port=8765, on_ready=None)   blocks until interrupted (`gscan.serve`)
    load_service(templates) -> Service;  create_app(service) -> the FastAPI application (tests, embedding)
    serve(..., depth_camera=load_depth_camera(depth_K, T_color_depth)): depth not registered to colour
    (gscan.io.camera.load_depth_camera), for the requests that name no depth camera of their own

The contract (endpoints, fields, errors) is in `gscan.service.service`; `gscan.service.api` is the HTTP layer
(FastAPI, imported only when an application is made); `gscan.client` is the Python client.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gscan._lazy import lazy_exports

if TYPE_CHECKING:
    from gscan.service.service import Service

# imported on first use: `gscan serve` builds its settings and checks its templates before the estimator loads
_EXPORTS = {"RequestError": "gscan.service.decode", "decode_frame": "gscan.service.decode",
            "load_service": "gscan.service.server", "serve": "gscan.service.server",
            "template_name": "gscan.service.server", "ServeParams": "gscan.service.params",
            "Service": "gscan.service.service"}


def create_app(service: Service) -> Any:
    """The ASGI application of a Service (gscan.service.api.create_app)."""
    from gscan.service.api import create_app as _create_app

    return _create_app(service)


__all__ = ["RequestError", "ServeParams", "Service", "create_app", "decode_frame", "load_service", "serve",
           "template_name"]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
