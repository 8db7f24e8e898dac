"""The HTTP layer of the service (FastAPI): routes, the OpenAPI page at /docs, one-line errors, the body limit.

This module keeps its annotations evaluated (no `from __future__ import annotations`): FastAPI reads the
route signatures and response models at run time to build the OpenAPI schema.
"""
import logging
import re
from typing import Annotated, Any

from fastapi import FastAPI, File, Form, Path, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from gscan._version import __version__
from gscan.errors import GscanError
from gscan.service.decode import RequestError
from gscan.service.service import Service

log = logging.getLogger(__name__)


class Pose(BaseModel):
    T_cam_obj: list[list[float]] | None = Field(description="4x4 object-to-camera transform (metres), null when "
                                                               "not found")
    score: float = Field(description="depth agreement of the pose, 0-1")
    n_matches: int
    view: str | None
    reason: str | None = Field(description="why the object was not found (null when found)")
    grasps: dict[str, list[list[float]]] = Field(description="grasp name -> 4x4 T_cam_grasp")
    timings_ms: dict[str, float]
    method: str = Field(description="gmatch | pnp | track")


class Instance(Pose):
    pixels: dict[str, Any] = Field(description="the pixels the pose explains: count and box [x0, y0, x1, y1]")


class InstanceList(BaseModel):
    template: str
    instances: list[Instance] = Field(description="every instance found, best score first")
    reason: str | None = Field(description="why none was found (null when some were)")
    stopped: str | None = Field(description="why the search stopped")
    refused: list[Instance] = Field(description="instances given to another template claiming their pixels")
    timings_ms: dict[str, float]


class EstimateResponse(BaseModel):
    results: dict[str, Pose] = Field(description="per template: the `gscan estimate --json` object (with all: its "
                                                 "first instance, or not found with the reason)")
    instances: dict[str, InstanceList] | None = Field(None, description="with all: per template, the `gscan "
                                                      "estimate --all --json` object of the template")
    timings_ms: dict[str, float]


class TrackResponse(BaseModel):
    session: str
    template: str
    frame: int = Field(description="the frame's index in the session")
    status: str = Field(description="found | tracked | refound | lost")
    result: Pose
    timings_ms: dict[str, float]


class EndResponse(BaseModel):
    session: str
    frames: int


class Health(BaseModel):
    templates: list[str]


class Error(BaseModel):
    detail: str = Field(description="one line naming the field")


DEPTH_INTRINSICS = ("depth from a separate camera, not registered to colour: that camera's 3x3 calibration as "
                    "cam_K.txt holds it (the depth image has its size; it is reprojected into the colour camera). "
                    "Default: the service's depth camera, else the depth is registered to colour")
DEPTH_TO_COLOR = ("with depth_intrinsics: T_color_depth, the depth camera's pose in the colour camera: 16 numbers "
                  "(a 4x4 in rows, metres) or JSON {\"T\": [[4x4]]}. Default: the colour camera's centre and axes")

ERRORS: dict[Any, dict[str, Any]] = {c: {"model": Error} for c in (400, 404, 409, 413, 422, 500)}


def _one_line(text: Any) -> str:
    return " ".join(str(text).split())[:500]


class BodyLimit:
    """ASGI middleware: a request body larger than `limit` bytes gets 413 before it is read (by its
    Content-Length), or as soon as the count passes the limit (a chunked body)."""

    def __init__(self, app: Any, limit: int):
        self.app = app
        self.limit = limit

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is not None and (not length.strip().isdigit() or int(length) > self.limit):
            bad = not length.strip().isdigit()
            await _send_json(send, 400 if bad else 413, "content-length: not a number" if bad else
                             f"request: body larger than {self.limit} bytes")
            return
        seen = 0
        started = exceeded = False
        too_big = f"request: body larger than {self.limit} bytes"

        async def counted() -> dict:
            nonlocal seen, exceeded
            msg = await receive()
            if msg.get("type") == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.limit:
                    exceeded = True
                    raise RequestError("request", f"body larger than {self.limit} bytes", 413)
            return msg

        async def tracked_send(msg: dict) -> None:
            nonlocal started
            if exceeded:  # whatever the app answers to the aborted body (its form parser says 400), it is a 413
                if msg.get("type") == "http.response.start" and not started:
                    started = True
                    await _send_json(send, 413, too_big)
                return
            started = started or msg.get("type") == "http.response.start"
            await send(msg)

        try:
            await self.app(scope, counted, tracked_send)
        except RequestError as e:  # raised outside the routes' error handlers
            if not started:
                started = True
                await _send_json(send, e.status, _one_line(e.detail))


async def _send_json(send: Any, status: int, detail: str) -> None:
    import json

    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


def create_app(service: Service) -> Any:
    """The FastAPI application of a Service (routes in gscan.service.service's docstring), wrapped in BodyLimit."""
    app = FastAPI(title="gscan pose estimation", version=__version__,
                  description="6DoF pose of scanned objects in RGB-D frames, templates kept warm. Colour: PNG or "
                              "JPEG; depth: a 16-bit PNG; intrinsics: the 3x3 numbers of a cam_K.txt; depth from a "
                              "separate camera: depth_intrinsics and depth_to_color. A bad request "
                              "gets 4xx and {\"detail\": \"one line naming the field\"}.")

    @app.exception_handler(RequestError)
    async def _request_error(_: Request, e: RequestError) -> JSONResponse:
        return JSONResponse({"detail": _one_line(e.detail)}, status_code=e.status)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(_: Request, e: RequestValidationError) -> JSONResponse:
        errs = e.errors()
        err = errs[0] if errs else {}
        loc = [str(x) for x in err.get("loc", ()) if x not in ("body", "query", "path", "form", "header")]
        field = loc[0] if loc else "request"
        msg = "missing" if err.get("type") == "missing" else err.get("msg", "invalid")
        return JSONResponse({"detail": _one_line(f"{field}: {msg}")}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_: Request, e: StarletteHTTPException) -> JSONResponse:
        detail = _one_line(e.detail)  # the framework's own (an unparsable body, an unknown path): name the request
        return JSONResponse({"detail": detail if re.match(r"^[\w.-]+: ", detail) else f"request: {detail}"},
                            status_code=e.status_code)

    @app.exception_handler(Exception)
    async def _internal_error(_: Request, e: Exception) -> JSONResponse:
        if isinstance(e, GscanError):
            return JSONResponse({"detail": _one_line(e)}, status_code=400)
        log.exception("request failed")
        return JSONResponse({"detail": _one_line(f"internal error: {e.__class__.__name__}: {e}")}, status_code=500)

    async def _read(field: str, f: UploadFile | None) -> bytes | None:
        if f is None:
            return None
        data = await f.read()
        if not data and field != "mask":
            raise RequestError(field, "empty file")
        return data

    @app.get("/health", response_model=Health)
    def health() -> dict[str, Any]:
        """The templates this service holds (a template's name is its file name without .gscan)."""
        return {"templates": list(service.estimators)}

    @app.post("/estimate", response_model=EstimateResponse, responses=ERRORS)
    async def estimate(
        color: Annotated[UploadFile, File(description="colour image, PNG or JPEG")],
        depth: Annotated[UploadFile, File(description="depth, 16-bit PNG, raw units (see depth_scale)")],
        intrinsics: Annotated[str, Form(description="the 3x3 calibration as cam_K.txt holds it")],
        depth_scale: Annotated[float, Form(description="metres per raw depth unit")] = 0.001,
        mask: Annotated[UploadFile | None,
                        File(description="optional search mask (PNG or JPEG, object > half)")] = None,
        templates: Annotated[str | None, Form(description="comma-separated template names (default: all)")] = None,
        depth_intrinsics: Annotated[str | None, Form(description=DEPTH_INTRINSICS)] = None,
        depth_to_color: Annotated[str | None, Form(description=DEPTH_TO_COLOR)] = None,
        all: Annotated[bool, Form(description="every instance of every template (`instances`)")] = False,
    ) -> dict[str, Any]:
        """The pose of every requested template's object in one RGB-D frame (all: every instance of each)."""
        c, d, m = await _read("color", color), await _read("depth", depth), await _read("mask", mask)
        return await run_in_threadpool(service.estimate, c or b"", d or b"", intrinsics, depth_scale, m, templates,
                                       depth_intrinsics, depth_to_color, all)

    @app.post("/track/{session}", response_model=TrackResponse, responses=ERRORS)
    async def track(
        session: Annotated[str, Path(description="a client-chosen id: 1-64 letters, digits, '.', '_', '-'")],
        color: Annotated[UploadFile, File(description="colour image, PNG or JPEG")],
        depth: Annotated[UploadFile, File(description="depth, 16-bit PNG, raw units (see depth_scale)")],
        intrinsics: Annotated[str, Form(description="the 3x3 calibration as cam_K.txt holds it")],
        depth_scale: Annotated[float, Form(description="metres per raw depth unit")] = 0.001,
        mask: Annotated[UploadFile | None, File(description="optional search mask")] = None,
        template: Annotated[str | None, Form(description="the template to track (needed to start a session when "
                                                         "several are served)")] = None,
        depth_intrinsics: Annotated[str | None, Form(description=DEPTH_INTRINSICS)] = None,
        depth_to_color: Annotated[str | None, Form(description=DEPTH_TO_COLOR)] = None,
    ) -> dict[str, Any]:
        """The next frame of a tracking session (its first frame starts it): the previous pose is the prior, as
        in `gscan track`."""
        c, d, m = await _read("color", color), await _read("depth", depth), await _read("mask", mask)
        return await run_in_threadpool(service.track, session, c or b"", d or b"", intrinsics, depth_scale, m,
                                       template, depth_intrinsics, depth_to_color)

    @app.delete("/track/{session}", response_model=EndResponse, responses=ERRORS)
    def end_track(session: str) -> dict[str, Any]:
        """End a tracking session."""
        return service.end_track(session)

    return BodyLimit(app, service.params.max_request_bytes)
