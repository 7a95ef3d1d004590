"""The calibration report and its plots, over real HTTP against `calib serve`: the answer lists the plots and
the error table, every plot is a PNG, the page renders in headless Chromium with no broken image and holds the
figures of the calibration JSON."""
from __future__ import annotations

import html as htmllib
import re
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from calib_core import Twin, parse_model, write_measurements
from calib_core.robots import spray7
from calib_world import World
from calib_world.scenarios import hide
from service.report.figures import sig, std_str
from service.report.html import render

from .conftest import wait_for

CHROMIUM = Path("/usr/bin/chromium")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_job(server, ms_id: str, mode: str) -> dict:
    r = server.client.post("/jobs", json={"measurement_set_id": ms_id, "model": mode})
    assert r.status_code == 202, r.text

    def done():
        j = server.client.get(r.headers["location"]).json()
        return j if j["status"] in ("succeeded", "failed") else None

    j = wait_for(done, 90, f"the {mode} job")
    assert j["status"] == "succeeded", j
    return server.client.get(f"/calibrations/{j['calibration_id']}").json()


@pytest.fixture(scope="module")
def calibrations(server) -> dict:
    """An auto calibration of a twin hiding a backlash (one finding with a plot) and a geometric one."""
    model = parse_model(spray7())
    world = World(model, 3)
    info = hide(world, "hard_backlash", 5.0, np.random.default_rng(3), payload_kg=[0, 10, 20])
    meas = world.measure(info["q"], payload_kg=[0, 10, 20])
    rid = server.client.post("/robots", json=spray7()).json()["id"]
    r = server.client.post(f"/robots/{rid}/measurements",
                           files={"file": ("b.csv", write_measurements(meas, model))})
    assert r.status_code == 201, r.text
    ms = r.json()["id"]
    return {"auto": run_job(server, ms, "auto"), "geometric": run_job(server, ms, "geometric")}


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG_MAGIC
    return struct.unpack(">II", data[16:24])


def test_answer_lists_plots_report_and_error_table(calibrations):
    a = calibrations["auto"]
    cid = a["id"]
    assert a["report_url"] == f"/calibrations/{cid}/report"
    names = [p["name"] for p in a["plots"]]
    assert names == ["errors", "distribution", "finding-1"]
    for p in a["plots"]:
        assert p["url"] == f"/calibrations/{cid}/plots/{p['name']}.png" and p["title"]
    f = a["diagnosis"]["findings"][0]
    assert f["kind"] == "backlash" and f["plot_url"] == f"/calibrations/{cid}/plots/finding-1.png"
    # the error table is the answer's own numbers (one source): the final row is `metrics`, the geometric row
    # the diagnosis, the held-out mean / max the stored per-pose distances
    geo, fin = a["accuracy"]["models"]
    assert fin["final"] and fin["model"] == "geometric + backlash"
    assert fin["holdout"]["rms_mm"] == a["metrics"]["holdout_rms_mm"]
    assert fin["holdout"]["max_mm"] == a["metrics"]["holdout_max_mm"]
    assert fin["fit"] == {"mean_mm": a["metrics"]["mean_mm"], "rms_mm": a["metrics"]["rms_mm"],
                          "max_mm": a["metrics"]["max_mm"]}
    assert geo["holdout"]["rms_mm"] == a["diagnosis"]["geometric"]["holdout_rms_mm"]
    pp = a["diagnosis"]["per_pose"]
    per_pose = np.array(pp["geometric_holdout_mm"])[~np.array(pp["geometric_outlier"])]  # outliers left out
    assert geo["holdout"]["mean_mm"] == pytest.approx(per_pose.mean(), rel=1e-12)
    assert geo["holdout"]["max_mm"] == pytest.approx(per_pose.max(), rel=1e-12)
    assert np.sqrt(np.mean(per_pose**2)) == pytest.approx(geo["holdout"]["rms_mm"], rel=1e-9)
    assert a["accuracy"]["noise_floor_mm"] == a["diagnosis"]["noise_floor_mm"]
    assert "ISO 9283" in a["accuracy"]["note"]


def test_every_listed_plot_is_a_png(server, calibrations):
    for p in calibrations["auto"]["plots"]:
        r = server.client.get(p["url"])
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == "image/png"
        w, h = png_size(r.content)
        assert w >= 600 and h >= 300, (p["name"], w, h)
        assert server.client.get(p["url"]).content == r.content  # cached, identical


def test_unknown_plot_and_calibration_are_problems(server, calibrations):
    cid = calibrations["auto"]["id"]
    r = server.client.get(f"/calibrations/{cid}/plots/finding-9.png")
    assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json")
    assert "errors, distribution, finding-1" in r.json()["detail"]
    for path in ("/calibrations/nope/report", "/calibrations/nope/plots/errors.png"):
        r = server.client.get(path)
        assert r.status_code == 404 and r.headers["content-type"].startswith("application/problem+json"), path


def test_geometric_calibration_has_a_report_without_plots(server, calibrations):
    g = calibrations["geometric"]
    assert g["plots"] == [] and g["accuracy"]["models"][0]["model"] == "geometric"
    r = server.client.get(g["report_url"])
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "<img" not in r.text and f"{g['metrics']['holdout_rms_mm']:.3f}" in r.text
    assert server.client.get(f"/calibrations/{g['id']}/plots/errors.png").status_code == 404


def test_inline_report_is_one_self_contained_file(server, calibrations):
    a = calibrations["auto"]
    r = server.client.get(a["report_url"], params={"inline": "true"})
    assert r.status_code == 200
    srcs = re.findall(r'<img src="([^"]+)"', r.text)
    assert len(srcs) == len(a["plots"]) and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert "@media print" in r.text


def test_predict_takes_temperature_and_timestamp(server, calibrations):
    cid = calibrations["auto"]["id"]
    q = [[2000.0, 10.0, -20.0, 30.0, -40.0, 2000.0, 15.0]] * 2
    r = server.client.post(f"/calibrations/{cid}/predict", json={
        "joints": q, "temperature": [20.0, 25.0], "timestamp": "2026-11-03T08:00:19+00:00"})
    assert r.status_code == 200, r.text
    for bad in ({"temperature": [20.0]}, {"timestamp": ["yesterday", "2026-11-03T08:00:19Z"]}):
        r = server.client.post(f"/calibrations/{cid}/predict", json={"joints": q, **bad})
        assert r.status_code == 422 and r.json()["errors"], r.text


def text_of(dom: str) -> str:
    body = re.sub(r"<(script|style)\b.*?</\1>", " ", dom, flags=re.S)
    return re.sub(r"\s+", " ", htmllib.unescape(re.sub(r"<[^>]+>", " ", body)))


def chromium(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                           "--no-first-run", "--disable-background-networking", "--disable-component-update",
                           "--disable-sync", "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'chromium'}",
                           *args], capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is not installed (.ci/run installs it)")
def test_report_renders_in_headless_chromium(server, calibrations, tmp_path):
    a = calibrations["auto"]
    r = chromium(tmp_path, "--virtual-time-budget=15000", "--dump-dom", server.url + a["report_url"])
    assert r.returncode == 0, r.stderr[-3000:]
    dom = r.stdout
    body = re.search(r"<body([^>]*)>", dom)
    assert body, dom[:2000]
    attrs = dict(re.findall(r'(data-images-[a-z]+)="([^"]*)"', body.group(1)))
    # every <img> loaded (complete, naturalWidth > 0): one per plot of the answer, none broken
    assert attrs.get("data-images-checked") == "yes", (attrs, r.stderr[-2000:])
    assert attrs["data-images-total"] == str(len(a["plots"])) == "3"
    assert attrs["data-images-broken"] == "0"
    srcs = re.findall(r'<img src="([^"]+)"', dom)
    assert sorted(srcs) == sorted(f"plots/{p['name']}.png" for p in a["plots"])

    text = text_of(dom)
    d, m = a["diagnosis"], a["metrics"]
    figures = {"held-out RMS": m["holdout_rms_mm"], "held-out max": m["holdout_max_mm"], "fit RMS": m["rms_mm"],
               "noise floor": d["noise_floor_mm"],
               "geometric held-out RMS": d["geometric"]["holdout_rms_mm"], "geometric fit RMS": d["geometric"]["rms_mm"]}
    for row in a["accuracy"]["models"]:  # the fit's RMS; held-out mean, RMS, max over every pose and without outliers
        figures[f"{row['model']} fit RMS"] = row["fit"]["rms_mm"]
        for part in ("holdout", "holdout_all"):
            for k, v in row[part].items():
                if k.endswith("_mm") and v is not None:
                    figures[f"{row['model']} {part} {k}"] = v
    for f in d["findings"]:
        figures[f"{f['kind']} before"] = f["holdout_rms_before_mm"]
        figures[f"{f['kind']} after"] = f["holdout_rms_after_mm"]
    for what, v in figures.items():
        assert f"{v:.3f}" in text, (what, f"{v:.3f}")
    for f in d["findings"]:
        assert f"{f['gain_pct']:.1f} %" in text
        for clause in f["evidence"].split("; ")[1:]:  # the evidence, a sentence per clause
            assert clause[1:] in text, clause
    for p in a["parameters"]:
        assert re.search(rf"\b{re.escape(p['name'])} {re.escape(sig(p['value'], p['std']))} ", text), p
    assert "ISO 9283" in text and d["explanation"] in text
    # the observability of the measured pose set, as the answer's identifiability reports it
    ident = a["identifiability"]
    assert f"measured poses {m['n_poses']} " in text
    assert f"parameters identifiable from them {ident['rank']} of {ident['n_parameters']} " in text
    assert f"condition number (column-normalised Jacobian) {ident['condition_number']:.3g} " in text
    assert f"observability index O1 {ident['observability_index']:.3g} " in text
    worst = max((p for p in a["parameters"] if not p.get("effect") and p.get("std") is not None and p["unit"] == "mm"),
                key=lambda p: p["std"])
    assert re.search(rf"Least well determined .*? {re.escape(worst['name'])} {std_str(worst['std'])} mm ", text), worst
    for r in ident["redundant"]:
        assert f"{r['name']} {', '.join(r['confounded_with'])}" in text


def test_report_shows_what_the_measured_poses_do_not_observe():
    """A pose set that leaves parameters unidentified and a joint frozen: the report says which, and ranks the
    least well determined parameters by their std, per unit (effects' parameters left out)."""
    answer = {"id": "c0ffee", "model": ["geometric"], "metrics": {"n_poses": 12, "holdout_rms_mm": 0.5},
              "parameters": [{"name": "J2.a", "value": 250.0, "std": 0.30, "unit": "mm"},
                             {"name": "J3.a", "value": 900.0, "std": 0.05, "unit": "mm"},
                             {"name": "J4.d", "value": 10.0, "std": 0.20, "unit": "mm"},
                             {"name": "J5.a", "value": 0.0, "std": 0.10, "unit": "mm"},
                             {"name": "J6.a", "value": 0.0, "std": 0.01, "unit": "mm"},
                             {"name": "J2.theta", "value": 0.1, "std": 0.004, "unit": "deg"},
                             {"name": "J4.compliance", "value": 1e-6, "std": 9.0, "unit": "mm",
                              "effect": "joint_compliance"}],
              "identifiability": {"rank": 20, "n_parameters": 44, "condition_number": 1234.5,
                                  "observability_index": 0.00123, "complete": False,
                                  "unidentifiable": ["J6.alpha", "J7.alpha"], "frozen_joints": ["J7"],
                                  "redundant": [{"name": "J1.a", "confounded_with": ["base.x"]}], "nonfunctional": []}}
    text = text_of(render(answer))
    assert "identifies all the model's structure can no " in text
    assert "condition number (column-normalised Jacobian) 1.23e+03 " in text
    assert "observability index O1 0.00123 " in text
    assert ("Not observed. 2 parameters the model's structure can identify but these poses cannot: J6.alpha, "
            "J7.alpha (left at nominal); joints that never moved: J7.") in text
    least = text[text.index("Least well determined"):text.index("Not identifiable")]
    assert re.findall(r"(J\d\.\w+) [\d.]+ (mm|deg)", least) == [
        ("J2.a", "mm"), ("J4.d", "mm"), ("J5.a", "mm"), ("J2.theta", "deg")]  # largest 3 per unit, by std
    assert "J4.compliance" not in least and "J1.a base.x" in text


def test_report_of_a_search_stopped_at_its_time_budget_says_so():
    """The headline tile and a caution say the search stopped, as the verdict and the JSON do; a complete answer
    carries neither."""
    verdict = "search stopped at its time budget: 1 cause(s) confirmed so far, not a complete answer"
    finding = {"kind": "joint_compliance", "joints": ["J3"], "holdout_rms_before_mm": 0.4,
               "holdout_rms_after_mm": 0.1, "gain_pct": 75.0, "evidence": "..."}
    answer = {"id": "c0ffee", "model": ["geometric", "joint_compliance"], "metrics": {"n_poses": 150},
              "parameters": [], "diagnosis": {"verdict": verdict, "search_complete": False, "findings": [finding],
                                              "noise_floor_mm": 0.08, "explanation": "..."}}
    text = text_of(render(answer))
    assert "Cause so far: joint compliance on J3 (the search stopped at its time budget)." in text
    assert f"Caution. {verdict[0].upper() + verdict[1:]}: causes not reached were never tested" in text
    answer["diagnosis"].update(verdict="causes found", search_complete=True)
    assert "time budget" not in text_of(render(answer))


def test_steps_in_the_session_send_the_reader_to_its_log():
    """A step of T1 that the data cannot tell from a step of the target (the Motoman's answer): what to do next is to
    check the session's log there, not to measure poses that tell them apart 'as a cause fitted on a load identified
    from the data' (the report said so, twice, with one line per step that read the same); a step without a
    look-alike is sent to the log too; a pair the plan service cannot rebuild is said so, with the identified load
    only where that is why."""
    step = lambda what, at, lo, hi: {  # noqa: E731
        "kind": "unexplained", "joints": [what] if what not in ("robot", "target") else [],
        "form": f"step[{what} @ {at}]", "holdout_rms_before_mm": 0.6, "holdout_rms_after_mm": 0.5, "gain_pct": 16.0,
        "evidence": "...", "follows": [{"what": "measurement order (sequence)",
                                        "detail": f"in time order between {lo} and {hi} (sequence {at})"}]}
    t1 = {**step("T1", 87, 85, 89), "indistinguishable_from": [
        {"kind": "unexplained", "joints": [], "form": "step[target @ 108.5]", "plannable": False}]}
    t1b = {**step("T1", 13.5, 12, 15), "indistinguishable_from": [
        {"kind": "unexplained", "joints": [], "form": "step[target @ 10.5]", "plannable": False}]}
    play = {"kind": "backlash", "joints": ["L1"], "form": "backlash[L1]", "holdout_rms_before_mm": 2.2,
            "holdout_rms_after_mm": 1.6, "gain_pct": 29.0, "evidence": "...", "indistinguishable_from": [
                {"kind": "cyclic_joint_error", "joints": ["L1"], "harmonic": 2, "form": "cyclic_joint_error[L1, h2]",
                 "plannable": False}]}
    answer = {"id": "c0ffee", "model": ["geometric", "unexplained"], "metrics": {"n_poses": 410}, "parameters": [],
              "diagnosis": {"verdict": "causes found", "search_complete": True, "noise_floor_mm": 0.04,
                            "explanation": "...", "findings": [play, t1, step("robot", 168, 167, 169), t1b]}}
    text = text_of(render(answer))
    start = text.index("What to do next")
    nxt = text[start:text.index("Evidence", start)]
    assert "Check the session's log in time order between 85 and 89 (sequence 87): T1's zero stepped there, or the " \
           "target on its flange (at 108.5)" in nxt, nxt
    assert "between 12 and 15 (sequence 13.5): T1's zero stepped there, or the target on its flange (at 10.5)" in nxt
    assert "between 167 and 169 (sequence 168): the robot against the tracker stepped there" in nxt, nxt
    assert "tell a step in the session" not in nxt and "measurement order (sequence); until then" not in nxt, nxt
    assert "apart from cyclic joint error on L1 (harmonic 2) (chosen by hand: the plan service cannot rebuild this " \
           "pair from the stored calibration)" in nxt, nxt  # not for an identified load: not said so
    assert nxt.count("Check the session's log") == 3 and nxt.count("Use the calibrated model") == 1, nxt


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is not installed (.ci/run installs it)")
def test_report_prints_to_pdf(server, calibrations, tmp_path):
    pdf = tmp_path / "report.pdf"
    r = chromium(tmp_path, "--virtual-time-budget=15000", "--no-pdf-header-footer", f"--print-to-pdf={pdf}",
                 server.url + calibrations["auto"]["report_url"])
    assert r.returncode == 0 and pdf.exists(), r.stderr[-3000:]
    data = pdf.read_bytes()
    assert data[:5] == b"%PDF-" and len(re.findall(rb"/Type\s*/Page\b", data)) >= 2


# --- issue 10: plots drawn once by the worker and stored; `$` in names; 10k poses ---------------------------

import sqlite3  # noqa: E402
import time  # noqa: E402

from service.report import plots as report_plots  # noqa: E402


def stored_plots(server, cal_id: str) -> dict[str, bytes]:
    with sqlite3.connect(server.db_path) as c:
        return dict(c.execute("SELECT name, png FROM calibration_plots WHERE calibration_id = ?", (cal_id,)))


def test_plots_are_drawn_by_the_worker_and_stored(server, calibrations):
    """The job stored its PNGs with its result; the API serves those bytes (it draws nothing)."""
    a, g = calibrations["auto"], calibrations["geometric"]
    stored = stored_plots(server, a["id"])
    assert sorted(stored) == sorted(p["name"] for p in a["plots"]) == ["distribution", "errors", "finding-1"]
    for p in a["plots"]:
        assert stored[p["name"]][:8] == PNG_MAGIC
        assert server.client.get(p["url"]).content == stored[p["name"]]
    assert stored_plots(server, g["id"]) == {}  # a geometric calibration has no plots
    r = server.client.get(a["report_url"], params={"inline": "true"})
    srcs = re.findall(r'<img src="data:image/png;base64,([^"]+)"', r.text)
    import base64
    assert sorted(base64.b64decode(s) for s in srcs) == sorted(stored.values())


def test_dollar_in_joint_names_and_a_fast_inline_report(server):
    """Joint names with `$` (matplotlib mathtext) used to break the plots and the inline report with a 500;
    the inline report of a small calibration is served from stored plots, well under a second."""
    doc = spray7()
    names = {j["name"]: f"{j['name']}$^$" for j in doc["joints"]}
    for j in doc["joints"]:
        j["name"] = names[j["name"]]
    model = parse_model(doc)
    world = World(model, 3)
    info = hide(world, "hard_backlash", 5.0, np.random.default_rng(3), payload_kg=[0, 10, 20])
    meas = world.measure(info["q"], payload_kg=[0, 10, 20])
    rid = server.client.post("/robots", json=doc).json()["id"]
    r = server.client.post(f"/robots/{rid}/measurements", files={"file": ("d.csv", write_measurements(meas, model))})
    assert r.status_code == 201, r.text
    a = run_job(server, r.json()["id"], "auto")
    assert a["plots"] and any("$^$" in " ".join(f.get("joints") or []) for f in a["diagnosis"]["findings"]), a["plots"]
    for p in a["plots"]:
        r = server.client.get(p["url"])
        assert r.status_code == 200 and r.content[:8] == PNG_MAGIC, (p["name"], r.text[:300])
    t0 = time.perf_counter()
    r = server.client.get(a["report_url"], params={"inline": "true"})
    took = time.perf_counter() - t0
    assert r.status_code == 200, r.text[:500]
    assert len(re.findall(r'<img src="data:image/png;base64,', r.text)) == len(a["plots"])
    assert "$^$" in r.text
    assert took < 1.0, took


def test_plots_of_10k_poses_are_aggregated():
    """At 10k poses the error plot is not one bar per pose (20 s a plot before), and every plot draws fast."""
    rng = np.random.default_rng(0)
    n = 10_000
    answer = {"model": ["geometric", "backlash"], "diagnosis": {
        "noise_floor_mm": 0.05,
        "per_pose": {"geometric_holdout_mm": rng.random(n).tolist(),
                     "final_holdout_mm": (0.2 * rng.random(n)).tolist()},
        "findings": [{"kind": "backlash", "joints": ["J5"], "plot": {
            "x": rng.uniform(-1, 1, n).tolist(), "residual_mm": rng.normal(0, 0.1, n).tolist(),
            "fit_mm": rng.normal(0, 0.1, n).tolist(), "x_label": "load torque on J5 (N m)"}}]}}
    fig = report_plots.figure(answer, "errors")
    assert sum(len(ax.patches) for ax in fig.axes) < 1000
    for name in report_plots.names(answer):
        t0 = time.perf_counter()
        png = report_plots.png(answer, name)
        assert png[:8] == PNG_MAGIC and time.perf_counter() - t0 < 5.0, name
