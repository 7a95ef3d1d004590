"""The red team's load (issue 10): N clients mixing good and hostile uploads, jobs, cancels, reports and reads
against a real `calib serve` on a fresh SQLite file (embedded workers), real HTTP, for a while; then a graceful
restart on the same file and a check that no accepted write was lost.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_redteam.py [--clients 50] [--seconds 60]

Every client is a thread with its own keep-alive `http.client` connection and loops over a weighted mix:
- robots: the spray7 model, and hostile models (a NaN literal, JSON nested 900 deep, a = 1e200, joints named
  `x` / `timestamp`, a 300-character robot name, a 300-character joint name);
- measurement CSVs: good 150-pose sets, and hostile ones (a coordinate of 1e305, a 1.8 MB header of empty
  columns, a field over 131072 characters, `1_000` as a number, 2 poses, a 600-character filename), and a body
  over CALIB_MAX_UPLOAD_BYTES sent without `Expect: 100-continue`;
- jobs: `geometric` and `auto` on good sets, cancels (`POST /jobs/{id}/cancel` and `DELETE /jobs/{id}`), reads;
- calibrations: JSON, the report (plain and `?inline=true`), plots, predict (good, and 100k rows of "x" to a
  calibration that does not exist);
- issue 33's inputs: URDFs with rpy=1e300 and with nothing in them, a CSV of one setup per row, predicts of
  10,000 rows and compensates of 500 targets on real calibrations, 50-pose plans; and, at set times, a burst of six
  concurrent 19 MB hostile CSVs (duplicated point ids: seconds each to check) with the good uploads timed while they
  are checked, and three 90 MB uploads from urllib (no `Expect`), whose 413 must be read (`--no-issue33` leaves them
  all out, for the issue-10 load alone);
- plus a dedicated /health poller in a process of its own (so the load generator's GIL does not inflate it).

Measured: requests and status codes per kind, any 5xx (first bodies printed), transport errors (no answer),
hostile inputs that were accepted, /health p50/p95/p99, the RSS of the server and of its job processes every
second (bounded: the server's peak in the second half of the run within 1.25x + 50 MB of the first
half's). After the load: SIGTERM, `calib serve` again on the same file, then every robot, measurement set and job
answered 201/202 must be there, every job must reach a terminal state within --drain-seconds, every succeeded
job's calibration must be readable and every job whose cancel answered 200 must be `cancelled`.
Prints markdown tables; exits 1 when a target is missed. Not a test.
"""
from __future__ import annotations

import argparse
import collections
import copy
import http.client
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from benchmarks import free_port, server_env  # noqa: E402

TERMINAL = {"succeeded", "failed", "cancelled"}
BOUNDARY = "calibredteam7f3a9c"
HEALTH_P99_TARGET_MS = 200.0


# ---------------------------------------------------------------- server

SERVER_ENV: dict[str, str] = {}
"""--server-env KEY=VALUE: extra CALIB_* settings for the server (A/B runs of a setting on the same tree)."""


def start_server(db_path: Path, log: Path, port: int, max_upload: int | None) -> tuple[subprocess.Popen, float]:
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "service.cli", "--log-level", "WARNING", "serve", "--port", str(port)],
                         cwd=ROOT, env={**server_env(db_path, max_upload), **SERVER_ENV}, stdout=open(log, "ab"),
                         stderr=subprocess.STDOUT, start_new_session=True)
    while time.perf_counter() - t0 < 180:
        if p.poll() is not None:
            raise SystemExit(f"the server exited ({p.returncode}); see {log}")
        try:
            st, _, _ = request(("127.0.0.1", port), "GET", "/health", timeout=2)
            if st == 200:
                return p, time.perf_counter() - t0
        except OSError:
            pass
        time.sleep(0.05)
    p.kill()
    raise SystemExit("the server did not start")


def request(addr, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
            timeout: float = 60) -> tuple[int, dict, bytes]:
    """One request on a fresh connection (setup and checks only)."""
    c = http.client.HTTPConnection(*addr, timeout=timeout)
    try:
        c.request(method, path, body=body, headers=headers or {})
        r = c.getresponse()
        return r.status, dict(r.getheaders()), r.read()
    finally:
        c.close()


def descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    kids = [int(x) for x in f.read().split()]
                out += kids
                todo += kids
        except OSError:
            pass
    return out


def rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


class RssSampler(threading.Thread):
    def __init__(self, pid: int, every: float = 1.0):
        super().__init__(daemon=True)
        self.pid, self.every, self.samples = pid, every, []  # (t, server MB, children MB, n children)
        self.halt = threading.Event()

    def run(self) -> None:
        t0 = time.monotonic()
        while not self.halt.is_set():
            kids = descendants(self.pid)
            self.samples.append((time.monotonic() - t0, rss_mb(self.pid), sum(rss_mb(k) for k in kids), len(kids)))
            self.halt.wait(self.every)


# ---------------------------------------------------------------- /health poller (a process of its own)

def health_poller(url_port: int, seconds: float, out: str, interval: float) -> None:
    lat, codes, fails = [], collections.Counter(), []
    conn = None
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        t0 = time.perf_counter()
        try:
            if conn is None:
                conn = http.client.HTTPConnection("127.0.0.1", url_port, timeout=30)
            conn.request("GET", "/health")
            r = conn.getresponse()
            r.read()
            codes[r.status] += 1
            lat.append((time.perf_counter() - t0) * 1000)
            if r.will_close:
                conn.close()
                conn = None
        except (OSError, http.client.HTTPException) as exc:
            fails.append(repr(exc))
            lat.append((time.perf_counter() - t0) * 1000)
            if conn is not None:
                conn.close()
            conn = None
        time.sleep(max(0.0, interval - (time.perf_counter() - t0)))
    Path(out).write_text(json.dumps({"lat_ms": lat, "codes": codes, "fails": fails[:5], "n_fail": len(fails)}))


# ---------------------------------------------------------------- inputs

def multipart(filename: str, data: bytes) -> tuple[bytes, dict]:
    head = (f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="file"; filename="{filename}"\r\n'
            "Content-Type: text/csv\r\n\r\n").encode()
    return head + data + f"\r\n--{BOUNDARY}--\r\n".encode(), {
        "Content-Type": f"multipart/form-data; boundary={BOUNDARY}"}


def _lines(csv_text: str) -> list[str]:
    return csv_text.strip().splitlines()


def _edit(csv_text: str, row: int, col: str, value: str) -> str:
    ls = _lines(csv_text)
    k = ls[0].split(",").index(col)
    f = ls[row].split(",")
    f[k] = value
    ls[row] = ",".join(f)
    return "\n".join(ls) + "\n"


def _nested(depth: int):
    v: list = []
    for _ in range(depth):
        v = [v]
    return v


def build_inputs(max_upload: int) -> dict:
    from calib_core import Twin, parse_model, write_measurements
    from calib_core.robots import spray7

    model = spray7()
    m = parse_model(model)
    good_csvs = [write_measurements(Twin(m, seed).measure(n=150), m) for seed in (7, 8, 9)]
    c = good_csvs[0]
    ls = _lines(c)

    def js(doc) -> bytes:
        return json.dumps(doc).encode()  # NaN / Infinity as Python writes them

    def joint(k: int, **kw) -> dict:
        d = copy.deepcopy(model)
        d["joints"][k].update(kw)
        return d

    hostile_models = {
        "NaN literal": json.dumps(model).replace('"d": 626', '"d": NaN', 1).encode(),
        "NaN in extra field": js({**model, "note": float("nan")}),
        "nested 900 deep": js({**model, "note": _nested(900)}),
        "joints nested 900 deep": js({**model, "joints": _nested(900)}),
        "a = 1e200": js(joint(1, a=1e200)),
        "joint named x": js(joint(1, name="x")),
        "joint named timestamp": js(joint(2, name="timestamp")),
        "robot name 300 chars": js({**model, "name": "r" * 300}),
        "joint name 300 chars": js(joint(1, name="J" * 300)),
    }
    hostile_csvs = {
        "coordinate 1e305": ("c.csv", _edit(c, 5, "x", "1e305").encode()),
        "1.8 MB header of empty columns": ("h.csv", b"," * 1_800_000 + b"\n" + ls[1].encode()),
        "field over 131072 chars": ("f.csv", _edit(c, 4, "point", "P" * 131_073).encode()),
        "1_000 as a number": ("u.csv", _edit(c, 6, "x", "1_000").encode()),
        "2 poses": ("two.csv", ("\n".join(ls[:3]) + "\n").encode()),
        "600-char filename": ("n" * 596 + ".csv", c.encode()),
    }
    # an oversized body: a valid-looking CSV just over the limit, one multipart part
    row = (ls[1] + "\n").encode()
    big = ls[0].encode() + b"\n" + row * ((max_upload + 1024 * 1024) // len(row) + 1)
    joints_good = [[float(v) for v in ln.split(",")[1:8]] for ln in ls[1:21]]
    joints_10k = [[float(v) for v in ln.split(",")[1:8]] for ln in (ls[1:] * 67)[:10_000]]
    targets_500 = [[float(v) for v in ln.split(",")[8:11]] for ln in (ls[1:] * 4)[:500]]
    seeds_500 = [[float(v) for v in ln.split(",")[1:8]] for ln in (ls[1:] * 4)[:500]]
    own_setups = "\n".join([ls[0] + ",setup"] + [f"{ln},S{i:03d}" for i, ln in enumerate(ls[1:])]) + "\n"
    dup_19mb = (ls[0] + "\n" + "\n".join(ls[1:] * (19_000_000 // len(c))) + "\n").encode()
    return {
        "model": model,
        "good_csvs": [multipart("good.csv", x.encode()) for x in good_csvs],
        "hostile_models": hostile_models,
        "hostile_csvs": {k: multipart(fn, data) for k, (fn, data) in hostile_csvs.items()},
        "oversized": multipart("huge.csv", big),
        "predict_hostile": json.dumps({"joints": [["x"]] * 100_000}).encode(),
        "predict_good": json.dumps({"joints": joints_good}).encode(),
        "predict_10k": json.dumps({"joints": joints_10k}).encode(),
        "compensate_500": json.dumps({"targets": targets_500, "seed_joints": seeds_500}).encode(),
        "plan_50": json.dumps({"n_poses": 50, "purpose": "geometric"}).encode(),
        "hostile_urdfs": {"rpy=1e300": URDF.replace('rpy="0 0 0"', 'rpy="1e300 0 0"', 1).encode(),
                          "no link": b'<robot name="empty"/>', "a link, no joint": b'<robot name="one"><link name="a"/>'
                                                                                    b'</robot>'},
        "own_setups": multipart("setups.csv", own_setups.encode()),
        "hostile_19mb": multipart("dup19.csv", dup_19mb),
        "body_90mb": multipart("huge90.csv", (ls[0] + "\n").encode() + row * (90_000_000 // len(row) + 1)),
    }


URDF = """<?xml version="1.0"?>
<robot name="two">
  <link name="base"/><link name="l1"/><link name="tip"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.3" rpy="0 0 0"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="10" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="tip"/><origin xyz="0.4 0 0" rpy="0 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="10" velocity="1"/></joint>
</robot>
"""


# ---------------------------------------------------------------- the load

class Shared:
    def __init__(self):
        self.lock = threading.Lock()
        self.robots: list[str] = []  # answered 201
        self.sets: list[str] = []  # answered 201
        self.jobs: list[str] = []  # answered 202
        self.cancelled: set[str] = set()  # cancel answered 200
        self.calibrations: list[str] = []
        self.stats: dict[str, dict] = {}  # kind -> {"codes": Counter, "lat": [], "transport": Counter}
        self.fivexx: list[str] = []
        self.hostile_accepted: list[str] = []
        self.transport_samples: list[str] = []

    def record(self, kind: str, status: int | None, lat: float, body: bytes | None = None, err: str | None = None):
        with self.lock:
            s = self.stats.setdefault(kind, {"codes": collections.Counter(), "lat": [], "transport": 0})
            if status is None:
                s["transport"] += 1
                if len(self.transport_samples) < 8:
                    self.transport_samples.append(f"{kind}: {err}")
                return
            s["codes"][status] += 1
            s["lat"].append(lat)
            if status >= 500 and len(self.fivexx) < 8:
                self.fivexx.append(f"{kind} -> {status}: {(body or b'')[:600].decode('utf-8', 'replace')}")


# kind: (weight, what)
MIX = {
    "POST /robots (good)": 2,
    "POST /robots (hostile)": 3,
    "POST measurements (good)": 8,
    "POST measurements (hostile)": 5,
    "POST measurements (oversized, no Expect)": 0.25,
    "POST /jobs geometric": 2,
    "POST /jobs auto": 1,
    "cancel job (POST cancel / DELETE)": 1,
    "GET /jobs/{id}": 4,
    "GET /calibrations/{id}": 2,
    "GET report": 1,
    "GET report?inline=true": 0.3,
    "GET plots/*.png": 1.5,
    "POST predict (good)": 1,
    "POST predict 100k x to a missing id": 0.4,
    "GET /measurements/{id}": 1.5,
    "GET /robots/{id}": 1,
    "GET /robots?limit=20": 0.5,
}
MIX_33 = {  # issue 33's inputs in the mix (--no-issue33 leaves them out)
    "POST /robots URDF (hostile: rpy=1e300, empty)": 0.5,
    "POST measurements (one setup per row)": 0.5,
    "POST predict 10k rows": 0.3,
    "POST compensate 500 targets": 0.3,
    "POST plan 50 poses": 0.1,
}
EVENTS_33 = ("POST measurements (19 MB hostile, burst of 6)", "POST measurements (good, during the burst)",
             "POST 90 MB upload (urllib, no Expect)")
"""Kinds of the timed events (Events); listed in the report after the mix."""
HOSTILE_KINDS = {"POST /robots (hostile)", "POST measurements (hostile)", "POST measurements (oversized, no Expect)",
                 "POST predict 100k x to a missing id", "POST /robots URDF (hostile: rpy=1e300, empty)",
                 "POST measurements (one setup per row)", "POST measurements (19 MB hostile, burst of 6)",
                 "POST 90 MB upload (urllib, no Expect)"}
# kind: (the Shared list of accepted ids it reads, path) for the kinds that are one GET of one such id
GET_ONE = {
    "GET /calibrations/{id}": ("calibrations", "/calibrations/{}"),
    "GET report": ("calibrations", "/calibrations/{}/report"),
    "GET report?inline=true": ("calibrations", "/calibrations/{}/report?inline=true"),
    "GET /measurements/{id}": ("sets", "/measurements/{}"),
    "GET /robots/{id}": ("robots", "/robots/{}"),
}


class Client(threading.Thread):
    def __init__(self, k: int, port: int, inputs: dict, sh: Shared, t_end: float, timeout: float):
        super().__init__(daemon=True)
        self.port, self.inp, self.sh, self.t_end, self.timeout = port, inputs, sh, t_end, timeout
        self.rng = random.Random(1000 + k)
        self.conn: http.client.HTTPConnection | None = None
        self.kinds, self.weights = list(MIX), list(MIX.values())

    def call(self, kind: str, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
             label: str | None = None) -> tuple[int | None, bytes]:
        t0 = time.perf_counter()
        try:
            if self.conn is None:
                self.conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=self.timeout)
            self.conn.request(method, path, body=body, headers=headers or {})
            r = self.conn.getresponse()
            data = r.read()
            if r.will_close:
                self.conn.close()
                self.conn = None
        except (OSError, http.client.HTTPException) as exc:
            if self.conn is not None:
                self.conn.close()
            self.conn = None
            self.sh.record(kind, None, time.perf_counter() - t0, err=f"{label or ''} {exc!r}")
            return None, b""
        self.sh.record(kind, r.status, time.perf_counter() - t0, data)
        if kind in HOSTILE_KINDS and 200 <= r.status < 300:
            with self.sh.lock:
                self.sh.hostile_accepted.append(f"{kind} [{label}] -> {r.status}")
        return r.status, data

    def pick(self, xs: list[str]) -> str | None:
        return self.rng.choice(xs) if xs else None

    def run(self) -> None:
        sh, inp, rng = self.sh, self.inp, self.rng
        J = {"Content-Type": "application/json"}
        while time.monotonic() < self.t_end:
            kind = rng.choices(self.kinds, self.weights)[0]
            if kind == "POST /robots (good)":
                doc = {**inp["model"], "name": f"spray7-load-{rng.randrange(10**6)}"}
                st, b = self.call(kind, "POST", "/robots", json.dumps(doc).encode(), J)
                if st == 201:
                    with sh.lock:
                        sh.robots.append(json.loads(b)["id"])
            elif kind == "POST /robots (hostile)":
                label = rng.choice(list(inp["hostile_models"]))
                self.call(kind, "POST", "/robots", inp["hostile_models"][label], J, label=label)
            elif kind == "POST measurements (good)":
                body, h = rng.choice(inp["good_csvs"])
                st, b = self.call(kind, "POST", f"/robots/{self.pick(sh.robots)}/measurements", body, h)
                if st == 201:
                    with sh.lock:
                        sh.sets.append(json.loads(b)["id"])
            elif kind == "POST measurements (hostile)":
                label = rng.choice(list(inp["hostile_csvs"]))
                body, h = inp["hostile_csvs"][label]
                self.call(kind, "POST", f"/robots/{self.pick(sh.robots)}/measurements", body, h, label=label)
            elif kind == "POST measurements (oversized, no Expect)":
                body, h = inp["oversized"]
                self.call(kind, "POST", f"/robots/{self.pick(sh.robots)}/measurements", body, h, label="oversized")
            elif kind in ("POST /jobs geometric", "POST /jobs auto"):
                mode = kind.rsplit(" ", 1)[1]
                doc = {"measurement_set_id": self.pick(sh.sets), "model": mode}
                st, b = self.call(kind, "POST", "/jobs", json.dumps(doc).encode(), J)
                if st == 202:
                    with sh.lock:
                        sh.jobs.append(json.loads(b)["id"])
            elif kind == "cancel job (POST cancel / DELETE)":
                jid = self.pick(sh.jobs)
                if jid is None:
                    continue
                st, _ = (self.call(kind, "POST", f"/jobs/{jid}/cancel") if rng.random() < 0.5
                         else self.call(kind, "DELETE", f"/jobs/{jid}"))
                if st == 200:
                    with sh.lock:
                        sh.cancelled.add(jid)
            elif kind == "GET /jobs/{id}":
                jid = self.pick(sh.jobs)
                if jid is None:
                    continue
                st, b = self.call(kind, "GET", f"/jobs/{jid}")
                if st == 200:
                    cid = json.loads(b).get("calibration_id")
                    if cid:
                        with sh.lock:
                            if cid not in sh.calibrations:
                                sh.calibrations.append(cid)
            elif kind in GET_ONE:
                ids, path = GET_ONE[kind]
                self.call(kind, "GET", path.format(self.pick(getattr(sh, ids))))
            elif kind == "GET plots/*.png":
                name = rng.choice(["errors", "distribution", "finding-1"])
                self.call(kind, "GET", f"/calibrations/{self.pick(sh.calibrations)}/plots/{name}.png")
            elif kind == "POST predict (good)":
                self.call(kind, "POST", f"/calibrations/{self.pick(sh.calibrations)}/predict", inp["predict_good"], J)
            elif kind == "POST predict 100k x to a missing id":
                self.call(kind, "POST", "/calibrations/does-not-exist/predict", inp["predict_hostile"], J,
                          label="100k x")
            elif kind == "GET /robots?limit=20":
                self.call(kind, "GET", f"/robots?limit=20&offset={rng.randrange(0, max(1, len(sh.robots)))}")
            elif kind == "POST /robots URDF (hostile: rpy=1e300, empty)":
                label = rng.choice(list(inp["hostile_urdfs"]))
                self.call(kind, "POST", "/robots", inp["hostile_urdfs"][label], {"Content-Type": "application/xml"},
                          label=label)
            elif kind == "POST measurements (one setup per row)":
                body, h = inp["own_setups"]
                self.call(kind, "POST", f"/robots/{self.pick(sh.robots)}/measurements", body, h, label="setups")
            elif kind == "POST predict 10k rows":
                self.call(kind, "POST", f"/calibrations/{self.pick(sh.calibrations)}/predict", inp["predict_10k"], J)
            elif kind == "POST compensate 500 targets":
                self.call(kind, "POST", f"/calibrations/{self.pick(sh.calibrations)}/compensate",
                          inp["compensate_500"], J)
            elif kind == "POST plan 50 poses":
                self.call(kind, "POST", f"/robots/{self.pick(sh.robots)}/plan", inp["plan_50"], J)
        if self.conn is not None:
            self.conn.close()


class Events(threading.Thread):
    """Issue 33's timed inputs: at 5 s a burst of six concurrent 19 MB hostile CSVs, with a good 150-pose upload
    every 0.5 s while they are checked (each timed: a small upload must not wait behind them); at 20, 35 and 50 s of
    the load (those within it) a 90 MB upload from urllib, which sends its whole body before it reads (its 413 must
    arrive, not a reset)."""

    def __init__(self, port: int, inputs: dict, sh: Shared, t0: float, seconds: float, timeout: float):
        super().__init__(daemon=True)
        self.port, self.inp, self.sh, self.t0, self.seconds, self.timeout = port, inputs, sh, t0, seconds, timeout

    def one(self, kind: str, body: bytes, headers: dict, label: str) -> None:
        c = Client(0, self.port, self.inp, self.sh, 0, self.timeout)
        st, b = c.call(kind, "POST", f"/robots/{self.sh.robots[0]}/measurements", body, headers, label=label)
        if c.conn is not None:
            c.conn.close()
        if st == 201:
            with self.sh.lock:
                self.sh.sets.append(json.loads(b)["id"])

    def urllib_90mb(self) -> None:
        import urllib.error
        import urllib.request

        kind = EVENTS_33[2]
        body, h = self.inp["body_90mb"]
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/robots/{self.sh.robots[0]}/measurements",
                                     data=body, headers=h, method="POST")
        t = time.perf_counter()
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                st, data = r.status, r.read()
        except urllib.error.HTTPError as e:
            st, data = e.code, e.read()
        except OSError as exc:
            self.sh.record(kind, None, time.perf_counter() - t, err=f"90 MB {exc!r}")
            return
        self.sh.record(kind, st, time.perf_counter() - t, data)
        if 200 <= st < 300:
            with self.sh.lock:
                self.sh.hostile_accepted.append(f"{kind} -> {st}")

    def run(self) -> None:
        def at(s: float) -> bool:
            left = self.t0 + s - time.monotonic()
            if s >= self.seconds:
                return False
            time.sleep(max(0.0, left))
            return True

        if at(5):
            body, h = self.inp["hostile_19mb"]
            burst = [threading.Thread(target=self.one, args=(EVENTS_33[0], body, h, "19 MB"), daemon=True)
                     for _ in range(6)]
            for b in burst:
                b.start()
            time.sleep(0.5)
            good, gh = self.inp["good_csvs"][1]
            while any(b.is_alive() for b in burst) and time.monotonic() < self.t0 + self.seconds:
                threading.Thread(target=self.one, args=(EVENTS_33[1], good, gh, "good"), daemon=True).start()
                time.sleep(0.5)
            for b in burst:
                b.join(self.timeout)
        for s in (20, 35, 50):
            if at(s):
                self.urllib_90mb()


# ---------------------------------------------------------------- checks after the restart

def get_json(addr, path: str) -> tuple[int, dict | None]:
    st, _, b = request(addr, "GET", path, timeout=60)
    try:
        return st, json.loads(b)
    except ValueError:
        return st, None


def verify(addr, sh: Shared, drain_s: float) -> dict:
    out = {"robots_missing": [], "sets_missing": [], "jobs_missing": [], "not_terminal": [], "cal_missing": [],
           "cancel_lost": []}
    for rid in sh.robots:
        if get_json(addr, f"/robots/{rid}")[0] != 200:
            out["robots_missing"].append(rid)
    for sid in sh.sets:
        if get_json(addr, f"/measurements/{sid}")[0] != 200:
            out["sets_missing"].append(sid)
    status: dict[str, dict] = {}
    t0 = time.monotonic()
    pending = list(sh.jobs)
    while True:
        nxt = []
        for jid in pending:
            st, j = get_json(addr, f"/jobs/{jid}")
            if st != 200 or j is None:
                out["jobs_missing"].append(jid)
                continue
            status[jid] = j
            if j["status"] not in TERMINAL:
                nxt.append(jid)
        pending = nxt
        if not pending or time.monotonic() - t0 > drain_s:
            break
        time.sleep(1.0)
    out["drain_s"] = time.monotonic() - t0
    out["not_terminal"] = pending
    out["final"] = collections.Counter(j["status"] for j in status.values())
    fail_msgs = collections.Counter()
    for jid, j in status.items():
        if j["status"] == "succeeded":
            if not j.get("calibration_id") or get_json(addr, f"/calibrations/{j['calibration_id']}")[0] != 200:
                out["cal_missing"].append(jid)
        if j["status"] == "failed":
            fail_msgs[(j.get("error") or j.get("message") or "")[:120]] += 1
        if jid in sh.cancelled and j["status"] != "cancelled":
            out["cancel_lost"].append(f"{jid}: {j['status']}")
    out["fail_msgs"] = fail_msgs
    return out


# ---------------------------------------------------------------- main

def pct(xs, q):
    if not xs:
        return float("nan")
    s = sorted(xs)
    return s[min(len(s) - 1, int(round(q / 100 * (len(s) - 1))))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--drain-seconds", type=float, default=600.0, help="bounded wait for every job to finish")
    ap.add_argument("--max-upload-bytes", type=int, default=None,
                    help="CALIB_MAX_UPLOAD_BYTES for the server (default: the server's default, 20 MiB)")
    ap.add_argument("--timeout", type=float, default=120.0, help="client socket timeout, s")
    ap.add_argument("--health-interval", type=float, default=0.05)
    ap.add_argument("--keep", action="store_true", help="keep the temp dir (database, server log)")
    ap.add_argument("--skip", action="append", default=[], metavar="TEXT",
                    help="leave out the kinds whose name contains TEXT (repeatable), to attribute a miss")
    ap.add_argument("--server-env", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting for the server, e.g. CALIB_ROUTE_THREADS=4 (repeatable)")
    ap.add_argument("--no-issue33", action="store_true", help="leave out issue 33's inputs (the issue-10 load alone)")
    ap.add_argument("--_health", nargs=4, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._health:
        health_poller(int(a._health[0]), float(a._health[1]), a._health[2], float(a._health[3]))
        return
    SERVER_ENV.update(kv.split("=", 1) for kv in a.server_env)
    if not a.no_issue33:
        MIX.update(MIX_33)

    for kind in list(MIX):
        if any(x in kind for x in a.skip):
            del MIX[kind]
    from service.config import Settings
    max_upload = a.max_upload_bytes or Settings().max_upload_bytes
    tmp = tempfile.mkdtemp(prefix="calib-redteam-")
    db_path, log = Path(tmp) / "redteam.db", Path(tmp) / "server.log"
    port = free_port()
    addr = ("127.0.0.1", port)
    print(f"temp dir {tmp}; building inputs ...", file=sys.stderr)
    inp = build_inputs(max_upload)
    proc, t_start = start_server(db_path, log, port, a.max_upload_bytes)
    print(f"calib serve up in {t_start:.1f} s (pid {proc.pid}), port {port}", file=sys.stderr)
    targets: dict[str, bool] = {}
    try:
        sh = Shared()
        # seed: one robot, one set, one finished auto job (a calibration to read from the first second)
        J = {"Content-Type": "application/json"}
        st, _, b = request(addr, "POST", "/robots", json.dumps(inp["model"]).encode(), J)
        assert st == 201, b
        sh.robots.append(json.loads(b)["id"])
        body, h = inp["good_csvs"][0]
        st, _, b = request(addr, "POST", f"/robots/{sh.robots[0]}/measurements", body, h)
        assert st == 201, b
        sh.sets.append(json.loads(b)["id"])
        doc = {"measurement_set_id": sh.sets[0], "model": "auto"}
        st, _, b = request(addr, "POST", "/jobs", json.dumps(doc).encode(), J)
        assert st == 202, b
        jid = json.loads(b)["id"]
        sh.jobs.append(jid)
        for _ in range(1200):
            _, j = get_json(addr, f"/jobs/{jid}")
            if j["status"] in TERMINAL:
                break
            time.sleep(0.1)
        assert j["status"] == "succeeded", j
        sh.calibrations.append(j["calibration_id"])

        rss = RssSampler(proc.pid)
        rss.start()
        time.sleep(1.2)
        hout = Path(tmp) / "health.json"
        hp = subprocess.Popen([sys.executable, __file__, "--_health", str(port), str(a.seconds), str(hout),
                               str(a.health_interval)], cwd=ROOT)
        t0 = time.monotonic()
        load = [os.getloadavg()[0]]
        clients = [Client(k, port, inp, sh, t0 + a.seconds, a.timeout) for k in range(a.clients)]
        events = None if a.no_issue33 else Events(port, inp, sh, t0, a.seconds, a.timeout)
        for c in clients + ([events] if events else []):
            c.start()
        for c in clients + ([events] if events else []):
            c.join(a.seconds + a.timeout + 60)
        wall = time.monotonic() - t0
        load.append(os.getloadavg()[0])
        stuck = sum(c.is_alive() for c in clients + ([events] if events else []))
        hp.wait(a.seconds + 120)
        time.sleep(1.0)
        rss.halt.set()
        rss.join()
        health = json.loads(hout.read_text())
        _, hj = get_json(addr, "/health")
        queue_at_end = hj.get("jobs") if hj else None

        # graceful restart on the same file
        t = time.perf_counter()
        proc.send_signal(signal.SIGTERM)
        try:
            rc = proc.wait(60)
        except subprocess.TimeoutExpired:
            rc = "did not stop in 60 s (killed)"
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
        t_stop = time.perf_counter() - t
        proc, t_start2 = start_server(db_path, log, port, a.max_upload_bytes)
        rss2 = RssSampler(proc.pid)
        rss2.start()
        ver = verify(addr, sh, a.drain_seconds)
        rss2.halt.set()
        rss2.join()
    finally:
        try:
            proc.send_signal(signal.SIGTERM)
            proc.wait(30)
        except Exception:  # noqa: BLE001
            os.killpg(proc.pid, signal.SIGKILL)

    # ------------------------------------------------------------ report
    n_all = sum(sum(s["codes"].values()) + s["transport"] for s in sh.stats.values())
    print(f"\n## Red-team load: {a.clients} clients, {wall:.0f} s, calib serve on SQLite (embedded workers), "
          f"{os.cpu_count()} CPUs, limit {max_upload / 2**20:.0f} MiB"
          + (f", {' '.join(a.server_env)}" if a.server_env else "")
          + f"; load average {load[0]:.1f} when the load began, {load[1]:.1f} when it ended\n")
    print(f"{n_all} requests ({n_all / wall:.1f}/s); clients still running at the end: {stuck}"
          + (f"; left out: {a.skip}" if a.skip else "") + "\n")
    print("| kind | requests | status codes | no answer | p50 ms | p99 ms |")
    print("|---|---:|---|---:|---:|---:|")
    n5, ntr = 0, 0
    for kind in [*MIX, *EVENTS_33]:
        s = sh.stats.get(kind)
        if not s:
            continue
        codes = ", ".join(f"{k}: {v}" for k, v in sorted(s["codes"].items()))
        n = sum(s["codes"].values()) + s["transport"]
        n5 += sum(v for k, v in s["codes"].items() if k >= 500)
        ntr += s["transport"]
        lat = [x * 1000 for x in s["lat"]]
        print(f"| {kind} | {n} | {codes} | {s['transport']} | {pct(lat, 50):.0f} | {pct(lat, 99):.0f} |")
    allcodes = collections.Counter()
    for s in sh.stats.values():
        allcodes.update(s["codes"])
    print(f"| **all** | {n_all} | {', '.join(f'{k}: {v}' for k, v in sorted(allcodes.items()))} | {ntr} | | |")

    hl = health["lat_ms"]
    print("\n| target | measured | met |")
    print("|---|---|---|")
    targets["no 5xx"] = n5 == 0
    print(f"| no 5xx | {n5} | {'yes' if n5 == 0 else 'NO'} |")
    targets["every request answered"] = ntr == 0 and stuck == 0
    print(f"| every request answered (no reset/timeout) | {ntr} without an answer | {'yes' if ntr == 0 else 'NO'} |")
    hostile_ok = not sh.hostile_accepted
    targets["hostile refused"] = hostile_ok
    print(f"| every hostile input refused (4xx) | {len(sh.hostile_accepted)} accepted "
          f"| {'yes' if hostile_ok else 'NO'} |")
    p99 = pct(hl, 99)
    targets["/health p99"] = p99 < HEALTH_P99_TARGET_MS and health["n_fail"] == 0
    print(f"| /health p99 < {HEALTH_P99_TARGET_MS:.0f} ms ({len(hl)} polls every {a.health_interval * 1000:.0f} ms, "
          f"own process) | p50 {pct(hl, 50):.1f} / p95 {pct(hl, 95):.1f} / p99 {p99:.1f} / max {max(hl):.0f} ms; "
          f"codes {dict(health['codes'])}, failures {health['n_fail']} | {'yes' if targets['/health p99'] else 'NO'} |")
    srv = [x[1] for x in rss.samples]
    tot = [x[1] + x[2] for x in rss.samples]
    half = len(srv) // 2
    bounded = max(srv[half:]) <= 1.25 * max(srv[:half]) + 50 if len(srv) > 4 else True
    targets["RSS bounded"] = bounded
    print(f"| server RSS bounded ({len(srv)} samples, 1/s) | server: start {srv[0]:.0f}, max {max(srv):.0f}, end "
          f"{srv[-1]:.0f} MB; with job processes: start {tot[0]:.0f}, max {max(tot):.0f}, end {tot[-1]:.0f} MB; "
          f"max of 2nd half vs 1st half {max(srv[half:]):.0f} / {max(srv[:half]):.0f} MB "
          f"| {'yes' if bounded else 'NO'} |")
    lost = (len(ver["robots_missing"]) + len(ver["sets_missing"]) + len(ver["jobs_missing"]) + len(ver["cal_missing"])
            + len(ver["cancel_lost"]))
    targets["no accepted write lost"] = lost == 0
    rc = f"{rc} (uvicorn re-raises SIGTERM after its graceful shutdown)" if rc == -signal.SIGTERM else rc
    print(f"| no accepted write lost (SIGTERM after {t_stop:.1f} s, exit {rc}; restart {t_start2:.1f} s) | robots "
          f"{len(sh.robots) - len(ver['robots_missing'])}/{len(sh.robots)}, sets "
          f"{len(sh.sets) - len(ver['sets_missing'])}/{len(sh.sets)}, jobs {len(sh.jobs) - len(ver['jobs_missing'])}"
          f"/{len(sh.jobs)}, succeeded jobs with their calibration readable: all but {len(ver['cal_missing'])}, "
          f"cancels answered 200 still cancelled: {len(sh.cancelled) - len(ver['cancel_lost'])}/{len(sh.cancelled)} "
          f"| {'yes' if lost == 0 else 'NO'} |")
    targets["every job terminal"] = not ver["not_terminal"]
    print(f"| every job terminal within {a.drain_seconds:.0f} s of the restart | queue at the end of the load "
          f"{queue_at_end}; drained in {ver['drain_s']:.0f} s; final {dict(ver['final'])}; not terminal "
          f"{len(ver['not_terminal'])} | {'yes' if not ver['not_terminal'] else 'NO'} |")
    if rss2.samples:
        s2 = [x[1] + x[2] for x in rss2.samples]
        print(f"\nRSS after the restart, while the queue drained (server + job processes): start {s2[0]:.0f}, "
              f"max {max(s2):.0f}, end {s2[-1]:.0f} MB")
    print("\nRSS during the load (s: server MB + job processes MB):",
          " ".join(f"{t:.0f}:{s:.0f}+{c:.0f}" for t, s, c, _ in rss.samples[::5]))
    if ver["fail_msgs"]:
        print("\nfailed jobs, by message:")
        for m, n in ver["fail_msgs"].most_common(8):
            print(f"- {n} x {m!r}")
    for title, xs in (("5xx bodies", sh.fivexx), ("requests without an answer", sh.transport_samples),
                      ("hostile inputs accepted", sh.hostile_accepted[:8]), ("/health failures", health["fails"]),
                      ("writes lost", ver["robots_missing"][:5] + ver["sets_missing"][:5] + ver["jobs_missing"][:5]
                       + ver["cal_missing"][:5] + ver["cancel_lost"][:5]),
                      ("jobs not terminal", ver["not_terminal"][:8])):
        if xs:
            print(f"\n{title}:")
            for x in xs:
                print(f"- {x}")
    print(f"\nserver log: {log}" if a.keep else "")
    if not a.keep:
        import shutil
        shutil.rmtree(tmp, ignore_errors=True)
    print("targets: " + ", ".join(f"{k} {'met' if v else 'MISSED'}" for k, v in targets.items()))
    sys.exit(0 if all(targets.values()) else 1)


if __name__ == "__main__":
    main()
