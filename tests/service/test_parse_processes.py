"""Uploads' CSVs are checked in parse processes (CALIB_PARSE_PROCESSES, issue 10: parsing held half of the API
process's GIL under the red team's load): the same answer as parsing in the API process, problem for problem, and
a parse process that dies in a call costs that upload a 503, never the server (one that died idle costs nothing)."""
from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from calib_core.model import parse_model
from service.measurements.service import PARSERS, checked_upload
from service.problems import ProblemError

from .test_corpus import BROKEN_CSV


@pytest.fixture(scope="module")
def model(model_doc):
    return parse_model(model_doc)


@pytest.fixture(scope="module", autouse=True)
def parsers():
    PARSERS.warm(1)
    yield
    PARSERS.shutdown()


def _outcome(raw, model, processes, **kw):
    try:
        return "ok", checked_upload(raw, model, processes=processes, **kw)
    except ProblemError as exc:
        return "problem", (exc.status, exc.detail, exc.kind, exc.errors, exc.extra)


@pytest.mark.parametrize("case", sorted(BROKEN_CSV))
def test_a_parse_process_refuses_what_the_api_process_refuses(model, csv_text, case):
    raw = BROKEN_CSV[case](csv_text)
    here, there = _outcome(raw, model, 0), _outcome(raw, model, 1)
    assert here[0] == "problem" and there == here


def test_a_good_upload_gives_the_same_summary_in_a_parse_process(model, csv_text):
    lines = csv_text.splitlines()
    f = lines[5].split(",")
    f[2] = "80.5"  # J2 beyond its limits: accepted with limits="warn", the extent reported
    lines[5] = ",".join(f)
    raw = ("\n".join(lines) + "\n").encode()
    here, there = _outcome(raw, model, 0, limits="warn"), _outcome(raw, model, 1, limits="warn")
    assert here[0] == "ok" and there == here
    assert there[1]["n_poses"] == 150 and there[1]["columns"][:2] == ["point", "J1"]
    assert there[1]["out_of_limits"][0]["joint"] == "J2" and there[1]["out_of_limits"][0]["first_rows"] == [6]


def test_a_parse_process_that_died_idle_costs_nothing_and_is_replaced(model, csv_text):
    """Killed between calls (its fork server killed, the OOM killer): the next upload is not sent to it, a fresh
    process checks it (before a20f489: a 503 "could not start")."""
    checked_upload(csv_text.encode(), model, processes=1)  # the lanes are configured
    pids = PARSERS.small.pids()  # a 150-pose CSV is checked in the small uploads' lane
    assert pids and os.getpid() not in pids
    os.kill(pids[0], signal.SIGKILL)
    time.sleep(0.2)
    assert checked_upload(csv_text.encode(), model, processes=1)["n_poses"] == 150
    assert PARSERS.small.pids() != pids


def _cpu_ticks(pid: int) -> int:
    """The CPU time process pid has used, in clock ticks (user + system)."""
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def test_a_parse_process_that_died_in_a_call_costs_that_upload_a_503_and_is_replaced(model, csv_text):
    """Killed while it checks an upload: that upload is a 503 saying nothing was stored (its check may have been
    what killed it: it is not sent again), the next one is checked by a fresh process."""
    head = csv_text.splitlines()[0]
    row = ",".join(["x"] * len(head.split(",")))
    slow = (head + "\n" + "\n".join([row] * (2_000_000 // (len(row) + 1))) + "\n").encode()  # each cell an error
    lane = PARSERS.lane(slow, 1, 120.0)  # the large uploads' lane, one process
    busy = lane.pids()
    idle = _cpu_ticks(busy[0])
    out: list = []
    t = threading.Thread(target=lambda: out.append(_outcome(slow, model, 1)))
    t.start()
    deadline = time.monotonic() + 30
    while _cpu_ticks(busy[0]) < idle + 10 and time.monotonic() < deadline:  # checking it (a second or two)
        time.sleep(0.01)
    os.kill(busy[0], signal.SIGKILL)
    t.join(60)
    assert out and out[0][0] == "problem" and out[0][1][0] == 503 and "nothing was stored" in out[0][1][1], out
    assert checked_upload(csv_text.encode(), model, processes=1)["n_poses"] == 150
    assert lane.pids() != busy
