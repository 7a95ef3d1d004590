"""`calib demo`: the whole story, end to end, over HTTP against a `calib serve` the demo starts itself.

Without data: the 7-DoF spray-painting robot of Wang et al. 2023 as a digital twin in the independent simulated
world `calib_world` (its own kinematics, statics and noise; true geometry and masses off the model's, a laser
tracker, one hidden physical cause drawn at random unless `--effect` names a world kind), 150 calibration poses
(the first 50 planned by `POST /robots/{id}/plan`, D-optimal for the geometry, the others random) and 100
validation poses; when the diagnosis lists look-alike causes a pose can split, 30 poses planned to split them are
measured, added and diagnosed again. With `--robot MODEL.json --data MEASUREMENTS.csv`: real measurements, 30 %
of the poses held out client-side for validation (a look-alike plan is shown, not measured).

The story is printed on stdout; the progress bar and the server's failures go to stderr.
"""
from __future__ import annotations

import json
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import httpx
import numpy as np

from calib_core.diagnose import follows_what
from calib_core.identify import evaluate, identify
from calib_core.io import MeasurementError, Measurements, parse_measurements, write_measurements
from calib_core.model import LENGTH_TO_MM, ModelError, RobotModel, parse_model

from .cli import HIDDEN_KINDS
from .config import Settings
from .report.figures import finding_title

N_CAL, N_VAL = 150, 100
N_PLAN = 50
"""Of the simulated campaign's N_CAL calibration poses, this many are planned by POST /robots/{id}/plan (D-optimal
for the geometry); the rest are random, the spread over the workspace the diagnosis compares causes on."""
REACH_MM = 1e-3
"""POST /calibrations/{id}/compensate's tolerance (calib_core.compensate's tol_mm): `reachable` means within it."""
N_SPLIT = 30
"""Poses planned (purpose `diagnosis`) to tell apart look-alike causes when the diagnosis lists some."""
HOLDOUT_FRACTION = 0.3
JOB_QUEUE_S = 120.0
"""The demo waits for a job as long as the server's job time limit (CALIB_JOB_TIMEOUT_S) plus this, for the queue."""
SIZE_RANGE = (4.0, 10.0)
"""A drawn hidden cause's part no geometric parameter can absorb is this many times the noise RMS."""
EFFECTS = (*HIDDEN_KINDS, "none")
"""`--effect`: the world's kinds (calib_world.KINDS, checked by the tests) and none."""
WIDTH = 100


class DemoError(Exception):
    pass


# ----------------------------------------------------------------------------------------------- output

def say(text: str = "", indent: int = 0) -> None:
    pad = " " * indent
    print(textwrap.fill(text, WIDTH, initial_indent=pad, subsequent_indent=pad + "  ", break_on_hyphens=False,
                        break_long_words=False) if text else "", flush=True)


def head(text: str) -> None:
    print(f"\n{text}", flush=True)


def fmm(v: float) -> str:
    return f"{v:.3f} mm"


def table(rows: list[tuple[str, dict]]) -> None:
    """Aligned `label   0.123 mm RMS, max 0.456 mm` lines."""
    w = max(len(label) for label, _ in rows) + 2
    for label, e in rows:
        print(f"   {label + ':':<{w}} {e['rms_mm']:8.3f} mm RMS, max {e['max_mm']:8.3f} mm", flush=True)


def _stem(message: str | None) -> str:
    """A job message without the elapsed time the worker appends ('testing 33 causes (12.0 s)')."""
    return re.sub(r" \(\d+(\.\d+)? s\)$", "", message or "")


class ProgressBar:
    """A text bar on stderr: redrawn in place on a terminal, one line per new message otherwise (and one every
    LOG_EVERY_S while a step lasts, so a log shows the demo alive).

    The fraction shown never goes back (a job's later stage can report less than an earlier one: the Motoman's bar
    went 78 % -> 36 %), and the time shown is the wall time since the bar started, queue included, from the demo's
    own clock (the worker's message carries the job's run time, which stood still while the job was queued)."""

    LOG_EVERY_S = 30.0

    def __init__(self, stream=sys.stderr, width: int = 30, clock=time.monotonic):
        self.stream, self.width, self.clock = stream, width, clock
        self.tty = hasattr(stream, "isatty") and stream.isatty()
        self.last = None
        self.shown = 0.0  # the largest fraction shown so far
        self.t0 = clock()
        self.logged = self.t0

    def update(self, fraction: float, message: str | None) -> None:
        self.shown = max(self.shown, min(max(float(fraction or 0.0), 0.0), 1.0))
        n = int(round(self.shown * self.width))
        now = self.clock()
        stem = _stem(message)
        line = f"  [{'#' * n}{'.' * (self.width - n)}] {100 * self.shown:3.0f} %  {now - self.t0:5.1f} s  {stem}"
        if self.tty:
            self.stream.write("\r" + line[:WIDTH].ljust(WIDTH))
            self.stream.flush()
        elif stem != _stem(self.last) or now - self.logged >= self.LOG_EVERY_S:
            self.stream.write(line + "\n")  # a log gets a line per step (and per LOG_EVERY_S), not per poll
            self.stream.flush()
            self.logged = now
        self.last = message

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


# ----------------------------------------------------------------------------------------------- server

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Server:
    """`calib serve` in a subprocess (its own process group) on a free loopback port."""

    proc: subprocess.Popen
    url: str
    log: Path

    @classmethod
    def start(cls, database_url: str, log: Path, timeout: float = 60.0) -> "Server":
        port = free_port()
        env = {k: v for k, v in os.environ.items() if k not in ("CALIB_TEST_JOB_DELAY_S",)}
        env.update({"CALIB_DATABASE_URL": database_url, "CALIB_EMBEDDED_WORKERS": "1", "CALIB_POLL_SECONDS": "0.1",
                    "CALIB_HEARTBEAT_SECONDS": "0.5",  # the worker writes progress with its heartbeat
                    "PYTHONUNBUFFERED": "1"})
        fh = open(log, "ab")
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "--log-level", "WARNING", "serve",
                                 "--host", "127.0.0.1", "--port", str(port)], env=env, stdout=fh,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        fh.close()
        server = cls(proc, f"http://127.0.0.1:{port}", log)
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                raise DemoError(f"calib serve exited (status {proc.returncode}):\n{server.tail()}")
            try:
                if httpx.get(server.url + "/health", timeout=2).status_code == 200:
                    return server
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                server.stop()
                raise DemoError(f"calib serve did not answer within {timeout:.0f} s:\n{server.tail()}")
            time.sleep(0.1)

    def tail(self, n: int = 30) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def stop(self) -> None:
        stop_process_group(self.proc, 20)


def stop_process_group(proc: subprocess.Popen, grace_s: float) -> None:
    """SIGTERM a server started in its own process group, SIGKILL it if it outlives grace_s."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(5)
    except ProcessLookupError:
        pass


class Api:
    """The few REST calls of the story, with problem documents turned into DemoError."""

    def __init__(self, url: str, token: str | None, job_wait_s: float = 600.0):
        """job_wait_s: how long `wait` waits for a job; the server's own job time limit plus the queue's time
        (a client limit below the server's cut an hour-long job at 600 s)."""
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.refused: list[str] = []  # every call the service answered with a 4xx or 5xx: 'POST /path -> 422'
        self.c = httpx.Client(base_url=url, timeout=120, headers=headers, event_hooks={"response": [self._seen]})
        self.job_wait_s = job_wait_s

    def _seen(self, r: httpx.Response) -> None:
        if r.status_code >= 400:
            self.refused.append(f"{r.request.method} {r.request.url.path} -> {r.status_code}")

    def close(self) -> None:
        self.c.close()

    def call(self, method: str, path: str, expect: tuple[int, ...] = (200,), **kw) -> httpx.Response:
        r = self.c.request(method, path, **kw)
        if r.status_code not in expect:
            try:
                body = r.json()
                detail = body.get("detail") or body
                errors = body.get("errors") or []
            except ValueError:
                detail, errors = r.text[:500], []
            more = "".join(f"\n    {e}" for e in errors[:10])
            raise DemoError(f"{method} {path} answered {r.status_code}: {detail}{more}")
        return r

    def submit(self, ms_id: str, mode: str) -> str:
        return self.call("POST", "/jobs", (202,), json={"measurement_set_id": ms_id, "model": mode}).headers["location"]

    def wait(self, loc: str, bar: ProgressBar | None = None) -> dict:
        timeout = self.job_wait_s
        deadline = time.monotonic() + timeout
        try:
            while True:
                j = self.call("GET", loc).json()
                if bar is not None:
                    bar.update(j["progress"], j.get("message") or j["status"])
                if j["status"] == "succeeded":
                    return j
                if j["status"] == "failed":
                    raise DemoError(f"the {j['model']} job failed: {j.get('error')}")
                if time.monotonic() > deadline:
                    raise DemoError(f"the {j['model']} job did not finish within {timeout:.0f} s")
                time.sleep(0.2)
        finally:
            if bar is not None:
                bar.close()

    def predict_mm(self, cal_id: str, model: RobotModel, meas: Measurements) -> np.ndarray:
        """Positions (N, 3) in mm predicted by the service for the poses of `meas` (internal units), each with what
        its CSV row says (_pose_fields; one request per setup)."""
        out = np.empty((meas.n_poses, 3))
        for rows in _groups(meas):
            body = {"joints": _commands(model, meas.joints[rows]).tolist(), **_pose_fields(model, meas, rows)}
            if meas.payload is not None:
                body["payload"] = meas.payload[rows].tolist()
            if meas.temperature is not None:
                body["temperature"] = meas.temperature[rows].tolist()
            if meas.timestamp is not None:
                body["timestamp"] = [datetime.fromtimestamp(t, timezone.utc).isoformat() for t in meas.timestamp[rows]]
            r = self.call("POST", f"/calibrations/{cal_id}/predict", json=body).json()
            out[rows] = np.asarray(r["positions"], float) * LENGTH_TO_MM[model.length_unit]
        return out


def _commands(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """The actuated joints' values (N, n_act) in the model's units from row values (N, n) in internal units: what
    predict and compensate take (coupled rows follow, fixed rows do not move)."""
    return q[:, model.actuated] / model.joint_scale()[model.actuated]


def _groups(meas: Measurements, by_payload: bool = False) -> list[np.ndarray]:
    """The rows of each setup (and payload): a predict or compensate request takes one setup (and one payload)."""
    n = meas.n_poses
    keys = np.c_[np.zeros(n) if meas.setup is None else meas.setup, meas.payload_kg() if by_payload else np.zeros(n)]
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    return [np.flatnonzero(inv == g) for g in range(inv.max() + 1)]


def _pose_fields(model: RobotModel, meas: Measurements, rows: np.ndarray) -> dict:
    """A request's setup, each row's target and its measured torques, as the CSV gives them: without the target,
    every pose of a set with a marker per payload run (the iiwa) was placed at the first marker, and the demo
    reported 2.2 mm where the service's folds said 0.4 mm."""
    body: dict = {}
    if meas.setup is not None:
        body["setup"] = meas.setup_names[meas.setup[rows[0]]]
    if meas.target is not None:
        body["target"] = [model.target_names[t] for t in meas.target[rows]]
    if meas.tau is not None:
        tau = meas.tau[rows]
        body["tau"] = {f"tau_{model.joint_names[j]}": [None if np.isnan(v) else float(v) for v in tau[:, j]]
                       for j in range(model.n_joints) if not np.isnan(tau[:, j]).all()}
    return body


UNEXPLAINED = {"smooth_field": "corrected by a smooth joint-space field",
               "joint_driven_offsets": "corrected by offsets of the other joints following one joint",
               None: "not corrected: no correction helped on held-out poses"}


def cause_name(f: dict) -> str:
    """A finding's name in the story: a named cause on its joints, a step in time order, or structure outside the
    vocabulary with the correction the diagnosis kept (never a correction it did not make)."""
    if f["kind"] != "unexplained":
        return finding_title(f)
    if "correction" not in f:  # a step in time order (diagnose._finding of a SessionStep)
        return "a step in time order" + (f" of {', '.join(f['joints'])}" if f.get("joints") else "")
    said = UNEXPLAINED[f["correction"]]
    if f.get("weighted_as_pose_noise"):
        said = ("not corrected by a model, but what the targets of a pose share is weighted as noise of each pose"
                if f["correction"] is None else said + ", and what the targets of a pose share weighted as noise")
    return f"structure no named cause explains, {said}"


def errors_mm(points_mm: np.ndarray, predicted_mm: np.ndarray) -> dict:
    d = np.linalg.norm(points_mm - predicted_mm, axis=1)
    return {"n": int(len(d)), "rms_mm": float(np.sqrt(np.mean(d**2))), "mean_mm": float(d.mean()),
            "max_mm": float(d.max())}


# ----------------------------------------------------------------------------------------------- data

@dataclass
class Campaign:
    model_doc: dict
    model: RobotModel
    csv_text: str  # what is uploaded
    cal: Measurements  # the uploaded poses, parsed
    val: Measurements  # validation poses, never uploaded
    source: str  # one line: where the data comes from
    validation: str  # one line: what the validation poses are
    twin: object | None = None  # the simulated world (calib_world.World)
    hidden: dict | None = None  # calib_world.hide's description of the hidden cause
    val_truth: np.ndarray | None = None  # noise-free validation points of the simulated world
    n_total: int = 0
    n_planned: int = 0  # the first n_planned calibration poses are the geometric plan's


def spray7_model() -> tuple[dict, RobotModel]:
    """The simulated campaign's robot: its contract JSON and the parsed model."""
    from calib_core.robots import spray7

    doc = spray7()
    return doc, parse_model(doc)


def simulated(effect: str | None, seed: int, planned: np.ndarray | None = None) -> Campaign:
    """The twin's campaign: N_CAL calibration poses (the `planned` rows (k, n) first, internal units, then random
    ones), the hidden cause sized on them, and N_VAL random validation poses; all drawn from `seed`."""
    from calib_world import KINDS, World, hide

    doc, model = spray7_model()
    rng = np.random.default_rng((seed, 1))
    kind = effect or str(rng.choice(KINDS))
    if kind != "none" and kind not in KINDS:
        raise DemoError(f"unknown effect {kind!r}: use one of {', '.join(KINDS)} or none")
    world = World(model, seed)
    hidden = None
    planned = np.zeros((0, model.n_joints)) if planned is None else np.atleast_2d(np.asarray(planned, float))
    size = float(np.exp(rng.uniform(*np.log(SIZE_RANGE)))) if kind != "none" else None
    q = np.vstack([planned, world.sample_joints(N_CAL - len(planned), rng)])
    if kind != "none":
        hidden = hide(world, kind, size, rng, q=q)
        thermal = hidden["temperature"]
    else:
        thermal = False
    cal = world.measure(q, temperature=thermal)
    val = world.campaign(world.sample_joints(N_VAL, rng), temperature=thermal)
    rep = 1000 * world.repeatability_mm
    return Campaign(doc, model, write_measurements(cal, model), cal, val.meas,
                    source=f"simulated: a digital twin of the robot in an independent world (its true geometry "
                           f"off by the paper's errors, masses not the model's, tool point off by millimetres, laser "
                           f"tracker noise 15 um + 6 um/m, repeatability {rep:.0f} um), seed {seed}",
                    validation=f"{N_VAL} more poses measured on the same twin, never uploaded",
                    twin=world, hidden=hidden, val_truth=val.truth.points, n_total=N_CAL + N_VAL,
                    n_planned=len(planned))


def from_files(robot: Path, data: Path, seed: int, instrument: str | None = None, limits: str = "reject") -> Campaign:
    try:
        doc = json.loads(robot.read_text())
    except (OSError, ValueError) as exc:
        raise DemoError(f"cannot read the model {robot}: {exc}") from None
    try:
        model = parse_model(doc)
    except ModelError as exc:
        raise DemoError(f"the model {robot} is not valid: {exc}") from None
    try:
        text = data.read_text(encoding="utf-8-sig")
        meas = parse_measurements(text, model, instrument=instrument, limits=limits)
    except OSError as exc:
        raise DemoError(f"cannot read the measurements {data}: {exc}") from None
    except MeasurementError as exc:
        listed = "".join(f"\n    row {e['row']}, column {e['column']}: {e['message']}" for e in exc.errors[:10])
        raise DemoError(f"{data} does not fit the contract CSV ({exc.total} errors):{listed}") from None
    lines = text.splitlines()
    body = [k for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
    header, rows = body[0], body[1:]
    if len(rows) != meas.n_poses:
        raise DemoError(f"{data}: {len(rows)} data lines but {meas.n_poses} poses parsed")
    n_val = int(round(HOLDOUT_FRACTION * meas.n_poses))
    if meas.n_poses - n_val < 30 or n_val < 5:
        raise DemoError(f"{data} has {meas.n_poses} poses: too few to hold out {100 * HOLDOUT_FRACTION:.0f} %")
    # the targets measured at one pose go to the same side (they share the pose's errors); one target: row by row
    unit = meas.pose_index()
    n_units = int(unit.max()) + 1
    n_val_units = int(round(HOLDOUT_FRACTION * n_units))
    perm = np.random.default_rng(seed).permutation(n_units)
    held = np.isin(unit, perm[:n_val_units])
    val_idx, cal_idx = np.flatnonzero(held), np.flatnonzero(~held)
    upload = "\n".join([lines[header]] + [lines[rows[i]] for i in cal_idx]) + "\n"
    share = f"{100 * HOLDOUT_FRACTION:.0f} %"
    held_out = f"{len(val_idx)} poses ({share})" if n_units == meas.n_poses else \
        f"{len(val_idx)} rows (the targets of {n_val_units} poses together, {share})"
    return Campaign(doc, model, upload, meas.subset(cal_idx), meas.subset(val_idx),
                    source=f"{data} ({counted(meas)}) and the model {robot}",
                    validation=f"{held_out} held out at random (seed {seed}) before the upload, never seen by the "
                               "service",
                    n_total=meas.n_poses)


def _n_poses(meas: Measurements) -> int:
    """Poses of the robot: the rows measuring several targets at one placement count once (Measurements.pose_index)."""
    return int(meas.pose_index().max()) + 1 if meas.n_poses else 0


def _unit(meas: Measurements) -> str:
    """What a row of `meas` is: a pose (one target per placement), else a row (one target of a pose)."""
    return "poses" if _n_poses(meas) == meas.n_poses else "rows"


def counted(meas: Measurements, brief: bool = False) -> str:
    """What the rows of a measurement set are, in words: poses, or rows of several targets (markers) per pose; the
    6-D rows and the points the fit makes of them. Agile Justin's "1000 measured poses" were 500 poses x 2 markers,
    the iiwa's 554 rows 2216 points in the answer's metrics."""
    from calib_core.orientation import LEVER_MM

    rows, poses = meas.n_poses, _n_poses(meas)
    if poses == rows:
        out = f"{rows} measured poses"
    else:
        per = np.bincount(meas.pose_index())
        targets = len(np.unique(meas.target)) if meas.target is not None else 1
        out = (f"{rows} rows: {poses} poses x {per[0]} targets (markers)" if (per == per[0]).all() else
               f"{rows} rows: {poses} poses, {per.min()} to {per.max()} of the {targets} targets (markers) each")
    if meas.orientation is not None and (n6 := int((~np.isnan(meas.orientation[:, 0])).sum())):
        each = "each" if n6 == rows else f"{n6} of them"
        out += (f" ({'' if n6 == rows else f'{n6} '}6-D: {rows + 3 * n6} points in the fit)" if brief else
                f"; {each} 6-D (a point and an orientation): the fit takes each 6-D row as its point and 3 virtual "
                f"points {LEVER_MM:g} mm along the measured axes, {rows + 3 * n6} points in all")
    return out


# ----------------------------------------------------------------------------------------------- story

def run(args) -> int:
    import logging

    logging.getLogger("httpx").setLevel(logging.WARNING)  # the story is the output, not the requests
    settings = Settings.from_env()
    t_start = time.monotonic()
    seed = args.seed if args.seed is not None else (0 if args.data else secrets.randbelow(1_000_000))
    if bool(args.robot) != bool(args.data):
        print("calib demo: --robot and --data go together (a model JSON and its measurement CSV)", file=sys.stderr)
        return 2
    try:
        if args.data:
            camp = from_files(Path(args.robot), Path(args.data), seed, getattr(args, "instrument", None),
                              getattr(args, "limits", "reject"))
        else:  # measured after the plan step, on the server's planned poses
            from calib_world import KINDS

            if args.effect not in (None, "none", *KINDS):
                raise DemoError(f"unknown effect {args.effect!r}: use one of {', '.join(KINDS)} or none")
            camp = None
    except DemoError as exc:
        print(f"calib demo: {exc}", file=sys.stderr)
        return 2
    log = Path(tempfile.mkdtemp(prefix="calib-demo-")) / "server.log"
    try:
        return _story(args, settings, camp, seed, log, t_start)
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


def _story(args, settings: Settings, camp: Campaign | None, seed: int, log: Path, t_start: float) -> int:
    if camp is None:
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
        return _chapters(args, api, server, camp, seed, t_start, chapter)
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
              chapter: Chapters) -> int:
    if camp is None:  # simulated: plan the poses first, then measure the twin there
        doc, model = spray7_model()
        chapter("Which poses to measure: POST /robots/{id}/plan")
        robot = api.call("POST", "/robots", (201,), json=doc).json()
        say(f"POST /robots -> robot {robot['id']}.", 3)
        planned = _plan_geometry(api, robot["id"], model, seed)
        camp = simulated(args.effect, seed, planned)
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
    """One is the other cause on more joints (calib_core.plan.nested, on the answer's labels)."""
    x, y = set(f.get("joints") or []), set(a.get("joints") or [])
    return f["kind"] == a["kind"] and f.get("harmonic") == a.get("harmonic") and (x <= y or y <= x)


def _plannable(f: dict, a: dict) -> bool:
    """Whether the answer says a diagnosis plan can split the finding from this look-alike (`plannable`, set by
    calib_core.pipeline with calib_core.plan.plannable; an answer without it: unless nested)."""
    return not _nested(f, a) and a.get("plannable", True) is not False


def _together(findings: list[dict], a: str, b: str) -> bool:
    """Whether one finding still names both labels, as itself or as a look-alike."""
    return any({a, b} <= {_label(f), *map(_label, f.get("indistinguishable_from") or [])} for f in findings)


def _split_lookalikes(api: Api, robot_id: str, ms_id: str, camp: Campaign, findings: list[dict], seed: int) -> None:
    """Plan N_SPLIT poses that tell the listed look-alikes apart; on the twin, measure them, add them to the
    campaign as a new set, run `auto` on it and tell whether each pair is still listed."""
    # two forms of one look-alike (on the model's masses, on an identified load) read the same here: one pair
    pairs = list({(_label(f), _label(a)): (f, a) for f in findings for a in f.get("indistinguishable_from") or []}
                 .values())
    say(f"The diagnosis lists causes these poses cannot tell apart: "
        f"{'; '.join(f'{_label(f)} ~ {_label(a)}' for f, a in pairs)}.", 3)
    nested = [(f, a) for f, a in pairs if _nested(f, a)]
    if nested:
        say(f"{'; '.join(f'{_label(a)} is {_label(f)}' for f, a in nested)} on more joints: the richer form fits "
            "whatever the smaller one fits, so no pose can split them; the diagnosis keeps the smaller one.", 3)
    unplanned = [(f, a) for f, a in pairs if not _nested(f, a) and not _plannable(f, a)]
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
    reached, reasons = np.zeros(len(seeds), bool), [None] * len(seeds)
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
    n_ok = int(reached.sum())
    if camp.twin is None:
        say(f"{len(joints)} targets (the held-out measured points, their measured joints as seeds): the calibrated "
            f"model reaches {n_ok} of them (the answer's `reachable`: within {REACH_MM:g} mm; largest model "
            f"residual {np.nanmax(resid):.4f} mm). Their real accuracy needs a re-measurement of the robot at the "
            "compensated joints.", 3)
        _unreached(reached, reasons, resid)
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


def _why(reason: str | None) -> str:
    """A compensation reason without its target's own figures, to count targets by it: 'not reachable: 0.310 mm
    left after 30 iterations (needs A2 beyond its limit)' -> 'needs A2 beyond its limit'."""
    if not reason:
        return "no reason given"
    m = re.fullmatch(r"not reachable: [\d.]+ mm left after \d+ iterations \((.*)\)", reason)
    return m.group(1) if m else reason


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
        say(f"{len(idx)} x {why}{most}", 5)


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
