"""The estimation service's state and work (`gscan serve`), independent of the HTTP layer (gscan.service.api):
templates loaded once and kept warm.

    GET    /health              -> {"templates": [names]}
    POST   /estimate            multipart: color, depth, intrinsics, [depth_scale], [mask], [templates],
                                [depth_intrinsics], [depth_to_color], [all]
                                -> {"results": {name: <the estimate --json object>}, "timings_ms": {"total": ...}}
                                with all=true also "instances": {name: <its estimate --all --json object>}
    POST   /track/{session}     multipart: color, depth, intrinsics, [depth_scale], [mask], [template],
                                [depth_intrinsics], [depth_to_color]
                                -> {"session", "template", "frame", "status", "result", "timings_ms"}
    DELETE /track/{session}     -> {"session", "frames"}
    GET    /docs                the OpenAPI page

Depth not registered to colour (a separate depth camera): a request's `depth_intrinsics` (the depth camera's
3x3, as cam_K.txt holds it) and optional `depth_to_color` (T_color_depth: 16 numbers or JSON, metres; default
the colour camera's centre and axes) describe its depth camera, whose image is reprojected into the colour
camera before estimation; a request without them uses the service's depth camera when it was started with
one (`depth_camera`), else its depth is registered to colour. `depth_to_color` alone is refused (422).

A bad request gets HTTP 4xx and {"detail": "one line naming the field"}; an error inside the estimator gets
500 with one line; neither stops the server. Requests are decoded and estimated one at a time (a lock): the
estimator is tuned for one thread, and a second concurrent frame would only slow both. A tracking session (a
client-chosen id) keeps a `gscan.estimate.Tracker`, the same as `gscan track` frame by frame; sessions idle
for `session_ttl_s` are dropped, and at most `max_sessions` are kept (the least recently used goes first).
"""
from __future__ import annotations

import logging
import re
import threading
import time
from collections import OrderedDict
from typing import Any

from gscan.estimate import Estimator, Tracker, estimate_templates
from gscan.estimate.result import not_found
from gscan.io.camera import DepthCamera
from gscan.service.decode import RequestError, decode_frame, depth_camera_fields
from gscan.service.params import ServeParams

log = logging.getLogger(__name__)

SESSION_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


class _Session:
    def __init__(self, name: str, tracker: Tracker):
        self.template = name
        self.tracker = tracker
        self.frames = 0
        self.used = time.monotonic()


class Service:
    """The service's state: the warm estimators, the tracking sessions and the lock that serialises work."""

    def __init__(self, estimators: dict[str, Estimator], params: ServeParams | None = None,
                 depth_camera: DepthCamera | None = None):
        if not estimators:
            raise ValueError("the service needs at least one template")
        self.estimators = dict(estimators)
        self.params = params or ServeParams()
        self.depth_camera = depth_camera  # for requests that name none (None: their depth is registered)
        self.lock = threading.Lock()
        self.sessions: OrderedDict[str, _Session] = OrderedDict()

    def names(self, field: str, text: str | None) -> list[str]:
        """Template names of a comma-separated field (None or empty: all)."""
        if text is None or not text.strip():
            return list(self.estimators)
        names = [t.strip() for t in text.split(",") if t.strip()]
        unknown = [n for n in names if n not in self.estimators]
        if unknown:
            raise RequestError(field, f"unknown template {unknown[0]!r} (serving: {', '.join(self.estimators)})", 404)
        return list(dict.fromkeys(names))

    def request_depth_camera(self, depth_intrinsics: str | None,
                             depth_to_color: str | None) -> tuple[DepthCamera | None, bool]:
        """The depth camera of a request: its own fields', else the service's (None: registered depth), and
        whether it is the service's."""
        own = depth_camera_fields(depth_intrinsics, depth_to_color)
        return (own, False) if own is not None else (self.depth_camera, self.depth_camera is not None)

    def estimate(self, color: bytes, depth: bytes, intrinsics: str, depth_scale: float, mask: bytes | None,
                 templates: str | None, depth_intrinsics: str | None = None,
                 depth_to_color: str | None = None, all_instances: bool = False) -> dict[str, Any]:
        """The pose of every requested template's object; all_instances: every instance of each
        (`estimate_templates`), the response's "instances" {name: the `estimate --all` object of the template}
        and its "results" each template's first instance (or its reason)."""
        t0 = time.perf_counter()
        names = self.names("templates", templates)
        cam, served = self.request_depth_camera(depth_intrinsics, depth_to_color)
        with self.lock:
            frame = decode_frame(color, depth, intrinsics, depth_scale, mask, max_pixels=self.params.max_pixels,
                                 depth_camera=cam, served=served)
            if all_instances:
                outs = estimate_templates([self.estimators[n] for n in names], frame, frame.mask)
                insts = {n: o.to_json() for n, o in zip(names, outs, strict=True)}
                first_of = {n: i["instances"][0] if i["instances"] else not_found(i["reason"] or "not found").to_json()
                            for n, i in insts.items()}
                return {"results": first_of, "instances": insts,
                        "timings_ms": {"total": (time.perf_counter() - t0) * 1e3}}
            first = self.estimators[names[0]]
            q = first.prepare(frame, frame.mask)  # the frame's full-image work, shared by the templates
            results = {}
            for n in names:
                est = self.estimators[n]
                same = est.params == first.params and est.camera_fix == first.camera_fix
                results[n] = (est.estimate_prepared(q) if same else est.estimate(frame, frame.mask)).to_json()
        return {"results": results, "timings_ms": {"total": (time.perf_counter() - t0) * 1e3}}

    def track(self, session: str, color: bytes, depth: bytes, intrinsics: str, depth_scale: float,
              mask: bytes | None, template: str | None, depth_intrinsics: str | None = None,
              depth_to_color: str | None = None) -> dict[str, Any]:
        t0 = time.perf_counter()
        if not SESSION_ID.match(session):
            raise RequestError("session", "1-64 letters, digits, '.', '_' or '-'", 400)
        cam, served = self.request_depth_camera(depth_intrinsics, depth_to_color)
        with self.lock:
            self._expire()
            s = self.sessions.get(session)
            if s is None:
                if template is None or not template.strip():
                    if len(self.estimators) > 1:
                        raise RequestError("template", f"required to start a session when serving several "
                                                       f"templates ({', '.join(self.estimators)})", 422)
                    template = next(iter(self.estimators))
                name = self.names("template", template)
                if len(name) != 1:
                    raise RequestError("template", "one template per session")
                s = _Session(name[0], Tracker(self.estimators[name[0]]))
            elif template is not None and template.strip() and template.strip() != s.template:
                raise RequestError("template", f"session {session!r} tracks {s.template!r}, not {template.strip()!r}",
                                   409)
            frame = decode_frame(color, depth, intrinsics, depth_scale, mask, name=f"{session}:{s.frames}",
                                 max_pixels=self.params.max_pixels, depth_camera=cam, served=served)
            step = s.tracker.step(frame, frame.mask)
            s.frames += 1
            s.used = time.monotonic()
            self.sessions[session] = s
            self.sessions.move_to_end(session)
            while len(self.sessions) > self.params.max_sessions:
                self.sessions.popitem(last=False)
            return {"session": session, "template": s.template, "frame": s.frames - 1, "status": step.status,
                    "result": step.result.to_json(), "timings_ms": {"total": (time.perf_counter() - t0) * 1e3}}

    def end_track(self, session: str) -> dict[str, Any]:
        with self.lock:
            s = self.sessions.pop(session, None)
        if s is None:
            raise RequestError("session", f"no tracking session {session!r}", 404)
        return {"session": session, "frames": s.frames}

    def _expire(self) -> None:
        now = time.monotonic()
        for k in [k for k, s in self.sessions.items() if now - s.used > self.params.session_ttl_s]:
            del self.sessions[k]
