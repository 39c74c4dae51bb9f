"""The sensor's HTTP API (the part ouster-sdk and ouster-cli call), on a configurable address.

Endpoints (FW 3.1 style, shared/research/ouster-wire.md §5.3):

* ``GET /api/v1/sensor/metadata`` and ``/api/v1/sensor/metadata/<section>``
* ``GET /api/v1/sensor/config[?staging=true]``; ``POST /api/v1/sensor/config?staging=..
  &reinit=..&persist=..`` merges a JSON object into the staged config (``"udp_dest": "@auto"``
  becomes the caller's address); ``reinit=true`` makes the staged config active and draws a
  new init_id, as a real sensor does, and tells the emulator through ``on_reinit``
* ``GET|PUT|DELETE /api/v1/user/data``; ``GET /api/v1/system/firmware``

``sensor_info.status`` says :attr:`SensorApi.status` where it is set: INITIALIZING while the
emulator powers on (ouster-sdk's client then asks again once a second until it reads RUNNING,
as it does at a real sensor's boot; ouster-cli's own replay server says INITIALIZING until
its UDP sockets are open, too).

A sensor whose configuration is fixed (a scored run's: ``fixed=True``) takes a change of
where its stream goes (``udp_dest``, ``udp_port_lidar``, ``udp_port_imu``: what ouster-sdk's
``SensorFrameSetSource(HOST)`` and ouster-ros set) and hands it to ``on_redirect`` without a
new init_id, so the scored stream goes on; any other change (the mode, the profile, ...) is
refused. ``udp_dest`` must be a loopback address: this emulator sends nowhere else.

Unknown paths answer 404, malformed JSON 400, bodies over 64 KiB 413; every error body has
the shape a real sensor's has, ``{"error": {"title": "400 Bad Request", "description":
"..."}}`` (FW 2.3.1's answer to a refused configuration, quoted in ouster-sdk issue #437;
FW 3.x's refusal status we could not check, we answer 400). No path ever touches the
filesystem. Binds 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import ipaddress
import json
import threading
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs, urlsplit

from emulators.faults import next_init_id
from protocols.ouster import EMULATED_PROFILES, MetadataError, SensorMetadata, firmware_of

__all__ = ["SensorApi"]

MAX_BODY = 64 * 1024
#: what a fixed (run) sensor lets a client change: where its stream goes
REDIRECT_KEYS = ("udp_dest", "udp_port_lidar", "udp_port_imu")
#: what the emulator's packets may carry (metadata read from a file may say any divisor)
EMULATED_COLUMNS_PER_PACKET = (8, 16, 32, 64, 128)
_CONFIG_KEYS = {"lidar_mode": "mode", "udp_profile_lidar": "profile",
                "udp_dest": "udp_dest", "udp_port_lidar": "udp_port_lidar",
                "udp_port_imu": "udp_port_imu", "columns_per_packet": "columns_per_packet"}


def _truthy(v: list[str] | None) -> bool:
    return bool(v) and v[0].lower() in ("true", "1", "yes")  # type: ignore[index]


class SensorApi:
    """Serves the metadata of the running emulator and takes configuration changes.

    Args:
        meta: the active metadata (its init_id must equal the packets').
        host, port: where to listen (port 0 picks a free one; ouster-sdk needs 80).
        on_reinit: called with the new active metadata after ``reinit=true``.
        fixed: the configuration of a scored run: only the stream's destination may change.
        on_redirect: (fixed only) called with the metadata of the new destination, same
            init_id.
    """

    def __init__(self, meta: SensorMetadata, host: str = "127.0.0.1", port: int = 80,
                 on_reinit: Callable[[SensorMetadata], None] | None = None, *,
                 fixed: bool = False,
                 on_redirect: Callable[[SensorMetadata], None] | None = None) -> None:
        self._lock = threading.Lock()
        self.meta = meta
        self.staged: dict[str, Any] = dict(meta.to_json()["config_params"])
        self.user_data: Any = ""
        self.on_reinit = on_reinit
        self.fixed = fixed  # a run's sensor: a reinit may change only where the stream goes
        self.on_redirect = on_redirect
        self.requests: list[str] = []
        #: what ``sensor_info.status`` says (None: the metadata's own, RUNNING): a sensor
        #: that is not sending yet says INITIALIZING, and ouster-sdk's client waits for it
        self.status: str | None = None
        api = self

        class Handler(BaseHTTPRequestHandler):
            server_version = "tcf-hil-os0"
            protocol_version = "HTTP/1.1"

            def log_message(self, format: str, *args: Any) -> None:
                return

            def _send(self, status: int, body: Any) -> None:
                data = json.dumps(body).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def _body(self) -> Any:
                try:
                    n = int(self.headers.get("Content-Length") or 0)
                except ValueError as err:
                    raise _HttpError(HTTPStatus.BAD_REQUEST,
                                     "Content-Length: expected a number") from err
                if n < 0:
                    raise _HttpError(HTTPStatus.BAD_REQUEST, f"Content-Length {n}")
                if n > MAX_BODY:
                    raise _HttpError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
                                     f"body of {n} bytes; at most {MAX_BODY}")
                raw = self.rfile.read(n) if n else b""
                if not raw.strip():
                    return None
                try:
                    return json.loads(raw)
                except ValueError as err:  # not UTF-8, not JSON, or an integer too long
                    msg = str(err).splitlines()[0][:200]
                    raise _HttpError(HTTPStatus.BAD_REQUEST, f"malformed JSON: {msg}") from err
                except RecursionError as err:
                    raise _HttpError(HTTPStatus.BAD_REQUEST,
                                     "malformed JSON: nested too deeply") from err

            def _handle(self, method: str) -> None:
                url = urlsplit(self.path)
                api.requests.append(f"{method} {self.path}")
                try:
                    status, body = api.route(method, url.path.rstrip("/"), parse_qs(url.query),
                                             self._body if method in ("POST", "PUT") else None,
                                             self.client_address[0])
                except _HttpError as err:
                    status, body = err.status, err.body()
                except Exception as err:  # a callback failed (e.g. the disk is full)
                    status, body = 500, _HttpError(500, f"{type(err).__name__}: {err}").body()
                self._send(status, body)

            def do_GET(self) -> None:
                self._handle("GET")

            def do_POST(self) -> None:
                self._handle("POST")

            def do_PUT(self) -> None:
                self._handle("PUT")

            def do_DELETE(self) -> None:
                self._handle("DELETE")

        self.server = ThreadingHTTPServer((host, port), Handler)
        self.server.daemon_threads = True
        self.address = self.server.server_address
        self._thread = threading.Thread(target=self.server.serve_forever, name="sensor-http",
                                        daemon=True)

    def start(self) -> SensorApi:
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread.is_alive():  # shutdown() waits for a serve loop that must be running
            self.server.shutdown()
        self.server.server_close()

    def __enter__(self) -> SensorApi:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def set_metadata(self, meta: SensorMetadata) -> None:
        """The sensor re-initialised on its own (an injected fault): serve ``meta`` now."""
        self.update(lambda _m: meta)

    def update(self, change: Callable[[SensorMetadata], SensorMetadata]) -> SensorMetadata:
        """Serve ``change(active metadata)`` from now on, applied under the API's lock (so a
        client's redirect on the HTTP thread is not lost); returns it."""
        with self._lock:
            self.meta = change(self.meta)
            self.staged = dict(self.meta.to_json()["config_params"])
            return self.meta

    # The routing is plain data in, data out (tested without sockets too).
    def route(self, method: str, path: str, query: dict[str, list[str]],
              body: Callable[[], Any] | None, client_ip: str) -> tuple[int, Any]:
        with self._lock:
            doc = self.meta.to_json()
            if self.status is not None:
                doc["sensor_info"] = {**doc["sensor_info"], "status": self.status}
            if method == "GET" and path == "/api/v1/sensor/metadata":
                return 200, doc
            if method == "GET" and path.startswith("/api/v1/sensor/metadata/"):
                section = path.rsplit("/", 1)[1]
                if section in doc:
                    return 200, doc[section]
                raise _HttpError(HTTPStatus.NOT_FOUND, f"no metadata section {section!r}")
            if path == "/api/v1/sensor/config":
                if method == "GET":
                    return 200, (self.staged if _truthy(query.get("staging"))
                                 else doc["config_params"])
                if method == "POST":
                    return self._post_config(query, body() if body else None, client_ip)
            if path == "/api/v1/user/data":
                if method == "GET":
                    return 200, self.user_data
                if method == "PUT":
                    self.user_data = body() if body else ""
                    return 200, ""
                if method == "DELETE":
                    self.user_data = ""
                    return 200, ""
            if method == "GET" and path == "/api/v1/system/firmware":
                return 200, {"fw": self.meta.image_rev}
        raise _HttpError(HTTPStatus.NOT_FOUND, f"{method} {path} is not served here")

    def _post_config(self, query: dict[str, list[str]], change: Any,
                     client_ip: str) -> tuple[int, Any]:
        if change is not None and not isinstance(change, dict):
            raise _HttpError(HTTPStatus.BAD_REQUEST, "config must be a JSON object")
        change = dict(change or {})
        if "udp_dest" in change:  # checked before anything is staged
            if change["udp_dest"] == "@auto":
                change["udp_dest"] = client_ip
            _check_loopback(change["udp_dest"])
        self.staged.update(change)
        if _truthy(query.get("reinit")):
            kw = {attr: self.staged[key] for key, attr in _CONFIG_KEYS.items()
                  if key in self.staged}
            if self.fixed:
                return self._redirect()
            kw["init_id"] = next_init_id(self.meta.init_id)
            return self._activate(kw, self.on_reinit)
        return 200, {}

    def _activate(self, kw: dict[str, Any],
                  tell: Callable[[SensorMetadata], None] | None) -> tuple[int, Any]:
        """Make the active metadata with ``kw`` changed the sensor's (400 where that is no
        valid metadata), staged = active, and ``tell`` about it."""
        try:
            new = self.meta.with_changes(**kw)
        except (MetadataError, TypeError, ValueError) as err:
            raise _HttpError(HTTPStatus.BAD_REQUEST, f"config rejected: {err}") from err
        for name in ("udp_port_lidar", "udp_port_imu"):  # (a document may say 0: not set;
            if not 1 <= getattr(new, name) <= 0xFFFF:     # a sensor sends to a real port)
                raise _HttpError(HTTPStatus.BAD_REQUEST, f"config rejected: {name} "
                                 f"{getattr(new, name)}; expected 1 .. 65535")
        if not new.udp_dest:
            raise _HttpError(HTTPStatus.BAD_REQUEST, "config rejected: udp_dest is empty")
        if new.columns_per_packet != self.meta.columns_per_packet and \
                new.columns_per_packet not in EMULATED_COLUMNS_PER_PACKET:
            raise _HttpError(HTTPStatus.BAD_REQUEST, (
                f"config rejected: columns_per_packet {new.columns_per_packet}; the emulator "
                f"writes {', '.join(map(str, EMULATED_COLUMNS_PER_PACKET))}"))
        if new.profile != self.meta.profile:
            fw = firmware_of(new)
            offered = fw.profiles if fw is not None else EMULATED_PROFILES
            if new.profile not in offered:
                raise _HttpError(HTTPStatus.BAD_REQUEST, (
                    f"config rejected: udp_profile_lidar {new.profile}; this sensor "
                    f"(firmware {fw.version if fw else new.image_rev}) offers "
                    f"{', '.join(offered)}"))
        self.meta = new
        self.staged = dict(new.to_json()["config_params"])
        if tell is not None:
            tell(new)
        return 200, {}

    def _redirect(self) -> tuple[int, Any]:
        """A fixed sensor's reinit: a new destination is taken (same init_id: the scored
        stream goes on), any other change refused; either way staged = active after it."""
        now = self.meta.to_json()["config_params"]
        changed = sorted(k for k in self.staged if now.get(k) != self.staged[k])
        refused = [k for k in changed if k not in REDIRECT_KEYS]
        staged, self.staged = self.staged, dict(now)
        if refused:
            raise _HttpError(HTTPStatus.BAD_REQUEST,
                             "this sensor's configuration is fixed for the scored run "
                             f"(asked to change {', '.join(refused)}); only udp_dest, "
                             "udp_port_lidar and udp_port_imu may change")
        if not changed:
            return 200, {}
        for key in ("udp_port_lidar", "udp_port_imu"):
            port = staged[key]
            if not (isinstance(port, int) and not isinstance(port, bool) and 0 < port < 65536):
                raise _HttpError(HTTPStatus.BAD_REQUEST,
                                 f"{key} {str(port)[:20]}: expected a port 1 .. 65535")
        return self._activate({k: staged[k] for k in REDIRECT_KEYS}, self.on_redirect)


def _check_loopback(value: Any) -> None:
    """An IPv4 loopback address (the sender is IPv4; nothing leaves the machine)."""
    try:
        ok = isinstance(value, str) and ipaddress.IPv4Address(value).is_loopback
    except ValueError:
        ok = False
    if not ok:
        raise _HttpError(HTTPStatus.BAD_REQUEST,
                         f"udp_dest {str(value)[:60]!r}: this emulated sensor sends only to an "
                         "IPv4 loopback address (127.0.0.0/8)")


class _HttpError(Exception):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = int(status)
        self.message = message

    def body(self) -> dict[str, Any]:
        """The error as a real sensor writes it."""
        return {"error": {"title": f"{self.status} {HTTPStatus(self.status).phrase}",
                          "description": self.message}}
