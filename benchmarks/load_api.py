"""Load benchmark of the REST API: N concurrent clients uploading measurement CSVs and querying, for a while,
against `calib serve` on SQLite (started here on a temporary file unless --url is given).

    .venv/bin/python benchmarks/load_api.py --clients 50 --duration 60

Each client loops: POST /robots/{id}/measurements (150-pose spray7 CSV), GET /measurements/{id},
GET /robots/{id}, GET /robots?limit=20. At the end every upload answered 201 is read back and counted in the
database. Prints a markdown table: throughput, p50/p99 latency per call, errors, uploads stored.
"""
from __future__ import annotations

import argparse
import asyncio
import os
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import free_port  # noqa: E402
from calib_core import Twin, parse_model, write_measurements  # noqa: E402
from calib_core.robots import spray7  # noqa: E402


def start_server(db_path: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    env = {**os.environ, "CALIB_DATABASE_URL": f"sqlite:///{db_path}"}
    p = subprocess.Popen([sys.executable, "-m", "service.cli", "--log-level", "WARNING", "serve", "--port", str(port)],
                         cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    for _ in range(300):
        try:
            if httpx.get(url + "/health", timeout=1).status_code == 200:
                return p, url
        except httpx.HTTPError:
            time.sleep(0.1)
    p.kill()
    raise SystemExit("the server did not start")


async def client_loop(c: httpx.AsyncClient, rid: str, csv: bytes, t_end: float, lat: dict, uploads: list, errors: dict):
    async def call(kind: str, coro):
        t0 = time.perf_counter()
        try:
            r = await coro
        except httpx.HTTPError as exc:
            errors[kind] = errors.get(kind, 0) + 1
            errors.setdefault("_last", repr(exc))
            return None
        lat.setdefault(kind, []).append(time.perf_counter() - t0)
        if r.status_code >= 300:
            errors[kind] = errors.get(kind, 0) + 1
            errors.setdefault("_last", f"{r.status_code} {r.text[:200]}")
            return None
        return r

    while time.monotonic() < t_end:
        r = await call("POST /robots/{id}/measurements",
                       c.post(f"/robots/{rid}/measurements", files={"file": ("load.csv", csv, "text/csv")}))
        if r is not None:
            uploads.append(r.json()["id"])
            await call("GET /measurements/{id}", c.get(f"/measurements/{r.json()['id']}"))
        await call("GET /robots/{id}", c.get(f"/robots/{rid}"))
        await call("GET /robots", c.get("/robots", params={"limit": 20}))


async def run(url: str, clients: int, duration: float, poses: int) -> dict:
    model_doc = spray7()
    m = parse_model(model_doc)
    csv = write_measurements(Twin(m, 7).measure(n=poses), m).encode()
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=limits) as c:
        rid = (await c.post("/robots", json=model_doc)).json()["id"]
        lat: dict[str, list[float]] = {}
        uploads: list[str] = []
        errors: dict = {}
        t0 = time.monotonic()
        await asyncio.gather(*(client_loop(c, rid, csv, t0 + duration, lat, uploads, errors) for _ in range(clients)))
        wall = time.monotonic() - t0
        # every upload answered 201 must be there
        missing = 0
        for k in range(0, len(uploads), 200):
            rs = await asyncio.gather(*(c.get(f"/measurements/{i}") for i in uploads[k:k + 200]))
            missing += sum(r.status_code != 200 for r in rs)
    return {"lat": lat, "uploads": uploads, "errors": errors, "wall": wall, "missing": missing, "rid": rid,
            "csv_bytes": len(csv)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--poses", type=int, default=150)
    ap.add_argument("--url", help="an already running server (default: start calib serve on a temp SQLite file)")
    a = ap.parse_args()
    tmp = tempfile.TemporaryDirectory()
    db_path = Path(tmp.name) / "load.db"
    proc = None
    url = a.url
    if url is None:
        proc, url = start_server(db_path)
    try:
        res = asyncio.run(run(url, a.clients, a.duration, a.poses))
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(30)
    stored = None
    if a.url is None:
        with sqlite3.connect(db_path) as con:
            stored = con.execute("SELECT count(*) FROM measurement_sets WHERE robot_id = ?", (res["rid"],)).fetchone()[0]
    lat, wall = res["lat"], res["wall"]
    n_all = sum(len(v) for v in lat.values())
    all_ms = np.concatenate([np.array(v) for v in lat.values()]) * 1000
    n_err = sum(v for k, v in res["errors"].items() if not k.startswith("_"))
    print(f"\n## API load: {a.clients} clients, {wall:.0f} s, calib serve on SQLite (WAL), "
          f"{a.poses}-pose CSV ({res['csv_bytes']} bytes), {os.cpu_count()} CPUs\n")
    print("| call | requests | req/s | p50 ms | p99 ms |")
    print("|---|---:|---:|---:|---:|")
    for kind, v in lat.items():
        ms = np.array(v) * 1000
        print(f"| {kind} | {len(v)} | {len(v) / wall:.1f} | {np.percentile(ms, 50):.1f} | {np.percentile(ms, 99):.1f} |")
    print(f"| **all** | {n_all} | {n_all / wall:.1f} | {np.percentile(all_ms, 50):.1f} | {np.percentile(all_ms, 99):.1f} |")
    print(f"\nuploads answered 201: {len(res['uploads'])}; read back: {len(res['uploads']) - res['missing']}; "
          f"rows in the database: {stored if stored is not None else 'n/a (--url)'}; errors: {n_err}"
          + (f" (last: {res['errors']['_last']})" if n_err else ""))
    ok = res["missing"] == 0 and (stored is None or stored == len(res["uploads"])) and n_err == 0
    print("every upload stored: " + ("yes" if ok else "NO"))
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
