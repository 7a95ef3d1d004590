"""Issue 33: a read-only (or failed) window of the database leaves nothing behind, and /health and the writes agree,
over real HTTP against `calib serve`.

SQLite: the file made read-only for a while (chmod 444) and writable again. Before, connections opened during the
window were read-only for good and stayed in the pool: about 75 % of the writes after the window answered 503
"read-only" while /health said 200; during the window /health said 503 while the connections opened before it still
wrote. The server runs without CAP_DAC_OVERRIDE when the tests run as root (root writes a 0444 file otherwise).

PostgreSQL: the test's own database set read-only (`default_transaction_read_only`) for a while: writes are 503 (not
500) and /health says so; afterwards every write succeeds (the sessions opened meanwhile are not kept read-only).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlsplit, urlunsplit

import httpx
import pytest

from .conftest import PG_URL, ROOT, Proc, Server, assert_problem, sqlite_count

SETPRIV = shutil.which("setpriv")
WRITES = 16


class _NoOverrideProc(Proc):
    """Proc, but a root test run starts the server without the capability to write files it has no write
    permission for (as any service user is), so a chmod makes the database read-only for it."""

    def __init__(self, args: list[str], env: dict, log):
        if os.geteuid() == 0 and SETPRIV is None:
            pytest.skip("running as root without setpriv: a chmod cannot make the database read-only for the server")
        prefix = [SETPRIV, "--bounding-set", "-dac_override,-dac_read_search", "--"] if os.geteuid() == 0 else []
        self.log = log
        self._fh = open(log, "ab")
        self.p = subprocess.Popen([*prefix, sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env,
                                  stdout=self._fh, stderr=subprocess.STDOUT, start_new_session=True)


class _Server(Server, _NoOverrideProc):
    pass


def _burst(url: str, n: int, fn) -> list[httpx.Response]:
    """n requests at once, each on a connection of its own (so the server's pool opens connections meanwhile)."""
    def one(i):
        with httpx.Client(base_url=url, timeout=60) as c:
            return fn(c, i)
    with ThreadPoolExecutor(n) as ex:
        return list(ex.map(one, range(n)))


def _named(doc: dict, tag: str) -> dict:
    return {**doc, "name": f"{doc['name']}-{tag}"}


def _health(client) -> httpx.Response:
    r = client.get("/health")
    assert r.status_code in (200, 503), r.text
    return r


def _read_only_window(s, db, model_doc, tag: str) -> None:
    """The file read-only: /health says so and every write is refused with 503 "read-only", reads go on."""
    db.chmod(0o444)
    try:
        h = _health(s.client)
        assert h.status_code == 503 and "read-only" in h.json()["detail"], h.text
        during = _burst(s.url, WRITES, lambda c, i: c.post("/robots", json=_named(model_doc, f"{tag}-{i}")))
        during += [s.client.post("/robots", json=_named(model_doc, f"{tag}-seq-{i}")) for i in range(4)]
        codes = [r.status_code for r in during]
        assert codes.count(201) == 0, f"/health says 503 but writes were stored: {codes}"  # they agree
        for r in during:
            assert "read-only" in assert_problem(r, 503)["detail"] and int(r.headers["retry-after"]) > 0
        assert s.client.get("/robots", params={"limit": 1}).status_code == 200
    finally:
        db.chmod(0o644)


def _writes_all_stored(s, model_doc, tag: str) -> int:
    assert _health(s.client).status_code == 200
    after = _burst(s.url, WRITES, lambda c, i: c.post("/robots", json=_named(model_doc, f"{tag}-{i}")))
    after += [s.client.post("/robots", json=_named(model_doc, f"{tag}-seq-{i}")) for i in range(8)]
    codes = [r.status_code for r in after]
    assert codes == [201] * len(after), f"writes after the window: {codes}"
    return len(after)


def test_sqlite_read_only_window_leaves_no_read_only_connection_and_health_agrees(tmp_path, model_doc):
    """Two windows: the first before any write (every write connection is opened during it, read-only), the second
    with the pool full of connections opened writable."""
    db = tmp_path / "calib.db"
    s = _Server(f"sqlite:///{db}", tmp_path / "server.log", CALIB_EMBEDDED_WORKERS="0", CALIB_PARSE_PROCESSES="0",
                CALIB_PLAN_PROCESSES="0")
    stored = 0
    try:
        _read_only_window(s, db, model_doc, "ro1")
        stored += _writes_all_stored(s, model_doc, "after1")  # before: 503 "read-only" while /health said 200
        _read_only_window(s, db, model_doc, "ro2")  # before: the connections opened before it wrote on
        stored += _writes_all_stored(s, model_doc, "after2")
    finally:
        s.stop()
    assert sqlite_count(db, "robots") == stored  # nothing answered 201 is missing, nothing refused is stored


@pytest.fixture
def pg_database():
    """A database of its own on the CALIB_TEST_POSTGRES_URL server (it is set read-only for a while), migrated."""
    if not PG_URL:
        pytest.skip("CALIB_TEST_POSTGRES_URL is not set (.ci/run starts a PostgreSQL server)")
    pytest.importorskip("psycopg")
    from sqlalchemy import create_engine, text

    from service.cli import db_upgrade

    name = f"calib_ro_{uuid.uuid4().hex[:12]}"
    admin = create_engine(PG_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.execute(text(f'CREATE DATABASE "{name}"'))
    u = urlsplit(PG_URL)
    url = urlunsplit((u.scheme, u.netloc, "/" + name, u.query, ""))
    db_upgrade(url)

    def read_only(on: bool) -> None:
        with admin.connect() as c:
            c.execute(text(f'ALTER DATABASE "{name}" SET default_transaction_read_only = {"on" if on else "off"}'))

    try:
        yield url, read_only
    finally:
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def test_postgres_read_only_window_is_503_and_leaves_nothing_behind(tmp_path, model_doc, pg_database):
    url, read_only = pg_database
    s = Server(url, tmp_path / "server.log", CALIB_EMBEDDED_WORKERS="0", CALIB_PARSE_PROCESSES="0",
               CALIB_PLAN_PROCESSES="0", CALIB_ROUTE_THREADS=WRITES)  # the window's burst opens new sessions
    try:
        post = lambda c, i: c.post("/robots", json=_named(model_doc, f"before-{i}"))  # noqa: E731
        assert all(r.status_code == 201 for r in _burst(s.url, 4, post))
        stored = 4
        read_only(True)  # sessions opened from now on are read-only; those in the pool are not
        try:
            during = _burst(s.url, WRITES, lambda c, i: c.post("/robots", json=_named(model_doc, f"ro-{i}")))
            codes = [r.status_code for r in during]
            assert 500 not in codes and set(codes) <= {201, 503}, codes
            for r in during:
                if r.status_code == 503:
                    assert "read-only" in assert_problem(r, 503)["detail"] and int(r.headers["retry-after"]) > 0
            stored += codes.count(201)
            if 503 in codes:  # read-only sessions were met: /health asks a new session of its own, and says so
                h = _health(s.client)
                assert h.status_code == 503 and "read-only" in h.json()["detail"], h.text
        finally:
            read_only(False)
        assert _health(s.client).status_code == 200
        after = _burst(s.url, WRITES, lambda c, i: c.post("/robots", json=_named(model_doc, f"after-{i}")))
        after += [s.client.post("/robots", json=_named(model_doc, f"after-seq-{i}")) for i in range(8)]
        codes = [r.status_code for r in after]
        assert codes == [201] * len(after), f"writes after the window: {codes}"
        stored += len(after)
        r = s.client.get("/robots", params={"limit": 1000})
        assert int(r.headers["x-total-count"]) == stored
    finally:
        s.stop()
