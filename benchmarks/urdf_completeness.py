"""Issue 30's completeness table: noise-free fits of perturbed real URDFs, pinocchio as the truth, before / after.

For each robot of tests/core/test_pinocchio_reference.py (COMPLETE_CASES): every joint origin of the URDF moved
by up to 0.5 mm and 1 mrad (fixed joints too), an SMR 30/20/50 mm off each target link, the true points computed
by pinocchio from the perturbed URDF text in a random tracker frame at --poses random configurations; the NOMINAL
model (parse_urdf of the unperturbed URDF, the SMR's nominal offset as the target point unless the case says
otherwise) fitted by identify(regularize=False, folds=0). Printed: the model form, the parameters identified,
the RMS and max residual (mm) of the fit and the max error (mm) on 100 new configurations, worst over --seeds.
Also one line per FK check (FK_CASES): the max distance (mm) between our model's target points and pinocchio's
frame placements times the same point at 300 random configurations.

"before" runs calib_core of a git revision (default BEFORE_REV, the last commit before the complete per-row
geometry), extracted with `git archive` into a temporary directory; "after" the working tree (or --after REV).
The harness itself (tests/core/test_pinocchio_reference.py) is always the working tree's.

Needs the test extras (pin, example-robot-data).
Run:  .venv/bin/python -m benchmarks.urdf_completeness [--before 1bb654e] [--after worktree|REV] [--seeds 0 1 2]
      [--poses 300] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HARNESS = ROOT / "tests" / "core" / "test_pinocchio_reference.py"
BEFORE_REV = "1bb654e"  # HEAD when issue 30's harness was written, before the complete per-row geometry


def _worker(args) -> None:
    """Compute every check with the calib_core found first on sys.path; print JSON."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import importlib.util

    import calib_core  # from PYTHONPATH: the side's revision

    # the harness: the working tree's test module, loaded from its file (calib_core stays the side's)
    spec = importlib.util.spec_from_file_location("pinocchio_reference_harness", HARNESS)
    H = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = H  # dataclasses look their module up
    spec.loader.exec_module(H)
    out = {"calib_core": str(Path(calib_core.__file__).parent), "fk": [], "completeness": []}
    for c in H.FK_CASES:
        try:
            err, form, n = H.fk_error(c, n=300, seed=0)
            out["fk"].append({"case": c.id, "file": c.file, "targets": list(c.targets), "form": form, "rows": n,
                              "max_mm": err})
        except Exception as exc:  # noqa: BLE001  (a revision that cannot import the URDF: say so)
            out["fk"].append({"case": c.id, "file": c.file, "error": f"{type(exc).__name__}: {exc}"[:300]})
    for c in H.COMPLETE_CASES:
        t0 = time.perf_counter()
        try:
            res = [H.completeness(c, n=args.poses, seed=s) for s in args.seeds]
            out["completeness"].append({
                "case": c.id, "file": c.file, "targets": list(c.targets), "form": res[0].form, "note": c.note,
                "n_params": sorted({r.n_params for r in res}), "rows": res[0].n_rows,
                "rms_mm": max(r.rms_mm for r in res), "max_mm": max(r.max_mm for r in res),
                "holdout_max_mm": max(r.holdout_max_mm for r in res), "seconds": time.perf_counter() - t0})
        except Exception as exc:  # noqa: BLE001
            out["completeness"].append({"case": c.id, "file": c.file, "error": f"{type(exc).__name__}: {exc}"[:300]})
    print(json.dumps(out))


def _run_side(src: Path, args) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src), OPENBLAS_NUM_THREADS="1")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--poses", str(args.poses),
           "--seeds", *map(str, args.seeds)]
    res = subprocess.run(cmd, cwd=src, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"the worker on {src} failed:\n{res.stderr[-3000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    if Path(out["calib_core"]).resolve() != (src / "calib_core").resolve():
        raise SystemExit(f"the worker on {src} imported calib_core from {out['calib_core']}")
    return out


def _archive(rev: str, into: Path) -> str:
    sha = subprocess.run(["git", "rev-parse", "--short", rev], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip()
    tar = subprocess.run(["git", "archive", sha, "calib_core"], cwd=ROOT, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=tar, check=True)
    return sha


def _side(rev: str, tmp: Path, label: str) -> tuple[str, dict]:
    if rev == "worktree":
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "calib_core"], cwd=ROOT, capture_output=True,
                               text=True).stdout.strip()
        return f"{head}{' + uncommitted calib_core' if dirty else ''}", _run_side(ROOT, ARGS)
    d = tmp / label
    d.mkdir()
    return _archive(rev, d), _run_side(d, ARGS)


def _f(v) -> str:
    return f"{v:.1e}" if isinstance(v, float) else str(v)


def main() -> None:
    global ARGS
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", default=BEFORE_REV, help="git revision for 'before' (default %(default)s)")
    ap.add_argument("--after", default="worktree", help="'worktree' (default) or a git revision")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--poses", type=int, default=300)
    ap.add_argument("--json", help="also write both sides' results here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ARGS = ap.parse_args()
    if ARGS.worker:
        return _worker(ARGS)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        before_rev, before = _side(ARGS.before, Path(tmp), "before")
        after_rev, after = _side(ARGS.after, Path(tmp), "after")
    print(f"# URDF completeness (issue 30): before = {before_rev}, after = {after_rev}; "
          f"{ARGS.poses} configurations x targets, seeds {ARGS.seeds} (worst shown), 100 held-out configurations")
    print("# residual mm of a noise-free fit of the nominal model to pinocchio's points of the perturbed URDF\n")
    print("| case | URDF | form | points | before: params | RMS | max | after: params | RMS | max | held-out max |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    bmap = {r["case"]: r for r in before["completeness"]}
    for a in after["completeness"]:
        b = bmap.get(a["case"], {})

        def cols(r):
            if "error" in r:
                return [r["error"][:60], "-", "-"]
            return ["/".join(map(str, r["n_params"])), _f(r["rms_mm"]), _f(r["max_mm"])]
        form = a.get("form", b.get("form", "?"))
        rows = a.get("rows", b.get("rows", "?"))
        print(f"| {a['case']} | {a['file']} | {form} | {rows} | " + " | ".join(cols(b) if b else ["-"] * 3)
              + " | " + " | ".join(cols(a)) + f" | {_f(a.get('holdout_max_mm', '-'))} |")
    print("\n# FK: max distance mm between our target points and pinocchio's (300 random configurations, SMR 30/20/50 mm)\n")
    print("| case | URDF | targets | form | rows | before max mm | after max mm |")
    print("|---|---|---|---|---|---|---|")
    bfk = {r["case"]: r for r in before["fk"]}
    for a in after["fk"]:
        b = bfk.get(a["case"], {})
        val = lambda r: r.get("error", "-")[:60] if "max_mm" not in r else _f(r["max_mm"])  # noqa: E731
        print(f"| {a['case']} | {a['file']} | {', '.join(a.get('targets', []))} | {a.get('form', '?')} | "
              f"{a.get('rows', '?')} | {val(b)} | {val(a)} |")
    print(f"\n# {time.perf_counter() - t0:.0f} s")
    if ARGS.json:
        Path(ARGS.json).write_text(json.dumps({"before": {"rev": before_rev, **before},
                                               "after": {"rev": after_rev, **after}}, indent=1))


ARGS = None

if __name__ == "__main__":
    main()
