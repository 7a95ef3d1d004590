"""The world shares no code with the diagnosis: no module of calib_world imports it, even indirectly."""
import ast
import json
import subprocess
import sys
from pathlib import Path

import calib_world

FORBIDDEN = ("effects", "diagnose", "identify", "kinematics", "statics", "twin", "solve")
PACKAGE = Path(calib_world.__file__).parent
ROOT = PACKAGE.parent


def _forbidden(name: str) -> bool:
    parts = name.split(".")
    return parts[0] == "calib_core" and len(parts) > 1 and parts[1] in FORBIDDEN


def test_no_module_imports_the_diagnosis():
    files = sorted(PACKAGE.rglob("*.py"))
    assert files
    for f in files:
        tree = ast.parse(f.read_text(), str(f))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                assert node.level == 0 or node.module is None or not node.module.startswith("calib_core"), f
                mod = node.module or ""
                names = [mod] + [f"{mod}.{a.name}" for a in node.names]
                if node.level:  # relative imports stay inside calib_world
                    continue
            else:
                continue
            bad = [n for n in names if _forbidden(n)]
            assert not bad, f"{f.name} imports {bad}"
            if any(n == "calib_core" for n in names) and isinstance(node, ast.ImportFrom):
                assert not any(a.name in FORBIDDEN for a in node.names), f"{f.name}: from calib_core import ..."


SUBPROCESS = """
import json, sys
import numpy as np
import calib_core, calib_core.model, calib_core.io  # calib_core/__init__ itself may load the diagnosis
FORBIDDEN = %r
bad = lambda m: m.split(".")[0] == "calib_core" and len(m.split(".")) > 1 and m.split(".")[1] in FORBIDDEN
before = set(sys.modules)
for m in [m for m in sys.modules if bad(m)]:
    sys.modules[m] = None  # any import of it from now on raises ImportError
for a in FORBIDDEN:
    if hasattr(calib_core, a):
        delattr(calib_core, a)
import calib_world, calib_world.campaign, calib_world.scenarios, calib_world.mechanics, calib_world.robot
from calib_core.robots import spray7
world = calib_world.World(calib_core.model.parse_model(spray7()), 1)
rng = np.random.default_rng(1)
for kind in ("joint_spring", "telescopic_bending", "thermal_growth", "play_load_sign", "link_thermal_growth",
             "target_remount", "tilted_base_spring", "tilted_base_sag", "telescopic_sag", "two_joint_springs"):
    calib_world.hide(world, kind, 2.0, rng, n=30)
world.campaign(n=20, payload_kg=5.0, temperature=True, repeats=2)
print(json.dumps(sorted(m for m in set(sys.modules) - before if m.startswith("calib_core"))))
"""


def test_the_world_runs_with_the_diagnosis_unimportable():
    """Import and run the world in a fresh interpreter where every diagnosis module is blocked; it must not
    load a new calib_core module outside model / io (and robots, which the script itself uses)."""
    out = subprocess.run([sys.executable, "-c", SUBPROCESS % (FORBIDDEN,)], cwd=ROOT, capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    new = json.loads(out.stdout.strip().splitlines()[-1])
    assert set(new) <= {"calib_core.robots"}, new
