"""The interactive DFD page over HTTP: ``jaxdeform handles serve MESH`` (a local web server on 127.0.0.1).

This module is the transport only: it routes requests, checks their shape (body size, JSON objects, value types,
static file names, Host and Origin headers), calls an :class:`~jaxdeform.handles.session.EditSession`, which owns
the state, the deformation and the frames, and answers JSON or image bytes. The page (``static/`` beside this
module) shows the mesh as images rendered on the server, so it needs neither WebGL nor a GPU.

Endpoints (POST bodies are JSON objects; unless stated otherwise a POST answers the session's state):

- ``GET /``, ``GET /static/NAME`` (``.html``, ``.js``, ``.css`` from ``static/``), ``GET /favicon.ico`` (204);
- ``GET /api/mesh-info``; ``GET /api/state[?vertices=1[&dtype=float32|float64]]`` (deformed vertices as
  base64 little-endian floats, see :func:`encode_vertices`); ``GET /api/image.png[?scale=2]`` (or ``.jpg``;
  header ``X-Version``);
- ``POST /api/pick {x, y, action}`` (answers the pick and ``state``), ``POST /api/drag {mode, from, to[, handle]}``,
  ``POST /api/options {locality?, lambda?, symmetric?, pou?, show_weights?}``,
  ``POST /api/view {zoom?, azimuth?, elevation?, reset?}``,
  ``POST /api/handle {action: add, vertex | select | remove | reset, handle? | deselect | transform, handle?,
  transform}``, ``POST /api/anchor {action: toggle, vertex | clear}``, ``POST /api/reset {what}``.

A bad request answers 400 with ``{"error": one sentence}`` (the session's ``ValueError`` or library error, or
this module's :class:`BadRequest`); an unknown path 404; a request whose Host header does not name the loopback
address (DNS rebinding) or a cross-origin POST 403; a failure of the server itself 500. The server binds only an
IPv4 loopback address.
"""

from __future__ import annotations

import base64
import ipaddress
import json
import logging
import math
import re
import sys
import threading
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np

from jaxdeform.errors import JaxDeformError
from jaxdeform.handles.session import DRAG_MODES, PICK_ACTIONS, RESET_TARGETS, EditSession
from jaxdeform.handles.viewport import (  # noqa: F401 - re-exported: the page's constants
    JPEG_QUALITY,
    MARKER_RADIUS,
    ORBIT_DEG_PER_PIXEL,
    PREVIEW_SCALES,
    WEIGHT_COLORMAP,
    WEIGHT_RANGE,
)

log = logging.getLogger(__name__)

STATIC_DIR = Path(__file__).resolve().parent / "static"
#: Largest request body accepted (bytes).
MAX_BODY = 1 << 20
_STATIC_NAME = re.compile(r"^[A-Za-z0-9_-]+\.(html|js|css)$")
_CONTENT_TYPES = {"html": "text/html; charset=utf-8", "js": "text/javascript; charset=utf-8", "css": "text/css"}


class BadRequest(ValueError):
    """A request the page cannot serve; its message (one sentence) goes back with status 400."""


def encode_vertices(v: np.ndarray) -> dict:
    """Vertices as a JSON value with base64 little-endian bytes.

    **Arguments:**

    - ``v``: ``(V, 3)`` floats (non-floats are sent as float64).

    **Returns:**

    ``{"dtype", "shape", "data"}``.
    """
    a = np.asarray(v)
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
    return {"dtype": str(a.dtype.name), "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode("ascii")}


def decode_vertices(payload: dict) -> np.ndarray:
    """Inverse of :func:`encode_vertices`.

    **Arguments:**

    - ``payload``: ``{"dtype", "shape", "data"}``.

    **Returns:**

    A read-only array of the encoded dtype and shape.
    """
    dtype = np.dtype(payload["dtype"]).newbyteorder("<")
    return np.frombuffer(base64.b64decode(payload["data"]), dtype=dtype).reshape(payload["shape"])


# ------------------------------------------------------------------------------------ JSON value checks


def _number(body: dict, key: str) -> float:
    x = body.get(key)
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise BadRequest(f"'{key}' must be a finite number.")
    return float(x)


def _optional_number(body: dict, key: str) -> float | None:
    return _number(body, key) if key in body else None


def _point(body: dict, key: str) -> tuple[float, float]:
    p = body.get(key)
    if not isinstance(p, (list, tuple)) or len(p) != 2:
        raise BadRequest(f"'{key}' must be a pair [x, y] of display pixel coordinates.")
    return _number({"x": p[0]}, "x"), _number({"y": p[1]}, "y")


def _flag(body: dict, key: str) -> bool | None:
    if key not in body:
        return None
    x = body[key]
    if not isinstance(x, bool):
        raise BadRequest(f"'{key}' must be true or false.")
    return x


def _integer(body: dict, key: str) -> int:
    x = body.get(key)
    if isinstance(x, bool) or not isinstance(x, int):
        raise BadRequest(f"'{key}' must be an integer {key} index.")
    return x


def _handle(body: dict) -> int | None:
    """The body's ``handle`` index, or None (the session's selected handle) when absent or null."""
    return _integer(body, "handle") if body.get("handle") is not None else None


def _choice(body: dict, key: str, choices: tuple[str, ...], default: str | None = None) -> str:
    x = body.get(key, default)
    if not isinstance(x, str) or x not in choices:
        raise BadRequest(f"'{key}' must be one of {', '.join(choices)}.")
    return x


# ------------------------------------------------------------------------------------------- POST routes
# Each takes the session (its lock held by the caller) and the request's JSON object, returns the answer.


def _pick(s: EditSession, body: dict) -> dict:
    x, y = _number(body, "x"), _number(body, "y")
    return {**s.pick(x, y, _choice(body, "action", PICK_ACTIONS, "query")), "state": s.state()}


def _drag(s: EditSession, body: dict) -> dict:
    mode = _choice(body, "mode", DRAG_MODES)
    start, end = _point(body, "from"), _point(body, "to")
    s.drag(mode, start, end, handle=None if mode == "orbit" else _handle(body))
    return s.state()


_OPTIONS = {
    "locality": "locality",
    "lambda": "lam",
    "symmetric": "symmetric",
    "pou": "pou",
    "show_weights": "show_weights",
}


def _options(s: EditSession, body: dict) -> dict:
    unknown = sorted(set(body) - set(_OPTIONS))
    if unknown:
        raise BadRequest(f"unknown option '{unknown[0]}'; the options are {', '.join(sorted(_OPTIONS))}.")
    values = {
        name: (_optional_number(body, key) if key == "lambda" else _flag(body, key)) for key, name in _OPTIONS.items()
    }
    s.set_options(**values)
    return s.state()


def _view(s: EditSession, body: dict) -> dict:
    s.set_view(
        zoom=_optional_number(body, "zoom"),
        azimuth=_optional_number(body, "azimuth"),
        elevation=_optional_number(body, "elevation"),
        reset=bool(body.get("reset")),
    )
    return s.state()


def _handle_edit(s: EditSession, body: dict) -> dict:
    action = _choice(body, "action", ("add", "select", "deselect", "remove", "reset", "transform"))
    if action == "add":
        s.add_handle(_integer(body, "vertex"))
    elif action == "deselect":
        s.deselect()
    elif action == "select":
        s.select_handle(_handle(body))
    elif action == "remove":
        s.remove_handle(_handle(body))
    elif action == "reset":
        s.reset_handle(_handle(body))
    else:
        s.set_transform(_handle(body), body.get("transform"))
    return s.state()


def _anchor(s: EditSession, body: dict) -> dict:
    if _choice(body, "action", ("toggle", "clear")) == "clear":
        s.clear_anchors()
    else:
        s.toggle_anchor(_integer(body, "vertex"))
    return s.state()


def _reset(s: EditSession, body: dict) -> dict:
    s.reset(_choice(body, "what", RESET_TARGETS))
    return s.state()


POST_ROUTES: dict[str, Callable[[EditSession, dict], dict]] = {
    "/api/pick": _pick,
    "/api/drag": _drag,
    "/api/options": _options,
    "/api/view": _view,
    "/api/handle": _handle_edit,
    "/api/anchor": _anchor,
    "/api/reset": _reset,
}


# --------------------------------------------------------------------------------------------- HTTP layer


class _Handler(BaseHTTPRequestHandler):
    """One request: Host / Origin checks, routing, and the mapping of refusals to 4xx with one sentence."""

    server_version = "jaxdeform-handles"
    protocol_version = "HTTP/1.1"

    @property
    def session(self) -> EditSession:
        return self.server.session  # type: ignore[attr-defined]

    def log_message(self, fmt, *args):  # quiet: the terminal belongs to the CLI
        log.debug("%s - %s", self.address_string(), fmt % args)

    def _send(self, status: int, body: bytes, content_type: str, extra: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, obj) -> None:
        self._send(status, json.dumps(obj, allow_nan=False).encode("utf-8"), "application/json")

    def _error(self, status: int, message: str) -> None:
        self.close_connection = True  # a refused request's body may be unread: never reuse the connection
        self._json(status, {"error": message})

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").strip().lower()
        port = self.server.server_address[1]
        names = {"127.0.0.1", "localhost", self.server.server_address[0]}
        return host in names | {f"{n}:{port}" for n in names}

    def _route(self, method: str) -> None:
        if not self._host_ok():
            self._error(HTTPStatus.FORBIDDEN, "this page answers only requests addressed to 127.0.0.1 or localhost.")
            return
        url = urlsplit(self.path)
        path, query = url.path, parse_qs(url.query)
        try:
            if method == "GET":
                self._get(path, query)
            else:
                self._post(path)
        except BadRequest as exc:
            self._error(HTTPStatus.BAD_REQUEST, str(exc))
        except (ValueError, TypeError, JaxDeformError) as exc:  # e.g. from the Deformer: still the request's fault
            text = str(exc).strip()
            self._error(HTTPStatus.BAD_REQUEST, text.splitlines()[0] if text else "the request was refused.")
        except Exception as exc:  # noqa: BLE001 - answer instead of dropping the connection
            log.exception("request %s %s failed", method, path)
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"the server failed: {type(exc).__name__}: {exc}")

    def _get(self, path: str, query: dict) -> None:
        if path in ("/", "/index.html"):
            self._static("index.html")
        elif path.startswith("/static/"):
            self._static(path[len("/static/") :])
        elif path == "/favicon.ico":
            self._send(HTTPStatus.NO_CONTENT, b"", "image/x-icon")
        elif path == "/api/mesh-info":
            self._json(HTTPStatus.OK, self.session.mesh_info())
        elif path == "/api/state":
            want = query.get("vertices", ["0"])[-1] in ("1", "true", "yes")
            dtype = query.get("dtype", [None])[-1]
            if dtype not in (None, "float32", "float64"):
                raise BadRequest("'dtype' must be float32 or float64.")
            with self.session.lock:
                state = self.session.state()
                if want:
                    state["vertices"] = encode_vertices(self.session.deformed_vertices(dtype))
            self._json(HTTPStatus.OK, state)
        elif path in ("/api/image.png", "/api/image.jpg"):
            try:
                scale = int(query.get("scale", ["1"])[-1])
            except ValueError:
                raise BadRequest("'scale' must be an integer.") from None
            fmt = "png" if path.endswith(".png") else "jpeg"
            version, data = self.session.image_bytes(scale, fmt)
            self._send(HTTPStatus.OK, data, f"image/{fmt}", {"X-Version": str(version)})
        else:
            self._error(HTTPStatus.NOT_FOUND, f"there is no page or endpoint at {path}.")

    def _static(self, name: str) -> None:
        path = STATIC_DIR / name
        if not _STATIC_NAME.match(name) or not path.is_file():
            self._error(HTTPStatus.NOT_FOUND, f"there is no static file named {name!r}.")
            return
        self._send(HTTPStatus.OK, path.read_bytes(), _CONTENT_TYPES[name.rsplit(".", 1)[1]])

    def _body(self) -> dict:
        try:
            n = int(self.headers.get("Content-Length", "0"))
        except ValueError:
            raise BadRequest("the Content-Length header is not a number.") from None
        if n < 0 or n > MAX_BODY:
            raise BadRequest(f"the request body must hold at most {MAX_BODY} bytes.")
        raw = self.rfile.read(n)
        try:
            body = json.loads(raw.decode("utf-8")) if raw else None
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise BadRequest("the request body is not valid JSON.") from None
        if not isinstance(body, dict):
            raise BadRequest("the request body must be a JSON object.")
        return body

    def _post(self, path: str) -> None:
        origin = self.headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc.lower() not in {
            f"{n}:{self.server.server_address[1]}" for n in ("127.0.0.1", "localhost")
        }:
            self._error(HTTPStatus.FORBIDDEN, "cross-origin requests are refused.")
            return
        route = POST_ROUTES.get(path)
        if route is None:
            self._error(HTTPStatus.NOT_FOUND, f"there is no endpoint at {path}.")
            return
        body = self._body()
        with self.session.lock:
            answer = route(self.session, body)
        self._json(HTTPStatus.OK, answer)

    def do_GET(self):  # noqa: N802 - http.server's naming
        self._route("GET")

    def do_HEAD(self):  # noqa: N802
        self._route("GET")

    def do_POST(self):  # noqa: N802
        self._route("POST")

    def _unsupported(self) -> None:
        self._error(HTTPStatus.METHOD_NOT_ALLOWED, f"the page answers GET, HEAD and POST, not {self.command}.")

    do_PUT = do_DELETE = do_PATCH = do_OPTIONS = do_TRACE = do_CONNECT = _unsupported  # noqa: N815


class _Server(ThreadingHTTPServer):
    """The threading HTTP server of one session (requests meet under the session's lock)."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, session: EditSession):
        self.session = session
        super().__init__(address, _Handler)

    def handle_error(self, request, client_address) -> None:
        """A client that went away (closed tab, cancelled request) is logged at debug level, not printed."""
        exc = sys.exc_info()[1]
        if isinstance(exc, (ConnectionError, TimeoutError)):
            log.debug("client %s went away: %s", client_address, exc)
            return
        super().handle_error(request, client_address)


def loopback_host(host: str) -> str:
    """The IPv4 loopback address to bind for ``host``.

    **Arguments:**

    - ``host``: ``localhost`` (-> 127.0.0.1) or an IPv4 loopback address.

    **Returns:**

    The address to bind.

    **Raises:**

    ``ValueError`` for anything else.
    """
    name = "127.0.0.1" if host == "localhost" else host
    try:
        addr = ipaddress.ip_address(name)
    except ValueError:
        addr = None
    if addr is None or addr.version != 4 or not addr.is_loopback:
        raise ValueError(f"the page binds only to an IPv4 loopback address such as 127.0.0.1, got {host!r}.")
    return name


class PageServer:
    """A running page: ``url``, ``port``, ``session``; ``shutdown()`` stops it, ``wait()`` blocks until then."""

    def __init__(self, session: EditSession, host: str, port: int):
        self.session = session
        self._httpd = _Server((loopback_host(host), int(port)), session)
        self.host, self.port = self._httpd.server_address[:2]
        self.url = f"http://{self.host}:{self.port}/"
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jaxdeform-handles-page", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._httpd.serve_forever(poll_interval=0.2)
        finally:
            self._stopped.set()

    @property
    def server_address(self) -> tuple[str, int]:
        return self._httpd.server_address[:2]

    def shutdown(self) -> None:
        """Stop serving and close the socket (idempotent)."""
        if self._thread.is_alive():
            self._httpd.shutdown()
            self._thread.join()
        self._httpd.server_close()

    def wait(self) -> None:
        """Block until the server stops; Ctrl-C shuts it down."""
        try:
            while not self._stopped.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.shutdown()

    def __enter__(self) -> PageServer:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()


def serve(
    vertices,
    faces,
    Z,
    *,
    field_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    host: str = "127.0.0.1",
    port: int = 0,
    block: bool = True,
    width: int = 512,
    height: int = 512,
    up_axis: str = "y",
    announce: Callable[[str], None] | None = None,
) -> PageServer:
    """Serve the interactive page for a mesh with per-vertex features.

    **Arguments:**

    - ``vertices``, ``faces``: the mesh, ``(V, 3)`` and ``(F, 3)``.
    - ``Z``: per-vertex features ``(V, C)``, unit-norm rows.
    - ``field_fn``: points ``(P, 3)`` -> unit features ``(P, C)``; enables symmetry detection (eq. 9).
    - ``host``: the address to bind.
    - ``port``: the port; 0 takes a free port.
    - ``block``: serve until Ctrl-C (then shut down) before returning.
    - ``width``, ``height``, ``up_axis``: the displayed image and the camera's up axis (:class:`EditSession`).
    - ``announce``: ``announce(url)`` is called once the socket is bound.

    **Returns:**

    The :class:`PageServer`; without ``block`` it is returned at once, running.
    """
    session = EditSession(vertices, faces, Z, field_fn=field_fn, width=width, height=height, up_axis=up_axis)
    server = PageServer(session, host, port)
    if announce is not None:
        announce(server.url)
    if block:
        server.wait()
    return server
