"""Plans off the API's route threads (issue 33), over real HTTP against `calib serve`: with one plan process
(CALIB_PLAN_PROCESSES=1, one more plan waiting: CALIB_PLAN_ROOM=1, the default is 4) and a 1 s bound
(CALIB_PLAN_TIMEOUT_S), six concurrent 1000-pose plans on the spray robot (about 2.5 s each on one core) leave
GET /health and GET /robots fast, the plans beyond the waiting room get 503 with Retry-After at once, the ones that
run are stopped at the bound with a 503 naming it, and the next plan is answered. Four route threads
(CALIB_ROUTE_THREADS, the default; it was eight): more plans than route threads is what starved GET /robots (16 plans,
48 s); before, all six ran on the route threads, GET /robots waited seconds behind them and every plan was answered 200
after 15-30 s. The default waiting room serving a handful of plans: test_hardening_rooms.py."""
from __future__ import annotations

import threading
import time

import httpx
import pytest

from .conftest import Server, assert_problem

N_PLANS = 6
BIG = {"n_poses": 1000, "purpose": "geometric", "seed": 1}
GET_BOUND_S = 1.0


@pytest.fixture(scope="module")
def plan_server(tmp_path_factory):
    d = tmp_path_factory.mktemp("plansrv")
    s = Server(f"sqlite:///{d / 'calib.db'}", d / "server.log", CALIB_PLAN_PROCESSES=1, CALIB_PLAN_TIMEOUT_S=1,
               CALIB_PLAN_ROOM=1, CALIB_ROUTE_THREADS=4)
    yield s
    s.stop()


def test_plans_are_bounded_and_routes_stay_fast(plan_server, model_doc):
    s = plan_server
    r = s.client.post("/robots", json=model_doc)
    assert r.status_code == 201, r.text
    rid = r.json()["id"]
    answers: list[tuple[httpx.Response, float]] = []

    def fire():
        t0 = time.monotonic()
        with httpx.Client(base_url=s.url, timeout=60) as c:
            resp = c.post(f"/robots/{rid}/plan", json=BIG)
        answers.append((resp, time.monotonic() - t0))

    threads = [threading.Thread(target=fire) for _ in range(N_PLANS)]
    for t in threads:
        t.start()
    time.sleep(0.2)  # the plans are in
    gets = []
    with httpx.Client(base_url=s.url, timeout=60) as c:
        while any(t.is_alive() for t in threads):
            for path in ("/health", "/robots"):
                t0 = time.monotonic()
                assert c.get(path).status_code == 200
                gets.append((path, time.monotonic() - t0))
            time.sleep(0.05)
    for t in threads:
        t.join()
    slowest = max(gets, key=lambda g: g[1])
    print(f"{len(gets)} GETs while {N_PLANS} plans ran, slowest {slowest[0]} {slowest[1]:.3f} s; plans: "
          + ", ".join(f"{a.status_code} {dt:.2f} s" for a, dt in answers))
    assert len(gets) >= 4 and slowest[1] < GET_BOUND_S, gets  # (a) the routes answer meanwhile

    bodies = [(assert_problem(a, 503), a, dt) for a, dt in answers]  # (b, c) no plan queued unboundedly, none ran
    assert all(int(a.headers["Retry-After"]) > 0 for _, a, _ in bodies)
    busy = [dt for b, _, dt in bodies if "every plan process is busy" in b["detail"]]
    stopped = [(b, dt) for b, _, dt in bodies if "CALIB_PLAN_TIMEOUT_S" in b["detail"]]
    assert 1 <= len(stopped) <= 2 and "1 s" in stopped[0][0]["detail"], bodies
    # refused at once: before the plan that ran met its 1 s bound (an absolute 1 s here failed once at 1.06 s with
    # two diagnoses running beside the suite: a loaded machine slows the refusal and the stopped plan alike)
    assert len(busy) >= N_PLANS - 2 and max(busy) < min(dt for _, dt in stopped), (busy, stopped)

    r = s.client.post(f"/robots/{rid}/plan", json={"n_poses": 3, "seed": 2})  # (c) a new process plans the next
    assert r.status_code == 200, r.text
    assert len(r.json()["joints"]) == 3
