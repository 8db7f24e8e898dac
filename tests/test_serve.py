"""The estimation service (`gscan serve`, gscan.serve) started as a subprocess on a free port, driven through
gscan.client: 20 frames posted (the object present, absent, and bad requests), tracking sessions, depth from a
separate camera (the request's or the service's, against `gscan estimate --depth-intrinsics`), and the
request decoding on its own."""
from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
from _recordings import T_depth_offset

from gscan.client import GscanClient, Pose, ServiceError
from gscan.errors import InputError
from gscan.geometry.transforms import look_at, pose_error, rotvec_to_R, transform_points
from gscan.io.camera import DepthCamera, Intrinsics, load_depth_camera
from gscan.service.decode import RequestError, decode_frame, depth_camera_fields, depth_camera_intrinsics, parse_pose
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    default_distance,
    load_textured_mesh,
    place_distractors,
    rest_on_table,
)

TARGET = "Frozen_Scrabble_Jr"
DISTRACTORS = ("Crayola_Bonus_64_Crayons", "Little_Debbie_Cloud_Cakes_10_ct")
K_TEXT = "\n".join(" ".join(f"{x:.10g}" for x in row) for row in DEFAULT_INTRINSICS.K) + "\n"
# a separate depth camera (a stereo module beside the colour sensor): its own size and calibration
K_DEPTH = Intrinsics(452.0, 453.0, 241.0, 178.5, 480, 360)


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def frame_bytes(r) -> tuple[bytes, bytes]:
    """(colour PNG, 16-bit depth PNG in millimetres) of a rendered frame."""
    mm = np.clip(np.rint(r.depth * 1000.0), 0, 65535).astype(np.uint16)
    return png(cv2.cvtColor(r.color, cv2.COLOR_RGB2BGR)), png(mm)


def scene_of(meshes, seed: int, with_target: bool = True) -> tuple[SynthScene, np.ndarray, np.ndarray]:
    """(the scene, T_world_cam of the colour camera, T_cam_obj of the target) of a seeded random layout."""
    rng = np.random.default_rng(seed)
    target, distractors = meshes[0], meshes[1:]
    T_wt = rest_on_table(target, rotvec_to_R([0.0, 0.0, rng.uniform(0, 2 * np.pi)]))
    d_poses = place_distractors(target, T_wt, list(distractors), rng)
    objs = ([(target, T_wt)] if with_target else []) + list(zip(distractors, d_poses, strict=True))
    c = transform_points(T_wt, target.center[None])[0]
    el, az = np.radians(rng.uniform(30, 55)), rng.uniform(0, 2 * np.pi)
    eye = c + default_distance(target, fill=0.45) * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                                               np.sin(el)])
    T_wc = look_at(eye, c)
    return SynthScene(objs, seed=seed, table_kind="wood"), T_wc, np.linalg.inv(T_wc) @ T_wt


def render(meshes, seed: int, with_target: bool = True):
    scene, T_wc, T_gt = scene_of(meshes, seed, with_target)
    return scene.render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng(seed)), T_gt


def huge_png_header(width: int, height: int) -> bytes:
    """A PNG whose header claims width x height pixels (decoding it would take gigabytes)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64))
            + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def meshes(meshes_dir: Path):
    return [load_textured_mesh(meshes_dir / n / "model_0.obj") for n in (TARGET,) + DISTRACTORS]


@pytest.fixture(scope="module")
def template(cad_template) -> Path:
    return cad_template(TARGET, 16)  # TARGET.gscan: the service names it TARGET


@pytest.fixture(scope="module")
def service(template: Path):
    """`gscan serve` on a free port; stopped after the module."""
    with started_service(template) as running:
        yield running


@contextmanager
def started_service(template: Path, *options: str) -> Iterator[tuple[subprocess.Popen, GscanClient]]:
    """`gscan serve TEMPLATE --port 0 [options]` (the address read from its ready line), stopped at the end."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "gscan.cli", "serve", str(template), "--port", "0", *options],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    url = None
    t0 = time.monotonic()
    while time.monotonic() - t0 < 300:
        line = proc.stderr.readline()
        if not line:
            break
        m = re.search(r"at (http://127\.0\.0\.1:\d+)", line)
        if m:
            url = m.group(1)
            break
    if url is None:
        proc.kill()
        pytest.fail(f"the service did not start: {proc.stderr.read()}")
    try:
        yield proc, GscanClient(url, timeout=120)
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_twenty_frames_found_not_found_and_bad(service, meshes):
    proc, client = service
    assert client.health() == [TARGET]
    good = [(seed, True) for seed in range(8)] + [(seed, False) for seed in range(8, 12)]
    for seed, present in good:  # 12 frames the service answers with 200
        r, T_gt = render(meshes, seed, present)
        c, d = frame_bytes(r)
        res = client.estimate(c, d, K_TEXT)
        pose = res.results[TARGET]
        assert res.timings_ms["total"] > 0 and set(pose.timings_ms) >= {"features", "match", "total"}
        if present:
            assert pose.found, (seed, pose.reason)
            deg, m = pose_error(np.asarray(pose.T_cam_obj), T_gt)
            assert deg < 5.0 and m < 0.01, (seed, deg, m)
        else:
            assert not pose.found and pose.reason, seed
    r, _ = render(meshes, 0)
    c, d = frame_bytes(r)
    half = png(cv2.resize(np.clip(np.rint(r.depth * 1000), 0, 65535).astype(np.uint16), (320, 240),
                          interpolation=cv2.INTER_NEAREST))
    bad = [  # 8 bad requests: (fields, expected status, field named in the detail)
        ({"color": c[: len(c) // 3], "depth": d}, 400, "color"),  # corrupt (truncated) PNG
        ({"color": c, "depth": half}, 400, "depth"),  # depth of another size than the colour image
        ({"color": c, "depth": d, "intrinsics": None}, 422, "intrinsics"),  # a missing field
        ({"color": c, "depth": png(cv2.cvtColor(r.color, cv2.COLOR_RGB2GRAY))}, 400, "depth"),  # 8-bit depth
        ({"color": huge_png_header(60000, 60000), "depth": d}, 413, "color"),  # decoding would take 10 GB
        ({"color": c, "depth": d, "intrinsics": "1 2 3"}, 400, "intrinsics"),
        ({"color": c, "depth": d, "depth_scale": "1000"}, 400, "depth_scale"),  # puts the scene at kilometres
        ({"color": c, "depth": d, "templates": "nonexistent"}, 404, "templates"),
    ]
    for fields, status, field in bad:
        parts = {"intrinsics": K_TEXT, **fields}
        body = [(k, "f.png" if k in ("color", "depth") else None, v if isinstance(v, bytes) else v.encode())
                for k, v in parts.items() if v is not None]
        with pytest.raises(ServiceError) as e:
            client._request("POST", "/estimate", body)
        assert e.value.status == status, (field, e.value)
        assert e.value.detail.startswith(field + ":") and "\n" not in e.value.detail, e.value.detail
    assert proc.poll() is None  # still running ...
    assert client.health() == [TARGET]  # ... and answering
    again = client.estimate(c, d, K_TEXT).results[TARGET]
    assert again.found


def test_every_instance_through_the_service(service, meshes):
    """all=true: every copy of the object in a pile, each within 5 deg / 1 cm, best score first; `results` holds
    the first (a one-instance caller reads it as before)."""
    from gscan.synth.piles import render_pile

    _, client = service
    pile = render_pile([meshes[0], meshes[0], meshes[1]], 3)
    c, d = frame_bytes(pile.frame)
    res = client.estimate(c, d, K_TEXT, all_instances=True)
    poses = res.instances[TARGET]
    assert len(poses) == 2 and res.results[TARGET] == poses[0]
    hit = sorted(int(np.argmin([pose_error(np.asarray(p.T_cam_obj), T)[1] for T in pile.T_cam_objs[:2]]))
                 for p in poses)
    assert hit == [0, 1]
    for p, T in zip(poses, pile.T_cam_objs[hit], strict=True):
        deg, m = pose_error(np.asarray(p.T_cam_obj), T)
        assert deg < 5.0 and m < 0.01
    assert poses[0].score >= poses[1].score


def test_tracking_session_through_the_service(service, meshes):
    _, client = service
    rng_seed = 3
    r, T_gt = render(meshes, rng_seed)
    c, d = frame_bytes(r)
    steps = [client.track("cam-1", c, d, K_TEXT) for _ in range(3)]
    assert [s.status for s in steps] == ["found", "tracked", "tracked"]
    assert [s.frame for s in steps] == [0, 1, 2] and all(s.template == TARGET for s in steps)
    for s in steps:
        deg, m = pose_error(np.asarray(s.result.T_cam_obj), T_gt)
        assert deg < 5.0 and m < 0.01
    assert steps[1].result.method == "track"
    r0, _ = render(meshes, 9, with_target=False)
    lost = client.track("cam-1", *frame_bytes(r0), K_TEXT)
    assert lost.status == "lost" and not lost.result.found
    assert client.track("cam-1", c, d, K_TEXT).status == "refound"
    assert client.end_track("cam-1") == 5
    with pytest.raises(ServiceError) as e:
        client.end_track("cam-1")
    assert e.value.status == 404
    with pytest.raises(ServiceError) as e:
        client.track("bad id!", c, d, K_TEXT)
    assert e.value.status in (400, 404)


def test_openapi_page_and_unreachable_service(service):
    _, client = service
    import urllib.request

    with urllib.request.urlopen(client.url + "/openapi.json", timeout=30) as resp:
        spec = json.loads(resp.read())
    assert {"/health", "/estimate", "/track/{session}"} <= set(spec["paths"])
    with urllib.request.urlopen(client.url + "/docs", timeout=30) as resp:
        assert resp.status == 200 and b"swagger" in resp.read().lower()
    with pytest.raises(ServiceError) as e:
        GscanClient("http://127.0.0.1:9", timeout=5).health()
    assert e.value.status == 0 and "cannot reach" in e.value.detail


def test_decode_frame_checks_before_decoding(meshes):
    r, _ = render(meshes, 0)
    c, d = frame_bytes(r)
    f = decode_frame(c, d, K_TEXT, 0.001)
    assert f.color.shape == (480, 640, 3) and f.depth.dtype == np.float32
    np.testing.assert_allclose(f.depth[r.depth > 0], r.depth[r.depth > 0], atol=6e-4)
    with pytest.raises(RequestError, match="^color: .*larger") as e:
        decode_frame(huge_png_header(20000, 20000), d, K_TEXT, 0.001)
    assert e.value.status == 413
    with pytest.raises(RequestError, match="^mask: mask is 10x10"):
        decode_frame(c, d, K_TEXT, 0.001, mask=png(np.zeros((10, 10), np.uint8)))
    with pytest.raises(RequestError, match="^depth: all zero"):
        decode_frame(c, png(np.zeros((480, 640), np.uint16)), K_TEXT, 0.001)


def test_serve_from_python(template: Path):
    """gscan.serve (the public API's function) starts the service from Python."""
    code = ("import sys, gscan; gscan.serve([sys.argv[1]], port=0, on_ready=lambda url: print(url, flush=True))")
    proc = subprocess.Popen([sys.executable, "-c", code, str(template)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("http://127.0.0.1:"), proc.stderr.read() if proc.poll() is not None else url
        assert GscanClient(url, timeout=60).health() == [TARGET]
    finally:
        proc.terminate()
        proc.wait(30)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_body_limit_and_framework_errors(template: Path):
    """A body over the limit gets 413 whether its size is announced (Content-Length) or not (chunked); the
    framework's own errors (an unparsable body, an unknown path) get one line naming the request."""
    from fastapi.testclient import TestClient

    from gscan.service import ServeParams, create_app, load_service

    client = TestClient(create_app(load_service([template], ServeParams(max_request_bytes=10_000))))
    form = {"content-type": "multipart/form-data; boundary=b"}
    r = client.post("/estimate", content=b"x" * 20_000, headers=form)
    assert r.status_code == 413 and r.json()["detail"].startswith("request: ")
    r = client.post("/estimate", content=(b"x" * 1000 for _ in range(50)), headers=form)  # chunked
    assert r.status_code == 413 and r.json()["detail"].startswith("request: ")
    r = client.post("/estimate", content=b"x" * 100, headers=form)
    assert r.status_code == 400 and r.json()["detail"].startswith("request: ")
    r = client.get("/nowhere")
    assert r.status_code == 404 and r.json()["detail"] == "request: Not Found"
    assert client.get("/health").json() == {"templates": [TARGET]}


def _post_estimate(client: GscanClient, color: bytes, depth: bytes, **fields: object) -> dict:
    """POST /estimate with the depth camera fields as given (text as it is, a matrix as rows of numbers), which
    the client, sending a DepthCamera's values, cannot get wrong."""
    extra = [(k, None, (v if isinstance(v, str) else "\n".join(" ".join(repr(float(x)) for x in row)
                                                               for row in np.asarray(v))).encode())
             for k, v in fields.items()]
    return client._request("POST", "/estimate", client._frame_fields(color, depth, K_TEXT, 0.001, None) + extra)


def test_depth_from_a_separate_camera(template: Path, meshes, tmp_path: Path):
    """Depth from a camera 5 cm beside the colour camera, with its own size and calibration: the request's
    depth_intrinsics / depth_to_color fields, or the service's own (--depth-intrinsics / --depth-to-color),
    give the pose `gscan estimate --depth-intrinsics --depth-to-color` gives on the same files (the depth
    aligned to colour the same way), within 5 deg / 1 cm of the truth; bad values get 4xx naming the field."""
    T_cd = T_depth_offset()
    scene, T_wc, T_gt = scene_of(meshes, 2)
    r = scene.render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng(2))
    rd = scene.render(T_wc @ T_cd, K_DEPTH, rng=np.random.default_rng([2, 1]))
    c, d = frame_bytes(r)[0], png(np.clip(np.rint(rd.depth * 1000.0), 0, 65535).astype(np.uint16))
    files = {"color.png": c, "depth.png": d, "cam_K.txt": K_TEXT.encode()}
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    np.savetxt(tmp_path / "depth_K.txt", K_DEPTH.K)
    np.savetxt(tmp_path / "T_color_depth.txt", T_cd)
    cli = subprocess.run([sys.executable, "-m", "gscan.cli", "estimate", str(template), "--color",
                          str(tmp_path / "color.png"), "--depth", str(tmp_path / "depth.png"), "--intrinsics",
                          str(tmp_path / "cam_K.txt"), "--depth-intrinsics", str(tmp_path / "depth_K.txt"),
                          "--depth-to-color", str(tmp_path / "T_color_depth.txt"), "--json"],
                         capture_output=True, text=True, timeout=300, check=False)
    assert cli.returncode == 0, cli.stderr
    T_cli = np.asarray(json.loads(cli.stdout)["T_cam_obj"])
    assert T_cli.shape == (4, 4), json.loads(cli.stdout)["reason"]
    deg, m = pose_error(T_cli, T_gt)
    assert deg < 5.0 and m < 0.01, (deg, m)

    with started_service(template, "--depth-intrinsics", str(tmp_path / "depth_K.txt"), "--depth-to-color",
                         str(tmp_path / "T_color_depth.txt")) as (proc, client):
        served = client.estimate(c, d, K_TEXT).results[TARGET]  # the service's depth camera
        own = client.estimate(c, d, K_TEXT, depth_camera=DepthCamera(K_DEPTH, T_cd)).results[TARGET]
        # the fields as a cam_K.txt and a pose .json hold them
        as_json = Pose.from_json(_post_estimate(client, c, d, depth_intrinsics=(tmp_path / "depth_K.txt").read_text(),
                                                depth_to_color=json.dumps({"T": T_cd.tolist()}))["results"][TARGET])
        for pose in (served, own, as_json):
            assert pose.found, pose.reason
            np.testing.assert_allclose(np.asarray(pose.T_cam_obj), T_cli, atol=1e-9)
        step = client.track("offset", c, d, K_TEXT, depth_camera=DepthCamera(K_DEPTH.K, T_cd))
        assert step.status == "found"
        np.testing.assert_allclose(np.asarray(step.result.T_cam_obj), T_cli, atol=1e-9)
        # the colour camera's own depth, named as a depth camera equal to the colour camera: found, at the truth
        reg = client.estimate(c, frame_bytes(r)[1], K_TEXT,
                              depth_camera=DepthCamera(DEFAULT_INTRINSICS)).results[TARGET]
        assert reg.found and pose_error(np.asarray(reg.T_cam_obj), T_gt)[0] < 5.0
        shifted = T_cd.copy()
        shifted[0, 3] = 5.0  # metres: every depth pixel lands beside the colour image
        skewed = T_cd.copy()
        skewed[:3, :3] *= 1.2  # not a rotation
        tiny = png(np.full((24, 32), 800, np.uint16))
        bad = [  # (request's depth camera fields, depth image, status, field named)
            ({"depth_to_color": T_cd}, d, 422, "depth_to_color"),  # without depth_intrinsics
            ({"depth_intrinsics": "1 2 3"}, d, 400, "depth_intrinsics"),
            ({"depth_intrinsics": K_DEPTH.K, "depth_to_color": "1 0 0"}, d, 400, "depth_to_color"),
            ({"depth_intrinsics": K_DEPTH.K, "depth_to_color": skewed}, d, 400, "depth_to_color"),
            ({"depth_intrinsics": K_DEPTH.K, "depth_to_color": shifted}, d, 400, "depth_to_color"),
            ({"depth_intrinsics": K_DEPTH.K}, tiny, 400, "depth_intrinsics"),  # principal point far outside 32x24
            ({}, tiny, 400, "depth"),  # the service's depth camera cannot be of a 32x24 image either
        ]
        for fields, depth_png, status, field in bad:
            with pytest.raises(ServiceError) as e:
                _post_estimate(client, c, depth_png, **fields)
            assert e.value.status == status, (field, e.value)
            assert e.value.detail.startswith(field + ":") and "\n" not in e.value.detail, e.value.detail
        assert proc.poll() is None and client.estimate(c, d, K_TEXT).results[TARGET].found


def test_depth_camera_fields_and_poses(tmp_path: Path):
    """A request's depth camera fields: a pose as 16 or 12 numbers or JSON, rigid and within range, and
    depth_to_color only with depth_intrinsics; the service's own depth camera from its files (an Open3D JSON
    keeps its size, a cam_K.txt fits any)."""
    T = T_depth_offset()
    rows = "\n".join(" ".join(repr(float(x)) for x in row) for row in T)
    for text in (rows, "\n".join(rows.splitlines()[:3]), json.dumps({"T": T.tolist()}), json.dumps(T.tolist())):
        np.testing.assert_allclose(parse_pose(text, "depth_to_color"), T, atol=1e-12)
    for text, why in (("1 2 3", "16 numbers"), ('{"R": 1}', "16 numbers"), ("nan " * 16, "finite"),
                      (" ".join(["2"] * 16), "not a rigid"), ("1 0 0 5e6 0 1 0 0 0 0 1 0 0 0 0 1", "beyond")):
        with pytest.raises(RequestError, match=f"^depth_to_color: .*{why}"):
            parse_pose(text, "depth_to_color")
    assert depth_camera_fields(None, None) is None and depth_camera_fields(" ", "") is None
    cam = depth_camera_fields(K_TEXT, None)
    assert cam is not None and np.array_equal(cam.T_color_depth, np.eye(4)) and cam.size is None
    assert depth_camera_intrinsics(cam, 640, 480) == DEFAULT_INTRINSICS
    with pytest.raises(RequestError, match="^depth_to_color: given without depth_intrinsics") as e:
        depth_camera_fields(None, rows)
    assert e.value.status == 422
    o3d = {"width": 480, "height": 360, "intrinsic_matrix": K_DEPTH.K.T.flatten().tolist()}
    (tmp_path / "depth_K.json").write_text(json.dumps(o3d))
    (tmp_path / "T.json").write_text(json.dumps({"T": T.tolist()}))
    served = load_depth_camera(tmp_path / "depth_K.json", tmp_path / "T.json")
    assert served.size == (480, 360) and depth_camera_intrinsics(served, 480, 360, served=True) == K_DEPTH
    np.testing.assert_allclose(served.T_color_depth, T, atol=1e-12)
    with pytest.raises(RequestError, match="^depth: depth is 640x480 but the service's depth camera is calibrated "
                                           "for 480x360"):
        depth_camera_intrinsics(served, 640, 480, served=True)
    (tmp_path / "depth_K.txt").write_text("615 0 319.5\n0 615 239.5\n")
    with pytest.raises(InputError, match="depth_K.txt: malformed cam_K.txt: expected a 3x3 matrix"):
        load_depth_camera(tmp_path / "depth_K.txt")
