"""`calib demo`: the whole story, end to end, over HTTP against a `calib serve` the demo starts itself.

Without data: the 7-DoF spray-painting robot of Wang et al. 2023 as a digital twin in the independent simulated
world `calib_world` (its own kinematics, statics and noise; true geometry and masses off the model's, a laser
tracker, one hidden physical cause drawn at random unless `--effect` names a world kind), 150 calibration poses
(the first 50 planned by `POST /robots/{id}/plan`, D-optimal for the geometry, the others random) and 100
validation poses; when the diagnosis lists look-alike causes a pose can split, 30 poses planned to split them are
measured, added and diagnosed again. With `--robot MODEL.json --data MEASUREMENTS.csv`: real measurements, 30 %
of the poses held out client-side for validation (a look-alike plan is shown, not measured). With `--robot
MODEL.json` alone: a twin of that robot in the same world (a drawn cause its joints cannot show is passed over).

The story is printed on stdout; the progress bar and the server's failures go to stderr.
"""
from __future__ import annotations

import json
import re
import secrets
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from calib_core.diagnosis import follows_what
from calib_core.identify import evaluate, identify
from calib_core.io import Measurements, write_measurements
from calib_core.model import LENGTH_TO_MM, RobotModel

from .cli import HIDDEN_KINDS
from .config import Settings
from .demo_campaign import (Campaign, _commands, _groups, _n_poses, _pose_fields, _unit, cause_name, counted,
                            errors_mm, from_files, read_model, simulated, spray7_model)
from .demo_client import Api, Server
from .demo_console import DemoError, ProgressBar, fmm, head, say, table
from .report.figures import step_title

N_PLAN = 50
"""Of the simulated campaign's N_CAL calibration poses, this many are planned by POST /robots/{id}/plan (D-optimal
for the geometry); the rest are random, the spread over the workspace the diagnosis compares causes on."""
REACH_MM = 1e-3
"""POST /calibrations/{id}/compensate's tolerance (calib_core.compensate's tol_mm): `reachable` means within it."""
N_SPLIT = 30
"""Poses planned (purpose `diagnosis`) to tell apart look-alike causes when the diagnosis lists some."""
JOB_QUEUE_S = 120.0
"""The demo waits for a job as long as the server's job time limit (CALIB_JOB_TIMEOUT_S) plus this, for the queue."""
EFFECTS = (*HIDDEN_KINDS, "none")
"""`--effect`: the world's kinds (calib_world.KINDS, checked by the tests) and none."""
# ----------------------------------------------------------------------------------------------- story

def run(args) -> int:
    import logging

    logging.getLogger("httpx").setLevel(logging.WARNING)  # the story is the output, not the requests
    settings = Settings.from_env()
    t_start = time.monotonic()
    seed = args.seed if args.seed is not None else (0 if args.data else secrets.randbelow(1_000_000))
    if args.data and not args.robot:
        print("calib demo: --data needs --robot (the model JSON the measurement CSV is of)", file=sys.stderr)
        return 2
    own = None  # a user's robot without data: a twin of it
    try:
        if args.data:
            camp = from_files(Path(args.robot), Path(args.data), seed, getattr(args, "instrument", None),
                              getattr(args, "limits", "reject"))
        else:  # measured after the plan step, on the server's planned poses
            from calib_world import KINDS

            if args.effect not in (None, "none", *KINDS):
                raise DemoError(f"unknown effect {args.effect!r}: use one of {', '.join(KINDS)} or none")
            camp = None
            own = read_model(Path(args.robot)) if args.robot else None
    except DemoError as exc:
        print(f"calib demo: {exc}", file=sys.stderr)
        return 2
    log = Path(tempfile.mkdtemp(prefix="calib-demo-")) / "server.log"
    try:
        return _story(args, settings, camp, seed, log, t_start, own)
    except DemoError as exc:
        print(f"\ncalib demo failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("\ncalib demo: interrupted", file=sys.stderr)
        return 130


class Chapters:
    """Numbered chapter headings (the story's chapters depend on the data and on what the service finds)."""

    def __init__(self):
        self.n = 0

    def __call__(self, title: str) -> None:
        self.n += 1
        head(f"{self.n}. {title}")


def _story(args, settings: Settings, camp: Campaign | None, seed: int, log: Path, t_start: float,
           own: tuple[dict, RobotModel] | None = None) -> int:
    if own is not None:
        model = own[1]
        say(f"calib demo: a digital twin of your robot {model.name} ({model.n_joints} joints, "
            f"{str(own[0].get('convention', 'mdh')).upper()}, {model.length_unit}/{model.angle_unit}), from "
            f"{args.robot}, in the independent simulated world.")
    elif camp is None:
        say("calib demo: the 7-DoF spray-painting robot of Wang et al. (Machines 2023, 11, 20): a 4 m rail, waist, "
            "two parallel pitch joints, forearm roll, a telescopic forearm (1700-2300 mm) and a wrist.")
    else:
        model = camp.model
        say(f"calib demo on real measurements: robot {model.name} ({model.n_joints} joints, "
            f"{str(camp.model_doc.get('convention', 'mdh')).upper()}, {model.length_unit}/{model.angle_unit}).")

    chapter = Chapters()
    chapter("The service")
    db = settings.database_url
    server = Server.start(db, log)
    api = Api(server.url, settings.api_token, settings.job_timeout_s + JOB_QUEUE_S)
    try:
        say(f"calib serve is running on {server.url} (database {_show_db(db)}; its log: {log}).", 3)
        return _chapters(args, api, server, camp, seed, t_start, chapter, own)
    finally:
        api.close()
        if api.refused:  # the story never asks what its own answers rule out: a refusal is a bug of the demo's
            print(f"calib demo: the service refused {len(api.refused)} of the demo's own calls: "
                  f"{'; '.join(api.refused[:10])}", file=sys.stderr, flush=True)
        if args.keep_serving:
            say("")
            say(f"The service keeps running on {server.url} (report, /docs); Ctrl-C stops it.")
            try:
                server.proc.wait()
            except KeyboardInterrupt:
                pass
        server.stop()


def _show_db(url: str) -> str:
    if url.startswith("sqlite:///"):
        path = url[len("sqlite:///"):]
        return f"SQLite file {Path(path).resolve()}" if path and path != ":memory:" else url
    try:
        from sqlalchemy.engine import make_url
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - only for display
        return url.split("@")[-1]


def _chapters(args, api: Api, server: Server, camp: Campaign | None, seed: int, t_start: float,
              chapter: Chapters, own: tuple[dict, RobotModel] | None = None) -> int:
    if camp is None:  # simulated: plan the poses first, then measure the twin there
        doc, model = own or spray7_model()
        chapter("Which poses to measure: POST /robots/{id}/plan")
        robot = api.call("POST", "/robots", (201,), json=doc).json()
        say(f"POST /robots -> robot {robot['id']}.", 3)
        planned = _plan_geometry(api, robot["id"], model, seed)
        camp = simulated(args.effect, seed, planned, own)
    else:
        model = camp.model
        robot = api.call("POST", "/robots", (201,), json=camp.model_doc).json()
    chapter("The measurement campaign")
    say(f"Data: {camp.source}.", 3)
    if camp.twin is not None:
        hidden = "one physical cause the model does not know, drawn at random" if not args.effect else (
            "no cause beyond the geometry" if args.effect == "none" else f"one physical cause the model does not "
                                                                         f"know (--effect {args.effect})")
        say(f"The twin hides {hidden}: it is revealed at the end (calib demo --seed {seed} repeats this run).", 3)
    if camp.n_planned:
        say(f"Calibration poses: {camp.cal.n_poses}, uploaded: the {camp.n_planned} planned poses, then "
            f"{camp.cal.n_poses - camp.n_planned} random ones within the joint limits (the spread over the "
            f"workspace the diagnosis compares causes on). Validation: {camp.validation}.", 3)
    else:
        say(f"Uploaded for calibration: {counted(camp.cal, brief=True)}. Validation: {camp.validation}.", 3)
    params = {"limits": getattr(args, "limits", "reject")}
    if getattr(args, "instrument", None):
        params["instrument"] = args.instrument
    ms = api.call("POST", f"/robots/{robot['id']}/measurements", (201,), params=params,
                  files={"file": ("campaign.csv", camp.csv_text.encode(), "text/csv")}).json()
    say(("" if camp.n_planned else f"POST /robots -> robot {robot['id']}; ") +
        f"POST /robots/{{id}}/measurements -> {ms['n_poses']} {_unit(camp.cal)} stored (set {ms['id']}).", 3)
    for o in ms.get("out_of_limits") or []:
        say(f"--limits warn: {o['joint']} outside its limits [{o['limits'][0]}, {o['limits'][1]}] {o['unit']} on "
            f"{o['rows']} row(s); the data span {o['min']:g} to {o['max']:g} {o['unit']}.", 3)

    chapter("The calibration: POST /jobs {\"model\": \"auto\"}")
    say("The service identifies the geometric model, then looks at what it still gets wrong, names the cause, "
        "adds it to the model and checks the gain on poses it did not fit (a geometric-only job runs alongside, "
        "for comparison).", 3)
    geo_loc = api.submit(ms["id"], "geometric")
    t0 = time.monotonic()
    auto_loc = api.submit(ms["id"], "auto")
    job = api.wait(auto_loc, ProgressBar())
    dt = time.monotonic() - t0
    geo_job = api.wait(geo_loc)
    cal_id = job["calibration_id"]
    cal = api.call("GET", f"/calibrations/{cal_id}").json()
    geo_cal = api.call("GET", f"/calibrations/{geo_job['calibration_id']}").json()
    say(f"Job {job['id']} succeeded in {dt:.1f} s: calibration {cal_id}, model {' + '.join(cal['model'])}, "
        f"{len(cal['parameters'])} parameters.", 3)
    _observed(cal)

    chapter(f"What the service found (errors on the {camp.val.n_poses} validation {_unit(camp.val)}"
            + ("" if _unit(camp.val) == "poses" else f", {_n_poses(camp.val)} poses") + ")")
    before = evaluate(identify(model, camp.cal, free=("base", "tool"), folds=1), camp.val)
    geo_pred = api.predict_mm(geo_cal["id"], model, camp.val)
    ext_pred = api.predict_mm(cal_id, model, camp.val)
    geo_val, ext_val = errors_mm(camp.val.points, geo_pred), errors_mm(camp.val.points, ext_pred)
    d = cal.get("diagnosis") or {}
    g = d.get("geometric") or {}
    floor = d.get("noise_floor_mm")
    rows = [("before calibration (nominal model, placed in the tracker frame)", before),
            (f"after the geometric model ({len(geo_cal['parameters'])} parameters)", geo_val)]
    findings = d.get("findings") or []
    if findings:
        rows.append((f"after the extended model ({' + '.join(cal['model'])})", ext_val))
    table(rows)
    print(flush=True)
    if floor is not None and g.get("holdout_rms_mm") is not None:
        ratio = g["holdout_rms_mm"] / floor
        verdict = ("the residual has structure a better model can remove" if ratio >= 1.25 else
                   "that is the noise floor: nothing is left to explain")
        say(f"What the geometric model still gets wrong: on the calibration poses (cross-validated) it leaves "
            f"{fmm(g['holdout_rms_mm'])} RMS, {ratio:.1f}x the noise floor of {fmm(floor)} "
            f"({d.get('noise_floor_basis') or 'instrument and repeatability'}): {verdict}.", 3)
    for k, f in enumerate(findings, 1):
        odd = ", not a physical size" if f.get("physical") is False else ""
        name = cause_name(f)
        if f.get("significant") is False and f["kind"] != "correction":
            name += " (confirmed when found; no size in the final model: the causes after it explain it)"
        if f["kind"] == "correction":
            odd = f", follows {f.get('follows')}"
            name = (f"a correction that follows {follows_what(f)} (not a physical cause: "
                    f"{f.get('bound') or 'its size is not physical'})")
        say(f"Cause {k} [{f['kind']}{odd}]: {name}. Held-out {fmm(f['holdout_rms_before_mm'])} -> "
            f"{fmm(f['holdout_rms_after_mm'])}, {f['gain_pct']:.1f} % better.", 3)
        say(f"Evidence: {f['evidence']}", 5)
    if not findings:
        say("Named cause: none. " + (d.get("explanation", "").split(". ", 1)[-1] if d else ""), 3)
    for note in (d.get("notes") or []) if findings else []:  # without findings the explanation above carries them
        say(f"Note: {note.rstrip('.')}.", 3)
    gain = 100.0 * (geo_val["rms_mm"] - ext_val["rms_mm"]) / geo_val["rms_mm"]
    if findings:
        say(f"Gain of the extended model on the validation poses: {gain:.1f} % ({fmm(geo_val['rms_mm'])} -> "
            f"{fmm(ext_val['rms_mm'])} RMS; max {fmm(geo_val['max_mm'])} -> {fmm(ext_val['max_mm'])}).", 3)
    else:
        say(f"The final model is the geometric one: {fmm(ext_val['rms_mm'])} RMS on the validation poses.", 3)
    if camp.val_truth is not None:
        geo_t, ext_t = errors_mm(camp.val_truth, geo_pred), errors_mm(camp.val_truth, ext_pred)
        noise = camp.twin.noise_rms_mm(camp.val.joints)
        final = (f"the geometric model {fmm(geo_t['rms_mm'])}, the extended one {fmm(ext_t['rms_mm'])}" if findings
                 else f"the final model {fmm(ext_t['rms_mm'])}")
        say(f"Against the twin's noise-free truth at the validation poses (what the tracker cannot show): {final} "
            f"RMS, for a measurement noise of {fmm(noise)} RMS.", 3)

    if any(f.get("indistinguishable_from") for f in findings):
        chapter("Telling look-alike causes apart" + (": POST /robots/{id}/plan {\"purpose\": \"diagnosis\"}" if any(
            _plannable(f, a) for f in findings for a in f.get("indistinguishable_from") or []) else ""))
        _split_lookalikes(api, robot["id"], ms["id"], camp, findings, seed)

    chapter("Compensation: POST /calibrations/{id}/compensate")
    _compensation(api, camp, cal_id, before)

    if camp.hidden is not None or (camp.twin is not None and args.effect == "none"):
        chapter("The twin's secret")
        _reveal(camp, findings)

    head("The report")
    report = Path(args.report).resolve()
    html = api.call("GET", f"/calibrations/{cal_id}/report", params={"inline": "true"}).text
    report.parent.mkdir(parents=True, exist_ok=True)
    report.write_text(html, encoding="utf-8")
    say(f"Saved to {report} (one file, plots included: open it in a browser, print it, mail it).", 3)
    live = server.url if args.keep_serving else "http://127.0.0.1:8000"
    say(f"Live at {live}/calibrations/{cal_id}/report" + ("" if args.keep_serving else " once `calib serve` runs") +
        f"; the same figures as JSON: GET /calibrations/{cal_id}.", 3)
    head("Explore the API")
    if args.keep_serving:
        say(f"Open {server.url}/docs to try every call on this run's service; later, `calib serve` (same database: "
            "this calibration is there) serves them at http://127.0.0.1:8000/docs.", 3)
    else:
        say("Start the service with `calib serve` (same database: this calibration is there) and open "
            "http://127.0.0.1:8000/docs to try every call; `calib demo --keep-serving` keeps this run's service "
            "up instead.", 3)
    say(f"Total demo time {time.monotonic() - t_start:.0f} s.", 3)
    return 0


def _observed(cal: dict) -> None:
    """One sentence on what the measured poses observe, from the calibration answer's `identifiability`."""
    ident = cal.get("identifiability") or {}
    if ident.get("condition_number") is None:
        return
    lacks = ident.get("unidentifiable") or []
    frozen = ident.get("frozen_joints") or []
    verdict = ("all the model's structure can identify" if ident.get("complete") else
               "not everything the model's structure can identify: " + "; ".join(
                   ([f"{len(lacks)} parameter(s) left at nominal ({', '.join(lacks)})"] if lacks else []) +
                   ([f"{', '.join(frozen)} never moved"] if frozen else [])))
    say(f"The measured poses observe the geometry with condition number {ident['condition_number']:.1f} and "
        f"observability index O1 {ident['observability_index']:.4f} ({ident['rank']} identifiable parameters: "
        f"{verdict}); the report lists the least well determined ones.", 3)


def _label(f: dict) -> str:
    """`kind[J1,J2]` of a finding or look-alike; `kind[J1, h2]` with a cyclic error's harmonic."""
    h = f.get("harmonic")
    return f"{f['kind']}[{','.join(f.get('joints') or [])}{'' if h is None else f', h{h}'}]"


def _nested(f: dict, a: dict) -> bool:
    """One is the other cause on more joints, or in another form on the same ones (calib_core.plan.nested, on the
    answer's labels); a cause on no joint (the robot against the tracker, the target) is not a joint's on fewer."""
    x, y = set(f.get("joints") or []), set(a.get("joints") or [])
    return (f["kind"] == a["kind"] and f.get("harmonic") == a.get("harmonic") and bool(x) == bool(y)
            and (x <= y or y <= x))


def _nesting(f: dict, a: dict) -> str:
    """How a nested pair reads: the cause on more joints is the other on more joints; on the same joints, another
    form of it. (It read "unexplained[] is unexplained[T1] on more joints" for a step of the target beside one of
    T1, a cause on no joint.)"""
    x, y = set(f.get("joints") or []), set(a.get("joints") or [])
    if x == y:
        return f"{_label(a)} is {_label(f)} in another form"
    small, big = (f, a) if x < y else (a, f)
    return f"{_label(big)} is {_label(small)} on more joints"


def _steps(f: dict, a: dict) -> bool:
    """Both a step in the session (service.report.figures.step_title): poses measured after it are after both."""
    return bool(step_title(f) and step_title(a))


def _plannable(f: dict, a: dict) -> bool:
    """Whether the answer says a diagnosis plan can split the finding from this look-alike (`plannable`, set by
    calib_core.pipeline with calib_core.plan.plannable; an answer without it: unless nested), and they are not two
    steps in the session (_steps)."""
    return not _nested(f, a) and not _steps(f, a) and a.get("plannable", True) is not False


def _together(findings: list[dict], a: str, b: str) -> bool:
    """Whether one finding still names both labels, as itself or as a look-alike."""
    return any({a, b} <= {_label(f), *map(_label, f.get("indistinguishable_from") or [])} for f in findings)


def _split_lookalikes(api: Api, robot_id: str, ms_id: str, camp: Campaign, findings: list[dict], seed: int) -> None:
    """Plan N_SPLIT poses that tell the listed look-alikes apart; on the twin, measure them, add them to the
    campaign as a new set, run `auto` on it and tell whether each pair is still listed."""
    # two forms of one look-alike (on the model's masses, on an identified load) read the same here: one pair
    pairs = list({(_label(f), _label(a), *((f.get("form"), a.get("form")) if _steps(f, a) else ())): (f, a)
                  for f in findings for a in f.get("indistinguishable_from") or []}.values())
    said = [f"{f['form']} ~ {a['form']}" if _steps(f, a) else f"{_label(f)} ~ {_label(a)}" for f, a in pairs]
    say(f"The diagnosis lists causes these poses cannot tell apart: {'; '.join(said)}.", 3)
    steps = [(f, a) for f, a in pairs if _steps(f, a)]
    nested = [(f, a) for f, a in pairs if _nested(f, a) and not _steps(f, a)]
    if nested:
        say(f"{'; '.join(_nesting(f, a) for f, a in nested)}: the richer form fits whatever the other fits, so no "
            "pose can split them; the diagnosis names the one it found.", 3)
    if steps:
        said = "; ".join(f"{f['form']} ~ {a['form']}" for f, a in steps)
        say(f"{said}: steps in the session's order, which no pose measured from now on can tell apart (such a pose "
            "comes after both); the cell's log of that session can (a joint re-homed, the target re-seated).", 3)
    unplanned = [(f, a) for f, a in pairs if not _nested(f, a) and not _steps(f, a) and not _plannable(f, a)]
    if unplanned:
        said = "; ".join(f"{_label(f)} ~ {a.get('form') or _label(a)}" for f, a in unplanned)
        why = (": a cause fitted on a load identified from this set's data is not among the plan's candidates"
               if all("identified load" in (a.get("form") or "") for _, a in unplanned) else "")
        say(f"No pose plan can be asked for {said}: the answer marks the look-alike not `plannable` (the plan "
            f"service cannot rebuild it from the stored calibration{why}).", 3)
    planned = [(f, a) for f, a in pairs if _plannable(f, a)]
    if not planned:
        return
    say("The service plans the poses that best separate " + ("the others" if len(planned) < len(pairs) else "them") +
        " (T-optimal: the largest expected held-out difference between the rivals).", 3)
    body = {"n_poses": N_SPLIT, "purpose": "diagnosis", "measurement_set_id": ms_id, "seed": seed}
    t0 = time.monotonic()
    r = api.c.post(f"/robots/{robot_id}/plan", json=body)
    dt = time.monotonic() - t0
    if r.status_code != 200:  # e.g. only nested look-alikes: no pose can split them
        detail = r.json().get("detail", r.text[:300]) if r.headers.get("content-type", "").endswith("json") else r.text
        say(f"POST /robots/{{id}}/plan answered {r.status_code}: {detail}", 3)
        return
    p = r.json()
    rivals = p["observability"]["rivals"]
    say(f"POST /robots/{{id}}/plan {json.dumps(body)} -> {len(p['joints'])} poses in {dt:.1f} s. Expected "
        "separation (chi-square units: how much worse the wrong model fits):", 3)
    for rv in rivals:
        verdict = "expected to split" if rv["expected_to_split"] else "may not split"
        say(f"{rv['found']} vs {rv['look_alike']}: {rv['planned']['separation_chi2']:.0f} with the planned poses, "
            f"{rv['random']['separation_chi2']:.0f} with as many random ones; the diagnosis needs about "
            f"{rv['separation_needed_chi2']:.0f} -> {verdict}.", 5)
    if camp.twin is None:
        say("Measure these poses (`calib plan --purpose diagnosis` writes them as CSV for the robot program), add them "
            "to the set and run the `auto` job again.", 3)
        return
    model = camp.model
    cal = camp.cal
    new = camp.twin.measure(planned_rows(model, p["joints"]), payload_kg=p.get("payload_kg"),
                            temperature=cal.temperature is not None, start_time=float(cal.timestamp[-1]) + 20.0)
    cat = lambda a, b: None if a is None else np.concatenate([a, b])  # noqa: E731
    both = Measurements(np.vstack([cal.joints, new.joints]), np.vstack([cal.points, new.points]),
                        list(cal.point_ids) + [f"S{i + 1:03d}" for i in range(new.n_poses)],
                        cat(cal.timestamp, new.timestamp), cat(cal.temperature, new.temperature),
                        cat(cal.payload, new.payload))
    ms = api.call("POST", f"/robots/{robot_id}/measurements", (201,),
                  files={"file": ("campaign+split.csv", write_measurements(both, model).encode(), "text/csv")}).json()
    say(f"The twin is measured at the {new.n_poses} planned poses; the campaign with them uploaded as set {ms['id']} "
        f"({ms['n_poses']} poses) and diagnosed again:", 3)
    job = api.wait(api.submit(ms["id"], "auto"), ProgressBar())
    again = api.call("GET", f"/calibrations/{job['calibration_id']}").json()
    after = (again.get("diagnosis") or {}).get("findings") or []
    named = "; ".join(_label(f) + "".join(f" ~ {_label(a)}" for a in f.get("indistinguishable_from") or [])
                      for f in after) or "none"
    say(f"Calibration {again['id']}: {named}.", 3)
    for f, a in planned:
        still = _together(after, _label(f), _label(a))
        say(f"{_label(f)} vs {_label(a)}: {'still listed as look-alikes' if still else 'told apart'}.", 5)
    say("The rest of the story stays with the first calibration (the report, the compensation).", 3)


def planned_rows(model: RobotModel, joints) -> np.ndarray:
    """A plan answer's `joints` (model units, actuated joints) as row values (N, n) in internal units."""
    q = np.asarray(joints, float) * model.joint_scale()[model.actuated]
    return model.expand_joints(q)


def _plan_geometry(api: Api, robot_id: str, model: RobotModel, seed: int) -> np.ndarray:
    """POST /robots/{id}/plan for N_PLAN geometric poses; tells how they compare with random ones; returns their
    rows (internal units)."""
    body = {"n_poses": N_PLAN, "purpose": "geometric", "seed": seed}
    t0 = time.monotonic()
    p = api.call("POST", f"/robots/{robot_id}/plan", json=body).json()
    dt = time.monotonic() - t0
    o = p["observability"]
    g = o["geometry"]
    dist = np.linalg.norm(o["tracker_mm"]) / 1000.0
    loads = f", with load variety on {', '.join(o['loaded_joints'])}" if o.get("loaded_joints") else ""
    say(f"POST /robots/{{id}}/plan {json.dumps(body)} -> {len(p['joints'])} poses in {dt:.1f} s, chosen among the "
        f"{o['visible_candidates']} of {o['candidates']} candidate poses within the joint limits whose target faces "
        f"the tracker (assumed {dist:.1f} m from the robot base, incidence at most {o['max_incidence_deg']:g} deg): "
        f"D-optimal, the most information on the {g['n_parameters']} identifiable geometric parameters{loads}.", 3)
    rows = [(f"the {N_PLAN} planned poses", g["planned"]), (f"{N_PLAN} random poses the tracker sees", g["random"])]
    w = max(len(label) for label, _ in rows) + 2
    for label, v in rows:
        print(f"   {label + ':':<{w}} condition number {v['condition_number']:6.1f}, observability index O1 "
              f"{v['observability_index']:.4f}", flush=True)
    if g.get("information_gain_per_parameter") is not None:
        say(f"Information per parameter: {g['information_gain_per_parameter']:.2f}x that of the random poses "
            f"(the planned set's parameter uncertainty is {1 / np.sqrt(g['information_gain_per_parameter']):.2f}x "
            f"the random set's, geometric mean). The twin is measured at the planned poses below.", 3)
    return planned_rows(model, p["joints"])


def _compensation(api: Api, camp: Campaign, cal_id: str, before: dict) -> None:
    model = camp.model
    js, ls = model.joint_scale(), LENGTH_TO_MM[model.length_unit]
    if camp.twin is not None:
        # targets: where the program (nominal model in the tracker frame) believes the validation poses put the tool
        nominal = identify(model, camp.cal, free=("base", "tool"), folds=1)
        seeds = camp.val.joints
        targets_mm = nominal.predict(seeds)
    else:
        seeds, targets_mm = camp.val.joints, camp.val.points
    val = camp.val
    joints, resid = np.empty_like(seeds), np.full(len(seeds), np.nan)
    reached, reasons, notes = np.zeros(len(seeds), bool), [None] * len(seeds), []
    for rows in _groups(val, by_payload=True):
        body = {"targets": (targets_mm[rows] / ls).tolist(), "seed_joints": _commands(model, seeds[rows]).tolist(),
                **_pose_fields(model, val, rows)}
        if val.payload is not None:
            body["payload"] = float(val.payload[rows[0]])
        r = api.c.post(f"/calibrations/{cal_id}/compensate", json=body)
        if r.status_code != 200:
            say(f"compensation: the service answered {r.status_code}: {r.text[:300]}", 3)
            return
        out = r.json()
        joints[rows] = model.expand_joints(np.asarray(out["joints"], float) * js[model.actuated])
        resid[rows] = [np.nan if v is None else v for v in out.get("residual_mm", [])]
        reached[rows] = out["reachable"]
        for i, why in zip(rows, out["reason"]):
            reasons[i] = why
        notes += [_told(rows, n) for n in out.get("notes") or []]
    n_ok = int(reached.sum())
    if camp.twin is None:
        say(f"{len(joints)} targets (the held-out measured points, their measured joints as seeds): the calibrated "
            f"model reaches {n_ok} of them (the answer's `reachable`: within {REACH_MM:g} mm; largest model "
            f"residual {np.nanmax(resid):.4f} mm). Their real accuracy needs a re-measurement of the robot at the "
            "compensated joints.", 3)
        _unreached(reached, reasons, resid)
        _notes(notes)
        return
    twin = camp.twin
    as_programmed = twin.measure(seeds).points  # the robot at the program's joints
    compensated = twin.measure(joints).points  # the robot at the service's joints
    e0, e1 = errors_mm(as_programmed, targets_mm), errors_mm(compensated, targets_mm)
    say(f"{len(joints)} targets: where the robot program, using the nominal model, believes the validation poses "
        f"put the tool. Measured on the twin:", 3)
    table([("at the program's joints (uncompensated)", e0), ("at the compensated joints from the service", e1)])
    say(f"The calibrated model reaches {n_ok} of {len(joints)} targets (the answer's `reachable`: within "
        f"{REACH_MM:g} mm; largest model residual {np.nanmax(resid):.4f} mm); what is left is the robot's "
        "repeatability and the tracker noise.", 3)
    _unreached(reached, reasons, resid)
    _notes(notes)


def _why(reason: str | None) -> str:
    """A compensation reason without its target's own figures, to count targets by it: 'not reachable: 0.310 mm
    left after 30 iterations (needs A2 beyond its limit)' -> 'needs A2 beyond its limit'; 'still converging: raise
    max_iter above 30 (about 41 at this rate)' -> 'still converging: raise max_iter above 30'."""
    if not reason:
        return "no reason given"
    m = re.fullmatch(r"not reachable: [\d.]+ mm left after \d+ iterations \((.*)\)", reason)
    return re.sub(r" \(about \d+ at this rate\)$", "", m.group(1) if m else reason)


def _told(rows: np.ndarray, note: str) -> str:
    """A note of the request for validation targets `rows`, its "rows 0, 2 ..." (the request's own) told as the
    targets they are (numbered from 1): the demo sends one request per setup and payload."""
    def targets(m: re.Match) -> str:
        idx = [int(rows[int(k)]) + 1 for k in m.group(1).split(", ")]
        return f"target{'s' * (len(idx) > 1 or bool(m.group(2)))} {', '.join(map(str, idx))}{m.group(2) or ''}"

    return re.sub(r"\brows? (\d+(?:, \d+)*)( \.\.\.)?", targets, note)


def _notes(notes: list[str]) -> None:
    """What the compensation answers said beside the commands (a gear play's flank in doubt, a drift held at its
    edge, a load not given), each once."""
    for n in dict.fromkeys(notes):
        say(f"The answer notes: {n}", 3)


def _unreached(reached: np.ndarray, reasons: list, resid: np.ndarray) -> None:
    """The targets not reached, counted by the answer's `reason` (largest residual of each)."""
    miss = np.flatnonzero(~reached)
    if not len(miss):
        return
    by: dict[str, list[int]] = {}
    for i in miss:
        by.setdefault(_why(reasons[i]), []).append(i)
    say(f"Not reached: {len(miss)} target(s), by the answer's `reason`:", 3)
    for why, idx in sorted(by.items(), key=lambda kv: -len(kv[1])):
        left = resid[idx]
        most = f"; up to {np.nanmax(left):.3f} mm left" if np.isfinite(left).any() else ""
        rates = [int(m.group(1)) for i in idx if (m := re.search(r"\(about (\d+) at this rate\)", reasons[i] or ""))]
        slowest = f" (the slowest about {max(rates)} at its rate)" if rates else ""
        say(f"{len(idx)} x {why}{slowest}{most}", 5)


def _reveal(camp: Campaign, findings: list[dict]) -> None:
    named = [(f["kind"], tuple(f.get("joints") or ())) for f in findings]
    if camp.hidden is None:
        verdict = "no finding: correct" if not named else f"found {named}: a false alarm"
        say(f"The twin hid nothing beyond the geometry -> {verdict}.", 3)
        return
    h = camp.hidden
    kind, expected, joints = h["kind"], h["expected"], tuple(h["joints"])
    label = kind.replace("_", " ") + (f" on {', '.join(joints)}" if joints else "")
    params = ", ".join(f"{k}={_show(v)}" for k, v in h["parameters"].items() if k not in ("cause", "world_kind"))
    say(f"The twin hid {label}, sized {h['size']:.1f}x the noise -> {_verdict(expected, joints, findings)}.", 3)
    say(f"The cause: {h['parameters']['cause']}({params}); its part no geometric parameter can absorb is "
        f"{fmm(h['unabsorbed_rms_mm'])} RMS (of {fmm(h['total_rms_mm'])}) against a noise of "
        f"{fmm(h['noise_rms_mm'])}.", 5)
    if expected == "unexplained":
        say("No named cause of the diagnosis has this shape: a correct diagnosis reports it as unexplained "
            "structure, not as a named cause.", 5)
    else:
        say(f"A correct diagnosis names it {expected.replace('_', ' ')}.", 5)


def _verdict(expected: str, joints: tuple, findings: list[dict]) -> str:
    """Whether the findings name the hidden cause (its kind on its joints, or it listed as a look-alike)."""
    def same(f):
        return f["kind"] == expected and (expected == "unexplained" or set(joints) == set(f.get("joints") or ()))
    named = [(f["kind"], tuple(f.get("joints") or ())) for f in findings]
    if any(same(f) for f in findings):
        return "named correctly"
    if any(same(a) for f in findings for a in f.get("indistinguishable_from") or ()):
        return "named among look-alikes this pose set cannot tell apart"
    return "not named" if not named else f"named differently: {named}"


def _show(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "(" + ", ".join(_show(x) for x in v) + ")"
    return str(v)
