"""The interactive DFD page (jaxdeform.handles.server): JSON endpoints over urllib, and the page in headless Chromium.

The server runs in-process (a thread) on a free port with a real mesh (spot; a synthetic ellipsoid when the data is
absent) and a cheap synthetic feature array Z (a unit-normalised smooth function of the positions). Every deformed
mesh the server reports is compared with ``weights.Deformer.deform`` recomputed here from the reported handles,
transforms and options; picks with ``cast_rays`` of the reported camera; images with ``render``. Browser tests drive
Debian's Chromium through playwright and skip when either is missing.
"""

from __future__ import annotations

import io
import json
import math
import os
import socket
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from conftest import DATA
from PIL import Image

from jaxdeform.handles.server import WEIGHT_COLORMAP, WEIGHT_RANGE, decode_vertices, loopback_host, serve
from jaxdeform.handles.weights import Deformer
from jaxdeform.mesh.render import Camera, cast_rays, render

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]


# ---------------------------------------------------------------------------------------------- fixtures


def ellipsoid(n_lat: int = 16, n_lon: int = 24, radii=(1.0, 0.7, 0.5)):
    """A closed UV ellipsoid centred at 0, mirror symmetric about x = 0 (n_lon even)."""
    th = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    ph = 2.0 * np.pi * np.arange(n_lon) / n_lon
    t, p = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    v = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]]) * np.asarray(radii)
    idx = 1 + np.arange((n_lat - 1) * n_lon).reshape(n_lat - 1, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    top = np.stack([np.zeros(n_lon, int), nxt[0], idx[0]], 1)
    a, b, c, d = idx[:-1], nxt[:-1], nxt[1:], idx[1:]
    mid = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    last = v.shape[0] - 1
    bottom = np.stack([np.full(n_lon, last), idx[-1], nxt[-1]], 1)
    return v, np.concatenate([top, mid, bottom]).astype(np.int64)


def smooth_features(points: np.ndarray) -> np.ndarray:
    """A cheap stand-in for distilled features: unit rows of a smooth function of the positions."""
    u = np.asarray(points, dtype=np.float64)
    z = np.stack([np.sin(2.0 * u[:, 0]), np.cos(3.0 * u[:, 1]), u[:, 2], u[:, 0] * u[:, 1], np.ones(len(u))], 1)
    return (z / np.linalg.norm(z, axis=1, keepdims=True)).astype(np.float32)


def mirror_features(points: np.ndarray) -> np.ndarray:
    """Unit features invariant under x -> -x only (a field with one symmetry plane)."""
    u = np.asarray(points, dtype=np.float64)
    z = np.stack([2.0 * u[:, 0] ** 2, u[:, 1], u[:, 2], 0.5 * np.ones(len(u))], 1)
    return (z / np.linalg.norm(z, axis=1, keepdims=True)).astype(np.float32)


@pytest.fixture(scope="module")
def mesh():
    path = DATA / "test-meshes" / "spot.obj"
    if path.is_file():
        from jaxdeform.mesh.io import load_mesh

        v, f = load_mesh(path)
    else:  # the real data is absent: the same checks on a synthetic closed mesh
        v, f = ellipsoid(24, 36)
    v = np.asarray(v, dtype=np.float64)
    return v, np.asarray(f, dtype=np.int64), smooth_features(v)


@pytest.fixture(scope="module")
def server(mesh):
    v, f, z = mesh
    srv = serve(v, f, z, block=False)
    yield srv
    srv.shutdown()


@pytest.fixture(scope="module")
def deformer(mesh):
    v, f, z = mesh
    return Deformer(v, f, z)


@pytest.fixture()
def fresh(server):
    """The module's server with all handles, anchors, options and the view reset."""
    post(server, "/api/reset", {"what": "all"})
    post(server, "/api/reset", {"what": "view"})
    return server


# ---------------------------------------------------------------------------------------------- helpers


def request(srv, path, body=None, *, raw: bytes | None = None, headers=None):
    """(status, parsed JSON or bytes) of a GET (body None) or a POST."""
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    req = urllib.request.Request(srv.url.rstrip("/") + path, data=data, headers=dict(headers or {}))
    if data is not None:
        req.add_header("Content-Type", "application/json")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            status, payload, ctype = r.status, r.read(), r.headers.get("Content-Type", "")
    except urllib.error.HTTPError as e:
        status, payload, ctype = e.code, e.read(), e.headers.get("Content-Type", "")
    return status, (json.loads(payload) if ctype.startswith("application/json") else payload)


def get(srv, path):
    status, out = request(srv, path)
    assert status == 200, out
    return out


def post(srv, path, body):
    status, out = request(srv, path, body)
    assert status == 200, out
    return out


def camera_of(state) -> Camera:
    c = state["camera"]
    return Camera(eye=c["eye"], target=c["target"], up=c["up"], fov_deg=c["fov_deg"])


def project(cam: Camera, w: int, h: int, p) -> np.ndarray:
    """Display coordinates of a point: where the renderer's pixel-centre rays (Camera docstring) would see it."""
    fwd, right, up = cam.basis()
    q = np.asarray(p, dtype=np.float64) - np.asarray(cam.eye)
    s = math.tan(math.radians(cam.fov_deg) / 2.0) / (min(w, h) / 2.0)
    return np.array([w / 2.0 + (q @ right) / (q @ fwd) / s, h / 2.0 - (q @ up) / (q @ fwd) / s])


def served_vertices(srv) -> tuple[dict, np.ndarray]:
    st = get(srv, "/api/state?vertices=1")
    return st, decode_vertices(st["vertices"]).astype(np.float64)


def expected(deformer: Deformer, state) -> np.ndarray:
    a = state["deform_args"]
    anchors = np.asarray(a["anchors"], dtype=np.int64) if a["anchors"] else ()
    out = deformer.deform(
        np.asarray(a["handles"], dtype=np.int64),
        np.asarray(a["transforms"]),
        anchors=anchors,
        locality=a["locality"],
        symmetric=a["symmetric"],
        pou=a["pou"],
    )
    return np.asarray(out, dtype=np.float64)


def image_of(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def check_one_sentence(message):
    assert isinstance(message, str) and 10 < len(message) < 200, message
    assert message.endswith(".") and "\n" not in message and "Traceback" not in message, message


# ------------------------------------------------------------------------------------------- endpoints


def test_pick_is_the_ray_cast_of_the_displayed_image(fresh, mesh):
    v, f, _ = mesh
    info = get(fresh, "/api/mesh-info")
    assert (info["n_vertices"], info["n_faces"]) == (v.shape[0], f.shape[0])
    w, h = info["width"], info["height"]
    st = get(fresh, "/api/state")
    hits = cast_rays(v, f, camera_of(st), w, h)  # nothing deformed yet: the rest mesh is displayed
    x, y = info["covered_pixel"]
    i, j = int(y), int(x)
    assert hits.hit[max(i - 3, 0) : i + 4, max(j - 3, 0) : j + 4].all()  # an interior covered pixel, as promised
    r = post(fresh, "/api/pick", {"x": x, "y": y, "action": "query"})
    assert r["hit"] and r["triangle"] == hits.triangle[i, j]
    corners = f[r["triangle"]]
    assert r["vertex"] == corners[np.argmin(np.linalg.norm(v[corners] - hits.points[i, j], axis=1))]
    np.testing.assert_allclose(r["point"], hits.points[i, j], atol=1e-9)
    assert r["handle"] is None and r["state"]["handles"] == []  # a query changes nothing
    bi, bj = np.argwhere(~hits.hit)[0]
    r = post(fresh, "/api/pick", {"x": bj + 0.5, "y": bi + 0.5, "action": "handle"})
    assert not r["hit"] and r["vertex"] is None and r["handle"] is None and r["state"]["handles"] == []
    # a handle click adds the picked vertex; a second click on its marker selects it instead of adding another
    r = post(fresh, "/api/pick", {"x": x, "y": y, "action": "handle"})
    assert r["handle"] == 0 and r["state"]["handles"] == [r["vertex"]] and r["state"]["selected"] == 0
    m = r["state"]["markers"][0]
    np.testing.assert_allclose([m["x"], m["y"]], project(camera_of(st), w, h, v[r["vertex"]]), atol=1e-9)
    r = post(fresh, "/api/pick", {"x": m["x"] + 3, "y": m["y"] - 2, "action": "handle"})
    assert r["handle"] == 0 and len(r["state"]["handles"]) == 1


def test_translate_drag_follows_the_cursor_and_matches_the_deformer(fresh, mesh, deformer):
    v, f, _ = mesh
    info = get(fresh, "/api/mesh-info")
    w, h = info["width"], info["height"]
    x, y = info["covered_pixel"]
    hv = post(fresh, "/api/pick", {"x": x, "y": y, "action": "handle"})["vertex"]
    cam = camera_of(get(fresh, "/api/state"))
    steps = [(x, y), (x + 7, y - 2), (x + 19.5, y - 11), (x + 33, y - 25)]
    for a, b in zip(steps[:-1], steps[1:]):
        post(fresh, "/api/drag", {"mode": "translate", "from": list(a), "to": list(b)})
    st, got = served_vertices(fresh)
    assert st["handles"] == [hv] and len(st["transforms"]) == 1
    t = np.asarray(st["transforms"][0])
    np.testing.assert_allclose(t[:, :3], np.eye(3), atol=1e-12)  # a pure translation ...
    np.testing.assert_allclose(t[:, 3] @ cam.basis()[0], 0.0, atol=1e-9)  # ... in the view plane
    np.testing.assert_allclose(got, expected(deformer, st), atol=1e-5)
    np.testing.assert_allclose(got[hv], v[hv] + t[:, 3], atol=1e-5)  # the handle moved by the translation
    moved = project(cam, w, h, got[hv]) - project(cam, w, h, v[hv])
    np.testing.assert_allclose(moved, np.subtract(steps[-1], steps[0]), atol=1e-3)  # exactly with the cursor
    assert np.linalg.norm(got - v, axis=1).max() > 0.1 * np.linalg.norm(t[:, 3])


def test_rotate_anchor_locality_pou_options_match_the_deformer(fresh, mesh, deformer):
    v, f, _ = mesh
    info = get(fresh, "/api/mesh-info")
    x, y = info["covered_pixel"]
    hv = post(fresh, "/api/pick", {"x": x, "y": y, "action": "handle"})["vertex"]
    st = get(fresh, "/api/state")
    m = st["markers"][0]
    post(fresh, "/api/drag", {"mode": "rotate", "from": [m["x"] + 40, m["y"]], "to": [m["x"], m["y"] - 40]})
    st, got = served_vertices(fresh)
    fwd, right, up = camera_of(st).basis()
    r = np.asarray(st["transforms"][0])[:, :3]
    np.testing.assert_allclose(r @ right, up, atol=1e-9)  # 90 degrees counter-clockwise on screen
    np.testing.assert_allclose(r @ fwd, fwd, atol=1e-9)  # about the view axis ...
    np.testing.assert_allclose(got[hv], v[hv], atol=1e-5)  # ... through the handle
    np.testing.assert_allclose(got, expected(deformer, st), atol=1e-5)
    # anchors, a second handle, locality and partition of unity: the served mesh is always Deformer.deform's
    dist = np.linalg.norm(v - v[hv], axis=1)
    far = int(np.argmax(dist))
    z = mesh[2]
    # a second handle away from the first but with similar features, so that their weights overlap (sum above 1)
    second = int(np.argmin(np.where(dist > 0.3 * dist.max(), np.linalg.norm(z - z[hv], axis=1), np.inf)))
    assert deformer.weights([hv, second], anchors=[far]).sum(axis=1).max() > 1.05
    post(fresh, "/api/anchor", {"action": "toggle", "vertex": far})
    post(fresh, "/api/handle", {"action": "add", "vertex": second})
    post(
        fresh,
        "/api/handle",
        {"action": "transform", "handle": 1, "transform": [[1, 0, 0, 0.1], [0, 1, 0, 0.2], [0, 0, 1, -0.1]]},
    )
    previous = None
    # (partition of unity only changes vertices whose weights sum above 1, so it is switched on without locality)
    for options in ({}, {"pou": True}, {"locality": True, "lambda": 3.0}, {"locality": False, "pou": False}):
        if options:
            post(fresh, "/api/options", options)
        st, got = served_vertices(fresh)
        assert st["deform_args"]["anchors"] == [far] and len(st["deform_args"]["handles"]) == 2
        np.testing.assert_allclose(got, expected(deformer, st), atol=1e-5)
        if previous is not None:
            assert np.abs(got - previous).max() > 1e-4  # each option changes the deformation
        previous = got
    assert st["options"] == {"locality": False, "lambda": 3.0, "symmetric": False, "pou": False, "show_weights": True}


def test_image_is_the_render_of_the_reported_state(fresh, mesh, deformer):
    v, f, _ = mesh
    info = get(fresh, "/api/mesh-info")
    w, h = info["width"], info["height"]
    x, y = info["covered_pixel"]
    post(fresh, "/api/pick", {"x": x, "y": y, "action": "handle"})
    post(fresh, "/api/drag", {"mode": "translate", "from": [x, y], "to": [x + 20, y + 10]})
    post(fresh, "/api/drag", {"mode": "orbit", "from": [10, 10], "to": [40, 20]})
    st, got = served_vertices(fresh)
    assert (st["camera"]["azimuth"], st["camera"]["elevation"]) != (30.0, 20.0)
    weight = np.asarray(deformer.weights(np.asarray(st["handles"])))[:, 0]
    for scale in (1, 2):
        img = image_of(get(fresh, f"/api/image.png?scale={scale}"))
        ref = render(
            got,
            f,
            camera=camera_of(st),
            width=w // scale,
            height=h // scale,
            scalar=weight,
            cmap=WEIGHT_COLORMAP,
            vmin=WEIGHT_RANGE[0],
            vmax=WEIGHT_RANGE[1],
            colorbar=False,
        )
        np.testing.assert_array_equal(img, ref)
        jpeg = image_of(get(fresh, f"/api/image.jpg?scale={scale}"))  # the drag frames: lossy, same picture
        assert jpeg.shape == ref.shape and np.abs(jpeg.astype(float) - ref).mean() < 3.0
    post(fresh, "/api/options", {"show_weights": False})
    ref = render(got, f, camera=camera_of(st), width=w, height=h, colorbar=False)
    np.testing.assert_array_equal(image_of(get(fresh, "/api/image.png")), ref)


@pytest.mark.parametrize(
    "path, body",
    [
        ("/api/pick", b"{not json"),
        ("/api/pick", [1, 2]),
        ("/api/pick", {"y": 3}),
        ("/api/pick", {"x": -1, "y": 3}),
        ("/api/pick", {"x": 3, "y": 3, "action": "explode"}),
        ("/api/pick", {"x": True, "y": 3}),
        ("/api/drag", {"mode": "translate", "from": [0, 0], "to": [1, 1]}),  # nothing selected
        ("/api/drag", {"mode": "translate", "from": [0, 0]}),
        ("/api/drag", {"mode": "fly", "from": [0, 0], "to": [1, 1]}),
        ("/api/options", {"speed": 3}),
        ("/api/options", {"lambda": -1}),
        ("/api/options", {"locality": "yes"}),
        ("/api/options", {"symmetric": True}),  # no field was given
        ("/api/handle", {"action": "select", "handle": 5}),
        ("/api/handle", {"action": "add", "vertex": 10**9}),
        ("/api/anchor", {"action": "toggle", "vertex": -1}),
        ("/api/reset", {"what": "everything"}),
        ("/api/view", {"zoom": 0}),
    ],
)
def test_bad_requests_answer_400_with_one_sentence(fresh, path, body):
    raw = body if isinstance(body, bytes) else json.dumps(body).encode()
    status, out = request(fresh, path, raw=raw)
    assert status == 400, out
    check_one_sentence(out["error"])
    assert get(fresh, "/api/state")["handles"] == []  # nothing changed


def test_other_refusals_and_static_files(fresh, mesh):
    v, _, _ = mesh
    status, out = request(fresh, "/api/image.png?scale=3")
    assert status == 400
    check_one_sentence(out["error"])
    post(fresh, "/api/handle", {"action": "add", "vertex": 5})
    status, out = request(fresh, "/api/handle", {"action": "transform", "handle": 0, "transform": [[1, 0, 0]]})
    assert status == 400 and "transform" in out["error"]
    status, out = request(fresh, "/api/anchor", {"action": "toggle", "vertex": 5})  # a handle cannot be an anchor
    assert status == 400
    check_one_sentence(out["error"])
    for path in ("/api/nothing", "/static/../server.py", "/static/missing.js", "/etc/passwd"):
        status, out = request(fresh, path)
        assert status == 404
        check_one_sentence(out["error"])
    status, _ = request(fresh, "/api/nothing", {})
    assert status == 404
    status, out = request(fresh, "/api/state", headers={"Host": "attacker.example:80"})  # DNS rebinding
    assert status == 403
    status, out = request(fresh, "/api/reset", {"what": "all"}, headers={"Origin": "http://attacker.example"})
    assert status == 403 and get(fresh, "/api/state")["handles"] == [5]
    page = get(fresh, "/").decode()
    for name in ("app.js", "style.css"):
        assert f"/static/{name}" in page
        assert len(get(fresh, f"/static/{name}")) > 100
    assert "http://" not in page and "https://" not in page  # everything is served locally


def test_absurd_transforms_other_methods_and_disconnects(fresh, mesh, capfd):
    """Drags or transforms that are not finite or move a handle beyond 1,000 mesh sizes answer a JSON 400 and
    change nothing; the state never carries NaN; PUT / DELETE answer a JSON 405; a client that goes away mid-
    answer prints nothing."""
    post(fresh, "/api/handle", {"action": "add", "vertex": 5})
    before = get(fresh, "/api/state")
    for body in (
        {"mode": "translate", "from": [0, 0], "to": [1e300, 1e300]},
        {"mode": "translate", "from": [0, 0], "to": [1e308, -1e308]},
        {"mode": "rotate", "from": [1e300, 0], "to": [0, 1e300]},
    ):
        status, out = request(fresh, "/api/drag", body)
        if status == 200:  # a rotation by a finite angle is a valid edit: the mesh stays finite
            assert np.isfinite(served_vertices(fresh)[1]).all()
            post(fresh, "/api/reset", {"what": "transforms"})
            continue
        assert status == 400, out
        check_one_sentence(out["error"])
    huge = [[1e300, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
    far = [[1, 0, 0, 1e9], [0, 1, 0, 0], [0, 0, 1, 0]]
    for t in (huge, far):
        status, out = request(fresh, "/api/handle", {"action": "transform", "handle": 0, "transform": t})
        assert status == 400 and "not applied" in out["error"], out
    status, raw = request(fresh, "/api/state?vertices=1", headers={"Accept": "application/json"})
    assert status == 200 and raw["transforms"] == before["transforms"]
    assert np.isfinite(decode_vertices(raw["vertices"])).all()
    for method in ("PUT", "DELETE"):
        req = urllib.request.Request(fresh.url + "api/state", data=b"{}", method=method)
        try:
            urllib.request.urlopen(req, timeout=30)
            raise AssertionError(f"{method} was answered")
        except urllib.error.HTTPError as e:
            assert e.code == 405 and e.headers.get("Content-Type", "").startswith("application/json")
            check_one_sentence(json.loads(e.read())["error"])
    capfd.readouterr()
    for _ in range(5):  # ask for a large image and hang up before reading it
        with socket.create_connection((fresh.host, fresh.port)) as sock:
            sock.sendall(f"GET /api/image.png?scale=2 HTTP/1.1\r\nHost: 127.0.0.1:{fresh.port}\r\n\r\n".encode())
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    time.sleep(1.0)
    get(fresh, "/api/state")
    err = capfd.readouterr().err
    assert "Traceback" not in err and "BrokenPipe" not in err and "ConnectionReset" not in err, err


def test_binds_only_loopback(server, mesh):
    assert server.server_address[0] == "127.0.0.1" and server.url == f"http://127.0.0.1:{server.port}/"
    assert loopback_host("localhost") == "127.0.0.1"
    for host in ("0.0.0.0", "192.168.1.2", "::1", "example.com"):
        with pytest.raises(ValueError, match="loopback"):
            loopback_host(host)
    v, f, z = mesh
    with pytest.raises(ValueError, match="loopback"):
        serve(v, f, z, host="0.0.0.0", block=False)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # this machine's outward address (no packet sent)
        try:
            s.connect(("10.255.255.255", 1))
            ip = s.getsockname()[0]
        except OSError:
            ip = "127.0.0.1"
    if not ip.startswith("127."):
        with pytest.raises(OSError):
            socket.create_connection((ip, server.port), timeout=2).close()


def test_symmetric_deformation_with_a_field():
    v, f = ellipsoid()
    z = mirror_features(v)
    d = Deformer(v, f, z, field_fn=mirror_features)
    plane = d.symmetry_plane()
    if plane is None:
        pytest.skip("weights.Deformer found no symmetry plane for an x-mirror-symmetric field")
    np.testing.assert_allclose(np.abs(np.asarray(plane.normal, dtype=float)), [1.0, 0.0, 0.0], atol=1e-6)
    with serve(v, f, z, field_fn=mirror_features, block=False, width=128, height=128) as srv:
        info = get(srv, "/api/mesh-info")
        assert info["symmetry_available"] and info["field_given"]
        hv = int(np.argmax(v[:, 0]))  # the tip on the +x side
        post(srv, "/api/handle", {"action": "add", "vertex": hv})
        post(
            srv,
            "/api/handle",
            {"action": "transform", "handle": 0, "transform": [[1, 0, 0, 0.3], [0, 1, 0, 0.1], [0, 0, 1, 0.0]]},
        )
        _, plain = served_vertices(srv)
        post(srv, "/api/options", {"symmetric": True})
        st, sym = served_vertices(srv)
        assert st["symmetry_plane"] is not None and st["deform_args"]["symmetric"]
        np.testing.assert_allclose(sym, expected(d, st), atol=1e-5)
        assert np.abs(sym - plain).max() > 1e-3


# ------------------------------------------------------------------------------------------------ browser


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"Chromium is not installed at {CHROMIUM} (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("the python package playwright is not installed (pip install playwright)")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture()
def page(browser, fresh):
    pg = browser.new_page(viewport={"width": 1000, "height": 720})
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(fresh.url)
    wait_idle(pg)
    yield pg
    pg.close()
    assert not errors, errors


def wait_idle(pg):
    pg.wait_for_function("() => window.dfdIdle && window.dfdIdle()", timeout=20_000)


def origin(pg) -> tuple[float, float]:
    box = pg.locator("#overlay").bounding_box()
    return box["x"], box["y"]


def shot(pg) -> np.ndarray:
    return image_of(pg.locator("#mesh").screenshot())


def coverage(img: np.ndarray) -> np.ndarray:
    return np.any(img < 250, axis=-1)  # the background is white


def drag(pg, start, end, *, shift: bool = False, steps: int = 8):
    if shift:
        pg.keyboard.down("Shift")
    pg.mouse.move(*start)
    pg.mouse.down()
    pg.mouse.move(*end, steps=steps)
    pg.mouse.up()
    if shift:
        pg.keyboard.up("Shift")
    wait_idle(pg)


def click_handle(pg, srv) -> tuple[int, dict]:
    """Click the covered pixel the server reports; returns (handle vertex, state)."""
    x, y = get(srv, "/api/mesh-info")["covered_pixel"]
    ox, oy = origin(pg)
    pg.mouse.click(ox + x, oy + y)
    wait_idle(pg)
    st = get(srv, "/api/state")
    assert len(st["handles"]) == 1 and st["selected"] == 0
    return st["handles"][0], st


def test_browser_click_and_drag_moves_the_mesh(page, fresh, mesh, deformer):
    v, _, _ = mesh
    hv, st = click_handle(page, fresh)
    before = shot(page)
    w, h = st["width"], st["height"]
    ox, oy = origin(page)
    m = st["markers"][0]
    start = (round(ox + m["x"]), round(oy + m["y"]))
    end = (start[0] + 45, start[1] - 35)
    drag(page, start, end)
    after = shot(page)
    assert before.shape == after.shape == (h, w, 3)
    assert np.count_nonzero(coverage(before) != coverage(after)) > 100  # the silhouette moved on the page
    st, got = served_vertices(fresh)
    np.testing.assert_allclose(got, expected(deformer, st), atol=1e-5)
    t = np.asarray(st["transforms"][0])
    np.testing.assert_allclose(got[hv], v[hv] + t[:, 3], atol=1e-5)
    cam = camera_of(st)
    moved = project(cam, w, h, got[hv]) - project(cam, w, h, v[hv])
    np.testing.assert_allclose(moved, (45, -35), atol=0.05)  # the handle followed the mouse
    status = page.locator("#status").inner_text()
    assert "1 handle" in status and "error" not in page.locator("#status").get_attribute("class")


def test_browser_shift_drag_rotates_about_the_view_axis(page, fresh, mesh, deformer):
    v, _, _ = mesh
    hv, st = click_handle(page, fresh)
    before = shot(page)
    ox, oy = origin(page)
    m = st["markers"][0]
    start = (round(ox + m["x"] + 60), round(oy + m["y"]))
    end = (round(ox + m["x"]), round(oy + m["y"] - 60))
    drag(page, start, end, shift=True, steps=10)
    st, got = served_vertices(fresh)
    assert len(st["handles"]) == 1  # shift + drag off the mesh's handle rotates it, it adds nothing
    a = np.subtract(start, (ox + m["x"], oy + m["y"]))
    b = np.subtract(end, (ox + m["x"], oy + m["y"]))
    turn = math.atan2(-b[1], b[0]) - math.atan2(-a[1], a[0])  # counter-clockwise on screen
    fwd, right, up = camera_of(st).basis()
    r = np.asarray(st["transforms"][0])[:, :3]
    np.testing.assert_allclose(r @ fwd, fwd, atol=1e-6)
    np.testing.assert_allclose(r @ right, math.cos(turn) * right + math.sin(turn) * up, atol=1e-3)
    np.testing.assert_allclose(got[hv], v[hv], atol=1e-5)
    np.testing.assert_allclose(got, expected(deformer, st), atol=1e-5)
    assert np.count_nonzero(np.any(before != shot(page), axis=-1)) > 100


def test_browser_locality_toggle(page, fresh, mesh, deformer):
    _, st = click_handle(page, fresh)
    ox, oy = origin(page)
    m = st["markers"][0]
    start = (round(ox + m["x"]), round(oy + m["y"]))
    drag(page, start, (start[0] - 30, start[1] - 30))
    _, global_ = served_vertices(fresh)
    img_global = shot(page)
    page.locator("#locality").check()
    wait_idle(page)
    st, local = served_vertices(fresh)
    assert st["options"]["locality"] and st["deform_args"]["locality"] == st["options"]["lambda"] > 0
    np.testing.assert_allclose(local, expected(deformer, st), atol=1e-5)
    assert np.abs(local - global_).max() > 1e-3
    assert np.count_nonzero(np.any(img_global != shot(page), axis=-1)) > 100
    page.locator("#lambda").fill("6")
    page.locator("#lambda").press("Tab")  # commit the value (change event)
    t0 = time.monotonic()
    while get(fresh, "/api/state")["options"]["lambda"] != 6.0 and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    wait_idle(page)
    st, sharper = served_vertices(fresh)
    assert st["deform_args"]["locality"] == 6.0
    np.testing.assert_allclose(sharper, expected(deformer, st), atol=1e-5)
    assert np.abs(sharper - local).max() > 1e-4
