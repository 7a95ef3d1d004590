"""Issue 33, the lanes' waiting rooms sized for the red team's load, over real HTTP against `calib serve`
(service/lanes.py). The red team's load got 16 x 503: 14 hostile 1.8 MB CSVs refused "every CSV check process is busy
(1 running, 8 waiting)" while six 19 MB CSVs held the large-upload lane, whose room counted uploads, and 2 of its
50-pose plans refused "every plan process is busy" (one plan process, one plan waiting).

- Large uploads: the room counts bytes (CALIB_PARSE_ROOM_BYTES, default 8 uploads of CALIB_MAX_UPLOAD_BYTES). Here
  CALIB_MAX_UPLOAD_BYTES=4 MB (a 32 MB room) and one parse process stand for the red team's 20 MiB and one process.
  A slow 3.9 MB hostile CSV is checked (about 2 s), five 3.8 MB CSVs wait (cheap to refuse, but large: 19 MB), then six
  1.8 MB hostile CSVs come: each is admitted and answered 422. Before, the room held 8 uploads whatever their size and
  three of the six were 503. Then a byte flood: another slow CSV is checked while twelve 3.8 MB ones come at once
  (45.6 MB): those beyond the 32 MB room get 503 with Retry-After naming CALIB_PARSE_ROOM_BYTES, the others 422.
- Plans: the default room (CALIB_PLAN_ROOM, 4 per plan process; the plan waits on the event loop, holding no route
  thread): twelve concurrent 50-pose plans on one plan process, five are answered 200 (one running, four waiting) and
  the rest 503 with Retry-After at once. Before, two were answered (one running, one waiting).
"""
from __future__ import annotations

import threading
import time

import httpx
import pytest

from .conftest import Server, assert_problem

MAX_UPLOAD = 4_000_000
ROOM = 8 * MAX_UPLOAD  # CALIB_PARSE_ROOM_BYTES' default
BIG, MID = 3_800_000, 1_800_000


def _slow_csv(csv_text: str, nbytes: int) -> bytes:
    """Rows whose every value is "x": each cell an error, about 2 s to check at 3.9 MB (test_hardening_lanes.py)."""
    head = csv_text.splitlines()[0]
    row = ",".join(["x"] * len(head.split(",")))
    return (head + "\n" + "\n".join([row] * (nbytes // (len(row) + 1))) + "\n").encode()


def _header_csv(csv_text: str, nbytes: int) -> bytes:
    """A header of empty columns (the red team's hostile 1.8 MB CSV): refused in milliseconds, however large."""
    return b"," * nbytes + b"\n" + csv_text.splitlines()[1].encode() + b"\n"


@pytest.fixture(scope="module")
def room_server(tmp_path_factory, model_doc):
    d = tmp_path_factory.mktemp("roomsrv")
    s = Server(f"sqlite:///{d / 'calib.db'}", d / "server.log", CALIB_PARSE_PROCESSES=1,
               CALIB_MAX_UPLOAD_BYTES=MAX_UPLOAD, CALIB_PLAN_PROCESSES=1, CALIB_EMBEDDED_WORKERS="0",
               CALIB_COMPUTE_PROCESSES="0")
    r = s.client.post("/robots", json=model_doc)
    assert r.status_code == 201, r.text
    s.rid = r.json()["id"]
    yield s
    s.stop()


class _Fire:
    """Requests in threads of their own, each answer kept with its tag and how long it took."""

    def __init__(self, s: Server):
        self.s, self.threads, self.answers = s, [], []
        self.lock = threading.Lock()

    def post(self, tag: str, path: str, **kw) -> None:
        def go():
            t0 = time.monotonic()
            with httpx.Client(base_url=self.s.url, timeout=120) as c:
                r = c.post(path, **kw)
            with self.lock:
                self.answers.append((tag, r, time.monotonic() - t0))
        t = threading.Thread(target=go, daemon=True)
        t.start()
        self.threads.append(t)

    def upload(self, tag: str, data: bytes) -> None:
        self.post(tag, f"/robots/{self.s.rid}/measurements", files={"file": (f"{tag}.csv", data)})

    def join(self) -> list[tuple[str, httpx.Response, float]]:
        for t in self.threads:
            t.join(120)
        assert not any(t.is_alive() for t in self.threads), "a request was not answered"
        return self.answers

    def codes(self, prefix: str) -> list[int]:
        return sorted(r.status_code for tag, r, _ in self.answers if tag.startswith(prefix))


def test_a_mid_size_upload_is_admitted_behind_large_ones_and_a_byte_flood_is_refused(room_server, csv_text):
    s = room_server
    slow, big, mid = _slow_csv(csv_text, 3_900_000), _header_csv(csv_text, BIG), _header_csv(csv_text, MID)
    assert len(slow) < MAX_UPLOAD - 1000 and MID > 1024 * 1024  # all in the large-upload lane, none a 413

    # the red team's picture: large CSVs hold the lane, mid-size ones come
    f = _Fire(s)
    f.upload("slow", slow)
    time.sleep(0.4)  # it is being checked
    for i in range(5):
        f.upload(f"big{i}", big)  # 19 MB waiting of a 32 MB room; 6 uploads of the old room's 9
    time.sleep(0.4)
    for i in range(6):
        f.upload(f"mid{i}", mid)  # 10.8 MB more: within the room by bytes, beyond it by count
    f.join()
    print("before the flood: " + ", ".join(f"{tag} {r.status_code} {dt:.2f} s" for tag, r, dt in f.answers))
    assert f.codes("mid") == [422] * 6, [(t, r.text[:200]) for t, r, _ in f.answers if t.startswith("mid")]
    assert f.codes("big") == [422] * 5 and f.codes("slow") == [422]
    assert all(assert_problem(r, 422)["type"].endswith("invalid-csv") for _, r, _ in f.answers)

    # a byte flood: twelve large CSVs at once while a slow one is checked; at most 32 MB of them wait
    g = _Fire(s)
    g.upload("slow", slow)
    time.sleep(0.4)
    for i in range(12):
        g.upload(f"flood{i}", big)
    g.join()
    print("the flood: " + ", ".join(f"{tag} {r.status_code} {dt:.2f} s" for tag, r, dt in g.answers))
    assert g.codes("slow") == [422]
    codes = g.codes("flood")
    refused = [(r, dt) for tag, r, dt in g.answers if tag.startswith("flood") and r.status_code == 503]
    assert set(codes) <= {422, 503} and codes.count(422) <= ROOM // BIG + 1, codes
    assert len(refused) >= 2, codes  # 8 x 3.8 MB fit in the room, the rest do not
    admitted = [dt for tag, r, dt in g.answers if tag.startswith("flood") and r.status_code == 422]
    for r, dt in refused:
        body = assert_problem(r, 503)
        assert int(r.headers["Retry-After"]) > 0, r.headers
        assert "every CSV check process is busy" in body["detail"] and "CALIB_PARSE_ROOM_BYTES" in body["detail"], body
        assert dt < min(admitted), (dt, admitted)  # refused at once, not after waiting for the slow check

    r = s.client.post(f"/robots/{s.rid}/measurements", files={"file": ("good.csv", csv_text)})
    assert r.status_code == 201, r.text  # the lanes serve on


def test_a_handful_of_concurrent_plans_is_served_and_more_are_refused(room_server):
    s = room_server
    f = _Fire(s)
    for i in range(12):
        f.post(f"plan{i}", f"/robots/{s.rid}/plan", json={"n_poses": 50, "purpose": "geometric", "seed": i})
    f.join()
    print("plans: " + ", ".join(f"{r.status_code} {dt:.2f} s" for _, r, dt in sorted(f.answers, key=lambda a: a[2])))
    ok = [r for _, r, _ in f.answers if r.status_code == 200]
    busy = [(r, dt) for _, r, dt in f.answers if r.status_code != 200]
    assert len(ok) >= 5, [r.text[:200] for r, _ in busy]  # one running, four waiting; before: two
    assert all(len(r.json()["joints"]) == 50 for r in ok)
    assert len(busy) >= 3, len(ok)  # the room is still bounded
    first = min(dt for _, r, dt in f.answers if r.status_code == 200)
    for r, dt in busy:
        body = assert_problem(r, 503)
        assert "every plan process is busy" in body["detail"] and int(r.headers["Retry-After"]) > 0, body
        assert dt < first, (dt, first)  # refused at once, before the first plan is computed
