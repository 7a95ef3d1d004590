"""What each of the server's processes imports: the API process (it parses and answers, never diagnoses) skips the
parts of scipy that calib_core imports where it uses them; the fork server preloads every one of them, so the job
and lane processes it forks never import at their first diagnosis."""
import ast
import json
import subprocess
import sys
from pathlib import Path

from service.processes import PRELOAD

ROOT = Path(__file__).resolve().parents[2]
LATE = ("scipy.stats", "scipy.optimize", "scipy.spatial")


def _imported_after(modules: list[str]) -> set[str]:
    """The modules a fresh interpreter holds after importing `modules`."""
    code = (f"import importlib, json, sys\nfor m in {modules!r}: importlib.import_module(m)\n"
            "print(json.dumps(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    return set(json.loads(out.stdout))


def _late_scipy_imports() -> set[str]:
    """Every scipy module calib_core imports inside a function (`from scipy import stats` -> scipy.stats)."""
    found = set()
    for path in (ROOT / "calib_core").rglob("*.py"):
        for fn in ast.walk(ast.parse(path.read_text())):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("scipy"):
                    found |= ({f"scipy.{a.name}" for a in node.names} if node.module == "scipy" else {node.module})
    return found


def test_the_api_process_does_not_import_what_only_a_diagnosis_needs():
    held = _imported_after(["service.app"])
    assert not [m for m in LATE if m in held], sorted(m for m in held if m.startswith(LATE))


def test_the_fork_server_preloads_every_scipy_module_calib_core_imports_late():
    late = _late_scipy_imports()
    assert {"scipy.stats", "scipy.optimize"} <= late, late  # the walk sees them (else the test proves nothing)
    missing = late - _imported_after(PRELOAD)
    assert not missing, f"a job process would import {sorted(missing)} at its first call: add them to PRELOAD"


def test_constants_from_scipy_special_are_scipy_stats_values():
    from scipy import stats

    from calib_core.diagnosis import masses, plays

    assert masses.MASS_DROP == float(stats.chi2.ppf(0.99, 1))
    assert plays.SWITCH_LR == 0.5 * stats.chi2.ppf(0.95, 1)
