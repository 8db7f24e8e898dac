"""Web viewer of a template database (viser): the server and the app that owns its scene and GUI (`gscan view`).

`serve(db_path, ...)` loads a complete template (`gscan.viewer.data`, `TemplateDB.open(require_complete=True)`),
starts a viser server bound to `host:port` (127.0.0.1 by default; a port in use raises `PortInUseError`, never a
silent move to another port) and populates the scene (`gscan.viewer.scene`), all in the template (object) frame:

- the fused mesh (vertex colours) and point cloud; the template's axes;
- one camera frustum per registered view carrying its downscaled snapshot, coloured by registration
  quality (green good .. red poor); unregistered views are listed in the GUI, not drawn;
- pose-graph edges as line segments between camera centres: sequential edges green .. red by ICP RMSE,
  loop closures cyan .. magenta by RMSE, rejected edges grey (own toggle); a legend explains the scales;
- the views' 3D keypoints (hidden by default), grasp frames as axes;
- optionally a query RGB-D frame's cloud placed in the template frame by an estimated `T_cam_obj`, and the
  instances an estimate found in it (`gscan.viewer.instances`): the template's mesh at each pose, labelled with
  its rank and score, and an "Instances" panel naming each one found and each one refused with its reason.

GUI: layer toggles, point / frustum size sliders, a view slider + dropdown (or click a frustum) showing the
view's image with its keypoints and its edges, "Go to view" (moves every browser's camera to the view's
pose), and the "Match panel": for a chosen edge, both images side by side with the matched keypoint pairs
joined by lines and the edge's numbers. Only gscan.viewer imports viser.
"""
from __future__ import annotations

import contextlib
import errno
import io
import logging
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gscan.errors import InputError
from gscan.geometry.coverage import CoverageMap
from gscan.io.camera import RGBDFrame
from gscan.template.db import Edge, View, unregistered_names
from gscan.viewer.access import TokenGate, check_token
from gscan.viewer.data import ViewerData, ViewerOptions, load_viewer_data
from gscan.viewer.draw import draw_keypoints, draw_matches, legend_html
from gscan.viewer.instances import ShownInstances
from gscan.viewer.text import md_text

log = logging.getLogger(__name__)

_SELECT_EDGE = "(select an edge)"


class PortInUseError(InputError):
    """The viewer's port cannot be bound (exit code 2 in the CLI)."""

    def __init__(self, host: str, port: int, detail: str = "already in use", fix: str = "port"):
        self.host, self.port = host, int(port)
        super().__init__(None, f"cannot serve the viewer on {host}:{port}: {detail}", fix=fix)


# ------------------------------------------------------------------------------------------ helpers
def check_port(host: str, port: int) -> None:
    """Raise PortInUseError when `host:port` cannot be bound (viser would silently move to another port)."""
    if not 1 <= port <= 65535:
        raise InputError(None, f"the port must be 1-65535, not {port}", fix="port")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise PortInUseError(host, port, f"unknown host ({e.strerror})", fix="host") from None
    for family, stype, proto, _, addr in infos[:1]:
        with socket.socket(family, stype, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server does
            try:
                s.bind(addr)
                s.listen(1)
            except OSError as e:
                detail = "already in use" if e.errno == errno.EADDRINUSE else (e.strerror or str(e))
                raise PortInUseError(host, port, detail) from None


# ------------------------------------------------------------------------------------------ the app
class ViewerApp:
    """A running viewer: `server` (viser.ViserServer), `url`, `data`; it builds its scene and GUI on the server
    at construction. select_view / select_edge / go_to_view drive the GUI from Python (the browser drives the
    same functions); `stop()` shuts the server down.

    scene_frame / T_cam_obj [4 x 4]: a query frame and the object's pose in it (see `serve`); grasps:
    {name: T_obj_grasp [4 x 4]} drawn as axes; gate / token: the token gate in front of viser (None: viser
    serves host:port itself) and its token, which the url carries; instances: an estimate's instances in the
    frame, drawn relative to T_cam_obj.
    """

    def __init__(self, server: Any, data: ViewerData, host: str, port: int, options: ViewerOptions,
                 scene_frame: RGBDFrame | None = None, T_cam_obj: np.ndarray | None = None,
                 grasps: dict[str, np.ndarray] | None = None, gate: TokenGate | None = None,
                 token: str | None = None, instances: ShownInstances | None = None):
        self.server, self.data, self.host, self.port, self.options = server, data, host, port, options
        self.gate = gate
        self.url = f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"  # IPv6 in brackets
        if token is not None:
            self.url += f"/?token={token}"
        self._lock = threading.RLock()
        self._names = [v.name for v in data.views]
        self._by_name = {v.name: v for v in data.views}
        self._current: str | None = None
        self._edge_labels: dict[str, Edge] = {}
        from gscan.viewer.scene import build_scene  # scipy: loaded once a template is served

        scene = build_scene(server, data, options, scene_frame, T_cam_obj, grasps or {}, self.select_view, instances)
        self.layers: dict[str, list] = scene.layers  # layer key -> viser scene handles (toggled together)
        self.frustum_scale = scene.frustum_scale  # frustum depth (m) at "Frustum size" 1
        self.scene_points_obj = scene.scene_points_obj  # [N x 3] query-frame cloud drawn (template frame) or None
        self.instances_obj = scene.instances_obj  # T_obj_inst [4 x 4] of each instance drawn (template frame)
        self.instances = instances
        self._build_gui(scene_frame is not None, T_cam_obj)
        if data.views:
            self.select_view(data.views[0].name)

    # -- selection ---------------------------------------------------------------------------------
    def select_view(self, name: str) -> None:
        """Show view `name` in the Views folder and list its edges in the Match panel."""
        with self._lock:
            if name not in self._by_name:
                raise KeyError(f"no view named {name!r}")
            if name == self._current:
                return
            self._current = name
            self._view_slider.value = self._names.index(name)
            self._view_dropdown.value = name
            v, d = self._by_name[name], self.data
            px, _ = d.keypoints[name]
            self._view_image.image = draw_keypoints(d.thumbs[name], px, d.image_wh[name])
            self._view_md.content = self._view_markdown(v)
            self._goto_button.disabled = v.T_obj_cam is None
            edges = [e for e in d.edges if name in (e.src, e.tgt)]
            self._edge_labels = {_edge_label(e): e for e in edges}
            self._edge_dropdown.options = [_SELECT_EDGE, *self._edge_labels]
            self._edge_dropdown.value = _SELECT_EDGE
            self._show_edge(None)

    def select_edge(self, label: str) -> None:
        with self._lock:
            if label != _SELECT_EDGE and label not in self._edge_labels:
                raise KeyError(f"no edge {label!r} for the selected view")
            self._edge_dropdown.value = label
            self._show_edge(self._edge_labels.get(label))

    def _show_layer(self, key: str, visible: bool) -> None:
        for h in self.layers[key]:
            h.visible = visible

    def go_to_view(self, name: str | None = None) -> None:
        """Move every connected browser's camera to the pose of view `name` (default: the selected one)."""
        name = name or self._current
        if name is None:
            return
        v = self._by_name[name]
        if v.T_obj_cam is None:
            return
        R, t = v.T_obj_cam[:3, :3], v.T_obj_cam[:3, 3]
        depth = max(float((self.data.center - t) @ R[:, 2]), 0.1 * self.data.size)
        fov = 2.0 * np.arctan2(v.intrinsics.height / 2.0, v.intrinsics.fy)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position = t
                client.camera.look_at = t + R[:, 2] * depth
                client.camera.up_direction = -R[:, 1]
                client.camera.fov = float(fov)

    def stop(self) -> None:
        if self.gate is not None:
            self.gate.stop()
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()

    # -- GUI ---------------------------------------------------------------------------------------
    def _build_gui(self, has_frame: bool, T_cam_obj: np.ndarray | None) -> None:
        """The GUI panel: summary, layer toggles and sizes, the Views folder, the Match panel, the legend."""
        from gscan.viewer.scene import symmetry_label

        gui, d, o = self.server.gui, self.data, self.options
        reg = d.registered
        unreg = unregistered_names(d.views, d.meta.get("skipped"))  # as `gscan poses` lists them
        acc = sum(e.accepted for e in d.edges)
        loops = sum(e.accepted and e.kind == "loop" for e in d.edges)
        summary = [f"**{md_text(d.path.name)}** · {md_text(d.meta.get('source', 'scan'))}  ",
                   f"views: {len(d.views)} · registered: {len(reg)}  ",
                   f"edges: {acc} accepted ({loops} loop) · {len(d.edges) - acc} rejected  ",
                   f"size: {d.size * 100:.1f} cm  ", coverage_markdown(d.coverage)]
        if unreg:
            summary.append(f"  \n**unregistered ({len(unreg)}):** " + ", ".join(md_text(n) for n in unreg))
        axes = d.symmetries.axes()
        summary.append("  \n**symmetries:** " + (", ".join(
            f"{symmetry_label(a.fold, a.in_texture)} about ({', '.join(f'{x + 0.0:.2f}' for x in a.direction)})"
            for a in axes) if axes else "none found"))
        if has_frame:
            placed = "the estimated pose" if self.instances is None else "the first instance's pose"
            summary.append("  \n**query frame:** " + ("pose not found (cloud not placed)" if T_cam_obj is None
                                                       else f"cloud placed by {placed}"))
        gui.add_markdown("\n".join(summary))
        if self.instances is not None:
            with gui.add_folder("Instances"):
                self._instances_md = gui.add_markdown(self.instances.markdown())

        with gui.add_folder("Layers", expand_by_default=False):
            toggles = [("Mesh", "mesh"), ("Cloud", "cloud"), ("Frustums", "frustums"), ("Edges", "edges"),
                       ("Rejected edges", "rejected"), ("3D keypoints", "keypoints"), ("Grasps", "grasps"),
                       ("Symmetry axes", "symmetries"), ("Query frame", "scene"), ("Coverage", "coverage"),
                       ("Instances", "instances")]
            for label, key in toggles:
                if self.layers.get(key):
                    cb = gui.add_checkbox(label, initial_value=all(h.visible for h in self.layers[key]))
                    cb.on_update(lambda ev, k=key: self._show_layer(k, ev.target.value))
            base = 0.004 * d.size * 1000.0
            ps = gui.add_slider("Point size (mm)", min=0.1, max=round(max(4 * base, 1.0), 1), step=0.1,
                                initial_value=round(base, 1))

            @ps.on_update
            def _(_ev) -> None:
                for key, f in (("cloud", 1.0), ("scene", 1.0), ("keypoints", 1.5)):
                    for h in self.layers.get(key, []):
                        h.point_size = f * ps.value / 1000.0

            fs = gui.add_slider("Frustum size", min=0.25, max=3.0, step=0.05, initial_value=1.0)

            @fs.on_update
            def _(_ev) -> None:
                for h in self.layers.get("frustums", []):
                    h.scale = self.frustum_scale * fs.value

        with gui.add_folder("Views"):
            n = max(len(d.views), 1)
            self._view_slider = gui.add_slider("View #", min=0, max=max(n - 1, 1), step=1, initial_value=0,
                                               disabled=len(d.views) < 2)
            self._view_dropdown = gui.add_dropdown("View", [v.name for v in d.views] or ["(no views)"])
            self._goto_button = gui.add_button("Go to view", icon=None)
            self._view_image = gui.add_image(np.full((240, 320, 3), 90, np.uint8), label="View image",
                                             format="jpeg", jpeg_quality=o.jpeg_quality)
            self._view_md = gui.add_markdown("")
        self._view_slider.on_update(lambda ev: self.select_view(self._names[int(ev.target.value)])
                                    if int(ev.target.value) < len(self._names) else None)
        self._view_dropdown.on_update(lambda ev: self.select_view(ev.target.value)
                                      if ev.target.value in self._by_name else None)
        self._goto_button.on_click(lambda _ev: self.go_to_view())

        with gui.add_folder("Match panel"):
            self._edge_dropdown = gui.add_dropdown("Edge", [_SELECT_EDGE])
            self._match_image = gui.add_image(np.full((240, 640, 3), 90, np.uint8), label="Matches", format="jpeg",
                                              jpeg_quality=o.jpeg_quality, visible=False)
            self._match_md = gui.add_markdown("", visible=False)
        self._edge_dropdown.on_update(lambda ev: self.select_edge(ev.target.value)
                                      if ev.target.value == _SELECT_EDGE or ev.target.value in self._edge_labels
                                      else None)

        with gui.add_folder("Legend", expand_by_default=False):
            gui.add_html(legend_html(o.rmse_red_m))

    # -- panels ------------------------------------------------------------------------------------
    def _view_markdown(self, v: View) -> str:
        n_kp = len(self.data.keypoints[v.name][0])
        q = self.data.quality.get(v.name)
        lines = [f"**{md_text(v.name)}** ({self._names.index(v.name) + 1}/{len(self._names)})  ",
                 f"keypoints: {n_kp} · quality: {'-' if q is None else f'{q:.2f}'}"
                 + ("" if v.keyframe else " · not a keyframe") + "  "]
        if v.T_obj_cam is None:
            lines.append("**unregistered** (not drawn)")
        else:
            lines.append("centre (m): " + ", ".join(f"{x:+.3f}" for x in v.T_obj_cam[:3, 3]))
        edges = [e for e in self.data.edges if v.name in (e.src, e.tgt)]
        if edges:
            lines += ["", "| edge | kind | matches | mm | ok |", "|---|---|---|---|---|"]
            for e in edges:
                other = e.tgt if e.src == v.name else e.src
                arrow = "→" if e.src == v.name else "←"
                lines.append(f"| {arrow} {md_text(other)} | {md_text(e.kind)} | {len(e.matches)} | {_mm(e.rmse)} | "
                             f"{'yes' if e.accepted else 'no'} |")
        else:
            lines.append("\nno edges")
        return "\n".join(lines)

    def _show_edge(self, e: Edge | None) -> None:
        if e is None:
            self._match_image.visible = False
            self._match_md.visible = False
            return
        d = self.data
        grey = np.full((240, 320, 3), 90, np.uint8)
        side = {n: (d.thumbs.get(n, grey), d.keypoints[n][0] if n in d.keypoints else np.zeros((0, 2)),
                    d.image_wh.get(n, (320, 240))) for n in (e.src, e.tgt)}
        (img_s, px_s, wh_s), (img_t, px_t, wh_t) = side[e.src], side[e.tgt]
        m = np.asarray(e.matches, dtype=np.int64).reshape(-1, 2)
        ok = (m[:, 0] >= 0) & (m[:, 0] < len(px_s)) & (m[:, 1] >= 0) & (m[:, 1] < len(px_t))
        self._match_image.image = draw_matches(img_s, px_s, wh_s, img_t, px_t, wh_t, m[ok],
                                               self.options.max_match_lines)
        txt = [f"**{md_text(e.src)} → {md_text(e.tgt)}**  ",
               f"kind: {md_text(e.kind)} · accepted: {'yes' if e.accepted else 'no'}  ",
               f"matches: {len(m)} · cost: {_num(e.cost, '.4f')}  ",
               f"RMSE: {_mm(e.rmse)} mm · fitness: {_num(e.fitness, '.3f')}"]
        if e.reason:
            txt.append(f"  \nreason: {md_text(e.reason)}")
        if not ok.all():
            txt.append(f"  \n{int((~ok).sum())} match indices out of range (not drawn)")
        self._match_md.content = "\n".join(txt)
        self._match_image.visible = True
        self._match_md.visible = True


def coverage_markdown(coverage: CoverageMap | None) -> str:
    """The panel's lines on the template's coverage: the share of viewing directions seen and each missing region
    (None: a template made before coverage was recorded)."""
    if coverage is None:
        return "coverage: unknown (not recorded in this template)"
    return "  \n".join([f"coverage: {coverage.share:.0%} of the viewing directions seen"]
                        + [f"missing: {md_text(m)}" for m in coverage.missing()])


def _edge_label(e: Edge) -> str:
    return f"{e.src} → {e.tgt} ({e.kind}{'' if e.accepted else ', rejected'})"


def _num(x: float | None, fmt: str) -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, fmt)


def _mm(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x * 1000:.2f}"


# ------------------------------------------------------------------------------------------ building
def serve(db_path: str | Path, host: str = "127.0.0.1", port: int = 8080, scene_frame: RGBDFrame | None = None,
          T_cam_obj: np.ndarray | None = None, grasps: dict[str, np.ndarray] | None = None,
          options: ViewerOptions = ViewerOptions(), token: str | None = None,
          instances: ShownInstances | None = None) -> ViewerApp:
    """Load a complete template and serve it on http://host:port; returns once the scene is populated.

    scene_frame / T_cam_obj [4 x 4]: a query frame and the object's estimated pose in it; the frame's cloud
    is drawn in the template frame (inv(T_cam_obj) applied), or listed as "not found" when T_cam_obj is None.
    grasps: {name: T_obj_grasp [4 x 4]} drawn as axes, added to the template's own grasps.
    token: serve only connections that carry it (`gscan.viewer.access.TokenGate`; viser then listens on
    127.0.0.1 alone); the app's url carries it.
    instances: the instances an estimate found in scene_frame (`gscan.viewer.instances.read_estimate_result`),
    each drawn at its pose relative to T_cam_obj (default: the first instance's pose, which the template frame
    then shows), and listed, with the refused ones, in the "Instances" panel.
    Raises InputError (partial / missing database, a token that cannot stand in a URL) and PortInUseError.
    """
    data = load_viewer_data(db_path, options)  # a bad template is named before any port is tried
    if token is not None:
        check_token(token)
    check_port(host, port)
    import viser  # once the template and the port are checked: a bad one is answered without it

    quiet_websockets()
    with contextlib.redirect_stdout(io.StringIO()) as banner:  # viser prints a banner; library code never prints
        server = viser.ViserServer(host="127.0.0.1" if token is not None else host, port=0 if token is not None
                                   else port, label=f"gscan · {Path(db_path).name}", verbose=False)
    log.debug("viser: %s", banner.getvalue().strip())
    bound = server.get_port()
    gate = None
    try:
        if token is not None:
            gate = TokenGate(host, port, bound, token)
            gate.start()
        elif bound != port:  # lost a race for the port after check_port: viser moved on silently
            raise PortInUseError(host, port)
    except BaseException as e:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
        if isinstance(e, OSError):  # the gate lost the race for the port
            raise PortInUseError(host, port, e.strerror or str(e)) from None
        raise
    if instances is not None and T_cam_obj is None and instances.found:
        T_cam_obj = instances.found[0].T_cam_obj
    try:
        return ViewerApp(server, data, host, port, options, scene_frame, T_cam_obj, {**data.grasps, **(grasps or {})},
                         gate=gate, token=token, instances=instances)
    except BaseException:
        if gate is not None:
            gate.stop()
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
        raise


class _DropHandshakeNoise(logging.Filter):
    """websockets logs a traceback for every TCP connection that is not a WebSocket/HTTP request (port
    probes, health checks); they are not errors of the viewer."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "opening handshake failed" not in record.getMessage()


def quiet_websockets() -> None:
    lg = logging.getLogger("websockets.server")
    if not any(isinstance(f, _DropHandshakeNoise) for f in lg.filters):
        lg.addFilter(_DropHandshakeNoise())


def run_viewer(db_path: str | Path, host: str = "127.0.0.1", port: int = 8080, scene_frame: RGBDFrame | None = None,
               T_cam_obj: np.ndarray | None = None, grasps: dict[str, np.ndarray] | None = None,
               on_ready: Callable[[str], None] | None = None, options: ViewerOptions = ViewerOptions(),
               token: str | None = None, instances: ShownInstances | None = None) -> None:
    """`serve` and block until interrupted (Ctrl+C); `on_ready(url)` is called once the scene is populated."""
    app = serve(db_path, host, port, scene_frame=scene_frame, T_cam_obj=T_cam_obj, grasps=grasps, options=options,
                token=token, instances=instances)
    try:
        if on_ready is not None:
            on_ready(app.url)
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
