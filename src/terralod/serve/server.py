"""``terralod serve``: both web formats straight from a store, and the change site's page, over HTTP.

Routes (GET and HEAD; everything else is 405; any other path is 404, never a file from elsewhere):

- ``/`` the page of :mod:`terralod.site` (``/site.js``, ``/site.css``: package data), the same page an exported
  site folder holds, answering the same paths: ``/site.json`` (the manifest), ``/epochs/I/tileset.json`` and
  its tiles (3D Tiles of epoch I, pruned as the site's are), ``/pairs/K.json`` and its rasters' tiles: one
  :class:`terralod.site.plan.SitePlan` (the plan the site writer writes), made on the first request that
  needs it under its own lock (never the encoders'), then kept;
- ``/cesium/...`` CesiumJS's browser build, the copy the package carries (:func:`terralod.serve.cesium_dir`;
  resolved paths must stay inside that folder);
- ``/3dtiles/tileset.json``, ``/3dtiles/tiles/L/X_Y.glb`` (:class:`terralod.export.tiles3d.Tiles3D`);
- ``/terrain/layer.json``, ``/terrain/Z/X/Y.terrain`` (:class:`terralod.export.quantized_mesh.QuantizedMesh`,
  always gzip'd, as the format's clients expect);
- ``/info.json`` the terrain's bounds (degrees), heights, epochs and node counts for the page;
- a store with epochs: ``/e/EPOCH/3dtiles/...`` and ``/e/EPOCH/terrain/...`` the same for one epoch (the
  plain paths are the store's latest).

Tiles are encoded on the first request and kept in a byte-bounded LRU cache; every response carries a
strong ``ETag`` (``If-None-Match`` → 304) and is gzip'd when the client accepts it. The store is opened
read-only; the encoders (which share one SQLite connection and, for TINs, one model whose scale state
``lod_mesh`` changes) run one at a time behind a lock, cache hits do not wait for it.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import logging
import mimetypes
import re
import sys
import threading
from collections import OrderedDict
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from terralod.serve import cesium_dir

log = logging.getLogger("terralod.serve")

__all__ = ["TileService", "make_server"]

#: Files of the page (the change site's, package data of terralod.site); only these names are served.
PAGE_FILES = ("index.html", "site.js", "site.css")
_SITE_TILES = re.compile(r"^/epochs/(\d{1,4})(/tileset\.json|/tiles/\d{1,3}/\d{1,9}_\d{1,9}\.glb)$")
_SITE_PAIR = re.compile(r"^/pairs/(\d{1,4})\.json$")
_SITE_RASTER = re.compile(r"^/pairs/[0-9a-f]{12}-(dod|before)/\d{1,2}/\d{1,6}_\d{1,6}\.i32\.gz$")
_GLB = re.compile(r"^/3dtiles/tiles/(\d{1,3})/(\d{1,9})_(\d{1,9})\.glb$")
_TERRAIN = re.compile(r"^/terrain/(\d{1,2})/(\d{1,9})/(\d{1,9})\.terrain$")
_EPOCH = re.compile(r"^/e/([^/]{1,64})(/.*)$")


def _change_available() -> bool:
    """Whether the change extra (xdem, shapely) is installed: the site's pairs are measured with it."""
    import importlib.util

    return all(importlib.util.find_spec(m) is not None for m in ("xdem", "shapely"))


class _LRU:
    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.size = 0
        self.items: OrderedDict[str, tuple[bytes, str, str, bool]] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: str) -> tuple[bytes, str, str, bool] | None:
        with self.lock:
            v = self.items.get(key)
            if v is not None:
                self.items.move_to_end(key)
            return v

    def put(self, key: str, value: tuple[bytes, str, str, bool]) -> None:
        with self.lock:
            if key in self.items:
                return
            self.items[key] = value
            self.size += len(value[0])
            while self.size > self.max_bytes and len(self.items) > 1:
                _, old = self.items.popitem(last=False)
                self.size -= len(old[0])


class TileService:
    """What the handler asks for: bytes by URL path (None = 404), encoded once and cached."""

    def __init__(self, terrain: Any, *, cache_bytes: int = 256 << 20, site_options: Any = None) -> None:
        from terralod.export.common import check_exportable
        from terralod.export.geodesy import Geodesy

        check_exportable(terrain)
        self.terrain = terrain
        Geodesy(terrain.crs, str(terrain.path) if terrain.path is not None else None)  # fail early on the CRS
        self.cache = _LRU(cache_bytes)
        self.lock = threading.Lock()
        self._views: dict[str | None, dict[str, Any]] = {}
        self.cesium = cesium_dir()
        self.stats = {"requests": 0, "encoded": 0, "hits": 0}
        self.site_options = site_options
        self._plan: Any = None
        self._plan_lock = threading.Lock()

    # lazily built views (their set-up reads the whole LOD tree / the source), one set per epoch
    def _view(self, epoch: str | None, kind: str) -> Any:
        v = self._views.setdefault(epoch, {})
        if kind not in v:
            if "terrain" not in v:
                same = epoch is None or epoch == getattr(self.terrain, "epoch", None)
                v["terrain"] = self.terrain if same else self.terrain.with_epoch(epoch)
            if kind == "tiles3d":
                from terralod.export.tiles3d import Tiles3D

                v[kind] = Tiles3D(v["terrain"])
            elif kind == "qm":
                from terralod.export.quantized_mesh import QuantizedMesh

                v[kind] = QuantizedMesh(v["terrain"])
        return v[kind]

    def tiles3d(self, epoch: str | None = None) -> Any:
        return self._view(epoch, "tiles3d")

    def qm(self, epoch: str | None = None) -> Any:
        return self._view(epoch, "qm")

    # the change site's page (terralod.site): the same paths as an exported site folder
    def _site_epochs(self) -> list[str | None]:
        return list(self.terrain.epochs) or [None]

    def site_plan(self) -> Any:
        """The site's :class:`~terralod.site.plan.SitePlan` (pairs measured as ``terralod change`` measures
        them, co-registered as ``site_options`` say), made once under its own lock on a connection of its
        own: a tile request never waits for it."""
        with self._plan_lock:
            if self._plan is None:
                from terralod.site.plan import SiteOptions, plan_store_site
                from terralod.terrain import open_terrain

                if not _change_available():  # without the change extra the page shows the epochs only
                    log.warning(
                        "the change extra is not installed: the page shows the epochs without their change"
                    )
                options = self.site_options or SiteOptions()
                if self.terrain.path is None:
                    self._plan = plan_store_site(self.terrain, options, measure=_change_available())
                else:
                    with open_terrain(self.terrain.path) as own:
                        self._plan = plan_store_site(own, options, measure=_change_available())
            return self._plan

    def site_manifest(self) -> dict[str, Any]:
        return self.site_plan().manifest()  # type: ignore[no-any-return]

    def site_pair(self, k: int) -> tuple[dict[str, Any], dict[str, bytes]] | None:
        """Pair ``k`` of the plan: its description and the files it names."""
        plan = self.site_plan()
        if k >= len(plan.pairs):
            return None
        return plan.pair_meta[k], plan.pair_files(k)

    def _site_tileset(self, i: int) -> dict[str, Any] | None:
        """Epoch ``i``'s tileset as the site writes it: pruned at the plan's ``keep_error_m``."""
        import copy

        from terralod.site.build import prune_tileset

        epochs = self._site_epochs()
        if i >= len(epochs):
            return None
        keep = self.site_plan().keep_error_m
        with self.lock:
            ts = copy.deepcopy(self.tiles3d(epochs[i]).tileset())
        prune_tileset(ts, keep)
        return ts

    def _planned(self, path: str) -> tuple[bytes, str, bool] | None:
        """A path the site plan answers (``/site.json``, ``/pairs/...``, ``/epochs/I/tileset.json``), or
        None; computed outside the encoder lock."""
        if path == "/site.json":
            return json.dumps(self.site_manifest()).encode(), "application/json", False
        m = _SITE_TILES.match(path)
        if m and m.group(2) == "/tileset.json":
            ts = self._site_tileset(int(m.group(1)))
            return (
                None
                if ts is None
                else (json.dumps(ts, separators=(",", ":")).encode(), "application/json", False)
            )
        m = _SITE_PAIR.match(path)
        if m:
            plan = self.site_plan()
            k = int(m.group(1))
            if k >= len(plan.pairs):
                return None
            return json.dumps(plan.pair_meta[k], separators=(",", ":")).encode(), "application/json", False
        if _SITE_RASTER.match(path):  # a tile of a pair's raster (terralod.site.tiles), gzip'd as it is read
            body = self.site_plan().files.get(path[1:])
            return (body, "application/gzip", False) if body is not None else None
        return None

    def info(self) -> dict[str, Any]:
        qm = self.qm()
        lo, hi = self.terrain.elevation_range_m
        tree = self.terrain.lod_tree()
        return {"name": Path(str(self.terrain.path)).name if self.terrain.path else "terrain",
                "kind": self.terrain.kind, "bounds_deg": list(qm.bbox), "elevation_range_m": [lo, hi],
                "epochs": list(self.terrain.epochs), "epoch": getattr(self.terrain, "epoch", None),
                "nodes": len(tree), "max_zoom": qm.max_zoom, "cesium": self.cesium is not None}  # fmt: skip

    def _encode(self, path: str) -> tuple[bytes, str, bool] | None:
        """(body, content type, already gzip'd) of a dynamic path, or None when it is not in the tile set."""
        epoch: str | None = None
        if path == "/info.json":
            return json.dumps(self.info()).encode(), "application/json", False
        m = _SITE_TILES.match(path)
        if m:  # a tile of epoch I (its tileset is planned: _planned)
            epochs = self._site_epochs()
            i = int(m.group(1))
            if i >= len(epochs):
                return None
            epoch = epochs[i]
            path = "/3dtiles" + m.group(2)
        m = _EPOCH.match(path)
        if m:
            if m.group(1) not in self.terrain.epochs:
                return None
            epoch, path = m.group(1), m.group(2)
        if path == "/3dtiles/tileset.json":
            ts = self.tiles3d(epoch).tileset()
            return json.dumps(ts, separators=(",", ":")).encode(), "application/json", False
        m = _GLB.match(path)
        if m:
            code = tuple(int(a) for a in m.groups())
            view = self.tiles3d(epoch)
            if code not in view.nodes or not view.has_content(code):
                return None
            return view.glb(code), "model/gltf-binary", False
        if path == "/terrain/layer.json":
            return json.dumps(self.qm(epoch).layer()).encode(), "application/json", False
        m = _TERRAIN.match(path)
        if m:
            z, x, y = (int(a) for a in m.groups())
            qm = self.qm(epoch)
            if not qm.available(z, x, y):
                return None
            return qm.tile(z, x, y).data, "application/vnd.quantized-mesh", True
        return None

    def get(self, path: str) -> tuple[bytes, str, str, bool] | None:
        """(body, content type, etag, gzip'd) for a URL path, None for 404."""
        self.stats["requests"] += 1
        hit = self.cache.get(path)
        if hit is not None:
            self.stats["hits"] += 1
            return hit
        static = self._static(path)
        if static is not None:
            return static
        got = self._planned(path)  # the site plan: its own lock, never the encoders'
        if got is None:
            with self.lock:
                hit = self.cache.get(path)
                if hit is not None:
                    return hit
                got = self._encode(path)
                if got is None:
                    return None
                self.stats["encoded"] += 1
        body, ctype, gz = got
        if not gz and len(body) > 1024 and not ctype.startswith("image/") and ctype != "application/gzip":
            body, gz = gzip.compress(body, 6, mtime=0), True
        value = (body, ctype, '"' + hashlib.sha1(body).hexdigest() + '"', gz)
        self.cache.put(path, value)
        return value

    def _static(self, path: str) -> tuple[bytes, str, str, bool] | None:
        if path in ("/", "/index.html"):
            name = "index.html"
        elif path[1:] in PAGE_FILES:
            name = path[1:]
        elif path.startswith("/cesium/") and self.cesium is not None:
            rel = path[len("/cesium/") :]
            f = (self.cesium / rel).resolve()
            if not f.is_relative_to(self.cesium) or not f.is_file():
                return None
            body = f.read_bytes()
            ctype = mimetypes.guess_type(f.name)[0] or "application/octet-stream"
            value = (body, ctype, '"' + hashlib.sha1(body).hexdigest() + '"', False)
            if len(body) < (8 << 20):
                self.cache.put(path, value)
            return value
        else:
            return None
        body = resources.files("terralod.site").joinpath("static", name).read_bytes()
        ctype = mimetypes.guess_type(name)[0] or "application/octet-stream"
        return (body, ctype, '"' + hashlib.sha1(body).hexdigest() + '"', False)


#: Seconds a connection may sit idle or half-sent before the server closes it.
REQUEST_TIMEOUT_S = 20.0
#: Requests handled at once; further connections wait in the listen backlog, not in threads.
MAX_THREADS = 32
#: Bytes of a refused request's body the server reads (and drops) to keep the connection; more closes it.
MAX_DISCARD_BYTES = 64 << 10


class _Handler(BaseHTTPRequestHandler):
    server_version = "terralod"
    service: TileService
    protocol_version = "HTTP/1.1"
    timeout = REQUEST_TIMEOUT_S  # socket timeout: an idle or half-sent request is dropped, not waited for

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
        log.debug("%s " + format, self.address_string(), *args)

    def _send(self, code: int, body: bytes = b"", ctype: str = "text/plain; charset=utf-8",
              headers: dict[str, str] | None = None, head: bool = False) -> None:  # fmt: skip
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Access-Control-Allow-Origin", "*")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if not head and body:
            self.wfile.write(body)

    def _serve(self, head: bool) -> None:
        try:
            raw = urlsplit(self.path).path
            path = unquote(raw)
            if "\x00" in path or "\\" in path or "/../" in path + "/" or not path.startswith("/"):
                self._send(404, b"not found\n", head=head)
                return
            if path == "/favicon.ico":
                self._send(204, head=head)
                return
            got = self.service.get(path)
        except Exception as exc:  # noqa: BLE001 - one failed tile must not stop the server
            log.warning("%s: %s", self.path, exc)
            self._send(500, f"error: {type(exc).__name__}\n".encode(), head=head)
            return
        if got is None:
            self._send(404, b"not found\n", head=head)
            return
        body, ctype, etag, gz = got
        headers = {"ETag": etag, "Cache-Control": "no-cache"}
        if self.headers.get("If-None-Match") == etag:
            self.send_response(304)
            self.send_header("ETag", etag)
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        if gz:
            if "gzip" in (self.headers.get("Accept-Encoding") or ""):
                headers["Content-Encoding"] = "gzip"
            else:
                body = gzip.decompress(body)
        headers["Vary"] = "Accept-Encoding"
        self._send(200, body, ctype, headers, head)

    def do_GET(self) -> None:  # noqa: N802 - http.server's names
        self._drop_body()
        self._serve(False)

    def do_HEAD(self) -> None:  # noqa: N802
        self._drop_body()
        self._serve(True)

    def _drop_body(self) -> None:
        """Read a request's body (so it is never parsed as the next request) or close after replying."""
        try:
            n = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            n = -1
        chunked = "chunked" in (self.headers.get("Transfer-Encoding") or "").lower()
        if n == 0 and not chunked:
            return
        if 0 < n <= MAX_DISCARD_BYTES and not chunked:
            try:
                self.rfile.read(n)
                return
            except OSError:  # the client went away mid-body: fall through and close
                pass
        self.close_connection = True

    def _refuse(self) -> None:
        self._drop_body()
        hdr = {"Allow": "GET, HEAD"}
        if self.close_connection:
            hdr["Connection"] = "close"
        self._send(405, b"read-only: GET and HEAD only\n", headers=hdr)

    do_POST = do_PUT = do_DELETE = do_PATCH = _refuse  # noqa: N815


class _Server(ThreadingHTTPServer):
    """At most :data:`MAX_THREADS` requests at once; one log line per failed connection, no traceback."""

    daemon_threads = True
    request_queue_size = 1024

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._slots = threading.BoundedSemaphore(MAX_THREADS)
        self.failures = 0

    def process_request(self, request: Any, client_address: Any) -> None:
        self._slots.acquire()  # the accept loop waits here: connections queue in the kernel's backlog
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    def handle_error(self, request: Any, client_address: Any) -> None:
        exc = sys.exc_info()[1]
        self.failures += 1
        who = client_address[0] if isinstance(client_address, tuple) else client_address
        if isinstance(exc, ConnectionError | TimeoutError):
            log.info("%s: client went away (%s)", who, type(exc).__name__)
        else:
            log.warning("%s: request failed: %s: %s", who, type(exc).__name__, exc)


def make_server(
    terrain: Any,
    host: str = "127.0.0.1",
    port: int = 8000,
    *,
    request_timeout_s: float = REQUEST_TIMEOUT_S,
    site_options: Any = None,
) -> tuple[ThreadingHTTPServer, TileService]:
    """A server (not started: call ``serve_forever``) and its service for ``terrain``; ``site_options``
    (:class:`terralod.site.plan.SiteOptions`) say how the page's pairs are measured, as for an exported site.

    The service is made first, so a store error is raised as itself (a :class:`terralod.errors.StoreError`
    naming the store), never reported as a failure to listen."""
    service = TileService(terrain, site_options=site_options)
    handler = type("Handler", (_Handler,), {"service": service, "timeout": request_timeout_s})
    return _Server((host, port), handler), service
