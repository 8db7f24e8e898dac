"""The HTTP pose-estimation service (`gscan serve`): templates kept warm, frames posted as multipart.

    serve(templates, host="127.0.0.1", port=8765, on_ready=None)   blocks until interrupted (`gscan.serve`)
    load_service(templates) -> Service;  create_app(service) -> the FastAPI application (tests, embedding)
    serve(..., depth_camera=load_depth_camera(depth_K, T_color_depth)): depth not registered to colour
    (gscan.io.camera.load_depth_camera), for the requests that name no depth camera of their own

The contract (endpoints, fields, errors) is in `gscan.service.service`; `gscan.service.api` is the HTTP layer
(FastAPI, imported only when an application is made); `gscan.client` is the Python client.
"""
from typing import Any

from gscan.service.decode import RequestError, decode_frame
from gscan.service.server import load_service, serve, template_name
from gscan.service.service import ServeParams, Service


def create_app(service: Service) -> Any:
    """The ASGI application of a Service (gscan.service.api.create_app)."""
    from gscan.service.api import create_app as _create_app

    return _create_app(service)


__all__ = ["RequestError", "ServeParams", "Service", "create_app", "decode_frame", "load_service", "serve",
           "template_name"]
