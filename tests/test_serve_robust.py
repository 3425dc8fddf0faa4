"""``terralod serve`` under misbehaving clients: disconnects mid-response, half-sent and idle requests, bodies
on refused methods, many connections at once, and a damaged store at start-up.

Each case is a probe of the round-three reliability campaign kept as a test (bounded loops on loopback). The
server runs in this process on a small real store (the bundled Jacksboro DEM, UTM 16N) with a short request
timeout, so a half-sent request is dropped within about a second.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from pathlib import Path

import pytest

from terralod.cli import main

TIMEOUT_S = 1.0


@pytest.fixture(scope="module")
def small_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from terralod.io.reader import sample_heightfield
    from terralod.pyramid.builder import build_store

    p = tmp_path_factory.mktemp("serve") / "small.terra"
    build_store(sample_heightfield(), p, workers=1)
    return p


@pytest.fixture()
def live(small_store: Path):
    from terralod.serve import make_server
    from terralod.terrain import open_terrain

    t = open_terrain(small_store)
    srv, service = make_server(t, "127.0.0.1", 0, request_timeout_s=TIMEOUT_S)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    yield srv, srv.server_address[1]
    srv.shutdown()
    srv.server_close()
    t.close()


def _connect(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    return s


def _read_response(s: socket.socket) -> tuple[int, bytes]:
    """Status code and body of one HTTP/1.1 response with a Content-Length."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        chunk = s.recv(65536)
        if not chunk:
            raise ConnectionError("closed before the headers")
        buf += chunk
    head, body = buf.split(b"\r\n\r\n", 1)
    lines = head.decode("latin-1").split("\r\n")
    code = int(lines[0].split()[1])
    n = next(int(h.split(":", 1)[1]) for h in lines[1:] if h.lower().startswith("content-length"))
    while len(body) < n:
        chunk = s.recv(65536)
        if not chunk:
            break
        body += chunk
    return code, body[:n]


def test_disconnects_log_one_line_each_and_no_traceback(
    live, caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture
) -> None:
    srv, port = live
    caplog.set_level(logging.DEBUG, logger="terralod.serve")
    layer = b"GET /terrain/layer.json HTTP/1.1\r\nHost: x\r\n\r\n"
    n = 40
    for _ in range(n):  # ask, then vanish with a reset before the reply is read
        s = _connect(port)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        s.sendall(layer)
        s.close()
    s = _connect(port)  # the server still answers
    s.sendall(layer)
    assert _read_response(s)[0] == 200
    s.close()
    text = caplog.text + capfd.readouterr().err  # socketserver prints its tracebacks to stderr
    assert "Traceback" not in text
    assert srv.failures <= n
    assert len([r for r in caplog.records if r.levelno >= logging.INFO]) <= n


def test_refused_body_is_not_read_as_the_next_request(live) -> None:
    _, port = live
    s = _connect(port)
    body = b"GET /etc/passwd HTTP/1.1\r\nHost: x\r\n\r\n"  # a body that looks like a request
    s.sendall(
        b"POST /terrain/layer.json HTTP/1.1\r\nHost: x\r\nContent-Length: %d\r\n\r\n" % len(body) + body
    )
    code, _ = _read_response(s)
    assert code == 405
    s.sendall(b"GET /terrain/layer.json HTTP/1.1\r\nHost: x\r\n\r\n")
    code, got = _read_response(s)
    assert code == 200 and got.startswith(b"{")  # the answer to our GET, not to the smuggled one
    s.close()
    s = _connect(port)  # a body too large to drop: the server answers and closes
    s.sendall(b"PUT /x HTTP/1.1\r\nHost: x\r\nContent-Length: 10000000\r\n\r\n" + b"x" * 1000)
    assert _read_response(s)[0] == 405
    s.settimeout(30)
    rest = s.recv(100)
    assert rest == b""  # closed by the server, the 10 MB never parsed
    s.close()


def test_half_sent_and_idle_requests_time_out(live) -> None:
    _, port = live
    half = _connect(port)
    half.sendall(b"GET /terrain/layer.json HT")
    idle = _connect(port)
    t0 = time.monotonic()
    assert half.recv(100) == b""  # the server closed it (client timeout 30 s, server's TIMEOUT_S)
    assert idle.recv(100) == b""
    assert time.monotonic() - t0 < 25  # closed by the server's timeout, not by the client's
    half.close()
    idle.close()


def test_threads_are_bounded(live) -> None:
    from terralod.serve.server import MAX_THREADS

    _, port = live
    before = threading.active_count()
    socks = []
    for _ in range(3 * MAX_THREADS):
        s = _connect(port)
        s.sendall(b"GET / HT")
        socks.append(s)
    time.sleep(0.3)
    assert threading.active_count() - before <= MAX_THREADS
    for s in socks:
        s.close()


@pytest.mark.parametrize("damage", ["incomplete", "corrupt"])
def test_damaged_store_is_named_at_start(damage: str, small_store: Path, tmp_path: Path, capsys) -> None:
    """An interrupted build's store and a store with wiped pages: one line naming the store, never "cannot
    listen" (the store error used to be caught as a failure to bind, being an OSError)."""
    bad = tmp_path / "bad.terra"
    if damage == "incomplete":
        from terralod.io.reader import sample_heightfield
        from terralod.pyramid.builder import build_store

        build_store(sample_heightfield(), bad, workers=1, stop_after=3)
    else:
        data = bytearray(small_store.read_bytes())
        data[4096 : 4096 + 20000] = b"\x00" * 20000  # wipe pages after the header
        bad.write_bytes(bytes(data))
    with pytest.raises(SystemExit) as exc:
        main(["serve", str(bad), "--port", "0"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2
    assert "cannot listen" not in err and "bad.terra" in err and len(err.splitlines()) == 1, err
