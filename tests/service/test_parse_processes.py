"""Uploads' CSVs are checked in parse processes (CALIB_PARSE_PROCESSES, issue 10: parsing held half of the API
process's GIL under the red team's load): the same answer as parsing in the API process, problem for problem, and
a parse process that dies costs its upload a 503, never the server."""
from __future__ import annotations

import os
import signal

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


def test_a_parse_process_that_died_costs_one_503_and_is_replaced(model, csv_text):
    checked_upload(csv_text.encode(), model, processes=1)  # the lanes are configured
    pids = PARSERS.small.pids()  # a 150-pose CSV is checked in the small uploads' lane
    assert pids and os.getpid() not in pids
    os.kill(pids[0], signal.SIGKILL)
    with pytest.raises(ProblemError) as exc:
        for _ in range(50):  # the pool notices the death at its next submit at the latest
            checked_upload(csv_text.encode(), model, processes=1)
    assert exc.value.status == 503 and exc.value.headers.get("Retry-After")
    assert "nothing was stored" in exc.value.detail
    assert checked_upload(csv_text.encode(), model, processes=1)["n_poses"] == 150  # a fresh process
    assert PARSERS.small.pids() != pids
