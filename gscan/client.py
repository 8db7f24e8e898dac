"""A small typed client of the `gscan serve` HTTP service (standard library only).

    from gscan.client import GscanClient
    client = GscanClient("http://127.0.0.1:8765")
    client.health()                                     # ["mug", "box"]
    r = client.estimate("color.png", "depth.png", "cam_K.txt")
    pose = r.results["mug"]
    if pose.found:
        print(pose.T_cam_obj, pose.grasps)
    step = client.track("arm-camera", color_png_bytes, depth_png_bytes, K, template="mug")
    step.status                                         # "found" | "tracked" | "refound" | "lost"
    client.end_track("arm-camera")
    r = client.estimate(color, depth_from_the_stereo_module, K, depth_camera=load_depth_camera("depth_K.txt", "T.txt"))

Images are given as file paths or encoded bytes (colour PNG or JPEG, depth a 16-bit PNG); numpy arrays are
encoded to PNG (colour RGB uint8, depth uint16 raw units), which needs OpenCV. Intrinsics: a cam_K.txt path,
its text, or a 3x3 nested list / array. Depth from a separate camera (not registered to colour): its
`gscan.io.camera.DepthCamera` (`depth_camera`, e.g. from `gscan.io.camera.load_depth_camera`), sent as the
request's `depth_intrinsics` (its K) and `depth_to_color` (its T_color_depth) fields; without one the service's
own depth camera applies (`gscan serve --depth-intrinsics`), else the depth is taken as registered. A refused request
raises `ServiceError` with the HTTP status and the service's one-line detail; a service that cannot be reached
raises `ServiceError` with status 0.
"""
from __future__ import annotations

import json
import os
import urllib.error
import urllib.parse
import urllib.request
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Union

if TYPE_CHECKING:  # the client itself needs only the standard library
    from gscan.io.camera import DepthCamera

ImageInput = Union[str, "os.PathLike[str]", bytes, Any]  # a path, encoded bytes, or a numpy array
IntrinsicsInput = Union[str, "os.PathLike[str]", Any]  # a cam_K.txt path or text, or a 3x3 matrix


class ServiceError(Exception):
    """A request the service refused (status 4xx / 5xx, detail: its one-line reason), or could not be sent
    (status 0)."""

    def __init__(self, status: int, detail: str):
        super().__init__(f"HTTP {status}: {detail}" if status else detail)
        self.status = status
        self.detail = detail


@dataclass(frozen=True)
class Pose:
    """One template's result (the `gscan estimate --json` object). T_cam_obj: 4x4 nested lists (metres) or None
    when not found (see `reason`); grasps: name -> 4x4 T_cam_grasp; symmetry: the object's symmetries the pose was
    picked under (None for an object without them)."""

    T_cam_obj: list[list[float]] | None
    score: float
    n_matches: int
    view: str | None
    reason: str | None
    grasps: dict[str, list[list[float]]] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)
    method: str = "gmatch"
    symmetry: str | None = None

    @property
    def found(self) -> bool:
        return self.T_cam_obj is not None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Pose:
        return cls(d.get("T_cam_obj"), float(d.get("score", 0.0)), int(d.get("n_matches", 0)), d.get("view"),
                   d.get("reason"), dict(d.get("grasps") or {}), dict(d.get("timings_ms") or {}),
                   str(d.get("method", "gmatch")), d.get("symmetry"))


@dataclass(frozen=True)
class EstimateResponse:
    results: dict[str, Pose]  # template name -> result (with all_instances: its first instance)
    timings_ms: dict[str, float]
    instances: dict[str, list[Pose]] = field(default_factory=dict)  # with all_instances: every one, best first


@dataclass(frozen=True)
class TrackResponse:
    session: str
    template: str
    frame: int  # the frame's index in the session
    status: str  # "found" | "tracked" | "refound" | "lost"
    result: Pose
    timings_ms: dict[str, float]


class GscanClient:
    """Client of one `gscan serve` instance at `url` (e.g. "http://127.0.0.1:8765"); `timeout` in seconds."""

    def __init__(self, url: str = "http://127.0.0.1:8765", timeout: float = 30.0):
        self.url = url.rstrip("/")
        self.timeout = timeout

    def health(self) -> list[str]:
        """The names of the templates the service holds."""
        return list(self._request("GET", "/health")["templates"])

    def estimate(self, color: ImageInput, depth: ImageInput, intrinsics: IntrinsicsInput, depth_scale: float = 0.001,
                 mask: ImageInput | None = None, templates: list[str] | None = None,
                 depth_camera: DepthCamera | None = None, all_instances: bool = False) -> EstimateResponse:
        """The pose of every requested template's object (default: all) in one RGB-D frame (depth from a
        separate camera: `depth_camera`); all_instances: every instance of each (`EstimateResponse.instances`)."""
        fields = self._frame_fields(color, depth, intrinsics, depth_scale, mask, depth_camera)
        if templates:
            fields.append(("templates", None, ",".join(templates).encode()))
        if all_instances:
            fields.append(("all", None, b"true"))
        d = self._request("POST", "/estimate", fields)
        insts = {k: [Pose.from_json(p) for p in v["instances"]] for k, v in (d.get("instances") or {}).items()}
        return EstimateResponse({k: Pose.from_json(v) for k, v in d["results"].items()}, dict(d["timings_ms"]),
                                insts)

    def track(self, session: str, color: ImageInput, depth: ImageInput, intrinsics: IntrinsicsInput,
              depth_scale: float = 0.001, mask: ImageInput | None = None, template: str | None = None,
              depth_camera: DepthCamera | None = None) -> TrackResponse:
        """The next frame of tracking session `session` (its first frame starts it; `template` is needed then
        when the service holds several; depth from a separate camera: `depth_camera`)."""
        fields = self._frame_fields(color, depth, intrinsics, depth_scale, mask, depth_camera)
        if template:
            fields.append(("template", None, template.encode()))
        d = self._request("POST", f"/track/{urllib.parse.quote(session, safe='')}", fields)
        return TrackResponse(d["session"], d["template"], int(d["frame"]), d["status"], Pose.from_json(d["result"]),
                             dict(d["timings_ms"]))

    def end_track(self, session: str) -> int:
        """End a tracking session; returns the number of frames it saw."""
        return int(self._request("DELETE", f"/track/{urllib.parse.quote(session, safe='')}")["frames"])

    # ---------------------------------------------------------------------------------------------
    def _frame_fields(self, color: ImageInput, depth: ImageInput, intrinsics: IntrinsicsInput, depth_scale: float,
                      mask: ImageInput | None,
                      depth_camera: DepthCamera | None = None) -> list[tuple[str, str | None, bytes]]:
        fields = [("color", "color.png", _image_bytes(color, depth=False)),
                  ("depth", "depth.png", _image_bytes(depth, depth=True)),
                  ("intrinsics", None, _intrinsics_text(intrinsics).encode()),
                  ("depth_scale", None, repr(float(depth_scale)).encode())]
        if mask is not None:
            fields.append(("mask", "mask.png", _image_bytes(mask, depth=False)))
        if depth_camera is not None:  # its K (the service fits it to the depth image's size) and T_color_depth
            fields.append(("depth_intrinsics", None, _matrix_text(depth_camera.K, 3, "depth_intrinsics").encode()))
            fields.append(("depth_to_color", None,
                           _matrix_text(depth_camera.T_color_depth, 4, "depth_to_color").encode()))
        return fields

    def _request(self, method: str, path: str, fields: list[tuple[str, str | None, bytes]] | None = None) -> Any:
        body, headers = None, {"Accept": "application/json"}
        if fields is not None:
            body, ctype = _multipart(fields)
            headers["Content-Type"] = ctype
        req = urllib.request.Request(self.url + path, data=body, headers=headers, method=method)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                return json.loads(resp.read().decode("utf-8"))
        except urllib.error.HTTPError as e:
            raw = e.read().decode("utf-8", "replace")
            try:
                detail = str(json.loads(raw).get("detail", raw))
            except (ValueError, AttributeError):
                detail = raw.strip() or e.reason
            raise ServiceError(e.code, detail) from None
        except (urllib.error.URLError, OSError) as e:
            reason = getattr(e, "reason", e)
            raise ServiceError(0, f"cannot reach {self.url}: {reason}") from None


def _multipart(fields: list[tuple[str, str | None, bytes]]) -> tuple[bytes, str]:
    """multipart/form-data body of (name, filename or None, data) fields and its content type."""
    boundary = "gscan-" + uuid.uuid4().hex
    out = bytearray()
    for name, filename, data in fields:
        out += f"--{boundary}\r\n".encode()
        disp = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out += f"Content-Disposition: {disp}\r\n".encode()
        if filename:
            out += b"Content-Type: application/octet-stream\r\n"
        out += b"\r\n" + data + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out), f"multipart/form-data; boundary={boundary}"


def _image_bytes(img: ImageInput, depth: bool) -> bytes:
    if isinstance(img, (bytes, bytearray, memoryview)):
        return bytes(img)
    if isinstance(img, (str, os.PathLike)):
        return Path(img).read_bytes()
    if hasattr(img, "shape") and hasattr(img, "dtype"):  # a numpy array: PNG-encoded with OpenCV
        import cv2
        import numpy as np

        a = np.asarray(img)
        if depth:
            if a.dtype != np.uint16:
                raise TypeError(f"a depth array must be uint16 raw units, not {a.dtype}")
        elif a.ndim == 3:
            a = cv2.cvtColor(np.ascontiguousarray(a, dtype=np.uint8), cv2.COLOR_RGB2BGR)
        ok, buf = cv2.imencode(".png", a)
        if not ok:
            raise ValueError("cannot encode the array as PNG")
        return buf.tobytes()
    raise TypeError(f"an image must be a path, bytes or a numpy array, not {type(img).__name__}")


def _intrinsics_text(K: IntrinsicsInput) -> str:
    return _matrix_text(K, 3, "intrinsics")


def _matrix_text(M: Any, n: int, what: str) -> str:
    """An n x n matrix field's text: a file's (a path), the text itself, or the rows of a nested list / array."""
    if isinstance(M, os.PathLike) or (isinstance(M, str) and "\n" not in M.strip() and Path(M).is_file()):
        return Path(M).read_text(encoding="utf-8")
    if isinstance(M, str):
        return M
    rows = [[float(x) for x in row] for row in M]
    if len(rows) != n or any(len(r) != n for r in rows):
        raise ValueError(f"{what} must be a {n}x{n} matrix")
    return "\n".join(" ".join(repr(x) for x in r) for r in rows) + "\n"
