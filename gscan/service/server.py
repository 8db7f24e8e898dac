"""Starting the service: templates loaded (and their kernels warmed up) once, then uvicorn on a socket bound
before anything is announced, so a busy port is a one-line error and `on_ready` only runs once requests are
accepted (queued by the kernel until uvicorn takes them)."""
from __future__ import annotations

import logging
import socket
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from gscan.errors import InputError
from gscan.io.camera import DepthCamera
from gscan.service.params import ServeParams
from gscan.template.db import open_estimable

if TYPE_CHECKING:  # imported once the templates are checked: a bad one is refused without numba and scipy
    from gscan.service.service import Service

log = logging.getLogger(__name__)


def template_name(path: str | Path) -> str:
    """A template's name in the service: its file name without `.gscan`."""
    p = Path(path)
    return p.name[: -len(".gscan")] if p.name.endswith(".gscan") else p.stem


def load_service(templates: Sequence[str | Path], params: ServeParams | None = None,
                 depth_camera: DepthCamera | None = None) -> Service:
    """Load every template (InputError naming a bad one, or two templates of one name); `depth_camera`: the
    service's own, for requests that name none (`gscan.io.camera.load_depth_camera`)."""
    if not templates:
        raise InputError(None, "no template given")
    params = params or ServeParams()
    opened = {}
    for t in templates:
        name = template_name(t)
        if name in opened:
            raise InputError(t, f"another template is already served as {name!r} (names are file names without "
                                ".gscan)")
        opened[name] = open_estimable(t)
    from gscan.estimate.estimator import Estimator
    from gscan.service.service import Service

    return Service({name: Estimator(tpl, params.estimate) for name, tpl in opened.items()}, params, depth_camera)


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
          depth_camera: DepthCamera | None = None) -> None:
    """Serve pose estimation for `templates` over HTTP (gscan.service.api) until interrupted (Ctrl+C / SIGTERM).
    Binds 127.0.0.1 by default: other machines reach it only when `host` says so. on_ready(url) is called
    once requests are accepted. depth_camera: the depth camera of requests that name none
    (`gscan.io.camera.load_depth_camera`; None: their depth is registered to colour)."""
    import uvicorn

    service = load_service(templates, params, depth_camera)
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
