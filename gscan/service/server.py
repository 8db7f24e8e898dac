"""Starting the service: templates loaded (and their kernels warmed up) once, then uvicorn on a socket bound
before anything is announced, so a busy port is a one-line error and `on_ready` only runs once requests are
accepted (queued by the kernel until uvicorn takes them)."""
from __future__ import annotations

import logging
import socket
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from gscan.errors import InputError, not_a_file
from gscan.estimate import Estimator
from gscan.service.decode import DepthCameraSpec, RequestError, parse_K
from gscan.service.service import ServeParams, Service

log = logging.getLogger(__name__)


def template_name(path: str | Path) -> str:
    """A template's name in the service: its file name without `.gscan`."""
    p = Path(path)
    return p.name[: -len(".gscan")] if p.name.endswith(".gscan") else p.stem


def load_depth_camera(intrinsics: str | Path, T_color_depth: str | Path | None = None) -> DepthCameraSpec:
    """The service's depth camera, for requests that name none: its intrinsics file (a cam_K.txt, which fits
    depth images of any size, or an Open3D / BOP intrinsics JSON with its size) and T_color_depth's (a 4x4
    text or JSON matrix, metres; None: the colour camera's centre and axes). InputError naming the file."""
    from gscan.io.camera import load_intrinsics
    from gscan.io.poses import read_pose_file, read_pose_txt

    path = Path(intrinsics)
    if not path.is_file():
        raise not_a_file(path, "intrinsics file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read intrinsics ({e.__class__.__name__})") from None
    if path.suffix.lower() == ".json" or text.lstrip().startswith("{"):
        intr = load_intrinsics(path)
        K, size = intr.K, (intr.width, intr.height)
    else:
        try:
            K, size = parse_K(text), None
        except RequestError as e:
            raise InputError(path, e.reason) from None
    T = np.eye(4)
    if T_color_depth is not None:
        pose = Path(T_color_depth)
        T = read_pose_file(pose) if pose.suffix.lower() == ".json" else read_pose_txt(pose)
    return DepthCameraSpec(K, size, T, served=True)


def load_service(templates: Sequence[str | Path], params: ServeParams | None = None,
                 depth_camera: DepthCameraSpec | None = None) -> Service:
    """Load every template (InputError naming a bad one, or two templates of one name); `depth_camera`: the
    service's own, for requests that name none (`load_depth_camera`)."""
    if not templates:
        raise InputError(None, "no template given")
    estimators: dict[str, Estimator] = {}
    for t in templates:
        name = template_name(t)
        if name in estimators:
            raise InputError(t, f"another template is already served as {name!r} (names are file names without "
                                ".gscan)")
        estimators[name] = Estimator.from_path(t)
    return Service(estimators, params or ServeParams(), depth_camera)


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on host:port (port 0: a free one); InputError when it cannot be had."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise InputError(None, f"--host {host!r}: {e.strerror or e}") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(128)
    except OSError as e:
        sock.close()
        raise InputError(None, f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    return sock


def serve(templates: Sequence[str | Path], host: str = "127.0.0.1", port: int = 8765,
          on_ready: Callable[[str], None] | None = None, params: ServeParams | None = None,
          depth_intrinsics: str | Path | None = None, depth_to_color: str | Path | None = None) -> None:
    """Serve pose estimation for `templates` over HTTP (gscan.service.api) until interrupted (Ctrl+C / SIGTERM).
    Binds 127.0.0.1 by default: other machines reach it only when `host` says so. on_ready(url) is called
    once requests are accepted. depth_intrinsics / depth_to_color: files of the depth camera of requests that
    name none (`load_depth_camera`); a depth-to-colour pose needs the intrinsics too."""
    import uvicorn

    if depth_intrinsics is None and depth_to_color is not None:
        raise InputError(depth_to_color, "a depth-to-colour pose needs the depth camera's intrinsics too")
    cam = None if depth_intrinsics is None else load_depth_camera(depth_intrinsics, depth_to_color)
    service = load_service(templates, params, cam)
    sock = bind(host, port)
    from gscan.service.api import create_app

    app = create_app(service)
    h, p = sock.getsockname()[:2]
    url = f"http://{'[' + h + ']' if ':' in h else h}:{p}"
    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off", timeout_keep_alive=30)
    server = uvicorn.Server(config)
    if on_ready is not None:
        on_ready(url)
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()
