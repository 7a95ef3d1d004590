"""What `calib demo` prints on its console, checked against what it could get wrong (issue 31): it never asks the
API what its own answer rules out (the Motoman's plan to split look-alikes the plan service then refused with a
422), its progress never goes back and runs on the wall clock (78 % -> 36 %, job time standing still in the queue),
every target compensation does not reach is counted with the answer's reason (the iiwa: 209 of 238, no reason),
and its counts say what they count (poses, rows, markers, virtual points; the noise model's real source)."""
from __future__ import annotations

import inspect
import io
import json
import re

import numpy as np
import pytest

from calib_core import datasets
from calib_core.compensate import compensate
from calib_core.io import parse_measurements, write_measurements
from calib_core.model import parse_model
from calib_core.orientation import with_orientation
from calib_core.twin import Twin
from service import demo

from .conftest import Server
from .test_demo import flat

BAR = re.compile(r"^\s*\[[#.]+\]\s+(\d+) %\s+(\d+\.\d) s\s", re.M)


def progress(err: str) -> list[tuple[int, float]]:
    """(percent, wall seconds) of every progress line the demo printed on stderr."""
    return [(int(p), float(t)) for p, t in BAR.findall(err)]


# ----------------------------------------------------------------------------------------------- progress

class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_progress_never_goes_back_and_shows_wall_time():
    """A job's later stage can report less than an earlier one (the Motoman's bar went 78 % -> 36 %); the worker's
    message carries the job's run time, which stood still while the job was queued: the bar shows the largest
    fraction so far and the wall time since it started, and a log gets a line at least every LOG_EVERY_S."""
    out, clock = io.StringIO(), Clock()
    bar = demo.ProgressBar(out, clock=clock)
    steps = [(0.0, "queued"), (0.0, "queued"), (0.14, "identifying the geometric model (0.5 s)"),
             (0.78, "revisiting each finding (29.8 s)"), (0.36, "testing 32 candidate causes (31.0 s)"),
             (0.36, "testing 32 candidate causes (40.0 s)"), (0.36, "testing 32 candidate causes (80.0 s)"),
             (0.9, "drawing the plots (90.0 s)"), (1.0, "done")]
    for k, (f, m) in enumerate(steps):
        clock.t += 20.0 if k else 0.0
        bar.update(f, m)
    bar.close()
    shown = progress(out.getvalue())
    assert [p for p, _ in shown] == sorted(p for p, _ in shown) and shown[-1][0] == 100, out.getvalue()
    assert [t for _, t in shown] == sorted(t for _, t in shown) and shown[-1][1] == 160.0, out.getvalue()
    assert "(80.0 s)" not in out.getvalue() and "78 %" in out.getvalue()  # the demo's clock, not the job's
    # a step lasting 60 s prints again after LOG_EVERY_S (30 s): the log shows the demo alive
    assert out.getvalue().count("testing 32 candidate causes") == 2, out.getvalue()


# ----------------------------------------------------------------------------------------------- compensation

def test_every_target_not_reached_is_counted_by_its_reason(tmp_path, capsys, seed):
    """Targets 3 m off the workspace among reachable ones: the answer gives a reason exactly where `reachable` is
    false, and the demo counts the targets it does not reach by that reason."""
    from calib_core.robots import arm6

    doc = arm6()
    model = parse_model(doc)
    rng = np.random.default_rng(seed)
    meas = Twin(model, seed=int(rng.integers(1 << 30))).measure(n=60)
    (tmp_path / "model.json").write_text(json.dumps(doc))
    (tmp_path / "data.csv").write_text(write_measurements(meas, model))
    camp = demo.from_files(tmp_path / "model.json", tmp_path / "data.csv", int(rng.integers(1000)))
    far = rng.choice(camp.val.n_poses, 4, replace=False)
    camp.val.points[far] += 3000.0 * np.array([1.0, 0.0, 0.0])
    server = Server(f"sqlite:///{tmp_path / 'calib.db'}", tmp_path / "server.log")
    api = demo.Api(server.url, None)
    try:
        robot = api.call("POST", "/robots", (201,), json=camp.model_doc).json()
        ms = api.call("POST", f"/robots/{robot['id']}/measurements", (201,),
                      files={"file": ("cal.csv", camp.csv_text.encode(), "text/csv")}).json()
        cal_id = api.wait(api.submit(ms["id"], "geometric"))["calibration_id"]
        body = {"targets": camp.val.points.tolist(), "seed_joints": demo._commands(model, camp.val.joints).tolist()}
        answer = api.call("POST", f"/calibrations/{cal_id}/compensate", json=body).json()
        capsys.readouterr()
        demo._compensation(api, camp, cal_id, {})
        story = flat(capsys.readouterr().out)
    finally:
        api.close()
        server.stop()
    reachable, reason = np.array(answer["reachable"]), answer["reason"]
    assert all((why is None) == ok for ok, why in zip(reachable, reason)), answer
    assert not reachable[far].any() and reachable.sum() >= camp.val.n_poses - len(far) - 1, (seed, answer)
    missed = int((~reachable).sum())
    assert f"reaches {camp.val.n_poses - missed} of them (the answer's `reachable`: within 0.001 mm" in story, story
    assert f"Not reached: {missed} target(s), by the answer's `reason`:" in story, story
    counted = {}
    for why in (r for r, ok in zip(reason, reachable) if not ok):
        counted[demo._why(why)] = counted.get(demo._why(why), 0) + 1
    for why, n in counted.items():
        assert f"{n} x {why}" in story, (why, story)
    assert "no reason given" not in story
    assert not api.refused


def test_the_demo_states_the_compensation_tolerance_it_quotes():
    assert demo.REACH_MM == inspect.signature(compensate).parameters["tol_mm"].default


# ----------------------------------------------------------------------------------------------- counts

def test_counts_say_what_they_count():
    """Rows of two targets per pose are poses x markers (Agile Justin's "1000 measured poses" were 500 poses x 2
    markers); a set of one target per row is poses."""
    from tests.core.test_shared_motion import _campaign
    from tests.core.test_tree import torso_two_arms

    model = parse_model(torso_two_arms())
    meas, *_ = _campaign(model, np.random.default_rng(3), "none", 0.0)
    both = parse_measurements(write_measurements(meas, model), model)
    rows, poses = both.n_poses, demo._n_poses(both)
    assert poses < rows
    assert demo.counted(both).startswith(f"{rows} rows: {poses} poses x {rows // poses} targets (markers)")
    assert demo._unit(both) == "rows"
    one = both.subset(both.target == 0)
    assert demo.counted(one) == f"{one.n_poses} measured poses" and demo._unit(one) == "poses"


@pytest.mark.skipif(not (datasets.SHARED_DATASETS / datasets.IIWA_DIR).is_dir(), reason="the iiwa dataset is absent")
def test_6d_rows_are_counted_and_their_noise_named_as_it_is():
    """The iiwa's 554 uploaded 6-D rows were 2216 'measured poses' in the answer and their noise 'from the CSV's
    sigma column' (there is none: the optical preset): the demo says what the fit makes of each row, and the
    expanded rows name the preset as their noise source."""
    ds = datasets.iiwa7_payload(None, orientation=True, torques=True)
    model = parse_model(ds.model)
    meas = parse_measurements(ds.csv_text, model, instrument=ds.instrument)
    assert "sigma" not in ds.csv_text.splitlines()[0].split(",")
    said = demo.counted(meas)
    n = meas.n_poses
    assert said.startswith(f"{n} measured poses; each 6-D") and f"{4 * n} points in all" in said, said
    assert demo.counted(meas, brief=True) == f"{n} measured poses (6-D: {4 * n} points in the fit)"
    _, expanded = with_orientation(model, meas)
    assert expanded.n_poses == 4 * n
    source = expanded.noise_source()
    assert "sigma column" not in source and ds.instrument in source, source
    assert expanded.subset(np.arange(10)).noise_source() == source


# ----------------------------------------------------------------------------------------------- the Motoman
# one `calib demo` run on the Motoman, shared with test_demo.py (conftest.motoman_demo)

def test_the_motoman_demo_never_calls_what_its_answer_rules_out(motoman_demo):
    """No call of the demo is refused (every 4xx and 5xx it gets is listed on stderr); a plan to split look-alikes
    is announced and asked for only where the answer marks them `plannable`, and the plan service agrees with the
    answer: it plans when one is, and says there is nothing to split when none is."""
    out, err, tmp = motoman_demo
    story = flat(out)
    assert "refused" not in err and " answered 4" not in story and " answered 5" not in story, err + story
    cal_id = re.search(r"succeeded in [\d.]+ s: calibration ([0-9a-f-]{36}), model", story).group(1)
    server = Server(f"sqlite:///{tmp / 'calib.db'}", tmp / "check.log")
    try:
        cal = server.client.get(f"/calibrations/{cal_id}").json()
        findings = cal["diagnosis"]["findings"]
        looks = [(f, a) for f in findings for a in f.get("indistinguishable_from") or []]
        assert all(isinstance(a.get("plannable"), bool) for _, a in looks), looks
        planned = [(f, a) for f, a in looks if demo._plannable(f, a)]
        assert ('"purpose": "diagnosis"' in story) == bool(planned), story
        if looks:
            r = server.client.post(f"/robots/{cal['robot_id']}/plan", json={
                "n_poses": 10, "purpose": "diagnosis", "measurement_set_id": cal["measurement_set_id"], "seed": 0})
            assert r.status_code == (200 if planned else 422), r.text
        # the noise floor names its basis as the answer gives it
        d = cal["diagnosis"]
        assert flat(f"the noise floor of {d['noise_floor_mm']:.3f} mm ({d['noise_floor_basis']})") in story
    finally:
        server.stop()
    assert "(586 measured poses)" in story and "Uploaded for calibration: 410 measured poses. Validation" in story


def test_the_motoman_demo_progress_is_monotone_in_wall_time(motoman_demo):
    _, err, _ = motoman_demo
    shown = progress(err)
    assert len(shown) >= 3 and shown[-1][0] == 100, err
    bars, bar = [], []  # each bar (one per job the demo waits for with one) ends at 100 %
    for p, t in shown:
        bar.append((p, t))
        if p == 100:
            bars.append(bar)
            bar = []
    assert bars and not bar, err
    for got in bars:
        assert [p for p, _ in got] == sorted(p for p, _ in got), err
        assert [t for _, t in got] == sorted(t for _, t in got), err
    assert not re.search(r"\(\d+\.\d s\)$", err, re.M), err  # the job's own run time is not shown


def test_the_motoman_demo_compensation_gives_every_reason(motoman_demo):
    out, _, _ = motoman_demo
    story = flat(out)
    m = re.search(r"(\d+) targets \(the held-out .*? reaches (\d+) of them \(the answer's `reachable`", story)
    assert m, story
    missed = int(m.group(1)) - int(m.group(2))
    if missed:
        assert f"Not reached: {missed} target(s), by the answer's `reason`:" in story
        assert sum(int(n) for n in re.findall(r"(\d+) x ", story.split("Not reached:")[1].split("The report")[0])) \
            == missed
    else:
        assert "Not reached" not in story


def test_an_answers_notes_are_told_with_the_targets_they_name(capsys):
    """A compensation note names rows of its own request; the demo, which sends one request per setup and payload,
    tells them as the validation targets they are (numbered from 1), each note once."""
    rows = np.array([4, 9, 12, 30])
    note = "J4's gear play: at rows 0, 2 ... the load on J4 is near where it changes sign"
    told = demo._told(rows, note)
    assert told == "J4's gear play: at targets 5, 13 ... the load on J4 is near where it changes sign"
    assert demo._told(rows, "the load on row 3 gave") == "the load on target 31 gave"
    assert demo._told(rows, "every row gave none") == "every row gave none"
    demo._notes([told, told, "thermal drift: held"])
    out = capsys.readouterr().out
    assert out.count("The answer notes: J4's gear play") == 1 and "The answer notes: thermal drift" in out
