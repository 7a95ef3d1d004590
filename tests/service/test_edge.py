"""The HTTP edge over real HTTP against `calib serve`: the API token, database faults answered 503, offline docs,
oversized bodies without `Expect: 100-continue`, HEAD, 500s on keep-alive connections, paging, the model cache."""
from __future__ import annotations

import base64
import http.client
import json
import re
import shutil
import socket
import sqlite3
import subprocess
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from types import SimpleNamespace
from urllib.parse import urlsplit, urlunsplit

import httpx
import pytest

from .conftest import PG_URL, PROBLEM, Proc, Server, assert_problem, base_env, free_port, reset_postgres, wait_for

CHROMIUM = Path("/usr/bin/chromium")


def assert_unavailable(r) -> dict:
    body = assert_problem(r, 503)
    assert int(r.headers["retry-after"]) > 0
    return body


def assert_health_unavailable(client) -> dict:
    r = client.get("/health")
    assert r.status_code == 503, r.text
    assert int(r.headers["retry-after"]) > 0
    body = r.json()
    assert body["status"] == "unavailable" and body["detail"], body
    return body


class LooseServer(Server):
    """`calib serve` that may start with its database down: ready once /health answers at all."""

    def ready(self) -> bool:
        httpx.get(self.url + "/health", timeout=10)
        return True


# ---------------------------------------------------------------------------------------------------- auth

@pytest.mark.parametrize("value", ["", "   "])
def test_empty_token_refuses_to_start(tmp_path, value):
    """CALIB_API_TOKEN set to nothing must not silently switch authentication off: `calib serve` says so and
    exits instead of serving."""
    port = free_port()
    p = Proc(["serve", "--port", str(port)], base_env(f"sqlite:///{tmp_path / 'e.db'}", CALIB_API_TOKEN=value),
             tmp_path / "server.log")
    try:
        code = p.p.wait(90)
    except subprocess.TimeoutExpired:
        code = None
    finally:
        p.kill()
    assert code not in (None, 0), "the server ran with an empty CALIB_API_TOKEN:\n" + p.output()[-2000:]
    assert "CALIB_API_TOKEN is set but empty" in p.output(), p.output()[-2000:]


def test_token_gates_every_read_but_health_and_may_be_non_ascii(tmp_path, model_doc, csv_text):
    token = "clé-Ünïcode-🔑-s3cret"
    s = Server(f"sqlite:///{tmp_path / 'auth.db'}", tmp_path / "server.log", CALIB_API_TOKEN=token,
               CALIB_EMBEDDED_WORKERS="0")
    good = {"Authorization": b"Bearer " + token.encode("utf-8")}  # raw UTF-8 bytes, as a client sends them
    basic = {"Authorization": b"Basic " + base64.b64encode(b"anyone:" + token.encode("utf-8"))}
    bad = [{}, {"Authorization": "Bearer wrong"}, {"Authorization": b"Bearer " + token[:-1].encode("utf-8")},
           {"Authorization": b"Bearer " + token.encode("utf-8") + b"x"},
           {"Authorization": b"Basic " + base64.b64encode(b"anyone:wrong")}, {"Authorization": "Basic !!"},
           {"Authorization": b"Token " + token.encode("utf-8")}]
    try:
        r = s.client.post("/robots", json=model_doc)
        assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer")
        r = s.client.post("/robots", json=model_doc, headers=good)
        assert r.status_code == 201, r.text
        rid = r.json()["id"]
        r = s.client.post(f"/robots/{rid}/measurements", files={"file": ("a.csv", csv_text)}, headers=good)
        assert r.status_code == 201, r.text
        ms = r.json()["id"]
        reads = {"/robots": 200, f"/robots/{rid}": 200, f"/robots/{rid}/measurements": 200,
                 f"/measurements/{ms}": 200, "/jobs/nope": 404, "/calibrations/nope": 404,
                 "/calibrations/nope/report": 404, "/calibrations/nope/plots/errors.png": 404,
                 "/docs": 200, "/redoc": 200, "/openapi.json": 200, "/docs-assets/swagger-ui.css": 200,
                 "/no/such/route": 404}
        for path, status in reads.items():
            for h in bad:
                r = s.client.get(path, headers=h)
                assert_problem(r, 401)
                assert "Bearer" in r.headers["www-authenticate"], (path, h)
            assert s.client.head(path).status_code == 401, path
            assert s.client.get(path, headers=good).status_code == status, path
            assert s.client.get(path, headers=basic).status_code == status, path  # a browser's way
        for h in bad[1:3]:
            assert_problem(s.client.post("/jobs", json={"measurement_set_id": ms}, headers=h), 401)
        req = urllib.request.Request(s.url + "/robots", data=b" " * (5 * 1024 * 1024), method="POST")
        with pytest.raises(urllib.error.HTTPError) as e:  # refused unread: the client still reads the 401
            urllib.request.urlopen(req, timeout=60)
        assert e.value.code == 401 and json.loads(e.value.read())["status"] == 401
        r = s.client.get("/health")  # the one open call (load balancers, probes)
        assert r.status_code == 200 and r.json()["status"] == "ok"
    finally:
        s.stop()


# ----------------------------------------------------------------------------------------- database faults

def test_sqlite_directory_deleted_refuses_reads_and_writes_with_503(tmp_path, model_doc, csv_text):
    """The directory of the SQLite file deleted while running: no 201/202 for writes that would be lost at
    restart, no empty database silently created, /health notices."""
    data = tmp_path / "data"
    data.mkdir()
    s = Server(f"sqlite:///{data / 'calib.db'}", tmp_path / "server.log")
    try:
        r = s.client.post("/robots", json=model_doc)
        assert r.status_code == 201, r.text
        rid = r.json()["id"]
        ms = s.client.post(f"/robots/{rid}/measurements", files={"file": ("a.csv", csv_text)}).json()["id"]
        shutil.rmtree(data)
        for _ in range(3):  # more than once: pooled connections must not slip through
            assert_unavailable(s.client.post("/robots", json=model_doc))
            assert_unavailable(s.client.post(f"/robots/{rid}/measurements", files={"file": ("a.csv", csv_text)}))
            assert_unavailable(s.client.post("/jobs", json={"measurement_set_id": ms, "model": "geometric"}))
            assert_unavailable(s.client.get(f"/robots/{rid}"))
            assert_unavailable(s.client.get("/robots"))
        assert "gone" in assert_health_unavailable(s.client)["detail"]
        data.mkdir()  # the directory comes back empty: still refused, and no new empty database appears
        assert_unavailable(s.client.post("/robots", json=model_doc))
        assert_health_unavailable(s.client)
        time.sleep(0.5)  # the embedded dispatcher polls meanwhile; it must not create the file either
        assert not (data / "calib.db").exists(), list(data.iterdir())
    finally:
        s.stop()


def test_read_only_sqlite_reads_and_refuses_writes_with_503(tmp_path, model_doc):
    from service.cli import db_upgrade

    path = tmp_path / "ro.db"
    db_upgrade(f"sqlite:///{path}")
    s = Server(f"sqlite:///{path}", tmp_path / "rw.log", CALIB_EMBEDDED_WORKERS="0")
    try:
        rid = s.client.post("/robots", json=model_doc).json()["id"]
    finally:
        s.stop()
    s = LooseServer(f"sqlite:///file:{path}?mode=ro&uri=true", tmp_path / "ro.log", CALIB_EMBEDDED_WORKERS="0")
    try:
        assert s.client.get(f"/robots/{rid}").status_code == 200  # reads still work
        body = assert_unavailable(s.client.post("/robots", json=model_doc))
        assert "read-only" in body["detail"]
        assert "read-only" in assert_health_unavailable(s.client)["detail"]
    finally:
        s.stop()


def test_postgres_unreachable_is_503_not_500(tmp_path, model_doc):
    pytest.importorskip("psycopg")
    url = f"postgresql+psycopg://calib@127.0.0.1:{free_port()}/calib"  # nothing listens there
    s = LooseServer(url, tmp_path / "server.log", CALIB_EMBEDDED_WORKERS="0")
    try:
        assert_unavailable(s.client.get("/robots"))
        assert_unavailable(s.client.get("/jobs/x"))
        assert_unavailable(s.client.post("/robots", json=model_doc))
        assert assert_health_unavailable(s.client)["database"] == "postgresql"
    finally:
        s.stop()


class TcpProxy:
    """127.0.0.1:port -> target, which the test can cut (every connection reset, new ones refused) and restore."""

    def __init__(self, host: str, port: int):
        self.target = (host, port)
        self.up = True
        self.conns: list[socket.socket] = []
        self.lock = threading.Lock()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                c, _ = self.listener.accept()
            except OSError:
                return
            if not self.up:
                c.close()
                continue
            try:
                u = socket.create_connection(self.target, timeout=5)
            except OSError:
                c.close()
                continue
            with self.lock:
                self.conns += [c, u]
            for a, b in ((c, u), (u, c)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        for x in (a, b):
            try:
                x.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self) -> None:
        self.up = False
        with self.lock:
            for c in self.conns:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                c.close()
            self.conns.clear()

    def restore(self) -> None:
        self.up = True

    def close(self) -> None:
        self.cut()
        self.listener.close()


@pytest.mark.skipif(not PG_URL, reason="CALIB_TEST_POSTGRES_URL is not set (.ci/run starts a PostgreSQL server)")
def test_postgres_going_down_is_503_and_the_service_recovers(tmp_path, model_doc):
    reset_postgres(PG_URL)
    u = urlsplit(PG_URL.replace("postgresql+psycopg", "postgresql", 1))
    proxy = TcpProxy(u.hostname, u.port or 5432)
    user = f"{u.username}{':' + u.password if u.password else ''}@" if u.username else ""
    url = urlunsplit(("postgresql+psycopg", f"{user}127.0.0.1:{proxy.port}", u.path, u.query, ""))
    s = Server(url, tmp_path / "server.log", CALIB_EMBEDDED_WORKERS="0")
    try:
        r = s.client.post("/robots", json=model_doc)
        assert r.status_code == 201, r.text
        rid = r.json()["id"]
        proxy.cut()
        assert_unavailable(s.client.get(f"/robots/{rid}"))
        assert_unavailable(s.client.post("/robots", json=model_doc))
        assert_health_unavailable(s.client)
        proxy.restore()
        wait_for(lambda: s.client.get("/health").status_code == 200, 30, "/health to recover")
        assert s.client.get(f"/robots/{rid}").status_code == 200
        assert s.client.post("/robots", json=model_doc).status_code == 201
    finally:
        s.stop()
        proxy.close()


# ----------------------------------------------------------------------------------------------- offline docs

def test_docs_pages_load_nothing_from_other_hosts(server):
    for page in ("/docs", "/redoc"):
        r = server.client.get(page)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        refs = re.findall(r'(?:src|href)\s*=\s*["\']([^"\']+)', r.text)
        assert refs, r.text
        assert all(ref.startswith("/") and not ref.startswith("//") for ref in refs), (page, refs)
        assert "https://" not in r.text and "http://" not in r.text, page
        for ref in refs:
            a = server.client.get(ref)
            assert a.status_code == 200 and len(a.content) > 1000, ref


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is not installed (.ci/run installs it)")
@pytest.mark.parametrize("page, expect", [("/docs", "opblock-summary-path"), ("/redoc", "Store a robot model")])
def test_docs_render_offline_in_headless_chromium(server, tmp_path, page, expect):
    """Every host but this machine unreachable (as on a cell network): the docs still render every operation."""
    r = subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                        "--disable-background-networking", "--disable-component-update", "--disable-sync",
                        "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'chromium'}",
                        "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
                        "--virtual-time-budget=20000", "--dump-dom", server.url + page],
                       capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    dom = r.stdout
    assert expect in dom, dom[:3000]
    for path in ("/robots/{robot_id}/measurements", "/calibrations/{calibration_id}/compensate", "/jobs/{job_id}"):
        assert path in dom, (page, path)
    if page == "/docs":
        assert dom.count("opblock-summary-path") >= 11, dom.count("opblock-summary-path")


# ------------------------------------------------------------------------------------------ oversized bodies

def test_oversized_body_without_expect_continue_gets_the_413(server):
    """urllib sends the whole body at once (no `Expect: 100-continue`): it must read the 413, not a reset."""
    limit = 20 * 1024 * 1024
    req = urllib.request.Request(server.url + "/robots", data=b" " * (2 * limit), method="POST",
                                 headers={"Content-Type": "application/json"})
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(req, timeout=120)
    assert e.value.code == 413
    assert e.value.headers["content-type"].startswith(PROBLEM)
    body = json.loads(e.value.read())
    assert body["status"] == 413 and str(limit) in body["detail"]


def test_oversized_chunked_body_gets_the_413(server):
    """No Content-Length: the body is counted as it streams; the answer still arrives whole."""
    chunk = b" " * (1024 * 1024)
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=120)
    try:
        conn.request("POST", "/robots", body=(chunk for _ in range(40)), encode_chunked=True,
                     headers={"Content-Type": "application/json", "Transfer-Encoding": "chunked"})
        r = conn.getresponse()
        assert r.status == 413 and r.getheader("content-type").startswith(PROBLEM)
        assert json.loads(r.read())["status"] == 413
    finally:
        conn.close()
    assert server.client.get("/health").status_code == 200


# ---------------------------------------------------------------------------------------------- HEAD, 500s

def test_head_answers_like_get_on_every_get_route(server, model_doc, csv_text):
    c = server.client
    rid = c.post("/robots", json=model_doc).json()["id"]
    ms = c.post(f"/robots/{rid}/measurements", files={"file": ("a.csv", csv_text)}).json()["id"]
    job = c.post("/jobs", json={"measurement_set_id": ms, "model": "geometric"}).json()["id"]
    cal = wait_for(lambda: c.get(f"/jobs/{job}").json()["calibration_id"], 120, "the job to finish")
    ids = {"robot_id": rid, "measurement_set_id": ms, "job_id": job, "calibration_id": cal, "name": "errors"}
    paths = [p for p, ops in c.get("/openapi.json").json()["paths"].items() if "get" in ops]
    assert len(paths) >= 8, paths
    urls = [re.sub(r"\{(\w+)\}", lambda m: ids[m.group(1)], p) for p in paths]
    urls += ["/docs", "/redoc", "/openapi.json", "/docs-assets/swagger-ui.css", "/robots/nope", "/no/such/route"]
    for url in urls:
        g, h = c.get(url), c.head(url)
        assert h.status_code == g.status_code, (url, h.status_code, g.status_code)
        assert h.content == b"", url
        assert h.headers.get("content-type") == g.headers.get("content-type"), url
        if "content-length" in g.headers and url not in ("/health",):
            assert h.headers.get("content-length") == g.headers["content-length"], url
    assert c.head("/jobs").status_code == 405  # a POST-only route stays POST-only


def test_a_500_tells_the_keep_alive_client_the_connection_ends(server):
    """A stored row the service cannot read (corrupt JSON) is a 500: the answer is a problem document with
    `Connection: close`, not a connection dropped without a word after it."""
    bad = "corrupt-row"
    with sqlite3.connect(server.db_path) as db:
        db.execute("INSERT INTO robots (id, name, model_json, joint_names, created_at) VALUES (?, 'x', '{nope', "
                   "'[]', 0)", (bad,))
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    try:
        conn.request("GET", "/health")
        assert conn.getresponse().read() and conn.sock is not None  # a keep-alive connection
        conn.request("GET", f"/robots/{bad}")
        r = conn.getresponse()
        body = json.loads(r.read())
        assert r.status == 500 and r.getheader("content-type").startswith(PROBLEM), body
        assert body["status"] == 500
        assert (r.getheader("connection") or "").lower() == "close", r.getheaders()
        conn.request("GET", "/health")  # http.client opens a new connection, as told
        assert conn.getresponse().status == 200
    finally:
        conn.close()
        with sqlite3.connect(server.db_path) as db:
            db.execute("DELETE FROM robots WHERE id = ?", (bad,))


# --------------------------------------------------------------------------------------- paging, model cache

def test_robots_list_is_paged_with_total_and_links(server, model_doc):
    c = server.client
    mine = {c.post("/robots", json=model_doc).json()["id"] for _ in range(3)}
    r = c.get("/robots")
    assert r.status_code == 200 and isinstance(r.json(), list)  # the contract's shape
    total = int(r.headers["x-total-count"])
    assert total >= 3 and len(r.json()) == min(total, 100)
    seen, url, pages = [], "/robots?limit=2", 0
    while url:
        r = c.get(url)
        assert r.status_code == 200 and int(r.headers["x-total-count"]) == total
        page = r.json()
        assert 1 <= len(page) <= 2
        seen += [x["id"] for x in page]
        m = re.search(r'<([^>]+)>;\s*rel="next"', r.headers.get("link", ""))
        url = m.group(1) if m else None
        pages += 1
        assert pages <= total
    assert len(seen) == len(set(seen)) == total and mine <= set(seen)
    assert 'rel="prev"' in c.get("/robots?limit=2&offset=2").headers["link"]


def test_robots_page_is_bounded_in_bytes(server, model_doc):
    """Two 5 MB models never come in one answer: the page ends early and links to the rest."""
    big = dict(model_doc, meta={"notes": "x" * (5 * 1024 * 1024)})
    ids = [server.client.post("/robots", json=big).json()["id"] for _ in range(2)]
    total = int(server.client.get("/robots?limit=1").headers["x-total-count"])
    r = server.client.get(f"/robots?limit=1000&offset={total - 2}")
    assert [x["id"] for x in r.json()] == ids[:1]
    assert f"offset={total - 1}" in r.headers["link"]


def test_model_cache_is_bounded_by_bytes(model_doc):
    from service.robots import service

    cache = service._cache
    size = len(json.dumps(model_doc, sort_keys=True))
    old = cache.max_bytes
    try:
        cache.clear()
        cache.max_bytes = 10 * size
        robots = [SimpleNamespace(id=f"r{i}", model_json=model_doc) for i in range(40)]
        for r in robots:
            assert list(service.model_of(r).joint_names) == [j["name"] for j in model_doc["joints"]]
            assert cache.bytes <= cache.max_bytes
        assert len(cache) == 10 and cache.bytes == 10 * size
        assert service.model_of(robots[-1]) is service.model_of(robots[-1])  # a hit
        huge = SimpleNamespace(id="huge", model_json=dict(model_doc, meta={"notes": "x" * (20 * size)}))
        service.model_of(huge)  # larger than the whole cache: parsed, not kept
        assert cache.get("huge") is None and cache.bytes <= cache.max_bytes
    finally:
        cache.max_bytes = old
        cache.clear()
