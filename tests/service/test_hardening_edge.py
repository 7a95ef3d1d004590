"""Issue 33, the HTTP edge over real HTTP against `calib serve`: the 413 of a body far over the limit reaches plain
clients (Python's http.client and urllib send the whole body before they read any answer). Before, a body beyond
the drain bound (4x the limit: 80 MiB by default) was answered with `Connection: close` unread, and such a client saw
BrokenPipe / connection reset instead of the 413 (curl, which reads while it sends, got it)."""
from __future__ import annotations

import http.client
import json
import urllib.error
import urllib.request

import pytest

from .conftest import PROBLEM, Server

LIMIT = 20 * 1024 * 1024
BIG = 90 * 1000 * 1000  # the 90 MB: beyond the old drain bound of 4x the limit


@pytest.fixture(scope="module")
def edge_server(tmp_path_factory):
    d = tmp_path_factory.mktemp("edge")
    s = Server(f"sqlite:///{d / 'calib.db'}", d / "server.log", CALIB_EMBEDDED_WORKERS="0",
               CALIB_PARSE_PROCESSES="0", CALIB_PLAN_PROCESSES="0")
    yield s
    s.stop()


@pytest.fixture(scope="module")
def big_body() -> bytes:
    return b" " * BIG


def _assert_413(status: int, headers, body: bytes) -> None:
    assert status == 413, body[:500]
    assert headers["content-type"].startswith(PROBLEM)
    doc = json.loads(body)
    assert doc["status"] == 413 and str(LIMIT) in doc["detail"], doc


def test_a_90_mb_body_reaches_urllib_as_the_413(edge_server, big_body):
    req = urllib.request.Request(edge_server.url + "/robots", data=big_body, method="POST",
                                 headers={"Content-Type": "application/json"})
    with pytest.raises(urllib.error.HTTPError) as e:  # before: URLError(BrokenPipeError) / ConnectionResetError
        urllib.request.urlopen(req, timeout=60)
    _assert_413(e.value.code, e.value.headers, e.value.read())


def test_a_90_mb_upload_reaches_http_client_as_the_413(edge_server, big_body):
    """The measurement upload, multipart, as a cell PC's script would send it with http.client."""
    boundary = "hardening413"
    head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"big.csv\"\r\n"
            "Content-Type: text/csv\r\n\r\n").encode()
    body = head + big_body + f"\r\n--{boundary}--\r\n".encode()
    conn = http.client.HTTPConnection("127.0.0.1", edge_server.port, timeout=60)
    try:
        conn.request("POST", "/robots/nope/measurements", body=body,  # any robot: the size is refused first
                     headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
        resp = conn.getresponse()
        _assert_413(resp.status, resp.headers, resp.read())
    finally:
        conn.close()
    assert edge_server.client.get("/health").status_code == 200
