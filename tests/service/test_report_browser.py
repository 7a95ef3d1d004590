"""The report for a person, in a real browser (issue 31): headless Chromium opens the report of the Motoman's
`calib demo` run and of Agile Justin's `auto` job (real measured robots, served over HTTP), every plot loads, every
figure the page shows is the answer's (the same checks as test_report_consistency.py, on the DOM Chromium built),
and a full-page screenshot is saved in the tests' artefacts (`CALIB_TEST_ARTEFACTS`, default `.artefacts/`) for a
person to look at. The spray demo's report is opened in test_report.py."""
from __future__ import annotations

import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from calib_core import datasets
from calib_core.io import parse_measurements
from calib_core.model import parse_model

from .conftest import ROOT, Server
from .test_real_cells_api import _calibrated
from .test_report import CHROMIUM, chromium, text_of
from .test_report_consistency import check_report

pytestmark = [pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is not installed (.ci/run "
                                                                "installs it)"),
              pytest.mark.skipif(not datasets.available(), reason="the shared real datasets are not present")]

ARTEFACTS = Path(os.environ.get("CALIB_TEST_ARTEFACTS", ROOT / ".artefacts"))


def opened(tmp_path: Path, url: str, a: dict, name: str) -> str:
    """The report at `url` as Chromium renders it: its DOM, checked for loaded plots and the answer's figures; the
    full page saved as ARTEFACTS/<name>.png."""
    r = chromium(tmp_path, "--virtual-time-budget=15000", "--dump-dom", url)
    assert r.returncode == 0, r.stderr[-3000:]
    dom = r.stdout
    attrs = dict(re.findall(r'(data-images-[a-z]+)="([^"]*)"', re.search(r"<body([^>]*)>", dom).group(1)))
    assert attrs.get("data-images-checked") == "yes", (attrs, r.stderr[-2000:])
    assert attrs["data-images-total"] == str(len(a["plots"])) and attrs["data-images-broken"] == "0", attrs
    check_report(a, dom)  # what the browser shows is the answer, one number per figure
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    shot = ARTEFACTS / f"{name}.png"
    shot.unlink(missing_ok=True)
    r = chromium(tmp_path, "--virtual-time-budget=15000", "--hide-scrollbars", "--window-size=1280,7000",
                 f"--screenshot={shot}", url)
    assert r.returncode == 0 and shot.exists(), r.stderr[-3000:]
    png = shot.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and struct.unpack(">II", png[16:24]) == (1280, 7000)
    return dom


def test_the_motoman_report_in_chromium(motoman_demo, tmp_path):
    out, _, tmp = motoman_demo
    cal_id = re.search(r"succeeded in [\d.]+ s: calibration ([0-9a-f-]{36}), model", " ".join(out.split())).group(1)
    server = Server(f"sqlite:///{tmp / 'calib.db'}", tmp / "browser.log")
    try:
        a = server.client.get(f"/calibrations/{cal_id}").json()
        dom = opened(tmp_path, server.url + a["report_url"], a, "report-motoman")
    finally:
        server.stop()
    text = text_of(dom)
    assert "410 calibration poses counted" in text, text[:2000]
    assert len(a["diagnosis"]["findings"]) >= 2 and "in plain words" in text


def test_the_agile_justin_report_in_chromium(server, tmp_path, seed):
    """Agile Justin's right arm (a tree's branch, real measurements), on a drawn 120 of its 500 poses so the `auto`
    job takes seconds; its findings, corrections included, as the browser shows them."""
    ds = datasets.agile_justin("right")
    model = parse_model(ds.model)
    meas = parse_measurements(ds.csv_text, model)
    sub = meas.subset(np.sort(np.random.default_rng(seed).permutation(meas.n_poses)[:120]))
    job = _calibrated(server, ds.model, model, sub, "justin.csv", "auto", 240)
    a = server.client.get(f"/calibrations/{job['calibration_id']}").json()
    dom = opened(tmp_path, server.url + a["report_url"], a, "report-agile-justin")
    text = text_of(dom)
    assert f"{sub.n_poses} calibration poses counted" in text, (seed, text[:2000])
    for f in a["diagnosis"]["findings"]:
        if f["kind"] == "correction":  # said as one, never under a physical name
            assert "A correction that follows" in text, (seed, f)
