"""The blind diagnosis's run time, this code against another revision, on the same data in the same run (issue 32).

Cases: the four real datasets as `calib convert-dataset` writes them (70/30 split by pose, seed 0; the diagnosis runs
on the 70 %, its extended model is judged on the 30 % it never saw) and the independent world (spray7, mass data
15 % off, one drawn cause at 5x the noise) at 150 and 2000 poses. Each case runs in its own process, one BLAS
thread, with PYTHONPATH set to the revision's tree (a `git worktree` made once under /tmp), so both revisions see
the same machine at the same time; scipy's modules are imported before the clock on both sides, as the service's fork
server has them (--cache reuses a committed revision's earlier results). Per case: wall time and its ratio, the CPU
time of the diagnosis's processes (its own and the children it forked and waited for: the work done in parallel,
wasted or not), the findings (kind and joints) and the held-out RMS on the 30 % (or on 100 fresh world poses), with
their relative difference; with --repeat, each side's median over interleaved runs.

Run: .venv/bin/python -m benchmarks.bench_diagnosis_speed [--base REV]
     [--cases motoman motoman_order iiwa justin hilti w150 w2000]
     [--jobs 2] [--workers 2] [--repeat 3]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASE = "c65e151"
"""The code at the start of issue 32's speed work (the session's first commit)."""
CASES = ("motoman", "motoman_order", "iiwa", "justin", "hilti", "w150", "w2000")
"""motoman: the CSV without its measurement order, as the base reads it; motoman_order: with the `sequence` column
(issue 34, RESULTS 9.1.1), against the base's motoman (the base cannot read the column)."""

CHILD = r'''
import json, os, sys, time
import numpy as np
import scipy.linalg, scipy.optimize, scipy.special, scipy.stats  # before the clock on both sides, as the service's
# fork server imports them (service/processes.py PRELOAD): the base imports scipy.stats with its module, this code
# where a diagnosis first uses it, which put 0.3-1.3 s of import on this code's clock alone
if os.path.isdir(os.path.join(os.getcwd(), "calib_core", "diagnosis")):  # by the tree: the editable install's
    from calib_core.diagnosis import diagnose  # finder would otherwise serve a missing subpackage from the repo
else:
    from calib_core.diagnose import diagnose
from calib_core import datasets as D
from calib_core.identify import evaluate
from calib_core.io import parse_measurements
from calib_core.model import parse_model

case, root, workers = sys.argv[1], sys.argv[2], int(sys.argv[3])
if case.startswith("w"):
    from calib_core.robots import spray7
    from calib_world import World
    from calib_world.scenarios import hide
    model = parse_model(spray7())
    n = int(case[1:])
    world = World(model, 7)
    q = world.sample_joints(n + 100, np.random.default_rng(7))
    hide(world, "joint_spring", 5.0, np.random.default_rng(7), q=q[:n])
    meas = world.measure(q)
    train, test = meas.subset(np.arange(n)), meas.subset(np.arange(n, n + 100))
else:
    name = {"motoman": "motoman_leica", "motoman_order": "motoman_leica", "iiwa": "iiwa7_payload",
            "justin": "dlr_agile_justin", "hilti": "hilti_trailblazer"}[case]
    ds = {"motoman_leica": lambda: D.motoman_leica(root),
          "iiwa7_payload": lambda: D.iiwa7_payload(None, root, orientation=True, torques=True),
          "dlr_agile_justin": lambda: D.agile_justin_tree(root),
          "hilti_trailblazer": lambda: D.hilti_trailblazer(root)}[name]()
    model = parse_model(ds.model)
    meas = parse_measurements(ds.csv_text, model, instrument="optical" if name == "iiwa7_payload" else None)
    if case == "motoman" and getattr(meas, "sequence", None) is not None:  # like for like with the base
        import dataclasses
        meas = dataclasses.replace(meas, sequence=None)
    groups = (np.array([int(p.split("-")[0]) for p in meas.point_ids]) if name == "dlr_agile_justin"
              else np.arange(meas.n_poses))
    ids = np.unique(groups)
    perm = np.random.default_rng(0).permutation(len(ids))
    k = int(round(0.7 * len(ids)))
    cal = np.isin(groups, ids[np.sort(perm[:k])])
    train, test = meas.subset(cal), meas.subset(~cal)
t, cpu = time.perf_counter(), os.times()
d = diagnose(model, train, **({"workers": workers} if workers > 1 else {}))
wall, done = time.perf_counter() - t, os.times()
cpu = sum(getattr(done, k) - getattr(cpu, k) for k in ("user", "system", "children_user", "children_system"))
found = [f"{f['kind']}{'(' + f['follows'] + ')' if f['kind'] == 'correction' else ''} "
         f"{','.join(f.get('joints') or [])}".strip() for f in d.findings]
print(json.dumps({"wall_s": wall, "cpu_s": cpu, "findings": found,
                  "heldout_rms_mm": evaluate(d.calibration, test)["rms_mm"], "search_complete": not d.untested}))
'''


def tree_of(rev: str) -> Path:
    """A worktree of `rev` under /tmp (made once); the current tree for 'HEAD+' (uncommitted changes included)."""
    if rev == "HEAD+":
        return ROOT
    sha = subprocess.run(["git", "rev-parse", "--short", rev], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.strip()
    path = Path(f"/tmp/calib-bench-{sha}")
    if not path.exists():
        subprocess.run(["git", "worktree", "add", "--detach", str(path), sha], cwd=ROOT, check=True,
                       capture_output=True)
    return path


CACHE = Path("/tmp/calib-bench-cache")
"""With --cache, a committed revision's result per case is kept here and reused (its code does not change); off by
default, since the two sides are then no longer measured under the same load. The working tree is never cached."""


def run(case: str, tree: Path, root: str, cache: bool = False, workers: int = 1) -> dict:
    sha = None if tree == ROOT or not cache else tree.name.rsplit("-", 1)[-1]
    hit = CACHE / f"{sha}-{case}{'' if workers == 1 else f'-w{workers}'}.json"
    if sha and hit.exists():
        return json.loads(hit.read_text())
    out = _run(case, tree, root, workers)
    if sha and "error" not in out:
        CACHE.mkdir(exist_ok=True)
        hit.write_text(json.dumps(out))
    return out


def _run(case: str, tree: Path, root: str, workers: int = 1) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               MKL_NUM_THREADS="1", CALIB_SHARED_DATASETS=root)
    r = subprocess.run([sys.executable, "-c", CHILD, case, root, str(workers)], cwd=tree, env=env, capture_output=True,
                       text=True)
    if r.returncode != 0:
        return {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}
    return json.loads(r.stdout.strip().splitlines()[-1])


def _median(results: list[dict]) -> dict:
    """One side's runs of a case as one result: the median wall and CPU time (with the wall's range when there are
    several), the first run's findings and held-out figure (a diagnosis is deterministic: several runs that disagree
    are an error)."""
    ok = [r for r in results if "error" not in r]
    if len(ok) < len(results):
        return next(r for r in results if "error" in r)
    first = dict(ok[0])
    if any((r["findings"], r["heldout_rms_mm"]) != (first["findings"], first["heldout_rms_mm"]) for r in ok[1:]):
        return {"error": "runs of one revision gave different answers"}
    if len(ok) > 1:
        walls = [r["wall_s"] for r in ok]
        first.update(wall_s=statistics.median(walls), wall_min_s=min(walls), wall_max_s=max(walls))
        if all("cpu_s" in r for r in ok):
            first["cpu_s"] = statistics.median(r["cpu_s"] for r in ok)
    return first


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_diagnosis_speed", description=__doc__.splitlines()[0])
    p.add_argument("--base", default=BASE, help=f"the revision to compare with (default {BASE})")
    p.add_argument("--new", default="HEAD+", help="this code: HEAD+ (the working tree, default) or a revision")
    p.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    p.add_argument("--jobs", type=int, default=2, help="cases run at once (processes)")
    p.add_argument("--workers", type=int, default=1, help="this code's diagnosis processes (diagnose(workers=...), "
                   "as an auto job runs it: CALIB_DIAGNOSIS_WORKERS); the base always runs in one")
    p.add_argument("--repeat", type=int, default=1, help="runs of each side, interleaved (base, new, base, ...): the "
                   "table gives each side's median time and the ratio of the medians (this machine's speed varies "
                   "10-25 %% from run to run, the one-process base's as much as its CPU time)")
    p.add_argument("--cache", action="store_true", help=f"reuse committed revisions' results from {CACHE}")
    p.add_argument("--root", default=os.environ.get("CALIB_SHARED_DATASETS", str(ROOT.parent / "shared" / "datasets")))
    args = p.parse_args(argv)
    base, new = tree_of(args.base), tree_of(args.new)
    t0 = time.perf_counter()
    sides = (("base", base, 1), ("new", new, args.workers))
    tasks = [(c, which, tree, w) for c in args.cases for _ in range(max(args.repeat, 1)) for which, tree, w in sides]
    on = lambda case, which: "motoman" if (case, which) == ("motoman_order", "base") else case  # noqa: E731
    with ThreadPoolExecutor(args.jobs) as pool:  # each task is its own process; threads only wait
        done = list(pool.map(lambda t: (t[0], t[1], run(on(t[0], t[1]), t[2], args.root, args.cache, t[3])), tasks))
    runs: dict = {}
    for case, which, res in done:
        runs.setdefault(case, {}).setdefault(which, []).append(res)
    out = {case: {which: _median(rs) for which, rs in sides_.items()} for case, sides_ in runs.items()}
    times = f", the median of {args.repeat} interleaved runs each" if args.repeat > 1 else ""
    print(f"## The diagnosis's run time: {args.new} ({args.workers} process{'es' if args.workers > 1 else ''}) against "
          f"{args.base} (one) ({args.jobs} case(s) at once, one BLAS thread each{times})\n")
    print("| case | base (s) | new (s) | speed-up | CPU base / new (s) | findings base | findings new | "
          "held-out RMS base -> new (mm) | complete base / new |")
    print("|---|---|---|---|---|---|---|---|---|")
    for case in args.cases:
        b, n = out[case]["base"], out[case]["new"]
        if "error" in b or "error" in n:
            print(f"| {case} | {b.get('error', '')} | {n.get('error', '')} | | | | | | |")
            continue
        diff = 100.0 * (n["heldout_rms_mm"] / b["heldout_rms_mm"] - 1.0)
        spread = "".join(f" {which} {x['wall_min_s']:.1f}-{x['wall_max_s']:.1f}"
                         for which, x in (("base", b), ("new", n)) if "wall_min_s" in x)
        same = "" if b["findings"] == n["findings"] else " **differ**"
        cpu = (f"{b['cpu_s']:.1f} / {n['cpu_s']:.1f}" if "cpu_s" in b and "cpu_s" in n else "")
        print(f"| {case} | {b['wall_s']:.1f} | {n['wall_s']:.1f} | {b['wall_s'] / n['wall_s']:.1f}x{spread} | {cpu} | "
              f"{'; '.join(b['findings']) or 'none'} | {'; '.join(n['findings']) or 'none'}{same} | "
              f"{b['heldout_rms_mm']:.3f} -> {n['heldout_rms_mm']:.3f} ({diff:+.1f} %) | "
              f"{b['search_complete']} / {n['search_complete']} |")
    print(f"\nwall time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
